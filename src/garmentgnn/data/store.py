"""On-disk layout of a generated dataset: sequence files and the manifest (export to
PC2/OBJ/glTF: :mod:`garmentgnn.data.export`).

Layout of an output folder ``OUT``::

    OUT/spec.json              the full item list (written once, checked on resume)
    OUT/manifest.json          one record per item: status pending/ok/failed, ...
    OUT/sequences/<id>.npz     one simulated sequence per item (ok items only)

Every file is written whole or not at all (:mod:`garmentgnn._files`, whose
``atomic_write_*`` are handed on here), so a reader (or a resumed run) never sees a
half-written file.  Sequence files are zip archives of ``.npy`` members written
with a fixed timestamp, so the same content gives byte-identical files.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import subprocess
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Union

import numpy as np

import garmentgnn
from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn._files import remove_stale_temporaries  # noqa: F401  (handed on)
from garmentgnn.data.sequence_check import SEQUENCE_KEYS, check_sequence

PathLike = Union[str, os.PathLike]

FORMAT_VERSION = 1
SEQUENCES = "sequences"
MANIFEST = "manifest.json"
SPEC = "spec.json"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def data_root() -> Path:
    """Where ``garmentgnn generate`` writes datasets without ``--out``:
    ``$GARMENTGNN_DATA_DIR``, else ``~/.cache/garmentgnn/datasets`` (outside any work tree)."""
    env = os.environ.get("GARMENTGNN_DATA_DIR")
    return Path(env) if env else Path.home() / ".cache" / "garmentgnn" / "datasets"


def sequence_path(root: PathLike, record: Dict[str, Any]) -> Path:
    """Where a manifest record's sequence file lives under ``root``."""
    return Path(root) / (record.get("file") or f"{SEQUENCES}/{record['id']}.npz")


def nbytes(value: Any) -> int:
    """Bytes held by the arrays and tensors of ``value`` (a dict, list or tuple of them,
    nested): what an in-memory copy of a loaded sequence costs."""
    if isinstance(value, dict):
        return sum(nbytes(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(nbytes(v) for v in value)
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    numel, size = getattr(value, "numel", None), getattr(value, "element_size", None)
    return int(numel() * size()) if callable(numel) and callable(size) else 0


class LRUCache(OrderedDict):
    """At most ``capacity`` entries and, with ``max_bytes``, at most that many bytes of
    arrays (:func:`nbytes`; the newest entry is kept whatever its size):
    :meth:`get_or_build` evicts the least recently used."""

    def __init__(self, capacity: int, max_bytes: Optional[int] = None) -> None:
        super().__init__()
        self.capacity = max(1, capacity)
        self.max_bytes = max_bytes
        self.bytes = 0
        self._sizes: Dict[Any, int] = {}

    def get_or_build(self, key, build: Callable[[], Any]) -> Any:
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = self[key] = build()
        if self.max_bytes is not None:
            self._sizes[key] = nbytes(value)
            self.bytes += self._sizes[key]
        while len(self) > 1 and (len(self) > self.capacity or (
                self.max_bytes is not None and self.bytes > self.max_bytes)):
            old, _ = self.popitem(last=False)
            self.bytes -= self._sizes.pop(old, 0)
        return value

    def __reduce__(self):
        # pickled empty: a cache need not travel to DataLoader / DDP worker processes
        # (and OrderedDict's own reduce would call __init__ without `capacity`)
        return (type(self), (self.capacity, self.max_bytes))


# --------------------------------------------------------------------------- sequence files
class IntegrityError(ValueError):
    """A file that is unreadable, or whose content differs from the hash recorded for
    it (bit rot, an edit, a truncated copy)."""


def _npz_bytes(arrays: Dict[str, np.ndarray]) -> bytes:
    """A deterministic ``.npz`` (fixed member order and timestamps, stored uncompressed)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for key in sorted(arrays):
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arrays[key]),
                                      allow_pickle=False)
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_DATE)
            info.external_attr = 0o644 << 16
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def write_sequence(path: PathLike, arrays: Dict[str, np.ndarray], meta: Dict[str, Any]) -> Path:
    """Atomically write one sequence file (``arrays`` + JSON ``meta``)."""
    missing = [k for k in SEQUENCE_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"write_sequence: missing arrays {missing}")
    data = dict(arrays)
    data["meta_json"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    return atomic_write_bytes(path, _npz_bytes(data))


def read_meta(path: PathLike) -> Dict[str, Any]:
    """Only the JSON metadata of a sequence file (does not read the positions)."""
    return load_sequence(path, ["meta_json"])["meta"]


def load_sequence(path: PathLike, keys: Optional[Iterable[str]] = None,
                  optional: Iterable[str] = ()) -> Dict[str, Any]:
    """All arrays (or ``keys``, plus those of ``optional`` the file has) of a sequence file
    as numpy arrays plus ``meta`` (dict).

    A missing file raises ``FileNotFoundError``; an unreadable one (truncated, corrupt
    zip member -- every member carries a CRC-32 --, missing array, bad metadata)
    :class:`IntegrityError`, naming the path."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such sequence file")
    try:
        with np.load(path, allow_pickle=False) as z:
            names = list(z.files) if keys is None else \
                [k for k in keys] + [k for k in optional if k in z.files]
            out: Dict[str, Any] = {k: z[k] for k in names if k != "meta_json"}
            meta = json.loads(z["meta_json"].tobytes().decode())
    except Exception as e:  # zip, npy-header, EOF, JSON and decoding errors of many kinds
        raise IntegrityError(f"{path}: unreadable sequence file ({type(e).__name__}: "
                             f"{str(e)[:120]}); delete it and rerun `garmentgnn generate`"
                             ) from None
    if not isinstance(meta, dict):
        raise IntegrityError(f"{path}: unreadable sequence file (metadata is not a JSON "
                             f"object); delete it and rerun `garmentgnn generate`")
    out["meta"] = meta
    return out


def file_sha256(path: PathLike) -> str:
    """Hex SHA-256 of a file's bytes (the integrity hash kept in manifest records)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_record_sequence(root: PathLike, record: Dict[str, Any],
                         keys: Optional[Iterable[str]] = None,
                         optional: Iterable[str] = ()) -> Dict[str, Any]:
    """:func:`load_sequence` of a manifest record's file, after checking its SHA-256
    against the record's ``sha256`` (records written before hashes were kept have
    none and are not checked).  Raises :class:`IntegrityError` on a mismatch and
    ``FileNotFoundError`` naming the file and the fix when it is missing."""
    path = sequence_path(root, record)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: sequence file of item {record.get('id')!r} is "
                                f"missing; rerun `garmentgnn generate` on {root} to make it")
    want = record.get("sha256")
    if want and file_sha256(path) != want:
        raise IntegrityError(f"{path}: SHA-256 differs from the manifest's (corrupt or "
                             f"changed file); delete it and rerun `garmentgnn generate` on "
                             f"{root}, or run `garmentgnn manifest --out {root}` to accept it")
    if keys is None:  # a whole file: its arrays must fit together
        return checked_sequence(path, load_sequence(path), record.get("id"))
    return load_sequence(path, keys, optional)


def validate_sequence(path: PathLike, item_id: Optional[str] = None) -> Optional[str]:
    """``None`` if ``path`` is a complete, loadable sequence file (of ``item_id``) that
    passes :func:`check_sequence`, otherwise a message saying what is wrong."""
    try:
        seq = load_sequence(path)
    except Exception as e:  # corrupt zip, truncated member, bad JSON, ...
        return f"unreadable: {type(e).__name__}: {e}"
    return check_sequence(seq, item_id)


def checked_sequence(path: PathLike, seq: Dict[str, Any],
                     item_id: Optional[str] = None) -> Dict[str, Any]:
    """``seq`` (loaded from ``path``) after :func:`check_sequence`;
    :class:`IntegrityError` naming the path, the problem and the fix otherwise."""
    msg = check_sequence(seq, item_id)
    if msg is not None:
        raise IntegrityError(f"{path}: {msg}; delete it and rerun `garmentgnn generate` on "
                             f"its dataset folder")
    return seq


# --------------------------------------------------------------------------- manifest
_GIT: Optional[Dict[str, Optional[str]]] = None


def code_version() -> Dict[str, Optional[str]]:
    """``garmentgnn.__version__`` and, where available, ``git rev-parse HEAD``."""
    global _GIT
    if _GIT is None:
        commit = None
        try:
            r = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                               timeout=10, cwd=Path(garmentgnn.__file__).resolve().parent)
            if r.returncode == 0:
                commit = r.stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            pass
        _GIT = {"version": garmentgnn.__version__, "git_commit": commit}
    return dict(_GIT)


def content_sha256(records: Iterable[Dict[str, Any]]) -> Optional[str]:
    """The dataset's content hash: hex SHA-256 of the lines ``"<id> <sha256>\\n"`` of its
    ok records, sorted by id (so independent of item order; one changed sequence file
    changes it).  Two datasets with the same spec but different simulated positions (another
    CPU's floating point) get different hashes.  ``None`` when an ok record has no
    ``sha256`` (a manifest written before hashes were kept: rebuild it)."""
    ok = [r for r in records if r.get("status") == "ok"]
    if any(not r.get("sha256") for r in ok):
        return None
    h = hashlib.sha256()
    for rid, sha in sorted((str(r["id"]), str(r["sha256"])) for r in ok):
        h.update(f"{rid} {sha}\n".encode())
    return h.hexdigest()


def write_manifest(out: PathLike, records: List[Dict[str, Any]], header: Dict[str, Any]) -> Path:
    """Atomically (re)write ``OUT/manifest.json`` (with its :func:`content_sha256`)."""
    counts: Dict[str, int] = {}
    for r in records:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    doc = dict(header)
    doc.update(format_version=FORMAT_VERSION, counts=counts, items=records,
               content_sha256=content_sha256(records))
    return atomic_write_json(Path(out) / MANIFEST, doc)


def read_json(path: PathLike, fix: str) -> Dict[str, Any]:
    """A JSON object from ``path``; ``ValueError`` naming the path and ``fix`` when the
    file is not one (truncated, edited, binary)."""
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not valid JSON ({e}); {fix}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(doc).__name__}; {fix}")
    return doc


def read_manifest(out: PathLike) -> Dict[str, Any]:
    """``OUT/manifest.json``; ``FileNotFoundError`` / ``ValueError`` naming the path and
    the command that makes or repairs it."""
    path = Path(out) / MANIFEST
    if not path.is_file():
        what = "folder does not exist" if not Path(out).is_dir() else f"has no {MANIFEST}"
        raise FileNotFoundError(f"{out}: {what}; make the dataset with `garmentgnn generate "
                                f"--preset tiny --out {out}`")
    doc = read_json(path, f"rebuild it with `garmentgnn manifest --out {out}`")
    if not isinstance(doc.get("items"), list):
        raise ValueError(f"{path}: no 'items' list; rebuild it with `garmentgnn manifest "
                         f"--out {out}`")
    check_manifest_ids(doc["items"], path, out)
    return doc


def dataset_dir(text: str) -> str:
    """An argparse type: a dataset folder made by ``garmentgnn generate`` (its
    ``manifest.json`` readable, :func:`read_manifest`; ``~`` expanded); otherwise the path
    and the command that makes or repairs it."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path; name a dataset folder")
    path = os.path.expanduser(text)
    try:
        read_manifest(path)
    except (OSError, ValueError) as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return path


def check_manifest_ids(items: List[Any], path: PathLike, out: PathLike) -> None:
    """Every record a JSON object with an ``id``, each id listed once: ``ValueError``
    naming the duplicated ids (a loader would use those sequences several times)."""
    seen: Dict[Any, int] = {}
    for r in items:
        if not isinstance(r, dict) or not isinstance(r.get("id"), str):
            raise ValueError(f"{path}: a record without an 'id' ({str(r)[:60]}); rebuild it "
                             f"with `garmentgnn manifest --out {out}`")
        seen[r["id"]] = seen.get(r["id"], 0) + 1
    dup = {k: n for k, n in seen.items() if n > 1}
    if dup:
        listed = ", ".join(f"{k!r} x{n}" for k, n in sorted(dup.items())[:5])
        more = f" and {len(dup) - 5} more" if len(dup) > 5 else ""
        raise ValueError(f"{path}: {len(dup)} id(s) listed more than once ({listed}{more}); "
                         f"rebuild it with `garmentgnn manifest --out {out}`")


def record_from_meta(meta: Dict[str, Any], seconds: Optional[float] = None) -> Dict[str, Any]:
    """The manifest record of an ok item, from a sequence file's metadata."""
    keys = ("id", "garment", "body", "motion", "material", "settings", "seed", "split",
            "num_frames", "num_vertices", "code", "nonconverged_frames", "penetrating_frames",
            "max_penetration_depth", "invalid_frames", "resimulated", "engine", "held_out")
    rec = {k: meta.get(k) for k in keys}
    if rec["engine"] is None:  # written before engines were recorded: the torch simulator
        rec["engine"] = {"name": "torch"}
    rec.update(status="ok", message="", seconds=seconds if seconds is not None
               else meta.get("seconds"), file=f"{SEQUENCES}/{meta['id']}.npz")
    return rec


def _engine_name(meta_or_item: Dict[str, Any]) -> str:
    engine = meta_or_item.get("engine")
    if isinstance(engine, dict):
        engine = engine.get("name")
    return str(engine or "torch")  # written before engines were recorded: torch


def listed_ok(out: PathLike, items: Optional[List[Dict[str, Any]]] = None) -> set:
    """The ids ``OUT/manifest.json`` lists as ok (empty when it is missing or unreadable):
    files of another dataset listed there were accepted by an earlier ``--force``.
    Given the spec's ``items``, only a manifest written for that spec (one listing every
    item) accepts anything: a spec copied in beside another dataset's manifest does not
    make that dataset's files its own."""
    try:
        records = read_manifest(out)["items"]
        listed = {r["id"] for r in records}
        ok = {r["id"] for r in records if r.get("status") == "ok"}
    except (OSError, ValueError, KeyError, TypeError):
        return set()
    if items is not None and not {it.get("id") for it in items} <= listed:
        return set()
    return ok


def foreign_sequence_files(out: PathLike, items: List[Dict[str, Any]],
                           accepted: Iterable[str] = ()) -> List[str]:
    """The sequence files under ``OUT/sequences`` that belong to another dataset than
    the spec ``items``: a file whose id no item has (and that is not ``accepted``), or
    whose engine is not its item's; each as ``"<file name> (engine E, split S)"``.
    Unreadable files are left to :func:`validate_sequence`."""
    by_id = {it.get("id"): it for it in items if isinstance(it, dict)}
    accepted = set(accepted)
    out_list = []
    for p in sorted((Path(out) / SEQUENCES).glob("*.npz")):
        item = by_id.get(p.stem)
        if item is None and p.stem in accepted:
            continue
        try:
            meta = read_meta(p)
        except (ValueError, OSError):
            continue
        if item is None or _engine_name(meta) != _engine_name(item):
            out_list.append(f"{p.name} (engine {_engine_name(meta)}, split "
                            f"{meta.get('split')})")
    return out_list


def foreign_message(out: PathLike, foreign: List[str], whose: str, what: str) -> str:
    """The error about :func:`foreign_sequence_files` ``foreign`` (not of ``whose``):
    ``what`` was refused, the files and the fix."""
    more = f" and {len(foreign) - 2} more" if len(foreign) > 2 else ""
    return (f"{out}: {len(foreign)} sequence file(s) in {SEQUENCES}/ belong to another "
            f"dataset than {whose} (another preset's, seed's or engine's: "
            f"{', '.join(foreign[:2])}{more}); {what}; use another --out, or --force to "
            f"list them beside this dataset's")


def rebuild_manifest(out: PathLike, write: bool = True, force: bool = False) -> Dict[str, Any]:
    """Recreate the manifest from ``OUT/sequences/*.npz`` (and ``OUT/spec.json`` when it
    exists, so items without a file are listed as ``pending``; failure messages are not
    recoverable from the sequence files, so failed items come back as pending).

    Unreadable sequence files are skipped (and listed under ``invalid``).  Files of
    another dataset than ``spec.json`` describes (:func:`foreign_sequence_files`; those
    the manifest lists as ok were accepted before) are a ``ValueError`` unless ``force``;
    files outside the spec are listed after its items.  A folder without
    ``sequences/`` holds no dataset (as ``garmentgnn manifest`` says): a ``ValueError``
    naming it, and nothing written (an empty manifest there read as an empty
    dataset)."""
    out = Path(out)
    spec_path = out / SPEC
    if not out.is_dir():
        raise ValueError(f"`out`: {out}: no such folder; give a dataset folder (made by "
                         f"garmentgnn generate)")
    if not (out / SEQUENCES).is_dir():
        raise ValueError(f"`out`: {out} holds no dataset (no {SEQUENCES}/ folder in it); "
                         f"nothing was written; give the folder garmentgnn generate "
                         f"wrote into")
    spec = None
    if spec_path.exists():
        spec = read_json(spec_path, "delete it (items without a file are then not listed)")
        if not isinstance(spec.get("items"), list) or \
                not all(isinstance(it, dict) and "id" in it for it in spec["items"]):
            raise ValueError(f"{spec_path}: no valid 'items' list; delete it (items without "
                             f"a file are then not listed)")
        foreign = [] if force else foreign_sequence_files(
            out, spec["items"], listed_ok(out, spec["items"]))
        if foreign:
            raise ValueError(foreign_message(out, foreign, f"{spec_path} describes",
                                             "the manifest is not rebuilt"))
    found: Dict[str, Dict[str, Any]] = {}
    invalid = []
    for p in sorted((out / SEQUENCES).glob("*.npz")):
        msg = validate_sequence(p, p.stem)
        if msg is not None:
            invalid.append(f"{p.name}: {msg}")
            continue
        found[p.stem] = dict(record_from_meta(read_meta(p)), sha256=file_sha256(p))
    header: Dict[str, Any] = {"rebuilt": True}
    records: List[Dict[str, Any]] = []
    if spec is not None:
        header.update({k: v for k, v in spec.items() if k != "items"})
        for it in spec["items"]:
            records.append(found.pop(it["id"], None) or pending_record(it))
    records.extend(found[k] for k in sorted(found))  # files outside the spec
    header["invalid"] = invalid
    header["code"] = code_version()
    if write:
        write_manifest(out, records, header)
    return read_manifest(out) if write else dict(header, items=records)


def outside_records(out: PathLike, ids: Iterable[str],
                    prev: Dict[str, Dict[str, Any]]) -> List[Dict[str, Any]]:
    """The ok records of the valid sequence files under ``OUT/sequences`` whose id is not
    in ``ids`` (another dataset's, kept beside a spec's items by ``generate --force`` and
    ``manifest --force``, so no record of a file that exists is dropped): ``prev``'s
    record where it is ok with the file's hash, else one made from the file."""
    ids = set(ids)
    recs = []
    for p in sorted((Path(out) / SEQUENCES).glob("*.npz")):
        if p.stem in ids or validate_sequence(p, p.stem) is not None:
            continue
        sha = file_sha256(p)
        old = prev.get(p.stem)
        recs.append(old if old and old.get("status") == "ok" and old.get("sha256") == sha
                    else dict(record_from_meta(read_meta(p)), sha256=sha))
    return recs


def pending_record(item: Dict[str, Any]) -> Dict[str, Any]:
    rec = {k: item.get(k) for k in ("id", "garment", "body", "motion", "material", "settings",
                                     "seed", "split")}
    rec.update(status="pending", message="", seconds=None, file=None,
               engine={"name": item.get("engine", "torch")}, held_out=item.get("held_out", []))
    return rec
