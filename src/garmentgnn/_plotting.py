"""matplotlib for the package's figures, on its off-screen Agg backend: every plotting
module draws through :func:`pyplot`, so PNGs are written the same way on a machine with no
display (a test run, a server) as on a desktop."""
from __future__ import annotations

from types import ModuleType

__all__ = ["pyplot"]


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` with the Agg backend selected."""
    # matplotlib is imported on the first figure, not with the package (about 0.3 s)
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt
