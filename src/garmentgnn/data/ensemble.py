"""An ensemble ground truth: ``K`` members of some of a dataset's test sequences, each
simulated again by the dataset's engine, at its settings, with the rest garment moved by
:data:`~garmentgnn.data.perturb.PERTURB_M` (1e-7 m) in random directions of its own.

Cloth simulation is chaotic, so the members differ by about as much as a learned model's
error (docs/bench.md, "Scores against an ensemble ground truth"); the bench and
``benchmarks/mgn_learn.py score`` score against them (:mod:`garmentgnn.bench.ensemble`).

The members live in the dataset folder's ``ensemble/`` sub-folder, a dataset folder of its
own (``spec.json``, ``manifest.json``, ``sequences/<id>.m<k>.npz``) made by the same
machinery as the dataset (:func:`garmentgnn.data.generate.generate`: workers, ``--backend
ray``, ``--limit``, resumable, the same valid-frame check and re-simulation of a
Blender run with frames that are not valid ground truth)::

    garmentgnn generate --ensemble 6 --sequences 24 --out DATASET

Its manifest records the dataset's identity (name, seed, engine, content SHA-256): a
reader (:func:`load_ensemble`) refuses an ensemble of another dataset, members whose
frames or vertices are not their sequence's, and fewer than two members.  A dataset
without ``ensemble/`` reads as before.  The sequences (:func:`pick_sequences`) are spread
deterministically over held-out groups and garment kinds.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from garmentgnn.data import store
from garmentgnn.data.generate import Summary, generate
from garmentgnn.data.perturb import PERTURB_M
from garmentgnn.data.validity import sequence_valid

__all__ = ["ENSEMBLE", "ENSEMBLE_SEQUENCES", "MEMBERS", "EnsembleSpec", "dataset_identity",
           "ensemble_dir", "ensemble_spec", "generate_ensemble", "load_ensemble",
           "member_id", "pick_sequences"]

#: the dataset folder's sub-folder that holds the members
ENSEMBLE = "ensemble"
#: members per sequence (``K``) and sequences of ``garmentgnn generate --ensemble``
MEMBERS = 6
ENSEMBLE_SEQUENCES = 24


def ensemble_dir(data) -> Path:
    """Where the members of dataset folder ``data`` live."""
    return Path(data) / ENSEMBLE


def member_id(sequence: str, k: int) -> str:
    """The id of member ``k`` (1-based) of test sequence ``sequence``."""
    return f"{sequence}.m{k}"


def _group(held_out: Sequence[str]) -> str:
    held = sorted(set(held_out))
    return held[0] if len(held) == 1 else "several" if held else "none"


def pick_sequences(records: Sequence[Dict[str, Any]], n: int) -> List[str]:
    """The ids of ``n`` ok test records (manifest items), spread over held-out groups
    (one part held out, or several) and, within a group, over garment kinds: taken in
    turn from each group, each group in turn from each kind, each kind in id order."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"`sequences`: expected a positive number of test sequences, got "
                         f"{n!r}; give 1 or more")
    test = sorted((r for r in records if r.get("split") == "test" and r.get("status") == "ok"),
                  key=lambda r: r["id"])
    cells: Dict[str, Dict[str, List[str]]] = {}
    for r in test:
        cells.setdefault(_group(r.get("held_out") or []), {}).setdefault(
            r["garment"]["kind"], []).append(r["id"])
    queues = {}  # per group: its ids, alternating over kinds
    for g, kinds in sorted(cells.items()):
        order, lists = [], [list(v) for _, v in sorted(kinds.items())]
        while any(lists):
            order += [x.pop(0) for x in lists if x]
        queues[g] = order
    out: List[str] = []
    while len(out) < min(n, len(test)):
        for g in sorted(queues):
            if queues[g] and len(out) < n:
                out.append(queues[g].pop(0))
    return out


def dataset_identity(data) -> Dict[str, Any]:
    """What an ensemble records of its dataset: name, seed, engine and the manifest's
    content SHA-256 (:func:`garmentgnn.data.store.content_sha256`)."""
    doc = store.read_manifest(data)
    engine = doc.get("engine")
    return {"name": doc.get("name"), "seed": doc.get("seed"),
            "engine": engine.get("name") if isinstance(engine, dict) else engine,
            "content_sha256": doc.get("content_sha256")}


@dataclass
class EnsembleSpec:
    """The members as a spec that :func:`garmentgnn.data.generate.generate` simulates:
    each an item of the dataset with its own id and ``member`` entry (the perturbation,
    which :func:`garmentgnn.data.presets.build_inputs` applies)."""
    name: str
    engine: str
    settings: Dict[str, Any]
    ensemble: Dict[str, Any]
    members: List[Dict[str, Any]] = field(default_factory=list)
    seed: Optional[int] = None

    def items(self) -> List[Dict[str, Any]]:
        return [dict(it) for it in self.members]

    def to_json(self) -> Dict[str, Any]:
        return {"name": self.name, "engine": self.engine, "settings": self.settings,
                "seed": self.seed, "ensemble": self.ensemble, "items": self.items()}


def _check_count(name: str, value: Any, low: int, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"`{name}`: {what} >= {low}, got {value!r}; give {low} or more")
    return value


def ensemble_spec(data, ensemble: int = MEMBERS, sequences: int = ENSEMBLE_SEQUENCES
                  ) -> EnsembleSpec:
    """The members of ``ensemble`` (``K``) re-simulations of ``sequences`` test sequences
    of dataset folder ``data`` (:func:`pick_sequences`)."""
    _check_count("ensemble", ensemble, 2, "an ensemble needs K")
    _check_count("sequences", sequences, 1, "expected a number of test sequences")
    doc = store.read_manifest(data)
    by_id = {r["id"]: r for r in doc["items"]}
    ids = pick_sequences(doc["items"], sequences)
    if not ids:
        raise ValueError(f"`out`: {data} has no simulated test sequence to make an ensemble "
                         f"of; generate the dataset first")
    identity = dataset_identity(data)
    members = []
    for sid in ids:
        r = by_id[sid]
        item = {k: r.get(k) for k in ("garment", "body", "motion", "material", "settings",
                                      "seed", "split", "held_out")}
        item["engine"] = identity["engine"] or (r.get("engine") or {}).get("name", "torch")
        for k in range(1, ensemble + 1):
            members.append(dict(item, id=member_id(sid, k), member={
                "of": sid, "k": k, "garment_m": PERTURB_M,
                "seed": (int(r["seed"]) + 1000 + k) & 0x7FFFFFFF}))
    header = {"dataset": identity, "members": ensemble, "garment_m": PERTURB_M,
              "sequences": ids}
    return EnsembleSpec(name=f"{identity['name']}-ensemble", engine=members[0]["engine"],
                        settings=dict(doc.get("settings") or members[0]["settings"]),
                        ensemble=header, members=members, seed=identity["seed"])


def _recorded(folder: Path, arg: str) -> Optional[Dict[str, Any]]:
    """The ``ensemble`` entry of an ensemble folder's spec (or manifest); ``None``
    without either; ``arg``: the argument named in errors."""
    for name in (store.SPEC, store.MANIFEST):
        if (folder / name).is_file():
            doc = store.read_json(folder / name, f"delete {folder} and generate it again")
            if not isinstance(doc.get("ensemble"), dict):
                raise ValueError(f"{arg}: {folder / name} is not an ensemble's (no "
                                 f"'ensemble' entry); delete {folder} and generate it again")
            return doc["ensemble"]
    return None


def _check_identity(data, recorded: Dict[str, Any], folder: Path, arg: str) -> None:
    mine = dataset_identity(data)
    theirs = recorded.get("dataset") or {}
    if theirs.get("content_sha256") != mine["content_sha256"]:
        raise ValueError(
            f"{arg}: {folder} holds an ensemble of another dataset ({theirs.get('name')!r}, "
            f"content SHA-256 {str(theirs.get('content_sha256'))[:12]}; {data} is "
            f"{mine['name']!r}, {str(mine['content_sha256'])[:12]}); delete {folder} and "
            f"run `garmentgnn generate --ensemble K --out {data}` to make this dataset's")


def generate_ensemble(data, ensemble: int = MEMBERS, sequences: int = ENSEMBLE_SEQUENCES,
                      **kwargs: Any) -> Summary:
    """Generate (or resume) the ensemble of dataset folder ``data`` into
    :func:`ensemble_dir` (``kwargs``: :func:`~garmentgnn.data.generate.generate`'s
    workers, limit, backend, ...).  Bad counts, a folder that is no dataset and an
    ensemble of another dataset already there are a ``ValueError``, nothing written."""
    spec = ensemble_spec(data, ensemble, sequences)
    folder = ensemble_dir(data)
    recorded = _recorded(folder, "`out`")
    if recorded is not None:
        _check_identity(data, recorded, folder, "`out`")
        if recorded.get("members") != ensemble or recorded.get("sequences") != \
                spec.ensemble["sequences"]:
            raise ValueError(
                f"`ensemble`: {folder} holds {recorded.get('members')} members of "
                f"{len(recorded.get('sequences') or [])} sequences; rerun with --ensemble "
                f"{recorded.get('members')} --sequences {len(recorded.get('sequences') or [])}"
                f" to resume it, or delete it to make another")
    return generate(spec, folder, **kwargs)


def load_ensemble(data, sequences: Optional[Sequence[str]] = None
                  ) -> Optional[Dict[str, Any]]:
    """The members of dataset folder ``data`` (``None`` when it has none):
    ``{"members": K, "dataset": identity, "sequences": {id: {"positions": [K, T, V, 3]
    float32, "valid": [T] bool (valid ground truth in every member)}}, "incomplete":
    [ids with a member not simulated]}``, of ``sequences`` only when given.  An ensemble
    of another dataset, fewer than 2 members, or a member whose frames or vertices are
    not its sequence's are a ``ValueError`` naming the file and the fix."""
    folder = ensemble_dir(data)
    if not (folder / store.MANIFEST).is_file():
        return None
    arg = "`data` (--data)"
    recorded = _recorded(folder, arg)
    _check_identity(data, recorded, folder, arg)
    K = recorded.get("members")
    if isinstance(K, bool) or not isinstance(K, int) or K < 2:
        raise ValueError(f"{arg}: {folder} has K = {K!r} members per sequence; an "
                         f"ensemble needs K >= 2: delete it and run `garmentgnn generate "
                         f"--ensemble {MEMBERS} --out {data}`")
    dataset = {r["id"]: r for r in store.read_manifest(data)["items"]}
    records = {r["id"]: r for r in store.read_manifest(folder)["items"]}
    out: Dict[str, Any] = {"members": K, "dataset": recorded["dataset"], "sequences": {},
                           "incomplete": []}
    for sid in recorded["sequences"]:
        if sequences is not None and sid not in sequences:
            continue
        recs = [records.get(member_id(sid, k)) for k in range(1, K + 1)]
        if any(r is None or r.get("status") != "ok" for r in recs):
            out["incomplete"].append(sid)
            continue
        base = dataset.get(sid) or {}
        want = (base.get("num_frames"), base.get("num_vertices"))
        pos, valid = [], None
        for r in recs:
            seq = store.load_record_sequence(folder, r, ["positions", "converged"],
                                             optional=["penetration"])
            P = np.asarray(seq["positions"])
            if P.shape[:2] != want:
                raise ValueError(
                    f"{arg}: {store.sequence_path(folder, r)} has {P.shape[0]} frames of "
                    f"{P.shape[1]} vertices, its sequence {sid} {want[0]} of {want[1]}; "
                    f"delete it and rerun `garmentgnn generate --ensemble {K} --out {data}`")
            v = sequence_valid(seq)
            valid = v if valid is None else valid & v
            pos.append(P)
        out["sequences"][sid] = {"positions": np.stack(pos), "valid": valid}
    return out
