"""A new method is one module file and one recipe (docs/model.md, "Adding a method", as
written there): in a folder of its own (never inside the package), it trains with
``garmentgnn train fit``, is benchmarked with ``garmentgnn bench --methods toy.yaml``,
predicts with ``garmentgnn predict --ckpt`` and is shown with ``garmentgnn show``,
through the method protocol of :class:`~garmentgnn.training.GarmentModule`.

The toy method extrapolates the skinned garment at constant velocity by one learned scalar
``k``: ``x_t = LBS_t + k (LBS_t - LBS_{t-1})``.  Oracles: that formula evaluated here with
the trained ``k`` on the dataset's stored arrays (the bench's E_dist, by hand) and on the
LBS garment ``predict --method lbs`` writes; the least-squares ``k`` of the training
frames, which the trained one must approach from 0.
"""
import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from garmentgnn.cli import main as cli_main
from garmentgnn.data import SequenceChunks
from garmentgnn.viz.animate import renderer_unavailable

from conftest import skirt_dataset
from test_own_garment import files  # noqa: F401 (a fixture)
from test_predict import read_pc2

DOC = Path(__file__).resolve().parents[1] / "docs" / "model.md"


def walkthrough():
    """docs/model.md's "Adding a method" files, {name: content}, as written there."""
    text = DOC.read_text().split("### Adding a method", 1)[1].split("\n### ", 1)[0]
    return dict(re.findall(r"^```\w+ (\S+)\n(.*?)^```", text, re.S | re.M))


def toy(frames: np.ndarray, k: float) -> np.ndarray:
    """The toy's garment from an LBS garment ``[T, V, 3]`` (frame 0: no earlier frame,
    its pose held)."""
    before = np.concatenate([frames[:1], frames[:-1]])
    return frames + k * (frames - before)


def test_a_method_in_a_folder_of_its_own_trains_benches_predicts_and_shows(
        files, tmp_path, monkeypatch, capsys):  # noqa: F811
    folder = tmp_path / "mine"
    folder.mkdir()
    files_ = walkthrough()
    assert set(files_) == {"toymethod.py", "toy.yaml"}
    for name, content in files_.items():
        (folder / name).write_text(content)
    monkeypatch.syspath_prepend(str(folder))
    data = skirt_dataset(tmp_path / "data", ["walk", "run", "arm_swing"], 6,
                         held_out={"test": ["arm_swing"]}, name="mini")

    # train fit
    run = tmp_path / "run"
    assert cli_main(["train", "fit", "--config", str(folder / "toy.yaml"), "--data.root",
                     str(data), "--trainer.default_root_dir", str(run),
                     "--seed_everything", "0"]) == 0
    (ckpt,) = [p for p in run.rglob("*.ckpt") if p.name != "last.ckpt"]
    k = float(torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]["model.k"])
    train = SequenceChunks(data, "train", chunk=10 ** 9, history=2)
    num = den = 0.0
    for i in range(len(train)):
        item = train[i]
        lbs = item.skinned().double().numpy()
        d = lbs - np.concatenate([lbs[:1], lbs[:-1]])
        num += float((d * (item["gt"].double().numpy() - lbs)).sum())
        den += float((d * d).sum())
    best = num / den
    assert abs(best) > 1e-3  # the data has something to learn
    assert abs(k - best) < 0.5 * abs(best), (k, best)

    # bench: the toy and LBS on the test split
    out = tmp_path / "bench"
    assert cli_main(["bench", "--out", str(out), "--data", str(data), "--learned-only",
                     "--no-progress", "--methods", str(folder / "toy.yaml"),
                     "LBS only"]) == 0
    recs = {r["method"]: r for r in json.loads((out / "results.json").read_text())["records"]
            if r["kind"] == "learned"}
    rec = recs[str(folder / "toy.yaml")]
    assert rec["status"] == "ok", rec.get("message")
    bench_ckpt = torch.load(rec["checkpoint"], map_location="cpu", weights_only=False)
    kb = float(bench_ckpt["state_dict"]["model.k"])
    test = SequenceChunks(data, "test", chunk=10 ** 9, history=2)
    item, keep = test[0], test.valid(0).numpy()
    pred = toy(item.skinned().double().numpy(), kb)
    err = np.linalg.norm(pred - item["gt"].double().numpy(), axis=-1)[keep]
    assert rec["metrics"]["E_dist"] == pytest.approx(100 * err.mean(), rel=1e-4)
    assert rec["metrics"]["E_dist"] != pytest.approx(recs["LBS only"]["metrics"]["E_dist"])
    assert rec["timing"]["latency_ms"] > 0

    # predict on a garment file, a body and a BVH take, against LBS on the same inputs
    common = ["--garment", str(files / "skirt.obj"), "--body", "regular", "--motion",
              str(files / "twirl.bvh"), "--scale", "0.01", "--frames", "5"]
    assert cli_main(["predict", "--method", "lbs", "--out", str(tmp_path / "p" / "lbs"),
                     *common]) == 0
    assert cli_main(["predict", "--ckpt", str(ckpt), "--out", str(tmp_path / "p" / "toy"),
                     *common]) == 0
    assert "ToyModule, frame-parallel: 5 frames" in capsys.readouterr().out

    pc2 = {n: read_pc2(tmp_path / "p" / f"{n}.pc2").astype(np.float64) for n in ("lbs", "toy")}
    np.testing.assert_allclose(pc2["toy"][1:], toy(pc2["lbs"], k)[1:], atol=2e-6)

    # show: the toy's panel beside the ground truth and LBS
    if renderer_unavailable():
        pytest.skip(f"show renders: {renderer_unavailable()}")
    shown = tmp_path / "show" / "cmp"
    assert cli_main(["show", "--data", str(data), "--ckpt", f"toy={ckpt}", "--out",
                     str(shown), "--no-gif", "--max-frames", "3", "--height", "720"]) == 0
    names = set(trimesh.load(shown.with_suffix(".glb"), force="scene").geometry)
    assert any("toy" in n for n in names), names




#: the packaged methods' classes, and the files allowed to name them in a test of a class
#: (their own, and the model packages that define them)
METHOD_CLASSES = ("GarTransModule", "BaselineModule", "RolloutModule", "MGNStyle", "DAStyle",
                  "HOODStyle", "NCSStyle")
OWN = ("training/module.py", "training/baselines.py", "training/rollout.py", "models/")
#: a decision by class: ``isinstance(x, RolloutModule)``, ``name == "NCSStyle"``, a
#: dict keyed by a class's name
BY_CLASS = re.compile(r"isinstance\([^)]*\b(%s)\b|==\s*[\"'](%s)[\"']|[\"'](%s)[\"']\s*:"
                      % (("|".join(METHOD_CLASSES),) * 3))


def test_no_method_is_known_by_its_class_outside_its_own_module():
    src = Path(__file__).resolve().parents[1] / "src" / "garmentgnn"
    found = [f"{p.relative_to(src)}:{i}: {line.strip()}"
             for p in sorted(src.rglob("*.py")) if not str(p.relative_to(src)).startswith(OWN)
             for i, line in enumerate(p.read_text().splitlines(), 1) if BY_CLASS.search(line)]
    assert found == []
    # the pattern finds what it is for
    assert BY_CLASS.search("if isinstance(module, RolloutModule):")
    assert BY_CLASS.search('KINDS = {"GarTransModule": "gartrans"}')
    assert BY_CLASS.search("if name == 'NCSStyle':")
