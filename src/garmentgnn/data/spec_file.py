"""A dataset spec from a YAML file (``garmentgnn generate --spec my_dataset.yaml``): the
user's garment meshes and BVH mocap beside templates and generators, as one
:class:`~garmentgnn.data.presets.Spec` (docs/own_garment.md)::

    name: my_dataset
    engine: torch            # torch | blender | auto (default auto)
    fps: 30                  # the dataset's frame rate: BVH takes are resampled to it
    frames: 60               # frames per sequence
    seed: 0
    settings: {substeps: 4}  # the engine's settings over its defaults (optional)
    garments:
      - file: shirt.obj      # relative to this file; OBJ, PLY, glTF/GLB ...
      - template: skirt      # a procedural garment
        resolution: 300
        params: {length: mini}
        held_out: test       # test | val: the split of every item holding it
    bodies:
      - regular              # anny's named shapes, or {model: anny, shape: [6 floats]}
    motions:
      - file: walk.bvh
        scale: 0.01          # metres per file unit (CMU and Mixamo: centimetres)
        up: Y                # the file's up axis (Y for most BVH; Z for Blender's Z-up export)
        fps: 120             # optional: the take's rate, checked against its Frame Time
        start: 0             # optional: first frame (at the dataset's fps)
        mapping: {pelvis_j: pelvis}  # file joint -> body joint or role, where names differ
      - generator: walk      # a procedural motion (speed, amplitude optional)
    materials: [silk]

Every file is read and checked when the spec is read (:func:`load_spec`), before
anything is written: garments against every body (:func:`~garmentgnn.data.assets.check_fit`),
motions on every body model; refusals are ``ValueError`` naming the file and the fix.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import yaml

from garmentgnn.body.factory import build_body
from garmentgnn.data.assets import (check_fit, file_name, motion_from_entry, read_garment_file,
                                    sha256_of)
from garmentgnn.data.keys import body_key, garment_key, motion_key
from garmentgnn.data.presets import BLENDER_SETTINGS, Spec, resolve_engine
from garmentgnn.physics.materials import MATERIALS

TOP = {"name", "engine", "fps", "frames", "seed", "settings", "garments", "bodies", "motions",
       "materials", "sample"}
GARMENT = {"file", "template", "resolution", "params", "held_out"}
MOTION = {"file", "generator", "scale", "up", "fps", "start", "mapping", "speed", "amplitude",
          "held_out"}
BODY = {"model", "shape", "held_out"}
SPLITS = ("test", "val")
TORCH_SETTINGS = {"substeps": 4, "preroll_frames": 6}


def _fail(path: Path, msg: str) -> ValueError:
    return ValueError(f"{path}: {msg}")


def _number(path: Path, where: str, value: Any, integer: bool = False,
            low: Optional[float] = None, positive: bool = False) -> Any:
    """``value`` of the spec's ``where`` checked as a number (``integer``: an int) of at
    least ``low`` (``positive``: above 0): a ``ValueError`` naming the file and the key,
    instead of Python's "could not convert string to float" or a value that passes
    and fails each item later."""
    kind = "an integer" if integer else "a number"
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or (isinstance(value, float)
                                             and not math.isfinite(value)):
        raise _fail(path, f"`{where}`: expected {kind}, got {value!r}")
    if (low is not None and value < low) or (positive and not value > 0):
        bound = "above 0" if positive else f">= {low:g}"
        raise _fail(path, f"`{where}`: expected {kind} {bound}, got {value!r}")
    return value


def _mapping(path: Path, where: str, value: Any) -> Dict[str, str]:
    """A ``mapping`` of file joint -> body joint or role (names as text)."""
    if value is None:
        return {}
    if not isinstance(value, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in value.items()):
        raise _fail(path, f"`{where}`: expected a mapping of file joint -> body joint or "
                          f"role, e.g. {{hip_root: pelvis}}, got {value!r}")
    return dict(value)


def _list(path: Path, doc: Dict[str, Any], key: str) -> List[Any]:
    v = doc.get(key)
    if not isinstance(v, list) or not v:
        raise _fail(path, f"`{key}`: expected a non-empty list, got {v!r}")
    return v


def _entry(path: Path, e: Any, allowed: set, what: str, i: int) -> Dict[str, Any]:
    if isinstance(e, str) and what == "bodies":
        e = {"model": "anny", "shape": e}
    if not isinstance(e, dict):
        raise _fail(path, f"`{what}[{i}]`: expected a mapping, got {e!r}")
    unknown = sorted(set(e) - allowed)
    if unknown:
        raise _fail(path, f"`{what}[{i}]`: unknown key(s) {unknown}; known: {sorted(allowed)}")
    if e.get("held_out") not in (None,) + SPLITS:
        raise _fail(path, f"`{what}[{i}].held_out`: expected test or val, got "
                          f"{e['held_out']!r}")
    return dict(e)


def _file(path: Path, e: Dict[str, Any], what: str, i: int) -> Dict[str, Any]:
    """``file`` resolved against the spec's folder, with its ``path`` and ``sha256``."""
    name = e["file"]
    if not isinstance(name, str) or not name.strip():
        raise _fail(path, f"`{what}[{i}].file`: expected a file name, got {name!r}")
    target = (path.parent / name).resolve()
    if not target.is_file():
        raise _fail(path, f"`{what}[{i}].file`: {target}: no such file (paths are relative "
                          f"to the spec file's folder)")
    return {"file": name, "path": str(target), "sha256": sha256_of(target)}


def _garment(path: Path, e: Dict[str, Any], i: int) -> Dict[str, Any]:
    if ("file" in e) == ("template" in e):
        raise _fail(path, f"`garments[{i}]`: give either `file` (a mesh) or `template` (a "
                          f"garment kind)")
    if "template" in e:
        params = e.get("params") or {}
        if not isinstance(params, dict):
            raise _fail(path, f"`garments[{i}].params`: expected a mapping of the "
                              f"template's parameters, got {params!r}")
        return {"kind": e["template"], "params": dict(params),
                "resolution": _number(path, f"garments[{i}].resolution",
                                      e.get("resolution", 300), integer=True, low=1)}
    if set(e) - {"file", "held_out"}:
        raise _fail(path, f"`garments[{i}]`: a mesh file takes no "
                          f"{sorted(set(e) - {'file', 'held_out'})}")
    g = _file(path, e, "garments", i)
    garment = read_garment_file(g["path"], name=file_name(g))
    return dict(g, kind=file_name(g), params={}, resolution=garment.num_vertices)


def _motion(path: Path, e: Dict[str, Any], i: int, frames: int) -> Dict[str, Any]:
    if ("file" in e) == ("generator" in e):
        raise _fail(path, f"`motions[{i}]`: give either `file` (a BVH) or `generator` (a "
                          f"procedural motion)")
    if "generator" in e:
        extra = sorted(set(e) - {"generator", "speed", "amplitude", "held_out"})
        if extra:
            raise _fail(path, f"`motions[{i}]`: a generator takes no {extra}")
        return {"name": e["generator"], "num_frames": frames,
                "speed": float(_number(path, f"motions[{i}].speed", e.get("speed", 1.0),
                                       positive=True)),
                "amplitude": float(_number(path, f"motions[{i}].amplitude",
                                           e.get("amplitude", 1.0), low=0))}
    extra = sorted(set(e) & {"speed", "amplitude"})
    if extra:
        raise _fail(path, f"`motions[{i}]`: a BVH file takes no {extra}")
    up = str(e.get("up", "Y")).upper()
    if up not in ("Y", "Z"):
        raise _fail(path, f"`motions[{i}].up`: expected Y or Z (the file's up axis), got "
                          f"{e.get('up')!r}")
    scale = _number(path, f"motions[{i}].scale", e.get("scale", 1.0), positive=True)
    start = _number(path, f"motions[{i}].start", e.get("start", 0), integer=True, low=0)
    mapping = _mapping(path, f"motions[{i}].mapping", e.get("mapping"))
    m = _file(path, e, "motions", i)
    m.update(name=file_name(m), num_frames=frames, speed=1.0, amplitude=1.0,
             scale=float(scale), up=up, start=int(start), mapping=mapping)
    if e.get("fps") is not None:
        m["fps"] = float(_number(path, f"motions[{i}].fps", e["fps"], positive=True))
    return m


def _settings(path: Path, doc: Dict[str, Any], engine: str) -> Tuple[Dict[str, Any], float]:
    settings = dict(BLENDER_SETTINGS if engine == "blender" else TORCH_SETTINGS)
    given = doc.get("settings") or {}
    if not isinstance(given, dict):
        raise _fail(path, f"`settings`: expected a mapping, got {given!r}")
    fps = doc.get("fps", given.get("fps", 30.0))
    if "fps" in given:
        _number(path, "settings.fps", given["fps"], positive=True)
    if "fps" in given and float(given["fps"]) != float(fps):
        raise _fail(path, f"`fps` {fps} and `settings.fps` {given['fps']} disagree; give the "
                          f"dataset's frame rate once, as `fps`")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not 0 < fps <= 1000:
        raise _fail(path, f"`fps`: expected frames per second, e.g. 30, got {fps!r}")
    settings.update(given)
    settings["fps"] = float(fps)
    return settings, float(fps)


def yaml_problem(exc: Exception) -> str:
    """A YAML error in one line that keeps where it is: ``line L, column C: problem``
    (the first line of PyYAML's message names neither)."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    what = f"{problem} ({context})" if context else str(problem)
    return f"line {mark.line + 1}, column {mark.column + 1}: {what}" if mark else what


def load_spec(path, engine: Optional[str] = None, seed: Optional[int] = None) -> Spec:
    """The :class:`Spec` of a YAML spec file (module doc), its files read and checked;
    ``engine`` / ``seed`` replace the file's.  ``ValueError`` (naming the file and the
    fix) for anything the dataset could not be made from."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"`spec`: {path}: no such file; write a dataset spec "
                         f"(docs/own_garment.md)")
    try:
        doc = yaml.safe_load(path.read_text())
    except UnicodeDecodeError as exc:
        raise _fail(path, f"not UTF-8 text (byte {exc.start}); save it as UTF-8") from None
    except yaml.YAMLError as exc:
        raise _fail(path, f"not readable YAML ({yaml_problem(exc)})") from None
    if not isinstance(doc, dict):
        raise _fail(path, "expected a mapping of name, garments, bodies, motions, ...")
    unknown = sorted(set(doc) - TOP)
    if unknown:
        raise _fail(path, f"unknown key(s) {unknown}; known: {sorted(TOP)}")
    engine = resolve_engine(engine or doc.get("engine", "auto"))
    settings, fps = _settings(path, doc, engine)
    frames = doc.get("frames", 60)
    if not isinstance(frames, int) or isinstance(frames, bool) or frames < 3:
        raise _fail(path, f"`frames`: expected 3 or more frames per sequence, got {frames!r}")
    held: Dict[str, Dict[str, List[str]]] = {s: {} for s in SPLITS}

    def hold(e, part, key):
        if e.get("held_out"):
            held[e["held_out"]].setdefault(part, []).append(key)

    bodies = []
    for i, e in enumerate(_list(path, doc, "bodies")):
        e = _entry(path, e, BODY, "bodies", i)
        b = {"model": e.get("model", "anny"), "shape": e.get("shape", "regular")}
        try:
            build_body(b)
        except (ValueError, TypeError, KeyError) as exc:
            raise _fail(path, f"`bodies[{i}]`: {exc}") from None
        bodies.append(b)
        hold(e, "bodies", body_key(b))
    garments = []
    for i, e in enumerate(_list(path, doc, "garments")):
        e = _entry(path, e, GARMENT, "garments", i)
        g = _garment(path, e, i)
        if "file" in g:
            garment = read_garment_file(g["path"], name=g["kind"])
            for b in bodies:
                check_fit(garment, build_body(b), f"{g['path']} on body {body_key(b)}")
        garments.append(g)
        hold(e, "garments", garment_key(g))
    motions = []
    for i, e in enumerate(_list(path, doc, "motions")):
        e = _entry(path, e, MOTION, "motions", i)
        m = _motion(path, e, i, frames)
        if "file" in m:
            for model in sorted({b["model"] for b in bodies}):  # skeletons: one per model
                body = build_body(next(b for b in bodies if b["model"] == model))
                motion_from_entry(m, body, fps)
        motions.append(m)
        hold(e, "motions", motion_key(m))
    materials = doc.get("materials", ["silk"])
    if not isinstance(materials, list) or not materials:
        raise _fail(path, f"`materials`: expected a non-empty list, got {materials!r}")
    name = str(doc.get("name") or path.stem)
    seed = int(_number(path, "seed", doc.get("seed", 0), integer=True)) if seed is None \
        else int(seed)
    try:
        spec = Spec(name=name, garments=garments, bodies=bodies, motions=motions,
                    materials=[str(x) for x in materials], settings=settings,
                    held_out={k: v for k, v in held.items() if v}, seed=seed,
                    sample=doc.get("sample"), engine=engine)
        spec.items()
    except ValueError as exc:
        raise _fail(path, str(exc)) from None
    bad = [m for m in spec.materials if m not in MATERIALS]
    if bad:
        raise _fail(path, f"`materials`: unknown {bad}; choose from {sorted(MATERIALS)}")
    return spec


__all__ = ["load_spec"]
