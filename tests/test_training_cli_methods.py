"""``garmentgnn train`` for every method: each packaged recipe builds the module it names
with the recipe's own arguments (the YAML file is the oracle), ``fit`` then ``test`` of a
baseline and an ablation through the command line, the test metrics against an
independent whole-sequence evaluation, and checkpoints in the layout written before
the CLI covered every method."""
from pathlib import Path

import inspect

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
import pytest
import torch
import yaml

from garmentgnn.cli import main as cli_main
from garmentgnn.metrics import evaluate_inputs
from garmentgnn.training import (BaselineModule, GarmentDataModule, GarTransModule,
                                 RolloutModule, load_recipe)
from garmentgnn.training.recipes import available, named_module, recipe_path
from garmentgnn.data import SequenceChunks
from garmentgnn.training.evaluate import evaluate_split
from garmentgnn.training.lightning_cli import DEFAULT_EPOCHS, main as train_main
from garmentgnn.models import GarTrans
from garmentgnn.models.baselines import NCSStyle
from garmentgnn.training.integrity import stamp_checkpoint
from recipe_helpers import module as recipe_module
from test_training import NY, root  # noqa: F401  (the module-scoped toy dataset fixture)
from test_training_cli import fast_args


CLASSES = {"garmentgnn.training.GarTransModule": GarTransModule,
           "garmentgnn.training.BaselineModule": BaselineModule,
           "garmentgnn.training.RolloutModule": RolloutModule}


def _config_args(name):
    """The ``--config`` flags of packaged recipe ``name`` (the simulator's windows and
    batch sized for the toy dataset)."""
    return ["--config", name] + (["--data.batch_size", "2"] if name == "mgn" else [])


def _test_args(data_root, tmp_path):
    # the toy dataset's held-out split is `val`; the baselines' pose history is 3
    return fast_args(data_root, tmp_path) + ["--data.test_split", "val",
                                             "--data.history", "3"]


def test_every_method_has_a_packaged_recipe():
    assert [n for n in available() if not n.startswith("ablations/")] == [
        "baselines/da", "baselines/hood", "baselines/ncs", "gartrans", "mgn"]


@pytest.mark.parametrize("name", available())
def test_each_packaged_recipe_builds_its_module(root, tmp_path, name):  # noqa: F811
    cli = train_main(_config_args(name) + _test_args(root, tmp_path), run=False)
    cfg = yaml.safe_load(recipe_path(name).read_text())
    assert isinstance(cli.model, CLASSES[cfg["model"]["class_path"]])
    assert isinstance(cli.datamodule, GarmentDataModule)
    expected = cfg["model"]["init_args"]
    hp = dict(cli.model.hparams)
    for k, v in expected.items():
        if k == "model":  # the model it is handed: its configured settings, as built
            got = hp["model"]["init_args"]
            assert hp["model"]["class_path"].rsplit(".", 1)[-1] == \
                v["class_path"].rsplit(".", 1)[-1]
            want = v.get("init_args") or {}
            assert {j: got[j] for j in want} == want
            assert got == cli.model.model.init_args
        else:
            assert hp[k] == (sorted(v) if k == "enabled" else v), k
    dims, model = cli.datamodule.dims, hp["model"]["init_args"]
    # the sizes linked from the data, where the model takes them
    for size in ("num_joints", "num_body_vertices", "nystrom_dim", "num_vertices"):
        assert model.get(size, dims[size]) == dims[size], size
    assert ("num_vertices" in model) == (name == "baselines/ncs")
    if name == "baselines/ncs":  # one garment on one body: the garment-specific size
        assert model["num_vertices"] == cli.datamodule.train_set.static(0).num_vertices


@pytest.mark.parametrize("name", available())
def test_each_recipe_builds_alike_from_python_and_the_command(root, tmp_path, name):  # noqa: F811
    """``load_recipe`` (what the bench, the scripts and the examples build) and
    ``garmentgnn train --config`` give equal hyper-parameters, data settings, weights
    (seeded alike), checkpoints and limits for every packaged recipe."""
    args = _config_args(name)[2:] + _test_args(root, tmp_path)
    recipe = load_recipe(name, args=args)
    cli = train_main(_config_args(name) + _test_args(root, tmp_path), run=False)
    assert dict(recipe.module.hparams) == dict(cli.model.hparams)
    assert dict(recipe.datamodule.hparams) == dict(cli.datamodule.hparams)
    torch.testing.assert_close(recipe.module.state_dict(), cli.model.state_dict())
    trainer = recipe.trainer()

    def checkpoints(callbacks):
        return [(c.monitor, c.save_last, c.filename, c._every_n_train_steps)
                for c in callbacks if isinstance(c, ModelCheckpoint)]
    assert checkpoints(trainer.callbacks) == checkpoints(cli.trainer.callbacks) != []
    assert checkpoints(recipe.callbacks) == checkpoints(cli.trainer.callbacks)
    assert (trainer.max_epochs, trainer.max_steps) == (cli.trainer.max_epochs,
                                                       cli.trainer.max_steps)


def _oracle(module, root, split):  # noqa: F811
    """Frame-weighted metrics of ``module`` and of LBS over whole sequences of ``split``
    (one call per sequence, not the CLI's chunks): ``evaluate_split`` for LBS,
    :func:`evaluate_inputs` of the module's prediction for the method."""
    lbs = evaluate_split(module, root, split, modes=("lbs",), history=3,
                         nystrom_dim=NY, num_landmarks=16)["lbs"]
    ds = SequenceChunks(root, split, chunk=10 ** 6, history=3, nystrom_dim=NY,
                        num_landmarks=16)
    sums, frames = {}, 0
    with torch.no_grad():
        for item in ds:
            B = item.num_frames
            frames += B
            for k, v in evaluate_inputs(module.predict_garment(item), item).items():
                sums[k] = sums.get(k, 0.0) + v * B
    return {k: v / frames for k, v in sums.items()}, lbs


@pytest.mark.parametrize("name,cls", [
    ("baselines/da", BaselineModule),  # 4 s
    pytest.param("baselines/ncs", BaselineModule, marks=pytest.mark.slow),
    pytest.param("ablations/wo_gating", GarTransModule, marks=pytest.mark.slow)])  # 24 s
def test_fit_then_test_any_method_through_the_command_line(root, tmp_path, capsys,  # noqa: F811
                                                            name, cls):
    args = _config_args(name) + _test_args(root, tmp_path)
    assert cli_main(["train", "fit"] + args) == 0
    (last,) = tmp_path.rglob("last.ckpt")
    module = cls.load_from_checkpoint(str(last), map_location="cpu").eval()
    # the data module's arguments travel with the checkpoint (save_hyperparameters)
    dm = GarmentDataModule.load_from_checkpoint(str(last))
    assert (dm.hparams.root, dm.hparams.chunk, dm.hparams.history) == (str(root), 4, 3)
    capsys.readouterr()
    cli = train_main(["test"] + args + ["--ckpt_path", str(last)])
    out = capsys.readouterr().out
    row = {"baselines/da": "| DA-style |", "baselines/ncs": "| NCS-style |"}.get(
        name, "| GarTrans (gt_edge) |")
    assert row in out and "| LBS only |" in out
    got = {k: float(v) for k, v in cli.trainer.callback_metrics.items()}
    method, lbs = _oracle(module, root, "val")
    for k in ("E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv", "collision"):
        assert got[f"test/{k}"] == pytest.approx(method[k], rel=1e-4, abs=1e-7), k
        assert got[f"test_lbs/{k}"] == pytest.approx(lbs[k], rel=1e-4, abs=1e-7), k


def _bench_style_checkpoint(module, dm, path):
    """A checkpoint of a module built in Python (``BaselineModule(DAStyle(...))``: no
    ``_class_path``) and trained without a data module's hyper-parameters."""
    trainer = L.Trainer(max_epochs=1, limit_train_batches=1, limit_val_batches=0,
                        accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.fit(module, dm)
    trainer.save_checkpoint(path)
    ck = torch.load(path, weights_only=False)
    ck.pop("datamodule_hyper_parameters", None)
    ck["hyper_parameters"].pop("_class_path", None)  # as a module built in Python has none
    stamp_checkpoint(ck)
    torch.save(ck, path)


def test_checkpoints_in_the_earlier_layout_load_and_other_methods_are_refused(
        root, tmp_path, capsys):  # noqa: F811
    data = {"chunk": 4, "history": 3, "nystrom_dim": NY, "num_landmarks": 16}
    dm = GarmentDataModule(root, **data)
    da = recipe_module("baselines/da", root, data)
    _bench_style_checkpoint(da, dm, tmp_path / "da.ckpt")
    args = _test_args(root, tmp_path / "run") + ["--trainer.limit_test_batches", "1"]
    cli = train_main(["test", "--config", "baselines/da", "--ckpt_path",
                      str(tmp_path / "da.ckpt")] + args)
    assert isinstance(cli.model, BaselineModule) and cli.model.method == "da"
    saved = torch.load(tmp_path / "da.ckpt", weights_only=False)["state_dict"]
    assert saved.keys() == cli.model.state_dict().keys()
    assert all(torch.equal(v, saved[k]) for k, v in cli.model.state_dict().items())
    assert "test/E_dist" in cli.trainer.callback_metrics
    # another module class, and the same module class with another model: the method
    # the checkpoint holds is named, with its config
    for config, model in (("gartrans", "GarTrans"), ("baselines/hood", "HOODStyle")):
        capsys.readouterr()
        rc = cli_main(["train", "test", "--config", config, "--ckpt_path",
                       str(tmp_path / "da.ckpt")] + args)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1
        assert (f"a checkpoint of DAStyle, not of {model}; give --config baselines/da"
                in err[0])


def test_the_cli_refuses_a_checkpoint_of_an_earlier_layout_saying_to_retrain(
        root, tmp_path, capsys):  # noqa: F811
    """``--ckpt_path`` rebuilds the module from the file's hyper-parameters: a checkpoint
    of an earlier layout (the model's settings among the module's) is refused in one line
    that says to retrain (there is no conversion)."""
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    hp = {**{k: v for k, v in module.hparams.items() if k != "model"},
          **module.model.init_args, "garment_state": False}
    old = tmp_path / "old.ckpt"
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": hp,
            "pytorch-lightning_version": L.__version__}
    stamp_checkpoint(ckpt)
    torch.save(ckpt, old)
    rc = cli_main(["train", "test", "--config", "gartrans", "--ckpt_path", str(old)]
                  + _test_args(root, tmp_path / "run"))
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert f"--ckpt_path {old}" in err[0] and "earlier layout" in err[0], err[0]
    assert "garment_state" in err[0] and "retrain it" in err[0], err[0]


def test_ncs_refuses_a_data_module_of_several_garments(root, tmp_path):  # noqa: F811
    dm = GarmentDataModule(root, chunk=4, history=3, nystrom_dim=NY, num_landmarks=16)
    assert dm.dims["num_vertices"] is not None  # one garment on one body
    V = dm.dims["num_vertices"]
    ncs = BaselineModule(NCSStyle(V + 1, dm.dims["num_joints"], history=1, hidden=8))
    with pytest.raises(ValueError, match="--data.train_ids"):
        ncs.compute_loss(dm.train_set[0])
    short = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)
    ncs = BaselineModule(NCSStyle(V, dm.dims["num_joints"], history=1, hidden=8))
    short.setup("fit")
    with pytest.raises(ValueError, match="--data.history 3"):
        ncs(short.train_set[0])


def test_data_module_keeps_its_arguments_and_sets_up_per_stage(root):  # noqa: F811
    dm = GarmentDataModule(Path(root), chunk=4, history=2, nystrom_dim=NY, num_landmarks=16,
                           test_split="val")
    assert dm.hparams.root == str(root) and dm.hparams.chunk == 4
    dm.setup("test")
    assert dm.test_set is not None and dm.train_set is None and dm.val_set is None
    dm.setup("validate")
    assert dm.val_set is not None and dm.train_set is None
    dm.setup("fit")
    assert dm.train_set is not None and dm.predict_set is None
    dm.setup("predict")
    assert [r["id"] for r in dm.predict_set.records] == [r["id"] for r in dm.test_set.records]
    with pytest.raises(ValueError, match="`stage`"):
        dm.setup("train")


@pytest.mark.parametrize("how", ["flags", "short name", "own config"])
def test_a_module_named_by_the_user_gets_its_own_defaults(root, tmp_path, how):  # noqa: F811
    """A module named on the command line or in the user's own config, not by a packaged
    config, is built with its own defaults (the oracle: its signature), not with the
    same-named arguments of the default module (GarTransModule's learning rate 3e-3 and
    rollout settings)."""
    module = "BaselineModule" if how == "short name" else "garmentgnn.training.BaselineModule"
    logger = ["--trainer.logger", "lightning.pytorch.loggers.CSVLogger"]
    named = ["--model", module, "--model.init_args.model", "garmentgnn.models.baselines.DAStyle"]
    if how == "own config":
        cfg = tmp_path / "mine.yaml"
        cfg.write_text(yaml.safe_dump({"model": {"class_path": module, "init_args": {
            "model": {"class_path": "garmentgnn.models.baselines.DAStyle"}}}}))
        named = ["--config", str(cfg)]
    args = named + logger + _test_args(root, tmp_path)
    cli = train_main(args, run=False)
    assert isinstance(cli.model, BaselineModule)
    own = inspect.signature(BaselineModule.__init__).parameters
    for name in ("lr", "rollout", "rollout_noise", "warmup"):
        assert cli.model.hparams[name] == own[name].default, name
    assert cli.model.hparams.lr != inspect.signature(
        GarTransModule.__init__).parameters["lr"].default  # the case that went wrong
    given = train_main(args + ["--model.init_args.lr", "0.003"], run=False)
    assert given.model.hparams.lr == pytest.approx(0.003, rel=1e-12)


def test_named_module_reads_flags_and_configs_in_order():
    hood, gartrans = str(recipe_path("baselines/hood")), str(recipe_path("gartrans"))
    assert named_module(["--data.root", "x"]) is None
    assert named_module(["--config", hood]) == "garmentgnn.training.BaselineModule"
    assert named_module(["--config", hood, "--config", gartrans]) == \
        "garmentgnn.training.GarTransModule"
    assert named_module([f"--config={gartrans}", "--model=BaselineModule"]) == \
        "garmentgnn.training.BaselineModule"
    assert named_module(["--model.class_path", "my.pkg.Module", "--config", hood]) == \
        "garmentgnn.training.BaselineModule"
    assert named_module(["--model", "cfg.yaml"]) is None  # a file of arguments


def test_a_run_that_counts_steps_or_time_trains_to_them(root, tmp_path):  # noqa: F811
    """A run without ``max_epochs`` ends at its ``max_steps`` or ``max_time``, not at the
    CLI's default epoch limit, which ended a longer ``mgn`` run early without an error
    (Lightning's own rule: with the steps or the time given, the epochs are unlimited);
    without either it trains the default epochs, and an explicit limit stays."""
    cfg = yaml.safe_load(recipe_path("mgn").read_text())
    args = _test_args(root, tmp_path)
    i = args.index("--trainer.max_epochs")
    del args[i:i + 2]

    def limits(name, *flags):
        t = train_main(_config_args(name) + args + list(flags), run=False).trainer
        return t.max_epochs, t.max_steps

    assert limits("mgn") == (-1, cfg["trainer"]["max_steps"])
    assert limits("mgn", "--trainer.max_steps", "10000000") == (-1, 10 ** 7)
    assert limits("gartrans") == (DEFAULT_EPOCHS, -1)
    assert limits("gartrans", "--trainer.max_steps", "100000") == (-1, 100000)
    assert limits("gartrans", "--trainer.max_time", "00:01:00:00")[0] == -1
    assert limits("mgn", "--trainer.max_epochs", "3") == (3, cfg["trainer"]["max_steps"])
