"""Reading and writing garment meshes (OBJ with its own parser; PLY, glTF/GLB, STL, OFF
... through trimesh; anything else meshio reads).

Validation (:func:`load_garment`): a garment must be a non-empty triangle mesh with
finite coordinates, face indices within range, no degenerate (zero-area or repeated
index) faces, no duplicate faces and no non-manifold edges (an edge in more than two
faces).  A file breaking any of these raises ``ValueError("<path>: <problem>")``;
``repair=True`` fixes what can be fixed (see :func:`load_garment`).

UVs: taken from the file when present -- per face corner for OBJ (``f v/vt``), per vertex
for the other formats (whose vertices duplicated along UV seams are welded back by
position, keeping each corner's UV).  UVs are assumed to be metres (material
coordinates); files whose UV area is far from the 3D area (e.g. texture coordinates
in [0, 1]) are scaled uniformly to match it (``uv_scale="auto"``).  Without UVs the
``uv_fallback`` decides (default ``"isometric"``: each face's UV is its own rest
triangle laid flat, rotated to follow the front-view projection ``(x, z)`` -- zero rest
stretch/shear, grain roughly vertical).  Per-vertex ``uv`` is the UV of the vertex's
first face corner, as for the templates.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

import meshio
import numpy as np
import torch
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from garmentgnn.garments._flatten import first_corner_uv, flat_triangles, rigid_align
from garmentgnn.garments.garment import KINDS, Garment

log = logging.getLogger(__name__)

PathLike = Union[str, Path]
UV_FALLBACKS = ("isometric", "planar", "error")


class _Raw:
    def __init__(self, vertices, faces, corner_uv=None, vertex_uv=None, meta=None):
        self.vertices = vertices
        self.faces = faces
        self.corner_uv = corner_uv  # [F, 3, 2] or None
        self.vertex_uv = vertex_uv  # [V, 2] or None
        self.meta = meta or {}


def _fail(path, msg: str):
    raise ValueError(f"{path}: {msg}")


# ---------------------------------------------------------------------------------------
# readers
# ---------------------------------------------------------------------------------------
def _decode_obj(path: Path) -> str:
    """The text of an OBJ file as Blender and trimesh read it: a UTF-8 byte-order mark
    is dropped, CRLF / CR line ends are line ends, and bytes that are not UTF-8
    (latin-1 comments or object names written by older exporters) are read as
    latin-1.  A file with NUL bytes is binary, not an OBJ."""
    data = path.read_bytes()
    if b"\0" in data:
        _fail(path, "cannot parse: not a text OBJ file (binary data, NUL bytes)")
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def _read_obj(path: Path) -> _Raw:
    text = _decode_obj(path)
    V: List[List[float]] = []
    VT: List[List[float]] = []
    faces: List[Tuple[int, int, int]] = []
    ftex: List[Tuple[int, int, int]] = []
    has_tex: List[bool] = []
    meta: Dict[str, object] = {}
    for ln, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            if s.startswith("# garmentgnn "):
                for kv in s[len("# garmentgnn "):].split():
                    if "=" in kv:
                        k, v = kv.split("=", 1)
                        meta[k] = v
            continue
        tok = s.split()
        try:
            if tok[0] == "v":
                if len(tok) < 4:
                    raise ValueError("a vertex needs 3 coordinates")
                V.append([float(t) for t in tok[1:4]])
            elif tok[0] == "vt":
                if len(tok) < 3:
                    raise ValueError("a texture vertex needs 2 coordinates")
                VT.append([float(t) for t in tok[1:3]])
            elif tok[0] == "f":
                if len(tok) < 4:
                    raise ValueError("a face needs at least 3 vertices")
                vi, ti = [], []
                for t in tok[1:]:
                    parts = t.split("/")
                    a = int(parts[0])
                    vi.append(a - 1 if a > 0 else len(V) + a)
                    if len(parts) > 1 and parts[1]:
                        b = int(parts[1])
                        ti.append(b - 1 if b > 0 else len(VT) + b)
                if ti and len(ti) != len(vi):
                    raise ValueError("some corners have texture indices and some not")
                for k in range(1, len(vi) - 1):  # fan triangulation of polygons
                    faces.append((vi[0], vi[k], vi[k + 1]))
                    ftex.append((ti[0], ti[k], ti[k + 1]) if ti else (-1, -1, -1))
                    has_tex.append(bool(ti))
            elif tok[0] in ("vn", "vp", "o", "g", "s", "usemtl", "mtllib", "l", "p"):
                continue
            else:
                raise ValueError(f"unknown statement {tok[0]!r}")
        except ValueError as e:
            _fail(path, f"cannot parse line {ln} ({line.strip()[:60]!r}): {e}")
    if "pinned" in meta:
        try:
            meta["pinned"] = [int(i) for i in str(meta["pinned"]).split(",") if i]
        except ValueError:
            _fail(path, "cannot parse the 'pinned' list of the garmentgnn header")
    verts = np.asarray(V, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    corner = None
    if faces and all(has_tex):
        T = np.asarray(ftex, dtype=np.int64)
        VTa = np.asarray(VT, dtype=np.float64).reshape(-1, 2)
        bad = (T < 0) | (T >= len(VTa))
        if bad.any():
            f = int(np.nonzero(bad.any(1))[0][0])
            _fail(path, f"face {f} references texture vertex {int(T[f][bad[f]][0]) + 1} but "
                        f"the file has only {len(VTa)} texture vertices")
        corner = VTa[T]
    elif any(has_tex):
        log.warning("%s: only some faces have UVs; ignoring the file's UVs", path)
    return _Raw(verts, F, corner_uv=corner, meta=meta)


def _read_trimesh(path: Path) -> _Raw:
    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds
        _fail(path, f"cannot parse: {type(e).__name__}: {e}")
    if not isinstance(m, trimesh.Trimesh):
        _fail(path, "cannot parse: no triangle mesh in the file")
    V = np.asarray(m.vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(m.faces, dtype=np.int64).reshape(-1, 3)
    uv = None
    vis = getattr(m, "visual", None)
    if vis is not None and getattr(vis, "uv", None) is not None:
        uv = np.asarray(vis.uv, dtype=np.float64)
        if uv.shape != (len(V), 2):
            uv = None
    return _Raw(V, F, vertex_uv=uv)


def _read_meshio(path: Path) -> _Raw:
    try:
        m = meshio.read(str(path))
    except Exception as e:
        _fail(path, f"cannot parse: {type(e).__name__}: {e}")
    tris = []
    for block in m.cells:
        if block.type == "triangle":
            tris.append(np.asarray(block.data))
        elif block.type == "quad":
            q = np.asarray(block.data)
            tris += [q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
    V = np.asarray(m.points, dtype=np.float64)
    if V.ndim == 2 and V.shape[1] == 2:
        V = np.concatenate([V, np.zeros((len(V), 1))], 1)
    F = np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)
    uv = None
    for key in ("uv", "UV", "texcoord", "TCoords", "st"):
        if key in m.point_data:
            a = np.asarray(m.point_data[key], dtype=np.float64)
            if a.ndim == 2 and a.shape[0] == len(V) and a.shape[1] >= 2:
                uv = a[:, :2]
                break
    return _Raw(V, F, vertex_uv=uv)


def _read(path: Path) -> _Raw:
    ext = path.suffix.lower().lstrip(".")
    if ext == "obj":
        return _read_obj(path)
    if ext in trimesh.available_formats():
        return _read_trimesh(path)
    return _read_meshio(path)


# ---------------------------------------------------------------------------------------
# checks and repairs
# ---------------------------------------------------------------------------------------
def _face_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def _degenerate(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    rep = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    fin = np.isfinite(V).all(1)
    scale = max(float(np.ptp(V[fin], axis=0).max()), 1e-12) if fin.any() else 1.0
    with np.errstate(invalid="ignore"):
        # faces touching a NaN vertex are not "degenerate": they stay and fail validation
        return rep | (_face_areas(V, F) <= 1e-14 * scale * scale)


def _duplicates(F: np.ndarray) -> np.ndarray:
    """Mask of faces repeating an earlier face's vertex set (any order/orientation)."""
    key = np.sort(F, axis=1)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return np.arange(len(F)) != first[inv.reshape(-1)]


def _nonmanifold_edges(F: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, cnt = np.unique(e, axis=0, return_counts=True)
    return u[cnt > 2], cnt[cnt > 2]


def _merge_vertices(V: np.ndarray, F: np.ndarray, tol: float) -> Tuple[np.ndarray, np.ndarray, int]:
    """Merge vertices closer than ``tol`` (``0``: identical positions); non-finite
    vertices are never merged.  Returns ``(vertices, faces, number removed)``."""
    n = len(V)
    finite = np.nonzero(np.isfinite(V).all(1))[0]
    if tol > 0:
        pairs = cKDTree(V[finite]).query_pairs(tol, output_type="ndarray")
        pairs = finite[pairs] if len(pairs) else np.zeros((0, 2), np.int64)
    else:
        _, inv = np.unique(V[finite], axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        order = np.argsort(inv, kind="stable")
        same = inv[order][1:] == inv[order][:-1]
        pairs = np.stack([finite[order][:-1][same], finite[order][1:][same]], 1)
    if len(pairs) == 0:
        return V, F, 0
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    # representative = first vertex of each component, in original order
    _, first = np.unique(comp, return_index=True)
    keep = np.sort(first)
    new_index = np.empty(comp.max() + 1, dtype=np.int64)
    new_index[comp[keep]] = np.arange(len(keep))
    return V[keep], new_index[comp][F], n - len(keep)


def _validate(path, V, F, finite: bool = True) -> None:
    if len(V) == 0 or len(F) == 0:
        _fail(path, f"empty mesh ({len(V)} vertices, {len(F)} faces)")
    if F.min() < 0 or F.max() >= len(V):
        f = int(np.nonzero((F < 0).any(1) | (F >= len(V)).any(1))[0][0])
        bad = int(F[f].max()) + 1 if F[f].max() >= len(V) else int(F[f].min()) + 1
        _fail(path, f"face {f} references vertex {bad} "
                    f"but the file has only {len(V)} vertices (index out of range)")
    bad = ~np.isfinite(V).all(1)
    if finite and bad.any():
        _fail(path, f"{int(bad.sum())} vertices have NaN/inf coordinates (first: vertex "
                    f"{int(np.nonzero(bad)[0][0]) + 1})")


def _check_topology(path, V, F) -> None:
    deg = _degenerate(V, F)
    if deg.any():
        _fail(path, f"{int(deg.sum())} degenerate (zero-area) faces, e.g. face "
                    f"{int(np.nonzero(deg)[0][0])}; load with repair=True to remove them")
    dup = _duplicates(F)
    if dup.any():
        _fail(path, f"{int(dup.sum())} duplicate faces, e.g. face {int(np.nonzero(dup)[0][0])}; "
                    "load with repair=True to remove them")
    nm, cnt = _nonmanifold_edges(F)
    if len(nm):
        a, b = (int(x) + 1 for x in nm[0])
        _fail(path, f"{len(nm)} non-manifold edges (shared by more than 2 faces), e.g. edge "
                    f"{a}-{b} in {int(cnt[0])} faces; not repairable automatically")


def _isometric_uv(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-face rest triangles laid flat, each rotated/translated onto its front-view
    projection ``(x, z)``: exact rest lengths, grain roughly along world Z."""
    tri = V[F]
    return rigid_align(flat_triangles(tri), tri[..., [0, 2]])


def load_garment(path: PathLike, repair: bool = False, uv_fallback: str = "isometric",
                 uv_scale: Union[str, float, None] = "auto", name: Optional[str] = None,
                 kind: Optional[str] = None, merge_tolerance: float = 1e-7) -> Garment:
    """Load a garment mesh and validate it.

    Args:
        path: ``.obj`` (own parser: polygons fan-triangulated, per-corner UVs), ``.ply``,
            ``.glb``/``.gltf``, ``.stl``, ``.off`` (trimesh), or anything meshio reads.
        repair: remove degenerate and duplicate faces, merge vertices closer than
            ``merge_tolerance`` (relative to the bounding-box size), drop vertices no
            face uses; what was done is logged and stored in ``garment.info["repair"]``.
            Non-manifold edges, NaN coordinates of used vertices, out-of-range indices
            and empty meshes are never repaired.
        uv_fallback: without UVs in the file: ``"isometric"`` (default, see the module
            doc), ``"planar"`` (front-view projection ``(x, z)``, not isometric) or
            ``"error"``.
        uv_scale: ``"auto"`` (rescale file UVs whose total area is off the 3D area by
            more than 20%), a factor, or ``None`` (keep as is).
        name, kind: for the :class:`Garment` (defaults: file stem / header / ``"other"``).

    Raises:
        FileNotFoundError: no such file.
        ValueError: ``"<path>: <problem>"`` for unparseable files and invalid meshes.
    """
    path = Path(path)
    if uv_fallback not in UV_FALLBACKS:
        raise ValueError(f"`uv_fallback`: use one of {UV_FALLBACKS}, got {uv_fallback!r}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    raw = _read(path)
    V, F = raw.vertices, raw.faces
    _validate(path, V, F, finite=not repair)  # repair first drops unused (NaN) vertices
    # per-corner UVs from whatever the file has
    corner = raw.corner_uv
    if corner is None and raw.vertex_uv is not None:
        corner = raw.vertex_uv[F]
        # formats with per-vertex UVs split vertices along UV seams: weld them back
        fin = np.isfinite(V).all(1)
        scale = max(float(np.ptp(V[fin], axis=0).max()), 1e-12) if fin.any() else 1.0
        V2, F2, n = _merge_vertices(V, F, 1e-9 * scale)
        if n:
            log.info("%s: welded %d vertices duplicated along UV seams", path, n)
            V, F = V2, F2
    if corner is not None and not np.isfinite(corner).all():
        _fail(path, "UV coordinates contain NaN/inf")
    report: Dict[str, int] = {}
    if repair:
        fin = np.isfinite(V).all(1)
        scale = max(float(np.ptp(V[fin], axis=0).max()), 1e-12) if fin.any() else 1.0
        V, F, nmerge = _merge_vertices(V, F, merge_tolerance * scale)
        report["merged_vertices"] = int(nmerge)
        deg = _degenerate(V, F)
        report["degenerate_faces"] = int(deg.sum())
        F = F[~deg]
        corner = corner[~deg] if corner is not None else None
        dup = _duplicates(F)
        report["duplicate_faces"] = int(dup.sum())
        F = F[~dup]
        corner = corner[~dup] if corner is not None else None
        used = np.zeros(len(V), bool)
        used[F.reshape(-1)] = True
        report["unreferenced_vertices"] = int((~used).sum())
        if not used.all():
            remap = np.cumsum(used) - 1
            V, F = V[used], remap[F]
        if any(report.values()):
            log.info("%s: repaired %s", path, report)
        _validate(path, V, F)
    _check_topology(path, V, F)
    if not repair:
        used = np.zeros(len(V), bool)
        used[F.reshape(-1)] = True
        if not used.all():
            log.warning("%s: %d vertices are not used by any face (load with repair=True to "
                        "drop them)", path, int((~used).sum()))
        fin = np.isfinite(V).all(1)
        scale = max(float(np.ptp(V[fin], axis=0).max()), 1e-12) if fin.any() else 1.0
        ndup = _merge_vertices(V[used], F[:0], merge_tolerance * scale)[2]
        if ndup:  # faces meeting at copies of a vertex are not connected there
            log.warning("%s: %d vertices lie on another vertex (closer than merge_tolerance "
                        "%.3g x the mesh size), so the faces meeting there are separate "
                        "pieces (cut along those edges); load with repair=True to weld them",
                        path, ndup, merge_tolerance)
    info: Dict[str, object] = {"source": str(path)}
    if repair:
        info["repair"] = report
    tri = V[F]
    if corner is None:
        if uv_fallback == "error":
            _fail(path, "the file has no UV coordinates (uv_fallback='error')")
        if uv_fallback == "isometric":
            corner = _isometric_uv(V, F)
        else:
            corner = tri[..., [0, 2]]
        info["uv"] = uv_fallback
    else:
        info["uv"] = "file"
        if uv_scale is not None:
            a3 = _face_areas(V, F).sum()
            d1, d2 = corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]
            a2 = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]).sum()
            if uv_scale == "auto":
                s = float(np.sqrt(a3 / a2)) if a2 > 0 else 1.0
                if abs(s * s - 1) <= 0.2:
                    s = 1.0
            else:
                s = float(uv_scale)
            if s != 1.0:
                corner = corner * s
                info["uv_scale"] = s
                log.info("%s: UVs scaled by %.4g to metres", path, s)
    uv = first_corner_uv(F, corner, len(V))
    meta = raw.meta
    pinned = None
    if "pinned" in meta:
        pinned = np.zeros(len(V), bool)
        idx = np.asarray(meta["pinned"], dtype=np.int64)
        if len(idx) and (idx.min() < 0 or idx.max() >= len(V)):
            _fail(path, "the garmentgnn header's pinned list is out of range")
        pinned[idx] = True
    k = kind or str(meta.get("kind", "other"))
    if k not in KINDS:
        k = "other"
    return Garment(vertices=torch.tensor(V, dtype=torch.float32),
                   faces=torch.tensor(F, dtype=torch.long),
                   uv=torch.tensor(uv, dtype=torch.float32),
                   face_uv=torch.tensor(corner, dtype=torch.float32),
                   name=name or str(meta.get("name", path.stem)), kind=k,
                   pinned=None if pinned is None else torch.tensor(pinned), info=info)


def save_garment(path: PathLike, garment: Garment) -> Path:
    """Write ``garment`` as a Wavefront OBJ: ``v`` (rest positions), ``vt`` (the
    per-corner ``face_uv`` rounded to 1 micrometre, corners with equal UVs sharing a
    ``vt``) and ``f v/vt``.  A
    ``# garmentgnn`` header line keeps name, kind and the pinned vertices, which
    :func:`load_garment` reads back."""
    path = Path(path)
    if path.suffix.lower() != ".obj":
        raise ValueError(f"{path}: save_garment writes OBJ files (use a .obj suffix)")
    coords, uvf = garment.uv_layout(decimals=6)
    V = garment.vertices.double().numpy()
    F = garment.faces.numpy()
    header = [f"# garmentgnn kind={garment.kind} name={garment.name.replace(' ', '_')}"]
    if garment.pinned is not None and bool(garment.pinned.any()):
        idx = ",".join(str(int(i)) for i in torch.nonzero(garment.pinned).flatten())
        header.append(f"# garmentgnn pinned={idx}")
    lines = header + [f"o {garment.name.replace(' ', '_')}"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    lines += [f"vt {u:.9g} {v:.9g}" for u, v in coords.double().numpy()]
    for (a, b, c), (ta, tb, tc) in zip(F + 1, uvf.numpy() + 1, strict=True):
        lines.append(f"f {a}/{ta} {b}/{tb} {c}/{tc}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
