"""The machine a throughput benchmark ran on, for its results (``step_profile.py``,
``train_scaling.py``)."""
from __future__ import annotations

import platform

import torch


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``, else the architecture) and the vector
    instructions PyTorch's CPU kernels use here (``torch.backends.cpu``)."""
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            name = next((ln.split(":", 1)[1].strip() for ln in f
                         if ln.startswith("model name")), name)
    except OSError:
        pass
    return f"{name} ({torch.backends.cpu.get_cpu_capability()})"
