"""Bad input to ``garmentgnn train`` and the data module: an untrained model scored
without a word, split names that match nothing, an ablation config without its base,
Nyström sizes that cannot fit, a NaN in a training file.  Each ended in a silent success
or an error naming an internal argument; now each is one ``error:`` line naming the flag
(or the file and the array) and the fix."""
import shutil
import subprocess
import sys

import lightning as L
import numpy as np
import pytest

from garmentgnn.cli import main as cli_main
from garmentgnn.data import read_manifest, store
from garmentgnn.data import SequenceChunks
from garmentgnn.models.baselines import NCSStyle
from garmentgnn.training import BaselineModule, GarmentDataModule, GarTransModule, load_recipe
from garmentgnn.training.recipes import resolve_config_args
from garmentgnn.training.lightning_cli import count_first
from garmentgnn.training.lightning_cli import main as train_main

from test_bad_input_cli import edit_sequence, one_error
from test_training import NY, root  # noqa: F401  (module-scoped toy dataset: train + val)
from test_training_cli import fast_args


def data_args(data_root, tmp_path):
    """:func:`fast_args` with a pose history of 3 and one training batch."""
    return fast_args(data_root, tmp_path, history=3, train_batches=1)


@pytest.fixture(scope="module")
def da_checkpoint(root, tmp_path_factory):  # noqa: F811
    """A DA-style checkpoint trained for one step on the toy dataset (~5 s)."""
    out = tmp_path_factory.mktemp("da")
    assert cli_main(["train", "fit", "--config", "baselines/da"] + data_args(root, out)) == 0
    (last,) = out.rglob("last.ckpt")
    return last


# ------------------------------------------------------------------ no checkpoint
@pytest.mark.parametrize("sub", ["test", "predict", "validate"])
def test_scoring_without_a_checkpoint_is_refused(root, tmp_path, capsys, sub):  # noqa: F811
    """`train test` printed the metrics of an untrained model (exit 0) before."""
    rc = cli_main(["train", sub, "--config", "baselines/da", "--data.test_split", "val"]
                  + data_args(root, tmp_path))
    one_error(capsys, rc, "--ckpt_path", "untrained", "pass --ckpt_path PATH")
    assert not list(tmp_path.rglob("predictions"))


@pytest.mark.parametrize("special", ["last", "best"])
def test_scoring_with_last_or_best_and_no_such_file_is_refused(root, tmp_path, capsys,  # noqa: F811
                                                               special):
    """`--ckpt_path last` with no last checkpoint in the new run's folder: Lightning
    warned and tested the untrained model."""
    rc = cli_main(["train", "test", "--config", "baselines/da", "--data.test_split", "val",
                   "--ckpt_path", special] + data_args(root, tmp_path))
    one_error(capsys, rc, f"--ckpt_path {special}", "untrained", "give the checkpoint file")


# ------------------------------------------------------------------ split names
def test_unknown_split_names_are_refused_listing_the_manifests(root):  # noqa: F811
    """`SequenceChunks(root, split="tset")` had length 0; the data module predicted
    nothing (exit 0) or trained without validation."""
    with pytest.raises(ValueError, match=r"`split`: .* no 'tset' split; name one that its "
                                         r"manifest lists: train, val"):
        SequenceChunks(root, split="tset", nystrom_dim=NY, num_landmarks=16)
    for name in ("predict_split", "test_split", "val_split", "train_split"):
        dm = GarmentDataModule(root, chunk=4, history=3, nystrom_dim=NY, num_landmarks=16,
                               **{name: "tset"})
        with pytest.raises(ValueError, match=f"`{name}`: .*'tset'.*train, val"):
            dm.setup({"predict_split": "predict", "test_split": "test"}.get(name, "fit"))


def test_empty_split_or_dataset_is_an_error(root, tmp_path):  # noqa: F811
    """A split whose sequences are all pending (or failed) gave zero chunks."""
    out = tmp_path / "d"
    shutil.copytree(root, out)
    doc = read_manifest(out)
    for r in doc["items"]:
        if r["split"] == "val":
            r.update(status="failed", message="diverged")
    store.write_manifest(out, doc["items"], {k: v for k, v in doc.items() if k != "items"})
    with pytest.raises(ValueError, match=r"`split`: no ok 'val' sequences .*'failed': 1.*"
                                         r"--retry-failed"):
        SequenceChunks(out, split="val", nystrom_dim=NY, num_landmarks=16)
    for r in doc["items"]:
        r.update(status="pending")
    store.write_manifest(out, doc["items"], {k: v for k, v in doc.items() if k != "items"})
    with pytest.raises(ValueError, match=r"`split`: no ok sequences under .*'pending': 2"):
        SequenceChunks(out, split=None, nystrom_dim=NY, num_landmarks=16)


def test_fit_with_a_misspelt_val_split_names_the_flag(root, tmp_path, capsys):  # noqa: F811
    """`fit --data.val_split vall` trained without validation (exit 0) before."""
    rc = cli_main(["train", "fit", "--config", "baselines/da", "--data.val_split", "vall"]
                  + data_args(root, tmp_path))
    one_error(capsys, rc, "--data.val_split", "'vall'", "train, val", "--data.val_split null")
    assert not list(tmp_path.rglob("*.ckpt"))


def test_predict_with_a_misspelt_split_names_the_flag(root, tmp_path, capsys,  # noqa: F811
                                                      da_checkpoint):
    """`predict --data.predict_split tset` wrote nothing and exited 0."""
    rc = cli_main(["train", "predict", "--config", "baselines/da", "--data.predict_split",
                   "tset", "--ckpt_path", str(da_checkpoint)] + data_args(root, tmp_path))
    one_error(capsys, rc, "--data.predict_split", "'tset'", "train, val")


# ------------------------------------------------------------------ recipes
def test_an_ablation_recipe_alone_trains_the_headline_but_its_layer(root, tmp_path):  # noqa: F811
    """An ablation recipe is complete: alone it builds GarTrans's module with the full
    model's loss weights, schedule and checkpoints (before, alone it trained without
    them), its one difference the layer."""
    args = data_args(root, tmp_path)
    gat = train_main(["--config", "ablations/gat"] + args, run=False)
    full = train_main(["--config", "gartrans"] + args, run=False)
    assert isinstance(gat.model, GarTransModule)
    one, other = dict(gat.model.hparams), dict(full.model.hparams)
    assert one.pop("model")["init_args"] == dict(other.pop("model")["init_args"],
                                                 dynamic_layer="gat")
    assert one == other
    assert [type(c) for c in gat.trainer.callbacks] == [type(c) for c in full.trainer.callbacks]
    with pytest.raises(ValueError, match="no packaged recipe of that name"):
        resolve_config_args(["--config=ablations/nope"])


# ------------------------------------------------------------------ Nyström sizes
@pytest.mark.parametrize("ny, lm, words", [
    ("32", "8", ["expected an int in [1, num_landmarks=8]", "got 32"]),
    ("60", "64", ["60 Nyström features with num_landmarks=64", ".npz", "lower nystrom_dim"]),
])
def test_nystrom_dim_that_cannot_fit_names_the_flags(root, tmp_path, capsys, ny, lm,  # noqa: F811
                                                     words):
    """"`k`: expected an int in [1, 8]" named an argument no flag has."""
    rc = cli_main(["train", "fit", "--config", "baselines/da"] + data_args(root, tmp_path)
                  + ["--data.nystrom_dim", ny, "--data.num_landmarks", lm])
    last = one_error(capsys, rc, "--data.nystrom_dim", *words)
    assert "`k`" not in last


# ------------------------------------------------------------------ NaN in a file
def test_nan_in_a_training_file_names_the_file_and_the_array(root, tmp_path, capsys):  # noqa: F811
    """"`pos`: contains NaN or inf entries" named neither the file nor the array."""
    out = tmp_path / "d"
    shutil.copytree(root, out)
    rec = next(r for r in read_manifest(out)["items"] if r["split"] == "train")
    path = store.sequence_path(out, rec)
    rot = store.load_sequence(path)["motion_rotations"].copy()
    rot[2, 1, 0] = np.nan
    edit_sequence(path, motion_rotations=rot)
    doc = read_manifest(out)  # the file's new hash accepted, as `manifest` would
    for r in doc["items"]:
        if r["id"] == rec["id"]:
            r["sha256"] = store.file_sha256(path)
    store.write_manifest(out, doc["items"], {k: v for k, v in doc.items() if k != "items"})
    rc = cli_main(["train", "fit", "--config", "baselines/da"] + data_args(out, tmp_path / "r"))
    one_error(capsys, rc, str(path), "motion_rotations contain NaN/inf in 1 of",
              "(first at index (2, 1, 0))")


# ------------------------------------------------------------------ int flags
def test_limit_test_batches_1_tests_one_batch(root, da_checkpoint, tmp_path):  # noqa: F811
    """`garmentgnn train test ... --trainer.limit_test_batches 1` tested every batch: `1`
    was read as the fraction 1.0.  (In a process of its own, as the command runs: the
    modules it imports first wrote ``Union[float, int]``, and typing's union cache, which
    ignores order, then made the Trainer's ``Optional[Union[int, float]]`` float-first.)"""
    code = "import sys; from garmentgnn.cli import main; sys.exit(main(sys.argv[1:]))"
    args = ["train", "test", "--config", "baselines/da", "--data.test_split", "val",
            "--ckpt_path", str(da_checkpoint), "--trainer.limit_test_batches", "1"]
    out = subprocess.run([sys.executable, "-c", code] + args + data_args(root, tmp_path),
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    log = out.stdout + out.stderr
    assert "`Trainer(limit_test_batches=1)` was configured so 1 batch will be used" in log
    assert "`Trainer(limit_val_batches=1)`" in log and "=1.0)" not in log
    dm = GarmentDataModule(root, chunk=4, history=3, nystrom_dim=NY, num_landmarks=16,
                           test_split="val")
    dm.setup("test")
    assert len(dm.test_dataloader()) > 1  # one batch is less than the split


def test_count_first_keeps_fractions_and_other_types():
    from typing import Optional, Union  # noqa: PLC0415
    u = type(Union[int, str])(Union, (float, int, str, type(None)))
    assert count_first(u).__args__ == (int, float, str, type(None))
    assert count_first(Optional[int]) is Optional[int]
    assert count_first(int) is int


# ------------------------------------------------------------------ nothing would run
@pytest.mark.parametrize("sub, flag", [("fit", "max_steps"), ("fit", "max_epochs"),
                                       ("fit", "limit_train_batches"),
                                       ("test", "limit_test_batches")])
def test_a_run_that_would_do_nothing_is_refused(root, da_checkpoint, tmp_path, capsys,  # noqa: F811
                                                sub, flag):
    """`fit --trainer.max_steps 0` exited 0 with no step and no checkpoint."""
    ckpt = ["--ckpt_path", str(da_checkpoint), "--data.test_split", "val"] if sub == "test" \
        else []
    rc = cli_main(["train", sub, "--config", "baselines/da"] + ckpt + data_args(root, tmp_path)
                  + [f"--trainer.{flag}", "0"])
    one_error(capsys, rc, f"--trainer.{flag} 0", f"`{sub}` would", "give a positive value")
    assert not list(tmp_path.rglob("*.ckpt"))


# ------------------------------------------------------------------ method needs
@pytest.mark.parametrize("config, history, need", [("baselines/hood", "1", "2")])
def test_a_history_too_short_for_the_method_is_refused_at_set_up(root, tmp_path, capsys,  # noqa: F811
                                                                 config, history, need):
    """`--data.history 1` with HOOD-style failed at the first step with "`j`: expected an
    int with -2 <= j <= -1"."""
    args = fast_args(root, tmp_path, history=int(history), train_batches=1)
    rc = cli_main(["train", "fit", "--config", config] + args)
    last = one_error(capsys, rc, f"--data.history {history}", "HOOD-style",
                     f"--data.history {need} or more")
    assert "`j`" not in last and not list(tmp_path.rglob("*.ckpt"))


def test_ncs_history_is_checked_at_set_up(root):  # noqa: F811
    """NCS-style with model history h reads h + 3 poses: refused when the run is built."""
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)
    dm.setup("fit")
    module = BaselineModule(NCSStyle(dm.dims["num_vertices"], dm.dims["num_joints"],
                                     history=1, hidden=8))
    trainer = L.Trainer(logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        max_steps=1)
    with pytest.raises(ValueError, match=r"--data.history 2: NCS-style \(model history 1\) "
                                         r"reads 4 poses.*--data.history 3 or more"):
        trainer.fit(module, dm)


# ------------------------------------------------------------------ config names
def test_unknown_recipe_name_lists_the_packaged_ones(root, tmp_path, capsys):  # noqa: F811
    """`--config nosuch` printed the whole usage and "File does not exist"."""
    rc = cli_main(["train", "fit", "--config", "nosuch"] + data_args(root, tmp_path))
    last = one_error(capsys, rc, "--config nosuch", "no packaged recipe",
                     "gartrans", "baselines/da", "ablations/gat")
    assert "usage" not in capsys.readouterr().err
    assert last.count("error:") == 1


# ------------------------------------------------------------------ data of the checkpoint
@pytest.mark.parametrize("sub", ["predict", "test"])
def test_scoring_with_other_model_inputs_than_the_checkpoints_is_refused(
        root, da_checkpoint, tmp_path, capsys, sub):  # noqa: F811
    """`train predict --data.history 1` on a checkpoint trained with history 3 wrote
    predictions from inputs the model never learned from (`show` refused the same)."""
    rc = cli_main(["train", sub, "--config", "baselines/da", "--data.test_split", "val",
                   "--ckpt_path", str(da_checkpoint)] + data_args(root, tmp_path)
                  + ["--data.history", "1"])
    one_error(capsys, rc, str(da_checkpoint), "--data.history 1 (checkpoint: 3)",
              "learned from inputs", "give the checkpoint's values")
    assert not list(tmp_path.rglob("predictions"))


def test_resuming_with_other_data_settings_names_each_flag(root, da_checkpoint, tmp_path,  # noqa: F811
                                                           capsys):
    """`train fit --ckpt_path X --data.chunk 2 --data.num_landmarks 8` compared only the
    `--model.*` flags with X, and resumed another run."""
    rc = cli_main(["train", "fit", "--config", "baselines/da", "--ckpt_path",
                   str(da_checkpoint)] + data_args(root, tmp_path)
                  + ["--data.chunk", "2", "--data.num_landmarks", "8"])
    one_error(capsys, rc, "--data.chunk 2 (checkpoint: 4)",
              "--data.num_landmarks 8 (checkpoint: 16)", "start a new run without --ckpt_path")
    assert not list(tmp_path.rglob("*.ckpt"))


# ------------------------------------------------------------------ two recipes
def test_two_complete_recipes_are_refused_naming_both(root, tmp_path, capsys):  # noqa: F811
    """`--config baselines/da --config ablations/gat` trained the ablation alone, the
    DA-style recipe dropped without a word (each recipe is complete)."""
    rc = cli_main(["train", "fit", "--config", "baselines/da", "--config", "ablations/gat"]
                  + data_args(root, tmp_path))
    one_error(capsys, rc, "--config baselines/da and --config ablations/gat",
              "complete recipe", "give one recipe")
    assert not list(tmp_path.rglob("*.ckpt"))
    with pytest.raises(ValueError, match="recipe gartrans and recipe baselines/hood"):
        load_recipe("gartrans", "baselines/hood", data={"root": str(root)})
    # a file of changes that names no module still goes on top of one
    changes = tmp_path / "changes.yaml"
    changes.write_text("model:\n  init_args:\n    lr: 0.002\n")
    recipe = load_recipe("gartrans", changes, data=dict(
        root=str(root), chunk=4, history=3, nystrom_dim=NY, num_landmarks=16))
    assert recipe.module.hparams.lr == pytest.approx(0.002)


def test_testing_ignores_a_training_batch_size_larger_than_the_split(
        root, da_checkpoint, tmp_path, capsys):  # noqa: F811
    """`train test --data.batch_size 999` was refused for the training split's size,
    though a test run trains nothing (the training chunks give the model's sizes only);
    `fit` still refuses it."""
    rc = cli_main(["train", "test", "--config", "baselines/da", "--data.test_split", "val",
                   "--ckpt_path", str(da_checkpoint)] + data_args(root, tmp_path)
                  + ["--data.batch_size", "999", "--trainer.limit_test_batches", "1"])
    assert rc == 0, capsys.readouterr().err[-800:]
    assert "LBS only" in capsys.readouterr().out
    rc = cli_main(["train", "fit", "--config", "baselines/da"] + data_args(root, tmp_path)
                  + ["--data.batch_size", "999"])
    one_error(capsys, rc, "--data.batch_size: 999 is more than", "give at most")


# ------------------------------------------------------------------ load_recipe
def test_load_recipe_names_a_missing_module_class_and_the_bad_set_key(root, tmp_path):  # noqa: F811
    """A recipe naming a class that does not exist ended in an `AttributeError` (or
    blamed the empty `args`); a bad value in `set` gave `Parser key "model":` above a
    dump of the whole configuration."""
    recipe = tmp_path / "mine.yaml"
    recipe.write_text("model:\n  class_path: garmentgnn.training.NoSuchModule\n")
    with pytest.raises(ValueError, match=r"^`recipes`: .*mine.yaml names the module `model: "
                                         r"class_path: garmentgnn.training.NoSuchModule`, "
                                         r"and there is no such class"):
        load_recipe(recipe, data={"root": str(root)})
    with pytest.raises(ValueError) as err:
        load_recipe("gartrans", data={"root": str(root)}, set={"model.init_args.lr": "fast",
                                                                "model.init_args.t_max": 3})
    msg = str(err.value)
    assert msg.startswith("`set`: 'model.init_args.lr' = 'fast': Parser key \"lr\": "
                          "Expected a <class 'float'>. Got value: fast"), msg
    assert "\n" not in msg and "Namespace(" not in msg
