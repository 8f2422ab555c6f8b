"""``garmentgnn sweep``: a search over a recipe's settings on Ray Tune (one ``ray start
--head`` of 2 CPUs for the module), each trial trained and scored as a bench run.

Oracles: the grid itself (every combination once), the recipe loader read back on each
trial's written recipe (its values are the trial's), and the local bench trained on a
trial's recipe file with the same seed (deterministic on the CPU: the same scores).  The
dataset is the tiny preset's, its simulation a test double (seconds)."""
import dataclasses
import itertools
import json
import sys
from pathlib import Path

import pytest
import yaml

from garmentgnn.bench import presets, runner
from garmentgnn.bench.sweep import check_space, parse_space, trial_recipe
from garmentgnn.cli import main as cli_main
from garmentgnn.training import load_recipe

from conftest import ray_head, tiny_stand_in

RECIPE = "baselines/da"
GRID = {"model.init_args.lr": [1e-3, 3e-3], "model.init_args.model.init_args.hidden": [16, 32]}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return tiny_stand_in(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def address():
    pytest.importorskip("ray.tune", reason="Ray Tune is in the ray extra (make install)")
    yield from ray_head(cpus=2)


def _grid_flags():
    return [a for k, vs in GRID.items() for a in ("--grid", f"{k}={','.join(map(str, vs))}")]


@pytest.mark.slow  # 4 trials on 2 CPUs and one bench run: about 1.5 min
def test_four_trial_grid_writes_every_recipe_beside_its_score(data, address, tmp_path, capsys):
    out = tmp_path / "sweep"
    assert cli_main(["sweep", "--recipe", RECIPE, "--data", str(data), "--out", str(out),
                     "--address", address, *_grid_flags()]) == 0
    assert "sweep: 4 trials; best test E_dist" in capsys.readouterr().out
    res = json.loads((out / "sweep.json").read_text())
    trials = res["trials"]
    combos = sorted(itertools.product(*GRID.values()))
    assert sorted(tuple(t["params"][k] for k in GRID) for t in trials) == combos
    assert [t["E_dist"] for t in trials] == sorted(t["E_dist"] for t in trials)  # best first
    table = (out / "sweep.md").read_text()
    for t in trials:
        folder = Path(t["recipe"]).parent
        assert folder.parent == out / "trials"
        score = json.loads((folder / "score.json").read_text())
        assert score["status"] == "ok" and score["E_dist"] == score["metrics"]["E_dist"] > 0
        assert score["test_frames"] == sum(s["frames"] for s in score["per_sequence"])
        # the written recipe is the trial's: read back by the recipe loader
        config = load_recipe(folder / "recipe.yaml").config
        for key, value in t["params"].items():
            node = config
            for part in key.split("."):
                node = node[part]
            assert node == value
        assert config["data"]["root"] == str(data) and config["seed_everything"] == 0
        assert f"[{folder.name}](trials/{folder.name}/recipe.yaml)" in table
    # the bench trained on the best trial's recipe file gives the same scores
    best = Path(trials[0]["recipe"])
    p = presets.preset("tiny").learned_only()
    p = dataclasses.replace(p, learned=dataclasses.replace(
        p.learned, methods=(str(best),), stability_cases=()))
    runner.run(p, tmp_path / "bench", seeds=1, data=data, progress=False)
    rec = json.loads(next((tmp_path / "bench" / "records").glob("learned--*")).read_text())
    assert rec["metrics"] == trials[0]["metrics"]
    assert rec["per_sequence"] == trials[0]["per_sequence"]


def test_parse_space_reads_values_and_refuses_bad_ones():
    space = parse_space({"grid": ["a.b=1e-3,3", "c=true,x"], "loguniform": ["d=1e-4,1e-1"]})
    assert space == {"a.b": ("grid", [0.001, 3]), "c": ("grid", [True, "x"]),
                     "d": ("loguniform", [1e-4, 1e-1])}
    assert isinstance(space["a.b"][1][0], float)
    for specs, text in (({}, "search space is empty"), ({"grid": []}, "search space is empty"),
                        ({"grid": ["a="]}, "KEY=V1,V2"), ({"grid": ["=1,2"]}, "KEY=V1,V2"),
                        ({"uniform": ["a=2,1"]}, "LO < HI"),
                        ({"loguniform": ["a=0,1"]}, "0 < LO"),
                        ({"randint": ["a=1,x"]}, "numbers"),
                        ({"grid": ["a=1"], "choice": ["a=2,3"]}, "swept twice")):
        with pytest.raises(ValueError, match=text):
            parse_space(specs)


def test_trial_recipe_is_the_recipe_with_the_values(data, tmp_path):
    budget = presets.preset("tiny").learned
    params = {"model.init_args.lr": 0.004, "model.init_args.model.init_args.heads": 4}
    path = tmp_path / "trial.yaml"
    path.write_text(trial_recipe(RECIPE, params, data, 3, budget))
    config = load_recipe(path).config
    assert config["model"]["init_args"]["lr"] == 0.004
    assert config["model"]["init_args"]["model"]["init_args"]["heads"] == 4
    assert config["model"]["init_args"]["model"]["init_args"]["hidden"] == 64  # the recipe's
    assert config["seed_everything"] == 3 and config["data"]["val_split"] is None
    assert config["trainer"]["max_epochs"] == budget.epochs
    doc = yaml.safe_load(path.read_text())
    assert doc["model"]["init_args"]["loss"] == {"enabled": ["vert", "edge", "norm"]}
    check_space(RECIPE, parse_space({"grid": ["model.init_args.lr=1,2"]}), data)


# --------------------------------------------------------------------------- bad input
def _one_error(capsys, argv, *expected):
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    for text in expected:
        assert text in err[0]


def test_bad_sweeps_are_one_error_line_and_write_nothing(data, tmp_path, capsys):
    pytest.importorskip("ray.tune")
    out = tmp_path / "out"
    base = ["sweep", "--recipe", RECIPE, "--data", str(data), "--out", str(out)]
    _one_error(capsys, base + ["--grid", "model.init_args.lrr=1e-3,3e-3"],
               "--grid model.init_args.lrr: the recipe baselines/da has no such setting",
               "did you mean model.init_args.lr")
    _one_error(capsys, base, "the search space is empty")
    _one_error(capsys, base + ["--grid", "model.init_args.lr="], "expected KEY=V1,V2")
    _one_error(capsys, base + ["--grid", "model.init_args.lr=1e-3", "--address",
                               "127.0.0.1:1"], "--address 127.0.0.1:1: no Ray cluster")
    _one_error(capsys, ["sweep", "--recipe", "no/such", "--data", str(data), "--out",
                        str(out), "--grid", "model.init_args.lr=1e-3"], "no/such")
    _one_error(capsys, ["sweep", "--recipe", RECIPE, "--data", str(tmp_path / "none"),
                        "--out", str(out), "--grid", "model.init_args.lr=1e-3"],
               "is not a generated dataset")
    assert not out.exists()


def test_sweep_without_ray_installed(data, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "out"
    _one_error(capsys, ["sweep", "--recipe", RECIPE, "--data", str(data), "--out", str(out),
                        "--grid", "model.init_args.lr=1e-3"], "sweep needs Ray",
               "pip install 'garmentgnn[ray]'")
    assert not out.exists()
