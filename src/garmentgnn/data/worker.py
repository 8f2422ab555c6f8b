"""One item's simulation, as every worker runs it (a process-pool worker of
:func:`garmentgnn.data.generate.generate`, or a Ray task of
:mod:`garmentgnn.data.ray_backend`): build its inputs, simulate, write its sequence file
and return its manifest record."""
from __future__ import annotations

import random
import time
import traceback
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import numpy as np
import torch

from garmentgnn.data import store
from garmentgnn.data._lifeline import watch_parent
from garmentgnn.data.presets import build_inputs
from garmentgnn.data.sequence_check import nonfinite_arrays
from garmentgnn.data.validity import invalid_frame_count
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.sim import SimSettings, simulate
from garmentgnn.sim.blender import BlenderSettings, blender_version, simulate_blender


def default_simulate(engine: str = "torch"):
    """The engine's simulate function: :func:`garmentgnn.sim.simulate` (``torch``) or
    :func:`garmentgnn.sim.blender.simulate_blender` (``blender``)."""
    if engine == "blender":
        return simulate_blender
    return simulate


def item_settings(item: Dict[str, Any]):
    """The engine's settings object of an item: :class:`garmentgnn.sim.SimSettings` or
    :class:`garmentgnn.sim.blender.BlenderSettings`."""
    if item.get("engine", "torch") == "blender":
        return BlenderSettings(**item["settings"])
    return SimSettings(**item["settings"])


def engine_info(engine: str, settings: Dict[str, Any]) -> Dict[str, Any]:
    """What the manifest and each sequence file record of the engine: name, version
    (the ``bpy`` package for Blender, garmentgnn's for the torch simulator), settings."""
    if engine == "blender":
        version = blender_version()
    else:
        version = store.code_version()["version"]
    return {"name": engine, "version": version, "settings": dict(settings)}


def plain_settings(item: Dict[str, Any]) -> Dict[str, Any]:
    """Settings as a plain dict (test doubles of the simulator)."""
    return dict(item["settings"])


#: what a Blender item is simulated again with when its first run leaves invalid frames
#: (:mod:`garmentgnn.data.validity`): at least this quality and collision quality
#: (docs/dataset.md); the better of the two runs is kept
RESIMULATE = {"quality": 10, "collision_quality": 5}


def resimulation_settings(item: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The item's settings raised to :data:`RESIMULATE`, or ``None`` where there is
    nothing to raise (an engine other than Blender, or settings already that high)."""
    if item.get("engine", "torch") != "blender":
        return None
    settings = dict(item["settings"])
    raised = {k: max(int(settings.get(k, getattr(BlenderSettings, k))), v)
              for k, v in RESIMULATE.items()}
    if all(int(settings.get(k, getattr(BlenderSettings, k))) == v for k, v in raised.items()):
        return None
    return dict(settings, **raised)


def _better(a: Dict[str, Any], b: Dict[str, Any]) -> bool:
    """Whether run ``a`` has fewer invalid frames than ``b`` (then a shallower deepest
    frame); a tie keeps ``b``."""
    key = [(r["invalid"], -np.inf if r["pen"] is None else float(r["pen"].max()))
           for r in (a, b)]
    return key[0] < key[1]


def _seed(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)


def _simulate(sim, inputs, settings) -> Dict[str, Any]:
    """One run of the engine on an item's inputs: its positions and per-frame records."""
    garment, body, motion, material = inputs
    res = sim(garment, body, motion, material, settings=settings, progress=None)
    T, V = motion.num_frames, garment.num_vertices
    if not getattr(res, "ok", True):
        raise RuntimeError(f"simulator: {getattr(res, 'message', 'not ok')}")
    P = np.asarray(torch.as_tensor(res.positions).detach().cpu(), dtype=np.float32)
    if P.shape != (T, V, 3):
        raise RuntimeError(f"simulator returned positions {P.shape}, expected {(T, V, 3)}")
    if not np.isfinite(P).all():
        raise RuntimeError("simulator returned NaN/inf positions")

    def arr(name, dtype, default):
        v = getattr(res, name, None)
        return np.asarray(default if v is None else torch.as_tensor(v).cpu(), dtype=dtype)

    converged = arr("converged", bool, np.ones(T, bool))
    pen = getattr(res, "penetration", None)  # exact end-of-frame depth (real simulator)
    pen = None if pen is None or len(pen) != T else np.asarray(pen, np.float32)
    return {"positions": P, "converged": converged, "pen": pen,
            "pen_limit": float(getattr(res, "max_penetration", np.inf)),
            "newton_iterations": arr("newton_iterations", np.int32, np.zeros(T)),
            "residual": arr("residual", np.float32, np.zeros(T)),
            "invalid": invalid_frame_count(converged, pen)}


def input_arrays(garment, body, motion) -> Dict[str, np.ndarray]:
    """The arrays of a sequence file that hold its inputs (garment, body shape, motion),
    as the model inputs read them (:func:`garmentgnn.data.chunks.static_inputs`): what
    a prediction on a new garment, body and motion builds without simulating."""
    V = garment.num_vertices
    return {
        "garment_vertices": garment.vertices.numpy().astype(np.float32),
        "garment_faces": garment.faces.numpy().astype(np.int64),
        "garment_uv": garment.uv.numpy().astype(np.float32),
        "garment_face_uv": garment.face_uv.numpy().astype(np.float32),
        "garment_pinned": (np.zeros(V, bool) if garment.pinned is None
                           else garment.pinned.numpy().astype(bool)),
        # the weights the engine skinned the garment with (the rest pose, the pre-roll,
        # pins), stored so the model inputs read them instead of recomputing them
        "garment_skin_weights": transfer_skinning_weights(
            garment.vertices.float(), garment.faces, body.vertices.float(),
            body.weights.float()).numpy().astype(np.float32),
        "body_shape": (np.zeros(0, np.float64) if body.shape is None
                       else body.shape.double().numpy()),
        "motion_rotations": motion.rotations.float().numpy(),
        "motion_translation": motion.translation.float().numpy(),
    }


def run_item(item: Dict[str, Any], out: str, simulate_fn: Optional[Callable] = None,
             settings_fn: Optional[Callable] = None) -> Dict[str, Any]:
    """Simulate one item and write ``OUT/sequences/<id>.npz``; returns its manifest record.

    A Blender item whose run leaves frames that are not valid ground truth
    (:func:`garmentgnn.data.validity.valid_frames`) is simulated once more with
    :func:`resimulation_settings`; the run with fewer invalid frames is written, and the
    record's ``resimulated`` says what was done (``None``: one run).  Exceptions from
    building or simulating are reported as ``status="failed"`` (nothing is written; a
    failed second run keeps the first); only ``BaseException``\\ s such as
    ``KeyboardInterrupt`` propagate."""
    t0 = time.perf_counter()
    _seed(item["seed"])
    rec = store.pending_record(item)
    try:
        sim = simulate_fn or default_simulate(item.get("engine", "torch"))
        if settings_fn is None:
            settings_fn = item_settings if simulate_fn is None else plain_settings
        inputs = build_inputs(item)
        garment, body, motion, _ = inputs
        run = _simulate(sim, inputs, settings_fn(item))
        used, resimulated = item["settings"], None
        raised = resimulation_settings(item) if run["invalid"] else None
        if raised is not None:
            resimulated = {k: raised[k] for k in RESIMULATE}
            resimulated.update(frames_before=run["invalid"], frames_after=None,
                               kept="first")
            try:
                _seed(item["seed"])
                again = _simulate(sim, inputs, settings_fn(dict(item, settings=raised)))
            except Exception as e:
                resimulated["message"] = f"{type(e).__name__}: {str(e)[:200]}"
            else:
                resimulated["frames_after"] = again["invalid"]
                if _better(again, run):
                    run, used, resimulated["kept"] = again, raised, "resimulated"
        T, V = motion.num_frames, garment.num_vertices
        converged, pen = run["converged"], run["pen"]
        arrays = dict(input_arrays(garment, body, motion), positions=run["positions"],
                      converged=converged, newton_iterations=run["newton_iterations"],
                      residual=run["residual"])
        if pen is not None:
            arrays["penetration"] = pen
        bad = nonfinite_arrays(arrays)  # a file that would fail store.check_sequence
        if bad is not None:
            raise RuntimeError(f"simulator or inputs: {bad}")
        meta = {k: item[k] for k in ("id", "garment", "body", "motion", "material", "settings",
                                     "seed", "split")}
        meta["held_out"] = item.get("held_out", [])
        meta.update(
            format_version=store.FORMAT_VERSION, num_frames=T, num_vertices=V,
            num_faces=int(garment.faces.shape[0]), fps=float(motion.fps),
            joint_names=list(motion.joint_names), garment_name=garment.name,
            material_params=asdict(inputs[3]), nonconverged_frames=int((~converged).sum()),
            penetrating_frames=None if pen is None else int((pen > run["pen_limit"]).sum()),
            max_penetration_depth=None if pen is None else float(pen.max()),
            invalid_frames=run["invalid"], resimulated=resimulated,
            code={"version": store.code_version()["version"]},
            engine=engine_info(item.get("engine", "torch"), used))
        path = Path(out) / store.SEQUENCES / f"{item['id']}.npz"
        store.write_sequence(path, arrays, meta)
        rec = store.record_from_meta(meta)
        rec.update(code=store.code_version(), sha256=store.file_sha256(path))
    except Exception as e:
        tb = traceback.format_exc(limit=3)
        rec.update(status="failed", message=f"{type(e).__name__}: {e}\n{tb}")
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    return rec


def init_worker(parent_pid: Optional[int] = None) -> None:
    """Set up a worker process: one torch thread, and (given ``parent_pid``) exit when
    that process does."""
    if parent_pid is not None:  # die with the parent, even when it is SIGKILLed
        watch_parent(parent_pid)
    torch.set_num_threads(1)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:
        pass


__all__ = ["RESIMULATE", "default_simulate", "engine_info", "init_worker", "input_arrays",
           "item_settings",
           "plain_settings", "resimulation_settings", "run_item"]
