"""Mixed precision: positions and what is computed from them stay float32 under
``torch.autocast`` (the models' kinematics, skinning and post-steps, and the losses)."""
from __future__ import annotations

import contextlib
from typing import Callable, Iterator

import torch
from torch import Tensor


@contextlib.contextmanager
def full_precision(x: Tensor) -> Iterator[Callable[[Tensor], Tensor]]:
    """Autocast off on ``x``'s device, yielding the cast of a tensor to float32 (or wider):
    under a mixed-precision step the kinematics, skinning and post-steps stay float32
    (bfloat16's 8-bit mantissa is about 4 mm at 1 m, the order of the errors the model
    learns; docs/bench.md, "Reduced precision") and the networks run in the low
    precision.  Without autocast it changes nothing (the cast is the identity)."""
    kind = x.device.type
    try:
        on = torch.is_autocast_enabled(kind)
    except RuntimeError:  # a device type without autocast (meta)
        on = False
    if not on:
        yield lambda t: t
        return
    with torch.autocast(kind, enabled=False):
        yield lambda t: t.to(torch.promote_types(t.dtype, torch.float32))
