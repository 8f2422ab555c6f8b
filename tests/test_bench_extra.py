"""The bench's extra reports on tiny sizes: GarTrans inputs, scaling, leave-out,
reduced precision and the long autoregressive rollout.  No timed asserts: speed targets
live in the benchmark reports, not here."""
import copy
import json
import math
from types import SimpleNamespace

import pytest
import torch

from garmentgnn.bench import leaveout, precision, report, scaling
from garmentgnn.bench.model_inputs import BenchChunks, untrained_module
from garmentgnn.bench.sequences import build_scene, case_item, make_sequence
from garmentgnn.models import PAPER_FORM
from garmentgnn.bench.timing import num_threads
from garmentgnn.data import Spec, generate
from garmentgnn.body.factory import build_body
from garmentgnn.data.store import load_sequence, sequence_path
from garmentgnn.garments import make_garment
from garmentgnn.models import GarTrans
from garmentgnn.models.baselines import LBSBaseline
from garmentgnn.data import SequenceChunks

NY, LANDMARKS, HISTORY = 8, 16, 2
KW = {"history": HISTORY, "nystrom_dim": NY, "num_landmarks": LANDMARKS}


def _numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _numbers(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield obj


def _vertices(item):
    """Independent vertex count of a case item's garment (the template alone)."""
    g = item["garment"]
    return make_garment(g["kind"], build_body(item["body"]), resolution=g["resolution"],
                        **g["params"]).num_vertices


def _lbs(seq):
    return LBSBaseline()(seq.scene, seq.motion.rotations, seq.motion.translation)


@pytest.fixture(autouse=True)
def one_thread():
    """The bench measures with one torch thread (``Preset.threads``); so do these tests."""
    with num_threads(1):
        yield


@pytest.fixture(scope="module")
def seq():
    return make_sequence(case_item("skirt-walk", "skirt", 200, "walk", 4, {"length": "mini"}), 0)


# --------------------------------------------------------------------------- inputs
def lbs_simulate(garment, body, motion, material, settings=None, progress=None):
    """Test double of the simulator: the garment skinned by LBS (like the bench's LBS)."""
    seq = SimpleNamespace(scene=build_scene(garment, body), motion=motion)
    T = motion.num_frames
    return SimpleNamespace(positions=_lbs(seq).float(), converged=torch.ones(T, dtype=torch.bool),
                           ok=True, message="")


def test_bench_items_equal_the_data_module_items(tmp_path):
    """The oracle is the training data module reading the same sequence from disk."""
    g = [{"kind": "skirt", "params": {"length": "mini"}, "resolution": 200}]
    b = [{"model": "capsule", "shape": "regular"}]
    m = [{"name": "walk", "num_frames": 6, "speed": 1.0, "amplitude": 1.0}]
    s = generate(Spec("t", g, b, m, ["silk"]), tmp_path, workers=0, simulate_fn=lbs_simulate,
                 progress=False)
    assert s.done == 1 and s.failed == 0
    ds = SequenceChunks(tmp_path, None, chunk=4, history=HISTORY, nystrom_dim=NY,
                        num_landmarks=LANDMARKS)
    record = json.loads((tmp_path / "manifest.json").read_text())["items"][0]
    stored = load_sequence(sequence_path(tmp_path, record))
    it = dict(stored["meta"], name="disk")
    bseq = make_sequence(it, it["seed"])
    ours = BenchChunks(bseq, chunk=4, gt=torch.from_numpy(stored["positions"]), **KW)
    assert len(ours) == len(ds) == 2
    for idx in range(2):
        a, b_ = ds[idx], ours[idx]
        assert set(a.keys()) == set(b_.keys())
        for k, v in a.items():
            if isinstance(v, torch.Tensor):
                assert v.dtype == b_[k].dtype, k
                torch.testing.assert_close(b_[k], v, rtol=0, atol=0, msg=k)
        torch.testing.assert_close(b_["rest"].uv_area, a["rest"].uv_area, rtol=0, atol=0)
    # without ground truth the items carry none (nothing is made up)
    assert "gt" not in BenchChunks(bseq, chunk=4, **KW)[0]
    with pytest.raises(ValueError, match="gt"):
        BenchChunks(bseq, gt=torch.zeros(2, 3, 3), **KW)
    with pytest.raises(ValueError, match="chunk"):
        BenchChunks(bseq, chunk=0, **KW)


# --------------------------------------------------------------------------- scaling
def test_cached_static_branch_equals_recomputing_it(seq):
    ds = BenchChunks(seq, chunk=1, **KW)
    module = untrained_module(ds[0])
    with torch.no_grad():
        static = module.encode_static(ds[0])
        for t in range(1, seq.num_frames):
            item = ds[t]
            cached = module(item, static)["final"]
            fresh = copy.copy(item)
            fresh.update(ds._build_static(0)[0])  # a newly built static part
            uncached = module(fresh)["final"]
            torch.testing.assert_close(cached, uncached, rtol=0, atol=1e-6)


def test_scaling_records_and_plot(tmp_path):
    template = case_item("scale", "skirt", 1, "walk", 4, {"length": "mini"})
    items = scaling.scaling_items(template, [200, 400])
    assert [i["name"] for i in items] == ["scale@200", "scale@400"]
    assert template["garment"]["resolution"] == 1  # the template is not modified
    recs = [scaling.run_record(it, warmup=0, repeats=1, **KW) for it in items]
    for r, it in zip(recs, items):
        assert r["status"] == "ok", r.get("traceback")
        # the vertex count is the one the template really produced
        assert r["num_vertices"] == _vertices(it)
        assert r["max_abs_diff_cached_vs_uncached_m"] <= 1e-6
        t = r["timing"]
        for mode in ("cached", "uncached"):
            assert t[mode]["latency_ms"] > 0 and t[mode]["peak_mem_mb"] >= 0
        assert set(t["components"]) == {f"{c}_ms" for c in scaling.COMPONENTS}
        assert all(math.isfinite(x) for x in _numbers(r))
        report.check_record(r)
    assert recs[0]["num_vertices"] < recs[1]["num_vertices"]
    png = scaling.plot(recs, tmp_path / "scaling.png")
    assert png.stat().st_size > 0
    md = "\n".join(scaling.markdown(recs, "scaling.png"))
    assert "| 200 | " in md and "![Scaling](scaling.png)" in md
    with pytest.raises(ValueError, match="resolutions"):
        scaling.scaling_items(template, [0])
    with pytest.raises(ValueError, match="template"):
        scaling.scaling_items({"name": "x"}, [10])
    bad = scaling.run_record(dict(template, garment={"kind": "nope", "params": {},
                                                     "resolution": 10}), **KW)
    assert bad["status"] == "failed" and "nope" in bad["message"]


# --------------------------------------------------------------------------- leave-out
def test_leaveout_measures_what_runs(seq):
    rec = leaveout.run_record(seq, _lbs(seq), warmup=0, repeats=1, **KW)
    assert rec["status"] == "ok", rec.get("traceback")
    report.check_record(rec)
    sc = rec["scenes"]
    assert set(sc) == set(leaveout.SCENES)
    full = sc["full"]
    assert full["branches"]["body_fc"] == 1 and full["branches"]["gru"] == 1
    assert {"collision", "stretch", "shear", "vert", "gravity"} <= set(full["loss_terms"])
    assert sc["no_body"]["branches"]["body_fc"] == 0
    assert "collision" not in sc["no_body"]["loss_terms"]
    assert sc["static_pose"]["branches"]["gru"] == 0
    assert sc["static_pose"]["branches"]["body_fc"] == 1
    assert not {"stretch", "shear"} & set(sc["no_uvs"]["loss_terms"])
    assert rec["not_left_out"] == []  # the current code skips everything asked
    for name, e in sc.items():
        assert all(math.isfinite(x) for x in _numbers(e["timing"])), name
        if name != "full":
            t = e["timing"]
            assert t["saved_ms"] == pytest.approx(t["forced_ms"] - t["left_out_ms"])
    md = "\n".join(leaveout.markdown([rec]))
    assert "Every part the scene does not need is skipped." in md


def test_leaveout_detection_fails_when_a_branch_runs(seq, monkeypatch):
    """A model that runs the body branch without a body must be reported as computing it."""
    original = GarTrans.encode_static

    def always_body(self, inputs):
        if inputs.get("body_joint_dists") is None:
            inputs = copy.copy(inputs)
            inputs.body_joint_dists = torch.zeros(self.body_fc[0].in_features,
                                                  self.num_joints)
        return original(self, inputs)
    monkeypatch.setattr(GarTrans, "encode_static", always_body)
    rec = leaveout.run_record(seq, _lbs(seq), warmup=0, repeats=1, **KW)
    assert rec["status"] == "ok", rec.get("traceback")
    assert rec["scenes"]["no_body"]["check"] == {"body_fc": "computed", "collision": "skipped"}
    assert rec["not_left_out"] == ["no_body: body_fc"]
    assert "Not left out by the current code: no_body: body_fc." in "\n".join(
        leaveout.markdown([rec]))
    with pytest.raises(ValueError, match="scene"):
        leaveout.scene_item({}, "no_legs")


# --------------------------------------------------------------------------- precision
@pytest.mark.float_sensitive
def test_precision_rows_lbs(seq):
    rec = precision.run_record(seq, "lbs", warmup=0, repeats=1)
    assert rec["status"] == "ok", rec.get("traceback")
    report.check_record(rec)
    rows = {(r["dtype"], r["mode"]): r for r in rec["rows"]}
    assert set(rows) == {("float32", "reference")} | {(d, m) for d in ("bfloat16", "float16")
                                                     for m in precision.MODES}
    assert rows["float32", "reference"]["max_dev_m"] == 0.0  # exactly: deterministic
    assert rows["float32", "reference"]["verdict"] == "stable"
    ref = _lbs(seq)
    for (d, mode), r in rows.items():
        assert r["verdict"] in ("stable", "degraded", "failed")
        assert r["status"] == "ok", r.get("message")  # the cast mode runs too
        assert (r["max_dev_m"] is None) == (r["nonfinite"] > 0)
        if mode == "autocast" and r["max_dev_m"] is not None:  # independent recomputation
            with torch.autocast("cpu", dtype=precision.DTYPES[d]):
                out = _lbs(seq).float()
            assert r["max_dev_m"] == float((out - ref).abs().max())
    assert all(math.isfinite(x) for x in _numbers(rec))


@pytest.mark.float_sensitive
def test_precision_rows_gartrans_never_crash(seq):
    rec = precision.run_record(seq, "gartrans", warmup=0, repeats=1, **KW)
    assert rec["status"] == "ok", rec.get("traceback")
    assert rec["module_kwargs"] == PAPER_FORM
    rows = {(r["dtype"], r["mode"]): r for r in rec["rows"]}
    assert rows["float32", "reference"]["max_dev_m"] == 0.0
    for r in rec["rows"]:  # each low-precision row ran (the cast mode on a cast copy)
        assert r["status"] == "ok", r.get("message")
    # autocast: the networks in low precision, the kinematics and skinning in float32
    # (bfloat16 positions alone are ~1 cm off at metre-scale coordinates)
    assert rows["bfloat16", "autocast"]["max_dev_m"] < 1e-3
    assert rows["bfloat16", "cast"]["max_dev_m"] > 1e-3
    assert "## Reduced precision" in "\n".join(precision.markdown([rec]))
    with pytest.raises(ValueError, match="method"):
        precision.run_record(seq, "nope")


def test_precision_verdicts():
    th = precision.PRECISION_THRESHOLDS
    row = {"status": "ok", "nonfinite": 0, "max_dev_m": 0.0}
    assert precision.precision_verdict(row) == ("stable", "")
    assert precision.precision_verdict(dict(row, max_dev_m=2 * th.degrade_deviation))[0] == \
        "degraded"
    assert precision.precision_verdict(dict(row, max_dev_m=2 * th.fail_deviation))[0] == "failed"
    assert precision.precision_verdict(dict(row, nonfinite=1, max_dev_m=None))[0] == "failed"
    v = precision.precision_verdict({"status": "unsupported", "message": "unsupported: x"})
    assert v == ("failed", "unsupported: x")


# --------------------------------------------------------------------------- long sequence
def test_long_metrics_against_known_drift():
    T, V = 40, 5
    fps = 30.0
    coarse = torch.zeros(T, V, 3)
    off = torch.linspace(0.001, 0.008, T).view(T, 1, 1)  # displacement grows 1 -> 8 mm
    pos = coarse + off * torch.tensor([1.0, 0.0, 0.0])
    body = torch.zeros(T, 2, 3)
    m = precision.long_metrics(pos, coarse, body, fps)
    w = T // 2  # the window is capped at half the sequence
    assert m["window"] == w
    assert m["disp_first_m"] == pytest.approx(float(off[:w].mean()))
    assert m["disp_last_m"] == pytest.approx(float(off[-w:].mean()))
    assert m["disp_growth"] == pytest.approx(m["disp_last_m"] / m["disp_first_m"])
    assert m["max_speed"] == pytest.approx(float(off[1] - off[0]) * fps, rel=1e-4)
    assert precision.long_verdict(m)[0] == "degraded"  # growth ~2.3 > 2
    calm = precision.long_metrics(coarse + 0.002, coarse, body, fps)
    assert calm["disp_growth"] == pytest.approx(1.0) and precision.long_verdict(calm)[0] == "stable"
    pos[-1, 0, 0] = float("nan")
    bad = precision.long_metrics(pos, coarse, body, fps)
    assert bad["nonfinite"] == 1 and precision.long_verdict(bad)[0] == "failed"
    with pytest.raises(ValueError, match="positions"):
        precision.long_metrics(pos[:, :2], coarse, body, fps)


def test_long_rollout_20_frames():
    item = case_item("long", "skirt", 200, "walk", 20, {"length": "mini"})
    rec = precision.run_long(item, **KW)
    assert rec["status"] == "ok", rec.get("traceback")
    report.check_record(rec)
    m = rec["metrics"]
    assert m["frames"] == 20 and m["window"] == 10 and m["nonfinite"] == 0
    assert rec["verdict"] in ("stable", "degraded", "failed")
    assert all(math.isfinite(x) for x in _numbers(rec))
    assert rec["num_vertices"] == _vertices(item)
    md = "\n".join(precision.long_markdown([rec]))
    assert "**not run**" in md and "| long |" in md


def test_report_validates_extra_records():
    with pytest.raises(ValueError, match="records"):
        report.check_record({"kind": "scaling", "method": "m", "case": "c", "seed": 0,
                             "status": "ok"})
    failed = {"kind": "precision", "method": "m", "case": "c", "seed": 0, "status": "failed",
              "message": "boom"}
    assert report.check_record(failed)["status"] == "failed"
