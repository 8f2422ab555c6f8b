"""Fabric materials in physical units."""
from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Dict, Mapping, Tuple, Union

import torch

#: the body's collision thickness (m): Eq. 10's ``epsilon``, the collision losses' and
#: the projections' margin (its one home)
COLLISION_MARGIN = 2e-3


@dataclass(frozen=True)
class Material:
    """Thin-shell cloth parameters (all per unit rest area, SI units).

    Attributes:
        density: surface density, kg/m^2.
        stretch: Baraff-Witkin stretch stiffness ``k_s`` of Eq. 12, N/m (energy per
            rest area per unit squared strain).
        shear: shear stiffness ``k_h`` of Eq. 13, N/m.
        bending: bending stiffness, N*m (J): energy ``k_b * l^2 / (4 A) * (theta - theta0)^2 / 2``
            per hinge (HOOD's discrete shell form).
        lame_mu, lame_lambda: StVK Lame parameters integrated over the thickness, N/m
            (the alternative membrane model).
        friction: Coulomb friction coefficient against the body.
        collision_margin: the body's collision thickness ``epsilon`` of Eq. 10, m.
    """

    density: float
    stretch: float
    shear: float
    bending: float
    lame_mu: float
    lame_lambda: float
    friction: float = 0.5
    collision_margin: float = COLLISION_MARGIN

    def __post_init__(self) -> None:
        for name in ("density", "stretch", "shear", "lame_mu"):
            if not getattr(self, name) > 0:
                raise ValueError(f"`{name}` must be positive, got {getattr(self, name)}")
        for name in ("bending", "lame_lambda", "friction", "collision_margin"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"`{name}` must be non-negative, got {getattr(self, name)}")

    def scaled(self, stiffness: float) -> "Material":
        """The same fabric with every stiffness multiplied by ``stiffness`` (e.g. 1000)."""
        if not stiffness > 0:
            raise ValueError(f"`stiffness` must be positive, got {stiffness}")
        return replace(self, stretch=self.stretch * stiffness, shear=self.shear * stiffness,
                       bending=self.bending * stiffness, lame_mu=self.lame_mu * stiffness,
                       lame_lambda=self.lame_lambda * stiffness)


#: Presets.  Silk uses HOOD's validation material (density 0.20022 kg/m^2,
#: mu 23600 N/m, lambda 44400 N/m, bending 3.96e-5 J), which its authors fitted to
#: a light woven fabric; the others scale density and stiffness toward heavier cloth
#: (orders of magnitude as in common cloth-simulation presets, not measurements).
MATERIALS: Dict[str, Material] = {
    "silk": Material(density=0.20022, stretch=23600.0, shear=8000.0, bending=3.96e-5,
                     lame_mu=23600.0, lame_lambda=44400.0, friction=0.3),
    "cotton": Material(density=0.30, stretch=60000.0, shear=20000.0, bending=2e-4,
                       lame_mu=60000.0, lame_lambda=90000.0, friction=0.5),
    "denim": Material(density=0.45, stretch=150000.0, shear=50000.0, bending=2e-3,
                      lame_mu=150000.0, lame_lambda=200000.0, friction=0.6),
    "leather": Material(density=0.90, stretch=400000.0, shear=150000.0, bending=2e-2,
                        lame_mu=400000.0, lame_lambda=500000.0, friction=0.7),
}


def material(name: str) -> Material:
    """Look up a preset by name (``ValueError`` listing the presets otherwise)."""
    if name not in MATERIALS:
        raise ValueError(f"`material`: unknown preset {name!r}; choose one of {sorted(MATERIALS)}")
    return MATERIALS[name]


#: the fabric as a learned model reads it (:func:`material_features`)
MATERIAL_FEATURES: Tuple[str, ...] = ("stretch", "shear", "bending", "density")


def material_features(fabric: Union[Material, Mapping[str, float]]) -> torch.Tensor:
    """``[4]`` float32: the natural logs of :data:`MATERIAL_FEATURES` of ``fabric`` (a
    :class:`Material`, or a mapping with those keys, such as a sequence's
    ``material_params``): the fabric input of a learned simulator."""
    get = (lambda k: getattr(fabric, k)) if isinstance(fabric, Material) else fabric.get
    values = []
    for k in MATERIAL_FEATURES:
        v = get(k)
        if not isinstance(v, (int, float)) or not v > 0 or not math.isfinite(v):
            raise ValueError(f"`fabric`: expected a positive {k!r}, got {v!r}")
        values.append(math.log(float(v)))
    return torch.tensor(values, dtype=torch.float32)
