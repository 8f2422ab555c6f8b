"""A Lightning callback timing every training step, for :mod:`train_scaling`.

Self-contained (``lightning``, ``torch`` and the standard library), so that a ``garmentgnn
train fit`` of any source tree can load it by class path
(``--trainer.callbacks+=scaling_parts.step_timer.StepTimer``, ``benchmarks/`` on
``PYTHONPATH``).
Each process (DDP replica) writes ``rank<r>.json`` into ``$GARMENTGNN_STEP_TIMES``: the
end time of every step and its vertex-frames (frames x vertices of the batch).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, List

import lightning as L
import torch


class StepTimer(L.Callback):
    """Step end times and vertex-frames of one process, written when training ends."""

    def __init__(self) -> None:
        self.ends: List[float] = []
        self.work: List[int] = []

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        self.ends.append(time.perf_counter())
        self.work.append(int(batch.gt.shape[0] * batch.gt.shape[1]))

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        out = os.environ.get("GARMENTGNN_STEP_TIMES")
        if not out:
            return
        rec = {"rank": trainer.global_rank, "world_size": trainer.world_size,
               "threads": torch.get_num_threads(), "ends": self.ends, "work": self.work}
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / f"rank{trainer.global_rank}.json").write_text(json.dumps(rec))
