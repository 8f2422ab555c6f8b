"""The physics engines as methods of the benchmark: a generated dataset's test sequences
simulated again, by Blender at cheaper settings than the dataset's own or by the torch
simulator at a few budgets, and scored against the dataset's file (its engine at its
own settings is the ground truth).  Each result is one JSON-able record of kind
:data:`KIND`, a point on the report's error-against-run-time plot.

An item is rebuilt exactly as the dataset generator built it
(:func:`garmentgnn.data.presets.build_inputs`: garment, body, motion with the item's seed,
material), and the rebuilt garment and motion are checked against the arrays the
sequence file stores, so a dataset made by other code fails its records instead of
giving a silently wrong error.  Errors (:func:`garmentgnn.metrics.evaluate`) are over
every recorded frame, ``0..frames-1``: with a pre-roll, frame 0 is already simulated.
``seconds`` is the wall time of the engine call alone (its pre-roll frames, and for
Blender the worker process's start, included), not building the inputs or scoring;
``seconds_per_frame`` divides it by the frames simulated, pre-roll included.

On the medium dataset's ~1,500-vertex garments (one thread, measured in
``docs/bench.md``) the torch simulator takes 0.45-1.1 s a simulated frame at one substep
and three Newton iterations, up to 4.4 s at two substeps and ten, Blender 0.04-0.1 s,
and the exact collision metric ~1 s a scored frame, so the bench scores the first
:data:`DEFAULT_FRAMES` frames of each sequence.
"""
from __future__ import annotations

import json
import math
import os
import random
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from garmentgnn.bench.records import failure
from garmentgnn.data import store
from garmentgnn.data.presets import ENGINES, build_inputs
from garmentgnn.data.validity import sequence_valid
from garmentgnn.data.worker import default_simulate
from garmentgnn.metrics import collision_rate, evaluate
from garmentgnn.sim import SimSettings
from garmentgnn.sim.blender import BlenderSettings, require_blender

KIND = "engine"
#: the held-out groups :func:`pick_sequences` draws from, in report order
GROUPS = ("motion", "body", "garment")
#: frames of each sequence the bench simulates (after the pre-roll): keeps the six
#: default settings on three medium sequences to ~15 minutes on one core
DEFAULT_FRAMES = 20
#: item keys :func:`engine_record` rebuilds a sequence from
ITEM_KEYS = ("id", "garment", "body", "motion", "material", "settings", "seed")


def settings_class(engine: str):
    """The settings dataclass of ``engine``: :class:`garmentgnn.sim.SimSettings`
    (``torch``) or :class:`garmentgnn.sim.blender.BlenderSettings` (``blender``)."""
    if engine == "blender":
        return BlenderSettings
    if engine == "torch":
        return SimSettings
    raise ValueError(f"`engine`: unknown {engine!r}; choose one of {ENGINES}")


@dataclass(frozen=True)
class EngineSetting:
    """One engine at one setting, a method of the report.

    Attributes:
        engine: ``"blender"`` or ``"torch"``.
        name: the method label in the report, e.g. ``"Blender q=2"``.
        settings: overrides of the dataset's engine settings (fields of
            :class:`~garmentgnn.sim.blender.BlenderSettings` or
            :class:`~garmentgnn.sim.SimSettings`); for an engine other than the
            dataset's, overrides of that engine's defaults with the dataset's ``fps``
            and ``preroll_frames``.
    """

    engine: str
    name: str
    settings: Dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise ValueError(f"`engine`: unknown {self.engine!r}; choose one of {ENGINES}")
        if not isinstance(self.name, str) or not self.name.strip():
            raise ValueError(f"`name`: expected a non-empty string, got {self.name!r}")
        if not isinstance(self.settings, dict):
            raise ValueError(f"`settings`: expected a dict of {self.engine} settings, got "
                             f"{type(self.settings).__name__}")
        known = {f.name for f in fields(settings_class(self.engine))}
        bad = sorted(set(self.settings) - known)
        if bad:
            raise ValueError(f"`settings`: {bad} are not {self.engine} settings; known: "
                             f"{sorted(known)}")


def default_settings() -> Tuple[EngineSetting, ...]:
    """The ladder the medium bench runs: Blender at three ``quality`` settings (cloth
    steps per frame) below the medium dataset's 5 (its ground truth; the collision
    quality stays the dataset's 2) and the torch simulator at three budgets (substeps per
    frame, Newton iterations per substep, no retries)."""
    return (
        EngineSetting("blender", "Blender q=2", {"quality": 2}),
        EngineSetting("blender", "Blender q=3", {"quality": 3}),
        EngineSetting("blender", "Blender q=4", {"quality": 4}),
        EngineSetting("torch", "torch sim sub=1,newton<=3", {"substeps": 1, "max_newton": 3,
                                                            "max_refinements": 0}),
        EngineSetting("torch", "torch sim sub=1,newton<=10", {"substeps": 1, "max_newton": 10,
                                                             "max_refinements": 0}),
        EngineSetting("torch", "torch sim sub=2,newton<=10", {"substeps": 2, "max_newton": 10,
                                                             "max_refinements": 0}),
    )


def _held_out(rec: Dict[str, Any]) -> List[str]:
    return list(rec.get("held_out") or [])


def pick_sequences(records: Sequence[dict], per_group: int = 1) -> List[dict]:
    """A small deterministic subset of a manifest's ok test items: ``per_group`` from
    each held-out group of :data:`GROUPS` (items whose ``held_out`` is exactly that one
    part), spread evenly over the group's items sorted by id.  Groups with fewer items
    give all they have; the result is in :data:`GROUPS` order."""
    if isinstance(records, (str, bytes, dict)) or not isinstance(records, Sequence):
        raise ValueError(f"`records`: expected a list of manifest items, got "
                         f"{type(records).__name__}")
    if not all(isinstance(r, dict) and "id" in r for r in records):
        raise ValueError("`records`: every entry must be a manifest item (a dict with an 'id')")
    if not isinstance(per_group, int) or isinstance(per_group, bool) or per_group < 1:
        raise ValueError(f"`per_group`: expected a positive int, got {per_group!r}")
    out: List[dict] = []
    for group in GROUPS:
        pool = sorted((r for r in records if r.get("status") == "ok"
                       and r.get("split") == "test" and _held_out(r) == [group]),
                      key=lambda r: r["id"])
        n = len(pool)
        picks = range(n) if n <= per_group else \
            sorted({int((i + 0.5) * n / per_group) for i in range(per_group)})
        out.extend(pool[i] for i in picks)
    return out


def item_engine(item: Dict[str, Any]) -> str:
    """The engine that made an item: a spec item names it (``"blender"``), a manifest
    record holds ``{"name": ..., "version": ..., "settings": ...}``."""
    e = item.get("engine", "torch")
    return (e or {}).get("name", "torch") if isinstance(e, dict) else str(e)


def resolve_settings(item: Dict[str, Any], setting: EngineSetting):
    """The settings object ``setting`` runs ``item`` with: the item's own settings
    (same engine) or the engine's defaults at the item's ``fps`` and
    ``preroll_frames`` (other engine), then ``setting.settings`` on top.  Bad values
    raise ``ValueError`` from the settings class."""
    cls = settings_class(setting.engine)
    base: Dict[str, Any]
    if item_engine(item) == setting.engine:
        base = dict(item["settings"])
    else:
        keep = {"fps", "preroll_frames"}
        base = {k: v for k, v in item["settings"].items() if k in keep}
    base.update(setting.settings)
    return cls(**base)


def _check_args(root, item, setting, frames) -> None:
    if not isinstance(root, (str, os.PathLike)):
        raise ValueError(f"`root`: expected the dataset folder's path, got {type(root).__name__}")
    if not isinstance(item, dict):
        raise ValueError(f"`item`: expected a manifest item (dict), got {type(item).__name__}")
    missing = [k for k in ITEM_KEYS if k not in item]
    if missing:
        raise ValueError(f"`item`: lacks {missing}; pass an entry of the dataset's "
                         f"manifest.json 'items'")
    if item.get("status", "ok") != "ok":
        raise ValueError(f"`item`: {item['id']!r} has status {item.get('status')!r}; only ok "
                         f"items have a sequence file to score against")
    if not isinstance(setting, EngineSetting):
        raise ValueError(f"`setting`: expected an EngineSetting, got {type(setting).__name__}")
    if frames is not None:
        n = int(item["motion"]["num_frames"])
        if not isinstance(frames, int) or isinstance(frames, bool) or not 1 <= frames <= n:
            raise ValueError(f"`frames`: expected None or an int in 1..{n} (the item's "
                             f"frames), got {frames!r}")


def _same(name: str, built: np.ndarray, stored: np.ndarray, atol: float = 1e-5) -> None:
    if built.shape != stored.shape or not np.allclose(built, stored, rtol=0, atol=atol):
        raise RuntimeError(f"the rebuilt {name} differs from the sequence file's (shape "
                           f"{built.shape} vs {stored.shape}): the dataset was made by other "
                           f"code; regenerate it with this version")


def engine_record(root, item: dict, setting: EngineSetting, frames: Optional[int] = None
                  ) -> Dict[str, Any]:
    """Simulate manifest item ``item`` of the dataset at ``root`` again with
    ``setting`` for its first ``frames`` frames (``None``: all) and score it against the
    file's positions over the same frames.

    Returns a JSON-able record: ``kind``, ``method`` (``setting.name``), ``case`` and
    ``sequence`` (the item id), ``seed`` 0, ``held_out``, ``engine``, ``settings`` (all
    of them), ``status`` ``"ok"``/``"failed"``, ``message``, ``metrics`` (E_dist ...,
    ``collision_rate``), ``frames``, ``seconds`` (the engine call), ``simulated_frames``
    (``frames`` plus the pre-roll), ``seconds_per_frame`` (per simulated frame)
    and, for the torch simulator, ``nonconverged_frames`` and ``newton_iterations``.
    Bad arguments raise ``ValueError``; anything failing after that (the engine, a
    missing or different sequence file) gives a failed record."""
    _check_args(root, item, setting, frames)
    n = int(item["motion"]["num_frames"]) if frames is None else frames
    st = resolve_settings(item, setting)
    rec: Dict[str, Any] = {"kind": KIND, "method": setting.name, "case": item["id"], "seed": 0,
                           "sequence": item["id"], "held_out": _held_out(item),
                           "engine": setting.engine, "frames": n,
                           "settings": json.loads(json.dumps(asdict(st)))}  # tuples to lists
    try:
        seq = store.load_record_sequence(root, item, ["positions", "garment_vertices",
                                                      "garment_faces", "motion_rotations",
                                                      "motion_translation", "converged"],
                                         optional=["penetration"])
        # the generator's seeding (garmentgnn.data.worker.run_item)
        torch.manual_seed(item["seed"])
        np.random.seed(item["seed"])
        random.seed(item["seed"])
        garment, body, motion, material = build_inputs(item, num_frames=n)
        _same("garment", garment.vertices.numpy().astype(np.float32), seq["garment_vertices"])
        _same("garment faces", garment.faces.numpy(), seq["garment_faces"], atol=0)
        _same("motion rotations", motion.rotations.float().numpy(), seq["motion_rotations"][:n])
        _same("motion translation", motion.translation.float().numpy(),
              seq["motion_translation"][:n])
        simulate = default_simulate(setting.engine)
        if setting.engine == "blender":  # finds the worker's interpreter (cached) untimed
            require_blender()
        t0 = time.perf_counter()
        res = simulate(garment, body, motion, material, settings=st, progress=None)
        seconds = time.perf_counter() - t0
        simulated = n + int(getattr(st, "preroll_frames", 0))
        rec.update(seconds=seconds, simulated_frames=simulated,
                   seconds_per_frame=seconds / simulated)
        if setting.engine == "torch":
            rec.update(nonconverged_frames=int((~res.converged).sum()),
                       newton_iterations=int(res.newton_iterations.sum()))
        if not res.ok:
            raise RuntimeError(f"{setting.engine} engine: {res.message}")
        pred = torch.as_tensor(res.positions).double()
        gt = torch.from_numpy(seq["positions"][:n]).double()
        if pred.shape != gt.shape:
            raise RuntimeError(f"the engine returned positions {tuple(pred.shape)}, the file "
                               f"holds {tuple(gt.shape)}")
        if not torch.isfinite(pred).all():
            raise RuntimeError(f"{int((~torch.isfinite(pred)).sum())} non-finite coordinates")
        # frames that are not valid ground truth are left out (and counted)
        keep = torch.from_numpy(sequence_valid(seq)[:n])
        if not bool(keep.any()):
            raise RuntimeError("no frame of the sequence file is valid ground truth (converged "
                               "and the body not through the cloth): nothing to score")
        m = evaluate(pred[keep], gt[keep], garment.faces)
        # the collision metric in float32, as the learned methods are scored
        # (evaluate_inputs)
        body_pos = body.pose(motion.rotations, motion.translation)[0].float()[keep]
        m["collision_rate"] = float(collision_rate(pred[keep].float(), body_pos,
                                                   body.faces).mean())
        rec.update(status="ok", message=str(res.message or "ok"), metrics=m,
                   excluded_frames=n - int(keep.sum()))
    except Exception as err:
        rec.update(failure(err))
    for k in ("seconds", "seconds_per_frame"):
        v = rec.get(k)
        if v is not None and not math.isfinite(v):
            rec[k] = None
    return rec


def dataset_items(root) -> List[dict]:
    """The manifest items of the dataset at ``root`` (:func:`pick_sequences` input)."""
    return list(store.read_manifest(Path(root))["items"])


__all__ = ["DEFAULT_FRAMES", "GROUPS", "KIND", "EngineSetting", "dataset_items", "default_settings",
           "engine_record", "item_engine", "pick_sequences", "resolve_settings",
           "settings_class"]
