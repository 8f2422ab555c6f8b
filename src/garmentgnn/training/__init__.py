"""Lightning training of GarTrans: chunked sequence data, the LightningModule and the
progressive schedule callback (paper §4.1)."""
from garmentgnn.training.datamodule import (
           EpochShuffleSampler,
           GarmentDataModule,
           SequenceChunks,
)
from garmentgnn.training.module import REST_BRANCH, GarTransModule
from garmentgnn.training.schedule import PHASE_TERMS, ProgressiveSchedule

__all__ = [
           "PHASE_TERMS",
           "REST_BRANCH",
           "EpochShuffleSampler",
           "GarTransModule",
           "GarmentDataModule",
           "ProgressiveSchedule",
           "SequenceChunks",
]
