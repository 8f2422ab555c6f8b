"""Headless PNG stills of meshes with matplotlib (flat Lambert shading, painter's order).

Good enough to look at garments on bodies from a test or a demo with no GPU and
no display; not a production renderer.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from garmentgnn._plotting import pyplot

ArrayLike = Union[np.ndarray, torch.Tensor]
Mesh = Tuple[ArrayLike, ArrayLike, Sequence[float]]  # vertices [V,3], faces [F,3], RGB


def _np(a: ArrayLike) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def draw_meshes(ax, meshes: Iterable[Mesh], elev: float = 10.0, azim: float = -90.0,
                light: Sequence[float] = (0.3, -0.8, 0.6)) -> None:
    """Draw shaded meshes into a matplotlib 3D axis (Z up; the default view looks
    at the body's front, which faces -Y)."""
    # matplotlib: loaded on the first figure, not with the package
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: PLC0415

    light_dir = np.asarray(light, dtype=float)
    light_dir /= np.linalg.norm(light_dir)
    polys, colors = [], []
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for verts, faces, rgb in meshes:
        v, f = _np(verts).astype(float), _np(faces).astype(int)
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
        shade = 0.35 + 0.65 * np.abs(n @ light_dir)  # two-sided: open garments show inside
        polys.append(tri)
        colors.append(np.clip(np.asarray(rgb)[None, :3] * shade[:, None], 0, 1))
        lo, hi = np.minimum(lo, v.min(0)), np.maximum(hi, v.max(0))
    coll = Poly3DCollection(np.concatenate(polys), facecolors=np.concatenate(colors),
                            edgecolors="none", linewidths=0.0)
    ax.add_collection3d(coll)
    centre, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()


def render_grid(cells: List[List[List[Mesh]]], path: Union[str, Path],
                titles: Optional[List[List[str]]] = None, cell_size: float = 2.6,
                dpi: int = 110, **view) -> Path:
    """Render a rows x cols grid of scenes (each a list of meshes) into one PNG."""
    plt = pyplot()

    rows, cols = len(cells), max(len(r) for r in cells)
    fig = plt.figure(figsize=(cell_size * cols, cell_size * 1.25 * rows))
    for i, row in enumerate(cells):
        for j, scene in enumerate(row):
            ax = fig.add_subplot(rows, cols, i * cols + j + 1, projection="3d")
            draw_meshes(ax, scene, **view)
            if titles:
                ax.set_title(titles[i][j], fontsize=8)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.95, wspace=0, hspace=0.05)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
