"""Pictures and films of garments: headless renders, animations, training plots.

* :mod:`garmentgnn.viz.mpl` -- small matplotlib stills (:func:`render_grid`,
  :func:`draw_meshes`), no extra dependencies, painter's order (no depth buffer);
* :mod:`garmentgnn.viz.animate` -- side-by-side MP4/GIF animations of ground truth and
  predictions with a per-vertex error colour map, rendered off-screen with
  pyvista/VTK (the ``viz`` extra: ``pip install garmentgnn[viz]``);
* :mod:`garmentgnn.viz.compare` -- the panels of a held-out sequence from trained
  checkpoints (ground truth | GarTrans | other checkpoints | LBS);
* :mod:`garmentgnn.viz.viewer` -- a single-file HTML viewer (three.js) of an exported glTF.
"""
from garmentgnn.viz.mpl import draw_meshes, render_grid

__all__ = ["draw_meshes", "render_grid"]
