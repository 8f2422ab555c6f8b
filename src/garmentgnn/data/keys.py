"""Readable keys of a dataset spec's entries (garment, body, motion).

Held-out lists name their garments, bodies and motions by these keys
(:class:`garmentgnn.data.presets.Spec`), and the bench groups sequences by them.
Plain string functions: importing them costs neither torch nor a body model.
"""
from __future__ import annotations

from typing import Any, Dict


def garment_key(g: Dict[str, Any]) -> str:
    """``kind-param=value...@resolution`` of a garment entry (``file:NAME@SHA8`` of a
    mesh file's)."""
    if "file" in g:
        return f"file:{g['file']}@{g['sha256'][:8]}"
    params = "".join(f"-{k}={v}" for k, v in sorted(g.get("params", {}).items()))
    return f"{g['kind']}{params}@{g['resolution']}"


def body_key(b: Dict[str, Any]) -> str:
    """``model:shape`` of a body entry (a custom shape as its values to 4 digits)."""
    s = b["shape"]
    s = s if isinstance(s, str) else "[" + ",".join(f"{x:.4g}" for x in s) + "]"
    return f"{b['model']}:{s}"


def motion_key(m: Dict[str, Any]) -> str:
    """``name-s<speed>-a<amplitude>-n<frames>`` of a motion entry (``file:NAME@SHA8-n<frames>``
    of a BVH file's)."""
    if "file" in m:
        return f"file:{m['file']}@{m['sha256'][:8]}-n{m['num_frames']}"
    return f"{m['name']}-s{m.get('speed', 1.0):g}-a{m.get('amplitude', 1.0):g}-n{m['num_frames']}"


__all__ = ["body_key", "garment_key", "motion_key"]
