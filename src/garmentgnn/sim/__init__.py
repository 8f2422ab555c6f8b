"""Reference implicit cloth simulator (Newton on the incremental potential); see docs/simulator.md."""
from garmentgnn.sim.simulator import (ClothSystem, SimResult, SimSettings, StepResult, simulate,
                                      step)

__all__ = ["ClothSystem", "SimResult", "SimSettings", "StepResult", "simulate", "step"]
