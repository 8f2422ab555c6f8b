"""The committed MGN-style learned simulator trained on `learn`
(``tests/data/mgn_learn.ckpt``: the averaged weights of docs/results/mgn_learn/million's
10^6 garment-frame run at step 20,250, without its optimizer state) rolls out, through
``garmentgnn train test``, the error recorded for it on one `learn` test sequence
(``tests/data/mgn_learn.json``), packed with its body in ``tests/data/mgn_learn_sample.zip``
(:mod:`garmentgnn.data.compact`; the sequence of the GarTrans sample,
``tests/data/learn_sample.zip``, from the dataset the report used), and LBS's beside it."""
import json
from pathlib import Path

import pytest
import torch

from garmentgnn.data import SequenceChunks, compact
from garmentgnn.training import RolloutModule
from garmentgnn.training.lightning_cli import main as train_main

DATA = Path(__file__).resolve().parent / "data"
CKPT, SAMPLE, RECORD = (DATA / "mgn_learn.ckpt", DATA / "mgn_learn_sample.zip",
                        DATA / "mgn_learn.json")


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mgn_sample")
    cache = tmp / "cache"
    root = tmp / "learn"
    compact.unpack(SAMPLE, root, cache_dir=cache)
    return root, cache


def test_the_checkpoint_is_small_and_the_headline_run():
    assert CKPT.stat().st_size <= 8 * 10 ** 6
    record = json.loads(RECORD.read_text())
    module = RolloutModule.load_from_checkpoint(str(CKPT), map_location="cpu")
    assert module.hparams.noise == record["run"]["noise"]
    assert int(torch.load(CKPT, weights_only=False)["global_step"]) == record["run"]["steps"]


@pytest.mark.slow
def test_the_learn_checkpoint_rolls_out_its_recorded_error(sample, tmp_path, monkeypatch):
    root, cache = sample
    record = json.loads(RECORD.read_text())
    monkeypatch.setenv("GARMENTGNN_CACHE_DIR", str(cache))  # the packed body, nothing else
    (item,) = SequenceChunks(root, "test", chunk=10 ** 9, history=1)
    assert item.seq_id == record["sequence"]
    cli = train_main(["test", "--config", "mgn", "--data.root", str(root),
                      "--data.train_split", "test", "--data.val_split", "null",
                      "--ckpt_path", str(CKPT), "--trainer.enable_progress_bar", "false",
                      "--trainer.default_root_dir", str(tmp_path),
                      "--trainer.logger.init_args.save_dir", str(tmp_path)])
    got = {k: float(v) for k, v in cli.trainer.callback_metrics.items()}
    # the rollout starts from the packed frames 0 and 1 and is scored from frame 2 on: a
    # deterministic function of the sample (a rollout amplifies round-off: 1e-3 relative)
    assert got["test/E_dist"] == pytest.approx(record["metrics"]["E_dist"], rel=1e-3)
    assert got["test_lbs/E_dist"] == pytest.approx(record["lbs"]["E_dist"], rel=1e-4)
    assert (got["test/E_dist"] < got["test_lbs/E_dist"]) == (
        record["metrics"]["E_dist"] < record["lbs"]["E_dist"])
