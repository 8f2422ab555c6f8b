"""What every bench report section shares: the metric columns and units, mean ± std
cells, markdown tables and the error-against-run-time plot."""
from __future__ import annotations

import re
import statistics
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Any

from garmentgnn._plotting import pyplot

__all__ = ["METRICS", "UNITS", "fmt", "slug", "mean_std", "pareto_front", "plot_points",
           "plot_summary", "save_figure", "table"]

METRICS: Tuple[str, ...] = ("E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv", "collision_rate")
UNITS = {"E_dist": "cm", "E_vnorm": "deg", "E_fnorm": "deg", "E_len": "%", "E_curv": "rad",
         "collision_rate": "%"}


def mean_std(values: Sequence[float]) -> Tuple[float, float]:
    m = statistics.fmean(values)
    return m, (statistics.stdev(values) if len(values) > 1 else 0.0)


def fmt(values: Sequence[float], digits: int = 3) -> str:
    m, s = mean_std(values)
    return f"{m:.{digits}g} ± {s:.2g}" if len(values) > 1 else f"{m:.{digits}g}"


def pareto_front(points: Sequence[Tuple[str, float, float]]) -> List[str]:
    """Names of the points not dominated in (latency, error), both lower-is-better."""
    front = []
    for name, x, y in points:
        if not any((x2 <= x and y2 <= y) and (x2 < x or y2 < y) for _, x2, y2 in points):
            front.append(name)
    return front


def table(header: List[str], rows: List[List[str]]) -> List[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def plot_summary(summ: Dict[str, Dict[str, Any]], path, title: str,
                 bands: Sequence[Tuple[str, float]] = ()) -> Optional[Path]:
    """``log latency`` vs ``E_dist`` of per-method means ``{method: {"latency_ms":
    {"mean": ...}, "E_dist": {"mean": ...}}}`` (Pareto front joined); ``None`` if no
    method has both numbers.  ``bands``: see :func:`plot_points`."""
    pts = [(m, e["latency_ms"]["mean"], e["E_dist"]["mean"]) for m, e in summ.items()
           if "latency_ms" in e and "E_dist" in e and e["latency_ms"]["mean"] > 0]
    if not pts:
        return None
    return plot_points(pts, path, title, bands=bands)


def plot_points(pts: Sequence[Tuple[str, float, float]], path, title: str,
                xlabel: str = "latency per frame at batch 1 (ms, log)",
                bands: Sequence[Tuple[str, float]] = ()) -> Path:
    """Scatter ``(name, time ms, E_dist cm)`` points on a log time axis, the Pareto front
    joined, into the PNG ``path``.  Each point has its own marker and colour and is named,
    with its error, in a legend beside the axes (text labels overlap when methods sit
    close together); the error axis turns logarithmic when the errors span more than a
    factor 5, so that one diverged method does not flatten the rest.  ``bands``: ``(name,
    E_dist cm)`` drawn as shaded horizontal bands from the axis' bottom up to that error
    (the ground truth's noise floors, :mod:`garmentgnn.bench.noise_floor`)."""
    plt = pyplot()

    front = set(pareto_front(pts))
    markers = "osD^vP*Xh<>p"
    fig, ax = plt.subplots(figsize=(9.6, 4.8))
    for i, (name, x, y) in enumerate(pts):
        label = f"{name}: {y:.3g} cm" + (" (front)" if name in front else "")
        ax.scatter([x], [y], marker=markers[i % len(markers)], s=42, zorder=3,
                   color=plt.get_cmap("tab20")(i % 20), label=label,
                   edgecolors="black" if name in front else "none", linewidths=1.2)
    fp = sorted((x, y) for n, x, y in pts if n in front)
    if len(fp) > 1:
        ax.step([p[0] for p in fp], [p[1] for p in fp], where="post", color="C3", alpha=0.5,
                label="Pareto front")
    ys = [y for _, _, y in pts if y > 0] + [y for _, y in bands if y > 0]
    if ys and max(ys) > 5 * min(ys):
        ax.set_yscale("log")
    bottom = 0.0 if ax.get_yscale() == "linear" else 0.5 * min(ys)
    for i, (name, y) in enumerate(sorted(bands, key=lambda b: -b[1])):
        ax.axhspan(bottom, y, color=("0.55", "tab:cyan", "tab:olive")[i % 3], alpha=0.18,
                   zorder=1, label=f"{name}: {y:.3g} cm")
    if bands:  # the bands reach down to the axis
        ax.set_ylim(bottom, ax.get_ylim()[1])
    ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("E_dist (cm" + (", log)" if ax.get_yscale() == "log" else ")"))
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    return save_figure(fig, path)


def save_figure(fig, path) -> Path:
    """Write a matplotlib figure to ``path`` (PNG, write-then-rename) and close it."""
    plt = pyplot()

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=120)
    plt.close(fig)
    tmp.replace(path)
    return path


def slug(s: str) -> str:
    """``s`` as a file-name part (records, model folders)."""
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", s).strip("_")
