"""The learned methods as ``garmentgnn bench`` builds them, from their packaged recipes
(:func:`~garmentgnn.training.load_recipe`), trained through the recipe's Lightning
``Trainer`` and measured on whole sequences while they train (:class:`Probe`), and the
parts that train them: ``grad``, ``overfit`` and ``curves``."""
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
from garmentgnn.bench.methods import DA, DATA, FULL, GARTRANS, HOOD, NCS, recipe_of
from garmentgnn.bench.tables import slug, table
from garmentgnn.models import GarTrans
from garmentgnn.metrics.garment_metrics import evaluate_inputs, vertex_distance
from garmentgnn.training import ProgressiveSchedule, Recipe, load_recipe
from garmentgnn.training.diagnostics import branch_gradients, dead_branches

from .curves import SURFACE, curves_markdown
from .variants import VARIANTS

#: the settings of :class:`ProgressiveSchedule` that the bench gives full GarTrans
#: (its defaults; the windows are each run's)
SCHEDULE: Dict[str, Any] = {k: p.default for k, p in inspect.signature(
    ProgressiveSchedule.__init__).parameters.items() if k not in ("self", "window", "window2")}


# ------------------------------------------------------------------ building methods
def data_settings(root: Path, seed: int = 0, split: str = "train",
                  data: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """The bench's data settings (``root``'s ``split``, no validation split, seed
    ``seed``) with ``data``'s (e.g. ``history``): :func:`load_recipe`'s ``data``."""
    return dict(root=root, val_split=None, seed=seed, train_split=split, cache_size=64,
                **(data or {}))


def gartrans(root: Path, method: str = FULL, overrides: Optional[Dict[str, Any]] = None,
             schedule: Union[bool, Dict[str, Any]] = False, seed: int = 0,
             data: Optional[Dict[str, Any]] = None) -> Recipe:
    """GarTrans variant ``method``'s recipe on ``root`` (:func:`data_settings`) with
    ``overrides`` (settings of the model or of the module, by name) and the module's
    ``schedule`` (default: none, phase 1's losses throughout; a dict:
    :class:`ProgressiveSchedule` arguments)."""
    model_args = inspect.signature(GarTrans.__init__).parameters
    settings: Dict[str, Any] = {"model.init_args.schedule": schedule}
    for k, v in (overrides or {}).items():
        at = "model.init_args.model.init_args" if k in model_args else "model.init_args"
        settings[f"{at}.{k}"] = v
    return load_recipe(recipe_of(method), args=["--seed_everything", str(seed)],
                       data=data_settings(root, seed, data=data), set=settings)


def _onto(value: Any) -> Any:
    """A ``load_recipe`` setting: a mapping's keys replace the recipe's (the rest of the
    recipe's mapping kept), any other value replaces it."""
    return (lambda old: dict(old or {}, **value)) if isinstance(value, dict) else value


def baseline(method: str, root: Path, overrides: Optional[Dict[str, Any]] = None,
             seed: int = 0, data: Optional[Dict[str, Any]] = None) -> Recipe:
    """Baseline ``method``'s recipe on ``root`` (:func:`data_settings`); ``overrides``:
    module settings by name, ``model`` the model's; a mapping (``loss``) goes onto the
    recipe's key by key."""
    settings: Dict[str, Any] = {}
    for k, v in (overrides or {}).items():
        if k == "model":
            settings.update({f"model.init_args.model.init_args.{mk}": mv
                             for mk, mv in v.items()})
        else:
            settings[f"model.init_args.{k}"] = _onto(v)
    return load_recipe(recipe_of(method), args=["--seed_everything", str(seed)],
                       data=data_settings(root, seed, data=data), set=settings)


def methods(root: Path, item: Any, only: Optional[Sequence[str]] = None,
            variants: Sequence[str] = ()) -> Dict[str, Callable[[], Recipe]]:
    """Every learned method of the bench (or those named in ``only``), freshly built
    (phase-1 losses for GarTrans), and GarTrans with each of ``variants``' settings.
    NCS-style, a model of one garment, is built for ``item``'s (its sequence the data)."""
    out: Dict[str, Callable[[], Recipe]] = {m: (lambda m=m: gartrans(root, m)) for m in GARTRANS}
    for m in (DA, HOOD):
        out[m] = lambda m=m: baseline(m, root)
    out[NCS] = lambda: baseline(NCS, root, data={"train_ids": [item.seq_id]})
    out = {k: v for k, v in out.items() if only is None or k in only}
    for v in variants:
        if "baseline" in VARIANTS[v]:  # a baseline's own settings: see `only`
            out[v] = lambda v=v: baseline(VARIANTS[v]["baseline"], root,
                                          VARIANTS[v].get("module"))
        else:
            out[f"GarTrans, {v}"] = lambda v=v: gartrans(root, overrides=VARIANTS[v].get("model"))
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


def _trainer(recipe: Recipe, steps: int, callbacks=(), folder: Optional[Path] = None,
             every: int = 0, **kw) -> L.Trainer:
    """``recipe``'s Trainer on the CPU for ``steps`` optimizer steps (no epoch limit, no
    log, no validation); with ``folder``, ``last.ckpt`` there every ``every`` steps (what
    :func:`part_curves` resumes from) instead of the recipe's checkpoints."""
    callbacks = list(callbacks)
    if folder is not None:
        callbacks.append(ModelCheckpoint(dirpath=folder, save_last=True, save_top_k=0,
                                         every_n_train_steps=every))
    return recipe.trainer(max_steps=steps, max_epochs=-1, accelerator="cpu", devices=1,
                          logger=False, enable_checkpointing=folder is not None,
                          enable_progress_bar=False, enable_model_summary=False,
                          limit_val_batches=0, num_sanity_val_steps=0, callbacks=callbacks,
                          **kw)


def first_chunk(root: Path) -> Any:
    """The first training chunk of ``root`` with the bench's data settings."""
    return gartrans(root).datamodule.train_set[0]


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
    item = first_chunk(root)
    res: Dict[str, Any] = {}
    for name, make in methods(root, item, only, variants).items():
        rep = branch_gradients(make().module, item)  # built at seed 0
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
    item = first_chunk(root)
    lbs = lbs_error([item])
    res: Dict[str, Any] = {"chunk": {"seq_id": item.seq_id, "frames": item.num_frames,
                                     "vertices": item.num_vertices}, "lbs": lbs, "methods": {}}
    for name, make in methods(root, item, only, variants).items():
        recipe = make()  # built at seed 0
        probe = Probe({"chunk": [item]}, every, name)
        loader = torch.utils.data.DataLoader(_Fixed(item, steps), batch_size=None,
                                             collate_fn=lambda x: x)
        t = time.perf_counter()
        try:
            _trainer(recipe, steps, [probe]).fit(recipe.module, loader)
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
            # the bench's schedule of full GarTrans, with v's settings (none without them)
            sched = ({**SCHEDULE, "window2": v["schedule"].get("window"), **v["schedule"]}
                     if "schedule" in v else False)
            model = dict(v.get("model") or {})
            if v.get("anneal"):  # the cosine's period: the run's epochs
                model["t_max"] = math.ceil(steps / v["trainer"]["limit_train_batches"])
            recipe = (baseline(v["baseline"], root, v.get("module"), seed, data)
                      if "baseline" in v else
                      gartrans(root, overrides=model, schedule=sched, seed=seed, data=data))
            probe = Probe(sequences(data.get("history")) if data else sets, every, name, surface)
            folder = None if runs_dir is None else runs_dir / f"{slug(name)}-{tag}--s{seed}"
            last_ckpt = None if folder is None else folder / "last.ckpt"
            trainer = _trainer(recipe, steps, [probe], folder, every, **v.get("trainer", {}))
            try:
                trainer.fit(
                    recipe.module, recipe.datamodule,
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
