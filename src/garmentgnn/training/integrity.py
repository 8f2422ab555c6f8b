"""Checkpoint integrity: a SHA-256 digest stored in every checkpoint and checked on load,
and the check that command-line flags agree with a resumed checkpoint.

:func:`checkpoint_digest` hashes what defines a run -- the weights (``state_dict``),
the ``hyper_parameters`` and the optimizer / scheduler states -- in a canonical
form (tensors by dtype, shape and bytes; containers recursively).
:class:`~garmentgnn.training.GarTransModule` stores it under
:data:`INTEGRITY_KEY` when Lightning saves a checkpoint and compares it when one is
loaded (``load_from_checkpoint`` or ``fit(ckpt_path=...)``), so a flipped bit in any
weight is an error instead of a silently different model.
"""
from __future__ import annotations

import hashlib
import os
import warnings
from typing import Any, Dict, Mapping

import torch

#: checkpoint key of the digest (``{"sha256": ..., "covers": [...]}``)
INTEGRITY_KEY = "garmentgnn_integrity"
#: the checkpoint entries the digest covers (when present)
COVERED = ("state_dict", "hyper_parameters", "optimizer_states", "lr_schedulers")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, changed since it was written, or
    in conflict with the flags it is resumed with."""


def _feed(h, obj: Any) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(obj, Mapping):
        h.update(b"{")
        for k in sorted(obj, key=repr):
            h.update(repr(k).encode() + b":")
            _feed(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(b"[")
        for v in obj:
            _feed(h, v)
            h.update(b",")
        h.update(b"]")
    else:
        h.update(repr(obj).encode())


def checkpoint_digest(checkpoint: Mapping[str, Any]) -> str:
    """Hex SHA-256 of the :data:`COVERED` entries of a checkpoint dict."""
    h = hashlib.sha256()
    for key in COVERED:
        if key in checkpoint:
            h.update(key.encode())
            _feed(h, checkpoint[key])
    return h.hexdigest()


def stamp_checkpoint(checkpoint: Dict[str, Any]) -> None:
    """Store the digest in ``checkpoint`` (call last, after every covered entry is set)."""
    checkpoint[INTEGRITY_KEY] = {"sha256": checkpoint_digest(checkpoint),
                                 "covers": [k for k in COVERED if k in checkpoint]}


def verify_checkpoint(checkpoint: Mapping[str, Any], source: str = "checkpoint") -> None:
    """Raise :class:`CheckpointError` when the stored digest differs from the content;
    warn when there is none (a checkpoint written before digests were kept)."""
    stamp = checkpoint.get(INTEGRITY_KEY)
    if stamp is None:
        warnings.warn(f"{source}: no integrity digest (written by an older garmentgnn); "
                      "its content cannot be checked", stacklevel=2)
        return
    want = stamp.get("sha256") if isinstance(stamp, Mapping) else None
    if want != checkpoint_digest(checkpoint):
        raise CheckpointError(f"{source}: content differs from its integrity digest (corrupt "
                              "or edited file); use another checkpoint, e.g. an earlier "
                              "epoch's, or retrain")


def load_checkpoint_file(path: os.PathLike | str) -> Dict[str, Any]:
    """``torch.load`` (weights only, CPU) of a checkpoint file, verified; unreadable or
    truncated files raise :class:`CheckpointError` naming the path."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # zip / pickle / storage errors of many kinds
        raise CheckpointError(f"{path}: unreadable checkpoint (truncated or corrupt: "
                              f"{type(e).__name__}); use another checkpoint or retrain"
                              ) from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise CheckpointError(f"{path}: not a Lightning checkpoint (no 'state_dict')")
    verify_checkpoint(ckpt, path)
    return ckpt


def hparam_conflicts(given: Mapping[str, Any], defaults: Mapping[str, Any],
                     stored: Mapping[str, Any]) -> Dict[str, tuple]:
    """``{name: (given, stored)}`` for every hyper-parameter set explicitly (``given``
    differs from ``defaults``) to something other than the checkpoint's ``stored``."""
    def same(a, b) -> bool:
        if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            return set(a) == set(b) and all(same(a[k], b[k]) for k in a)
        return a == b

    out = {}
    for k, v in given.items():
        if k in stored and k in defaults and not same(v, defaults[k]) \
                and not same(v, stored[k]):
            out[k] = (v, stored[k])
    return out


__all__ = ["COVERED", "CheckpointError", "INTEGRITY_KEY", "checkpoint_digest",
           "hparam_conflicts", "load_checkpoint_file", "stamp_checkpoint",
           "verify_checkpoint"]
