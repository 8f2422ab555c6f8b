"""The bench: tiny preset end to end, resume, atomic records, report rules."""
import json
import math
import os
import shlex
import time
from pathlib import Path

import pytest
import torch

from garmentgnn.bench import runner, precision, presets, report, stability, tables, timing
from garmentgnn.models.inputs import skin
from garmentgnn.bench.cli import _command, _learned_overrides
from garmentgnn.bench.records import NOT_RUN, failure, section
from garmentgnn.bench.sequences import case_item, make_sequence
from garmentgnn.cli import build_parser, main as cli_main
from garmentgnn.data import store
from garmentgnn.models.baselines import LBSBaseline
from garmentgnn.motion import within_limits

from conftest import ZERO_AREA_M2, numbers





@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    t0 = time.perf_counter()
    summary = runner.run(presets.preset("tiny"), out, progress=False, learned=False)
    return out, summary, time.perf_counter() - t0


def test_tiny_preset_report(tiny_run):
    out, summary, seconds = tiny_run
    p = presets.preset("tiny")
    expected = len(runner.tasks(p, [0]))
    assert summary.ran == expected and summary.skipped == 0
    for name in ("results.json", "report.md", "pareto.png", "scaling.png"):
        assert (out / name).stat().st_size > 0
    res = json.loads((out / "results.json").read_text())
    assert set(res) == {"meta", "summary", "not_run", "records"}
    recs = res["records"]
    assert len(recs) == expected
    assert len(list((out / "records").glob("*.json"))) == expected
    for r in recs:  # every number finite (no NaN/None smuggled in as a number)
        assert all(math.isfinite(x) for x in numbers(r)), r
    acc = [r for r in recs if r["kind"] == "accuracy"]
    assert {r["method"] for r in acc} == set(p.method_names())
    assert all(r["status"] == "ok" for r in acc), [r["message"] for r in acc]
    for r in acc:
        assert set(report.METRICS) <= set(r["metrics"])
        assert r["timing"]["latency_ms"] > 0 and r["timing"]["throughput_fps"] > 0
    ref = [r for r in acc if r["reference"]]
    assert len(ref) == 1 and ref[0]["metrics"]["E_dist"] == 0.0
    lbs = next(r for r in acc if r["method"] == "lbs")
    assert lbs["metrics"]["E_dist"] > 0 and lbs["timing"]["best_batch"] in p.batches
    stab = [r for r in recs if r["kind"] == "stability"]
    assert {r["case"] for r in stab} == set(p.stability_cases)
    assert all(r["verdict"] in ("stable", "degraded", "failed") for r in stab)
    # nothing was run for the learned methods (learned=False; tests/test_bench_learned.py
    # runs them), and the report says so without numbers
    assert set(runner.PLANNED) <= set(res["not_run"])
    md = (out / "report.md").read_text()
    assert "shaped like Table 1" in md and "shaped like Table 3" in md and "## Stability" in md
    for name in runner.PLANNED:
        assert f"- {name}: not run" in md


def test_tiny_preset_extra_reports(tiny_run):
    """Scaling, leave-out, precision and long-sequence records and report sections."""
    out, _, _ = tiny_run
    p = presets.preset("tiny")
    recs = json.loads((out / "results.json").read_text())["records"]
    by_kind = {k: [r for r in recs if r["kind"] == k]
               for k in ("scaling", "leaveout", "precision", "long_sequence")}
    for kind, rs in by_kind.items():
        assert rs and all(r["status"] == "ok" for r in rs), (kind, [r["message"] for r in rs])
    sc = by_kind["scaling"]
    assert sorted(r["resolution"] for r in sc) == sorted(p.scaling_resolutions)
    for r in sc:
        assert r["timing"]["cached"]["latency_ms"] > 0
        assert r["max_abs_diff_cached_vs_uncached_m"] <= 1e-6
    assert (out / "scaling.png").stat().st_size > 0
    lo = by_kind["leaveout"][0]
    assert lo["case"] == p.cases[0]["name"]
    assert lo["scenes"]["full"]["branches"]["body_fc"] == 1
    assert lo["scenes"]["no_body"]["branches"]["body_fc"] == 0
    assert {r["method"] for r in by_kind["precision"]} == set(
        precision.METHODS[m] for m in p.precision_methods)
    for r in by_kind["precision"]:
        f32 = next(w for w in r["rows"] if w["dtype"] == "float32")
        assert f32["max_dev_m"] == 0.0
        assert all(w["verdict"] in ("stable", "degraded", "failed") for w in r["rows"])
    long_ = by_kind["long_sequence"][0]
    assert long_["metrics"]["frames"] == p.long_item["motion"]["num_frames"]
    assert long_["verdict"] in ("stable", "degraded", "failed")
    md = (out / "report.md").read_text()
    for title in ("## Scaling", "## Leave-out", "## Reduced precision", "## Long sequence"):
        assert title in md
    assert "![Scaling](scaling.png)" in md
    assert "Reference simulator on the long sequence: **not run**" in md


def test_rerun_skips_finished_records(tiny_run):
    out, _, _ = tiny_run
    before = {p.name: p.stat().st_mtime_ns for p in (out / "records").glob("*.json")}
    summary = runner.run(presets.preset("tiny"), out, progress=False, learned=False)
    assert summary.ran == 0 and summary.skipped == len(before)
    after = {p.name: p.stat().st_mtime_ns for p in (out / "records").glob("*.json")}
    assert after == before


def test_deleted_record_is_rerun_and_leftovers_removed(tiny_run):
    out, _, _ = tiny_run
    rec = runner.record_path(out, "accuracy", "lbs", "skirt-walk", 0)
    rec.unlink()
    stale = rec.with_name(f".{rec.name}.tmp-99999")
    stale.write_text('{"half": ')  # a killed writer's leftover
    summary = runner.run(presets.preset("tiny"), out, progress=False, learned=False)
    assert summary.ran == 1
    assert json.loads(rec.read_text())["status"] == "ok"
    assert not stale.exists()


def test_record_is_never_half_written(tmp_path, monkeypatch):
    """A crash between writing and renaming leaves no record (and no temporary)."""
    path = runner.record_path(tmp_path, "accuracy", "m", "c", 0)

    def crash(src, dst):
        raise OSError("killed before rename")
    monkeypatch.setattr(store.os, "replace", crash)
    with pytest.raises(OSError):
        store.atomic_write_json(path, {"kind": "accuracy"})
    assert not path.exists()
    assert list(path.parent.iterdir()) == []
    monkeypatch.undo()
    # an existing but truncated/foreign file is not taken as a finished record
    path.write_text('{"kind": "accuracy", "method": "m"')
    assert runner.load_record(path, "accuracy", "m", "c", 0) is None
    path.write_text(json.dumps({"kind": "accuracy", "method": "other", "case": "c", "seed": 0,
                                "status": "ok"}))
    assert runner.load_record(path, "accuracy", "m", "c", 0) is None


def _acc(method="m", seed=0, status="ok", e=1.0, latency=2.0):
    return {"kind": "accuracy", "method": method, "case": "c", "seed": seed, "status": status,
            "message": "", "metrics": {m: e for m in report.METRICS},
            "timing": {"latency_ms": latency, "throughput_fps": 1e3 / latency,
                       "peak_mem_mb": 1.0}}


def test_report_refuses_non_finite_unless_failed(tmp_path):
    bad = _acc(e=float("nan"))
    with pytest.raises(ValueError, match="records"):
        report.write_report([bad], tmp_path)
    failed = dict(_acc("f", e=float("inf")), status="failed", message="diverged")
    paths = report.write_report([_acc("a", 0, e=1.0), _acc("a", 1, e=3.0), failed], tmp_path,
                                not_run=["x"])
    res = json.loads(paths["results"].read_text())
    assert res["summary"]["a"]["E_dist"] == {"mean": 2.0, "std": pytest.approx(math.sqrt(2)),
                                             "n": 2}
    assert res["records"][2]["metrics"]["E_dist"] is None
    md = paths["report"].read_text()
    assert "2 ± 1.4" in md and "| f | failed" in md and "- x: not run" in md
    with pytest.raises(ValueError, match="records"):
        report.write_report([{"kind": "accuracy"}], tmp_path)


def test_pareto_front():
    pts = [("a", 1.0, 5.0), ("b", 10.0, 1.0), ("c", 10.0, 6.0), ("d", 0.5, 7.0)]
    assert tables.pareto_front(pts) == ["a", "b", "d"]


def test_timing_helpers():
    with timing.num_threads(1):
        m = timing.side_by_side({"a": lambda: torch.ones(10).sum(),
                                 "b": lambda: torch.ones(1000).sum()}, warmup=1, repeats=3)
        assert set(m) == {"a", "b"} and m["a"]["threads"] == 1 and m["a"]["repeats"] == 3
        sweep = timing.batch_sweep(lambda b: (lambda: torch.ones(b, 100).sum()), [1, 4],
                                   warmup=0, repeats=2)
        assert sweep["best_batch"] in (1, 4) and sweep["latency_ms"] > 0
    mem = timing.peak_memory(lambda: torch.ones(8 << 20).sum())  # 32 MiB transient
    assert mem["peak_mb"] >= 16 and float(mem["result"]) == 8 << 20
    with pytest.raises(ValueError, match="batches"):
        timing.batch_sweep(lambda b: (lambda: None), [2, 4])
    with pytest.raises(ValueError, match="repeats"):
        timing.measure(lambda: None, repeats=0)


def test_stability_verdicts_and_plugged_predictor():
    m = {"nonfinite": 0.0, "max_speed": 1.0, "body_max_speed": 1.0, "energy_growth": 2.0,
         "max_penetration_m": 0.0}
    assert stability.verdict(m, True, 0) == ("stable", "")
    assert stability.verdict(dict(m, max_speed=100.0), True, 0)[0] == "failed"
    assert stability.verdict(dict(m, energy_growth=20.0), True, 0)[0] == "degraded"
    assert stability.verdict(m, True, 1)[0] == "degraded"
    assert stability.verdict(m, False, 0)[0] == "failed"
    assert stability.verdict(dict(m, nonfinite=3.0), True, 0)[0] == "failed"
    item = presets.preset("tiny").stability_item

    def exploding(seq):  # a learned method that blows up
        pos = LBSBaseline()(seq.scene, seq.motion.rotations, seq.motion.translation)
        pos[-1, 0, 0] = float("nan")
        return pos

    rec = stability.run_case("baseline", item, 0, exploding, method="nan-model")
    assert rec["status"] == "ok" and rec["verdict"] == "failed" and rec["metrics"]["nonfinite"] == 1

    def crashing(seq):
        raise RuntimeError("boom")
    rec = stability.run_case("baseline", item, 0, crashing)
    assert rec["status"] == "failed" and "boom" in rec["message"]
    with pytest.raises(ValueError, match="case"):
        stability.stability_sequence("nope", item, 0)


@pytest.mark.float_sensitive
def test_degenerate_and_extreme_cases_are_what_they_claim():
    item = presets.preset("tiny").stability_item
    seq, info = stability.stability_sequence("zero_area_face", item, 0)
    assert 0.0 <= info["uv_area_m2"] < ZERO_AREA_M2
    assert not bool(seq.rest.valid[info["face"]])
    seq, info = stability.stability_sequence("sliver_face", item, 0)
    assert info["uv_area_m2"] > 1e3 * ZERO_AREA_M2 and bool(seq.rest.valid[info["face"]])
    seq, info = stability.stability_sequence("extreme_pose", item, 0)
    assert info["joint_frames_clamped"] > 0
    assert within_limits(seq.motion.rotations, seq.body.skeleton, tol_deg=1e-2)
    seq, info = stability.stability_sequence("long_1000", item, 0)
    assert seq.num_frames == 1000 == info["num_frames"] and seq.body_frames.shape[0] == 1000


@pytest.mark.float_sensitive
def test_degenerate_case_on_a_pattern_laid_flat_per_face():
    """A T-shirt's face_uv is laid flat per face (no vertex whose UV corners all agree):
    the sliver still has 1/1000 of its face's UV area and the zero-area face exactly 0,
    every UV corner of the moved vertex shifted by the same step."""
    item = case_item("t", "tshirt", 200, "walk", 3, {"sleeves": "none"})
    base = make_sequence(item, 0).garment
    seq, info = stability.stability_sequence("sliver_face", item, 0)
    f, v = info["face"], info["vertex"]
    assert info["uv_corner_spread_m"] > 0  # no seam-free vertex: the smallest spread
    a0 = base.face_uv[f]
    area0 = 0.5 * abs(float(torch.linalg.det(torch.stack([a0[1] - a0[0], a0[2] - a0[0]]))))
    assert info["uv_area_m2"] == pytest.approx(area0 / 1000, rel=1e-2)
    mask = (base.faces == v)
    step = (seq.garment.face_uv - base.face_uv)[mask]
    assert torch.allclose(step, step[:1].expand_as(step), atol=1e-7) and step.abs().max() > 0
    assert torch.equal(seq.garment.face_uv[~mask], base.face_uv[~mask])
    seq, info = stability.stability_sequence("zero_area_face", item, 0)
    assert 0.0 <= info["uv_area_m2"] < ZERO_AREA_M2 and not bool(seq.rest.valid[info["face"]])


def test_register_and_cli_arguments(tmp_path):
    with pytest.raises(ValueError, match="name"):
        runner.register("lbs", lambda p: None)
    with pytest.raises(ValueError, match="factory"):
        runner.register("new", 3)
    with pytest.raises(ValueError, match="preset"):
        presets.preset("huge")
    with pytest.raises(ValueError, match="seeds"):
        runner.run(presets.preset("tiny"), tmp_path, seeds=0)
    assert cli_main(["bench", "--out", str(tmp_path), "--seeds", "0"]) == 2
    for bad in ("2/2", "1", "a/b", "0/2/3", "-1/2"):
        assert cli_main(["bench", "--out", str(tmp_path), f"--shard={bad}"]) == 2
    with pytest.raises(ValueError, match="shard"):
        runner.run(presets.preset("tiny"), tmp_path, shard=(2, 2))
    assert not os.listdir(tmp_path)
    assert Path(runner.__file__).exists()


@pytest.mark.parametrize("line", [
    "garmentgnn bench --preset medium --out /o --data /d",
    "garmentgnn bench --preset tiny --out o --seeds 2 --no-learned --retry-failed --no-progress",
    "garmentgnn bench --preset converge --out o --data d --minutes 2.5 --shard 1/2 "
    "--methods 'GarTrans (SAT)' DA-style",
    "garmentgnn bench --preset learn --out o --data d --batch-size 16 --lr-factor 4.0"])
def test_report_command_is_the_command_line(line):
    """The command the report quotes parses back to the same arguments."""
    args = build_parser().parse_args(shlex.split(line)[1:])
    assert _command(args) == line
    assert build_parser().parse_args(shlex.split(_command(args))[1:]) == args


def test_minutes_and_methods_override_the_preset(tmp_path, capsys):
    """``--minutes``/``--methods``: the learned budget and methods replaced, the seed
    plan's fixed methods kept where chosen; refused without learned runs."""
    conv = presets.preset("converge")
    full = conv.learned.seed_methods[0]
    p = _learned_overrides(conv, 90.0, ["DA-style", full, "DA-style"])
    assert p.learned.minutes == 90.0 and p.learned.methods == ("DA-style", full)
    assert p.learned.seed_methods == (full,) and p.learned.equal_steps == conv.learned.equal_steps
    assert _learned_overrides(conv, None, ["DA-style"]).learned.seed_methods == ()
    assert _learned_overrides(conv, None, None) is conv
    with pytest.raises(ValueError, match="minutes"):
        _learned_overrides(conv, 0.0, None)
    b = _learned_overrides(conv, None, None, 16, 4.0).learned
    assert (b.batch_size, b.lr_factor, b.minutes) == (16, 4.0, conv.learned.minutes)
    for args, flag in (((0, None), "--batch-size"), ((None, -1.0), "--lr-factor")):
        with pytest.raises(ValueError, match=flag):
            _learned_overrides(conv, None, None, *args)
    out = str(tmp_path / "o")
    assert cli_main(["bench", "--out", out, "--no-learned", "--minutes", "1"]) == 2
    assert cli_main(["bench", "--out", out, "--no-learned", "--batch-size", "4"]) == 2
    assert cli_main(["bench", "--out", out, "--batch-size", "0"]) == 2
    # neither a method nor a recipe: one error line naming both kinds of choice
    capsys.readouterr()
    assert cli_main(["bench", "--out", out, "--methods", "no-such-method"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: `methods`: unknown ['no-such-method']") and "recipe" in err
    assert err.count("\n") == 1
    assert not (tmp_path / "o").exists()


def test_failed_record_fields_and_report_section_start():
    try:
        raise RuntimeError("boom")
    except RuntimeError as err:
        fields = failure(err)
    assert fields["status"] == "failed" and fields["message"] == "RuntimeError: boom"
    assert "RuntimeError: boom" in fields["traceback"]
    recs, lines = section([{"kind": "a", "i": 0}, {"kind": "b"}, {"kind": "a", "i": 1}], "a", "A")
    assert [r["i"] for r in recs] == [0, 1] and lines == ["## A", ""]
    assert section([{"kind": "b"}], "a", "A") == ([], ["## A", "", NOT_RUN, ""])


def test_energy_growth_is_measured_against_the_lbs_garment():
    """A rollout that starts at rest is not scored against its (zero) start energy: LBS
    itself grows by 1 at most (it was 8e8 on `learn`), a garment held at rest has no
    growth, and a tenfold jump in the LBS garment's speed at one frame is measured
    against the LBS garment's largest energy."""
    item = presets.preset("tiny").stability_item
    seq, _ = stability.stability_sequence("baseline", item, 0)
    T = seq.num_frames
    m = seq.motion
    lbs, _ = skin(seq.scene, m.rotations.to(seq.scene.rest_pos.dtype),
                  m.translation.to(seq.scene.rest_pos.dtype))
    lbs = lbs.double()
    out = stability.stability_metrics(seq, lbs)
    assert out["energy_growth"] <= 1.0 + 1e-9
    still = stability.stability_metrics(seq, seq.scene.rest_pos.double().expand(T, -1, -1))
    assert still["energy_growth"] <= 1.0
    assert stability.verdict(out, True, 0)[0] != "failed"
    # from frame k >= 2 on, shifted so that frame k's velocity is 10x LBS's there
    v = (lbs[1:] - lbs[:-1])
    k = int(v[1:].norm(dim=-1).amax(-1).argmax()) + 2
    fast = lbs.clone()
    fast[k:] += 9 * v[k - 1]
    e = stability.garment_energy(seq, fast)
    assert float(e.max()) / out["lbs_max_energy_J"] == pytest.approx(
        stability.stability_metrics(seq, fast)["energy_growth"])
    assert stability.stability_metrics(seq, fast)["energy_growth"] > 2
