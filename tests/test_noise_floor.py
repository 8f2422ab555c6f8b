"""The ground truth's noise floor: perturbations, per-frame divergence, the floor's summary,
and the bench report showing a floor read from a results file (synthetic records)."""
import json
import math

import numpy as np
import pytest
import torch

from garmentgnn.bench import noise_floor as nf
from garmentgnn.bench import report, tables
from garmentgnn.bench.tables import METRICS
from garmentgnn.garments import Garment
from garmentgnn.motion.sequence import Motion


def _garment():
    v = torch.tensor([[0.0, 0.0, 1.2], [0.5, 0.0, 1.2], [0.0, 0.5, 0.9]])
    return Garment(v, torch.tensor([[0, 1, 2]]), v[:, :2].clone(), name="g", kind="other")


def test_offsets_have_the_asked_length_and_are_seeded():
    d = nf.random_offsets(500, 1e-4, seed=3)
    assert d.dtype == torch.float64 and d.shape == (500, 3)
    assert torch.allclose(d.norm(dim=-1), torch.full((500,), 1e-4, dtype=torch.float64),
                          rtol=1e-12, atol=0)
    assert torch.equal(d, nf.random_offsets(500, 1e-4, seed=3))
    assert not torch.equal(d, nf.random_offsets(500, 1e-4, seed=4))
    # directions spread over the sphere: the mean direction is near 0
    assert float((d / 1e-4).mean(0).norm()) < 0.15
    for bad in (-1e-7, float("nan"), True, "1e-7"):
        with pytest.raises(ValueError, match="scale"):
            nf.random_offsets(3, bad, seed=0)


def test_perturbed_garment_and_motion():
    g = _garment()
    p = nf.perturbed_garment(g, 1e-4, seed=0)
    step = (p.vertices.double() - g.vertices.double()).norm(dim=-1)
    # float32 at ~1 m rounds to ~6e-8 m per coordinate
    assert p.vertices.dtype == torch.float32 and torch.all((step - 1e-4).abs() < 2e-7)
    assert torch.equal(p.faces, g.faces) and torch.equal(p.face_uv, g.face_uv)
    assert g.vertices[0, 2].item() == pytest.approx(1.2)  # the input is untouched
    T = 6
    m = Motion(torch.zeros(T, 2, 3), torch.zeros(T, 3, dtype=torch.float64), ["a", "b"], 30.0)
    q = nf.perturbed_motion(m, 1e-7, seed=1)
    assert torch.equal(q.rotations, m.rotations) and q.fps == 30.0
    assert torch.allclose(q.translation.norm(dim=-1), torch.full((T,), 1e-7, dtype=torch.float64))
    assert float(m.translation.abs().max()) == 0.0


def test_divergence_matches_numpy():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 7, 3))
    b = a + rng.normal(scale=1e-3, size=a.shape)
    mean, mx = nf.divergence(torch.tensor(a), torch.tensor(b, dtype=torch.float32))
    d = np.sqrt(((a - b.astype(np.float32).astype(np.float64)) ** 2).sum(-1)) * 100
    assert np.allclose(mean, d.mean(1), rtol=1e-12) and np.allclose(mx, d.max(1), rtol=1e-12)
    assert nf.divergence(torch.tensor(a), torch.tensor(a)) == ([0.0] * 4, [0.0] * 4)
    with pytest.raises(ValueError, match="one shape"):
        nf.divergence(torch.zeros(2, 3, 3), torch.zeros(3, 3, 3))


def _runs():
    def run(engine, seq, what, scale, mean, mx, status="ok"):
        return {"engine": engine, "preset": "tiny", "sequence": seq, "what": what,
                "scale_m": scale, "mean_cm": mean, "max_cm": mx, "status": status}
    return [run("torch", "a", "garment", 1e-7, [0.0, 0.1, 0.2], [0.0, 1.0, 2.0]),
            run("torch", "b", "garment", 1e-7, [0.0, 0.3], [0.0, 5.0]),
            run("torch", "a", "garment", 1e-4, [1.0, 9.0], [3.0, 90.0]),
            run("torch", "a", "body", 1e-7, [7.0, 7.0], [70.0, 70.0]),
            run("torch", "c", "garment", 1e-7, [50.0], [500.0], status="failed"),
            run("blender", "s", "garment", 1e-7, [0.5, 0.5], [2.0, 4.0]),
            run("blender", "s", "repeat", 0.0, [0.0, 0.0], [0.0, 0.0])]


def test_summarize_takes_the_ok_runs_of_one_perturbation():
    floor = nf.summarize(_runs())
    assert set(floor) == {"torch", "blender"}
    assert floor["torch"]["mean_cm"] == pytest.approx(0.6 / 5) and floor["torch"]["max_cm"] == 5.0
    assert floor["torch"]["sequences"] == 2 and floor["torch"]["frames"] == 5
    assert floor["blender"]["mean_cm"] == pytest.approx(0.5) and floor["blender"]["max_cm"] == 4.0
    assert nf.summarize(_runs(), scale=1e-4)["torch"]["max_cm"] == 90.0
    assert nf.summarize(_runs(), what="body")["torch"]["mean_cm"] == 7.0


def _results_file(tmp_path):
    path = tmp_path / "gt_noise.json"
    path.write_text(json.dumps({"meta": {}, "floor": nf.summarize(_runs()), "runs": _runs()}))
    return path


def test_load_floor(tmp_path, monkeypatch):
    path = _results_file(tmp_path)
    loaded = nf.load_floor(path)
    assert loaded["path"] == str(path) and loaded["floor"]["blender"]["mean_cm"] == 0.5
    assert nf.load_floor(tmp_path / "none.json") is None
    monkeypatch.setenv(nf.ENV, str(path))
    assert nf.load_floor()["path"] == str(path)
    monkeypatch.delenv(nf.ENV)
    if nf.COMMITTED.is_file():  # the committed file is named by its place in the repository
        assert nf.load_floor()["path"] == "docs/results/benchmarks/gt_noise.json"
    bad = tmp_path / "bad.json"
    for text in ("{", '{"floor": {"torch": {"mean_cm": -1, "max_cm": 1, "scale_m": 1e-7}}}',
                 '{"runs": []}', '{"floor": {"torch": 3}}'):
        bad.write_text(text)
        with pytest.raises(ValueError, match="bad.json"):
            nf.load_floor(bad)


def _accuracy(method, e_dist, latency):
    return {"kind": "accuracy", "method": method, "case": "walk", "seed": 0, "status": "ok",
            "reference": method == "simulator",
            "metrics": {m: (e_dist if m == "E_dist" else 0.1) for m in METRICS},
            "timing": {"latency_ms": latency, "throughput_fps": 10.0, "peak_mem_mb": 1.0}}


def test_report_shows_the_floor_from_the_results_file(tmp_path, monkeypatch):
    records = [_accuracy("simulator", 0.0, 900.0), _accuracy("lbs", 4.0, 1.0),
               _accuracy("gartrans", 0.3, 20.0)]
    drawn = []
    real = tables.save_figure

    def spy(fig, path):  # the plot's bands, read off the figure before it is saved
        ax = fig.axes[0]
        drawn.append([(t.get_text()) for t in ax.get_legend().get_texts()])
        drawn.append([p.get_extents() for p in ax.patches])
        return real(fig, path)

    monkeypatch.setattr(tables, "save_figure", spy)
    paths = report.write_report(records, tmp_path / "r", floor=_results_file(tmp_path))
    md = paths["report"].read_text()
    summary = md.split("## Accuracy and cost over all cases")[1].split("\n## ")[0]
    torch_row = next(line for line in summary.splitlines()
                     if "noise floor: torch simulator (rest garment ±1e-07 m)" in line)
    cells = [c.strip() for c in torch_row.strip("|").split("|")]
    assert cells[1 + METRICS.index("E_dist")] == "0.12"  # 0.6 cm over 5 frames
    assert "noise floor: Blender (rest garment ±1e-07 m)* | " in summary
    assert "## The ground truth's noise floor" in md and "| 0.5 | 4 |" in md
    legend = drawn[0]
    assert "noise floor: Blender (rest garment ±1e-07 m): 0.5 cm" in legend
    assert "noise floor: torch simulator (rest garment ±1e-07 m): 0.12 cm" in legend
    assert len(drawn[1]) == 2  # two bands
    # no results file: no floor, and the report says nothing about one
    monkeypatch.setenv(nf.ENV, str(tmp_path / "missing.json"))
    md = report.write_report(records, tmp_path / "r2")["report"].read_text()
    assert "noise floor" not in md


def test_floor_reads_the_frames_valid_in_both_runs():
    """A run's ``valid`` leaves frames out of the floor (as every score leaves out frames
    that are not valid ground truth); the mean with them is kept beside it."""
    runs = _runs()[:2]
    runs[0] = dict(runs[0], valid=[True, False, True])  # 0.0, (0.1), 0.2
    f = nf.summarize(runs)["torch"]
    assert f["frames"] == 4 and f["left_out"] == 1
    assert f["mean_cm"] == pytest.approx(0.5 / 4) and f["all_frames_mean_cm"] == \
        pytest.approx(0.6 / 5)
    assert f["max_cm"] == 5.0
    none = nf.summarize([dict(runs[1], valid=[False, False])])["torch"]
    assert none["frames"] == 0 and none["max_cm"] == 0.0 and math.isnan(none["mean_cm"])


def test_a_dataset_preset_reads_its_own_committed_floor(tmp_path, monkeypatch):
    default = tmp_path / "gt_noise.json"
    monkeypatch.setattr(nf, "COMMITTED", default)
    monkeypatch.delenv(nf.ENV, raising=False)
    assert nf.committed("learn") == default and nf.committed(None) == default
    own = tmp_path / "gt_noise_learn.json"
    own.write_text(json.dumps({"meta": {}, "floor": nf.summarize(_runs()), "runs": []}))
    assert nf.committed("learn") == own and nf.committed("small") == default
    assert nf.load_floor(dataset="learn")["floor"]["torch"]["frames"] == 5
    assert nf.load_floor(dataset="small") is None  # no default file in tmp_path


def test_committed_results_file_loads_when_present():
    loaded = nf.load_floor(nf.COMMITTED)
    if loaded is None:
        pytest.skip("docs/results/benchmarks/gt_noise.json not written yet")
    assert {"blender", "torch"} <= set(loaded["floor"])
    for f in loaded["floor"].values():
        assert f["scale_m"] == nf.FLOOR_SCALE_M and 0 < f["mean_cm"] <= f["max_cm"]
