"""Blender's cloth as a simulation engine (the engine the paper used for ground truth, Sec. 4.1).

:func:`simulate_blender` has the signature of :func:`garmentgnn.sim.simulate` and returns
the same :class:`~garmentgnn.sim.SimResult`.  The garment and body trajectories are
computed here (:func:`garmentgnn.sim.trajectory.trajectories`, the same pre-roll as the
torch simulator); Blender runs in a separate worker process,
``garmentgnn/sim/_blender_worker.py``, started with an interpreter that has the ``bpy``
package (Blender as a Python module, GPL-3).  garmentgnn never imports ``bpy`` itself:
it stays MIT, Blender's single-scene, non-thread-safe state lives and dies with its
process, and a crash there fails one sequence, not the caller.

The interpreter (:func:`find_blender_python`): ``$GARMENTGNN_BPY_PYTHON``, else
``<venv>/bpy/bin/python`` (the worker environment ``make install`` creates beside the
project's, since ``bpy`` 5.0 pins ``numpy<2`` and CPython 3.11), else this interpreter
if it can import ``bpy``.

How our :class:`~garmentgnn.physics.Material` becomes Blender's cloth settings is one
function, :func:`blender_config`; ``docs/simulator.md`` has the table.
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Dict, Optional

import numpy as np
import torch

from garmentgnn._process import set_pdeathsig
from garmentgnn.geometry import face_areas, penetration_depth, unique_edges
from garmentgnn.physics import GRAVITY, Material
from garmentgnn.sim.settings import SimResult
from garmentgnn.sim.trajectory import trajectories

WORKER = Path(__file__).with_name("_blender_worker.py")
ENV_VAR = "GARMENTGNN_BPY_PYTHON"
INSTALL_HINT = (f"install Blender's Python module in a CPython 3.11 environment: `make install` "
                f"makes <venv>/bpy; or `python3.11 -m venv ENV && ENV/bin/pip install bpy` and "
                f"set {ENV_VAR}=ENV/bin/python")
#: Blender's cloth advances a frame as one time unit with gravity scaled by 1/1000
#: (measured: a 30-frame free fall is 0.9 x 1/2 g (30/30 s)^2), so a frame lasts
#: ``1 / sqrt(1000)`` s at ``time_scale`` 1.  Forces therefore carry a factor 1000.
BLENDER_TIME_UNIT = 1.0 / math.sqrt(1000.0)
#: Blender's solver loses gravity at gram-scale vertex masses (measured: a free 25-vertex
#: silk sheet of 0.3 g per vertex fell 0.54 m in 1 s instead of 4.9 m; at 0.03 kg 3.4 m;
#: at >= 0.3 kg exact), so masses and stiffnesses are scaled together to this mean vertex
#: mass (kg).  A mass-spring system's motion is unchanged by that scaling.
REFERENCE_VERTEX_MASS = 1.0


@dataclass(frozen=True)
class BlenderSettings:
    """Settings of the Blender engine (validated at construction).

    Attributes:
        fps: frame rate of the output; must equal the motion's fps.  Sets Blender's
            ``time_scale`` so that a frame lasts ``1 / fps`` seconds.
        preroll_frames: frames simulated (not recorded) while the body moves from the
            rest pose into the motion's first pose (at least 1: the first sample is the
            rest pose, which gives Blender its rest lengths).
        quality: cloth steps per frame (Blender's ``quality``).
        collision_quality: collision passes per step.
        collision_distance: the cloth's ``distance_min`` (m).
        body_thickness: the body collider's ``thickness_outer`` (m).
        self_collision: Blender's cloth self-collision.
        air_damping, damping: Blender's air damping and the tension / compression /
            shear spring damping (Blender's own units; our materials have no damping).
        threads: CPU cores the worker may use (its CPU affinity; Blender's cloth solver
            ignores its own thread setting); ``None``: all of them.
        timeout: seconds one sequence may take before its worker is killed.
        max_penetration: frames whose deepest garment vertex is further inside the body
            than this (m, measured exactly at the end of every recorded frame with
            :func:`garmentgnn.geometry.penetration_depth`) are flagged in the result.
    """

    fps: float = 30.0
    preroll_frames: int = 10
    quality: int = 5
    collision_quality: int = 2
    collision_distance: float = 0.005
    body_thickness: float = 0.005
    self_collision: bool = False
    air_damping: float = 1.0
    damping: float = 5.0
    threads: Optional[int] = None
    timeout: float = 1800.0
    max_penetration: float = 0.01

    def __post_init__(self) -> None:
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"`fps`: must be a positive finite number, got {self.fps!r}")
        for name, lo in (("preroll_frames", 1), ("quality", 1), ("collision_quality", 1),
                         ("threads", 1)):
            v = getattr(self, name)
            if name == "threads" and v is None:
                continue
            if not isinstance(v, int) or isinstance(v, bool) or v < lo:
                raise ValueError(f"`{name}`: must be an int >= {lo}, got {v!r}")
        for name in ("collision_distance", "body_thickness", "air_damping", "damping"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"`{name}`: must be a finite number >= 0, got {v!r}")
        for name in ("timeout", "max_penetration"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ValueError(f"`{name}`: must be a positive number, got {v!r}")


# --------------------------------------------------------------------------- the interpreter
def find_blender_python() -> Optional[str]:
    """The interpreter that runs the worker, or ``None`` (see the module doc)."""
    env = os.environ.get(ENV_VAR)
    if env:
        return env
    candidate = Path(sys.prefix) / "bpy" / "bin" / "python"
    if candidate.exists():
        return str(candidate)
    if importlib.util.find_spec("bpy") is not None:  # looks for it, does not import it
        return sys.executable
    return None


@lru_cache(maxsize=None)
def _bpy_version(python: str) -> Optional[str]:
    try:
        code = "import importlib.metadata as m; print(m.version('bpy'))"
        r = subprocess.run([python, "-c", code], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def blender_version() -> Optional[str]:
    """The ``bpy`` package version of the worker interpreter, or ``None`` without one."""
    python = find_blender_python()
    return None if python is None else _bpy_version(python)


def blender_available() -> bool:
    """Whether the Blender engine can run here (a worker interpreter with ``bpy``)."""
    return blender_version() is not None


def require_blender() -> str:
    """The worker interpreter; ``RuntimeError`` saying how to install ``bpy`` otherwise."""
    python = find_blender_python()
    if python is None:
        raise RuntimeError(f"the Blender engine needs the `bpy` package, which was not found; "
                           f"{INSTALL_HINT}")
    if _bpy_version(python) is None:
        raise RuntimeError(f"the Blender engine's interpreter {python} cannot import `bpy`; "
                           f"{INSTALL_HINT}")
    return python


# --------------------------------------------------------------------------- the mapping
def blender_config(material: Material, rest_vertices: torch.Tensor, faces: torch.Tensor,
                   settings: BlenderSettings) -> Dict[str, Dict[str, Any]]:
    """Blender properties for ``material`` on this garment (the table in docs/simulator.md).

    Blender's cloth is a mass-spring system in a time unit of ``1/sqrt(1000)`` s (see
    :data:`BLENDER_TIME_UNIT`), with per-vertex masses in kg and a structural spring of
    stiffness ``tension / L`` (``L`` the mean rest edge length).  A strip of our membrane
    (Eq. 12's ``k_s``, N/m) carries ``k_s * dl`` per edge, so ``tension = k_s * L / 1000``;
    shear likewise from ``k_h``.  Blender's angular bending spring has stiffness
    ``0.1 * bending * l``; matching the moment of our hinge energy
    (``k_b l^2 / (4A) * dtheta``, ``A ~ sqrt(3)/4 l^2``) over a lever ``l`` gives
    ``bending = k_b / (100 sqrt(3) L^2)``.  Mass is the density times the rest area,
    shared equally by the vertices.  Masses and stiffnesses are then multiplied by one
    factor that makes the vertex mass :data:`REFERENCE_VERTEX_MASS` (the motion is
    invariant; Blender's solver is not accurate at gram-scale masses).  Damping stays in
    Blender's units.  Friction: Blender's collider applies ``cloth_friction / 100`` as a
    Coulomb coefficient."""
    X = rest_vertices.detach().double()
    f = faces.long()
    e = unique_edges(f, X.shape[0]).edges
    L = float((X[e[:, 0]] - X[e[:, 1]]).norm(dim=1).mean())
    area = float(face_areas(X, f).sum())
    V = X.shape[0]
    s = settings
    mass = material.density * area / V
    scale = REFERENCE_VERTEX_MASS / mass
    cloth = {
        "quality": s.quality,
        "time_scale": 1.0 / (s.fps * BLENDER_TIME_UNIT),
        "mass": mass * scale,
        "tension_stiffness": scale * material.stretch * L / 1000.0,
        "compression_stiffness": scale * material.stretch * L / 1000.0,
        "shear_stiffness": scale * material.shear * L / 1000.0,
        "bending_stiffness": scale * material.bending / (100.0 * math.sqrt(3.0) * L * L),
        "air_damping": s.air_damping,
        "tension_damping": s.damping,
        "compression_damping": s.damping,
        "shear_damping": s.damping,
    }
    return {
        "gravity": list(GRAVITY),
        "cloth": cloth,
        "cloth_collision": {"collision_quality": s.collision_quality,
                            "distance_min": s.collision_distance,
                            "friction": 100.0 * material.friction,
                            "use_self_collision": s.self_collision},
        "collider": {"thickness_outer": s.body_thickness,
                     "cloth_friction": 100.0 * material.friction},
        "mean_edge_length": L,
        "area": area,
        "mass_scale": scale,
    }


# --------------------------------------------------------------------------- the engine
def _child_setup(cores: Optional[int]) -> Callable[[], None]:
    def setup() -> None:
        os.setsid()  # its own process group: killed as one on timeout
        set_pdeathsig()  # and it dies with its parent
        if cores is not None and hasattr(os, "sched_setaffinity"):
            allowed = sorted(os.sched_getaffinity(0))
            os.sched_setaffinity(0, allowed[:max(1, cores)])
    return setup


def run_blender_script(script: Path, arrays: Dict[str, np.ndarray], config: Dict[str, Any],
                       threads: Optional[int] = None,
                       timeout: float = 1800.0) -> Dict[str, np.ndarray]:
    """Run ``<Blender's python> script IN.npz OUT.npz`` in its own process group (killed
    after ``timeout`` s, and with this process), ``IN.npz`` holding ``arrays`` and
    ``config_json``; returns every array of ``OUT.npz``.  A failure raises
    ``RuntimeError`` with the end of Blender's output."""
    python = require_blender()
    with tempfile.TemporaryDirectory(prefix="garmentgnn-blender-") as tmp:
        inp, out = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(inp, config_json=np.frombuffer(json.dumps(config).encode(), np.uint8),
                 **arrays)
        proc = subprocess.Popen([python, str(script), str(inp), str(out)],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=_child_setup(threads))
        try:
            log, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise RuntimeError(f"Blender worker: no result after {timeout:g} s (killed)")
        except BaseException:
            os.killpg(proc.pid, signal.SIGKILL)
            raise
        if proc.returncode != 0 or not out.exists():
            tail = "\n".join(line for line in log.strip().splitlines()[-8:])
            raise RuntimeError(f"Blender worker failed (exit {proc.returncode}): {tail}")
        with np.load(out, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}


def run_worker(arrays: Dict[str, np.ndarray], config: Dict[str, Any],
               threads: Optional[int] = None,
               timeout: float = 1800.0) -> Dict[str, Any]:
    """Run the Blender cloth worker on raw arrays (``garment_frames``, ``faces``,
    ``pinned``, ``body_frames``, ``body_faces``); returns its ``positions`` and ``info``.
    A failure raises ``RuntimeError`` with the end of Blender's output."""
    z = run_blender_script(WORKER, arrays, config, threads=threads, timeout=timeout)
    return {"positions": z["positions"], "seconds_per_frame": z["seconds_per_frame"],
            "info": json.loads(z["info_json"].tobytes().decode())}


def simulate_blender(garment, body, motion, material: Material,
                     settings: Optional[BlenderSettings] = None,
                     progress: Optional[Callable[[int, int], None]] = None,
                     body_frames: Optional[torch.Tensor] = None):
    """Simulate ``garment`` on ``body`` following ``motion`` with Blender's cloth.

    Same inputs and output as :func:`garmentgnn.sim.simulate`: one output per motion
    frame, in the garment's own vertex order; frame 0 is the garment after the pre-roll.
    ``body`` is the collider and carries the pinned vertices; with ``body=None`` the cloth
    hangs from its pins at rest, with no collider.  ``progress`` is called once, at the
    end (the worker runs the sequence in one go)."""
    t0 = time.time()
    st = settings or BlenderSettings()
    if not isinstance(st, BlenderSettings):
        raise TypeError(f"`settings`: expected BlenderSettings, got {type(st).__name__}")
    if not isinstance(material, Material):
        raise TypeError(f"`material`: expected a Material, got {type(material).__name__}")
    fps_m = float(getattr(motion, "fps", st.fps))
    if abs(fps_m - st.fps) > 1e-6 * st.fps:
        raise ValueError(f"`settings.fps` ({st.fps}) differs from `motion.fps` ({fps_m}); "
                         f"use motion.resample({st.fps}) or set settings.fps")
    T, P = int(motion.num_frames), st.preroll_frames
    V = garment.vertices.shape[0]
    if body is None:
        if body_frames is not None:
            raise ValueError("`body_frames`: given without a `body`")
        skinned = garment.vertices.double().unsqueeze(0).expand(P + T, V, 3)
        frames, body_faces = torch.zeros(P + T, 0, 3), torch.zeros(0, 3, dtype=torch.long)
    else:
        skinned, frames = trajectories(garment, body, motion, P, body_frames)
        body_faces = body.faces
    pinned = (torch.zeros(V, dtype=torch.bool) if garment.pinned is None
              else garment.pinned.bool())
    arrays = {"garment_frames": skinned.float().numpy(),
              "faces": garment.faces.long().numpy(),
              "pinned": pinned.numpy(),
              "body_frames": frames.float().numpy(),
              "body_faces": body_faces.long().numpy()}
    config = blender_config(material, garment.vertices, garment.faces, st)
    res = run_worker(arrays, config, threads=st.threads, timeout=st.timeout)
    X = torch.from_numpy(res["positions"][P:]).float()
    if X.shape != (T, V, 3):
        raise RuntimeError(f"Blender worker returned {tuple(X.shape)}, expected {(T, V, 3)}")
    depth = torch.zeros(T)
    if body is not None:  # exact, at the end of every recorded frame
        for t in range(T):
            depth[t] = float(penetration_depth(X[t].double(), frames[P + t], body_faces).max())
    message = f"ok (Blender {res['info'].get('blender_version')})"
    deep = torch.nonzero(depth > st.max_penetration).flatten()
    if deep.numel():
        message += (f"; {deep.numel()} frame(s) deeper than {st.max_penetration * 1e3:.1f} mm "
                    f"in the body, first: frame {int(deep[0])} "
                    f"({float(depth[deep[0]]) * 1e3:.1f} mm)")
    if progress is not None:
        progress(T - 1, T)
    return SimResult(X, torch.ones(T, dtype=torch.bool), torch.zeros(T, dtype=torch.long),
                     torch.zeros(T), True, message, time.time() - t0,
                     torch.full((T,), st.quality, dtype=torch.long), penetration=depth,
                     max_penetration=st.max_penetration)
