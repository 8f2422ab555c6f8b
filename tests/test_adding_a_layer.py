"""docs/layers.md, "Adding a layer", as written: its layer file and recipe in a folder on
the Python path, trained as an ablation of GarTrans for two steps through `garmentgnn
train`, with no file of the package edited."""
import re
import sys
from pathlib import Path

import torch

from garmentgnn.cli import main as cli_main
from garmentgnn.training import GarTransModule
from test_layers_contract import EDGE_DIM
from test_training import root  # noqa: F401  (module-scoped toy dataset: train + val)
from test_training_cli import fast_args

DOC = Path(__file__).resolve().parents[1] / "docs" / "layers.md"


def walkthrough():
    """The section's file blocks ({name: content}) and its bash command."""
    text = DOC.read_text().split("## Adding a layer", 1)[1].split("\n## ", 1)[0]
    files = dict((name, code) for name, code in
                 re.findall(r"^```\w+ (\S+)\n(.*?)^```", text, re.S | re.M))
    (command,) = re.findall(r"^```bash\n(.*?)^```", text, re.S | re.M)
    return files, command.split()


def test_the_walkthrough_trains_the_new_layer(root, tmp_path, monkeypatch):  # noqa: F811
    files, command = walkthrough()
    assert set(files) == {"toy_conv.py", "toy.yaml"} and command[:2] == ["garmentgnn", "train"]
    for name, content in files.items():
        (tmp_path / name).write_text(content)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("toy_conv", None)
    argv = command[1:]
    argv[argv.index("--data.root") + 1] = str(root)
    assert cli_main(argv + fast_args(root, tmp_path / "run", train_batches=2)) == 0
    (ckpt,) = (tmp_path / "run").rglob("last.ckpt")
    module = GarTransModule.load_from_checkpoint(ckpt)
    import toy_conv  # noqa: PLC0415  (the doc's file)
    assert module.model.init_args["dynamic_layer"] == "toy_conv.ToyConv"
    assert all(type(layer) is toy_conv.ToyConv for layer in module.model.dynamic.layers)
    assert type(module.model.rest_attn.layers[0]) is not toy_conv.ToyConv  # only its slot
    # the contract's first check on the new layer: a batch of graphs is each graph alone
    layer = toy_conv.ToyConv(6, 4, heads=2, edge_dim=EDGE_DIM).eval()
    x, ei = torch.randn(5, 6), torch.tensor([[0, 1, 2, 3, 4], [1, 2, 3, 4, 0]])
    two = torch.cat([x, x]), torch.cat([ei, ei + 5], 1)
    torch.testing.assert_close(layer(*two)[:5], layer(x, ei))
