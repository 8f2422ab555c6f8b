"""``torch.compile`` of a geometry kernel with an eager fallback (the candidate face
search, the face cache's certification)."""
from __future__ import annotations

import warnings
from typing import Any, Callable, Dict

import torch
from torch.utils._python_dispatch import _get_current_dispatch_mode


def compiled_or_eager(fn: Callable[..., Any], store: Dict[str, Any], what: str,
                      stacklevel: int) -> Callable[..., Any]:
    """``fn`` through ``torch.compile(fn, dynamic=True)``, built once and kept in
    ``store["fn"]`` (a module's own dict, one per kernel).  Eager where compiling failed
    before (``store["failed"]``) and under a ``TorchDispatchMode`` (FLOP and operator
    counters see the eager operators; compiled code run under a mode was not run compiled
    again afterwards, so the search stayed eager, 3-4x slower).  Where compiling fails
    (e.g. no C++ compiler) it warns once ("compiled ``what`` unavailable") and every
    later call runs eager."""
    if store.get("failed"):
        return fn
    if "fn" not in store:
        store["fn"] = torch.compile(fn, dynamic=True)

    def guarded(*args: Any) -> Any:
        if _get_current_dispatch_mode() is not None:
            return fn(*args)
        try:
            return store["fn"](*args)
        except Exception as err:  # noqa: BLE001 -- any compiler failure: use eager
            warnings.warn(f"compiled {what} unavailable ({type(err).__name__}: {err}); "
                          f"using eager", RuntimeWarning, stacklevel=stacklevel)
            store["failed"] = True
            return fn(*args)
    return guarded
