"""Dataset specs: a spec (garments x bodies x motions x materials), the presets
(``tiny``, ``small``, ``medium``, ``learn``, ``paper``) and the engines that simulate them.

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

:mod:`garmentgnn.data.generate` simulates a spec's items into a dataset folder.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import random
from dataclasses import asdict, dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import torch

from garmentgnn.body.factory import body_model, build_body
from garmentgnn.data.assets import garment_from_entry, motion_from_entry
from garmentgnn.data.keys import body_key, garment_key, motion_key
from garmentgnn.data.perturb import perturbed_garment
from garmentgnn.garments import make_garment
from garmentgnn.motion import make_motion
from garmentgnn.physics.materials import MATERIALS
from garmentgnn.sim.blender import blender_available

# --------------------------------------------------------------------------- spec
#: garment: {"kind", "params" (template kwargs), "resolution"}
#: body: {"model": "capsule" | "anny", "shape": preset name or list of floats}
#: motion: {"name", "num_frames", "speed", "amplitude"}


def _canon(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"))


_PART = {"garments": "garment", "bodies": "body", "motions": "motion"}


def _portable(desc: Dict[str, Any]) -> Dict[str, Any]:
    """``desc`` without the absolute ``path`` of its file entries (their name and
    content hash stay): an item's id does not depend on where the files lie."""
    return {k: ({kk: vv for kk, vv in v.items() if kk != "path"}
                if isinstance(v, dict) and "file" in v else v) for k, v in desc.items()}


def _repeated(spec: "Spec") -> str:
    """The entries of ``spec``'s grid that are listed more than once, by part and
    position (``garments[0] and garments[2] (skirt.obj)``)."""
    out = []
    for part, entries, key in (("garments", spec.garments, garment_key),
                               ("bodies", spec.bodies, body_key),
                               ("motions", spec.motions, motion_key),
                               ("materials", spec.materials, str)):
        seen: Dict[str, List[int]] = {}
        for i, e in enumerate(entries):
            seen.setdefault(key(e), []).append(i)
        for k, where in seen.items():
            if len(where) > 1:
                out.append(" and ".join(f"{part}[{i}]" for i in where) + f" ({k})")
    return "; ".join(out) or "the same item twice"


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
    settings: Dict[str, Any] = field(
        default_factory=lambda: {"fps": 30.0, "substeps": 4, "preroll_frames": 6})
    held_out: Dict[str, Dict[str, List[str]]] = field(default_factory=dict)
    seed: int = 0
    sample: Optional[int] = None
    engine: str = "torch"

    def __post_init__(self) -> None:
        if self.engine not in ENGINES:
            raise ValueError(f"`engine`: unknown {self.engine!r}; choose one of {ENGINES}")

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
            digest = hashlib.sha1(f"{_canon(_portable(desc))}|seed={self.seed}".encode()
                                  ).hexdigest()
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
            raise ValueError(f"spec {self.name!r}: duplicate items (repeated grid entries): "
                             f"{_repeated(self)}; give each entry once")
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
        return "blender" if blender_available() else "torch"
    if name not in ENGINES:
        raise ValueError(f"`engine`: unknown {name!r}; choose 'auto' or one of {ENGINES}")
    return name


def preset(name: str, seed: int = 0, engine: str = "torch") -> Spec:
    """``tiny`` (tests, < 1 min), ``small`` (tens of minutes on 2 cores), ``medium``
    (Blender, about an hour on 2 cores), ``learn`` (Blender, about 400 small garments to
    learn from, sized for 2 cores) or ``paper`` (the paper's scale; hours to days),
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
    if name == "learn":
        return _learn(seed)
    if name == "learn_long":
        return _learn_long(seed)
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


PRESETS = ("tiny", "small", "medium", "learn", "learn_long", "paper")


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
        _g("skirt", res, length="knee", flare="a-line"),
        _g("skirt", res, length="mini", flare="flared"),
        _g("skirt", res, length="midi", flare="pencil"),
        _g("skirt", res, length="long", flare="full"),
        _g("dress", res, length="knee", flare="a-line"),
        _g("dress", res, length="midi", flare="flared"),
        _g("dress", res, length="long", flare="full", top="sleeveless"),
        _g("tshirt", res, sleeves="short", ease=0.02),
        _g("tshirt", res, sleeves="none", length="waist", neckline="scoop", ease=0.05),
        _g("tshirt", res, sleeves="long", ease=0.04),
        _g("trousers", res, length="shorts", ease=0.03),
        _g("trousers", res, length="knee", ease=0.05),
        _g("trousers", res, length="long", ease=0.02),
        _g("jumpsuit", res, length="knee", sleeves="none", ease=0.03),
        _g("jumpsuit", res, length="long", sleeves="short", ease=0.02),
        _g("jumpsuit", res, length="long", sleeves="none", ease=0.05)]
    rng = np.random.default_rng(seed + 1)
    # anny phenotype order: gender, age, muscle, weight, height, proportions
    bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")] + [
        {"model": "anny", "shape": [round(float(x), 4) for x in rng.uniform(0.2, 0.8, 6)]}
        for _ in range(29)]
    motions = _motions(n)
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


def _motions(n: int) -> List[Dict[str, Any]]:
    """The 21 motions of ``medium`` and ``learn``: the 7 generators at 2-3 (speed,
    amplitude) variants and 6 even mixes of two."""
    return [_m(name_, n, speed=s, amplitude=a) for name_, s, a in (
        ("walk", 1.0, 1.0), ("walk", 1.3, 1.2), ("walk", 0.7, 0.8), ("run", 1.0, 1.0),
        ("run", 1.2, 1.1), ("twirl", 1.0, 1.0), ("twirl", 0.7, 1.2), ("kick", 1.0, 1.0),
        ("kick", 1.2, 0.8), ("arm_swing", 1.0, 1.0), ("arm_swing", 1.4, 1.3), ("jump", 1.0, 1.0),
        ("jump", 0.8, 0.9), ("sit_stand", 1.0, 1.0), ("sit_stand", 1.5, 1.0),
        ("walk+arm_swing", 1.0, 1.0), ("walk+twirl", 1.0, 1.0), ("run+arm_swing", 1.0, 1.0),
        ("twirl+arm_swing", 1.0, 1.0), ("kick+arm_swing", 1.0, 1.0), ("jump+arm_swing", 1.0, 1.0))]


def _learn(seed: int) -> Spec:
    """A dataset sized to learn from on a small machine: a seeded sample of 420 sequences
    of 60 frames of about 400-vertex garments (25 cuts covering every kind and every
    length, flare, top, sleeve and neckline of the templates but the trousers' shorts,
    which the template refuses on 6 of these 28 bodies, whose thighs touch), 28 anny body
    shapes, the 21 motions of ``medium`` and three fabrics.  Held out for test: two
    garments (a dress and a jumpsuit), three bodies, two motions; for val: one garment (a
    T-shirt), two bodies, one motion.  Sized for about 45 minutes with the Blender engine
    and two workers on two otherwise idle cores (measured: docs/dataset.md)."""
    r = 400
    garments = [
        _g("skirt", r, length="mini", flare="a-line"),
        _g("skirt", r, length="mini", flare="flared"),
        _g("skirt", r, length="knee", flare="pencil"),
        _g("skirt", r, length="knee", flare="full"),
        _g("skirt", r, length="midi", flare="flared"),
        _g("skirt", r, length="long", flare="a-line"),
        _g("dress", r, length="knee", flare="a-line"),
        _g("dress", r, length="midi", flare="flared"),
        _g("dress", r, length="mini", flare="full", top="strapless"),
        _g("dress", r, length="long", flare="full", top="sleeveless", neckline="crew"),
        _g("dress", r, length="midi", flare="a-line", top="sleeveless", sleeves="short"),
        _g("tshirt", r, sleeves="short"),
        _g("tshirt", r, sleeves="none", length="waist", neckline="scoop"),
        _g("tshirt", r, sleeves="long", ease=0.04),
        _g("tshirt", r, sleeves="elbow", neckline="scoop"),
        _g("tshirt", r, sleeves="short", length="waist", neckline="scoop", ease=0.05),
        _g("tshirt", r, sleeves="none", ease=0.03),
        _g("trousers", r, length="knee", ease=0.05),
        _g("trousers", r, length="capri"),
        _g("trousers", r, length="long", ease=0.03),
        _g("trousers", r, length="long", ease=0.05),
        _g("jumpsuit", r, length="long", sleeves="short"),
        _g("jumpsuit", r, length="knee", sleeves="none", ease=0.03),
        _g("jumpsuit", r, length="capri", sleeves="elbow"),
        _g("jumpsuit", r, length="long", sleeves="long", ease=0.04)]
    rng = np.random.default_rng(seed + 2)
    # anny phenotype order: gender, age, muscle, weight, height, proportions
    bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")] + [
        {"model": "anny", "shape": [round(float(x), 4) for x in rng.uniform(0.2, 0.8, 6)]}
        for _ in range(25)]
    motions = _motions(60)
    keys = {"g": [garment_key(g) for g in garments], "b": [body_key(b) for b in bodies],
            "m": [motion_key(m) for m in motions]}
    return Spec(
        name="learn", garments=garments, bodies=bodies, motions=motions,
        materials=["silk", "cotton", "denim"],
        held_out={"test": {"garments": [keys["g"][7], keys["g"][23]], "bodies": keys["b"][3:6],
                           "motions": [keys["m"][6], keys["m"][20]]},
                  "val": {"garments": [keys["g"][15]], "bodies": keys["b"][6:8],
                          "motions": [keys["m"][8]]}},
        seed=seed, sample=420)


def _learn_long(seed: int) -> Spec:
    """``learn``'s held-out test design at 300 frames (10 s), to see a learned
    simulator's drift: ``learn``'s two test garments (a dress and a jumpsuit) and a train
    skirt, one of its test bodies and a train body, its held-out twirl and the train walk,
    in cotton; 12 sequences, 11 of them held out as ``learn``'s test groups (unseen
    garment, body, motion, several) and 1 of train parts only (the skirt on the train
    body, walking), which lands in ``train``.  About 12 minutes with the Blender engine
    on one core."""
    base = _learn(seed)
    g, b, m = base.garments, base.bodies, _motions(300)
    garments, bodies, motions = [g[7], g[23], g[4]], [b[3], b[1]], [m[6], m[0]]
    return Spec(
        name="learn_long", garments=garments, bodies=bodies, motions=motions,
        materials=["cotton"],
        held_out={"test": {"garments": [garment_key(x) for x in garments[:2]],
                           "bodies": [body_key(bodies[0])],
                           "motions": [motion_key(motions[0])]}},
        seed=seed)


# --------------------------------------------------------------------------- one item
def build_inputs(item: Dict[str, Any], num_frames: Optional[int] = None):
    """``(garment, body, motion, material)`` of an item: templates and generators, or
    the mesh and BVH files its entries name (:mod:`garmentgnn.data.assets`, refused
    when a file changed since the spec was read); an ensemble member's ``member``
    entry moves its rest garment (:func:`~garmentgnn.data.perturb.perturbed_garment`)."""
    body = build_body(item["body"])
    g = item["garment"]
    if "file" in g:
        garment = garment_from_entry(g, body)
    else:
        garment = make_garment(g["kind"], body, resolution=g["resolution"],
                               **g.get("params", {}))
    m = item["motion"]
    fps = float(item["settings"].get("fps", 30.0))
    if "file" in m:
        motion = motion_from_entry(m, body, fps, num_frames)
    else:
        model = body_model(item["body"]["model"])
        motion = make_motion(m["name"], model.skeleton, num_frames=num_frames or m["num_frames"],
                             fps=fps, speed=m["speed"], amplitude=m["amplitude"],
                             seed=item["seed"], rest_joints=body.joints.to(torch.float64))
    member = item.get("member")
    if member:  # an ensemble member: its rest garment moved (garmentgnn.data.ensemble)
        garment = perturbed_garment(garment, member["garment_m"], member["seed"])
    material = MATERIALS[item["material"]]
    return garment, body, motion, material


__all__ = ["BLENDER_SETTINGS", "ENGINES", "PRESETS", "Spec", "build_inputs", "preset",
           "resolve_engine"]
