"""Do the learned methods learn?  Step-0 gradients, one-chunk overfit, equal-step curves.

Its parts, each on a generated dataset (``--data``, e.g. ``garmentgnn generate --preset
small --engine blender``), every method built from its packaged configuration the way
``garmentgnn bench`` builds it (:mod:`garmentgnn.harness.methods`) and trained through the
same Lightning ``Trainer``:

* ``grad``: one backward pass of each method's phase-1 training loss on the first
  training chunk; per branch the trainable parameter tensors, how many got a non-zero
  gradient and the gradient norm (:func:`garmentgnn.training.diagnostics.branch_gradients`).
* ``overfit``: each method trained on that one chunk alone for ``--steps`` steps; its
  E_dist on the chunk against steps, and LBS's.
* ``curves``: GarTrans settings and the DA- and HOOD-style baselines (``--variants``,
  :data:`VARIANTS`; NCS-style trains per garment on test poses) trained for the same
  ``--steps`` on the training split; E_dist on the training and test sequences every
  ``--every`` steps, as a ratio to LBS's on the same sequences (``--surface``: the
  normal, edge-length and curvature errors too); with several ``--seed``, the mean over
  seeds and a paired Wilcoxon test of each variant against the first.
* ``energy``: the HOOD- and NCS-style models a ``garmentgnn bench`` run trained
  (``--bench``): their own objective, the physics terms they were trained on, on their
  test predictions against the same objective on the LBS garment, beside E_dist.
* ``oracle``: what those methods could reach at best: the trajectory that minimises a
  physics objective exactly, frame by frame (the objectives of the HOOD-style
  ``--variants``, default its configuration's, which NCS-style's shares, and the silk
  energies), on the test sequences, against LBS.

Each writes ``<part>.json`` and ``<part>.md`` (curves also ``<part>.png``) into
``~/.cache/garmentgnn/benchmarks/learning``, ``--out``, or with ``--commit`` the committed
copy ``docs/results/learning``::

    python benchmarks/learning.py grad overfit curves \
        --data ~/.cache/garmentgnn/datasets/small-blender
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import lightning as L
import torch

from garmentgnn._argparse import (Accumulate, HelpFormatter, add_output_args, check_unique,
                                  command_line, existing_file, int_at_least, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.harness import scoring
from garmentgnn.harness.methods import (BASELINES, DA, DATA, FULL, GARTRANS, HOOD, NCS,
                                      variant_settings)
from garmentgnn.harness.tables import table
from garmentgnn.data.keys import body_key, garment_key
from garmentgnn.data.store import read_json, read_manifest
from garmentgnn.metrics.garment_metrics import evaluate_inputs, vertex_distance
from garmentgnn.physics.materials import MATERIALS
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (BaselineModule, GarmentDataModule, GarTransModule,
                                 ProgressiveSchedule)
from garmentgnn.training.diagnostics import branch_gradients, dead_branches
from garmentgnn.training.module import loss_inputs

#: the surface metrics ``curves --surface`` adds (E_dist is always measured)
SURFACE = ("E_vnorm", "E_fnorm", "E_len", "E_curv")
RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "learning"

#: HOOD-style's configuration before it started from its own states with normalised inputs
_HOOD_FORMER: Dict[str, Any] = {"start_state": "lbs", "model": {"normalize": False}}
_S = MATERIALS["silk"]
#: loss weights that make the physics terms the silk preset's energies (SI units)
_SILK: Dict[str, float] = {"stretch": _S.stretch, "shear": _S.shear, "bending": _S.bending,
                           "gravity": 1.0, "inertia": 1.0}
#: GarTrans settings compared by ``curves``: model overrides of the packaged config,
#: Trainer arguments and data-module settings.  Every variant but ``config`` starts from
#: the former config's world-frame dynamic stack on raw inputs (:data:`_FORMER_INPUTS`,
#: merged in below), as they were measured, unless it names the switches itself
VARIANTS: Dict[str, Dict[str, Any]] = {
    "config": {},
    "former config (world frame, raw inputs)": {},
    "former config (gates at 0, acceleration)": {"model": {"gate_init": 0.0,
                                                           "accel_unit": None}},
    "gate 0.1": {"model": {"gate_init": 0.1}},
    "gate 1": {"model": {"gate_init": 1.0}},
    "gate 0.1, cm": {"model": {"gate_init": 0.1, "accel_unit": 0.01}},
    "gate 1, cm": {"model": {"gate_init": 1.0, "accel_unit": 0.01}},
    "gate 1, cm, adam 1e-3": {"model": {"gate_init": 1.0, "accel_unit": 0.01,
                                        "optimizer": "adam", "lr": 1e-3}},
    "gate 1, cm, 4 chunks/step": {"model": {"gate_init": 1.0, "accel_unit": 0.01},
                                  "trainer": {"accumulate_grad_batches": 4}},
    "gate 0.1, cm, adam 1e-3": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                          "optimizer": "adam", "lr": 1e-3}},
    "gate 0.1, cm, 4 chunks/step": {"model": {"gate_init": 0.1, "accel_unit": 0.01},
                                    "trainer": {"accumulate_grad_batches": 4}},
    "gate 0.1, cm, vert only": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                          "loss_weights": {"edge": 0.0, "norm": 0.0,
                                                           "curv": 0.0}}},
    "gate 0.1, cm, no limit/projection": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                                    "strain_limit": 0,
                                                    "collision_projection": None}},
    "lr 3e-4": {"model": {"lr": 3e-4}},
    "lr 1e-2": {"model": {"lr": 1e-2}},
    "input normalisers": {"model": {"input_norm": True}},
    # the dynamic stack in each vertex's skinned local frame (inputs and output)
    "local frame": {"model": {"local_frame": True}},
    "local frame, input normalisers": {"model": {"local_frame": True, "input_norm": True}},
    # the paper's blend shape B^t (a learned offset of the template, skinned with it)
    "blend shape": {"model": {"blend_shape": True}},
    "blend shape, local frame": {"model": {"blend_shape": True, "local_frame": True}},
    "blend shape, pose history 10": {"model": {"blend_shape": True}, "data": {"history": 10}},
    # ``schedule``: the bench's ProgressiveSchedule (the curvature term from phase 1, phases
    # 2 and 3 at plateaus of ``window`` epochs) instead of phase 1 alone
    "schedule": {"schedule": {"window": 1}},
    "schedule, no phase-3 freeze": {"schedule": {"window": 1, "freeze_rest": False}},
    "schedule, phase 1 only (curvature term)": {"schedule": {"window": 1, "max_phase": 1}},
    # ``data``: the data module's settings (the pose history is the GRU's input)
    "pose history 2": {"data": {"history": 2}},
    "pose history 10": {"data": {"history": 10}},
    "pose history 30": {"data": {"history": 30}},
    # the baselines on the same curves (``baseline``: the method, ``module``: overrides of
    # its packaged configuration)
    "DA-style": {"baseline": DA},
    "HOOD-style": {"baseline": HOOD},
    "HOOD-style, lr 1e-4": {"baseline": HOOD, "module": {"lr": 1e-4}},
    "HOOD-style, LBS start": {"baseline": HOOD, "module": {"start_state": "lbs"}},
    "HOOD-style, raw inputs": {"baseline": HOOD, "module": {"model": {"normalize": False}}},
    "HOOD-style, accelerations x10": {"baseline": HOOD, "module": {
        "model": {"accel_scale": 10.0}}},
    # its objective in SI units: the stiffnesses of the silk preset as the loss weights
    # (the configuration's are the GarTrans paper's loss weights, ~1/5000 of silk's
    # stretch), gravity and inertia at 1
    "HOOD-style, silk energies": {"baseline": HOOD, "module": {"loss": {"weights": _SILK}}},
    "HOOD-style, silk energies, collision x10": {"baseline": HOOD, "module": {
        "loss": {"weights": dict(_SILK, collision=15.0)}}},
    # the own-state chain never reset to LBS (the configuration resets where the kept
    # state drifted over 0.25 m from LBS on average): training sees the states a
    # diverging test rollout reaches
    "HOOD-style, no drift reset": {"baseline": HOOD, "module": {"max_start_drift": 100.0}},
    "HOOD-style, silk energies, no drift reset": {"baseline": HOOD, "module": {
        "loss": {"weights": _SILK}, "max_start_drift": 100.0}},
    # before its configuration started from its own states with normalised inputs
    "HOOD-style, former recipe": {"baseline": HOOD, "module": _HOOD_FORMER},
    "HOOD-style, former recipe, lr 1e-4": {"baseline": HOOD, "module": dict(
        _HOOD_FORMER, lr=1e-4)},
    "HOOD-style, former recipe, accelerations x10": {"baseline": HOOD, "module": dict(
        _HOOD_FORMER, model={"normalize": False, "accel_scale": 10.0})},
}
#: the config's dynamic-stack switches before ``local_frame`` and ``input_norm`` became
#: its defaults (docs/model.md)
_FORMER_INPUTS: Dict[str, Any] = {"local_frame": False, "input_norm": False}
for _name, _v in VARIANTS.items():
    if _name != "config" and "baseline" not in _v:
        _v["model"] = dict(_FORMER_INPUTS, **_v.get("model", {}))


# ------------------------------------------------------------------ building methods
def datamodule(root: Path, seed: int = 0, split: str = "train",
               data: Optional[Dict[str, Any]] = None) -> GarmentDataModule:
    """The bench's data settings, with ``data``'s overrides (e.g. ``history``)."""
    return GarmentDataModule(root, val_split=None, seed=seed, train_split=split, cache_size=64,
                             **dict(DATA, **(data or {})))


def gartrans(dims: Dict[str, int], method: str = "GarTrans (SAT)",
             overrides: Optional[Dict[str, Any]] = None) -> GarTransModule:
    hp, _ = variant_settings(method)
    return GarTransModule(**dims, **dict(hp, **(overrides or {})))


def baseline(method: str, dims: Dict[str, int], num_vertices: Optional[int] = None,
             overrides: Optional[Dict[str, Any]] = None) -> BaselineModule:
    cfg = dict(BASELINES[method])
    for k, v in (overrides or {}).items():  # a section (``model``, ``loss``) is merged
        cfg[k] = dict(cfg[k], **v) if isinstance(v, dict) and isinstance(cfg.get(k), dict) else v
    return BaselineModule(num_joints=dims["num_joints"], num_vertices=num_vertices,
                          fps=30.0, history=DATA["history"], **cfg)


def methods(dims: Dict[str, int], num_vertices: int, only: Optional[Sequence[str]] = None,
            variants: Sequence[str] = ()) -> Dict[str, Callable[[], L.LightningModule]]:
    """Every learned method of the bench (or those named in ``only``), freshly built
    (phase-1 losses for GarTrans), and GarTrans with each of ``variants``' settings."""
    out: Dict[str, Callable[[], L.LightningModule]] = {
        m: (lambda m=m: gartrans(dims, m)) for m in GARTRANS}
    for m in (DA, HOOD, NCS):
        out[m] = lambda m=m: baseline(m, dims, num_vertices)
    out = {k: v for k, v in out.items() if only is None or k in only}
    for v in variants:
        if "baseline" in VARIANTS[v]:  # a baseline's own settings: see `only`
            out[v] = lambda v=v: baseline(VARIANTS[v]["baseline"], dims, num_vertices,
                                          VARIANTS[v].get("module"))
        else:
            out[f"GarTrans, {v}"] = lambda v=v: gartrans(dims, overrides=VARIANTS[v].get("model"))
    return out


def whole_sequences(root: Path, split: str, history: Optional[int] = None) -> SequenceChunks:
    """``split``'s sequences, one item each, with the bench's data settings (``history``:
    another pose history length)."""
    return SequenceChunks(root, split, chunk=10 ** 9, history=history or DATA["history"],
                          nystrom_dim=DATA["nystrom_dim"], num_landmarks=DATA["num_landmarks"],
                          cache_size=64)


class _Fixed(torch.utils.data.Dataset):
    """One chunk, ``n`` times (an epoch of ``n`` steps on the same chunk)."""

    def __init__(self, item, n: int) -> None:
        self.item, self.n = item, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        return self.item


def _trainer(steps: int, callbacks=(), **kw) -> L.Trainer:
    return L.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False,
                     enable_checkpointing=False, enable_progress_bar=False,
                     enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                     callbacks=list(callbacks), **kw)


def predict(module: L.LightningModule, item) -> torch.Tensor:
    with torch.no_grad():
        out = module(item)
    return out["final"] if isinstance(out, dict) else out


class Probe(L.Callback):
    """E_dist (cm) of ``sets`` (name -> list of whole-sequence items) every ``every``
    optimizer steps, and at step 0."""

    def __init__(self, sets: Dict[str, List[Any]], every: int, label: str = "",
                 surface: bool = False) -> None:
        self.sets, self.every, self.label, self.surface = sets, every, label, surface
        self.rows: List[Dict[str, Any]] = []
        self.t0 = time.perf_counter()
        self.train_seconds = 0.0

    def measure(self, module: L.LightningModule, step: int) -> None:
        t = time.perf_counter()
        was = module.training
        module.eval()
        row: Dict[str, Any] = {"step": step, "train_seconds": self.train_seconds}
        for name, items in self.sets.items():
            preds = [predict(module, it) for it in items]
            errs = [float(vertex_distance(p, it.gt).mean()) for p, it in zip(preds, items)]
            row[f"{name}_sequences"] = {it.seq_id: e for it, e in zip(items, errs)}
            row[name] = (sum(e * it.gt.shape[0] for e, it in zip(errs, items))
                         / sum(it.gt.shape[0] for it in items))
            if self.surface:  # the other Table 3 metrics, frame-weighted
                row[f"{name}_metrics"] = self.weighted(
                    [(evaluate_inputs(p, it), it) for p, it in zip(preds, items)])
        module.train(was)
        self.rows.append(row)
        print(f"  {self.label} step {step}: " + ", ".join(f"{k} {row[k]:.3f} cm"
                                                      for k in self.sets), flush=True)
        self.t0 += time.perf_counter() - t  # evaluation is not training time

    @staticmethod
    def weighted(scored: List[Any]) -> Dict[str, float]:
        """The :data:`SURFACE` metrics of ``(metrics, item)`` pairs, weighted by frames."""
        frames = sum(it.gt.shape[0] for _, it in scored)
        return {k: sum(m[k] * it.gt.shape[0] for m, it in scored) / frames for k in SURFACE}

    def on_train_start(self, trainer, pl_module) -> None:
        self.t0 = time.perf_counter()
        self.measure(pl_module, 0)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.train_seconds = time.perf_counter() - self.t0
        step = trainer.global_step
        if step % self.every == 0 and (not self.rows or self.rows[-1]["step"] != step):
            self.measure(pl_module, step)


def lbs_error(items: Sequence[Any]) -> float:
    num = sum(float(vertex_distance(it.skinned(), it.gt).mean()) * it.gt.shape[0] for it in items)
    return num / sum(it.gt.shape[0] for it in items)


# ------------------------------------------------------------------------- the parts
def part_grad(root: Path, only: Optional[Sequence[str]] = None,
              variants: Sequence[str] = ()) -> Dict[str, Any]:
    dm = datamodule(root)
    dims = dm.dims
    item = dm.train_set[0]
    res: Dict[str, Any] = {}
    for name, make in methods(dims, item.num_vertices, only, variants).items():
        torch.manual_seed(0)
        rep = branch_gradients(make(), item)
        res[name] = {"branches": rep, "dead": dead_branches(rep)}
    rows = []
    for name, r in res.items():
        for b, g in r["branches"].items():
            rows.append([name, b, str(g["trainable"]), str(g["with_grad"]), f"{g['norm']:.3g}"])
    lines = table(["method", "branch", "trainable tensors", "with gradient", "gradient norm"],
                  rows)
    dead = {k: r["dead"] for k, r in res.items() if r["dead"]}
    lines += ["", "Branches without any gradient at step 0: " +
              (json.dumps(dead) if dead else "none")]
    return {"results": res, "markdown": lines}


def part_overfit(root: Path, steps: int, every: int,
                 only: Optional[Sequence[str]] = None,
                 variants: Sequence[str] = ()) -> Dict[str, Any]:
    dm = datamodule(root)
    dims = dm.dims
    item = dm.train_set[0]
    lbs = lbs_error([item])
    res: Dict[str, Any] = {"chunk": {"seq_id": item.seq_id, "frames": item.num_frames,
                                     "vertices": item.num_vertices}, "lbs": lbs, "methods": {}}
    for name, make in methods(dims, item.num_vertices, only, variants).items():
        torch.manual_seed(0)
        module = make()
        probe = Probe({"chunk": [item]}, every, name)
        loader = torch.utils.data.DataLoader(_Fixed(item, steps), batch_size=None,
                                             collate_fn=lambda x: x)
        t = time.perf_counter()
        try:
            _trainer(steps, [probe]).fit(module, loader)
            status = "ok"
        except Exception as err:  # a method that fails is reported, not hidden
            status = f"{type(err).__name__}: {err}"
        res["methods"][name] = {"curve": probe.rows, "status": status,
                                "seconds": time.perf_counter() - t}
        last = probe.rows[-1]["chunk"] if probe.rows else math.nan
        print(f"overfit {name}: {last:.3f} cm after {steps} steps (LBS {lbs:.3f})", flush=True)
    rows = []
    for name, r in res["methods"].items():
        c = r["curve"]
        pick = {row["step"]: row["chunk"] for row in c}
        cells = [name] + [f"{pick[s] / lbs:.3f}" if s in pick else "—"
                          for s in (0, steps // 3, 2 * steps // 3, steps)]
        best = min((row["chunk"] for row in c), default=math.nan)
        rows.append(cells + [f"{best / lbs:.3f}", r["status"] if r["status"] != "ok" else ""])
    lines = [f"One chunk ({item.num_frames} frames of `{item.seq_id}`, {item.num_vertices} "
             f"vertices), LBS E_dist {lbs:.3f} cm; E_dist / LBS's:", ""]
    lines += table(["method", "step 0", f"step {steps // 3}", f"step {2 * steps // 3}",
                    f"step {steps}", "best", "failure"], rows)
    return {"results": res, "markdown": lines}


def evenly(items: Sequence[Any], n: int) -> List[Any]:
    """``n`` of ``items``, evenly spaced, the first and the last among them."""
    pick = torch.linspace(0, len(items) - 1, min(n, len(items))).round().long()
    return [items[int(i)] for i in pick.unique()]


def part_curves(root: Path, steps: int, every: int, variants: Sequence[str],
                train_sequences: int, seeds: Sequence[int],
                surface: bool = False, test_sequences: Optional[int] = None) -> Dict[str, Any]:
    """Each variant trained once per seed; the table gives the mean over seeds at the last
    step and, against the first variant, a paired Wilcoxon test over (seed, test sequence).
    ``test_sequences``: that many of the test split, evenly spaced (default: all)."""
    dims = datamodule(root, seeds[0]).dims

    def sequences(history: Optional[int] = None) -> Dict[str, List[Any]]:
        test = whole_sequences(root, "test", history)
        train = whole_sequences(root, "train", history)
        return {"train": evenly(train, train_sequences),
                "test": evenly(test, test_sequences or len(test))}

    sets = sequences()
    lbs = {k: lbs_error(v) for k, v in sets.items()}
    res: Dict[str, Any] = {"lbs": lbs, "steps": steps, "seeds": list(seeds), "variants": {}}
    if surface:
        res["lbs_metrics"] = {k: Probe.weighted([(evaluate_inputs(it.skinned(), it), it)
                                                  for it in v]) for k, v in sets.items()}
    for name in variants:
        v = VARIANTS[name]
        data = v.get("data")
        runs = []
        for seed in seeds:
            L.seed_everything(seed, verbose=False)
            module = (baseline(v["baseline"], dims, overrides=v.get("module")) if "baseline" in v
                      else gartrans(dims, overrides=v.get("model")))
            probe = Probe(sequences(data.get("history")) if data else sets, every, name, surface)
            # the bench's schedule of full GarTrans, with v's settings
            sched = (ProgressiveSchedule(**dict(variant_settings(FULL)[1], **v["schedule"]))
                     if "schedule" in v else None)
            t = time.perf_counter()
            try:
                _trainer(steps, [probe] + ([sched] if sched else []),
                         **v.get("trainer", {})).fit(
                    module, datamodule(root, seed, data=data))
                status = "ok"
            except Exception as err:
                status = f"{type(err).__name__}: {err}"
            runs.append({"seed": seed, "curve": probe.rows, "status": status,
                         "seconds": time.perf_counter() - t,
                         **({"transitions": sched.transitions} if sched else {})})
            last = probe.rows[-1] if probe.rows else {}
            print(f"curves {name}, seed {seed}: " + ", ".join(
                f"{k} {last.get(k, math.nan) / lbs[k]:.3f}" for k in sets)
                + f" x LBS ({status})", flush=True)
        res["variants"][name] = {"settings": v, "runs": runs}
    return {"results": res, "markdown": curves_markdown(res, surface)}


def mean_curve(runs: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
    """The runs' curves averaged over seeds, at the steps every run measured."""
    curves = [r["curve"] for r in runs if r["curve"]]
    n = min((len(c) for c in curves), default=0)
    return [{"step": curves[0][i]["step"],
             **{k: sum(c[i][k] for c in curves) / len(curves) for k in ("train", "test")}}
            for i in range(n)]


def curves_markdown(res: Dict[str, Any], surface: bool = False) -> List[str]:
    """The table of :func:`part_curves`' (or :func:`merge_curves`') results."""
    lbs, seeds = res["lbs"], res["seeds"]
    measured = next((run["curve"][-1] for r in res["variants"].values() for run in r["runs"]
                     if run["curve"]), {})  # none where every run failed at once
    count = {k: len(measured.get(f"{k}_sequences", ())) for k in ("train", "test")}

    def last_sequences(runs):  # {"seed/sequence": E_dist} of the test split, last step
        return {f"{r['seed']}/{q}": e for r in runs if r["curve"]
                for q, e in r["curve"][-1]["test_sequences"].items()}

    def spread(values):
        m = sum(values) / len(values)
        if len(values) < 2:
            return f"{m:.3f}"
        return f"{m:.3f} ± {statistics.stdev(values):.3f}"

    names = list(res["variants"])
    ref = last_sequences(res["variants"][names[0]]["runs"]) if names else {}
    rows = []
    for name, r in res["variants"].items():
        ok = [run for run in r["runs"] if run["curve"]]
        failures = "; ".join(f"seed {run['seed']}: {run['status']}" for run in r["runs"]
                             if run["status"] != "ok")
        if not ok:
            rows.append([name, "—", "—", "—", "—", "—", failures])
            continue
        c = mean_curve(ok)
        best = min(c, key=lambda row: row["test"])
        p = "—"
        if name != names[0] and len(ok) == len(r["runs"]):
            try:
                w = scoring.wilcoxon(last_sequences(ok), ref)
                p = f"{w['p']:.2g} ({w['median_diff']:+.3f} cm)"
            except ValueError:
                pass
        rows.append([name, str(ok[0]["curve"][-1]["step"]),
                     spread([run["curve"][-1]["train"] / lbs["train"] for run in ok]),
                     spread([run["curve"][-1]["test"] / lbs["test"] for run in ok]),
                     f"{best['test'] / lbs['test']:.3f} @ {best['step']}", p, failures])
    lines = [f"E_dist / LBS's (LBS: train {lbs['train']:.3f} cm over {count['train']} "
             f"sequences, test {lbs['test']:.3f} cm over {count['test']}); "
             f"{'seed' if len(seeds) == 1 else 'mean ± std over seeds'} "
             f"{', '.join(map(str, seeds))}; p: paired Wilcoxon test against "
             f"`{names[0] if names else ''}` over (seed, test sequence) at the last step, "
             "with the median difference:", ""]
    lines += table(["variant", "steps", "train", "test", "best test (seed mean)",
                    "p vs first", "failure"], rows)
    phased = [(name, run["seed"], run["transitions"]) for name, r in res["variants"].items()
              for run in r["runs"] if "transitions" in run]
    if phased:
        def when(t):  # {phase: the epoch at whose end it began}; JSON keys are strings
            return ", ".join(f"phase {k} after epoch {t[k]}" for k in sorted(t, key=int))

        lines += ["", "Phase transitions: " + "; ".join(
            f"{name}, seed {s}: {when(t) or 'phase 1 only'}" for name, s, t in phased)]
    if surface:
        lm = res["lbs_metrics"]["test"]
        srows = [["LBS", "—"] + [f"{lm[k]:.4g}" for k in SURFACE]]
        for name, r in res["variants"].items():
            ok = [run["curve"][-1]["test_metrics"] for run in r["runs"]
                  if run["curve"] and "test_metrics" in run["curve"][-1]]
            if ok:
                srows.append([name, str(r["runs"][0]["curve"][-1]["step"])]
                             + [f"{sum(m[k] for m in ok) / len(ok):.4g}" for k in SURFACE])
        lines += ["", "Test split at the last step, mean over seeds (degrees, degrees, %, rad):",
                  ""]
        lines += table(["variant", "steps", *SURFACE], srows)
    return lines


def _errors(variant: Dict[str, Any]) -> List[Any]:
    """A variant's runs without their timings: what a rerun must reproduce exactly."""
    def drop(d: Dict[str, Any]) -> Dict[str, Any]:
        return {k: v for k, v in d.items() if "seconds" not in k}
    return [dict(drop(run), curve=[drop(p) for p in run.get("curve", [])])
            for run in variant.get("runs", [])]


def _read_curves(path: Path) -> Dict[str, Any]:
    """A ``curves.json`` (``FileNotFoundError`` / ``ValueError`` naming ``path`` when it is
    missing, not JSON or not the results of ``curves``)."""
    if not path.is_file():
        raise FileNotFoundError(f"`files`: {path}: no such file (a curves.json written by "
                                f"`python benchmarks/learning.py curves`)")
    doc = read_json(path, "give a curves.json written by `python benchmarks/learning.py "
                          "curves`")
    if not isinstance(doc.get("variants"), dict):
        raise ValueError(f"`files`: {path}: no 'variants': not the results of `curves`")
    return doc


def merge_curves(files: Sequence[Path], only: Optional[Sequence[str]] = None) -> Dict[str, Any]:
    """The ``curves.json`` of runs made in separate processes (other variants, the same
    dataset, steps and seeds) as one result; the first file's first variant kept is then
    the reference of every paired test.  ``only``: keep these variants alone.  A variant
    in more than one file is kept once where its errors agree exactly (a rerun that
    reproduced it), and refused where they differ."""
    parts = [_read_curves(Path(f)) for f in files]
    res = {k: v for k, v in parts[0].items() if k != "command"}
    res.update(variants={}, sources=[{"file": str(f), "command": p.get("command")}
                                     for f, p in zip(files, parts)])
    for f, part in zip(files, parts):
        for key in ("lbs", "steps", "seeds"):
            if part.get(key) != res.get(key):
                raise ValueError(f"`files`: {f} has another {key} ({part.get(key)} against "
                                 f"{res.get(key)}): not runs that can be compared")
        for name, v in part["variants"].items():
            if only is not None and name not in only:
                continue
            if name in res["variants"]:
                if _errors(res["variants"][name]) != _errors(v):
                    raise ValueError(f"`files`: variant {name!r} is in more than one file, "
                                     f"with other errors")
                continue  # a rerun that reproduced the first to the last digit: kept once
            res["variants"][name] = v
    missing = [name for name in only or () if name not in res["variants"]]
    if missing:
        raise ValueError(f"`only`: {missing} in none of the files")
    return res


def own_objective(module: BaselineModule, item: Any, pred: torch.Tensor) -> Dict[str, float]:
    """A physics-trained baseline's own training loss (its physics terms, inertia against
    ``2 p_{t-1} - p_{t-2}``) on the garment trajectory ``pred [T, V, 3]`` of ``item``'s
    frames, mean over frames ``2..T-1``: ``{"total": ..., term: ...}``."""
    frames = item.select(torch.arange(2, pred.shape[0]))
    with torch.no_grad():
        total, terms = module.loss_fn(loss_inputs(frames, pred[2:], module.dt,
                                                  predicted=2 * pred[1:-1] - pred[:-2],
                                                  ground_truth=False))
    return {"total": float(total), **{k: float(v) for k, v in terms.items()}}


def weighted_mean(rows: Sequence[Dict[str, Any]], key: Callable[[Dict[str, Any]], float],
                  weight: str = "frames") -> float:
    """``key`` of each sequence's row, averaged over sequences weighted by ``weight``
    (frames)."""
    return sum(key(r) * r[weight] for r in rows) / sum(r[weight] for r in rows)


def part_energy(root: Path, bench: Path, seed: int) -> Dict[str, Any]:
    """The HOOD- and NCS-style models a ``garmentgnn bench`` run left in ``bench/models``
    (seed ``seed``), on the test split: their own objective on their predictions against
    the same objective on the LBS garment, beside E_dist."""
    test = whole_sequences(root, "test")
    groups = sorted({(garment_key(r["garment"]), body_key(r["body"])) for r in test.records})
    res: Dict[str, Any] = {"bench": str(bench), "seed": seed, "methods": {}}
    for method in (HOOD, NCS):
        folder = bench / "models" / f"{method}--s{seed}"
        rows, loaded = [], {}
        for i in range(len(test)):
            r = test.records[test.index[i][0]]
            ckpt = (folder / "last.ckpt" if method == HOOD else folder /
                    f"garment{groups.index((garment_key(r['garment']), body_key(r['body'])))}"
                    / "last.ckpt")
            if not ckpt.is_file():
                continue
            if ckpt not in loaded:
                loaded[ckpt] = BaselineModule.load_from_checkpoint(ckpt, map_location="cpu")
            module, item = loaded[ckpt].eval(), test[i]
            pred, lbs = predict(module, item), item.skinned()
            ok = item.get("converged")  # E_dist as the bench scores it: converged frames
            ok = torch.ones(item.num_frames, dtype=torch.bool) if ok is None else ok
            rows.append({"sequence": item.seq_id, "frames": item.num_frames,
                         "scored": int(ok.sum()),
                         "method": own_objective(module, item, pred),
                         "lbs": own_objective(module, item, lbs),
                         "E_dist": float(vertex_distance(pred[ok], item.gt[ok]).mean()),
                         "E_dist_lbs": float(vertex_distance(lbs[ok], item.gt[ok]).mean())})
        res["methods"][method] = rows
    lines = [f"Each method's own objective (its physics terms, mean per frame) on its test "
             f"predictions and on the LBS garment; E_dist in cm over the frames the engine "
             f"converged on, as the bench scores it; bench `{bench.name}`, seed {seed}:", ""]
    out = []
    for method, rows in res["methods"].items():
        if not rows:
            out.append([method, "0", "—", "—", "—", "—", "—", "no checkpoint"])
            continue
        own = weighted_mean(rows, lambda r: r["method"]["total"])
        base = weighted_mean(rows, lambda r: r["lbs"]["total"])
        lower = sum(r["method"]["total"] < r["lbs"]["total"] for r in rows)
        out.append([method, str(len(rows)), f"{own:.4g}", f"{base:.4g}", f"{own / base:.3f}",
                    f"{lower} of {len(rows)}",
                    f"{weighted_mean(rows, lambda r: r['E_dist'], 'scored'):.3f}",
                    f"{weighted_mean(rows, lambda r: r['E_dist_lbs'], 'scored'):.3f}"])
    lines += table(["method", "sequences", "objective", "objective, LBS", "ratio",
                    "sequences below LBS", "E_dist", "E_dist, LBS"], out)
    return {"results": res, "markdown": lines}


def objective_rollout(module: BaselineModule, item: Any, max_iter: int = 200) -> torch.Tensor:
    """The garment trajectory ``[T, V, 3]`` that minimises ``module``'s own objective
    (:func:`own_objective`'s) frame by frame: from the LBS garment of frames 0 and 1,
    each frame's free vertices by L-BFGS from the inertial prediction ``2 x_{t-1} -
    x_{t-2}``, the pinned ones on the LBS garment.  What a physics-trained model that
    fitted its objective exactly at every state would roll out: one implicit-Euler step
    of its objective's cloth a frame."""
    lbs, free = item.skinned(), ~item.pinned_mask()
    xs = [lbs[0].double(), lbs[1].double()]
    for t in range(2, lbs.shape[0]):
        frame, inertial = item.select(torch.tensor([t])), 2 * xs[-1] - xs[-2]
        body = frame.body_pos.double()  # in float64: the line search needs its resolution
        var = inertial[free].clone().requires_grad_(True)
        fixed = lbs[t].double()

        def place(v: torch.Tensor) -> torch.Tensor:
            return fixed.masked_scatter(free.unsqueeze(-1), v)

        opt = torch.optim.LBFGS([var], max_iter=max_iter, history_size=20,
                                tolerance_grad=1e-9, tolerance_change=1e-12,
                                line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            total, _ = module.loss_fn(dataclasses.replace(loss_inputs(
                frame, place(var)[None], module.dt, predicted=inertial[None],
                ground_truth=False), body_pos=body))
            total.backward()
            return total

        opt.step(closure)
        x = place(var.detach())
        if not torch.isfinite(x).all():
            raise FloatingPointError(f"`objective_rollout`: frame {t} of {item.seq_id} is not "
                                     f"finite")
        xs.append(x)
    return torch.stack(xs).to(lbs.dtype)


def part_oracle(root: Path, variants: Sequence[str], test_sequences: Optional[int],
                max_iter: int = 200) -> Dict[str, Any]:
    """For each physics-trained variant (its objective: the loss terms and weights of
    its configuration), :func:`objective_rollout` on the test sequences against the
    LBS garment: E_dist (the frames the engine converged on, as the bench scores it),
    its objective and how far it is from LBS at the last frame."""
    wrong = [name for name in variants if VARIANTS[name].get("baseline") != HOOD]
    if wrong:
        raise ValueError(f"`variants`: {wrong} not trained on a physics objective; give "
                         f"HOOD-style variants")
    test = whole_sequences(root, "test")
    picked = evenly(list(range(len(test))), test_sequences or len(test))
    dims = datamodule(root).dims
    res: Dict[str, Any] = {"max_iter": max_iter, "variants": {}}
    out = []
    for name in variants:
        v = VARIANTS[name]
        module = baseline(v["baseline"], dims, overrides=v.get("module")).eval()
        module.loss_fn.compile_search = False  # the same search, not compiled per shape
        rows = []
        for i in picked:
            item, t = test[i], time.perf_counter()
            pred, lbs = objective_rollout(module, item, max_iter), item.skinned()
            ok = item.get("converged")
            ok = torch.ones(item.num_frames, dtype=torch.bool) if ok is None else ok
            rows.append({"sequence": item.seq_id, "frames": item.num_frames,
                         "scored": int(ok.sum()), "seconds": time.perf_counter() - t,
                         "oracle": own_objective(module, item, pred),
                         "lbs": own_objective(module, item, lbs),
                         "E_dist": float(vertex_distance(pred[ok], item.gt[ok]).mean()),
                         "E_dist_lbs": float(vertex_distance(lbs[ok], item.gt[ok]).mean()),
                         "from_lbs_last": float((pred[-1] - lbs[-1]).norm(dim=-1).mean())})
            r = rows[-1]
            print(f"oracle {name}, {item.seq_id}: E_dist {r['E_dist']:.3f} cm, LBS "
                  f"{r['E_dist_lbs']:.3f} cm ({r['seconds']:.0f} s)", flush=True)
        res["variants"][name] = {"settings": v, "rows": rows}
        e = weighted_mean(rows, lambda r: r["E_dist"], "scored")
        el = weighted_mean(rows, lambda r: r["E_dist_lbs"], "scored")
        try:
            w = scoring.wilcoxon({r["sequence"]: r["E_dist"] for r in rows},
                                 {r["sequence"]: r["E_dist_lbs"] for r in rows})
            p = f"{w['p']:.2g}"
        except ValueError:
            p = "—"
        objective = (sum(r["oracle"]["total"] for r in rows)
                     / sum(r["lbs"]["total"] for r in rows))
        out.append([name, str(len(rows)), f"{e:.3f}", f"{el:.3f}", f"{e / el:.3f}",
                    f"{sum(r['E_dist'] < r['E_dist_lbs'] for r in rows)} of {len(rows)}", p,
                    f"{objective:.3f}",
                    f"{100 * sum(r['from_lbs_last'] for r in rows) / len(rows):.1f}"])
    lines = [f"The trajectory that minimises each objective frame by frame (L-BFGS, at most "
             f"{max_iter} iterations a frame, from the LBS garment of frames 0 and 1) on "
             f"{len(picked)} of {len(test)} test sequences; E_dist in cm over the frames the "
             f"engine converged on, frame-weighted; p: paired Wilcoxon test against LBS over "
             f"sequences:", ""]
    lines += table(["objective of", "sequences", "E_dist", "E_dist, LBS", "x LBS",
                    "sequences below LBS", "p", "objective / LBS's",
                    "from LBS at the last frame (cm)"], out)
    return {"results": res, "markdown": lines}


#: the curves plot's top (E_dist / LBS): a diverging variant is clipped there and says so
#: in the legend, so that it does not flatten the differences near 1
PLOT_TOP = 1.5


def plot_curves(res: Dict[str, Any], path: Path) -> None:
    """E_dist / LBS against steps, train and test.  Where some variant stays below
    :data:`PLOT_TOP` the axis is linear and diverging variants are clipped (so they do
    not flatten the differences near 1); where none does, the axis is logarithmic."""
    plt = pyplot()
    rows = len(res["variants"])  # legend lines, below each panel (not over its curves)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2 + 0.16 * rows), sharey=True)
    n = len(res.get("seeds", [0]))  # files written before the seeds: one run, "curve"
    curves = {name if n == 1 else f"{name} (mean of {n} seeds)":
              mean_curve(r.get("runs", [r])) for name, r in res["variants"].items()}
    curves = {name: c for name, c in curves.items() if c}
    clip = any(max(row[s] / res["lbs"][s] for row in c) <= PLOT_TOP
               for c in curves.values() for s in ("train", "test"))
    low, high = PLOT_TOP, 1.0
    for ax, split in zip(axes, ("train", "test")):
        for name, c in curves.items():
            y = [row[split] / res["lbs"][split] for row in c]
            low, high = min(low, min(y)), max(high, min(max(y), PLOT_TOP))
            clipped = clip and max(y) > PLOT_TOP
            label = f"{name} (up to {max(y):.1f}x: clipped)" if clipped else name
            ax.plot([row["step"] for row in c], [min(v, PLOT_TOP) if clip else v for v in y],
                    marker=".", label=label)
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_title(f"{split} sequences (LBS {res['lbs'][split]:.2f} cm = 1)")
        ax.set_xlabel("optimizer steps")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    if clip:
        pad = 0.05 * (high - low) + 0.005
        axes[0].set_ylim(max(0.0, low - pad), high + pad)
    else:
        axes[0].set_yscale("log")
    axes[0].set_ylabel("E_dist / LBS" + ("" if clip else " (log scale)"))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """The command line, checked: a repeated list flag (``--seed 0 --seed 1``) adds up,
    a value given twice, a count below 1, ``--every`` over ``--steps``, a missing
    dataset or ``--curves`` file end in one ``error:`` line (exit status 2)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=HelpFormatter)
    ap.add_argument("parts", nargs="+", choices=("grad", "overfit", "curves", "energy", "oracle",
                                                  "merge"),
                    help="what to run (merge: the `curves` results of --curves as one table)")
    ap.add_argument("--data", default=None,
                    help="a generated dataset folder (every part but merge)")
    ap.add_argument("--curves", nargs="+", default=None, action=Accumulate, type=existing_file,
                    help="merge: curves.json files of the same dataset, steps and seeds")
    ap.add_argument("--bench", default=None,
                    help="energy: the output folder of a `garmentgnn bench` run on --data")
    add_output_args(ap, RESULTS, "folder for <part>.json, .md and .png")
    ap.add_argument("--steps", type=int_at_least(1), default=300,
                    help="optimizer steps (overfit, curves)")
    ap.add_argument("--every", type=int_at_least(1), default=50,
                    help="steps between measurements (at most --steps)")
    ap.add_argument("--variants", nargs="+", default=None, choices=list(VARIANTS),
                    action=Accumulate,
                    help="GarTrans settings compared by `curves` (default: all), added to "
                         "`grad` and `overfit` (default: none), kept by `merge` (default: "
                         "all); the HOOD-style objectives of `oracle` (default: its "
                         "configuration's and the silk energies)")
    ap.add_argument("--methods", nargs="+", default=None, action=Accumulate,
                    help="the methods `grad` and `overfit` run (default: every learned "
                         "method of the bench)")
    ap.add_argument("--train-sequences", type=int_at_least(1), default=6,
                    help="training sequences measured by `curves` (evenly spaced)")
    ap.add_argument("--test-sequences", type=int_at_least(1), default=None,
                    help="test sequences measured by `curves` and `oracle` (evenly spaced; "
                         "default: all)")
    ap.add_argument("--seed", type=int, nargs="+", default=[0], action=Accumulate,
                    help="training seeds (curves: each variant once per seed; repeat the "
                         "flag or list several); the bench run's seed (energy: one)")
    ap.add_argument("--surface", action="store_true",
                    help="curves: also the normal, edge-length and curvature errors")
    ap.add_argument("--threads", type=int_at_least(1), default=1, help="torch threads")
    args = ap.parse_args(argv)
    for flag in ("parts", "seed", "variants", "methods", "curves"):
        check_unique(ap, getattr(args, flag), "--" + flag if flag != "parts" else "parts")
    if args.every > args.steps and set(args.parts) & {"overfit", "curves"}:
        ap.error(f"--every {args.every}: more than --steps {args.steps}; nothing would be "
                 f"measured after step 0")
    if args.data is None and set(args.parts) - {"merge"}:
        raise SystemExit("error: give --data DIR, the generated dataset to train on")
    if args.data is not None and set(args.parts) - {"merge"}:
        try:
            read_manifest(Path(args.data).expanduser())
        except (OSError, ValueError) as err:
            raise SystemExit(f"error: --data {err}") from None
    if "merge" in args.parts and not args.curves:
        raise SystemExit("error: merge: give --curves FILE FILE ..., `curves` results")
    for f in (args.curves or []) if "merge" in args.parts else []:
        try:
            _read_curves(Path(f))
        except (OSError, ValueError) as err:
            raise SystemExit(f"error: {_curves_message(err)}") from None
    return args


def _curves_message(err: Exception) -> str:
    """An error of :func:`merge_curves` with the flag named."""
    msg = str(err).replace("`files`", "--curves")
    return msg if msg.startswith("--") else "--curves " + msg


def main(argv: Optional[Sequence[str]] = None) -> None:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    root, out = Path(args.data or "."), output_path(args, RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    command = command_line("benchmarks/learning.py", argv)
    for part in args.parts:
        if part == "grad":
            r = part_grad(root, args.methods, args.variants or ())
        elif part == "overfit":
            r = part_overfit(root, args.steps, args.every, args.methods,
                             args.variants or ())
        elif part == "energy":
            if args.bench is None:
                raise SystemExit("error: `energy` reads a bench run's models: give --bench DIR")
            if len(args.seed) != 1:
                raise SystemExit("error: `energy` reads one bench run's models: give one --seed")
            r = part_energy(root, Path(args.bench).expanduser(), args.seed[0])
        elif part == "oracle":
            try:
                r = part_oracle(root, args.variants or ["HOOD-style",
                                                        "HOOD-style, silk energies"],
                                args.test_sequences)
            except ValueError as err:
                raise SystemExit(f"error: {err}") from None
        elif part == "merge":
            try:
                res = merge_curves([Path(f).expanduser() for f in args.curves],
                                   args.variants)
            except (OSError, ValueError) as err:
                raise SystemExit(f"error: {_curves_message(err)}") from None
            r = {"results": res, "markdown": [
                "Merged from:", ""] + [f"- `{src['command']}`" for src in res["sources"]]
                + [""] + curves_markdown(res, "lbs_metrics" in res)}
            plot_curves(res, out / f"{part}.png")
        else:
            r = part_curves(root, args.steps, args.every, args.variants or list(VARIANTS),
                            args.train_sequences, args.seed, args.surface,
                            args.test_sequences)
            plot_curves(r["results"], out / f"{part}.png")
        (out / f"{part}.json").write_text(json.dumps({"command": command, **r["results"]},
                                                     indent=1))
        (out / f"{part}.md").write_text(f"# {part}\n\n`{command}`\n\n" +
                                        "\n".join(r["markdown"]) + "\n")
        print("\n".join(r["markdown"]), flush=True)


if __name__ == "__main__":
    main()
