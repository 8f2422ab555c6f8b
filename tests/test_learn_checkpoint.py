"""The committed GarTrans trained on `learn` (``tests/data/gartrans_learn.ckpt``, the
`learn` bench preset's run of seed 0) scores, through ``garmentgnn train test``, the
error the bench recorded for it on one `learn` test sequence
(``tests/data/gartrans_learn.json``), packed with its body in
``tests/data/learn_sample.zip`` (:mod:`garmentgnn.data.compact`): anyone who
regenerates `learn` gets this row back."""
import json
from pathlib import Path

import pytest

from garmentgnn.data import SequenceChunks, compact
from garmentgnn.training.lightning_cli import main as train_main

DATA = Path(__file__).resolve().parent / "data"
CKPT, SAMPLE, RECORD = (DATA / "gartrans_learn.ckpt", DATA / "learn_sample.zip",
                        DATA / "gartrans_learn.json")


@pytest.mark.slow
def test_the_learn_checkpoint_scores_its_recorded_error(tmp_path, monkeypatch):
    record = json.loads(RECORD.read_text())
    cache = tmp_path / "cache"
    monkeypatch.setenv("GARMENTGNN_CACHE_DIR", str(cache))  # the packed body, nothing else
    root = tmp_path / "learn"
    compact.unpack(SAMPLE, root, cache_dir=cache)
    (item,) = SequenceChunks(root, "test", chunk=10 ** 9)
    assert item.seq_id == record["sequence"]
    assert int(item.valid.sum()) == record["frames"]  # the frames the record scored
    cli = train_main(["test", "--config", "gartrans", "--data.root", str(root),
                      "--data.train_split", "test", "--ckpt_path", str(CKPT),
                      "--model.init_args.compile_search", "false",
                      "--trainer.enable_progress_bar", "false",
                      "--trainer.default_root_dir", str(tmp_path),
                      "--trainer.logger.init_args.save_dir", str(tmp_path)])
    got = {k: float(v) for k, v in cli.trainer.callback_metrics.items()}
    # the sample's positions are packed within 0.013 mm: E_dist within 0.005 cm
    assert got["test/E_dist"] == pytest.approx(record["metrics"]["E_dist"], abs=5e-3)
    assert got["test/E_vnorm"] == pytest.approx(record["metrics"]["E_vnorm"], rel=1e-3)
    assert got["test/E_dist"] < got["test_lbs/E_dist"]
