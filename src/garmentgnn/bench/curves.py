"""Learning curves inside ``garmentgnn bench``: a learned method's validation E_dist
against optimizer steps and training wall time, recorded while it trains
(:class:`LearningCurve`), and a snapshot of its weights at one fixed step, so that the
methods are compared at equal steps as well as at equal wall time.

The report reads the curves (:func:`markdown`, :func:`plot`): whether each run reached a
validation plateau (:func:`plateau`), at which epoch, and every method's test error at
the equal-step snapshot beside its error at the end of the equal time budget.  The bench's
other training-time helpers live here too: :class:`TrainClock` (training wall time and
epochs, kept in checkpoints) and :func:`quiet_lightning`.
"""
from __future__ import annotations

import contextlib
import io
import logging
import statistics
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence

import lightning as L
import torch

from garmentgnn._files import atomic_write_bytes
from garmentgnn._plotting import pyplot
from garmentgnn.bench import scoring
from garmentgnn.bench.tables import fmt, save_figure, table
from garmentgnn.training import TimeBudget

__all__ = ["LearningCurve", "TrainClock", "markdown", "plateau", "plot", "quiet_lightning"]

#: the record kind of :mod:`garmentgnn.bench.learned` (restated: that module imports this)
_KIND = "learned"
#: :func:`plateau`'s defaults: the last quarter of the steps improves the best validation
#: error by less than 2%
TAIL, TOLERANCE = 0.25, 0.02
_now = time.perf_counter


@contextlib.contextmanager
def quiet_lightning() -> Iterator[None]:
    """Lightning's info messages and possible-user warnings off inside the block."""
    logger = logging.getLogger("lightning.pytorch")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", module=r"lightning\..*")
            warnings.filterwarnings("ignore", message=r".*(num_workers|does not have many "
                                                      r"workers|Checkpoint directory).*")
            yield
    finally:
        logger.setLevel(level)


class TrainClock(L.Callback):
    """Wall time of the training epochs and their count, kept in the checkpoint (so a
    resumed run reports the total); ``restored_epochs``: epochs done before this fit."""

    def __init__(self) -> None:
        self.seconds, self.epochs, self.restored_epochs = 0.0, 0, 0
        self._t0 = 0.0

    def state_dict(self) -> Dict[str, Any]:
        return {"seconds": self.seconds, "epochs": self.epochs}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.seconds = float(state["seconds"])
        self.epochs = self.restored_epochs = int(state["epochs"])

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._t0 = time.perf_counter()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.seconds += time.perf_counter() - self._t0
        self.epochs += 1


class LearningCurve(L.Callback):
    """Validation error every ``every`` optimizer steps (and before the first), against
    the steps and the training wall time, validation time not counted (nor in
    ``budget``'s time); with ``snapshot_step``, the module's ``state_dict`` at that step
    written to ``snapshot_path``.  Kept in checkpoints: a resumed fit continues its curve.

    Args:
        every: optimizer steps between two points.
        evaluate: the validation E_dist (cm) of the module, called in ``eval`` mode under
            ``torch.no_grad()``.
        snapshot_step, snapshot_path: where the equal-step weights go (both or neither).
        budget: the fit's :class:`TimeBudget`, paused while validating.
        train_evaluate: the same error on (a subset of) the training split, recorded
            beside it as ``train_E_dist`` (its time counted as validation time).
        train_chunks: the training split's chunks (an epoch of the whole split), kept in
            :meth:`to_json` so that a plot can read ``chunks`` as epochs.

    Attributes:
        points: ``{"step", "epoch", "chunks", "seconds", "E_dist"}`` per validation
            (``chunks``: training chunks seen, a batch of ``N`` chunks counting ``N``;
            ``epoch``: the trainer's, which counts limited epochs), and
            ``train_E_dist`` with ``train_evaluate``.
        seconds: training wall time so far (validation excluded).
        eval_seconds: validation wall time so far.
    """

    def __init__(self, every: int, evaluate: Callable[[L.LightningModule], float],
                 snapshot_step: Optional[int] = None, snapshot_path=None,
                 budget: Optional[TimeBudget] = None,
                 train_evaluate: Optional[Callable[[L.LightningModule], float]] = None,
                 train_chunks: Optional[int] = None) -> None:
        if not isinstance(every, int) or isinstance(every, bool) or every < 1:
            raise ValueError(f"`every`: expected a positive number of steps, got {every!r}")
        if (snapshot_step is None) != (snapshot_path is None):
            raise ValueError("`snapshot_step`, `snapshot_path`: give both or neither")
        if snapshot_step is not None and (not isinstance(snapshot_step, int)
                                          or snapshot_step < 1):
            raise ValueError(f"`snapshot_step`: expected a positive int, got {snapshot_step!r}")
        self.every, self.evaluate, self.budget = every, evaluate, budget
        self.train_evaluate, self.train_chunks = train_evaluate, train_chunks
        self.snapshot_step = snapshot_step
        self.snapshot_path = None if snapshot_path is None else Path(snapshot_path)
        self.points: List[Dict[str, float]] = []
        self.seconds = self.eval_seconds = 0.0
        self.chunks = 0
        self._t0: Optional[float] = None

    def state_dict(self) -> Dict[str, Any]:
        return {"points": list(self.points), "seconds": self.seconds,
                "eval_seconds": self.eval_seconds, "chunks": self.chunks}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.points = [dict(p) for p in state["points"]]
        self.seconds, self.eval_seconds = float(state["seconds"]), float(state["eval_seconds"])
        self.chunks = int(state.get("chunks", 0))

    def to_json(self) -> Dict[str, Any]:
        """What a bench record keeps."""
        return {"every": self.every, "points": self.points, "eval_seconds": self.eval_seconds,
                "snapshot_step": self.snapshot_step, "train_chunks": self.train_chunks}

    def _validate(self, trainer: L.Trainer, module: L.LightningModule) -> None:
        t = _now()
        with self.budget.paused() if self.budget is not None else contextlib.nullcontext():
            was = module.training
            module.eval()
            point = {"step": int(trainer.global_step), "epoch": int(trainer.current_epoch),
                     "chunks": self.chunks, "seconds": self.seconds}
            try:
                with torch.no_grad():
                    point["E_dist"] = float(self.evaluate(module))
                    if self.train_evaluate is not None:
                        point["train_E_dist"] = float(self.train_evaluate(module))
            finally:
                module.train(was)
        self.eval_seconds += _now() - t
        self.points.append(point)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.points:
            self._validate(trainer, pl_module)

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._t0 = _now()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any,
                           batch: Any, batch_idx: int) -> None:
        if self._t0 is not None:
            self.seconds += _now() - self._t0
        self.chunks += getattr(batch, "num_chunks", 1)
        step = int(trainer.global_step)
        if step == self.snapshot_step:
            buf = io.BytesIO()
            torch.save({"step": step, "state_dict": pl_module.state_dict()}, buf)
            atomic_write_bytes(self.snapshot_path, buf.getvalue())
        if step % self.every == 0:
            self._validate(trainer, pl_module)
        self._t0 = _now()


def plateau(points: Sequence[Dict[str, float]], tail: float = TAIL,
            tolerance: float = TOLERANCE) -> Dict[str, Any]:
    """Did a run reach a validation plateau?  ``reached`` when the best error of the last
    ``tail`` share of the steps is less than ``tolerance`` (relative) below the best error
    before it; ``gain`` that relative improvement; ``best`` / ``best_step`` /
    ``best_epoch`` the lowest point.  Needs at least 3 points after step 0."""
    pts = sorted(points, key=lambda p: p["step"])
    if len(pts) < 4:
        raise ValueError(f"`points`: need at least 4 validation points, got {len(pts)}")
    cut = pts[-1]["step"] * (1.0 - tail)
    early = min(p["E_dist"] for p in pts if p["step"] <= cut)
    late = min((p["E_dist"] for p in pts if p["step"] > cut), default=early)
    best = min(pts, key=lambda p: p["E_dist"])
    gain = (early - late) / early if early > 0 else 0.0
    return {"reached": gain < tolerance, "gain": gain, "best": best["E_dist"],
            "best_step": best["step"], "best_epoch": best["epoch"]}


def _curved(records: Sequence[Dict[str, Any]]) -> List[Dict[str, Any]]:
    return [r for r in records if r.get("kind") == _KIND and r.get("status") == "ok"
            and (r.get("curve") or {}).get("points")]


def _per_sequence(records: Sequence[Dict[str, Any]], method: str) -> Dict[str, float]:
    """``{sequence: E_dist}`` of ``method`` at the equal-step snapshot, mean over seeds."""
    vals: Dict[str, List[float]] = {}
    for r in records:
        if r["method"] == method:
            for s in r["equal_steps"]["per_sequence"]:
                vals.setdefault(s["sequence"], []).append(s["metrics"]["E_dist"])
    return {k: statistics.fmean(v) for k, v in vals.items()}


def _fit(r: Dict[str, Any]) -> str:
    """A run's last error on the curves' training sequences, and its ratio to LBS's."""
    last, lbs = r["curve"]["points"][-1].get("train_E_dist"), r["curve"].get("train_lbs_E_dist")
    if last is None:
        return "—"
    return f"{last:.3f}" + (f" ({last / lbs:.2f}x)" if lbs else "")


def markdown(records: Sequence[Dict[str, Any]], png: Optional[str] = None) -> List[str]:
    """The "Learning curves" section of ``report.md`` (empty without curves): per run,
    the validation error at the start, its best and last points, and the plateau test;
    then every method's test error at the equal-step snapshot beside the equal-time one."""
    rs = _curved(records)
    if not rs:
        return []
    lbs = next((r["curve"].get("lbs_E_dist") for r in rs if r["curve"].get("lbs_E_dist")), None)
    batch = (rs[0].get("config") or {}).get("batch_size", 1)
    lines = ["## Learning curves (validation split) and equal steps", "",
             f"Validation E_dist every {rs[0]['curve']['every']} optimizer steps"
             + (f" of {batch} chunks" if batch > 1 else "") + " while each method trains "
             "(the validation time is not counted in its budget); "
             + (f"LBS on the validation split: {lbs:.3f} cm. " if lbs else "")
             + f"Plateau: the best error of the last {TAIL:.0%} of the steps is less than "
             f"{TOLERANCE:.0%} below the best before it. p: paired two-sided Wilcoxon "
             "over the test sequences (means over seeds).", ""]
    train = any("train_E_dist" in p for r in rs for p in r["curve"]["points"])
    rows = []
    for r in rs:
        pts = r["curve"]["points"]
        try:
            pl = plateau(pts)
            verdict = (f"{'yes' if pl['reached'] else 'not converged'} (the last "
                       f"{TAIL:.0%}'s best is {abs(pl['gain']):.1%} "
                       f"{'below' if pl['gain'] >= 0 else 'above'} the best before it)")
            best = f"{pl['best']:.3f} @ {pl['best_step']} (epoch {pl['best_epoch']})"
        except ValueError:
            verdict, best = "too few points", "—"
        rows.append([r["method"], str(r["seed"]), str(pts[-1]["step"]), str(r.get("epochs", "—")),
                     f"{pts[0]['E_dist']:.3f}", best, f"{pts[-1]['E_dist']:.3f}",
                     verdict] + ([_fit(r)] if train else []))
    lines += table(["method", "seed", "steps", "epochs", "start (cm)", "best (cm) @ step",
                    "last (cm)", "plateau"] + (["last on training sequences (cm, x LBS)"]
                                               if train else []), rows) + [""]
    if png:
        lines += [f"![learning curves]({png})", ""]
    snap = [r for r in rs if r.get("equal_steps")]
    short: List[str] = []
    if snap:
        step = snap[0]["equal_steps"]["step"]
        short = sorted({r["method"] for r in snap if not r["equal_steps"]["reached"]})
        snap = [r for r in snap if r["equal_steps"]["reached"]]
    if snap:
        lines += [f"Test E_dist at equal steps (the weights after {step} optimizer steps) and "
                  "at equal wall time (the end of the budget), mean ± std over seeds:", ""]
        rows = []
        methods = list(dict.fromkeys(r["method"] for r in snap))
        ref = _per_sequence(snap, methods[0])
        for method in methods:
            mine = [r for r in snap if r["method"] == method]
            p = "—"
            if method != methods[0]:
                try:
                    p = f"{scoring.wilcoxon(ref, _per_sequence(snap, method))['p']:.3g}"
                except ValueError:
                    p = "too few sequences"
            rows.append([method, fmt([r["equal_steps"]["metrics"]["E_dist"] for r in mine]),
                         fmt([r["metrics"]["E_dist"] for r in mine]),
                         fmt([float(r.get("steps", 0)) for r in mine]), str(len(mine)), p])
        lines += table(["method", f"E_dist at {step} steps (cm)", "E_dist at equal time (cm)",
                        "steps in the time", "seeds", f"p vs {methods[0]} at {step} steps"],
                       rows) + [""]
    if short:
        lines += [f"Stopped by the time budget before {step} steps (no equal-step "
                  f"score): {', '.join(short)}.", ""]
    return lines


def _epochs(r: Dict[str, Any]) -> List[float]:
    """A curve's points in epochs of the whole training split (the trainer's own epochs
    for a curve recorded without ``train_chunks``)."""
    n = r["curve"].get("train_chunks")
    return [p["chunks"] / n if n and "chunks" in p else float(p["epoch"])
            for p in r["curve"]["points"]]


def plot(records: Sequence[Dict[str, Any]], path) -> Optional[Path]:
    """``learning_curves.png``: validation E_dist of every method's first seed (solid) and,
    where recorded, its error on the training sequences (dashed) against optimizer steps,
    epochs of the training split and training wall time, LBS on the validation split as a
    black dashed line; the error axis stops at 1.5x LBS's error, and a method whose curve
    goes above is marked so in the legend; ``None`` without curves."""
    rs = _curved(records)
    if not rs:
        return None
    plt = pyplot()
    first: Dict[str, Dict[str, Any]] = {}
    for r in sorted(rs, key=lambda r: r["seed"]):
        first.setdefault(r["method"], r)
    lbs = next((r["curve"].get("lbs_E_dist") for r in rs if r["curve"].get("lbs_E_dist")), None)
    errs = [p[k] for r in first.values() for p in r["curve"]["points"]
            for k in ("E_dist", "train_E_dist") if k in p]
    top = max(errs) if lbs is None else min(max(errs), 1.5 * lbs)
    bottom = min(errs + ([lbs] if lbs else []))
    lo, hi = bottom - 0.05 * (top - bottom), top + 0.05 * (top - bottom)
    fig, axes = plt.subplots(1, 3, figsize=(16.0, 5.2), sharey=True)
    for i, (method, r) in enumerate(first.items()):
        pts = r["curve"]["points"]
        y = [p["E_dist"] for p in pts]
        label = method + (f" (up to {max(y):.3g} cm, above the frame)" if max(y) > hi else "")
        style = dict(color=plt.get_cmap("tab10")(i % 10), marker=".", markersize=3, lw=1.2)
        xs = ([p["step"] for p in pts], _epochs(r), [p["seconds"] / 60.0 for p in pts])
        trained = [(k, p["train_E_dist"]) for k, p in enumerate(pts) if "train_E_dist" in p]
        for ax, x in zip(axes, xs):
            ax.plot(x, y, label=label if ax is axes[0] else None, **style)
            if trained:
                ax.plot([x[k] for k, _ in trained], [e for _, e in trained], ls="--",
                        color=style["color"], lw=1.0, alpha=0.8)
    if any("train_E_dist" in p for r in first.values() for p in r["curve"]["points"]):
        axes[0].plot([], [], color="grey", ls="--", label="dashed: training sequences")
    for ax, xlabel in zip(axes, ("optimizer steps", "epochs of the training split",
                                 "training wall time (min)")):
        if lbs:
            ax.axhline(lbs, color="black", ls="--", lw=1,
                       label=f"LBS (validation): {lbs:.3g} cm" if ax is axes[0] else None)
        ax.set_xlabel(xlabel)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylim(lo, hi)
    axes[0].set_ylabel("E_dist (cm): validation solid")
    for ax, title in zip(axes, ("against optimizer steps", "against epochs",
                                "against training wall time")):
        ax.set_title(title)
    fig.suptitle("Learning curves (first seed of each method)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=8,
               frameon=False)
    fig.tight_layout(rect=(0, 0.06 + 0.035 * ((len(labels) - 1) // 4), 1, 1))
    return save_figure(fig, path)
