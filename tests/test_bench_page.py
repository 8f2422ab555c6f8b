"""The bench report's animation of a held-out sequence (garmentgnn.bench.page): from a
run's records and a GarTrans checkpoint, inline in report.md, errors checked against a
prediction whose error is known exactly (the simulation moved by 1 cm)."""
import json
import re

import lightning as L
import numpy as np
import pytest
from PIL import Image

from garmentgnn.bench import report
from garmentgnn.bench.page import ENV_VAR, MEDIA, write_media
from garmentgnn.data import store
from garmentgnn.training import GarTransModule, GarmentDataModule
from garmentgnn.viz.animate import renderer_unavailable
from garmentgnn.viz.compare import comparison
from garmentgnn.models import GarTrans

from test_viz_export import dataset  # noqa: F401  (the shared two-sequence toy dataset)

WHY = renderer_unavailable()
METRICS = dict.fromkeys(report.METRICS, 1.0)


def _checkpoint(root, path):
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=8, num_landmarks=16,
                           val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    trainer = L.Trainer(max_epochs=0, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=str(path.parent))
    trainer.fit(module, dm)
    trainer.save_checkpoint(path)
    return path


def _records(root, ckpt):
    base = {"kind": "learned", "case": "mini", "status": "ok", "message": "ok",
            "metrics": METRICS, "timing": {"latency_ms": 1.0, "throughput_fps": 1.0},
            "train_seconds": 1.0, "dataset": {"root": str(root), "name": "v"}}
    cfg = {"config": {"data": {"history": 2, "num_landmarks": 16}}}
    return [dict(base, method="GarTrans (SAT)", seed=1, checkpoint=str(ckpt), **cfg),
            dict(base, method="GarTrans (SAT)", seed=2, checkpoint=str(ckpt) + ".gone", **cfg),
            dict(base, method="DA-style", seed=1),
            dict(base, method="LBS only", seed=0)]


@pytest.mark.skipif(WHY is not None, reason=f"no off-screen renderer: {WHY}")
def test_report_shows_the_heldout_animation(dataset, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.setenv(ENV_VAR, "1")
    ckpt = _checkpoint(dataset, tmp_path / "models" / "m.ckpt")
    out = tmp_path / "bench"
    rec = [r for r in store.read_manifest(dataset)["items"] if r["split"] == "test"][0]
    gt = store.load_sequence(store.sequence_path(dataset, rec))["positions"]
    (out / MEDIA / "predictions").mkdir(parents=True)
    np.save(out / MEDIA / "predictions" / "DA-style.npy", gt + np.float32([0.0, 0.01, 0.0]))
    report.write_report(_records(dataset, ckpt), out)
    text = (out / "report.md").read_text()
    section = text[text.index("## Animation of a held-out sequence"):]
    assert f"`{rec['id']}`" in section
    assert "simulated (ground truth) | GarTrans (SAT) | DA-style | LBS only" in section
    assert "DA-style 1.00 cm" in section  # exactly 1 cm off everywhere
    # the still's rule and its numbers: DA-style is 1 cm off on that frame too
    assert "closest to GarTrans (SAT)'s median per-frame error" in section
    assert re.search(r"The picture is frame \d+, .*DA-style 1\.00 cm", section)
    assert "training seed 1" in section
    links = re.findall(r"\]\((media/[^)]+)\)", section)
    assert {"media/heldout.png", "media/heldout.gif", "media/heldout.mp4",
            "media/heldout.glb"} <= set(links), links
    for link in links:
        assert (out / link).is_file() and (out / link).stat().st_size > 1000, link
    png = Image.open(out / "media" / "heldout.png")
    assert png.size[1] >= 720
    pixels = np.asarray(png.convert("RGB"), np.float64)
    assert pixels.std() > 10  # not blank
    info = json.loads((out / MEDIA / "heldout.json").read_text())["info"]
    assert info["frames"] == gt.shape[0]
    # a rerun with the same inputs reuses the files
    mtime = (out / "media" / "heldout.png").stat().st_mtime_ns
    report.write_report(_records(dataset, ckpt), out)
    assert (out / "media" / "heldout.png").stat().st_mtime_ns == mtime
    assert section == (out / "report.md").read_text()[text.index("## Animation"):]


def test_no_animation_without_checkpoint_or_when_turned_off(dataset, tmp_path,  # noqa: F811
                                                            monkeypatch):
    monkeypatch.setenv(ENV_VAR, "1")
    recs = _records(dataset, tmp_path / "missing.ckpt")
    assert write_media(recs, tmp_path) == []  # no checkpoint on disk: no section
    report.write_report(recs, tmp_path)
    assert "Animation" not in (tmp_path / "report.md").read_text()
    assert not (tmp_path / MEDIA).exists()
    monkeypatch.setenv(ENV_VAR, "0")
    (tmp_path / "x.ckpt").write_bytes(b"")
    assert write_media(_records(dataset, tmp_path / "x.ckpt"), tmp_path) == []


@pytest.mark.skipif(WHY is not None, reason=f"no off-screen renderer: {WHY}")
def test_animation_shows_the_sequence_the_predictions_were_made_on(dataset, tmp_path,  # noqa: F811
                                                                   monkeypatch):
    """The learned methods score a subset of the split (``test_sequences``) whose first
    sequence -- the one the saved baseline predictions show -- need not be the split's
    first; the animation must be of that sequence, not of index 0."""
    monkeypatch.setenv(ENV_VAR, "1")
    ckpt = _checkpoint(dataset, tmp_path / "models" / "m.ckpt")
    items = store.read_manifest(dataset)["items"]
    assert len(items) == 2
    first_scored = items[1]  # not index 0 of the whole dataset
    gt = store.load_sequence(store.sequence_path(dataset, first_scored))["positions"]
    out = tmp_path / "bench"
    (out / MEDIA / "predictions").mkdir(parents=True)
    np.save(out / MEDIA / "predictions" / "DA-style.npy", gt + np.float32([0.0, 0.01, 0.0]))
    recs = [dict(r, per_sequence=[{"sequence": first_scored["id"], "frames": 7}])
            for r in _records(dataset, ckpt)]
    section = "\n".join(write_media(recs, out, split=None))
    assert f"`{first_scored['id']}`" in section and f"`{items[0]['id']}`" not in section
    assert "DA-style 1.00 cm" in section


def test_comparison_selects_a_sequence_by_id(dataset):  # noqa: F811
    items = store.read_manifest(dataset)["items"]
    for k, rec in enumerate(items):
        assert comparison(dataset, {}, split=None, index=rec["id"]).seq_id == rec["id"]
        assert comparison(dataset, {}, split=None, index=k).seq_id == rec["id"]
    with pytest.raises(ValueError, match="ids"):
        comparison(dataset, {}, split="test", index="no-such-sequence")
