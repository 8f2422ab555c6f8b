"""A prediction's error split into a static drape and dynamics, in the skinned frame.

With ``M_t = M_v(t) = sum_j W_vj A_j(t)`` each vertex's blended skinning transform
(Eq. 1, :meth:`~garmentgnn.models.inputs.GarmentInputs.skinning_transforms`), a posed
garment ``x_t`` is un-skinned into the rest frame by ``u_t = M_t^-1 x_t``.  The *static
drape* of a sequence is its time mean there, ``ū = mean_t u_t``, and ``M_t ū`` is that
drape posed at frame ``t``: what stays put in the skinned frame.  For a prediction
``p_t`` and the ground truth ``x_t`` (each with its own drape ``ū^pred``, ``ū^gt``):

* ``E_static  = mean_{t,v} |M_t ū^pred - M_t ū^gt|`` (cm): how far apart the two static
  drapes are when posed at each frame;
* ``E_dynamic = mean_{t,v} |(p_t - M_t ū^pred) - (x_t - M_t ū^gt)|`` (cm): how far apart
  what is left of each after removing its own static drape (the motion about the drape);
* ``E_dist    = mean_{t,v} |p_t - x_t|`` (cm), the usual distance, for reference.

``p_t - x_t`` is the sum of the two differences, so ``E_dist <= E_static + E_dynamic``.
Plain LBS (``p_t = M_t rest``) has no dynamics of its own: its ``E_dynamic`` is the
in-sample static oracle's error (``M_t ū^gt`` against ``x_t``) and its ``E_static`` is
how far the rest garment is from the true drape.  A method that learned the drape and
nothing else has ``E_static ~ 0`` and ``E_dynamic`` = LBS's.
"""
from __future__ import annotations

from typing import Dict, Optional

import torch
from torch import Tensor

from garmentgnn.metrics.garment_metrics import frame_mask

__all__ = ["posed", "split_inputs", "static_dynamic_split", "to_rest_frame"]


def _affine(transforms: Tensor, name: str = "transforms") -> None:
    """Raise unless ``transforms [..., 4, 4]`` is finite with bottom row ``[0, 0, 0, 1]``."""
    if transforms.dim() < 2 or transforms.shape[-2:] != (4, 4):
        raise ValueError(f"`{name}`: expected [..., 4, 4] transforms, got "
                         f"{tuple(transforms.shape)}")
    if not torch.isfinite(transforms).all():
        raise ValueError(f"`{name}`: contains NaN/inf")
    bottom = transforms[..., 3, :].double()
    want = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=bottom.dtype, device=bottom.device)
    if not torch.allclose(bottom, want.expand_as(bottom), atol=1e-6, rtol=0.0):
        raise ValueError(f"`{name}`: expected affine transforms (bottom row [0, 0, 0, 1])")


def to_rest_frame(transforms: Tensor, x: Tensor) -> Tensor:
    """``u = M^-1 x`` per frame and vertex (float64): a posed garment ``x [T, V, 3]``
    un-skinned with ``transforms [T, V, 4, 4]`` into the rest frame, ``[T, V, 3]``.

    Raises:
        ValueError: a transform is not affine, not finite or singular.
    """
    _affine(transforms)
    M = transforms.double()
    lin, off = M[..., :3, :3], M[..., :3, 3]
    u, info = torch.linalg.solve_ex(lin, (x.double() - off).unsqueeze(-1))
    if (info != 0).any() or not torch.isfinite(u).all():
        raise ValueError("`transforms`: a blended transform is singular (cannot un-skin)")
    return u.squeeze(-1)


def posed(transforms: Tensor, u: Tensor) -> Tensor:
    """``M u`` (float64): rest-frame positions ``u`` (``[V, 3]``, one shape for every
    frame, or ``[T, V, 3]``) posed with ``transforms [T, V, 4, 4]``, ``[T, V, 3]``."""
    M = transforms.double()
    return (M[..., :3, :3] @ u.double().unsqueeze(-1)).squeeze(-1) + M[..., :3, 3]


def _positions(x: Tensor, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise TypeError(f"`{name}`: expected a torch.Tensor, got {type(x).__name__}")
    if x.dim() != 3 or x.shape[-1] != 3:
        raise ValueError(f"`{name}`: expected [T, V, 3] positions, got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError(f"`{name}`: contains NaN/inf")
    return x.double()


def static_dynamic_split(pred: Tensor, gt: Tensor, transforms: Tensor) -> Dict[str, float]:
    """The error of ``pred`` split into a static drape and dynamics (module doc).

    ``u_t = M_t^-1 x_t`` un-skins a garment into the rest frame; the static drape of a
    sequence is its time mean ``ū = mean_t u_t`` (for ``gt`` and for ``pred``
    separately).  Then, in float64 and in cm (positions in metres):

    * ``E_static  = mean_{t,v} |M_t ū^pred - M_t ū^gt| * 100``: how far apart the two
      static drapes are when posed at each frame;
    * ``E_dynamic = mean_{t,v} |(p_t - M_t ū^pred) - (x_t - M_t ū^gt)| * 100``: what is
      left of each after removing its own static drape;
    * ``E_dist    = mean_{t,v} |p_t - x_t| * 100``, for reference
      (``E_dist <= E_static + E_dynamic``, the triangle inequality).

    Args:
        pred: ``[T, V, 3]`` predicted garment, ``T >= 1``.
        gt: ``[T, V, 3]`` ground truth.
        transforms: ``[T, V, 4, 4]`` each vertex's blended skinning transform per frame.

    Returns:
        ``{"E_static": ..., "E_dynamic": ..., "E_dist": ...}`` (floats, cm).

    Raises:
        ValueError: shapes disagree, ``T == 0``, an input is not finite, or a transform
            is not affine or singular.
    """
    p, x = _positions(pred, "pred"), _positions(gt, "gt")
    if x.shape != p.shape:
        raise ValueError(f"`gt`: expected the shape of `pred` {tuple(p.shape)}, got "
                         f"{tuple(x.shape)}")
    T, V = p.shape[:2]
    if T < 1:
        raise ValueError("`pred`: expected at least one frame (T >= 1), got T = 0")
    if not isinstance(transforms, Tensor) or transforms.shape != (T, V, 4, 4):
        got = tuple(transforms.shape) if isinstance(transforms, Tensor) else type(transforms)
        raise ValueError(f"`transforms`: expected [{T}, {V}, 4, 4] (one per frame and "
                         f"vertex of `pred`), got {got}")
    drape_p = posed(transforms, to_rest_frame(transforms, p).mean(0))
    drape_x = posed(transforms, to_rest_frame(transforms, x).mean(0))

    def cm(d: Tensor) -> float:
        return float(d.norm(dim=-1).mean()) * 100.0

    return {"E_static": cm(drape_p - drape_x),
            "E_dynamic": cm((p - drape_p) - (x - drape_x)),
            "E_dist": cm(p - x)}


def split_inputs(pred: Tensor, inp, keep: Optional[Tensor] = None) -> Dict[str, float]:
    """:func:`static_dynamic_split` of ``pred [B, V, 3]`` against a model input's ``gt``
    (a :class:`~garmentgnn.models.inputs.GarmentInputs`, whose
    :meth:`~garmentgnn.models.inputs.GarmentInputs.skinning_transforms` give ``M_t``);
    ``keep``: a ``[B]`` bool mask of the frames to score (as in
    :func:`~garmentgnn.metrics.evaluate_inputs`)."""
    if inp.get("gt") is None:
        raise ValueError("`inp`: has no ground truth `gt` to score against")
    gt, M = inp.gt, inp.skinning_transforms(torch.float64)
    keep = frame_mask(keep, gt.shape[0])
    if keep is not None:
        pred, gt, M = pred[keep], gt[keep], M[keep]
    return static_dynamic_split(pred, gt, M)
