"""The panels of one held-out sequence: ground truth | trained checkpoints | LBS only.

:func:`comparison` runs every model on one sequence of a generated dataset (the
same inputs as :func:`garmentgnn.training.evaluate.evaluate_split`) and returns
:class:`~garmentgnn.viz.animate.Panel` objects with per-vertex errors, plus the posed
body, ready for :func:`~garmentgnn.viz.animate.render_animation` or for glTF export.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from garmentgnn.data import store
from garmentgnn.data.gltf import GltfMesh, write_gltf
from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.data import SequenceChunks
from garmentgnn.training.evaluate import predict
from garmentgnn.training.checkpoints import load_checkpoint
from garmentgnn.viz.animate import (GT_COLOR, Panel, default_error_limit, render_animation,
                                    vertex_error_cm)
from garmentgnn.viz.viewer import viewer_bundle, write_viewer

PathLike = Union[str, os.PathLike]


@dataclass
class Comparison:
    """A sequence's panels, garment faces and posed body (numpy, metres)."""

    seq_id: str
    panels: List[Panel]
    faces: np.ndarray
    body_positions: np.ndarray
    body_faces: np.ndarray
    fps: float
    frames: np.ndarray

    def __repr__(self) -> str:
        return (f"Comparison({self.seq_id!r}, panels={[p.title for p in self.panels]}, "
                f"frames={len(self.frames)})")


def parse_named(specs: Sequence[str], option: str = "--ckpt") -> List[Tuple[str, str]]:
    """``["GarTrans=a.ckpt", "b.ckpt"]`` -> ``[("GarTrans", "a.ckpt"), ("b", "b.ckpt")]``."""
    out = []
    for s in specs:
        name, sep, path = s.partition("=")
        if not sep:
            name, path = Path(s).stem, s
        if not name or not path:
            raise ValueError(f"`{option}`: expected NAME=PATH or PATH, got {s!r}")
        out.append((name, path))
    return out


def unique_names(named: Sequence[Tuple[str, str]]) -> None:
    """``ValueError`` when two of ``named`` (:func:`parse_named`'s pairs of ``--ckpt``
    and ``--pred``) share a panel name: one would silently replace the other."""
    seen: Dict[str, str] = {}
    for name, path in named:
        if name in seen:
            raise ValueError(f"`ckpt`: two panels named {name!r} ({seen[name]}, {path}); "
                             f"name them: --ckpt A={seen[name]} --ckpt B={path}")
        seen[name] = path


def comparison(root: PathLike, models: Mapping[str, object], split: Optional[str] = "test",
               index: Union[int, str] = 0, mode: str = "gartrans", lbs: bool = True,
               history: Optional[int] = None, num_landmarks: Optional[int] = None,
               max_frames: Optional[int] = None,
               predictions: Optional[Mapping[str, object]] = None) -> Comparison:
    """Ground truth, each of ``models`` (name -> :class:`GarTransModule` or checkpoint
    path; ``mode`` ``"gartrans"`` frame-parallel or ``"gartrans_ar"`` autoregressive),
    each of ``predictions`` (name -> ``[T, V, 3]`` array or ``.npy`` path: any other
    method's garment on this sequence, in our vertex order) and, with ``lbs``, the
    LBS-only coarse garment, on the ``index``-th sequence of ``split`` under ``root``
    (or, with a string ``index``, on the sequence of that id).
    Models run in eval mode (their mode is restored).  ``history`` and ``num_landmarks``
    (the data's pose history and Nyström landmarks) default to those the checkpoints were
    trained with (:func:`data_settings`); a model built for another skeleton, body or
    garment size than the sequence's is refused naming the sizes
    (:meth:`GarmentModule.check_data`)."""
    if mode not in ("gartrans", "gartrans_ar"):
        raise ValueError(f"`mode`: expected 'gartrans' or 'gartrans_ar', got {mode!r}")
    if max_frames is not None and (isinstance(max_frames, bool) or not isinstance(
            max_frames, int) or max_frames < 1):  # -3 dropped the last 3 frames, silently
        raise ValueError(f"`max_frames`: expected an int >= 1 (or None: every frame), got "
                         f"{max_frames!r}")
    loaded = {name: (load_checkpoint(m) if isinstance(m, (str, os.PathLike)) else m)
              for name, m in models.items()}
    where = {name: str(m) if isinstance(m, (str, os.PathLike)) else f"`models`[{name!r}]"
             for name, m in models.items()}
    history, num_landmarks = data_settings(loaded, where, history, num_landmarks)
    modes = {name: m.training for name, m in loaded.items()}
    try:
        for m in loaded.values():
            m.eval()
        with torch.no_grad():
            return _comparison(root, loaded, split, index, mode, lbs, history, num_landmarks,
                               max_frames, dict(predictions or {}), where)
    finally:
        for name, m in loaded.items():
            m.train(modes[name])


#: the data settings a checkpoint's data module fixes, and the flag of each
TRAINED_DATA = {"history": "--history", "num_landmarks": "--num-landmarks"}


def data_settings(loaded: Mapping[str, object], where: Mapping[str, str],
                  history: Optional[int], num_landmarks: Optional[int]) -> Tuple[int, int]:
    """``(history, num_landmarks)`` for the sequence the models are shown on: the values
    the checkpoints' data modules were trained with (``HISTORY`` and ``NUM_LANDMARKS`` of
    :mod:`garmentgnn.models.inputs` where none says), which a given value must match
    (another value would give the model other inputs than it learned from, silently);
    ``ValueError`` naming the flag, or the two checkpoints that disagree."""
    given = {"history": history, "num_landmarks": num_landmarks}
    out = {k: v for k, v in given.items() if v is not None}
    source: Dict[str, str] = {}
    for name, m in loaded.items():
        for key, value in (getattr(m, "trained_data", None) or {}).items():
            if key not in TRAINED_DATA or value is None:
                continue
            if key in source and out[key] != value:
                raise ValueError(f"`models`: {where[name]} was trained with {key} {value}, "
                                 f"{source[key]} with {out[key]}; show them separately")
            if given[key] is not None and given[key] != value:
                raise ValueError(f"`{key}` {given[key]}: {where[name]} was trained with "
                                 f"{key} {value}; drop the flag ({TRAINED_DATA[key]} "
                                 f"follows the checkpoint)")
            out[key], source[key] = value, where[name]
    return out.get("history", HISTORY), out.get("num_landmarks", NUM_LANDMARKS)


def _comparison(root, loaded, split, index, mode, lbs, history, num_landmarks, max_frames,
                predictions, where) -> Comparison:
    nys = {int(m.nystrom_dim) for m in loaded.values()
           if m.nystrom_dim is not None} or {NYSTROM_DIM}
    if len(nys) > 1:
        raise ValueError(f"`models`: checkpoints disagree on nystrom_dim {sorted(nys)}")
    if min(nys) > num_landmarks:
        raise ValueError(f"`num_landmarks` {num_landmarks}: the models read {min(nys)} "
                         f"Nyström features, which need at least as many landmarks")
    ids = None
    if isinstance(index, str):  # a sequence id: that sequence alone
        ids, index = [index], 0
    ds = SequenceChunks(root, split, chunk=10 ** 9, history=history, nystrom_dim=nys.pop(),
                        num_landmarks=num_landmarks, ids=ids)
    if not len(ds):
        raise ValueError(f"`split`: no {split!r} sequences under {root}")
    if not 0 <= index < len(ds):
        raise ValueError(f"`index`: {split!r} has {len(ds)} sequences, got index {index}")
    item = ds[index]
    dims = {"num_joints": item["rest_joints"].shape[0],
            "num_body_vertices": item["body_pos"].shape[1], "num_vertices": item.num_vertices}
    for name, module in loaded.items():
        if hasattr(module, "check_data"):
            module.check_data(dims, where[name])
    gt = item["gt"].double().numpy()
    panels = [Panel("simulated (ground truth)", gt, color=GT_COLOR)]
    for name, module in loaded.items():
        pred = predict(module, item, mode).double().numpy()
        if not np.isfinite(pred).all():
            raise ValueError(f"model {name!r} predicted NaN/inf on {item['seq_id']}")
        panels.append(Panel(name, pred, vertex_error_cm(pred, gt)))
    for name, pred in predictions.items():
        pred = np.load(pred) if isinstance(pred, (str, os.PathLike)) else pred
        pred = np.asarray(pred.detach().cpu() if hasattr(pred, "detach") else pred, np.float64)
        if pred.shape != gt.shape:
            raise ValueError(f"`predictions`[{name!r}]: expected {gt.shape} (the frames and "
                             f"vertices of {item['seq_id']}), got {pred.shape}")
        if not np.isfinite(pred).all():
            raise ValueError(f"`predictions`[{name!r}] contain NaN/inf")
        panels.append(Panel(name, pred, vertex_error_cm(pred, gt)))
    if lbs:
        pred = predict(None, item, "lbs").double().numpy()
        panels.append(Panel("LBS only", pred, vertex_error_cm(pred, gt)))
    meta = store.read_meta(store.sequence_path(root, ds.records[ds.index[index][0]]))
    fps = float((meta.get("settings") or {}).get("fps", 30.0))
    T = gt.shape[0] if max_frames is None else min(gt.shape[0], max_frames)
    if T < gt.shape[0]:
        for p in panels:
            p.positions = p.positions[:T]
            p.error = None if p.error is None else p.error[:T]
    return Comparison(item["seq_id"], panels, item["faces"].numpy(),
                      item["body_pos"][:T].double().numpy(), item["body_faces"].numpy(), fps,
                      item["frames"][:T].numpy())


def show(root: PathLike, checkpoints: Mapping[str, object], out: PathLike, *,
         split: Optional[str] = "test", index: Union[int, str] = 0, mode: str = "gartrans",
         lbs: bool = True,
         history: Optional[int] = None, num_landmarks: Optional[int] = None,
         max_frames: Optional[int] = None,
         predictions: Optional[Mapping[str, object]] = None, gltf: bool = True,
         html: bool = False, **render_kw) -> Dict[str, object]:
    """Render the comparison of one held-out sequence to ``<out>.mp4/.gif/.png`` and,
    with ``gltf``, export every panel with the body to ``<out>.glb`` (error colours and
    labels as in the animation), with ``html`` also the viewer page ``<out>.html``
    (:func:`garmentgnn.viz.viewer.write_viewer`); returns ``{"animation": Animation,
    "gltf": path or None, "html": path or None, "comparison": Comparison}``."""
    if html and not gltf:
        raise ValueError("`html`: the viewer page shows the glTF file; leave `gltf` on")
    if html:
        viewer_bundle()  # a missing or damaged bundle before anything is rendered
    c = comparison(root, checkpoints, split, index, mode, lbs, history, num_landmarks,
                   max_frames, predictions)
    anim = render_animation(c.panels, c.faces, out, c.body_positions, c.body_faces, fps=c.fps,
                            caption=c.seq_id, frame_offset=int(c.frames[0]), **render_kw)
    glb = page = None
    if gltf:
        glb = export_comparison_gltf(c, Path(out).with_suffix(".glb"), clim=anim.clim,
                                     cmap=render_kw.get("cmap", "YlOrRd"))
    if html:
        page = write_viewer(glb, Path(out).with_suffix(".html"), title=c.seq_id)
    return {"animation": anim, "gltf": glb, "html": page, "comparison": c}


def export_comparison_gltf(c: Comparison, path: PathLike, spacing: float = 0.0,
                           clim: Optional[Tuple[float, float]] = None,
                           cmap: str = "YlOrRd") -> Path:
    """Every panel's garment and the body as one glTF 2.0 binary with morph-target
    animation; panel ``j`` (and a copy of the body) is moved ``j * spacing`` along X by
    its node's translation (default: the body's width x 1.3), the vertex data stay in
    our order and coordinates.  Predicted garments carry their per-vertex error as
    colours of ``cmap`` over ``clim`` (cm; default as the animation's,
    :func:`~garmentgnn.viz.animate.default_error_limit`), per frame and unlit; every
    garment is labelled with its panel title and mean error, and the scene's extras
    hold the colour bar (``colorbar``: ``min``, ``max``, ``label``, ``colors``)."""
    from matplotlib import colormaps  # noqa: PLC0415 (matplotlib: loaded on the first figure)

    errs = [p.error for p in c.panels if p.error is not None]
    if clim is None:
        clim = (0.0, float(f"{max(default_error_limit(errs), 1e-3):.2g}"))
    lo, hi = float(clim[0]), float(clim[1])
    if not hi > lo:
        raise ValueError(f"`clim`: expected (low, high) in cm with high > low, got {clim}")
    cm = colormaps[cmap]
    extent = c.body_positions[..., 0] if len(c.body_positions) else c.panels[0].positions[..., 0]
    dx = spacing or 1.3 * max(float(np.ptp(extent)), 0.3)
    meshes = []
    for j, p in enumerate(c.panels):
        off = (j * dx, 0.0, 0.0)
        meshes.append(GltfMesh(f"body {j}" if j else "body", c.body_positions, c.body_faces,
                               (0.8, 0.8, 0.8), off))
        if p.error is None:
            meshes.append(GltfMesh(p.title, p.positions, c.faces, p.color, off, label=p.title))
            continue
        colors = cm(np.clip((p.error - lo) / (hi - lo), 0.0, 1.0))[..., :3]
        meshes.append(GltfMesh(p.title, p.positions, c.faces, p.color, off, colors=colors,
                               label=f"{p.title}\nmean {p.error.mean():.2f} cm"))
    bar = {"min": lo, "max": hi, "label": "distance to ground truth, E_dist (cm)",
           "colors": ["#%02x%02x%02x" % tuple(int(round(255 * v)) for v in cm(x)[:3])
                      for x in np.linspace(0.0, 1.0, 11)]} if errs else None
    return write_gltf(path, meshes, fps=c.fps, extras={"colorbar": bar} if bar else None)
