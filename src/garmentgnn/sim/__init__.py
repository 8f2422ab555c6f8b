"""Reference implicit cloth simulator (Newton on the incremental potential); see
docs/simulator.md."""
from garmentgnn.sim.colliders import Collider, Plane, Sphere
from garmentgnn.sim.simulator import (ClothSystem, Contact, SimResult, SimSettings, StepResult,
                                      simulate, step, trajectories)

__all__ = ["ClothSystem", "Collider", "Contact", "Plane", "SimResult", "SimSettings", "Sphere",
           "StepResult", "simulate", "step", "trajectories"]
