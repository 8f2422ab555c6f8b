"""Frames that are not valid ground truth (not converged, or the garment more than
``VALID_PENETRATION`` inside the body) are flagged per frame, left out of the metrics and of
the supervised loss, and a Blender item with such frames is simulated once more."""
import json
import math
import runpy
from pathlib import Path

import numpy as np
import pytest
import torch

from garmentgnn.data import (VALID_PENETRATION, SequenceChunks, generate, preset, read_manifest,
                             store, valid_frames)
from garmentgnn.data.worker import RESIMULATE, resimulation_settings, run_item
from garmentgnn.geometry import grid_mesh, unique_edges
from garmentgnn.bench import scoring
from garmentgnn.losses import GarTransLoss, LossInputs
from garmentgnn.metrics import evaluate
from garmentgnn.physics import ClothRest
from garmentgnn.training import GarmentDataModule, GarTransModule
from garmentgnn.training.evaluate import evaluate_split

from garmentgnn.models import GarTrans
from garmentgnn.sim.stand_in import skinned_wobble

ROOT = Path(__file__).resolve().parents[1]

#: per-frame depth inside the body (m) the double reports; frame 2 sits exactly on the line
DEPTHS = (0.0, 0.004, VALID_PENETRATION, 0.0101, 0.03, 0.0, 0.02, 0.0)
#: the frame the double flags as non-converged
NONCONVERGED = 5
#: the oracle, written out by hand: valid = converged and depth <= 1 cm
VALID = [True, True, True, False, False, False, False, True]


def deep_simulate(garment, body, motion, material, settings=None, progress=None):
    """:func:`garmentgnn.sim.stand_in.skinned_wobble` with :data:`DEPTHS` as its
    penetration and every frame that is not valid moved 1 m up: scored, those frames
    would dominate every error."""
    res = skinned_wobble(garment, body, motion, material, settings, progress)
    res.penetration = torch.tensor(DEPTHS[:motion.num_frames])
    res.max_penetration = 0.01
    res.converged[NONCONVERGED] = False
    for t, ok in enumerate(VALID):
        if not ok:
            res.positions[t, :, 2] += 1.0
    return res


@pytest.fixture(scope="module")
def deep(tmp_path_factory):
    out = tmp_path_factory.mktemp("deep")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=deep_simulate, progress=False)
    assert s.done == 8
    return out


# ------------------------------------------------------------------ the mask itself
def test_valid_frames_flags_the_exact_frames():
    conv = np.ones(8, bool)
    conv[NONCONVERGED] = False
    assert valid_frames(conv, np.array(DEPTHS, np.float32)).tolist() == VALID
    # another line moves the flags with it
    assert valid_frames(conv, DEPTHS, line=0.025).tolist() == \
        [True, True, True, True, False, False, True, True]
    # no penetration recorded: valid where converged; nothing at all: every frame
    assert valid_frames(conv).tolist() == conv.tolist()
    assert valid_frames(None, None, num_frames=3).tolist() == [True] * 3
    assert valid_frames(None, [0.0, float("nan")]).tolist() == [True, False]
    for bad, name in (((conv, DEPTHS[:5]), "converged"), ((None, None), "num_frames"),
                      ((conv, DEPTHS, 7), "num_frames")):
        with pytest.raises(ValueError, match=name):
            valid_frames(*bad)
    with pytest.raises(ValueError, match="line"):
        valid_frames(conv, DEPTHS, line=-0.01)


def test_the_reader_flags_the_exact_frames(deep):
    whole = SequenceChunks(deep, "test", chunk=10 ** 9, history=3, num_landmarks=64,
                           nystrom_dim=16)
    assert whole.valid(0).tolist() == VALID
    item = whole[0]
    assert item.valid.tolist() == VALID
    assert item.converged.tolist() == [t != NONCONVERGED for t in range(8)]
    chunks = SequenceChunks(deep, "test", chunk=3, history=3, num_landmarks=64, nystrom_dim=16)
    assert [chunks.valid(i).tolist() for i in range(3)] == [VALID[0:3], VALID[3:6], VALID[6:8]]
    assert [chunks[i].valid.tolist() for i in range(3)] == [VALID[0:3], VALID[3:6], VALID[6:8]]
    for rec in read_manifest(deep)["items"]:
        assert rec["invalid_frames"] == VALID.count(False)
        assert rec["penetrating_frames"] == 3  # deeper than the engine's own 10 mm flag
        assert rec["resimulated"] is None  # the torch engine is not simulated again


# ------------------------------------------------------------------ left out of every score
def test_scoring_leaves_them_out(deep):
    test = SequenceChunks(deep, "test", chunk=10 ** 9, history=3, num_landmarks=64,
                          nystrom_dim=16)
    per_seq = scoring.score(lambda i, item: item.skinned(), test)
    keep = torch.tensor(VALID)
    for i, s in enumerate(per_seq):
        item = test[i]
        assert s["frames"] == 4 and s["excluded_frames"] == 4
        want = evaluate(item.skinned()[keep].float(), item.gt[keep], item.faces,
                        item.body_pos[keep], item.body_faces)
        for k, v in want.items():
            got = s["metrics"]["collision_rate" if k == "collision" else k]
            assert got == pytest.approx(v, rel=1e-6, abs=1e-9), k
        assert s["metrics"]["E_dist"] < 25.0  # the invalid frames are 1 m off


def test_evaluate_split_and_the_test_step_leave_them_out(deep):
    dm = GarmentDataModule(deep, chunk=4, history=3, nystrom_dim=16, num_landmarks=64,
                           val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    res = evaluate_split(module, deep, "test", modes=("lbs",), history=3,
                         num_landmarks=64)["lbs"]
    assert res["frames"] == 4 * 4 and res["excluded_frames"] == 4 * 4
    test = SequenceChunks(deep, "test", chunk=10 ** 9, history=3, num_landmarks=64,
                          nystrom_dim=16)
    keep = torch.tensor(VALID)
    dists = [evaluate(test[i].skinned()[keep].float(), test[i].gt[keep], test[i].faces)
             ["E_dist"] for i in range(len(test))]
    assert res["E_dist"] == pytest.approx(sum(dists) / len(dists), rel=1e-6)

    chunks = SequenceChunks(deep, "test", chunk=4, history=3, num_landmarks=64, nystrom_dim=16)
    item = chunks[0]  # frames 0-3: frame 3 is 1.01 cm deep
    module.log = lambda *a, **k: None  # outside a Trainer
    with torch.no_grad():
        got = module.test_step(item, 0)
        pred = module.predict_garment(item)
    k4 = torch.tensor(VALID[:4])
    want = evaluate(pred[k4].float(), item.gt[k4], item.faces, item.body_pos[k4],
                    item.body_faces)
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-5, abs=1e-9), k
    c3 = SequenceChunks(deep, "test", chunk=3, history=3, num_landmarks=64, nystrom_dim=16)
    none = c3[1]  # frames 3, 4, 5: none valid, so the chunk is not scored
    assert not none.valid.any() and module._score(none.gt, none, "test") == {}


def test_files_without_penetration_still_load(deep, tmp_path):
    """A sequence file written before ``penetration`` was recorded (and a manifest without
    ``invalid_frames``): its frames are valid where they converged."""
    rec = read_manifest(deep)["items"][0]
    seq = store.load_sequence(store.sequence_path(deep, rec))
    meta = {k: v for k, v in seq.pop("meta").items()
            if k not in ("invalid_frames", "resimulated")}
    del seq["penetration"]
    (tmp_path / store.SEQUENCES).mkdir()
    store.write_sequence(tmp_path / store.SEQUENCES / f"{rec['id']}.npz", seq, meta)
    doc = store.rebuild_manifest(tmp_path)
    assert doc["items"][0]["invalid_frames"] is None
    ds = SequenceChunks(tmp_path, None, chunk=10 ** 9, history=3, num_landmarks=64,
                        nystrom_dim=16)
    assert ds.valid(0).tolist() == [t != NONCONVERGED for t in range(8)]
    assert ds[0].valid.tolist() == ds.converged(0).tolist()


# ------------------------------------------------------------------ re-simulation
def quality_simulate(garment, body, motion, material, settings=None, progress=None):
    """A Blender double: frames 3 and 4 are 2 cm deep at the presets' quality; at quality
    >= 10 with collision quality >= 5 only frame 4 is, 1.5 cm."""
    res = skinned_wobble(garment, body, motion, material, settings, progress)
    depth = torch.zeros(motion.num_frames)
    high = settings["quality"] >= 10 and settings["collision_quality"] >= 5
    depth[4] = 0.015 if high else 0.02
    if not high:
        depth[3] = 0.02
    res.penetration, res.max_penetration = depth, 0.01
    return res


def worse_simulate(garment, body, motion, material, settings=None, progress=None):
    """A Blender double whose higher quality run is deeper: the first run is kept."""
    res = quality_simulate(garment, body, motion, material, settings, progress)
    if settings["quality"] >= 10:
        res.penetration[:] = 0.05
    return res


def failing_simulate(garment, body, motion, material, settings=None, progress=None):
    if settings["quality"] >= 10:
        raise RuntimeError("Blender worker exited with status 1")
    return quality_simulate(garment, body, motion, material, settings, progress)


def blender_item():
    return preset("tiny", engine="blender").items()[0]


def test_a_blender_item_with_invalid_frames_is_simulated_again(tmp_path):
    item = blender_item()
    raised = resimulation_settings(item)
    assert {k: raised[k] for k in RESIMULATE} == RESIMULATE
    assert {k: v for k, v in raised.items() if k not in RESIMULATE} == \
        {k: v for k, v in item["settings"].items() if k not in RESIMULATE}
    rec = run_item(item, str(tmp_path), simulate_fn=quality_simulate)
    assert rec["status"] == "ok" and rec["invalid_frames"] == 1
    assert rec["resimulated"] == {"quality": 10, "collision_quality": 5, "frames_before": 2,
                                  "frames_after": 1, "kept": "resimulated"}
    assert rec["settings"] == item["settings"]  # the spec's (the id and seed hash them)
    assert rec["engine"]["settings"]["quality"] == 10  # what made the positions
    seq = store.load_sequence(store.sequence_path(tmp_path, rec))
    assert seq["penetration"][3] == 0.0 and seq["penetration"][4] == pytest.approx(0.015)
    assert seq["meta"]["resimulated"] == rec["resimulated"]
    assert store.rebuild_manifest(tmp_path)["items"][0]["resimulated"] == rec["resimulated"]


@pytest.mark.parametrize("double", [worse_simulate, failing_simulate])
def test_the_better_run_is_kept(tmp_path, double):
    rec = run_item(blender_item(), str(tmp_path), simulate_fn=double)
    assert rec["status"] == "ok" and rec["invalid_frames"] == 2
    r = rec["resimulated"]
    assert r["kept"] == "first" and r["frames_before"] == 2
    if double is worse_simulate:
        assert r["frames_after"] == 8
    else:
        assert r["frames_after"] is None and "status 1" in r["message"]
    assert rec["engine"]["settings"]["quality"] == blender_item()["settings"]["quality"]
    seq = store.load_sequence(store.sequence_path(tmp_path, rec))
    assert seq["penetration"][3] == pytest.approx(0.02)


def test_what_is_not_simulated_again(tmp_path):
    item = blender_item()
    high = dict(item, settings=dict(item["settings"], **RESIMULATE))
    assert resimulation_settings(high) is None  # already that high
    assert resimulation_settings(preset("tiny").items()[0]) is None  # the torch engine
    calls = []

    def counting(*args, **kwargs):
        calls.append(kwargs["settings"]["quality"])
        return quality_simulate(*args, **kwargs)

    rec = run_item(high, str(tmp_path), simulate_fn=counting)
    assert calls == [10] and rec["resimulated"] is None and rec["invalid_frames"] == 1


def test_generation_with_resimulation_resumes(tmp_path):
    spec = preset("tiny", engine="blender")
    s = generate(spec, tmp_path, workers=0, simulate_fn=quality_simulate, progress=False)
    assert s.done == 8
    before = {p.name: store.file_sha256(p) for p in (tmp_path / store.SEQUENCES).iterdir()}
    doc = json.loads((tmp_path / store.MANIFEST).read_text())
    assert all(r["resimulated"]["kept"] == "resimulated" for r in doc["items"])
    again = generate(spec, tmp_path, workers=0, simulate_fn=quality_simulate, progress=False)
    assert again.skipped == 8 and again.done == 0
    assert before == {p.name: store.file_sha256(p)
                      for p in (tmp_path / store.SEQUENCES).iterdir()}


# ------------------------------------------------------------------ the supervised loss
def test_the_supervised_terms_read_the_valid_frames_only():
    pos, faces = grid_mesh(4, 4, dtype=torch.float64)
    T = 4
    shift = torch.tensor([0.01, 0.5, 0.03, 0.7], dtype=torch.float64)  # per frame, along x
    gt = pos.expand(T, -1, -1).clone()
    gt[1] = float("nan")  # an invalid frame's ground truth is never read
    pred = pos.expand(T, -1, -1) + shift.view(T, 1, 1) * torch.tensor([1.0, 0, 0],
                                                                        dtype=torch.float64)
    pred = pred.clone().requires_grad_(True)
    mask = torch.tensor([True, False, True, False])
    loss = GarTransLoss(enabled=["vert", "edge", "norm"])
    total, terms = loss(LossInputs(pred=pred, faces=faces, gt=gt, frame_mask=mask))
    # oracle by hand: a translation moves every vertex by its shift and keeps lengths and
    # normals, so L_vert = 100 * mean(0.01, 0.03) and the other two are 0
    assert float(terms["vert"].detach()) == pytest.approx(100 * (0.01 + 0.03) / 2)
    assert float(terms["edge"].detach()) == pytest.approx(0.0, abs=1e-12)
    assert float(terms["norm"].detach()) == pytest.approx(0.0, abs=1e-12)
    total.backward()
    assert torch.isfinite(pred.grad).all()
    assert float(pred.grad[1].abs().sum()) == 0.0 and float(pred.grad[3].abs().sum()) == 0.0
    # a uniform scale of frame 0 only (frame 2 exact): L_edge = 15 * sum((0.1 l)^2) / 2
    scaled = pos.expand(T, -1, -1).clone()
    scaled[0] = 1.1 * pos
    _, t2 = loss(LossInputs(pred=scaled, faces=faces, gt=gt, frame_mask=mask))
    e = unique_edges(faces, pos.shape[0]).edges
    lengths = (pos[e[:, 1]] - pos[e[:, 0]]).norm(dim=-1)
    assert float(t2["edge"]) == pytest.approx(15 * float(((0.1 * lengths) ** 2).sum()) / 2)
    # without a mask every frame counts (and frame 1's NaN ground truth is read)
    _, t3 = loss(LossInputs(pred=pred.detach(), faces=faces, gt=pos.expand(T, -1, -1)))
    assert float(t3["vert"]) == pytest.approx(100 * float(shift.mean()))


def test_no_valid_frame_leaves_the_physics_terms():
    pos, faces = grid_mesh(4, 4, dtype=torch.float64)
    rest = ClothRest.from_mesh(pos, faces, pos[faces][..., :2])
    pred = (1.1 * pos).expand(2, -1, -1).clone().requires_grad_(True)
    loss = GarTransLoss(enabled=["vert", "curv", "stretch"])
    none = torch.zeros(2, dtype=torch.bool)
    total, terms = loss(LossInputs(pred=pred, faces=faces, gt=pos.expand(2, -1, -1),
                                   rest=rest, frame_mask=none))
    _, full = loss(LossInputs(pred=pred, faces=faces, gt=pos.expand(2, -1, -1), rest=rest))
    assert float(terms["vert"]) == 0.0 and float(terms["curv"]) == 0.0
    assert float(terms["stretch"]) == pytest.approx(float(full["stretch"])) and \
        float(full["stretch"]) > 0
    total.backward()
    assert math.isfinite(float(pred.grad.abs().sum()))
    for bad, err in ((torch.ones(3, dtype=torch.bool), ValueError), (torch.ones(2), ValueError),
                     ([True, False], TypeError)):
        with pytest.raises(err, match="frame_mask"):
            loss(LossInputs(pred=pred, faces=faces, gt=pos.expand(2, -1, -1), rest=rest,
                            frame_mask=bad))


def test_the_valid_frames_table_counts_the_exact_frames(deep, tmp_path):
    """``benchmarks/experiments/valid_frames.py``: per split and in all, the frames of the double's
    hand-written oracle (per sequence: frame 5 not converged; frames 3, 4, 6 deeper than
    1 cm; 4 frames left out; 3 cm deepest)."""
    script = runpy.run_path(str(ROOT / "benchmarks" / "experiments" / "valid_frames.py"),
                            run_name="script")
    script["main"](["--data", str(deep), "--out", str(tmp_path / "vf")])
    rows = {r["split"]: r for r in json.loads((tmp_path / "vf.json").read_text())["rows"]}
    splits = [rec["split"] for rec in read_manifest(deep)["items"]]
    n = {s: splits.count(s) if s != "all" else len(splits) for s in rows}
    for split, r in rows.items():
        assert r["sequences"] == n[split] and r["frames"] == 8 * n[split]
        assert (r["not_converged"], r["deep"], r["left_out"], r["with_invalid"]) == \
            (n[split], 3 * n[split], VALID.count(False) * n[split], n[split])
        assert r["deepest_m"] == pytest.approx(0.03) and r["resimulated"] == 0
    assert n["all"] == 8 and "| 32 (50.0%) |" in (tmp_path / "vf.md").read_text()
