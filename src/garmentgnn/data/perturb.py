"""Inputs moved by a rounding error: the perturbations that show the ground truth's
chaos (cloth simulation is chaotic: moving the rest garment by 1e-7 m moves Blender's
sequence by about 1 cm on ``learn``).

``benchmarks/gt_noise.py`` measures that divergence (:mod:`garmentgnn.bench.noise_floor`),
and an ensemble ground truth (:mod:`garmentgnn.data.ensemble`) simulates each of its
members from a rest garment moved so (:func:`perturbed_garment`).
"""
from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

__all__ = ["PERTURB_M", "perturbed_garment", "perturbed_motion", "random_offsets"]

#: the perturbation the floor is quoted at and an ensemble's members are simulated with
#: (a float32 rounding error at metre scale)
PERTURB_M = 1e-7


def _check_scale(scale: float) -> float:
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or \
            not math.isfinite(scale) or scale < 0:
        raise ValueError(f"`scale`: expected a finite distance >= 0 in metres, got {scale!r}")
    return float(scale)


def random_offsets(n: int, scale: float, seed: int) -> Tensor:
    """``[n, 3]`` float64 offsets of length ``scale`` (m) in uniformly random directions."""
    scale = _check_scale(scale)
    g = torch.Generator().manual_seed(int(seed))
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return scale * d / d.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def perturbed_garment(garment, scale: float, seed: int = 0):
    """A copy of ``garment`` whose rest vertices each moved ``scale`` metres in a random
    direction (then rounded to the garment's float32; UVs, faces and pins unchanged)."""
    v = garment.vertices
    new = (v.double() + random_offsets(v.shape[0], scale, seed)).to(v.dtype)
    return dataclasses.replace(garment, vertices=new)


def perturbed_motion(motion, scale: float, seed: int = 0):
    """A copy of ``motion`` whose root translation moved ``scale`` metres in a random
    direction at every frame (the body and the vertices pinned to it follow)."""
    t = motion.translation
    new = (t.double() + random_offsets(t.shape[0], scale, seed)).to(t.dtype)
    return dataclasses.replace(motion, translation=new)
