"""``benchmarks/size_study.py``'s parts: the sizes it trains (read from the recipes and
the models' signatures, worked out by hand here) and its Pareto front.  The study itself
runs for hours; its smoke run on ``tiny`` is in docs/bench.md ("Size study")."""
import sys
from pathlib import Path

import pytest
import yaml

from garmentgnn.bench import methods, presets
from garmentgnn.training import load_recipe

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import size_study  # noqa: E402

from conftest import tiny_stand_in  # noqa: E402


def test_sizes_are_the_defaults_times_the_factor():
    # DA-style: the recipe's hidden 64 and num_layers 3; MGN-style: the model's own
    # defaults, hidden 64 and layers 8 (its recipe sets neither); GarTrans: its factors
    m = size_study.MODEL
    assert size_study.size_settings(methods.DA, 0.5) == {f"{m}.hidden": 32,
                                                         f"{m}.num_layers": 2}
    assert size_study.size_settings(methods.DA, 2.0) == {f"{m}.hidden": 128,
                                                         f"{m}.num_layers": 6}
    assert size_study.size_settings(methods.MGN, 0.5) == {f"{m}.hidden": 32, f"{m}.layers": 4}
    assert size_study.size_settings(methods.MGN, 1.0) == {f"{m}.hidden": 64, f"{m}.layers": 8}
    assert size_study.size_settings(methods.FULL, 2.0) == {f"{m}.width": 2.0,
                                                           f"{m}.depth": 2.0}


def test_written_recipes_load_with_their_sizes(tmp_path):
    data = tiny_stand_in(tmp_path / "data")
    runs = size_study.write_recipes(tmp_path / "out", data, presets.preset("tiny").learned)
    assert len(runs) == len(size_study.STUDIED) * len(size_study.SIZES)
    for path, run in runs.items():
        if run["method"] == methods.DA and run["size"] == "2x":
            model = load_recipe(path).config["model"]["init_args"]["model"]["init_args"]
            assert (model["hidden"], model["num_layers"], model["heads"]) == (128, 6, 2)
        doc = yaml.safe_load(Path(path).read_text())
        assert doc["data"]["root"] == str(data)
    assert size_study.parameters(next(iter(runs)), data) > 0


def test_pareto_front_by_hand():
    pts = [(1, 5.0), (2, 4.0), (3, 4.5), (4, 1.0), (0.5, 6.0)]
    assert size_study.front(pts) == [(0.5, 6.0), (1, 5.0), (2, 4.0), (4, 1.0)]
    assert size_study.front([]) == []


def test_study_preset_trains_the_runs_only():
    p = size_study.study_preset("learn", 20.0, [methods.DA], epochs=None)
    assert p.learned.methods == (methods.DA,) and p.learned.minutes == 20.0
    assert p.learned.seeds == 1 and p.learned.curve_every is None
    assert p.learned.epochs == presets.preset("learn").learned.epochs
    assert not p.cases and not p.learned.stability_cases
    with pytest.raises(ValueError, match="minutes"):
        size_study.study_preset("learn", -1.0, [methods.DA])


def test_table_gives_each_size_against_lbs_on_the_same_sequences():
    res = {"command": "size_study.py", "minutes": 20.0, "threads": 1,
           "dataset": {"name": "learn", "sequences": {"test": 107}},
           "lbs": {"E_dist": 8.0, "inference_ms_per_frame": 0.5, "test_sequences": 40},
           "rows": [{"method": methods.DA, "size": "1x", "E_dist": 6.0, "parameters": 1000,
                     "train_vertex_frames_per_s": 2.0e5, "inference_ms_per_frame": 3.0,
                     "test_sequences": 40},
                    {"method": methods.DA, "size": "2x", "status": "failed"}]}
    lines = size_study.table(res).splitlines()
    assert "40 of its 107 test sequences" in lines[4]
    assert lines[8] == f"| {methods.LBS} | | 0 | | 0.5 | 8.0000 | 1 | |"
    assert lines[9] == f"| {methods.DA} | 1x | 1,000 | 2e+05 | 3 | 6.0000 | 0.750 | — |"
    assert lines[10] == f"| {methods.DA} | 2x | | | | failed | | |"
