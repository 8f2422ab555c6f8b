"""Dataset generation: a spec (garments x bodies x motions x materials), presets,
parallel workers, resume.

An *item* is one simulation: a garment template (kind + parameters + resolution) built
on a body (model + shape), driven by a procedural motion (name + speed + amplitude +
frame count) with a material preset and simulator settings.  Its ``id`` is a readable
prefix plus a hash of that canonical description and the spec's base seed, and its
``seed`` (motion jitter, torch/numpy RNG in the simulation) is derived from the same
hash, so an item's content never depends on which other items exist or on the order
they run in.

Split rule (the paper's held-out garments / bodies / motions, Sec. 4.1): each spec
names held-out garments, body shapes and motions for ``test`` and for ``val``.  An item
goes to ``test`` if its garment OR body OR motion is held out for test; otherwise to
``val`` if any of them is held out for val; otherwise to ``train``.  So no train item
shares a held-out component with a test item.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import multiprocessing
import os
import random
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from garmentgnn.data import store

# --------------------------------------------------------------------------- spec
#: garment: {"kind", "params" (template kwargs), "resolution"}
#: body: {"model": "capsule" | "anny", "shape": preset name or list of floats}
#: motion: {"name", "num_frames", "speed", "amplitude"}


def _canon(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


def garment_key(g: Dict[str, Any]) -> str:
    params = "".join(f"-{k}={v}" for k, v in sorted(g.get("params", {}).items()))
    return f"{g['kind']}{params}@{g['resolution']}"


def body_key(b: Dict[str, Any]) -> str:
    s = b["shape"]
    s = s if isinstance(s, str) else "[" + ",".join(f"{x:.4g}" for x in s) + "]"
    return f"{b['model']}:{s}"


def motion_key(m: Dict[str, Any]) -> str:
    return f"{m['name']}-s{m.get('speed', 1.0):g}-a{m.get('amplitude', 1.0):g}-n{m['num_frames']}"


_PART = {"garments": "garment", "bodies": "body", "motions": "motion"}


@dataclass
class Spec:
    """The full description of a dataset (see the module doc for the split rule).

    ``held_out`` maps ``"test"`` / ``"val"`` to ``{"garments": [...], "bodies": [...],
    "motions": [...]}`` of keys as given by :func:`garment_key`, :func:`body_key`,
    :func:`motion_key`.  ``sample``: if set, a seeded random subset of that many items
    of the full grid (kept in grid order)."""

    name: str
    garments: List[Dict[str, Any]]
    bodies: List[Dict[str, Any]]
    motions: List[Dict[str, Any]]
    materials: List[str]
    settings: Dict[str, Any] = field(default_factory=lambda: {"fps": 30.0, "substeps": 4, "preroll_frames": 6})
    held_out: Dict[str, Dict[str, List[str]]] = field(default_factory=dict)
    seed: int = 0
    sample: Optional[int] = None
    engine: str = "torch"

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise ValueError(f"`engine`: unknown {self.engine!r}; choose one of {ENGINES}")

    def split_of(self, garment: Dict, body: Dict, motion: Dict) -> str:
        return self.held_out_parts(garment, body, motion)[0]

    def held_out_parts(self, garment: Dict, body: Dict, motion: Dict) -> Tuple[str, List[str]]:
        """The item's split and which of its parts (``garment``, ``body``, ``motion``)
        are held out for it: reports break the test split down by these."""
        keys = {"garments": garment_key(garment), "bodies": body_key(body),
                "motions": motion_key(motion)}
        for split in ("test", "val"):
            h = self.held_out.get(split, {})
            parts = [_PART[k] for k in keys if keys[k] in h.get(k, ())]
            if parts:
                return split, parts
        return "train", []

    def items(self) -> List[Dict[str, Any]]:
        """Every item, in grid order (garment, body, motion, material)."""
        out = []
        for g, b, m, mat in itertools.product(self.garments, self.bodies, self.motions,
                                              self.materials):
            desc = {"garment": g, "body": b, "motion": m, "material": mat,
                    "settings": self.settings}
            if self.engine != "torch":  # torch items keep the ids they had before engines
                desc["engine"] = self.engine
            digest = hashlib.sha1(f"{_canon(desc)}|seed={self.seed}".encode()).hexdigest()
            shape = b["shape"] if isinstance(b["shape"], str) else "custom"
            iid = f"{g['kind']}-{b['model']}-{shape}-{m['name']}-{mat}-{digest[:10]}"
            split, parts = self.held_out_parts(g, b, m)
            out.append(dict(desc, id=iid, seed=int(digest[10:18], 16) & 0x7FFFFFFF,
                            split=split, held_out=parts, engine=self.engine))
        if self.sample is not None and self.sample < len(out):
            keep = sorted(random.Random(self.seed).sample(range(len(out)), self.sample))
            out = [out[i] for i in keep]
        ids = [it["id"] for it in out]
        if len(set(ids)) != len(ids):
            raise ValueError(f"spec {self.name!r}: duplicate items (repeated grid entries)")
        return out

    def to_json(self) -> Dict[str, Any]:
        d = asdict(self)
        d["items"] = self.items()
        return d


def _g(kind, resolution, **params):
    return {"kind": kind, "params": params, "resolution": resolution}


def _m(name, num_frames, speed=1.0, amplitude=1.0):
    return {"name": name, "num_frames": num_frames, "speed": speed, "amplitude": amplitude}


#: the engines a spec can name (``auto`` in :func:`resolve_engine` picks one)
ENGINES = ("torch", "blender")
#: the Blender engine's settings in every preset (:class:`garmentgnn.sim.blender.BlenderSettings`;
#: its run-time knobs ``threads`` and ``timeout`` do not change results and stay out of specs)
BLENDER_SETTINGS = {"fps": 30.0, "preroll_frames": 10, "quality": 5, "collision_quality": 2,
                    "collision_distance": 0.005, "body_thickness": 0.005, "self_collision": False,
                    "air_damping": 1.0, "damping": 5.0}


def resolve_engine(name: str = "auto") -> str:
    """``torch`` or ``blender``; ``auto`` is ``blender`` where its worker can run (see
    :func:`garmentgnn.sim.blender.blender_available`), else ``torch``."""
    if name == "auto":
        from garmentgnn.sim.blender import blender_available
        return "blender" if blender_available() else "torch"
    if name not in ENGINES:
        raise ValueError(f"`engine`: unknown {name!r}; choose 'auto' or one of {ENGINES}")
    return name


def preset(name: str, seed: int = 0, engine: str = "torch") -> Spec:
    """``tiny`` (tests, < 1 min), ``small`` (tens of minutes on 2 cores), ``medium``
    (Blender, about an hour on 2 cores) or ``paper`` (the paper's scale; hours to days),
    simulated by ``engine`` (``torch``, ``blender`` or ``auto``).  See ``docs/dataset.md``."""
    engine = resolve_engine(engine)
    spec = _preset(name, seed, engine)
    spec.engine = engine
    if engine == "blender":
        spec.settings = dict(BLENDER_SETTINGS)
    return spec


def _preset(name: str, seed: int, engine: str) -> Spec:
    if name == "tiny":
        return Spec(
            name="tiny",
            garments=[_g("skirt", 300, length="mini"), _g("tshirt", 300, sleeves="none")],
            bodies=[{"model": "capsule", "shape": "thin"},
                    {"model": "capsule", "shape": "regular"}],
            motions=[_m("walk", 8), _m("arm_swing", 8)],
            materials=["silk"],
            held_out={"test": {"motions": [motion_key(_m("arm_swing", 8))]}},
            seed=seed)
    if name == "small":
        # Sized from the measured simulator (docs/dataset.md): ~24 items x (15 simulated +
        # 6 pre-roll frames) of ~400-vertex garments, ~30 min on 2 cores.  Held-out
        # garments are new cuts of the trained kinds (as in the paper, Sec. 4.1), so the
        # train split sees every kind and the test split asks for generalisation to an
        # unseen shape, plus an unseen motion (kick); the fat body is held out for val.
        n = 60 if engine == "blender" else 16  # Blender is fast enough for longer sequences
        garments = [_g("skirt", 400), _g("skirt", 400, length="mini", flare="flared"),
                    _g("dress", 400), _g("tshirt", 400), _g("trousers", 400),
                    _g("skirt", 400, length="midi", flare="flared"),
                    _g("dress", 400, length="midi", flare="flared")]
        bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")]
        motions = [_m("walk", n), _m("run", n), _m("twirl", n), _m("arm_swing", n),
                   _m("kick", n)]
        return Spec(
            name="small", garments=garments, bodies=bodies, motions=motions,
            materials=["silk", "cotton"],
            held_out={"test": {"garments": [garment_key(g) for g in garments[5:]],
                               "motions": [motion_key(motions[4])]},
                      "val": {"bodies": [body_key(bodies[2])]}},
            seed=seed, sample=24)
    if name == "medium":
        return _medium(seed)
    if name == "paper":
        n = 300
        garments = (
            [_g("skirt", "medium", length=L, flare=f) for L in ("mini", "knee", "midi", "long")
             for f in ("pencil", "a-line", "flared", "full")]                              # 16
            + [_g("dress", "medium", length=L, flare=f) for L in ("knee", "midi", "long")
               for f in ("a-line", "flared", "full")]                                     # 9
            + [_g("tshirt", "medium", sleeves=s, length=L, neckline=nl)
               for s in ("none", "short", "elbow", "long") for L in ("hip", "waist")
               for nl in ("crew", "scoop")]                                               # 16
            + [_g("trousers", "medium", length=L) for L in ("shorts", "knee", "capri",
                                                             "long")]                     # 4
            + [_g("jumpsuit", "medium", length=L, sleeves=s) for L in ("knee", "long")
               for s in ("none", "short")])                                               # 4
        rng = np.random.default_rng(seed)
        # anny phenotype order: gender, age, muscle, weight, height, proportions
        test_bodies = [{"model": "anny", "shape": [round(float(x), 4) for x in
                                                   rng.uniform(0.2, 0.8, 6)]}
                       for _ in range(1)]
        bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")] \
            + test_bodies
        motions = [_m(name_, n, speed=s, amplitude=a)
                   for name_ in ("walk", "run", "twirl", "kick", "arm_swing", "jump",
                                 "sit_stand")
                   for s, a in ((1.0, 1.0), (0.8, 0.8), (1.25, 1.2))]
        test_garments = [garment_key(garments[i]) for i in range(0, len(garments), 10)]  # 5
        return Spec(
            name="paper", garments=garments, bodies=bodies, motions=motions,
            materials=["silk"],
            held_out={"test": {"garments": test_garments,
                               "bodies": [body_key(b) for b in test_bodies],
                               "motions": [motion_key(m) for m in motions
                                           if m["name"] == "sit_stand" and m["speed"] == 1.0]},
                      "val": {"garments": [garment_key(garments[i]) for i in (1, 17, 28)],
                              "motions": [motion_key(m) for m in motions
                                          if m["name"] == "jump" and m["speed"] == 1.25]}},
            seed=seed)
    raise ValueError(f"`preset`: unknown {name!r}; choose one of {PRESETS}")


PRESETS = ("tiny", "small", "medium", "paper")


def _medium(seed: int) -> Spec:
    """About 500 sequences of 60 frames (2 s at 30 fps) on 32 anny body shapes: 16 garments
    of every kind in several cuts and sizes (``ease``), three fabrics, 21 motions (the
    generators at several speeds and amplitudes, and even mixes of two).  Garments of
    about 1.3-1.6K vertices; the body collider is anny's 1,229-vertex topology.  Held out
    for test: one garment, three bodies, two motions; for val: one garment, two bodies,
    one motion.  Sized to generate in under an hour with the Blender engine and two
    workers on two cores (docs/dataset.md)."""
    n, res = 60, 1500
    garments = [
        _g("skirt", res, length="knee", flare="a-line"), _g("skirt", res, length="mini", flare="flared"),
        _g("skirt", res, length="midi", flare="pencil"), _g("skirt", res, length="long", flare="full"),
        _g("dress", res, length="knee", flare="a-line"), _g("dress", res, length="midi", flare="flared"),
        _g("dress", res, length="long", flare="full", top="sleeveless"),
        _g("tshirt", res, sleeves="short", ease=0.02), _g("tshirt", res, sleeves="none", length="waist",
                                                          neckline="scoop", ease=0.05),
        _g("tshirt", res, sleeves="long", ease=0.04),
        _g("trousers", res, length="shorts", ease=0.03), _g("trousers", res, length="knee", ease=0.05),
        _g("trousers", res, length="long", ease=0.02),
        _g("jumpsuit", res, length="knee", sleeves="none", ease=0.03),
        _g("jumpsuit", res, length="long", sleeves="short", ease=0.02),
        _g("jumpsuit", res, length="long", sleeves="none", ease=0.05)]
    rng = np.random.default_rng(seed + 1)
    # anny phenotype order: gender, age, muscle, weight, height, proportions
    bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")] + [
        {"model": "anny", "shape": [round(float(x), 4) for x in rng.uniform(0.2, 0.8, 6)]}
        for _ in range(29)]
    motions = [_m(name_, n, speed=s, amplitude=a) for name_, s, a in (
        ("walk", 1.0, 1.0), ("walk", 1.3, 1.2), ("walk", 0.7, 0.8), ("run", 1.0, 1.0),
        ("run", 1.2, 1.1), ("twirl", 1.0, 1.0), ("twirl", 0.7, 1.2), ("kick", 1.0, 1.0),
        ("kick", 1.2, 0.8), ("arm_swing", 1.0, 1.0), ("arm_swing", 1.4, 1.3), ("jump", 1.0, 1.0),
        ("jump", 0.8, 0.9), ("sit_stand", 1.0, 1.0), ("sit_stand", 1.5, 1.0),
        ("walk+arm_swing", 1.0, 1.0), ("walk+twirl", 1.0, 1.0), ("run+arm_swing", 1.0, 1.0),
        ("twirl+arm_swing", 1.0, 1.0), ("kick+arm_swing", 1.0, 1.0), ("jump+arm_swing", 1.0, 1.0))]
    keys = {"g": [garment_key(g) for g in garments], "b": [body_key(b) for b in bodies],
            "m": [motion_key(m) for m in motions]}
    return Spec(
        name="medium", garments=garments, bodies=bodies, motions=motions,
        materials=["silk", "cotton", "denim"],
        held_out={"test": {"garments": [keys["g"][5]], "bodies": keys["b"][3:6],
                           "motions": [keys["m"][6], keys["m"][20]]},
                  "val": {"garments": [keys["g"][9]], "bodies": keys["b"][6:8],
                          "motions": [keys["m"][8]]}},
        seed=seed, sample=520)

# --------------------------------------------------------------------------- one item
_MODELS: Dict[str, Any] = {}
_BODIES: Dict[str, Any] = {}


def body_model(name: str):
    """A (per-process cached) body model: ``capsule`` or ``anny``."""
    if name not in _MODELS:
        from garmentgnn.body import AnnyBodyModel, CapsuleBodyModel
        if name == "capsule":
            _MODELS[name] = CapsuleBodyModel()
        elif name == "anny":
            _MODELS[name] = AnnyBodyModel()
        else:
            raise ValueError(f"body model: unknown {name!r}; use 'capsule' or 'anny'")
    return _MODELS[name]


def build_body(spec: Dict[str, Any]):
    key = body_key(spec)
    if key not in _BODIES:
        _BODIES[key] = body_model(spec["model"])(spec["shape"])
    return _BODIES[key]


def build_inputs(item: Dict[str, Any], num_frames: Optional[int] = None):
    """``(garment, body, motion, material, settings_dict)`` of an item."""
    import torch

    from garmentgnn.garments import make_garment
    from garmentgnn.motion import make_motion
    from garmentgnn.physics.materials import MATERIALS

    body = build_body(item["body"])
    g = item["garment"]
    garment = make_garment(g["kind"], body, resolution=g["resolution"], **g.get("params", {}))
    m = item["motion"]
    model = body_model(item["body"]["model"])
    motion = make_motion(m["name"], model.skeleton, num_frames=num_frames or m["num_frames"],
                         fps=float(item["settings"].get("fps", 30.0)), speed=m["speed"],
                         amplitude=m["amplitude"], seed=item["seed"],
                         rest_joints=body.joints.to(torch.float64))
    material = MATERIALS[item["material"]]
    return garment, body, motion, material


def default_simulate(engine: str = "torch"):
    """The engine's simulate function: :func:`garmentgnn.sim.simulate` (``torch``) or
    :func:`garmentgnn.sim.blender.simulate_blender` (``blender``)."""
    if engine == "blender":
        from garmentgnn.sim.blender import simulate_blender
        return simulate_blender
    from garmentgnn.sim import simulate
    return simulate


def _settings(item):
    if item.get("engine", "torch") == "blender":
        from garmentgnn.sim.blender import BlenderSettings
        return BlenderSettings(**item["settings"])
    from garmentgnn.sim import SimSettings
    return SimSettings(**item["settings"])


def engine_info(engine: str, settings: Dict[str, Any]) -> Dict[str, Any]:
    """What the manifest and each sequence file record of the engine: name, version
    (the ``bpy`` package for Blender, garmentgnn's for the torch simulator), settings."""
    if engine == "blender":
        from garmentgnn.sim.blender import blender_version
        version = blender_version()
    else:
        version = store.code_version()["version"]
    return {"name": engine, "version": version, "settings": dict(settings)}


def _plain_settings(item):
    """Settings as a plain dict (test doubles of the simulator)."""
    return dict(item["settings"])


def run_item(item: Dict[str, Any], out: str, simulate_fn: Optional[Callable] = None,
             settings_fn: Optional[Callable] = None) -> Dict[str, Any]:
    """Simulate one item and write ``OUT/sequences/<id>.npz``; returns its manifest record.

    Exceptions from building or simulating are reported as ``status="failed"`` (nothing
    is written); only ``BaseException``\\ s such as ``KeyboardInterrupt`` propagate."""
    import torch
    t0 = time.perf_counter()
    seed = item["seed"]
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    rec = store.pending_record(item)
    try:
        sim = simulate_fn or default_simulate(item.get("engine", "torch"))
        if settings_fn is None:
            settings_fn = _settings if simulate_fn is None else _plain_settings
        settings = settings_fn(item)
        garment, body, motion, material = build_inputs(item)
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
        pen_limit = float(getattr(res, "max_penetration", np.inf))
        arrays = {
            "garment_vertices": garment.vertices.numpy().astype(np.float32),
            "garment_faces": garment.faces.numpy().astype(np.int64),
            "garment_uv": garment.uv.numpy().astype(np.float32),
            "garment_face_uv": garment.face_uv.numpy().astype(np.float32),
            "garment_pinned": (np.zeros(V, bool) if garment.pinned is None
                               else garment.pinned.numpy().astype(bool)),
            "body_shape": (np.zeros(0, np.float64) if body.shape is None
                           else body.shape.double().numpy()),
            "motion_rotations": motion.rotations.float().numpy(),
            "motion_translation": motion.translation.float().numpy(),
            "positions": P,
            "converged": converged,
            "newton_iterations": arr("newton_iterations", np.int32, np.zeros(T)),
            "residual": arr("residual", np.float32, np.zeros(T)),
        }
        if pen is not None:
            arrays["penetration"] = pen
        meta = {k: item[k] for k in ("id", "garment", "body", "motion", "material", "settings",
                                     "seed", "split")}
        meta["held_out"] = item.get("held_out", [])
        meta.update(
            format_version=store.FORMAT_VERSION, num_frames=T, num_vertices=V,
            num_faces=int(garment.faces.shape[0]), fps=float(motion.fps),
            joint_names=list(motion.joint_names), garment_name=garment.name,
            material_params=asdict(material), nonconverged_frames=int((~converged).sum()),
            penetrating_frames=None if pen is None else int((pen > pen_limit).sum()),
            max_penetration_depth=None if pen is None else float(pen.max()),
            code={"version": store.code_version()["version"]},
            engine=engine_info(item.get("engine", "torch"), item["settings"]))
        path = Path(out) / store.SEQUENCES / f"{item['id']}.npz"
        store.write_sequence(path, arrays, meta)
        rec = store.record_from_meta(meta)
        rec.update(code=store.code_version(), sha256=store.file_sha256(path))
    except Exception as e:
        tb = traceback.format_exc(limit=3)
        rec.update(status="failed", message=f"{type(e).__name__}: {e}\n{tb}")
    rec["seconds"] = round(time.perf_counter() - t0, 3)
    return rec


def _init_worker(parent_pid: Optional[int] = None) -> None:
    import torch

    from garmentgnn.data._lifeline import watch_parent
    if parent_pid is not None:  # die with the parent, even when it is SIGKILLed
        watch_parent(parent_pid)
    torch.set_num_threads(1)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:
        pass


# --------------------------------------------------------------------------- estimate
def estimate_seconds(items: Sequence[Dict[str, Any]], workers: int,
                     simulate_fn: Optional[Callable] = None, frames: int = 3
                     ) -> Tuple[float, float]:
    """Time a short run (``frames`` motion frames; frame 0 is the initial state, so
    ``frames - 1`` simulated ones) of the item with the largest garment resolution in
    ``items``, in this process with one thread, and extrapolate:
    ``sum(T - 1) * seconds_per_frame / workers``.  Returns ``(estimate_s,
    seconds_per_frame)``.  Ignores per-item setup and worker start-up; over-estimates for
    garments smaller than the calibration one."""
    import torch

    from garmentgnn.garments import RESOLUTIONS
    if not items:
        return 0.0, 0.0

    def res(it):
        r = it["garment"]["resolution"]
        return RESOLUTIONS[r] if isinstance(r, str) else int(r)

    probe = max(items, key=res)
    sim = simulate_fn or default_simulate(probe.get("engine", "torch"))
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        garment, body, motion, material = build_inputs(probe, num_frames=frames)
        settings = (_settings if simulate_fn is None else _plain_settings)(probe)
        t0 = time.perf_counter()
        sim(garment, body, motion, material, settings=settings, progress=None)
        per_frame = (time.perf_counter() - t0) / max(1, frames - 1)
    finally:
        torch.set_num_threads(n_threads)
    if probe.get("engine", "torch") == "blender":  # pre-roll frames and worker start-up count
        preroll = int(probe["settings"].get("preroll_frames", 0))
        per_frame *= (frames - 1) / (frames + preroll)
        total_frames = sum(it["motion"]["num_frames"] + preroll for it in items)
    else:
        total_frames = sum(max(1, it["motion"]["num_frames"] - 1) for it in items)
    return total_frames * per_frame / max(1, workers), per_frame


# --------------------------------------------------------------------------- driver
@dataclass
class Summary:
    total: int
    done: int = 0
    skipped: int = 0
    failed: int = 0
    pending: int = 0
    seconds: float = 0.0
    failures: List[str] = field(default_factory=list)

    def __str__(self) -> str:
        s = (f"{self.total} items: {self.done} simulated, {self.skipped} skipped (already "
             f"done), {self.failed} failed, {self.pending} pending; {self.seconds:.1f} s")
        for f in self.failures[:10]:
            s += f"\n  FAILED {f}"
        return s


class SpecMismatch(RuntimeError):
    pass


def _load_existing(out: Path, spec_json: Dict[str, Any], force: bool = False
                   ) -> Dict[str, Dict[str, Any]]:
    """Check ``OUT/spec.json`` (or, without it, ``OUT/manifest.json``) holds this
    dataset; return previous manifest records by id.  ``force``: replace another
    dataset's spec and manifest instead of refusing."""
    spec_path = out / store.SPEC
    ids = [it["id"] for it in spec_json["items"]]
    if force:
        store.atomic_write_json(spec_path, spec_json)
    elif not spec_path.exists() and (out / store.MANIFEST).exists():
        try:
            other = [r["id"] for r in store.read_manifest(out)["items"]]
        except (ValueError, KeyError, TypeError):
            other = None
        if other is None or not set(other) <= set(ids):
            raise SpecMismatch(f"{out} holds another dataset's {store.MANIFEST}; use another "
                               f"--out, or --force to overwrite it")
    if spec_path.exists():
        old = store.read_json(spec_path, "--force to overwrite it")
        if [it.get("id") for it in old.get("items", [])] != ids:
            raise SpecMismatch(
                f"{out} holds a different dataset (spec {old.get('name')!r}, seed "
                f"{old.get('seed')}); use another --out, or --force to overwrite it")
    else:
        store.atomic_write_json(spec_path, spec_json)
    prev = {}
    if (out / store.MANIFEST).exists():
        try:
            prev = {r["id"]: r for r in store.read_manifest(out)["items"]}
        except (ValueError, KeyError):
            prev = {}
    return prev


def generate(spec: Spec, out, workers: int = 1, limit: Optional[int] = None,
             simulate_fn: Optional[Callable] = None, settings_fn: Optional[Callable] = None,
             retry_failed: bool = False, progress: bool = True, estimate: bool = False,
             log: Optional[Callable[[str], None]] = None, force: bool = False,
             backend: str = "local", address: Optional[str] = None) -> Summary:
    """Generate (or resume generating) ``spec`` into ``out``.

    Items whose sequence file exists and validates are skipped; failed items are kept
    as failed unless ``retry_failed``.  ``workers=0`` runs in this process (debugging,
    tests); ``workers>=1`` uses a spawn-context process pool, one torch thread each.
    ``limit``: simulate at most this many (pending) items in this call.
    ``simulate_fn``/``settings_fn``: dependency injection for tests (picklable,
    module-level callables); default ``garmentgnn.sim.simulate`` / ``SimSettings``.
    The manifest is rewritten atomically after every finished item.  A folder holding
    another dataset raises :class:`SpecMismatch` unless ``force``.  Pool workers end
    when this process does, even when it is killed with ``SIGKILL``.
    ``backend="ray"`` runs one Ray task per item instead (:mod:`garmentgnn.data.ray_backend`;
    ``workers`` CPUs of a local cluster, or the cluster at ``address``).
    """
    if backend not in ("local", "ray"):
        raise ValueError(f"`backend`: 'local' or 'ray', got {backend!r}")
    if not str(out).strip():
        raise ValueError("`out`: empty path; name the output folder, e.g. --out data/tiny")
    if Path(out).exists() and not Path(out).is_dir():
        raise ValueError(f"`out`: {out} is a file; name a folder for the dataset")
    t_start = time.perf_counter()
    if spec.engine == "blender" and simulate_fn is None:
        from garmentgnn.sim.blender import require_blender
        require_blender()  # before any file is written: say how to install `bpy`
    if log is None:
        def log(msg: str) -> None:
            print(msg, flush=True)
    out = Path(out)
    (out / store.SEQUENCES).mkdir(parents=True, exist_ok=True)
    store.remove_stale_temporaries(out)
    store.remove_stale_temporaries(out / store.SEQUENCES)
    spec_json = spec.to_json()
    items = spec_json["items"]
    prev = _load_existing(out, spec_json, force)
    header = {k: v for k, v in spec_json.items() if k != "items"}
    header["code"] = store.code_version()
    header["engine"] = engine_info(spec.engine, spec.settings)

    records: Dict[str, Dict[str, Any]] = {}
    todo: List[Dict[str, Any]] = []
    summary = Summary(total=len(items))
    for it in items:
        path = out / store.SEQUENCES / f"{it['id']}.npz"
        old = prev.get(it["id"])
        if path.exists():
            msg = store.validate_sequence(path, it["id"])
            if msg is None and old and old.get("sha256") \
                    and store.file_sha256(path) != old["sha256"]:
                msg = "SHA-256 differs from the manifest's"
            if msg is None:
                records[it["id"]] = (old if old and old.get("status") == "ok"
                                     else dict(store.record_from_meta(store.read_meta(path)),
                                               sha256=store.file_sha256(path)))
                summary.skipped += 1
                continue
            log(f"warning: {path.name} is invalid ({msg}); simulating it again")
            path.unlink()
        if old and old.get("status") == "failed" and not retry_failed:
            records[it["id"]] = old
            summary.skipped += 1
            summary.failed += 1
            summary.failures.append(f"{it['id']}: {old.get('message', '').splitlines()[:1]}")
            continue
        records[it["id"]] = store.pending_record(it)
        todo.append(it)
    if limit is not None:
        todo = todo[:max(0, limit)]

    def flush():
        store.write_manifest(out, [records[it["id"]] for it in items], header)

    flush()
    if estimate and todo:
        est, per = estimate_seconds(todo, max(1, workers), simulate_fn)
        log(f"estimate: {len(todo)} items, "
            f"{sum(i['motion']['num_frames'] - 1 for i in todo)} simulated frames at "
            f"{per:.3f} s/frame on {max(1, workers)} worker(s) -> ~{est / 60:.1f} min")

    bar = None
    if progress and todo:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(todo), desc=f"generate {spec.name}", unit="seq",
                   file=sys.stderr)

    def finish(rec):
        records[rec["id"]] = rec
        if rec["status"] == "ok":
            summary.done += 1
        else:
            summary.failed += 1
            summary.failures.append(f"{rec['id']}: {rec['message'].splitlines()[0]}")
        flush()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(failed=summary.failed)

    try:
        if backend == "ray":
            from garmentgnn.data.ray_backend import run_on_ray
            run_on_ray(todo, str(out), finish, simulate_fn, settings_fn, workers=workers,
                       address=address)
        elif workers <= 0:
            import torch
            n_threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                for it in todo:
                    finish(run_item(it, str(out), simulate_fn, settings_fn))
            finally:
                torch.set_num_threads(n_threads)
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                     initializer=_init_worker,
                                     initargs=(os.getpid(),)) as pool:
                pending = {pool.submit(run_item, it, str(out), simulate_fn, settings_fn)
                           for it in todo}
                try:
                    while pending:
                        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for fut in finished:
                            finish(fut.result())
                except BaseException:
                    for fut in pending:
                        fut.cancel()
                    raise
    except BrokenProcessPool as e:
        raise RuntimeError(f"a worker process died ({e}); finished items are saved in "
                           f"{out}; rerun the same command to resume") from e
    finally:
        if bar is not None:
            bar.close()
        flush()
        summary.seconds = time.perf_counter() - t_start
        summary.pending = sum(r["status"] == "pending" for r in records.values())
    return summary
