"""Cloth energies and materials: one definition shared by ``sim/`` and ``losses/``."""
from garmentgnn.physics.energies import (GRAVITY, ClothRest, bending_energy, collision_energy,
                                         gravity_energy, inertia_energy, shear_energy,
                                         stretch_energy, stvk_energy)
from garmentgnn.physics.friction import friction_energy, friction_hessian
from garmentgnn.physics.materials import (COLLISION_MARGIN, MATERIAL_FEATURES, MATERIALS,
                                          Material, material, material_features)

__all__ = ["COLLISION_MARGIN", "GRAVITY", "MATERIAL_FEATURES", "MATERIALS", "ClothRest",
           "Material",
           "bending_energy", "collision_energy", "friction_energy", "friction_hessian",
           "gravity_energy", "inertia_energy", "material", "material_features", "shear_energy",
           "stretch_energy",
           "stvk_energy"]
