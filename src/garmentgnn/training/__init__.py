"""Lightning training: the data module, the GarTrans and baseline LightningModules
(both :class:`GarmentModule`), the progressive schedule callback (paper §4.1), a
wall-clock training budget and the packaged configurations."""
from garmentgnn.training.datamodule import (
           EpochShuffleSampler,
           GarmentDataModule,
)
from garmentgnn.training.base import GarmentModule
from garmentgnn.training.baselines import BaselineModule
from garmentgnn.training.budget import TimeBudget
from garmentgnn.training.module import REST_BRANCH, GarTransModule, loss_inputs
from garmentgnn.training.schedule import PHASE_TERMS, ProgressiveSchedule

__all__ = [
           "PHASE_TERMS",
           "REST_BRANCH",
           "BaselineModule",
           "EpochShuffleSampler",
           "GarTransModule",
           "GarmentModule",
           "GarmentDataModule",
           "ProgressiveSchedule",
           "TimeBudget",
           "loss_inputs",
]
