"""Lightning training: the data module, the GarTrans, baseline and learned-simulator
LightningModules (each a :class:`GarmentModule`), the progressive schedule callback (paper §4.1), a
wall-clock training budget, freed memory kept for the next step (:class:`KeepFreedMemory`),
the recipes' loader (:func:`load_recipe`) and the checkpoints' (:func:`load_checkpoint`)."""
from garmentgnn.training.datamodule import (
           EpochShuffleSampler,
           GarmentDataModule,
)
from garmentgnn.training.base import GarmentModule
from garmentgnn.training.baselines import BaselineModule
from garmentgnn.training.budget import TimeBudget
from garmentgnn.training.heap import KeepFreedMemory, keep_freed_memory
from garmentgnn.training.module import REST_BRANCH, GarTransModule, loss_inputs
from garmentgnn.training.schedule import PHASE_TERMS, ProgressiveSchedule
from garmentgnn.training.rollout import RolloutModule
from garmentgnn.training.loader import Recipe, load_recipe
from garmentgnn.training.checkpoints import fork_checkpoint, load_checkpoint

__all__ = [
           "PHASE_TERMS",
           "REST_BRANCH",
           "BaselineModule",
           "EpochShuffleSampler",
           "GarTransModule",
           "GarmentModule",
           "GarmentDataModule",
           "KeepFreedMemory",
           "ProgressiveSchedule",
           "Recipe",
           "RolloutModule",
           "TimeBudget",
           "fork_checkpoint",
           "keep_freed_memory",
           "load_checkpoint",
           "load_recipe",
           "loss_inputs",
]
