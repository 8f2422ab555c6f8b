"""A dataset folder as one compact file, and back: :func:`pack` / :func:`unpack`.

A generated dataset (``manifest.json`` + ``sequences/<id>.npz``, see
:mod:`garmentgnn.data.store`) is packed into one zip file (members stored, so sizes add
up exactly)::

    compact.json                  format, the manifest (packed records), spec.json, the
                                  source's content hash, each sequence's quantisation,
                                  the sequences left out
    sequences/<id>.npz            every array of the sequence file (deflated), positions
                                  quantised (below), everything else as it was
    bodies/anny/<name>.npz        the anny body cache files of the packed bodies (a
                                  machine without the ``anny`` package builds the bodies
                                  from them, :func:`garmentgnn.body.anny_body.body_cache_path`)

**Positions** are quantised per sequence and axis to 16 bits, relative to the frame's
``motion_translation`` (the body's root, which the garment travels with: a run of 60
frames goes 14 m, while the garment spans under 2 m about its root): ``q = round((p -
root_t - offset) / scale)`` with ``offset`` the axis minimum and ``scale`` its range over
65,535, stored as frame-to-frame differences (modulo 2^16, so they deflate well).  The
round trip is checked at pack time: a sequence whose largest error exceeds ``tolerance``
(0.1 mm) is a ``ValueError`` (it would need a range over 13 m about its root).  Every
other array, ``meta_json`` included, is kept bit for bit.

:func:`unpack` writes a dataset folder that :class:`~garmentgnn.data.SequenceChunks` and
:class:`~garmentgnn.training.GarmentDataModule` read like the original: the same ids,
records, splits and arrays (positions within the tolerance).  Its sequence files differ
from the source's, so their SHA-256 and the manifest's content hash are new; the
manifest's ``compact`` entry records the source's content hash (each record keeps its
source file's hash as ``source_sha256``), the quantisation error and what was left out.

**Size limit.**  When the chosen splits do not fit ``max_bytes``, the largest number of
whole sequences that fits is packed: each split's smallest packed sequence first (every
split stays represented), then the rest from the smallest up (ties by id), so the choice
is deterministic.  The same input gives a byte-identical file.

    python -m garmentgnn.data.compact pack ROOT OUT_FILE [--splits train val] [--max-mb 40]
    python -m garmentgnn.data.compact unpack FILE ROOT
"""
from __future__ import annotations

import io
import json
import os
import sys
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np

from garmentgnn._argparse import ArgumentParser
from garmentgnn.body import anny_body
from garmentgnn.data import store

__all__ = ["DEFAULT_MAX_BYTES", "FORMAT", "PackResult", "TOLERANCE", "UnpackResult",
           "pack", "unpack"]

PathLike = Union[str, os.PathLike]

FORMAT = "garmentgnn-compact"
VERSION = 2  # 2: positions relative to motion_translation
#: default size limit of a packed file (40 MB)
DEFAULT_MAX_BYTES = 40_000_000
#: largest position error of the quantisation (metres)
TOLERANCE = 1e-4
INDEX = "compact.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_LEVELS = 65535
#: bytes a stored zip member adds to its data besides twice its name (local header 30,
#: central directory entry 46)
_MEMBER_OVERHEAD = 76
_END_RECORD = 22


@dataclass
class PackResult:
    """What :func:`pack` wrote."""
    path: str
    bytes: int
    sequences: List[str]
    left_out: List[str]
    splits: Dict[str, int]
    max_position_error_m: float
    source_content_sha256: Optional[str]
    bodies: List[str] = field(default_factory=list)
    missing_bodies: List[str] = field(default_factory=list)


@dataclass
class UnpackResult:
    """What :func:`unpack` wrote."""
    root: str
    sequences: int
    content_sha256: Optional[str]
    source_content_sha256: Optional[str]
    bodies: List[str] = field(default_factory=list)


# --------------------------------------------------------------------------- arrays
def quantise(positions: np.ndarray, origin: Optional[np.ndarray] = None
             ) -> Tuple[np.ndarray, List[float], List[float]]:
    """``[T, V, 3]`` positions (less ``origin [T, 3]``, each frame's) as uint16 frame
    differences, with per-axis offset and scale."""
    p = np.asarray(positions, np.float64)
    if origin is not None:
        p = p - np.asarray(origin, np.float64)[:, None, :]
    lo = p.reshape(-1, 3).min(0) if p.size else np.zeros(3)
    hi = p.reshape(-1, 3).max(0) if p.size else np.zeros(3)
    scale = np.where(hi > lo, (hi - lo) / _LEVELS, 1.0)
    q = np.rint((p - lo) / scale).astype(np.uint16)
    delta = q.copy()
    delta[1:] -= q[:-1]  # modulo 2^16: cumsum in uint16 undoes it
    return delta, lo.tolist(), scale.tolist()


def dequantise(delta: np.ndarray, offset: Sequence[float], scale: Sequence[float],
               origin: Optional[np.ndarray] = None) -> np.ndarray:
    """The float32 positions of :func:`quantise`'s output (``origin``: the one it was
    given)."""
    q = np.cumsum(np.asarray(delta, np.uint16), axis=0, dtype=np.uint16)
    p = q * np.asarray(scale, np.float64) + np.asarray(offset, np.float64)
    if origin is not None:
        p = p + np.asarray(origin, np.float64)[:, None, :]
    return p.astype(np.float32)


def _origin(arrays: Dict[str, np.ndarray]) -> Optional[np.ndarray]:
    """The per-frame origin of a sequence's positions: its ``motion_translation``."""
    root, pos = arrays.get("motion_translation"), arrays["positions"]
    ok = root is not None and root.shape == (pos.shape[0], 3)
    return root if ok else None


def _npz_bytes(arrays: Dict[str, np.ndarray]) -> bytes:
    """A deterministic deflated ``.npz`` (sorted members, fixed timestamps)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key in sorted(arrays):
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arrays[key]),
                                      allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def _read_npz(data: bytes) -> Dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _packed_sequence(root: Path, rec: Dict[str, Any], tolerance: float
                     ) -> Tuple[bytes, Dict[str, Any]]:
    """One sequence file's packed member and its quantisation entry."""
    path = store.sequence_path(root, rec)
    with np.load(path, allow_pickle=False) as z:  # every array, meta_json included
        arrays = {k: z[k] for k in z.files}
    pos, origin = arrays["positions"], _origin(arrays)
    delta, offset, scale = quantise(pos, origin)
    back = dequantise(delta, offset, scale, origin)
    err = float(np.abs(back - pos).max()) if pos.size else 0.0
    if not err <= tolerance:
        span = float(max(np.asarray(scale) * _LEVELS))
        raise ValueError(f"`tolerance`: the 16-bit positions of {rec['id']} are off by up to "
                         f"{err:.3g} m (they span {span:.3g} m about their root), over "
                         f"{tolerance:g} m; raise tolerance or leave this sequence's split out")
    arrays["positions"] = delta
    entry = {"dtype": str(pos.dtype), "encoding": "uint16 frame differences",
             "origin": None if origin is None else "motion_translation",
             "offset": offset, "scale": scale, "max_error_m": err}
    return _npz_bytes(arrays), entry


# --------------------------------------------------------------------------- arguments
def _check_splits(splits: Optional[Iterable[str]], records: List[Dict[str, Any]],
                  root: Path) -> List[str]:
    listed = sorted({str(r.get("split")) for r in records if r.get("status") == "ok"})
    if splits is None:
        return listed
    if isinstance(splits, (str, bytes)) or not all(isinstance(s, str) for s in splits):
        raise TypeError(f"`splits`: expected a list of split names (e.g. ['train', 'val']), "
                        f"got {splits!r}")
    splits = list(dict.fromkeys(splits))
    missing = [s for s in splits if s not in listed]
    if not splits or missing:
        raise ValueError(f"`splits`: {root} has no ok sequences in {missing or 'an empty list'}"
                         f"; name splits its manifest lists: {', '.join(listed) or 'none'}")
    return splits


def _check_number(name: str, value: Any, low: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"`{name}`: expected a number, got {type(value).__name__} {value!r}")
    if not value > low or not np.isfinite(value):
        raise ValueError(f"`{name}`: expected a finite number > {low:g}, got {value!r}")


def _member_cost(name: str, data: bytes) -> int:
    return len(data) + _MEMBER_OVERHEAD + 2 * len(name.encode())


def _select(costs: Dict[str, int], split_of: Dict[str, str], room: int
            ) -> Tuple[List[str], List[str]]:
    """The packed ids (most sequences that fit ``room``, each split represented) and the
    ones left out."""
    ids = sorted(costs)
    if sum(costs.values()) <= room:
        return ids, []
    by_size = sorted(ids, key=lambda i: (costs[i], i))
    chosen: List[str] = []
    for s in sorted(set(split_of.values())):
        chosen.append(next(i for i in by_size if split_of[i] == s))
    need = sum(costs[i] for i in chosen)
    if need > room:
        raise ValueError(f"`max_bytes`: the smallest sequence of each split needs {need} "
                         f"bytes, {max(room, 0)} are left beside the index and the bodies; "
                         f"raise max_bytes by {need - room} or pack fewer splits")
    used = need
    for i in by_size:
        if i not in chosen and used + costs[i] <= room:
            chosen.append(i)
            used += costs[i]
    return sorted(chosen), sorted(set(ids) - set(chosen))


def _body_files(records: List[Dict[str, Any]]) -> Tuple[Dict[str, Path], List[str]]:
    """The anny body cache files of ``records`` (and of the ``regular`` body every
    :class:`AnnyBodyModel` loads first): ``{member name: path}``, and the missing ones."""
    shapes = [r["body"]["shape"] for r in records
              if isinstance(r.get("body"), dict) and r["body"].get("model") == "anny"]
    found: Dict[str, Path] = {}
    missing: List[str] = []
    for shape in (["regular"] + shapes) if shapes else []:
        path = anny_body.body_cache_path(shape)
        name = f"bodies/anny/{path.name}"
        if name in found or name in missing:
            continue
        if path.is_file():
            found[name] = path
        else:
            missing.append(name)
    return found, missing


# --------------------------------------------------------------------------- pack
def pack(root: PathLike, out_file: PathLike, splits: Optional[Iterable[str]] = None,
         max_bytes: int = DEFAULT_MAX_BYTES, tolerance: float = TOLERANCE,
         ids: Optional[Iterable[str]] = None) -> PackResult:
    """Pack the ok sequences of ``splits`` (default: every split) of the dataset at
    ``root`` into ``out_file`` (see the module doc), at most ``max_bytes`` bytes;
    ``ids``: only these sequences (e.g. a one-sequence sample a test scores)."""
    root = Path(root)
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int):
        raise TypeError(f"`max_bytes`: expected an int (bytes, e.g. 40_000_000), got "
                        f"{max_bytes!r}")
    if max_bytes < 1:
        raise ValueError(f"`max_bytes`: expected a positive size in bytes, got {max_bytes}")
    _check_number("tolerance", tolerance, 0.0)
    out_file = Path(out_file)
    if out_file.is_dir():
        raise ValueError(f"`out_file`: {out_file} is a folder; name a file in it, e.g. "
                         f"{out_file / (root.name + '.zip')}")
    manifest = store.read_manifest(root)
    items = manifest["items"]
    splits = _check_splits(splits, items, root)
    records = {r["id"]: r for r in items if r.get("status") == "ok" and r["split"] in splits}
    if ids is not None:
        if isinstance(ids, (str, bytes)):
            raise TypeError(f"`ids`: expected a list of sequence ids, got {ids!r}")
        ids = list(dict.fromkeys(ids))
        unknown = [i for i in ids if i not in records]
        if not ids or unknown:
            raise ValueError(f"`ids`: {unknown or 'an empty list'} not among the ok sequences "
                             f"of {splits} in {root}; name ids its manifest lists")
        records = {i: records[i] for i in ids}
    members: Dict[str, bytes] = {}
    entries: Dict[str, Dict[str, Any]] = {}
    for rid in sorted(records):
        store.load_record_sequence(root, records[rid], ["meta_json"])  # its hash checked
        data, entries[rid] = _packed_sequence(root, records[rid], float(tolerance))
        members[f"sequences/{rid}.npz"] = data
    bodies, missing = _body_files(list(records.values()))
    for name, path in bodies.items():
        members[name] = path.read_bytes()
    spec = None
    if (root / store.SPEC).is_file():
        spec = store.read_json(root / store.SPEC, "delete it or regenerate the dataset")
    header = {k: v for k, v in manifest.items() if k not in ("items", "counts")}

    def index(ids: List[str], left: List[str]) -> bytes:
        keep = set(ids)
        doc = {"format": FORMAT, "version": VERSION, "tolerance_m": float(tolerance),
               "source": {"name": manifest.get("name"), "root": root.name,
                          "content_sha256": manifest.get("content_sha256")},
               "splits": splits, "header": header, "spec": spec,
               "records": [r for i, r in records.items() if i in keep],  # the source's order
               "positions": {i: entries[i] for i in ids},
               "left_out": left, "bodies": sorted(bodies), "missing_bodies": missing}
        return json.dumps(doc, indent=1, sort_keys=True).encode()

    costs = {rid: _member_cost(f"sequences/{rid}.npz", members[f"sequences/{rid}.npz"])
             for rid in records}
    # the index of every sequence bounds any subset's (a record outweighs its id in left_out)
    fixed = _END_RECORD + _member_cost(INDEX, index(sorted(records), []))
    fixed += sum(_member_cost(n, members[n]) for n in bodies)
    ids, left = _select(costs, {i: records[i]["split"] for i in records}, max_bytes - fixed)
    blob = index(ids, left)
    chosen = [INDEX] + sorted(bodies) + [f"sequences/{i}.npz" for i in ids]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in chosen:
            info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
            info.external_attr = 0o644 << 16
            zf.writestr(info, blob if name == INDEX else members[name])
    data = buf.getvalue()
    if len(data) > max_bytes:  # the index is bounded above by the one of every sequence
        raise AssertionError(f"packed {len(data)} bytes over max_bytes={max_bytes}")
    store.atomic_write_bytes(out_file, data)
    counts: Dict[str, int] = {}
    for i in ids:
        counts[records[i]["split"]] = counts.get(records[i]["split"], 0) + 1
    return PackResult(str(out_file), len(data), ids, left, counts,
                      max((entries[i]["max_error_m"] for i in ids), default=0.0),
                      manifest.get("content_sha256"), sorted(bodies), missing)


# --------------------------------------------------------------------------- unpack
def read_index(file: PathLike) -> Dict[str, Any]:
    """The ``compact.json`` of a packed file; ``ValueError`` naming the file when it is
    not one."""
    file = Path(file)
    if not file.is_file():
        raise FileNotFoundError(f"`file`: {file} does not exist; make it with "
                                f"`python -m garmentgnn.data.compact pack ROOT {file}`")
    try:
        with zipfile.ZipFile(file) as zf:
            doc = json.loads(zf.read(INDEX))
    except (zipfile.BadZipFile, KeyError, ValueError) as e:
        raise ValueError(f"`file`: {file} is not a packed dataset ({type(e).__name__}: "
                         f"{str(e)[:80]}); pack one with `python -m garmentgnn.data.compact "
                         f"pack ROOT {file}`") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or doc.get("version") != VERSION:
        raise ValueError(f"`file`: {file} is not a {FORMAT} file of version {VERSION}; "
                         f"pack it again with this version")
    return doc


def unpack(file: PathLike, root: PathLike, cache_dir: Optional[PathLike] = None
           ) -> UnpackResult:
    """Write the dataset packed in ``file`` into the folder ``root`` (new or empty), and
    its anny body cache files under ``cache_dir`` (default: the project's cache,
    ``$GARMENTGNN_CACHE_DIR`` or ``~/.cache/garmentgnn``) where they are missing."""
    doc = read_index(file)
    root = Path(root)
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ValueError(f"`root`: {root} exists and is not an empty folder; unpack into a "
                         f"new folder")
    cache = Path(cache_dir) if cache_dir is not None else anny_body.cache_dir()
    records, written = [], []
    with zipfile.ZipFile(file) as zf:
        for rec in doc["records"]:
            arrays = _read_npz(zf.read(f"sequences/{rec['id']}.npz"))
            q = doc["positions"][rec["id"]]
            origin = arrays["motion_translation"] if q["origin"] else None
            arrays["positions"] = dequantise(arrays["positions"], q["offset"], q["scale"],
                                             origin).astype(q["dtype"])
            meta = json.loads(arrays.pop("meta_json").tobytes().decode())
            path = store.write_sequence(root / store.SEQUENCES / f"{rec['id']}.npz",
                                        arrays, meta)
            new = dict(rec, file=f"{store.SEQUENCES}/{rec['id']}.npz",
                       source_sha256=rec.get("sha256"), sha256=store.file_sha256(path))
            records.append(new)
        for name in doc["bodies"]:
            target = cache / Path(name).relative_to("bodies")
            if not target.exists():
                store.atomic_write_bytes(target, zf.read(name))
                written.append(str(target))
    if doc.get("spec") is not None:
        store.atomic_write_json(root / store.SPEC, doc["spec"])
    errors = [q["max_error_m"] for q in doc["positions"].values()]
    header = dict(doc["header"], compact={
        "source_content_sha256": doc["source"]["content_sha256"],
        "source": doc["source"]["root"], "packed_file": Path(file).name,
        "splits": doc["splits"], "positions": "16-bit per sequence and axis",
        "max_position_error_m": max(errors, default=0.0), "left_out": doc["left_out"]})
    store.write_manifest(root, records, header)
    return UnpackResult(str(root), len(records), store.read_manifest(root)["content_sha256"],
                        doc["source"]["content_sha256"], written)


# --------------------------------------------------------------------------- command line
def main(argv: Optional[List[str]] = None) -> int:
    ap = ArgumentParser(prog="python -m garmentgnn.data.compact",
                        description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack", help="pack a dataset folder into one file")
    p.add_argument("root", help="dataset folder (manifest.json + sequences/)")
    p.add_argument("out_file", help="the file to write")
    p.add_argument("--splits", nargs="+", default=None, help="splits (default: all)")
    p.add_argument("--ids", nargs="+", default=None,
                   help="only these sequence ids (default: every sequence of the splits)")
    p.add_argument("--max-mb", type=float, default=DEFAULT_MAX_BYTES / 1e6,
                   help="size limit in MB (10^6 bytes)")
    u = sub.add_parser("unpack", help="write a packed file's dataset folder")
    u.add_argument("file", help="a file written by `pack`")
    u.add_argument("root", help="a new or empty folder")
    u.add_argument("--cache-dir", default=None,
                   help="where the anny body cache files go (default: the project's cache)")
    a = ap.parse_args(argv)
    try:
        if a.cmd == "pack":
            if not a.max_mb > 0:
                ap.error(f"--max-mb: expected a positive size, got {a.max_mb}")
            res: Any = pack(a.root, a.out_file, a.splits, int(a.max_mb * 1e6), ids=a.ids)
        else:
            res = unpack(a.file, a.root, a.cache_dir)
    except (OSError, ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(asdict(res), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
