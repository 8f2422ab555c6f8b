"""The dataset a ``garmentgnn bench`` run trains and scores its learned methods on
(:mod:`garmentgnn.bench.learned`): generated (resumably) or given, with its fingerprint
and content hash."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

from garmentgnn.bench.methods import DATA
from garmentgnn.data import SequenceChunks, generate, preset, store
from garmentgnn.data.ensemble import load_ensemble

__all__ = ["DatasetInfo", "ensemble_sequences", "prepare_dataset"]


@dataclass
class DatasetInfo:
    """A generated dataset's folder, spec name, fingerprint (of its ok items' ids,
    splits, frame counts and generating code versions), ok sequence / frame counts per
    split and content hash (``garmentgnn.data.store.content_sha256``)."""

    root: Path
    name: str
    fingerprint: str
    sequences: Dict[str, int]
    frames: Dict[str, int]
    content_sha256: Optional[str] = None

    @property
    def case(self) -> str:
        """The records' ``case``: another dataset gives other records."""
        return f"{self.name}-{self.fingerprint[:8]}/test"

    def to_json(self) -> Dict[str, Any]:
        return dict(asdict(self), root=str(self.root))


def prepare_dataset(root, preset_name: Optional[str] = None, workers: int = 1,
                    progress: bool = True) -> DatasetInfo:
    """The dataset under ``root``; with ``preset_name``, first generate (or finish
    generating) that :func:`garmentgnn.data.generate.preset` there.

    Raises ``ValueError`` naming ``data`` when ``root`` holds no manifest or no ok
    ``train`` / ``test`` sequences."""
    root = Path(root)
    if preset_name is not None:
        if not isinstance(workers, int) or workers < 0:
            raise ValueError(f"`workers`: expected a non-negative int, got {workers!r}")
        generate(preset(preset_name), root, workers=workers, progress=progress,
                 log=None if progress else (lambda msg: None))
    try:
        man = store.read_manifest(root)
    except (OSError, ValueError) as err:
        raise ValueError(f"`data`: {root} is not a generated dataset (no readable "
                         f"manifest.json: {err})") from err
    ok = [r for r in man.get("items", []) if r.get("status") == "ok"]
    seqs = {s: sum(r["split"] == s for r in ok) for s in ("train", "val", "test")}
    frames = {s: sum(int(r["num_frames"]) for r in ok if r["split"] == s)
              for s in ("train", "val", "test")}
    for s in ("train", "test"):
        if not seqs[s]:
            raise ValueError(f"`data` (--data): {root} has no ok {s!r} sequences, which the "
                             f"learned methods {'train' if s == 'train' else 'are scored'} on "
                             f"({man.get('counts')}); give a dataset with a {s!r} split")
    digest = hashlib.sha1(json.dumps(sorted(
        (r["id"], r["split"], int(r["num_frames"]), str((r.get("code") or {}).get("version")))
        for r in ok)).encode())
    return DatasetInfo(root, str(man.get("name", root.name)), digest.hexdigest(), seqs, frames,
                       store.content_sha256(ok))


def ensemble_sequences(root) -> Tuple[Optional[Dict[str, Any]], Optional[SequenceChunks]]:
    """The ensemble ground truth of the dataset under ``root``
    (:func:`garmentgnn.data.ensemble.load_ensemble`) and its sequences as the learned
    methods read whole test sequences (:data:`garmentgnn.bench.methods.DATA`); ``(None,
    None)`` without one."""
    ensemble = load_ensemble(root)
    if ensemble is None or not ensemble["sequences"]:
        return None, None
    kw = {k: DATA[k] for k in ("history", "nystrom_dim", "num_landmarks")}
    return ensemble, SequenceChunks(root, "test", chunk=10 ** 9,
                                    ids=sorted(ensemble["sequences"]), **kw)
