"""docs/layers.md, "Adding a layer", as written: its layer file and recipe in a folder on
the Python path, trained as an ablation of GarTrans through `garmentgnn train` and run
beside full GarTrans by `garmentgnn bench`, two training steps each, with no file of the
package edited."""
import json
import re
import shlex
import sys
from pathlib import Path

import pytest
import torch

from garmentgnn.bench import methods
from garmentgnn.cli import main as cli_main
from garmentgnn.training import GarTransModule
from conftest import skirt_dataset
from test_layers_contract import EDGE_DIM
from test_training import root  # noqa: F401  (module-scoped toy dataset: train + val)
from test_training_cli import fast_args

DOC = Path(__file__).resolve().parents[1] / "docs" / "layers.md"


def walkthrough():
    """The section's file blocks ({name: content}) and its bash commands (each split as
    the shell splits it)."""
    text = DOC.read_text().split("## Adding a layer", 1)[1].split("\n## ", 1)[0]
    files = dict((name, code) for name, code in
                 re.findall(r"^```\w+ (\S+)\n(.*?)^```", text, re.S | re.M))
    (block,) = re.findall(r"^```bash\n(.*?)^```", text, re.S | re.M)
    return files, [shlex.split(line) for line in block.replace("\\\n", " ").splitlines()]


@pytest.fixture
def walked(tmp_path, monkeypatch):
    """The walk-through's files written into ``tmp_path``, on the Python path, the
    current folder; its commands."""
    files, commands = walkthrough()
    assert set(files) == {"toy_conv.py", "toy.yaml"}
    assert [c[:2] for c in commands] == [["garmentgnn", "train"], ["garmentgnn", "bench"]]
    for name, content in files.items():
        (tmp_path / name).write_text(content)
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("toy_conv", None)
    return commands


def test_the_walkthrough_trains_the_new_layer(root, tmp_path, walked):  # noqa: F811
    argv = walked[0][1:]
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


def test_the_walkthrough_benches_the_new_layer_beside_gartrans(tmp_path, walked):
    """The bench runs the recipe as a method: trained two steps (the dataset's two
    training chunks, one epoch of ``tiny``'s budget) with the layer in its dynamic stack,
    scored on the same test sequence as full GarTrans, its row named by the recipe."""
    data = skirt_dataset(tmp_path / "data", ["walk", "run", "arm_swing"], 4,
                         held_out={"test": ["arm_swing"]}, name="toy")
    argv = walked[1][1:]
    argv[argv.index("--data") + 1] = str(data)
    assert cli_main(argv + ["--no-progress"]) == 0
    out = tmp_path / argv[argv.index("--out") + 1]
    every = json.loads((out / "results.json").read_text())["records"]
    assert {r["kind"] for r in every} == {"learned", "learned_stability"}  # learned only
    records = {r["method"]: r for r in every if r["kind"] == "learned"}
    assert set(records) == {"toy.yaml", methods.FULL}
    toy, full = records["toy.yaml"], records[methods.FULL]
    assert toy["status"] == full["status"] == "ok"
    assert toy["steps"] == full["steps"] == 2
    assert toy["config"]["recipe"] == "toy.yaml"
    assert toy["config"]["model"]["init_args"]["model"]["init_args"]["dynamic_layer"] == \
        "toy_conv.ToyConv"
    assert [s["sequence"] for s in toy["per_sequence"]] == \
        [s["sequence"] for s in full["per_sequence"]]
    assert toy["metrics"]["E_dist"] != full["metrics"]["E_dist"]  # another model
    import toy_conv  # noqa: PLC0415  (the doc's file)
    module = GarTransModule.load_from_checkpoint(toy["checkpoint"])
    assert module.model.init_args["dynamic_layer"] == "toy_conv.ToyConv"
    assert all(type(layer) is toy_conv.ToyConv for layer in module.model.dynamic.layers)
    assert "toy.yaml" in (out / "report.md").read_text()
