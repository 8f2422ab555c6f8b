"""Training curves: the loss terms and the validation metrics per epoch, as one PNG.

:class:`TrainingPlots` (a Lightning callback; ``garmentgnn train`` always adds it)
records the epoch-level values Lightning logs (``train/*``: the total loss and each
weighted term; ``val/*``: the metrics of :func:`garmentgnn.metrics.evaluate`) -- the
same numbers the configured logger (CSV, TensorBoard) receives -- and at the end of
``fit`` writes ``training_curves.png`` into the run's log folder (``trainer.log_dir``).
:func:`plot_training_curves` draws the same figure from a list of per-epoch dicts,
e.g. read back from a CSVLogger's ``metrics.csv`` (:func:`read_metrics_csv`).
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import lightning as L

from garmentgnn._plotting import pyplot
from garmentgnn.metrics import METRIC_UNITS

PathLike = Union[str, os.PathLike]
FILENAME = "training_curves.png"


def read_metrics_csv(path: PathLike) -> List[Dict[str, float]]:
    """Per-epoch rows of a CSVLogger ``metrics.csv`` (step-level columns dropped,
    ``*_epoch`` suffixes removed, rows of the same epoch merged)."""
    rows: Dict[int, Dict[str, float]] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if not r.get("epoch"):
                continue
            ep = int(float(r["epoch"]))
            row = rows.setdefault(ep, {"epoch": ep})
            for k, v in r.items():
                if v in ("", None) or k in ("epoch", "step") or k.endswith("_step"):
                    continue
                row[k[:-6] if k.endswith("_epoch") else k] = float(v)
    return [rows[k] for k in sorted(rows)]


def plot_training_curves(history: List[Dict[str, float]], path: PathLike,
                         title: str = "") -> Optional[Path]:
    """One PNG: the training loss and its terms (log scale) in the first panel, then one
    panel per validation metric, against the epoch.  Returns ``None`` if ``history``
    holds no metric."""
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator  # noqa: PLC0415  (loaded with the first figure)

    keys = sorted({k for row in history for k in row if k != "epoch"})
    train = [k for k in keys if k.startswith("train/")]
    order = ["val/E_dist", "val/E_vnorm", "val/E_fnorm", "val/E_len", "val/E_curv"]
    val = sorted((k for k in keys if k.startswith("val/")),
                 key=lambda k: (order.index(k) if k in order else len(order), k))
    if not train and not val:
        return None
    n = (1 if train else 0) + len(val)
    cols = min(n, 4)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False)
    flat = list(axes.ravel())

    def series(k):
        pts = [(r["epoch"], r[k]) for r in history if k in r and math.isfinite(r[k])]
        return [p[0] for p in pts], [p[1] for p in pts]

    i = 0
    if train:
        ax = flat[0]
        for k in train:
            x, y = series(k)
            positive = [v for v in y if v > 0]
            if positive:
                ax.plot(x, y, marker=".", lw=2.2 if k == "train/loss" else 1.2,
                        label=k[len("train/"):])
        ax.set_yscale("log")
        ax.set_title("training loss and terms")
        ax.set_xlabel("epoch")
        ax.legend(fontsize=7, ncol=2)
        ax.grid(alpha=0.3)
        i = 1
    for k in val:
        ax = flat[i]
        i += 1
        x, y = series(k)
        name = k[len("val/"):]
        unit = METRIC_UNITS.get(name)
        ax.plot(x, y, marker=".", color="tab:red")
        ax.set_title(f"validation {name}" + (f" ({unit})" if unit else ""))
        ax.set_xlabel("epoch")
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.grid(alpha=0.3)
    for ax in flat[:i]:
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    for ax in flat[i:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


class TrainingPlots(L.Callback):
    """Records the epoch-level logged metrics and writes ``training_curves.png`` (in
    ``dirpath``, default ``trainer.log_dir``) at the end of fit; ``self.path`` then
    holds the file."""

    def __init__(self, dirpath: Optional[str] = None, filename: str = FILENAME) -> None:
        self.dirpath, self.filename = dirpath, filename
        self.history: List[Dict[str, float]] = []
        self.path: Optional[Path] = None

    def __repr__(self) -> str:
        return f"TrainingPlots(dirpath={self.dirpath!r}, filename={self.filename!r})"

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        row: Dict[str, float] = {"epoch": trainer.current_epoch}
        for k, v in trainer.callback_metrics.items():
            if k.endswith("_step") or not k.startswith(("train/", "val/")):
                continue
            row[k[:-6] if k.endswith("_epoch") else k] = float(v)
        self.history = [r for r in self.history if r["epoch"] != row["epoch"]] + [row]

    def on_fit_end(self, trainer, pl_module) -> None:
        folder = self.dirpath or trainer.log_dir or trainer.default_root_dir
        if trainer.is_global_zero and self.history:
            self.path = plot_training_curves(self.history, Path(folder) / self.filename)
            if self.path is not None:
                print(f"training curves: {self.path}")

    def state_dict(self) -> Dict[str, Any]:
        return {"history": self.history}

    def load_state_dict(self, state_dict: Dict[str, Any]) -> None:
        self.history = list(state_dict.get("history", []))
