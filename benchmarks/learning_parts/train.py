"""The learned methods as ``garmentgnn bench`` builds them, trained through the same
Lightning ``Trainer`` and measured on whole sequences while they train (:class:`Probe`),
and the parts that train them: ``grad``, ``overfit`` and ``curves``."""
from __future__ import annotations

import hashlib
import inspect
import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Union

import lightning as L
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from garmentgnn.data import SequenceChunks
from garmentgnn.data.store import read_manifest
from garmentgnn.bench import scoring
from garmentgnn.bench.methods import (BASELINES, DA, DATA, FULL, GARTRANS, HOOD, NCS,
                                        variant_settings)
from garmentgnn.bench.tables import slug, table
from garmentgnn.models import GarTrans
from garmentgnn.metrics.garment_metrics import evaluate_inputs, vertex_distance
from garmentgnn.training import (BaselineModule, GarmentDataModule, GarTransModule,
                                 ProgressiveSchedule)
from garmentgnn.training.configs import instantiate, merge
from garmentgnn.training.diagnostics import branch_gradients, dead_branches

from .curves import SURFACE, curves_markdown
from .variants import VARIANTS


# ------------------------------------------------------------------ building methods
def datamodule(root: Path, seed: int = 0, split: str = "train",
               data: Optional[Dict[str, Any]] = None) -> GarmentDataModule:
    """The bench's data settings, with ``data``'s overrides (e.g. ``history``)."""
    return GarmentDataModule(root, val_split=None, seed=seed, train_split=split, cache_size=64,
                             **dict(DATA, **(data or {})))


def gartrans(dims: Dict[str, int], method: str = "GarTrans (SAT)",
             overrides: Optional[Dict[str, Any]] = None,
             schedule: Union[bool, Dict[str, Any]] = False) -> GarTransModule:
    """GarTrans variant ``method`` as the bench builds it, with ``overrides`` (settings of
    the model or of the module, by name) and the module's ``schedule`` (default: none,
    phase 1's losses throughout; a dict: :class:`ProgressiveSchedule` arguments)."""
    spec, _ = variant_settings(method)
    ov, model_args = overrides or {}, inspect.signature(GarTrans.__init__).parameters
    spec = merge(spec, {"init_args": {"schedule": schedule,
                                      **{k: v for k, v in ov.items() if k not in model_args},
                                      "model": {"init_args": {k: v for k, v in ov.items()
                                                              if k in model_args}}}})
    return instantiate(spec, dims)


def baseline(method: str, dims: Dict[str, int], num_vertices: Optional[int] = None,
             overrides: Optional[Dict[str, Any]] = None) -> BaselineModule:
    """Baseline ``method`` as the bench builds it; ``overrides``' sections (``model``:
    the model's arguments, ``loss``) are merged, other values replace."""
    ov = dict(overrides or {})
    ov["model"] = {"init_args": ov.get("model", {})}
    spec = merge(BASELINES[method], {"init_args": ov})
    return instantiate(spec, dict(dims, num_vertices=num_vertices))


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


def whole_sequences(root: Path, split: str, history: Optional[int] = None,
                    ids: Optional[Sequence[str]] = None) -> SequenceChunks:
    """``split``'s sequences (``ids``: these alone), one item each, with the bench's data
    settings (``history``: another pose history length)."""
    return SequenceChunks(root, split, chunk=10 ** 9, history=history or DATA["history"],
                          nystrom_dim=DATA["nystrom_dim"], num_landmarks=DATA["num_landmarks"],
                          cache_size=64, ids=ids)


class _Fixed(torch.utils.data.Dataset):
    """One chunk, ``n`` times (an epoch of ``n`` steps on the same chunk)."""

    def __init__(self, item, n: int) -> None:
        self.item, self.n = item, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        return self.item


def _trainer(steps: int, callbacks=(), folder: Optional[Path] = None, every: int = 0,
             **kw) -> L.Trainer:
    """A CPU Trainer for ``steps`` optimizer steps; with ``folder``, ``last.ckpt`` there
    every ``every`` steps (what :func:`part_curves` resumes from)."""
    callbacks = list(callbacks)
    if folder is not None:
        callbacks.append(ModelCheckpoint(dirpath=folder, save_last=True, save_top_k=0,
                                         every_n_train_steps=every))
    return L.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False,
                     enable_checkpointing=folder is not None, enable_progress_bar=False,
                     enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                     callbacks=callbacks, **kw)


def predict(module: L.LightningModule, item) -> torch.Tensor:
    with torch.no_grad():
        out = module(item)
    return out["final"] if isinstance(out, dict) else out


def frame_errors(pred: torch.Tensor, item) -> torch.Tensor:
    """E_dist (cm) of each of ``item``'s valid ground-truth frames (``item.valid``: every
    frame where the item does not say)."""
    err = vertex_distance(pred, item.gt)  # [T]
    valid = item.get("valid")
    return err if valid is None else err[valid]


def split_error(errors: Sequence[torch.Tensor]) -> float:
    """The frame mean of per-sequence :func:`frame_errors` (cm)."""
    return float(torch.cat(list(errors)).mean())


class Probe(L.Callback):
    """E_dist (cm, on valid frames) of ``sets`` (name -> list of whole-sequence items)
    every ``every`` optimizer steps, and at step 0; per sequence its mean and its valid
    frame count."""

    def __init__(self, sets: Dict[str, List[Any]], every: int, label: str = "",
                 surface: bool = False) -> None:
        self.sets, self.every, self.label, self.surface = sets, every, label, surface
        self.rows: List[Dict[str, Any]] = []
        self.t0 = time.perf_counter()
        self.train_seconds = 0.0
        #: wall seconds of the run before this process (a resumed run)
        self.seconds_before = 0.0
        self.started = time.perf_counter()

    def state_dict(self) -> Dict[str, Any]:  # kept in the run's checkpoint
        return {"rows": self.rows, "train_seconds": self.train_seconds,
                "seconds": self.seconds()}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.rows, self.train_seconds = list(state["rows"]), float(state["train_seconds"])
        self.seconds_before = float(state["seconds"])
        self.started = time.perf_counter()

    def seconds(self) -> float:
        """Wall seconds of the run so far, a resumed run's earlier processes included."""
        return self.seconds_before + time.perf_counter() - self.started

    def measure(self, module: L.LightningModule, step: int) -> None:
        t = time.perf_counter()
        was = module.training
        module.eval()
        row: Dict[str, Any] = {"step": step, "train_seconds": self.train_seconds}
        for name, items in self.sets.items():
            preds = [predict(module, it) for it in items]
            errs = [frame_errors(p, it) for p, it in zip(preds, items)]
            row[f"{name}_sequences"] = {it.seq_id: float(e.mean()) for it, e in zip(items, errs)
                                        if e.numel()}
            row[name] = split_error(errs)
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
        self.t0 = time.perf_counter() - self.train_seconds
        if not self.rows:  # a resumed run measured its start before
            self.measure(pl_module, 0)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.train_seconds = time.perf_counter() - self.t0
        step = trainer.global_step
        if step % self.every == 0 and (not self.rows or self.rows[-1]["step"] != step):
            self.measure(pl_module, step)


def lbs_error(items: Sequence[Any]) -> float:
    """LBS's E_dist (cm) on ``items``' valid frames."""
    return split_error([frame_errors(it.skinned(), it) for it in items])


def sequence_facts(items: Sequence[Any], lbs_errors: Sequence[torch.Tensor],
                   records: Dict[str, Dict[str, Any]]) -> Dict[str, Dict[str, Any]]:
    """Per item: its held-out group, valid frame count and LBS's E_dist (cm) there, from
    the items' LBS :func:`frame_errors` (``lbs_errors``)."""
    out = {}
    for it, e in zip(items, lbs_errors):
        if e.numel():
            out[it.seq_id] = {"group": scoring.group_of(records[it.seq_id].get("held_out", []))
                              or "nothing held out", "frames": int(e.numel()),
                              "lbs": float(e.mean())}
    return out


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
                surface: bool = False, test_sequences: Optional[int] = None,
                done: Optional[Path] = None) -> Dict[str, Any]:
    """Each variant trained once per seed; the table gives the mean over seeds at the last
    step and, against the first variant, a paired Wilcoxon test over (seed, test sequence).
    ``test_sequences``: that many of the test split, taken in turn from each held-out
    group (:func:`~garmentgnn.bench.scoring.stratified`; default: all).  Errors are on
    valid ground-truth frames.  ``done``: a file that keeps every finished (variant,
    seed) run, beside a folder of each run's checkpoint (``runs/``, every ``every``
    steps, its curve in it), so that the part run again with the same settings after an
    interruption keeps the finished runs and resumes the one it was in."""
    dims = datamodule(root, seeds[0]).dims
    records = {r["id"]: r for r in read_manifest(root)["items"]}
    test_ids = None
    if test_sequences:
        test_ids = scoring.stratified([r for r in records.values() if r["split"] == "test"
                                       and r["status"] == "ok"], test_sequences)

    def sequences(history: Optional[int] = None) -> Dict[str, List[Any]]:
        test = whole_sequences(root, "test", history, test_ids)
        train = whole_sequences(root, "train", history)
        return {"train": evenly(train, train_sequences), "test": list(test)}

    sets = sequences()
    lbs_errs = {k: [frame_errors(it.skinned(), it) for it in v] for k, v in sets.items()}
    lbs = {k: split_error(e) for k, e in lbs_errs.items()}
    res: Dict[str, Any] = {"lbs": lbs, "steps": steps, "seeds": list(seeds), "variants": {},
                           "sequences": {k: sequence_facts(v, lbs_errs[k], records)
                                         for k, v in sets.items()}}
    if surface:
        res["lbs_metrics"] = {k: Probe.weighted([(evaluate_inputs(it.skinned(), it), it)
                                                  for it in v]) for k, v in sets.items()}
    key = {"data": str(root), "steps": steps, "every": every, "train_sequences":
           train_sequences, "test_sequences": test_sequences, "surface": surface}
    # each run's checkpoints, under a name of these settings
    runs_dir = None if done is None else done.parent / "runs" / hashlib.sha1(
        json.dumps(key, sort_keys=True).encode()).hexdigest()[:10]
    kept: Dict[str, Any] = {}
    if done is not None and done.is_file():
        saved = json.loads(done.read_text())
        kept = saved["runs"] if saved.get("key") == key else {}
    for name in variants:
        v = VARIANTS[name]
        data = v.get("data")
        runs = []
        # a kept run and a checkpoint count only for these very settings
        settings = json.loads(json.dumps(v))
        tag = hashlib.sha1(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:8]
        for seed in seeds:
            old = [r for r in kept.get(name, []) if r["seed"] == seed and r["status"] == "ok"
                   and r.get("settings") == settings]
            if old:  # finished before an interruption
                runs.append(old[0])
                continue
            L.seed_everything(seed, verbose=False)
            # the bench's schedule of full GarTrans, with v's settings (none without them)
            sched = ({**variant_settings(FULL)[1], "window2": v["schedule"].get("window"),
                      **v["schedule"]} if "schedule" in v else False)
            module = (baseline(v["baseline"], dims, overrides=v.get("module")) if "baseline" in v
                      else gartrans(dims, overrides=v.get("model"), schedule=sched))
            if v.get("anneal"):  # the cosine's period: the run's epochs
                module.hparams.t_max = math.ceil(steps / v["trainer"]["limit_train_batches"])
            probe = Probe(sequences(data.get("history")) if data else sets, every, name, surface)
            folder = None if runs_dir is None else runs_dir / f"{slug(name)}-{tag}--s{seed}"
            last_ckpt = None if folder is None else folder / "last.ckpt"
            trainer = _trainer(steps, [probe], folder, every, **v.get("trainer", {}))
            try:
                trainer.fit(
                    module, datamodule(root, seed, data=data),
                    ckpt_path=last_ckpt if last_ckpt is not None and last_ckpt.is_file()
                    else None)
                status = "ok"
            except Exception as err:
                status = f"{type(err).__name__}: {err}"
            runs.append({"seed": seed, "curve": probe.rows, "status": status,
                         "seconds": probe.seconds(),
                         **({"transitions": getattr(ProgressiveSchedule.of(trainer),
                                                    "transitions", {})} if sched else {})})
            last = probe.rows[-1] if probe.rows else {}
            print(f"curves {name}, seed {seed}: " + ", ".join(
                f"{k} {last.get(k, math.nan) / lbs[k]:.3f}" for k in sets)
                + f" x LBS ({status})", flush=True)
            if done is not None:
                kept.setdefault(name, []).append(dict(runs[-1], settings=settings))
                done.write_text(json.dumps({"key": key, "runs": kept}))
        res["variants"][name] = {"settings": v, "runs": runs}
    return {"results": res, "markdown": curves_markdown(res, surface)}
