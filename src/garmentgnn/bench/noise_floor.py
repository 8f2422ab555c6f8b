"""The ground truth's own noise floor: how far a cloth engine's output moves when its input
moves by a rounding error.

Cloth simulation is chaotic: moving the rest garment's vertices (or the body's root) by
1e-7 m at random gives a visibly different sequence.  ``benchmarks/gt_noise.py``
measures it per engine (:func:`~garmentgnn.data.perturb.perturbed_garment`,
:func:`~garmentgnn.data.perturb.perturbed_motion`, :func:`divergence`) and writes
``docs/results/benchmarks/gt_noise.json``, whose ``floor`` (:func:`summarize`) the bench
report prints beside its method rows and draws as a band on its error-against-time plot
(:func:`load_floor`, :func:`markdown`, :func:`bands`).  A difference between two methods'
``E_dist`` below the floor is one the simulation itself cannot decide.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garmentgnn.data.perturb import (PERTURB_M, perturbed_garment, perturbed_motion,
                                     random_offsets)

#: the inputs a run perturbs: the rest garment's vertices, the body motion's root
#: translation (every frame), or nothing (a plain rerun: must give 0)
WHATS = ("garment", "body", "repeat")
#: the perturbation the floor is quoted at (:data:`garmentgnn.data.perturb.PERTURB_M`)
FLOOR_SCALE_M = PERTURB_M
#: where ``benchmarks/gt_noise.py --commit`` puts the committed results
_REPO = Path(__file__).resolve().parents[3]
COMMITTED = _REPO / "docs" / "results" / "benchmarks" / "gt_noise.json"
#: an environment variable naming another results file for the bench report
ENV = "GARMENTGNN_NOISE_FLOOR"
ENGINE_NAMES = {"blender": "Blender", "torch": "torch simulator"}


def divergence(a: Tensor, b: Tensor) -> Tuple[List[float], List[float]]:
    """Per frame, the mean and the max over vertices of ``|a - b|`` (cm), for positions
    ``[T, V, 3]`` in metres."""
    a, b = torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)
    if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"`a`, `b`: expected two [T, V, 3] position arrays of one shape, "
                         f"got {tuple(a.shape)} and {tuple(b.shape)}")
    d = (a - b).norm(dim=-1) * 100.0
    return d.mean(dim=1).tolist(), d.amax(dim=1).tolist()


def summarize(runs: Sequence[Dict[str, Any]], scale: float = FLOOR_SCALE_M,
              what: str = "garment") -> Dict[str, Dict[str, Any]]:
    """Per engine, the floor: over its ok runs perturbing ``what`` by ``scale``, the mean
    of the per-frame mean distances (cm; comparable with ``E_dist``, the mean per-vertex
    distance) and the largest per-frame max (cm), over the frames that are valid ground
    truth in both runs (a run's ``valid``, ``[T]`` bools, as every score reads them;
    every frame for a run without it); ``left_out``: the frames that are not, and
    ``all_frames_mean_cm`` the mean with them."""
    out: Dict[str, Dict[str, Any]] = {}
    for engine in sorted({r["engine"] for r in runs}):
        rs = [r for r in runs if r["engine"] == engine and r["what"] == what
              and r.get("status", "ok") == "ok" and math.isclose(r["scale_m"], scale)]
        if not rs:
            continue
        keep = [r.get("valid") or [True] * len(r["mean_cm"]) for r in rs]
        means = [m for r, k in zip(rs, keep) for m, ok in zip(r["mean_cm"], k) if ok]
        every = [m for r in rs for m in r["mean_cm"]]
        out[engine] = {"what": what, "scale_m": scale, "preset": rs[0].get("preset"),
                       "sequences": len({r["sequence"] for r in rs}),
                       "frames": len(means), "left_out": len(every) - len(means),
                       "mean_cm": sum(means) / len(means) if means else float("nan"),
                       "all_frames_mean_cm": sum(every) / len(every),
                       "max_cm": max((m for r, k in zip(rs, keep)
                                      for m, ok in zip(r["max_cm"], k) if ok), default=0.0)}
    return out


def committed(dataset: Optional[str] = None) -> Path:
    """The committed results file of ``dataset``'s preset (``gt_noise_<name>.json``
    beside :data:`COMMITTED`) when there is one, else :data:`COMMITTED`."""
    own = COMMITTED.with_name(f"gt_noise_{dataset}.json") if dataset else None
    return own if own is not None and own.is_file() else COMMITTED


def load_floor(path=None, dataset: Optional[str] = None) -> Optional[Dict[str, Any]]:
    """The results file's ``floor`` and where it came from (``{"path", "floor",
    "dataset"}``), from ``path``, else ``$GARMENTGNN_NOISE_FLOOR``, else the committed
    one of the ``dataset`` preset's name (:func:`committed`); ``None`` when no such file
    exists.  A file that is not such a results file raises ``ValueError`` naming it."""
    if path is None:
        path = os.environ.get(ENV) or committed(dataset)
    path = Path(path)
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text())
        floor = doc["floor"]
        for engine, f in floor.items():
            if not (isinstance(f, dict) and float(f["mean_cm"]) >= 0 and
                    float(f["max_cm"]) >= 0 and float(f["scale_m"]) > 0):
                raise ValueError(engine)
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{path}: not a results file of benchmarks/gt_noise.py (no valid "
                         f"'floor': {type(e).__name__}: {e}); rerun it, or point ${ENV} at "
                         f"one") from None
    try:  # the committed file by its place in the repository, not this machine's path
        shown = str(path.resolve().relative_to(_REPO))
    except ValueError:
        shown = str(path)
    return {"path": shown, "floor": floor, "meta": doc.get("meta", {})}


def label(engine: str, f: Dict[str, Any]) -> str:
    """A floor's row name, e.g. ``noise floor: Blender (rest garment ±1e-07 m)``."""
    what = {"garment": "rest garment", "body": "body motion"}.get(f["what"], f["what"])
    return f"noise floor: {ENGINE_NAMES.get(engine, engine)} ({what} ±{f['scale_m']:g} m)"


def bands(loaded: Optional[Dict[str, Any]]) -> List[Tuple[str, float]]:
    """``(label, mean_cm)`` of each engine's floor, for a plot's horizontal bands."""
    if not loaded:
        return []
    return [(label(e, f), float(f["mean_cm"])) for e, f in sorted(loaded["floor"].items())]


def markdown(loaded: Optional[Dict[str, Any]]) -> List[str]:
    """The report's section on the floor (empty without one)."""
    if not loaded:
        return []
    lines = ["## The ground truth's noise floor", "",
             f"From `{loaded['path']}` (`benchmarks/gt_noise.py`): each engine simulated the "
             "same sequences again with every rest-garment vertex moved by the distance "
             "shown in a random direction; mean and largest per-vertex distance to the "
             "unperturbed run, on the frames that are valid ground truth in both runs. "
             "`E_dist` differences between methods below the mean are below what the "
             "simulation itself decides.", "",
             "| floor | preset | sequences | frames | left out | mean (cm) | max (cm) |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for e, f in sorted(loaded["floor"].items()):
        lines.append(f"| {label(e, f)} | {f.get('preset', '-')} | {f.get('sequences', '-')} | "
                     f"{f.get('frames', '-')} | {f.get('left_out', '-')} | "
                     f"{float(f['mean_cm']):.3g} | {float(f['max_cm']):.3g} |")
    return lines + [""]


__all__ = ["COMMITTED", "ENV", "FLOOR_SCALE_M", "WHATS", "bands", "committed", "divergence",
           "label",
           "load_floor", "markdown", "perturbed_garment", "perturbed_motion", "random_offsets",
           "summarize"]
