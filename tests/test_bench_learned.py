"""The learned methods inside ``garmentgnn bench`` (bench.learned): every method trained
and scored on one generated dataset's split, records, report table, resume, failures.

The dataset is a very small generated one (a mini skirt on one body, 3 motions of 4
frames, arm_swing held out for test) whose "simulation" is a test double: the garment
skinned by LBS plus a small smooth wobble (as in tests/test_training.py), so it takes
seconds.  Oracles: :func:`garmentgnn.training.evaluate.evaluate_split` (an independent
scoring path) for LBS and for the trained GarTrans checkpoint; an uninterrupted training
for the resumed one; a copy of the dataset with altered test positions for NCS."""
import dataclasses
import gc
import importlib
import inspect
import json
import math
import multiprocessing
import shutil
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from lightning.pytorch.callbacks import ModelCheckpoint

from garmentgnn.bench import runner, learned, methods, presets, report, scoring, stability, tables
from garmentgnn.cli import main as cli_main
from garmentgnn.data import store
from garmentgnn.models import gartrans
from garmentgnn.models.baselines import DAStyle
from garmentgnn.training import (BaselineModule, GarTransModule)
from garmentgnn.training.evaluate import evaluate_split
from garmentgnn.training import load_recipe
from garmentgnn.training.lightning_cli import main as train_main
from garmentgnn.training.recipes import recipe_path
from garmentgnn.sim.stand_in import skinned_wobble

from conftest import ZERO_AREA_M2, numbers, skirt_dataset

ROOT = Path(__file__).resolve().parents[1]






@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("data"), ["walk", "run", "arm_swing"], 4,
                         held_out={"test": ["arm_swing"]}, name="mini")


def learned_only(**budget) -> presets.Preset:
    """The tiny preset with its simulator parts removed (only the learned tasks run; the
    learned stability suite only when ``stability_cases`` is given)."""
    p = presets.preset("tiny").learned_only()
    budget.setdefault("stability_cases", ())
    return dataclasses.replace(p, learned=dataclasses.replace(p.learned, **budget))


#: the flow's budget: every method, and the stability suite on one case
FLOW = {"stability_cases": ("zero_area_face",)}


def records_of(out):
    return json.loads((Path(out) / "results.json").read_text())["records"]


@pytest.fixture(scope="module")
def flow(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    summary = runner.run(learned_only(**FLOW), out, data=data, progress=False)
    return out, summary


def test_presets_budgets():
    tiny, small = presets.preset("tiny"), presets.preset("small")
    assert tiny.dataset == "tiny" and small.dataset == "small"
    assert tiny.learned.seeds == 1 and small.learned.seeds >= 3
    assert set(tiny.learned.methods) == set(small.learned.methods) == set(methods.METHOD_NAMES)
    assert set(methods.METHOD_NAMES) >= set(runner.PLANNED)


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_every_method_produces_a_finite_record(flow, data):
    out, summary = flow
    p = learned_only()
    assert summary.failed == 0 and summary.skipped == 0
    assert summary.ran == len(records_of(out))
    recs = [r for r in records_of(out) if r["kind"] == learned.KIND]
    assert len(recs) == len(methods.METHOD_NAMES)  # one seed in tiny
    assert {r["method"] for r in recs} == set(methods.METHOD_NAMES)
    for r in recs:
        assert r["kind"] == "learned" and r["status"] == "ok", (r["method"], r["message"])
        assert all(math.isfinite(x) for x in numbers(r)), r["method"]
        assert set(r["metrics"]) == set(report.METRICS) | set(scoring.SPLIT_METRICS)
        assert r["metrics"]["E_dist"] > 0
        assert r["test_frames"] == 4  # 1 test sequence x 4 frames
        t = r["timing"]
        assert t["latency_ms"] > 0 and t["throughput_fps"] > 0 and t["peak_mem_mb"] >= 0
        assert t["best_batch"] in p.batches and t["threads"] == p.threads
        assert r["dataset"]["root"] == str(data) and r["dataset"]["sequences"]["test"] == 1
        trained = r["method"] != methods.LBS
        assert (r["train_seconds"] > 0) == trained
        assert r["epochs"] == (1 if trained else 0) and r["resumed_from_epoch"] == 0
    by = {r["method"]: r for r in recs}
    for name in methods.GARTRANS:
        assert by[name]["phase"] == 1  # 1 epoch: the window (1) never elapses
        # the variant's recipe, its schedule's windows the bench's (recorded)
        config = by[name]["config"]
        assert config["recipe"] == methods.GARTRANS[name]
        sched = config["model"]["init_args"]["schedule"]
        assert sched["window"] == sched["window2"] == p.learned.window
        assert (out / "models" / f"{tables.slug(name)}--s0" / "last.ckpt").exists()
    unsup = by["GarTrans w/o unsupervised loss"]["config"]["model"]["init_args"]["schedule"]
    assert unsup["max_phase"] == 1
    assert by[methods.NCS]["models"] == 1  # one per test garment
    for m in (methods.DA, methods.HOOD, methods.NCS):  # the report animation's panels
        P = np.load(out / "media" / "predictions" / f"{tables.slug(m)}.npy")
        assert P.shape[0] == 4 and P.shape[2] == 3 and np.isfinite(P).all()
    assert len(list((out / "models" / "NCS-style--s0").glob("garment*/last.ckpt"))) == 1
    # the methods differ (they are not all LBS in disguise)
    assert len({round(r["metrics"]["E_dist"], 9) for r in recs}) > 3


@pytest.mark.slow
def test_records_equal_evaluate_split(flow, data):
    """LBS and a trained GarTrans scored by training.evaluate.evaluate_split (frame-batched,
    its own loop) from the saved checkpoint give the records' numbers: the record scores
    the final trained weights, and GarTrans moved away from LBS."""
    out, _ = flow
    recs = {r["method"]: r for r in records_of(out) if r["kind"] == learned.KIND}
    rec = recs["GarTrans w/o edge gating"]
    module = GarTransModule.load_from_checkpoint(rec["checkpoint"], map_location="cpu")
    assert module.model.init_args["dynamic_layer"] == "gt_edge"
    ref = evaluate_split(module, data, "test", modes=("gartrans", "lbs"), history=3,
                         nystrom_dim=16, num_landmarks=64)
    for mode, name in (("gartrans", rec["method"]), ("lbs", methods.LBS)):
        r = ref[mode]
        assert r["frames"] == recs[name]["test_frames"]
        r["collision_rate"] = r.pop("collision")
        for m in report.METRICS:
            # float32 round-off: the records score frame by frame, evaluate_split per sequence
            assert recs[name]["metrics"][m] == pytest.approx(r[m], rel=1e-4, abs=1e-8), (name, m)
    assert rec["metrics"]["E_dist"] != pytest.approx(recs[methods.LBS]["metrics"]["E_dist"],
                                                     rel=1e-7)


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_report_has_the_held_out_table(flow):
    out, _ = flow
    md = (out / "report.md").read_text()
    assert "## Held-out test split" in md and "![Pareto, learned](pareto_learned.png)" in md
    assert (out / "pareto_learned.png").stat().st_size > 0
    table = md.split("## Held-out test split")[1].split("\n## ")[0]
    for name in methods.METHOD_NAMES:
        assert f"\n| {name}" in table, name
        assert f"- {name}: not run" not in md
    res = json.loads((out / "results.json").read_text())
    assert not set(methods.METHOD_NAMES) & set(res["not_run"])
    assert res["meta"]["dataset"]["sequences"] == {"train": 2, "val": 0, "test": 1}
    assert res["meta"]["preset_config"]["learned"]["epochs"] == 1


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_second_run_is_a_no_op(flow, data):
    out, first = flow
    files = sorted((out / "records").glob("*.json")) + sorted((out / "models").rglob("*.*"))
    before = {p: p.stat().st_mtime_ns for p in files}
    again = runner.run(learned_only(**FLOW), out, data=data, progress=False)
    assert again.ran == 0 and again.skipped == first.ran
    assert {p: p.stat().st_mtime_ns for p in files} == before


def test_interrupted_gartrans_training_resumes_from_last_ckpt(data, tmp_path, monkeypatch):
    p = learned_only(methods=("GarTrans (SAT)",), epochs=2)
    straight = runner.run(p, tmp_path / "straight", data=data, progress=False)
    assert straight.failed == 0
    ref = records_of(tmp_path / "straight")[0]

    save = ModelCheckpoint.on_train_epoch_end

    def save_then_die(self, trainer, pl_module):  # killed right after epoch 0's checkpoint
        save(self, trainer, pl_module)
        if trainer.current_epoch == 0:
            raise SystemExit("killed")
    monkeypatch.setattr(ModelCheckpoint, "on_train_epoch_end", save_then_die)
    out = tmp_path / "cut"
    with pytest.raises(SystemExit):
        runner.run(p, out, data=data, progress=False)
    last = out / "models" / "GarTrans_SAT--s0" / "last.ckpt"
    assert torch.load(last, weights_only=False)["epoch"] == 0
    assert not list((out / "records").glob("*.json"))  # no record of a killed task
    monkeypatch.undo()
    summary = runner.run(p, out, data=data, progress=False)
    rec = records_of(out)[0]
    assert summary.ran == 1 and rec["status"] == "ok", rec["message"]
    assert rec["resumed_from_epoch"] == 1 and rec["epochs"] == 2 == ref["epochs"]
    assert torch.load(last, weights_only=False)["epoch"] == 1
    assert rec["metrics"] == ref["metrics"]  # the same model as the uninterrupted training


def test_nan_loss_gives_a_failed_record_then_retry(data, tmp_path, monkeypatch):
    p = learned_only(methods=("GarTrans (SAT)", methods.DA))
    inner, da = gartrans.GarTrans.forward, DAStyle.forward

    def nan_gartrans(self, *a, **k):
        out = dict(inner(self, *a, **k))
        out["final"] = out["final"] * float("nan")
        return out

    monkeypatch.setattr(gartrans.GarTrans, "forward", nan_gartrans)
    monkeypatch.setattr(DAStyle, "forward", lambda self, *a, **k: da(self, *a, **k) * float("nan"))
    out = tmp_path / "nan"
    summary = runner.run(p, out, data=data, progress=False)
    assert summary.failed == 2
    for r in records_of(out):
        assert r["status"] == "failed" and "NonFiniteLossError" in r["message"], r["message"]
        assert "'vert'" in r["message"] and "metrics" not in r
    md = (out / "report.md").read_text()
    assert "## Failures" in md and "| GarTrans (SAT) (1/1 failed) | failed" in md
    monkeypatch.undo()
    assert runner.run(p, out, data=data, progress=False).ran == 0  # failed records are kept
    summary = runner.run(p, out, data=data, progress=False, retry_failed=True)
    assert summary.ran == 2 and summary.failed == 0


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_ncs_never_reads_test_positions(flow, data, tmp_path):
    """NCS trains on the test garments' poses only: moving the simulated test positions
    changes its score but not one of its weights."""
    out, _ = flow
    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    man = store.read_manifest(moved)
    for r in man["items"]:
        if r["split"] == "test":
            path = store.sequence_path(moved, r)
            seq = store.load_sequence(path)
            arrays = {k: seq[k] for k in store.SEQUENCE_KEYS}
            arrays["positions"] = arrays["positions"] + np.float32(0.05)
            store.write_sequence(path, arrays, seq["meta"])
    store.rebuild_manifest(moved)  # edited on purpose: record the new files' hashes
    summary = runner.run(learned_only(methods=(methods.NCS,)), tmp_path / "b", data=moved,
                          progress=False)
    assert summary.failed == 0
    for g in (0,):
        a, b = (torch.load(o / "models" / "NCS-style--s0" / f"garment{g}" / "last.ckpt",
                           weights_only=False)["state_dict"] for o in (out, tmp_path / "b"))
        assert all(torch.equal(a[k], b[k]) for k in a)
    e0 = next(r for r in records_of(out) if r["method"] == methods.NCS
              and r["kind"] == learned.KIND)["metrics"]["E_dist"]
    assert records_of(tmp_path / "b")[0]["metrics"]["E_dist"] != pytest.approx(e0)


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_learned_stability_records(flow, data):
    """Every method's first-seed model and the simulator on the stability case, built on
    the dataset's test sequence: a scored, finite record each, and a table in the report."""
    out, _ = flow
    recs = [r for r in records_of(out) if r["kind"] == learned.STABILITY_KIND]
    test_id = store.read_manifest(data)["items"][2]["id"]
    assert sorted(r["method"] for r in recs) == sorted(methods.METHOD_NAMES + (learned.SIMULATOR,))
    for r in recs:
        assert r["status"] == "ok" and r["case"] == "zero_area_face", (r["method"], r["message"])
        assert r["verdict"] in ("stable", "degraded", "failed") and r["seed"] == 0
        assert r["sequence"] == test_id and 0.0 <= r["info"]["uv_area_m2"] < ZERO_AREA_M2
        assert r["metrics"]["frames"] == 4 and r["metrics"]["nonfinite"] == 0
        assert all(math.isfinite(x) for x in numbers(r["metrics"])), r["method"]
    md = (out / "report.md").read_text()
    table = md.split("### Every method on a test sequence of the dataset")[1].split("\n## ")[0]
    for name in methods.METHOD_NAMES + (learned.SIMULATOR,):
        assert f"\n| {name} | zero_area_face | 0 |" in table, name


@pytest.mark.slow  # the module's end-to-end run (~20 s) comes first
def test_stability_baseline_case_is_the_test_prediction(flow, data, monkeypatch):
    """The unmodified case, rebuilt from the test record's description and presented by
    BenchChunks, gets exactly the prediction of the test set's own item (SequenceChunks
    over the generated file): the suite tests the trained models on their own inputs.
    The frame-parallel methods are called on chunks of 3 frames here, the whole-sequence
    prediction being the oracle."""
    monkeypatch.setattr(learned, "STABILITY_CHUNK", 3)
    out, _ = flow
    runner = learned.LearnedRunner(learned.prepare_dataset(data), learned_only().learned, out,
                                   (1,), 0, 1)
    base = runner.test.records[0]
    seq, _ = stability.stability_sequence("baseline", dict(base, name="baseline"), base["seed"])
    item = runner.test[0]
    before = None
    for method in ("GarTrans (SAT)", methods.HOOD, methods.NCS, methods.DA, methods.LBS):
        pred, info = runner.trained(method, 0)
        # one trained method at a time: the one before is freed with its data caches
        gc.collect()
        assert before is None or before() is None, method
        before = None if pred.module is None else weakref.ref(pred.module)
        if method != methods.LBS:  # the flow's model, not retrained
            assert info["resumed_from_epoch"] == info["epochs"] == 1, (method, info)
        with torch.no_grad():
            ref = stability.stability_metrics(seq, pred.predict(runner.test, 0, item))
        rec = runner.stability_record(method, 0, "baseline")
        assert rec["status"] == "ok", rec["message"]
        for k, v in ref.items():
            assert rec["metrics"][k] == pytest.approx(v, rel=1e-5, abs=1e-9), (method, k)
    with pytest.raises(ValueError, match="method"):
        runner.stability_record("nope", 0, "baseline")


def test_default_dataset_is_generated_under_out(tmp_path, monkeypatch):
    worker = importlib.import_module("garmentgnn.data.worker")
    monkeypatch.setattr(worker, "default_simulate", lambda engine="torch": skinned_wobble)
    p = dataclasses.replace(learned_only(methods=(methods.LBS,)), data_workers=0)
    summary = runner.run(p, tmp_path, progress=False)
    assert summary.failed == 0
    man = store.read_manifest(tmp_path / "data")
    assert man["name"] == "tiny" and man["counts"] == {"ok": 8}
    rec = records_of(tmp_path)[0]
    assert rec["dataset"]["root"] == str(tmp_path / "data")
    assert rec["case"].startswith("tiny-") and rec["test_frames"] == 32


@pytest.mark.parametrize("name", [m for m in methods.RECIPES if m != methods.NCS])
def test_bench_trains_what_garmentgnn_train_builds(name, data, tmp_path):
    """The module, data module and schedule the bench loads for each method are the ones
    ``garmentgnn train --config <its recipe>`` builds, the bench's settings (no
    validation split, its seed) given to both; the oracle is the command's own parser."""
    runner = learned.LearnedRunner(learned.prepare_dataset(data), methods.LearnedBudget(),
                                   tmp_path, (1,), 0, 1)
    # MGN-style's windows of 5 frames do not fit the 4-frame sequences (the bench fits them)
    extra = ["--data.chunk", "3", "--data.batch_size", "1"] if name == methods.MGN else []
    recipe, config = runner.load(name, 3, extra)
    cli = train_main(["--config", methods.RECIPES[name], *extra, "--data.root", str(data),
                      "--data.val_split", "null", "--data.seed", "3", "--data.num_workers",
                      "0", "--seed_everything", "3", "--trainer.logger", "false",
                      "--trainer.default_root_dir", str(tmp_path)], run=False)
    assert config["recipe"] == methods.RECIPES[name]
    assert dict(recipe.module.hparams) == dict(cli.model.hparams)
    assert recipe.module.model.init_args == cli.model.model.init_args
    assert dict(recipe.datamodule.hparams) == dict(cli.datamodule.hparams)
    torch.testing.assert_close(dict(recipe.module.state_dict()),  # seeded alike
                               dict(cli.model.state_dict()))
    schedules = [[vars(cb) for cb in m.configure_callbacks()] for m in (recipe.module, cli.model)]
    assert schedules[0] == schedules[1]


def test_baseline_recipes_build_their_modules(data):
    for name, recipe in methods.BASELINES.items():
        args = ["--data.root", str(data)] + (
            ["--data.train_split", "test"] if name == methods.NCS else [])  # one garment
        module = load_recipe(recipe, args=args).module
        cfg = yaml.safe_load(recipe_path(recipe).read_text())["model"]["init_args"]
        lr = cfg.get("lr", inspect.signature(BaselineModule).parameters["lr"].default)
        assert isinstance(module, BaselineModule) and module.hparams.lr == lr
        assert module.method == recipe.split("/")[1]
        assert set(module.loss_fn.enabled) == set(cfg["loss"]["enabled"])


def test_bad_arguments(data, tmp_path):
    with pytest.raises(ValueError, match="epochs"):
        methods.LearnedBudget(epochs=0)
    with pytest.raises(ValueError, match="methods"):
        methods.LearnedBudget(methods=("nope",))
    with pytest.raises(ValueError, match="stability_cases"):
        methods.LearnedBudget(stability_cases=("nope",))
    with pytest.raises(ValueError, match="data"):
        learned.prepare_dataset(tmp_path / "empty")
    with pytest.raises(ValueError, match="data"):
        runner.run(learned_only(), tmp_path / "x", data=data, learned=False)
    info = learned.prepare_dataset(data)
    with pytest.raises(ValueError, match="method"):
        learned.LearnedRunner(info, methods.LearnedBudget(), tmp_path, (1,), 0, 1).record("x", 0)
    assert cli_main(["bench", "--out", str(tmp_path / "y"), "--data", str(data),
                     "--no-learned"]) == 2
    assert cli_main(["bench", "--out", str(tmp_path / "y"), "--no-progress",
                     "--data", str(tmp_path / "empty")]) == 2  # not a dataset
    # a checkpoint folder of another configuration is refused, not resumed
    p = learned_only(methods=(methods.DA,))
    runner.run(p, tmp_path / "z", data=data, progress=False)
    (tmp_path / "z" / "records").joinpath(
        next(f.name for f in (tmp_path / "z" / "records").glob("*.json"))).unlink()
    p2 = learned_only(methods=(methods.DA,), epochs=2)
    summary = runner.run(p2, tmp_path / "z", data=data, progress=False)
    rec = records_of(tmp_path / "z")[0]
    assert summary.failed == 1 and "another dataset or configuration" in rec["message"]


def test_batched_runs_take_fewer_steps_at_the_scaled_learning_rate(data, tmp_path):
    """``batch_size``: the two training chunks are one optimizer step per epoch (two with
    one chunk a step); ``lr_factor`` multiplies the configured learning rate; both are
    in the run's configuration, so a folder trained otherwise is not resumed; the
    learning curve counts chunks."""
    full = next(iter(methods.GARTRANS))
    steps = {}
    for b in (1, 2):
        out = tmp_path / f"b{b}"
        p = learned_only(methods=(full, methods.DA), epochs=2, batch_size=b, lr_factor=2.0)
        assert runner.run(p, out, data=data, progress=False).failed == 0
        for r in records_of(out):
            steps[r["method"], b] = r["steps"]
            run = json.loads((out / "models" / f"{tables.slug(r['method'])}--s0"
                              / "run.json").read_text())
            assert run["config"]["data"]["batch_size"] == b and run["config"]["lr_factor"] == 2.0
            ckpt = torch.load(r["checkpoint"], map_location="cpu", weights_only=False)
            recipe = load_recipe(methods.RECIPES[r["method"]], args=["--data.root", str(data)])
            lr = recipe.module.hparams.lr  # the recipe's (or its module's default)
            assert ckpt["hyper_parameters"]["lr"] == pytest.approx(2 * lr)
    assert steps == {(full, 1): 4, (methods.DA, 1): 4, (full, 2): 2, (methods.DA, 2): 2}


def test_epoch_chunks_count_chunks_and_curves_read_a_subset(data, tmp_path):
    """``epoch_chunks`` is in chunks whatever the batch size (Lightning's limit is in
    batches, rounded up); ``val_sequences`` draws like ``scoring.stratified``."""
    info = learned.prepare_dataset(data)
    r = learned.LearnedRunner(info, methods.LearnedBudget(epoch_chunks=5, batch_size=2),
                              tmp_path, (1,), 0, 1)
    full = r.load(methods.FULL, 0, ["--data.batch_size", "2"])[0]
    ncs = r.load(methods.NCS, 0, set={"data.train_split": "test"})[0]
    assert r._epoch_batches(full.datamodule) == 3
    assert r._epoch_batches(ncs.datamodule) == 5  # NCS-style: one chunk a step
    whole = r._whole("train", None)
    one = r._whole("train", 1)
    assert len(whole) == 2 and [it.seq_id for it in one] == \
        scoring.stratified(whole.records, 1)
    with pytest.raises(ValueError, match="batch_size"):
        methods.LearnedBudget(batch_size=0)
    with pytest.raises(ValueError, match="--batch-size: 3 is more than the 2 training chunks"):
        learned.LearnedRunner(info, methods.LearnedBudget(batch_size=3), tmp_path, (1,), 0, 1)
    assert cli_main(["bench", "--out", str(tmp_path / "b"), "--data", str(data),
                     "--batch-size", "3", "--no-progress"]) == 2
    with pytest.raises(ValueError, match="lr_factor"):
        methods.LearnedBudget(lr_factor=0.0)
    with pytest.raises(ValueError, match="val_sequences"):
        methods.LearnedBudget(val_sequences=0)


@pytest.mark.slow
def test_time_budget_seed_plan_and_long_run(data, tmp_path):
    """A wall-clock budget per run, every seed for the full model and for the best
    ablation and baseline of seed 0 only, and the long run; records carry the held-out
    groups, the per-sequence results and the budget actually used."""
    full = next(iter(methods.GARTRANS))
    p = learned_only(seeds=2, epochs=3, minutes=0.002, epoch_chunks=1, seed_methods=(full,),
                     long_minutes=0.003)
    summary = runner.run(p, tmp_path, data=data, progress=False)
    recs = [r for r in records_of(tmp_path) if r["kind"] == learned.KIND]
    assert summary.failed == 0 and all(r["status"] == "ok" for r in recs)
    seeds = {}
    for r in recs:
        seeds.setdefault(r["method"], set()).add(r["seed"])
    seed0 = {r["method"]: r["metrics"]["E_dist"] for r in recs if r["seed"] == 0}
    plan = methods.seed_plan(dataclasses.replace(p.learned), seed0)
    assert {m: len(s) for m, s in seeds.items() if m != methods.LONG} == plan
    assert sum(n == 2 for n in plan.values()) == 3 and seeds[methods.LONG] == {0}
    for r in recs:
        if r["method"] != methods.LBS:
            want = 60 * (0.003 if r["method"] == methods.LONG else 0.002)
            assert r["budget_seconds"] == pytest.approx(want)  # NCS-style: all its models
            assert 1 <= r["epochs"] <= 3
        assert set(r["groups"]) == {"unseen motion"}
        assert [s["held_out"] for s in r["per_sequence"]] == [["motion"]]
        assert r["groups"]["unseen motion"]["E_dist"] == pytest.approx(r["metrics"]["E_dist"])
    run = json.loads((tmp_path / "models" / f"{tables.slug(full)}--s0" / "run.json").read_text())
    assert run["config"]["minutes"] == 0.002 and run["config"]["epoch_chunks"] == 1
    text = (tmp_path / "report.md").read_text()
    assert "### By held-out group" in text and "### Targets" in text
    assert "### Static drape and dynamics" in text
    # a second run redoes nothing
    again = runner.run(p, tmp_path, data=data, progress=False)
    assert again.ran == 0


def _shard(p: presets.Preset, out: Path, data: Path, shard) -> runner.RunSummary:
    return runner.run(p, out, data=data, progress=False, shard=shard, poll_seconds=0.1)


@pytest.mark.slow
def test_two_shards_share_one_bench(data, tmp_path):
    """Two processes on one ``OUT`` (``shard=(i, 2)``), started together: every task of
    the seed plan runs exactly once, the second seeds start only once every first seed is
    in (the plan needs them all), and the report holds every record."""
    full = next(iter(methods.GARTRANS))
    p = learned_only(seeds=2, epochs=2, minutes=0.002, epoch_chunks=1, seed_methods=(full,))
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        sums = pool.starmap(_shard, [(p, tmp_path, data, (i, 2)) for i in range(2)])
    recs = records_of(tmp_path)
    assert all(r["status"] == "ok" for r in recs)
    assert sum(s.ran for s in sums) == len(recs) == len(list((tmp_path / "records").iterdir()))
    assert any("report" in s.paths for s in sums)
    seed0 = {r["method"]: r["metrics"]["E_dist"] for r in recs if r["seed"] == 0}
    plan = methods.seed_plan(dataclasses.replace(p.learned), seed0)
    assert sorted((r["method"], r["seed"]) for r in recs) == \
        sorted((m, s) for m, k in plan.items() for s in range(k))
    meta = json.loads((tmp_path / "results.json").read_text())["meta"]
    assert meta["shards"] == 2 and meta["threads"] == max(1, p.threads // 2)
    # an unsharded rerun finds everything done
    assert runner.run(p, tmp_path, data=data, progress=False).ran == 0
