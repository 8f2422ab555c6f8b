"""A trained method on a garment, body and motion of your own: the deformed garment of
every frame, without simulating (``garmentgnn predict``; docs/own_garment.md).

The inputs are built as a dataset's sequence file holds them
(:func:`garmentgnn.data.worker.input_arrays`) and read as every reader of model inputs
reads them (:func:`garmentgnn.data.chunks.static_inputs`,
:func:`garmentgnn.models.inputs.with_frames`), so a checkpoint predicts here what
``garmentgnn train predict`` predicts on a simulated sequence of the same garment, body
and motion.  Frame-parallel methods (GarTrans, DA-, HOOD-, NCS-style) run in chunks of
the frames they were evaluated with; the MGN-style simulator rolls out over the whole
motion from the skinned garment, or from the first two frames a frame-parallel checkpoint
predicts (``start_from``); ``lbs`` is the rest garment skinned to the body.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np
import torch

from garmentgnn.body.body import Body
from garmentgnn.body.factory import build_body
from garmentgnn.data.assets import (check_fit, file_name, motion_from_entry, read_garment_file,
                                    sha256_of)
from garmentgnn.data.chunks import static_inputs
from garmentgnn.data.worker import input_arrays
from garmentgnn.garments import make_garment
from garmentgnn.garments.garment import Garment
from garmentgnn.garments.templates import TEMPLATES
from garmentgnn.models.inputs import (CHUNK, HISTORY, NUM_LANDMARKS, NYSTROM_DIM, GarmentInputs,
                                      with_frames)
from garmentgnn.motion import MOTIONS, make_motion
from garmentgnn.motion.sequence import Motion
from garmentgnn.physics.materials import MATERIALS
from garmentgnn.training.base import COMPILE_WORK
from garmentgnn.training.base import compile_pays as work_pays
from garmentgnn.training.checkpoints import load_checkpoint
from garmentgnn.viz.compare import data_settings

PathLike = Union[str, Path]
#: the method that needs no checkpoint: the rest garment skinned to the body
LBS = "lbs"
#: frames per frame-parallel chunk when a checkpoint does not say (the data module's)
DEFAULT_CHUNK = CHUNK
#: why ``start_from`` is refused for a method that is not autoregressive
_OWN_FRAMES = ("predicts every frame itself; only an autoregressive method (MGN-style) "
               "starts from another method's frames")


@dataclass
class Prediction:
    """The garment of every frame and what it was made from.

    ``positions [T, V, 3]`` float32 metres, ``faces [F, 3]``, ``seq``: the arrays and
    meta of a sequence file with these positions (what :mod:`garmentgnn.data.gltf` and
    :mod:`garmentgnn.data.export` write), ``frame_seconds [T]``: each frame's share of
    the time the method took, ``autoregressive``: rolled out frame by frame."""

    positions: np.ndarray
    faces: np.ndarray
    fps: float
    method: str
    seq: Dict[str, Any]
    frame_seconds: List[float] = field(default_factory=list)
    autoregressive: bool = False
    #: ``(first frame, frames)`` of every call of the method, in order
    chunks: List[Tuple[int, int]] = field(default_factory=list)
    #: whether the method ran its compiled nearest-face search (:func:`compile_pays`)
    compiled: bool = False

    @property
    def total_seconds(self) -> float:
        return float(sum(self.frame_seconds))

    @property
    def steady_frame_seconds(self) -> Optional[float]:
        """The median time of a frame after the first call (``None`` with one call):
        what a longer take costs per frame, set-up and compilation left out."""
        later = [self.frame_seconds[t] for t0, n in self.chunks[1:] for t in range(t0, t0 + n)]
        return float(np.median(later)) if later else None

    @property
    def setup_seconds(self) -> Optional[float]:
        """What the first call took beyond its frames at :attr:`steady_frame_seconds`:
        the set-up (the first allocations, caches) and any compilation."""
        steady = self.steady_frame_seconds
        if steady is None or not self.chunks:
            return None
        t0, n = self.chunks[0]
        return max(0.0, float(sum(self.frame_seconds[t0:t0 + n])) - n * steady)


class ResolutionWarning(UserWarning):
    """A garment far from the vertex counts the checkpoint was trained on."""


#: how far a garment's vertex count may be from the training garments' (a factor of their
#: fewest and most) before :func:`check_resolution` warns
RESOLUTION_FACTOR = 2.0
#: what was measured (docs/results/resolution/): models trained on ~400-vertex garments,
#: on the same held-out garments made at other resolutions
RESOLUTION_TREND = ("measured on learn's held-out garments made at 400 and 4,000 vertices "
                    "(docs/results/resolution), E_dist against LBS's stayed 1.07x for "
                    "GarTrans and 0.92x for DA-style, and went from 0.99x to 1.08x for the "
                    "MGN-style simulator (its stretch error from 10% to 15%)")


def check_resolution(num_vertices: int, module: Any, name: str) -> None:
    """A :class:`ResolutionWarning` when ``num_vertices`` lies outside
    :data:`RESOLUTION_FACTOR` times the range of the garments ``module``'s checkpoint was
    trained on (its dataset stamp's ``num_vertices``; nothing to compare without one),
    with the measured trend."""
    trained = (getattr(module, "trained_on", None) or {}).get("num_vertices")
    if not trained:
        return
    lo, hi = trained
    if lo / RESOLUTION_FACTOR <= num_vertices <= hi * RESOLUTION_FACTOR:
        return
    warnings.warn(f"the garment has {num_vertices:,} vertices, {name} was trained on "
                  f"garments of {lo:,}-{hi:,}; {RESOLUTION_TREND}", ResolutionWarning,
                  stacklevel=3)


# --------------------------------------------------------------------------- inputs
def body_entry(body: Union[str, List[float], Mapping[str, Any]]) -> Dict[str, Any]:
    """A body spec entry: anny's named shape (``"regular"``), ``"MODEL:SHAPE"``
    (``"capsule:regular"``), anny's 6 shape parameters, or ``{"model", "shape"}``."""
    if isinstance(body, str):
        model, _, shape = body.rpartition(":")
        return {"model": model or "anny", "shape": shape}
    if isinstance(body, Mapping):
        return {"model": body.get("model", "anny"), "shape": body.get("shape", "regular")}
    if isinstance(body, (list, tuple)):
        return {"model": "anny", "shape": [float(x) for x in body]}
    raise TypeError(f"`body`: expected a shape name, parameters or {{model, shape}}, got "
                    f"{type(body).__name__}")


def _is_path(x: Any) -> bool:
    return isinstance(x, Path) or (isinstance(x, str) and ("/" in x or "." in x))


def resolve_garment(garment: Union[PathLike, Garment], body: Body, resolution: int = 300,
                    params: Optional[Mapping[str, Any]] = None) -> Garment:
    """A :class:`Garment` as it is, a mesh file (read and checked against ``body``,
    :mod:`garmentgnn.data.assets`), or a template name built on ``body``."""
    if isinstance(garment, Garment):
        return garment
    if _is_path(garment):
        path = Path(garment)
        if not path.is_file():
            raise ValueError(f"`garment`: {path}: no such file; give a mesh file (OBJ, PLY, "
                             f"glTF) or a template name ({', '.join(TEMPLATES)})")
        g = read_garment_file(path)
        check_fit(g, body, str(path))
        return g
    if garment not in TEMPLATES:
        raise ValueError(f"`garment`: {garment!r} is neither a mesh file nor a template; "
                         f"templates: {', '.join(TEMPLATES)}")
    return make_garment(garment, body, resolution=resolution, **dict(params or {}))


def resolve_motion(motion: Union[PathLike, Motion], body: Body, fps: float,
                   frames: Optional[int], scale: float = 1.0, up: str = "Y",
                   mapping: Optional[Mapping[str, str]] = None, start: int = 0,
                   seed: int = 0, speed: float = 1.0, amplitude: float = 1.0) -> Motion:
    """A :class:`Motion` (on ``body``'s joints), a BVH file (read, retargeted and
    resampled to ``fps`` as a dataset spec's, :func:`motion_from_entry`; default every
    frame from ``start``) or a generator name (``frames`` frames, default 60)."""
    if isinstance(motion, Motion):
        return motion if frames is None else Motion(
            motion.rotations[:frames], motion.translation[:frames],
            list(motion.joint_names), motion.fps)
    if _is_path(motion):
        path = Path(motion)
        if not path.is_file():
            raise ValueError(f"`motion`: {path}: no such file; give a BVH file or a "
                             f"generator name ({', '.join(sorted(MOTIONS))})")
        entry = {"file": path.name, "path": str(path.resolve()), "sha256": sha256_of(path),
                 "scale": scale, "up": up, "mapping": dict(mapping or {}), "start": start}
        return motion_from_entry(entry, body, fps, frames)
    return make_motion(motion, body.skeleton, num_frames=frames or 60, fps=float(fps),
                       speed=speed, amplitude=amplitude, seed=seed,
                       rest_joints=body.joints.to(torch.float64))


def sequence_of(garment: Garment, body: Body, body_spec: Dict[str, Any], motion: Motion,
                material: str = "silk") -> Dict[str, Any]:
    """The arrays and meta of a sequence file of this garment, body and motion, without
    its simulated positions."""
    if material not in MATERIALS:
        raise ValueError(f"`material`: unknown {material!r}; choose from {sorted(MATERIALS)}")
    seq: Dict[str, Any] = input_arrays(garment, body, motion)
    seq["meta"] = {"id": f"{garment.name}-{motion.num_frames}f", "body": body_spec,
                   "material": material, "material_params": asdict(MATERIALS[material]),
                   "garment": {"kind": garment.name}, "settings": {"fps": float(motion.fps)},
                   "fps": float(motion.fps), "num_frames": motion.num_frames,
                   "num_vertices": garment.num_vertices}
    return seq


# --------------------------------------------------------------------------- methods
def _settings(module, where: str):
    """``(history, num_landmarks, nystrom_dim, chunk)`` the module was trained and
    evaluated with."""
    if module is None:
        return HISTORY, NUM_LANDMARKS, NYSTROM_DIM, DEFAULT_CHUNK
    history, landmarks = data_settings({"m": module}, {"m": where}, None, None)
    trained = getattr(module, "trained_data", None) or {}
    chunk = trained.get("eval_chunk") or trained.get("chunk") or DEFAULT_CHUNK
    ny = getattr(module, "nystrom_dim", None) or trained.get("nystrom_dim") or NYSTROM_DIM
    return int(history), int(landmarks), int(ny), int(chunk)


def check_method(module, item: GarmentInputs, where: str) -> None:
    """Refuse a checkpoint whose model cannot take this garment (NCS-style is specific
    to the garment it was trained on) or these data sizes (its module's
    ``check_data``)."""
    trained = getattr(module.model, "init_args", {}).get("num_vertices")
    if module.per_garment and item.num_vertices != trained:
        raise ValueError(f"`ckpt`: {where} is a {module.table_name} model, specific to the "
                         f"garment it was trained on ({trained} vertices); this garment has "
                         f"{item.num_vertices}; train {module.table_name} on this garment, "
                         f"or use a checkpoint of a method for every garment (GarTrans, "
                         f"DA-, HOOD- or MGN-style)")
    dims = {"num_joints": item["rest_joints"].shape[0],
            "num_body_vertices": item["body_pos"].shape[1], "num_vertices": item.num_vertices}
    if hasattr(module, "check_data"):
        module.check_data(dims, where)


def check_rate(module, fps: float, where: str) -> None:
    """Refuse ``fps`` other than the one a model learned at: the MGN-style simulator
    predicts accelerations in metres per frame squared (its model's ``fps``), so at
    another rate it would roll out a garment of another physics without a word
    (``garmentgnn train test`` refuses the same on a dataset)."""
    learned = None if module is None else module.learned_fps
    if learned is None:
        return
    if abs(fps - float(learned)) > 1e-6 * float(learned):
        raise ValueError(f"`fps`: {fps:g}, but {where} ({module.table_name}) learned its "
                         f"dynamics at {float(learned):g} fps; give fps {float(learned):g} "
                         f"(a BVH is resampled to it), or train a model at {fps:g} fps "
                         f"(--model.model.fps)")


def compile_pays(module, frames: int, vertices: int,
                 device: Union[str, torch.device] = "cpu") -> bool:
    """Whether ``module``'s compiled nearest-face search (GarTrans's ``compile_search``)
    pays back on ``frames`` frames of ``vertices`` garment vertices: on the CPU from
    :data:`COMPILE_WORK` vertex-frames on (below, the one-off compile costs more than
    eager loses on the take), on a GPU always; ``False`` for a module without one."""
    if not getattr(getattr(module, "model", None), "compile_search", False):
        return False
    return work_pays(frames * vertices, device)


def _motion_tensors(seq: Dict[str, Any]) -> Tuple[torch.Tensor, torch.Tensor]:
    """The sequence's joint rotations and root translations as float32 tensors."""
    return (torch.from_numpy(np.asarray(seq["motion_rotations"], np.float32)),
            torch.from_numpy(np.asarray(seq["motion_translation"], np.float32)))


@torch.no_grad()
def start_frames(starter, seq: Dict[str, Any], where: str = "start_from",
                 device: Union[str, torch.device] = "cpu") -> torch.Tensor:
    """The garment ``[2, V, 3]`` of frames 0 and 1 that ``starter``, a frame-parallel
    method, predicts on a sequence's arrays: its first chunk, as :func:`predict_sequence`
    runs it (the start an autoregressive method rolls out from with ``start_from``)."""
    history, landmarks, ny, chunk = _settings(starter, where)
    static, body = static_inputs(seq, seq["meta"], ny, landmarks)
    rot, tr = _motion_tensors(seq)
    frames = torch.arange(min(max(2, chunk), rot.shape[0]))
    item = with_frames(static, body, rot, tr, frames, history,
                       seq_id=str(seq["meta"].get("id", "sequence")))
    check_method(starter, item, where)
    starter.to(device)
    pred = starter.predict_sequence(item.to(device))[:2].detach().float()
    if not torch.isfinite(pred).all():
        raise ValueError(f"`start_from`: {where} predicted NaN/inf on frames 0 and 1")
    return pred


@torch.no_grad()
def predict_sequence(module, seq: Dict[str, Any], where: str = "checkpoint",
                     device: Union[str, torch.device] = "cpu",
                     on_frames: Optional[Callable[[int, int, float], None]] = None,
                     compile: Optional[bool] = None, info: Optional[Dict[str, Any]] = None,
                     start_from=None, start_where: str = "start_from"):
    """``(positions [T, V, 3] float32, frame_seconds [T], autoregressive)`` of ``module``
    (``None``: LBS) on a sequence's arrays (:func:`sequence_of`, or a sequence file
    loaded with :func:`garmentgnn.data.store.load_sequence`).  ``on_frames(first, count,
    seconds)`` is called after every chunk.

    ``start_from``: a frame-parallel module (``start_where``: its checkpoint) whose frames
    0 and 1 (:func:`start_frames`) an autoregressive ``module`` rolls out from instead of
    the skinned garment; its time is the first call's.

    ``compile``: run a GarTrans checkpoint's nearest-face search compiled (``None``: where
    it pays back, :func:`compile_pays`); compiled, the last, shorter chunk is padded to
    the chunk's frames (its last frame repeated, those outputs dropped: the frames are
    predicted independently), so its shape needs no second compilation.  ``info``, when
    given, receives ``chunks`` (``(first frame, frames)`` per call) and ``compiled``."""
    history, landmarks, ny, chunk = _settings(module, where)
    static, body = static_inputs(seq, seq["meta"], ny, landmarks)
    rot, tr = _motion_tensors(seq)
    T = rot.shape[0]
    autoregressive = module is not None and module.autoregressive
    if start_from is not None and not autoregressive:
        raise ValueError(f"`start_from`: {where} {_OWN_FRAMES}")
    if module is not None and T < module.min_frames:
        raise ValueError(f"`motion`: {T} frames; {module.table_name} needs "
                         f"{module.min_frames} or more")
    step = T if autoregressive else max(1, chunk)
    device = torch.device(device)
    model = getattr(module, "model", None)
    searches = hasattr(model, "compile_search")
    before = model.compile_search if searches else None
    if compile is None:
        compile = compile_pays(module, T, len(seq["garment_vertices"]), device)
    compile = bool(compile) and bool(before)
    if module is not None:
        module.to(device)
    out, seconds, chunks = [], [], []
    try:
        if searches:
            model.compile_search = compile
        for t0 in range(0, T, step):
            n = min(step, T - t0)
            frames = torch.arange(t0, t0 + n)
            if compile and n < step and t0 > 0:  # the compiled shape: no recompilation
                frames = torch.cat([frames, frames[-1:].expand(step - n)])
            item = with_frames(static, body, rot, tr, frames, history,
                               seq_id=str(seq["meta"].get("id", "sequence")))
            if module is not None and t0 == 0:
                check_method(module, item, where)
            item = item.to(device)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t = time.perf_counter()
            if module is None:
                pred = item.skinned()
            elif start_from is not None:
                start = start_frames(start_from, seq, start_where, device)
                pred = module.predict_sequence(item, start=start)
            else:
                pred = module.predict_sequence(item)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            dt = time.perf_counter() - t
            pred = pred.detach().float().cpu()[:n]
            if not torch.isfinite(pred).all():
                raise ValueError(f"`ckpt`: {where} predicted NaN/inf on frames "
                                 f"{t0}..{t0 + n - 1}")
            out.append(pred)
            seconds += [dt / n] * n
            chunks.append((t0, n))
            if on_frames is not None:
                on_frames(t0, n, dt)
    finally:
        if searches:
            model.compile_search = before
    if info is not None:
        info.update(chunks=chunks, compiled=compile)
    return torch.cat(out).numpy(), seconds, autoregressive


def load_method(ckpt: Optional[PathLike] = None, method: Optional[str] = None):
    """``(module or None, name)``: a checkpoint of any learned method
    (:func:`garmentgnn.training.checkpoints.load_checkpoint`), or ``method="lbs"``."""
    if (ckpt is None) == (method is None):
        raise ValueError("`ckpt`: give a checkpoint of a learned method, or method='lbs' "
                         "(not both)")
    if method is not None:
        if method != LBS:
            raise ValueError(f"`method`: only {LBS!r} runs without a checkpoint; give "
                             f"`ckpt` for a learned method")
        return None, LBS
    if not Path(ckpt).is_file():
        raise ValueError(f"`ckpt`: {ckpt}: no such file; give a checkpoint written by "
                         f"`garmentgnn train fit`")
    module = load_checkpoint(ckpt)
    return module, module.table_name


def load_starter(start_from: PathLike, module, name: str):
    """The frame-parallel module of the checkpoint ``start_from`` that an
    autoregressive ``module`` (named ``name``) starts from, or a ``ValueError``."""
    if module is None or not module.autoregressive:
        raise ValueError(f"`start_from`: {name} {_OWN_FRAMES}; drop start_from or give an "
                         f"MGN-style checkpoint")
    if not Path(start_from).is_file():
        raise ValueError(f"`start_from`: {start_from}: no such file; give a checkpoint of "
                         f"a frame-parallel method (DA-style, GarTrans, ...)")
    starter = load_checkpoint(start_from)
    if starter.autoregressive:
        raise ValueError(f"`start_from`: {start_from} is a {starter.table_name} checkpoint, "
                         f"which needs frames to start from itself; give a frame-parallel "
                         f"method's (DA-style, GarTrans, ...)")
    return starter


def predict_garment_motion(garment: Union[PathLike, Garment], body: Any = "regular",
                           motion: Union[PathLike, Motion] = "walk", *,
                           ckpt: Optional[PathLike] = None, method: Optional[str] = None,
                           frames: Optional[int] = None, fps: float = 30.0,
                           material: str = "silk", device: str = "cpu",
                           scale: float = 1.0, up: str = "Y",
                           mapping: Optional[Mapping[str, str]] = None, start: int = 0,
                           resolution: int = 300, seed: int = 0,
                           on_frames: Optional[Callable[[int, int, float], None]] = None,
                           compile: Optional[bool] = None,
                           start_from: Optional[PathLike] = None) -> Prediction:
    """The garment of a trained method (``ckpt``, or ``method="lbs"``) on ``garment``
    (a mesh file or a template name), ``body`` (:func:`body_entry`) and ``motion`` (a BVH
    file, with ``scale``, ``up``, ``mapping``, ``start`` as in a dataset spec, or a
    generator name), ``frames`` frames at ``fps``; ``compile``: see
    :func:`predict_sequence` (default: where it pays back).

    ``start_from``: for an MGN-style ``ckpt``, a frame-parallel checkpoint (DA-style,
    GarTrans, ...) whose frames 0 and 1 the rollout starts from instead of the skinned
    garment; neither needs a simulated frame (on `learn`'s test rollouts DA-style's start
    gave 0.770x LBS's error against the skinned garment's 0.821x,
    docs/learned_simulator.md)."""
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not 0 < fps <= 1000:
        raise ValueError(f"`fps`: expected frames per second, e.g. 30, got {fps!r}")
    if frames is not None and (not isinstance(frames, int) or frames < 1):
        raise ValueError(f"`frames`: expected 1 or more frames, got {frames!r}")
    if not isinstance(start, int) or isinstance(start, bool) or start < 0:
        raise ValueError(f"`start`: expected a first frame >= 0 of the take, got {start!r}")
    if mapping is not None and (not isinstance(mapping, Mapping) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in mapping.items())):
        raise TypeError(f"`mapping`: expected a mapping of file joint -> body joint or role, "
                        f"e.g. {{'hip_root': 'pelvis'}}, got {mapping!r}")
    module, name = load_method(ckpt, method)
    check_rate(module, float(fps), str(ckpt))
    starter = None
    if start_from is not None:
        starter = load_starter(start_from, module, name)
        name = f"{name} from {starter.table_name}"
    spec = body_entry(body)
    try:
        b = build_body(spec)
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"`body`: {exc}") from None
    g = resolve_garment(garment, b, resolution)
    check_resolution(int(g.vertices.shape[0]), module, name)
    if starter is not None:
        check_resolution(int(g.vertices.shape[0]), starter, starter.table_name)
    m = resolve_motion(motion, b, float(fps), frames, scale, up, mapping, start, seed)
    seq = sequence_of(g, b, spec, m, material)
    if isinstance(garment, (str, Path)) and _is_path(garment):
        seq["meta"]["garment"] = {"kind": file_name({"file": str(garment)})}
    where = str(ckpt) if ckpt is not None else LBS
    info: Dict[str, Any] = {}
    pos, secs, ar = predict_sequence(module, seq, where, device, on_frames, compile, info,
                                     starter, str(start_from))
    seq["positions"] = pos
    return Prediction(pos, np.asarray(seq["garment_faces"]), float(m.fps), name, seq, secs, ar,
                      info["chunks"], info["compiled"])


__all__ = ["COMPILE_WORK", "LBS", "Prediction", "ResolutionWarning", "body_entry", "check_rate",
           "compile_pays",
           "check_resolution", "check_method", "load_method", "load_starter",
           "predict_garment_motion", "predict_sequence", "resolve_garment", "resolve_motion",
           "sequence_of", "start_frames"]
