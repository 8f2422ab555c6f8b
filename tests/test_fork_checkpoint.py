"""A run branched on purpose: :func:`garmentgnn.training.fork_checkpoint` writes a
checkpoint with some settings changed, and ``garmentgnn train fit --ckpt_path`` resumes
it with the weights, the optimizer's state, the step and the data order it had, where the
original checkpoint with the same flags is refused."""
import pytest
import torch

from conftest import skirt_dataset
from garmentgnn.cli import main as cli_main
from garmentgnn.training import fork_checkpoint, load_checkpoint
from garmentgnn.training.integrity import (CheckpointError, load_checkpoint_file,
                                           stamp_checkpoint)
from garmentgnn.training.lightning_cli import main as train_main


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Two optimizer steps of a small MGN-style run (one-step windows) and its checkpoint."""
    tmp = tmp_path_factory.mktemp("fork")
    root = skirt_dataset(tmp / "data", ["walk", "run", "jump"], 8, held_out={"val": ["run"]},
                         name="fork")
    args = ["--config", "mgn", "--data.root", str(root), "--data.nystrom_dim", "8",
            "--data.num_landmarks", "16", "--data.batch_size", "2",
            "--trainer.limit_val_batches", "1", "--trainer.enable_progress_bar", "false",
            "--trainer.val_check_interval", "2", "--seed_everything", "0"]
    args += ["--model.init_args.stats_steps", "1", "--model.model.init_args.hidden", "8",
             "--model.model.init_args.layers", "1", "--model.model.init_args.heads", "1"]
    first = ["--model.init_args.rollout", "1", "--data.chunk", "3"]
    out = tmp / "first"
    cli = train_main(["fit", *args, *first, "--trainer.max_steps", "2",
                      "--trainer.default_root_dir", str(out),
                      "--trainer.logger.init_args.save_dir", str(out)])
    path = tmp / "first.ckpt"
    cli.trainer.save_checkpoint(path)
    return tmp, args, path


def _adam_steps(trainer):
    return {float(s["step"]) for s in trainer.optimizers[0].state.values()}


def test_a_forked_checkpoint_resumes_the_run_with_the_changed_settings(run, capsys):
    tmp, args, path = run
    src = load_checkpoint_file(path)
    assert src["global_step"] == 2 and src["hyper_parameters"]["rollout"] == 1
    branch = ["--model.init_args.rollout", "2", "--model.init_args.rollout_start", "0",
              "--data.chunk", "4"]
    tail = ["--trainer.max_steps", "4", "--trainer.default_root_dir", str(tmp / "b"),
            "--trainer.logger.init_args.save_dir", str(tmp / "b")]
    # the original checkpoint with the new flags: refused, naming the way to branch
    capsys.readouterr()
    rc = cli_main(["train", "fit", *args, *branch, *tail, "--ckpt_path", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--model.rollout 2 (checkpoint: 1)" in err[0]
    assert "fork_checkpoint" in err[0]

    forked = fork_checkpoint(path, tmp / "forked.ckpt", model={"rollout": 2, "rollout_start": 0},
                             data={"chunk": 4})
    ck = load_checkpoint_file(forked)  # its digest is renewed: it verifies
    assert ck["hyper_parameters"]["rollout"] == 2 and ck["hyper_parameters"]["rollout_start"] == 0
    assert ck["datamodule_hyper_parameters"]["chunk"] == 4
    for key in ("state_dict", "optimizer_states", "loops", "GarmentDataModule", "global_step"):
        assert repr(ck[key]) == repr(src[key]), key  # everything else as the run had it
    for k, v in src["state_dict"].items():
        assert torch.equal(ck["state_dict"][k], v)

    cli = train_main(["fit", *args, *branch, *tail, "--ckpt_path", str(forked)])
    module = cli.trainer.lightning_module
    assert cli.trainer.global_step == 4 and module.hparams.rollout == 2
    assert module.rollout_at(3) == 2 and cli.datamodule.hparams.chunk == 4
    assert _adam_steps(cli.trainer) == {4.0}  # Adam went on from the run's 2 steps


def test_a_setting_newer_than_the_checkpoint_can_be_forked(run):
    """A checkpoint written before the module had ``train_inextensible`` (the key removed
    from its settings, its digest renewed) forks to the new setting and loads with it;
    a name the module does not take is still refused."""
    tmp, _, path = run
    old = load_checkpoint_file(path)
    del old["hyper_parameters"]["train_inextensible"]
    stamp_checkpoint(old)
    torch.save(old, tmp / "older.ckpt")
    forked = fork_checkpoint(tmp / "older.ckpt", tmp / "newer.ckpt",
                             model={"train_inextensible": 100})
    assert load_checkpoint(forked).hparams.train_inextensible == 100
    assert load_checkpoint(tmp / "older.ckpt").hparams.train_inextensible == 0
    with pytest.raises(ValueError, match="'inextensible' is not a setting.*train_inext"):
        fork_checkpoint(tmp / "older.ckpt", tmp / "bad.ckpt", model={"inextensible": 100})


def test_what_a_fork_cannot_change_is_refused_and_nothing_is_written(run):
    tmp, _, path = run
    dest = tmp / "bad.ckpt"
    with pytest.raises(ValueError, match="`model`: 'rollouts' is not a setting.*rollout"):
        fork_checkpoint(path, dest, model={"rollouts": 2})
    with pytest.raises(ValueError, match="`model`: 'model' is not a setting"):
        fork_checkpoint(path, dest, model={"model": {"class_path": "x"}})
    with pytest.raises(ValueError, match="`data`: 'root' is not a setting"):
        fork_checkpoint(path, dest, data={"root": "/elsewhere"})
    with pytest.raises(ValueError, match="`data`: 'history' is not a setting"):
        fork_checkpoint(path, dest, data={"history": 3})  # an input the model reads
    with pytest.raises(ValueError, match="`rollout`"):  # the module's own check
        fork_checkpoint(path, dest, model={"rollout": 0})
    with pytest.raises(ValueError, match="`dest`"):
        fork_checkpoint(path, path, model={"rollout": 2})
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        fork_checkpoint(tmp / "missing.ckpt", dest)
    assert not dest.exists() and not list(tmp.glob("bad.ckpt*"))
