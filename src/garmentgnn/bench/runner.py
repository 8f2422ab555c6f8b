"""The benchmark runner behind ``garmentgnn bench``: presets, an open method registry,
resumable per-record output, and the report at the end.

Layout of ``OUT``::

    OUT/records/<kind>--<case>--<method>--s<seed>.json   one result each (atomic write)
    OUT/cache/gt--<case>--s<seed>.pt                      reference simulation (atomic)
    OUT/results.json, OUT/report.md, OUT/pareto.png       written at the end
    OUT/scaling.png                                       when scaling records exist
    OUT/data/                       the learned methods' generated dataset (unless --data)
    OUT/models/<method>--s<seed>/   their checkpoints (resumed from), run.json
    OUT/pareto_learned.png          when learned records exist

A rerun skips every task whose record file exists and is valid (failed records
included, unless ``retry_failed``); temporaries of a killed run are deleted first.

**Accuracy tasks** (method x case x seed): the method predicts the case's sequence;
errors (:func:`garmentgnn.metrics.evaluate`) are against the reference simulator at the
preset's finest budget, over frames ``1..T-1`` (frame 0 is the skinned initial state
shared by every method).  **Stability tasks** (case x seed) run the reference
simulator on :mod:`garmentgnn.bench.stability`'s cases.  **Extra reports** (first
seed only): :mod:`~garmentgnn.bench.scaling` (one record per garment size),
:mod:`~garmentgnn.bench.leaveout`, :mod:`~garmentgnn.bench.precision` (per method, and
the long autoregressive sequence).  **Learned tasks** (method x training seed,
:mod:`garmentgnn.bench.learned`): GarTrans, its Table 1 variants and the DA / HOOD /
NCS-style baselines trained on a generated dataset's train split and scored on its
test split, with LBS as the reference row.

Methods are looked up by name in :data:`METHODS`; :func:`register` adds one (e.g. a
trained GarTrans variant or learned baseline).  Names in :data:`PLANNED` that produce
no record are listed as "not run" in the report -- no number is ever made up for them.
"""
from __future__ import annotations

import io
import os
import platform
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor
from tqdm.auto import tqdm

from garmentgnn.bench import engines, leaveout, precision, scaling
from garmentgnn.bench import learned as learned_mod
from garmentgnn.bench import methods
from garmentgnn.bench import stability as stab
from garmentgnn.bench.presets import Preset, SimBudget
from garmentgnn.bench.records import collect, failure, json_safe, load_record, record_path
from garmentgnn.bench.report import check_record, write_report
from garmentgnn.bench.tables import slug
from garmentgnn.bench.sequences import BenchSequence, make_sequence
from garmentgnn.bench.timing import batch_sweep, num_threads, peak_memory
from garmentgnn._files import atomic_write_bytes, atomic_write_json, remove_stale_temporaries
from garmentgnn.data.ensemble import load_ensemble
from garmentgnn.data.store import code_version
from garmentgnn.metrics import evaluate
from garmentgnn.models.baselines import LBSBaseline


# --------------------------------------------------------------------------- presets
@dataclass
class Prediction:
    """A method's output for one sequence: ``positions [T, V, 3]`` (``None`` when it
    failed), ``ok``/``message``, and ``timing`` (``latency_ms``, ``throughput_fps``,
    ``best_batch``, ``peak_mem_mb``, ...) measured by the method itself."""

    positions: Optional[Tensor]
    ok: bool = True
    message: str = "ok"
    timing: Dict[str, Any] = field(default_factory=dict)


Method = Callable[[BenchSequence, Preset], Prediction]
#: name -> factory(preset) -> method
METHODS: Dict[str, Callable[[Preset], Method]] = {}

#: The comparison this bench is for (paper Tables 1 and 3): the learned methods of
#: :mod:`garmentgnn.bench.learned`.  Those that produce no record (not in the preset's
#: budget, or ``run(learned=False)``) show up as "not run".
PLANNED: Tuple[str, ...] = methods.METHOD_NAMES


def register(name: str, factory: Callable[[Preset], Method], overwrite: bool = False) -> None:
    """Make ``name`` runnable: ``factory(preset)`` returns ``method(sequence, preset) ->
    Prediction``.  Add the name to a preset's ``methods`` to run it."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"`name`: expected a non-empty string, got {name!r}")
    if not callable(factory):
        raise ValueError(f"`factory`: expected a callable, got {type(factory).__name__}")
    if name in METHODS and not overwrite:
        raise ValueError(f"`name`: {name!r} is already registered (pass overwrite=True)")
    METHODS[name] = factory


def _lbs_factory(p: Preset) -> Method:
    model = LBSBaseline()

    def run(seq: BenchSequence, preset_: Preset) -> Prediction:
        rot, tr = seq.motion.rotations, seq.motion.translation
        with torch.inference_mode():
            mem = peak_memory(lambda: model(seq.scene, rot, tr))
            T = rot.shape[0]

            def make(b: int):
                idx = torch.arange(b) % T
                r, t = rot[idx], tr[idx]
                return lambda: model(seq.scene, r, t)
            timing = batch_sweep(make, preset_.batches, preset_.warmup, preset_.repeats)
        timing.update(peak_mem_mb=mem["peak_mb"], memory_method=mem["method"],
                      note="median wall time of one call predicting `batch` frames")
        return Prediction(mem["result"], timing=timing)

    return run


def simulator_method(budget: SimBudget) -> Callable[[Preset], Method]:
    """Factory of the reference simulator at ``budget`` (not batchable: throughput is
    one frame at a time; timing and memory of the one run that produced the result)."""
    predict = stab.simulator_predictor(substeps=budget.substeps, max_newton=budget.max_newton)

    def factory(p: Preset) -> Method:
        def run(seq: BenchSequence, preset_: Preset) -> Prediction:
            t0 = time.perf_counter()
            mem = peak_memory(lambda: predict(seq))
            wall = time.perf_counter() - t0
            res = mem["result"]
            frames = max(1, seq.num_frames - 1)
            ms = 1e3 * wall / frames
            timing = {"latency_ms": ms, "throughput_fps": 1e3 / ms, "best_batch": 1,
                      "threads": torch.get_num_threads(), "peak_mem_mb": mem["peak_mb"],
                      "memory_method": mem["method"],
                      "note": f"one run: wall time / {frames} simulated frames (incl. setup)",
                      "newton_iterations": int(res.newton_iterations.sum()),
                      "nonconverged_frames": int((~res.converged).sum())}
            if not res.ok:
                return Prediction(None, False, res.message, timing)
            return Prediction(res.positions, True, "ok", timing)
        return run

    return factory


register("lbs", _lbs_factory)


def _method(name: str, p: Preset) -> Method:
    for b in (p.reference,) + p.budgets:
        if b.name == name:
            return simulator_method(b)(p)
    if name not in METHODS:
        raise ValueError(f"`methods`: {name!r} is not registered; known: {sorted(METHODS)}")
    return METHODS[name](p)


# --------------------------------------------------------------------------- runner
@dataclass
class RunSummary:
    ran: int
    skipped: int
    failed: int
    seconds: float
    paths: Dict[str, Path]

    def __str__(self) -> str:
        report = self.paths.get("report") or "not yet (other shards still running; the " \
            "last to finish writes it)"
        return (f"bench: ran {self.ran}, skipped {self.skipped} (already done), "
                f"failed {self.failed}, {self.seconds:.1f} s; report: {report}")


class _Context:
    """Per-run caches: sequences and ground truths by (case, seed)."""

    def __init__(self, preset_: Preset, out: Path) -> None:
        self.p, self.out = preset_, out
        self.seqs: Dict[Tuple[str, int], BenchSequence] = {}
        self.gts: Dict[Tuple[str, int], Dict[str, Any]] = {}

    def sequence(self, item: Dict[str, Any], seed: int) -> BenchSequence:
        key = (item["name"], seed)
        if key not in self.seqs:
            self.seqs[key] = make_sequence(item, seed)
        return self.seqs[key]

    def ground_truth(self, item: Dict[str, Any], seed: int) -> Dict[str, Any]:
        """``{"ok", "message", "positions", "timing"}`` of the reference run (cached on disk)."""
        key = (item["name"], seed)
        if key in self.gts:
            return self.gts[key]
        path = self.out / "cache" / f"gt--{slug(item['name'])}--s{seed}.pt"
        gt = None
        if path.exists():
            try:
                gt = torch.load(path, weights_only=True)
            except Exception:  # a damaged cache file is recomputed
                gt = None
        if gt is None:
            seq = self.sequence(item, seed)
            try:
                pred = _method(self.p.reference.name, self.p)(seq, self.p)
                gt = {"ok": pred.ok, "message": pred.message, "timing": pred.timing,
                      "positions": pred.positions}
            except Exception as err:
                gt = {"ok": False, "message": f"{type(err).__name__}: {err}", "timing": {},
                      "positions": None}
            buf = io.BytesIO()
            torch.save(gt, buf)
            atomic_write_bytes(path, buf.getvalue())
        self.gts[key] = gt
        return gt


def _accuracy_record(ctx: _Context, method: str, item: Dict[str, Any], seed: int
                     ) -> Dict[str, Any]:
    p = ctx.p
    rec: Dict[str, Any] = {"kind": "accuracy", "method": method, "case": item["name"],
                           "seed": seed, "reference": method == p.reference.name}
    t0 = time.perf_counter()
    try:
        seq = ctx.sequence(item, seed)
        rec["num_vertices"] = seq.garment.num_vertices
        rec["num_frames"] = seq.num_frames
        gt = ctx.ground_truth(item, seed)
        if not gt["ok"]:
            raise RuntimeError(f"ground truth ({p.reference.name}) failed: {gt['message']}")
        if rec["reference"]:
            pred = Prediction(gt["positions"], True, "ok", dict(gt["timing"]))
        else:
            pred = _method(method, p)(seq, p)
        rec["timing"] = pred.timing
        if not pred.ok:
            raise RuntimeError(pred.message)
        pos = pred.positions.detach()
        T, V = seq.num_frames, seq.garment.num_vertices
        if pos.shape != (T, V, 3):
            raise RuntimeError(f"predicted positions of shape {tuple(pos.shape)}, expected "
                               f"{(T, V, 3)}")
        if not torch.isfinite(pos).all():
            raise RuntimeError(f"{int((~torch.isfinite(pos)).sum())} non-finite coordinates")
        g = gt["positions"]
        m = evaluate(pos[1:].double(), g[1:].double(), seq.garment.faces,
                     seq.body_frames[1:].double(), seq.body.faces)
        m["collision_rate"] = m.pop("collision")
        rec.update(status="ok", message="ok", metrics=m)
    except Exception as err:
        rec.update(failure(err))
    rec["seconds"] = time.perf_counter() - t0
    return rec


def tasks(p: Preset, seeds: Sequence[int], learned_seeds: Sequence[int] = (),
          data_case: Optional[str] = None, plan: Optional[Dict[str, int]] = None
          ) -> List[Tuple[str, str, Dict[str, Any], int]]:
    """Every ``(kind, method, case item, seed)`` of a preset, in run order; the learned
    methods (``p.learned``) for each of ``learned_seeds``, on the dataset ``data_case``
    (:attr:`garmentgnn.bench.learned.DatasetInfo.case`); ``plan``: the number of
    seeds of each learned method (:func:`garmentgnn.bench.methods.seed_plan`; default:
    every seed, the seed-free methods one), and with it the long run
    (:data:`~garmentgnn.bench.methods.LONG`) when the budget has one."""
    out: List[Tuple[str, str, Dict[str, Any], int]] = []
    for seed in seeds:
        for item in p.cases:
            for m in p.method_names():
                out.append(("accuracy", m, item, seed))
        for case in p.stability_cases:
            out.append(("stability", "sim", dict(p.stability_item, name=case), seed))
    if seeds:  # the extra reports: first seed only
        s0 = seeds[0]
        if p.scaling_item is not None:
            for it in scaling.scaling_items(p.scaling_item, p.scaling_resolutions):
                out.append(("scaling", scaling.METHOD, it, s0))
        if p.leaveout and p.cases:
            out.append(("leaveout", leaveout.METHOD, p.cases[0], s0))
        for m in p.precision_methods:
            if p.cases:
                out.append(("precision", precision.METHODS[m], p.cases[0], s0))
        if p.long_item is not None:
            out.append(("long_sequence", precision.LONG_METHOD, p.long_item, s0))
    if learned_seeds and p.learned is not None:
        if not data_case:
            raise ValueError("`data_case`: the learned tasks need the dataset's case name")
        for i, seed in enumerate(learned_seeds):
            for m in p.learned.methods:
                n = plan.get(m, 1) if plan is not None else \
                    (1 if m in methods.SEED_FREE else len(learned_seeds))
                if i < n:
                    out.append(("learned", m, {"name": data_case}, seed))
        if plan is not None and p.learned.long_minutes is not None:
            out.append(("learned", methods.LONG, {"name": data_case}, learned_seeds[0]))
        # the stability suite on the dataset: each method's first-seed model, the simulator
        for case in p.learned.stability_cases:
            for m in p.learned.methods + (learned_mod.SIMULATOR,):
                if not (m == learned_mod.SIMULATOR and case in learned_mod.SIMULATOR_SKIPS):
                    out.append(("learned_stability", m, {"name": case}, learned_seeds[0]))
    return out


def _extra_record(ctx: _Context, kind: str, method: str, item: Dict[str, Any], seed: int
                  ) -> Dict[str, Any]:
    """A scaling / leave-out / precision / long-sequence record (those modules turn
    their own exceptions into failed records)."""
    p = ctx.p
    kw = dict(p.model_inputs, seed=seed)
    if kind == "scaling":
        return scaling.run_record(item, warmup=p.warmup, repeats=p.repeats, **kw)
    if kind == "long_sequence":
        return precision.run_long(item, **kw)
    if kind == "precision":
        key = {v: k for k, v in precision.METHODS.items()}[method]
        return precision.run_record(ctx.sequence(item, seed), key, warmup=p.warmup,
                                    repeats=p.repeats, **kw)
    if kind == "leaveout":
        gt = ctx.ground_truth(item, seed)
        if not gt["ok"]:
            return {"kind": kind, "method": method, "case": item["name"], "seed": seed,
                    "status": "failed", "message": f"ground truth ({p.reference.name}) "
                                                   f"failed: {gt['message']}"}
        return leaveout.run_record(ctx.sequence(item, seed), gt["positions"],
                                   warmup=p.warmup, repeats=p.repeats, **kw)
    raise ValueError(f"`kind`: unknown task kind {kind!r}")


def run(p: Preset, out, seeds: Optional[int] = None, progress: bool = True,
        retry_failed: bool = False, data=None, learned: bool = True,
        command: Optional[str] = None, shard: Optional[Tuple[int, int]] = None,
        poll_seconds: float = 30.0, backend=None) -> RunSummary:
    """Run (or resume) preset ``p`` into ``out`` and write the report.

    ``seeds`` overrides both the preset's seeds and its learned methods' training seeds.
    The learned methods (``p.learned``, unless ``learned=False``) train on the dataset
    ``data`` (a generated dataset folder) or, by default, on ``p.dataset`` generated
    (resumably) under ``OUT/data``.  ``command``: the command line, for the report.

    ``shard=(i, n)``: run only the ``i``-th of ``n`` interleaved parts of the task list,
    with ``max(1, p.threads // n)`` threads, so that ``n`` processes started on the same
    ``OUT`` share the preset's cores (every record says its threads).  Before the seed
    plan a shard waits (polling every ``poll_seconds``) for every method's first-seed
    record, whoever runs it; the shard that finds every record written writes the report
    (the others' summaries have no ``report`` path).  ``backend``: where the learned runs
    go (:class:`garmentgnn.bench.ray_backend.RayBackend`; ``None``: this process)."""
    if not isinstance(p, Preset):
        raise ValueError(f"`p`: expected a Preset, got {type(p).__name__}")
    if shard is not None and not (isinstance(shard, tuple) and len(shard) == 2
                                  and all(isinstance(v, int) for v in shard)
                                  and 0 <= shard[0] < shard[1]):
        raise ValueError(f"`shard`: expected (i, n) with 0 <= i < n, got {shard!r}")
    n = p.seeds if seeds is None else seeds
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"`seeds`: expected a positive int, got {seeds!r}")
    for m in p.methods:
        if m not in METHODS:
            raise ValueError(f"`p.methods`: {m!r} is not registered; known: {sorted(METHODS)}")
    if data is not None and (not learned or p.learned is None):
        raise ValueError("`data`: given, but no learned methods run (learned=False or the "
                         "preset has none)")
    if not learned and p.learned is not None and not tasks(p, list(range(n))):
        raise ValueError(f"`learned=False` (--no-learned): preset {p.name!r} runs learned "
                         f"methods only, so nothing would run; run it with them")
    if data is not None:  # an ensemble ground truth of another dataset: before any file
        load_ensemble(data)
    out = Path(out)
    for sub in ("records", "cache"):
        (out / sub).mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(out / sub)
    remove_stale_temporaries(out)
    t0 = time.perf_counter()
    runner, lseeds, data_info = None, [], None
    if learned and p.learned is not None:
        if data is None and not p.dataset:
            raise ValueError("`p.dataset`: the preset has learned methods but no dataset")
        data_info = learned_mod.prepare_dataset(
            out / "data" if data is None else data, p.dataset if data is None else None,
            workers=p.data_workers, progress=progress)
        runner = learned_mod.LearnedRunner(data_info, p.learned, out, p.batches, p.warmup,
                                           p.repeats)
        lseeds = list(range(p.learned.seeds if seeds is None else n))
    case = data_info.case if data_info else None
    budget = p.learned if runner is not None else None
    if budget is not None and budget.seed_methods is not None:
        # first pass: seed 0 of every method; the seed plan depends on its results
        first = tasks(p, list(range(n)), lseeds, case, {m: 1 for m in budget.methods})
    else:
        first = tasks(p, list(range(n)), lseeds, case)
    ctx = _Context(p, out)
    records: Dict[Tuple[str, str, str, int], Dict[str, Any]] = {}
    ran = skipped = 0
    threads = p.threads if shard is None else max(1, p.threads // shard[1])

    def mine(todo):
        """This shard's part of ``todo`` (every task without ``shard``)."""
        return list(todo) if shard is None else list(todo)[shard[0]::shard[1]]

    def kept(kind, method, case, seed):  # the record on disk this run keeps (None: run it)
        rec = load_record(record_path(out, kind, method, case, seed), kind, method, case, seed)
        return rec if rec is not None and (rec["status"] == "ok" or not retry_failed) else None

    def save(key, rec, bar) -> None:
        nonlocal ran
        records[key] = rec = json_safe(_finalize(rec))
        atomic_write_json(record_path(out, *key), rec)
        ran += 1
        bar.update(1)

    def run_all(todo, bar) -> None:
        nonlocal skipped
        if backend is not None and runner is not None:  # the learned runs, in parallel
            backend.run(runner, [(m, s) for k, m, it, s in todo if k == learned_mod.KIND
                                 and kept(k, m, it["name"], s) is None], threads,
                        lambda r: save((r["kind"], r["method"], r["case"], r["seed"]), r, bar))
        for kind, method, item, seed in todo:
            case = item["name"]
            if (kind, method, case, seed) in records:
                continue
            rec = kept(kind, method, case, seed)
            if rec is not None:
                skipped += 1
                records[(kind, method, case, seed)] = rec
                bar.update(1)
            else:
                bar.set_postfix_str(f"{kind} {method} {case} s{seed}", refresh=False)
                if kind == "accuracy":
                    rec = _accuracy_record(ctx, method, item, seed)
                elif kind == "stability":
                    settings = dict(p.stability_settings)
                    rec = stab.run_case(case, p.stability_item, seed,
                                        stab.simulator_predictor(**settings), method)
                elif kind == "learned":
                    rec = runner.record(method, seed)
                elif kind == "learned_stability":
                    rec = runner.stability_record(method, seed, case)
                elif kind == engines.KIND:
                    rec = engines.engine_record(data_info.root, item["item"],
                                                engine_settings[method], p.engine_frames)
                else:
                    rec = _extra_record(ctx, kind, method, item, seed)
                save((kind, method, case, seed), rec, bar)

    # the engines on a few of the learned methods' test sequences
    engine_settings = {e.name: e for e in engines.default_settings()} if p.engines else {}
    if engine_settings and runner is not None:
        # from the sequences the learned methods are scored on, so that both sit on
        # one plot
        picked = engines.pick_sequences(runner.test.records, p.engine_per_group)
        first += [(engines.KIND, name, {"name": it["id"], "item": it}, 0)
                  for it in picked for name in engine_settings]
    own = mine(first)
    with num_threads(threads), tqdm(total=len(own), desc=f"bench {p.name}",
                                    disable=not progress) as bar:
        run_all(own, bar)
        who = "" if shard is None else f"shard {shard[0]}/{shard[1]}"
        done = collect(out, first, records, budget is not None and budget.seed_methods is not None,
                       poll_seconds, who)
        if budget is not None and budget.seed_methods is not None:
            seed0 = {r["method"]: r["metrics"]["E_dist"] for r in records.values()
                     if r["kind"] == learned_mod.KIND and r["seed"] == lseeds[0]
                     and r["status"] == "ok"}
            plan = methods.seed_plan(replace(budget, seeds=len(lseeds)), seed0)
            # split by the plan alone (not by what is on disk), so every shard agrees
            added = [t for t in tasks(p, list(range(n)), lseeds, case, plan)
                     if t not in first]
            own = mine(added)
            bar.total = bar.n + len(own)
            run_all(own, bar)
            done = collect(out, first + added, records)
    if not done:
        failed = sum(r["status"] == "failed" for r in records.values())
        return RunSummary(ran, skipped, failed, time.perf_counter() - t0, {})
    records = list(records.values())
    # the simulator-case methods (and their reference) only where the preset has cases
    planned = list(PLANNED) + ([m for m in METHODS if m not in p.method_names()]
                               if p.cases else [])
    not_run = [m for m in planned if not any(r["method"] == m for r in records)]
    meta = {"command": command or f"garmentgnn.bench.runner.run(preset {p.name!r})",
            "preset": p.name, "seeds": n, "threads": threads,
            "shards": 1 if shard is None else shard[1],
            "torch": torch.__version__, "python": platform.python_version(),
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip()
                       + f", {os.cpu_count()} CPUs",
            "code": code_version(),
            "reference": (p.reference.name + " (ground truth of the simulator cases)"
                          if p.cases else "each dataset sequence's own simulation"),
            "preset_config": json_safe(asdict(p))}
    if data_info is not None:
        meta["dataset"] = data_info.to_json()
    paths = write_report(records, out, not_run, meta)
    failed = sum(r["status"] == "failed" for r in records)
    return RunSummary(ran, skipped, failed, time.perf_counter() - t0, paths)


def _finalize(rec: Dict[str, Any]) -> Dict[str, Any]:
    """A record the report accepts: one with non-finite numbers is marked failed."""
    try:
        check_record(rec)
    except ValueError as err:
        rec = dict(rec, status="failed", message=f"refused by the report: {err}")
    return rec
