"""The bench: accuracy against a reference simulation, run time and
memory, a stability suite, and scaling / leave-out / reduced-precision / long-sequence
reports; ``garmentgnn bench`` (see :mod:`garmentgnn.bench.cli`)."""
from garmentgnn.bench.runner import METHODS, PLANNED, Prediction, register, run
from garmentgnn.bench.presets import PRESET_NAMES, Preset, SimBudget, preset
from garmentgnn.bench.report import write_report

__all__ = ["METHODS", "PLANNED", "PRESET_NAMES", "Prediction", "Preset", "SimBudget", "preset",
           "register", "run", "write_report"]
