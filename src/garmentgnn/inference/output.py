"""The files of a prediction: an animated glTF with the body (``.glb``), a PC2 point
cache (``.pc2``) and one OBJ per frame (a folder), written by the exporters of
:mod:`garmentgnn.data.export` and :mod:`garmentgnn.data.gltf`."""
from __future__ import annotations

from pathlib import Path
from typing import Dict, Union

from garmentgnn.data.export import check_output, write_obj_sequence, write_pc2
from garmentgnn.data.gltf import sequence_meshes, write_gltf

PathLike = Union[str, Path]


def output_paths(out: PathLike, name: str = "prediction") -> Dict[str, Path]:
    """``{"glb", "pc2", "obj"}`` for ``out``: a folder (one that exists, or a path ending
    in ``/``) gets ``<name>.glb``, ``<name>.pc2`` and ``<name>_obj/``; anything else is a
    stem (a ``.glb`` / ``.pc2`` suffix dropped): ``<out>.glb``, ``<out>.pc2``,
    ``<out>_obj/``.  Each is checked writable (:func:`check_output`) before any work."""
    text = str(out)
    if not text.strip():
        raise ValueError("`out`: empty path; name a folder or a file stem, e.g. out/walk")
    path = Path(out)
    if path.is_dir() or text.endswith(("/", "\\")):
        stem = path / name
    else:
        stem = path.with_suffix("") if path.suffix.lower() in (".glb", ".pc2") else path
    paths = {"glb": stem.parent / (stem.name + ".glb"), "pc2": stem.parent / (stem.name + ".pc2"),
             "obj": stem.parent / (stem.name + "_obj")}
    for fmt, p in (("gltf", paths["glb"]), ("pc2", paths["pc2"]), ("obj", paths["obj"])):
        try:
            check_output(p, fmt)
        except ValueError as exc:
            raise ValueError(f"`out` {out}: {str(exc).split(': ', 1)[-1]}") from None
    return paths


def write_prediction(prediction, out: PathLike, body: bool = True) -> Dict[str, Path]:
    """Write ``prediction`` (:class:`~garmentgnn.inference.predict.Prediction`) to
    :func:`output_paths`; returns them."""
    paths = output_paths(out)
    for p in (paths["glb"], paths["pc2"]):
        p.parent.mkdir(parents=True, exist_ok=True)
    meshes, fps = sequence_meshes(prediction.seq, body=body)
    write_gltf(paths["glb"], meshes, fps=fps)
    write_pc2(paths["pc2"], prediction.positions)
    write_obj_sequence(paths["obj"], prediction.positions, prediction.faces)
    return paths


__all__ = ["output_paths", "write_prediction"]
