"""The engines as bench methods (:mod:`garmentgnn.bench.engines`): a dataset's sequence
simulated again at the dataset's own settings reproduces its file (the oracle), a
cheaper budget is worse but finite, a different scene is caught, and bad arguments and
failing engines give clear errors and failed records."""
import json
import random

import pytest
import torch

from garmentgnn.bench import engines
from garmentgnn.bench.engines import (KIND, EngineSetting, default_settings, engine_record,
                                      pick_sequences, resolve_settings)
from garmentgnn.data import store
from garmentgnn.data.generate import generate
from garmentgnn.data.keys import motion_key
from garmentgnn.data.presets import BLENDER_SETTINGS, Spec
from garmentgnn.sim import SimSettings, simulate as real
from garmentgnn.sim.blender import BlenderSettings, blender_available

from conftest import numbers

GARMENT = {"kind": "skirt", "params": {"length": "mini"}, "resolution": 200}
BODY = {"model": "capsule", "shape": "regular"}
MOTION = {"name": "arm_swing", "num_frames": 6, "speed": 1.0, "amplitude": 1.0}


def _spec(engine: str = "torch") -> Spec:
    spec = Spec("engines", [GARMENT], [BODY], [MOTION], ["silk"],
                settings={"fps": 30.0, "substeps": 4, "preroll_frames": 2},
                held_out={"test": {"motions": [motion_key(MOTION)]}}, engine=engine)
    if engine == "blender":
        spec.settings = dict(BLENDER_SETTINGS, preroll_frames=2)
    return spec


def _dataset(spec: Spec, out):
    s = generate(spec, out, workers=0, progress=False)
    assert s.done == 1 and s.failed == 0, str(s)
    (item,) = store.read_manifest(out)["items"]
    return out, item


@pytest.fixture(scope="module")
def torch_data(tmp_path_factory):
    """One test sequence (held-out motion) simulated by the torch engine."""
    return _dataset(_spec(), tmp_path_factory.mktemp("engines"))


@pytest.fixture(scope="module")
def own(torch_data):
    root, item = torch_data
    return engine_record(root, item, EngineSetting("torch", "own settings"))


# --------------------------------------------------------------------------- torch engine
def test_own_settings_reproduce_the_file(torch_data, own):
    root, item = torch_data
    assert own["status"] == "ok", own["message"]
    assert own["metrics"]["E_dist"] < 1e-6  # cm: the same scene, the same engine
    assert own["metrics"]["E_len"] < 1e-6
    assert {k: own[k] for k in ("kind", "method", "case", "sequence", "seed", "engine")} == {
        "kind": KIND, "method": "own settings", "case": item["id"], "sequence": item["id"],
        "seed": 0, "engine": "torch"}
    assert own["held_out"] == ["motion"]
    assert own["frames"] == 6 and own["simulated_frames"] == 6 + 2
    assert own["seconds"] > 0
    assert own["seconds_per_frame"] == pytest.approx(own["seconds"] / 8)
    assert own["settings"] == json.loads(json.dumps(own["settings"]))
    assert {k: own["settings"][k] for k in item["settings"]} == item["settings"]
    assert own["nonconverged_frames"] >= 0 and own["newton_iterations"] > 0
    assert "collision" not in own["metrics"] and 0 <= own["metrics"]["collision_rate"] <= 100
    json.dumps(own, allow_nan=False)  # JSON-able, every number finite
    assert all(x == x for x in numbers(own))


def test_first_frames_match_the_file(torch_data):
    root, item = torch_data
    rec = engine_record(root, item, EngineSetting("torch", "own"), frames=3)
    assert rec["status"] == "ok", rec["message"]
    assert rec["frames"] == 3 and rec["simulated_frames"] == 5
    assert rec["metrics"]["E_dist"] < 1e-6


def test_cheaper_budget_is_worse_but_finite(torch_data, own):
    root, item = torch_data
    rec = engine_record(root, item, EngineSetting("torch", "cheap", {"substeps": 1,
                                                                     "max_newton": 2}))
    assert rec["status"] == "ok", rec["message"]
    assert rec["settings"]["substeps"] == 1 and rec["settings"]["max_newton"] == 2
    assert rec["settings"]["preroll_frames"] == 2  # the rest from the dataset
    e = rec["metrics"]["E_dist"]
    assert 1e-3 < e < 100 and e > 1000 * own["metrics"]["E_dist"]


def test_another_material_is_not_the_file(torch_data):
    """The oracle can fail: the right garment and motion in another fabric."""
    root, item = torch_data
    rec = engine_record(root, dict(item, material="denim"), EngineSetting("torch", "own"))
    assert rec["status"] == "ok", rec["message"]
    assert rec["metrics"]["E_dist"] > 1e-2


def test_another_motion_seed_is_caught(torch_data):
    root, item = torch_data
    rec = engine_record(root, dict(item, seed=item["seed"] + 1), EngineSetting("torch", "own"))
    assert rec["status"] == "failed"
    assert "motion rotations differs from the sequence file" in rec["message"]


def test_failing_engine_gives_a_failed_record(torch_data, monkeypatch):
    root, item = torch_data

    def broken(engine):
        def simulate(*args, **kwargs):
            raise RuntimeError("solver exploded")
        return simulate

    monkeypatch.setattr(engines, "default_simulate", broken)
    rec = engine_record(root, item, EngineSetting("torch", "broken"))
    assert rec["status"] == "failed" and "solver exploded" in rec["message"]
    assert rec["kind"] == KIND and rec["case"] == item["id"] and "metrics" not in rec
    json.dumps(rec, allow_nan=False)


def test_nan_positions_give_a_failed_record(torch_data, monkeypatch):
    root, item = torch_data

    def nan_engine(engine):
        def simulate(*args, **kwargs):
            res = real(*args, **kwargs)
            res.positions[-1, 0, 0] = float("nan")
            return res
        return simulate

    monkeypatch.setattr(engines, "default_simulate", nan_engine)
    rec = engine_record(root, item, EngineSetting("torch", "nan"), frames=2)
    assert rec["status"] == "failed" and "non-finite" in rec["message"]


def test_missing_file_gives_a_failed_record(torch_data, tmp_path):
    _, item = torch_data
    rec = engine_record(tmp_path, item, EngineSetting("torch", "own"), frames=2)
    assert rec["status"] == "failed" and "missing" in rec["message"]


# --------------------------------------------------------------------------- arguments
@pytest.mark.parametrize("frames", [0, 7, 2.0, True, "3"])
def test_bad_frames(torch_data, frames):
    root, item = torch_data
    with pytest.raises(ValueError, match="`frames`"):
        engine_record(root, item, EngineSetting("torch", "own"), frames=frames)


def test_bad_arguments(torch_data):
    root, item = torch_data
    s = EngineSetting("torch", "own")
    with pytest.raises(ValueError, match="`setting`"):
        engine_record(root, item, {"engine": "torch"})
    with pytest.raises(ValueError, match="`item`"):
        engine_record(root, {"id": "x"}, s)
    with pytest.raises(ValueError, match="`item`"):
        engine_record(root, dict(item, status="failed"), s)
    with pytest.raises(ValueError, match="`root`"):
        engine_record(None, item, s)
    with pytest.raises(ValueError, match="settings.substeps"):
        engine_record(root, item, EngineSetting("torch", "bad", {"substeps": 0}))
    with pytest.raises(ValueError, match="`engine`"):
        EngineSetting("mujoco", "x")
    with pytest.raises(ValueError, match="`name`"):
        EngineSetting("torch", "")
    with pytest.raises(ValueError, match="`settings`.*quality"):
        EngineSetting("torch", "x", {"quality": 2})  # a Blender setting
    with pytest.raises(ValueError, match="`settings`"):
        EngineSetting("blender", "x", [("quality", 2)])


# --------------------------------------------------------------------------- the ladder
def _record(i, split="test", held_out=("motion",), status="ok"):
    return {"id": f"item-{i:03d}", "split": split, "held_out": list(held_out), "status": status}


def test_pick_sequences_one_per_group_deterministic():
    recs = ([_record(i, held_out=("motion",)) for i in range(5)]
            + [_record(10 + i, held_out=("body",)) for i in range(4)]
            + [_record(20 + i, held_out=("garment",)) for i in range(3)]
            + [_record(30, held_out=("garment", "motion")), _record(31, split="val"),
               _record(32, status="failed", held_out=("body",)),
               _record(33, split="train", held_out=())])
    picks = pick_sequences(recs)
    assert [p["held_out"] for p in picks] == [["motion"], ["body"], ["garment"]]
    shuffled = list(recs)
    random.Random(3).shuffle(shuffled)
    assert pick_sequences(shuffled) == picks  # independent of the manifest's order
    two = pick_sequences(recs, per_group=2)
    assert [p["id"] for p in two] == ["item-001", "item-003", "item-011", "item-013",
                                      "item-020", "item-022"]
    many = pick_sequences(recs, per_group=10)  # a group gives what it has
    assert len(many) == 5 + 4 + 3
    assert pick_sequences([_record(1, split="val")]) == []
    with pytest.raises(ValueError, match="`per_group`"):
        pick_sequences(recs, per_group=0)
    with pytest.raises(ValueError, match="`records`"):
        pick_sequences({"items": recs})
    with pytest.raises(ValueError, match="`records`"):
        pick_sequences([1, 2])


def test_default_settings_are_cheaper_than_the_dataset():
    ladder = default_settings()
    assert len({s.name for s in ladder}) == len(ladder)
    blender = [s for s in ladder if s.engine == "blender"]
    sim = [s for s in ladder if s.engine == "torch"]
    assert 2 <= len(blender) <= 3 and 2 <= len(sim) <= 3
    medium = {"engine": {"name": "blender"}, "settings": dict(BLENDER_SETTINGS)}
    for s in blender:
        st = resolve_settings(medium, s)
        assert isinstance(st, BlenderSettings)
        assert st.quality < BLENDER_SETTINGS["quality"]
        assert st.collision_quality <= BLENDER_SETTINGS["collision_quality"]
        assert (st.fps, st.preroll_frames) == (30.0, BLENDER_SETTINGS["preroll_frames"])
    for s in sim:  # the torch simulator on a Blender dataset: its fps and pre-roll
        st = resolve_settings(medium, s)
        assert isinstance(st, SimSettings)
        assert (st.fps, st.preroll_frames) == (30.0, BLENDER_SETTINGS["preroll_frames"])
    costs = [resolve_settings(medium, s).substeps * resolve_settings(medium, s).max_newton
             for s in sim]
    assert costs == sorted(costs) and len(set(costs)) == len(costs)


# --------------------------------------------------------------------------- Blender
needs_blender = pytest.mark.skipif(not blender_available(),
                                   reason="bpy not installed (make install)")


@needs_blender
@pytest.mark.slow
def test_blender_own_settings_reproduce_the_file(tmp_path):
    root, item = _dataset(_spec("blender"), tmp_path)
    own = engine_record(root, item, EngineSetting("blender", "Blender own"))
    assert own["status"] == "ok", own["message"]
    assert own["metrics"]["E_dist"] == 0.0  # Blender's cloth is deterministic
    cheap = engine_record(root, item, EngineSetting("blender", "Blender q=1",
                                                    {"quality": 1, "collision_quality": 1}))
    assert cheap["status"] == "ok", cheap["message"]
    assert cheap["settings"]["quality"] == 1
    assert 1e-3 < cheap["metrics"]["E_dist"] < 100
    other = engine_record(root, dict(item, material="denim"), EngineSetting("blender", "own"))
    assert other["metrics"]["E_dist"] > 1e-2
    sim = engine_record(root, item, EngineSetting("torch", "torch sim", {"substeps": 1}),
                        frames=2)
    assert sim["status"] == "ok", sim["message"]
    assert sim["settings"]["preroll_frames"] == 2 and sim["settings"]["substeps"] == 1
    assert torch.isfinite(torch.tensor(sim["metrics"]["E_dist"]))
