"""The bench report's media: an animation of a held-out test sequence, inline in ``report.md``.

:func:`write_media` finds, in a bench run's records, the learned methods' dataset and
the GarTrans checkpoints (records of kind ``learned`` with a ``checkpoint``), and renders
ground truth | GarTrans (and its variants) | other methods | LBS only on the first test
sequence with :func:`garmentgnn.viz.compare.show` (one camera, per-vertex error colour
map in cm on a shared scale): ``OUT/media/heldout.mp4``, ``.gif``, ``.png`` (the middle
frame, shown inline), ``.glb`` (every panel with the body) and, when the viewer is built,
``heldout.html`` (:func:`garmentgnn.viz.viewer.write_viewer`).  It returns the markdown
lines of the report's section.

Methods that are not GarTrans checkpoints (the DA/HOOD/NCS-style baselines) appear when
their prediction of that sequence is saved as ``OUT/media/predictions/<method>.npy``
(``[T, V, 3]``, our vertex order; the bench's learned runner saves them for the first
training seed, :meth:`~garmentgnn.bench.learned.LearnedRunner.save_prediction`) or passed
in ``predictions``.

A rerun with the same checkpoints, predictions and options reuses the files (the options
and the files' sizes and times are kept in ``OUT/media/heldout.json``).  Set
``GARMENTGNN_BENCH_MEDIA=0`` to leave the animation out of the report (the test suite
does, as it writes many reports); without a working off-screen renderer the section says
why instead.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

from garmentgnn._files import atomic_write_json
from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS
from garmentgnn.viz.animate import renderer_unavailable
from garmentgnn.viz.compare import show
from garmentgnn.viz.viewer import write_viewer

PathLike = Union[str, os.PathLike]
MEDIA = "media"
STEM = "heldout"
ENV_VAR = "GARMENTGNN_BENCH_MEDIA"
#: at most this many GarTrans checkpoints are shown (GarTrans first, then its variants)
MAX_MODELS = 3


def media_enabled() -> bool:
    """Whether :func:`write_media` renders (``$GARMENTGNN_BENCH_MEDIA`` is not ``0``)."""
    return os.environ.get(ENV_VAR, "1").strip() != "0"


def _checkpoints(records: Sequence[Dict[str, Any]], max_models: int):
    """``(dataset root, seed, {method: checkpoint}, data options, first scored sequence)``
    of the lowest seed whose GarTrans records are ok and whose checkpoints exist, or
    ``None``.  The first scored sequence (the id of the records' first ``per_sequence``
    entry, ``None`` without one) is the one the saved predictions of
    :meth:`garmentgnn.bench.learned.LearnedRunner.save_prediction` show."""
    rs = [r for r in records if r.get("kind") == "learned" and r.get("status") == "ok"
          and r.get("checkpoint") and Path(r["checkpoint"]).is_file()
          and (r.get("dataset") or {}).get("root")]
    if not rs:
        return None
    seed = min(r["seed"] for r in rs)
    mine = [r for r in rs if r["seed"] == seed]
    root = mine[0]["dataset"]["root"]
    # GarTrans itself first (variants are named "GarTrans w/o ..."), in record order
    mine.sort(key=lambda r: (r["method"] != "GarTrans (SAT)", not r["method"].startswith(
        "GarTrans")))
    models = {r["method"]: r["checkpoint"] for r in mine if r["dataset"]["root"] == root}
    data = (mine[0].get("config") or {}).get("data") or {}
    first = next((r["per_sequence"][0]["sequence"] for r in mine if r.get("per_sequence")),
                 None)
    return root, seed, dict(list(models.items())[:max_models]), data, first


def _stamp(paths: Sequence[PathLike], options: Dict[str, Any]) -> Dict[str, Any]:
    files = {}
    for p in paths:
        st = Path(p).stat()
        files[str(p)] = [st.st_size, st.st_mtime_ns]
    return {"options": options, "files": files}


def write_media(records: Sequence[Dict[str, Any]], out: PathLike, *,
                split: Optional[str] = "test", index: Optional[Union[int, str]] = None,
                predictions: Optional[Mapping[str, PathLike]] = None,
                max_models: int = MAX_MODELS, max_frames: Optional[int] = 120,
                height: int = 720, force: bool = False) -> List[str]:
    """Render the held-out animation of a bench run into ``out/media`` and return the
    report section's markdown lines (``[]`` when the run has no trained GarTrans
    checkpoint or ``$GARMENTGNN_BENCH_MEDIA`` is ``0``).

    Args:
        records: the run's records (:func:`garmentgnn.bench.report.check_record`ed).
        out: the bench folder (``report.md`` lives there; links are relative to it).
        split, index: which sequence of the learned methods' dataset: an index into
            ``split`` (``None``: every split) or a sequence id; default: the first
            sequence the records were scored on (the one the saved predictions show),
            else the first.
        predictions: more panels, ``{name: .npy path}`` (added to the files found in
            ``out/media/predictions``).
        max_models: GarTrans checkpoints shown at most (GarTrans first).
        max_frames: the first frames only (keeps GIFs small); ``None``: all.
        height: frame height in px (>= 720).
        force: render even if the files of an identical earlier call exist.
    """
    if not media_enabled():
        return []
    found = _checkpoints(records, max_models)
    if found is None:
        return []
    root, seed, models, data, first = found
    if index is None:
        index = first if first is not None else 0
    out = Path(out)
    media = out / MEDIA
    preds: Dict[str, str] = {p.stem: str(p) for p in sorted((media / "predictions").glob("*.npy"))}
    preds.update({k: str(v) for k, v in (predictions or {}).items()})
    lines = ["## Animation of a held-out sequence", ""]
    why = renderer_unavailable()
    if why is not None:
        return lines + [f"Not rendered here: {why}.", ""]
    options = {"root": str(root), "seed": seed, "models": models, "predictions": preds,
               "split": split, "index": index, "max_frames": max_frames, "height": height,
               "history": data.get("history", HISTORY),
               "num_landmarks": data.get("num_landmarks", NUM_LANDMARKS)}
    stamp_path = media / f"{STEM}.json"
    stamp = _stamp(list(models.values()) + list(preds.values()), options)
    base = media / STEM
    try:
        old = json.loads(stamp_path.read_text()) if stamp_path.is_file() else None
    except (OSError, ValueError):
        old = None
    if force or old is None or old.get("stamp") != stamp or not base.with_suffix(".png").is_file():
        try:
            res = show(root, models, base, split=split, index=index, mode="gartrans",
                       history=options["history"], num_landmarks=options["num_landmarks"],
                       max_frames=max_frames, predictions=preds, height=height)
        except (ValueError, RuntimeError, OSError) as err:  # shown in the report, not hidden
            return lines + [f"Not rendered: {type(err).__name__}: {err}", ""]
        a, c = res["animation"], res["comparison"]
        info = {"seq_id": c.seq_id, "panels": [p.title for p in c.panels],
                "mean_error_cm": a.mean_error, "frames": a.frames, "size": list(a.size),
                "fps": a.fps, "clim": list(a.clim), "seconds": a.seconds,
                "still_frame": a.still_frame, "still_error_cm": a.still_error,
                "diverged": a.diverged,
                "files": {k: (None if v is None else Path(v).name) for k, v in
                          (("mp4", a.mp4), ("gif", a.gif), ("png", a.still),
                           ("glb", res["gltf"]))}}
        html = None
        try:
            html = write_viewer(res["gltf"], base.with_suffix(".html"), title=c.seq_id)
        except (OSError, RuntimeError, FileNotFoundError):
            pass  # the viewer bundle is not built: the .glb is still linked
        info["files"]["html"] = None if html is None else Path(html).name
        atomic_write_json(stamp_path, {"stamp": stamp, "info": info})
    else:
        info = old["info"]
    return lines + _markdown(info, seed, models, preds)


def _still(info: Dict[str, Any]) -> str:
    """The still's frame and numbers, and the diverged panels, as a sentence."""
    text = ""
    if info.get("diverged"):
        text += (f" Diverged (left the frame; clipped, labelled and left out of the colour "
                 f"scale): {', '.join(info['diverged'])}.")
    errs = info.get("still_error_cm") or {}
    names = [p for p in info["panels"] if p in errs]  # the panels' order (the JSON sorts)
    if names:
        text += (f" The picture is frame {info['still_frame'] + 1}, the one closest to "
                 f"{names[0]}'s median per-frame error; on it: "
                 + ", ".join(f"{k} {errs[k]:.2f} cm" for k in names) + ".")
    return text


def _markdown(info: Dict[str, Any], seed: int, models: Mapping[str, str],
              preds: Mapping[str, str]) -> List[str]:
    f = {k: (f"{MEDIA}/{v}" if v else None) for k, v in info["files"].items()}
    links = " · ".join(f"[{label}]({f[k]})" for k, label in
                       (("mp4", "MP4"), ("gif", "GIF"), ("glb", "glTF (.glb)"),
                        ("html", "3D viewer (HTML)")) if f.get(k))
    errs = ", ".join(f"{name} {info['mean_error_cm'][name]:.2f} cm" for name in info["panels"]
                     if name in info["mean_error_cm"])
    missing = "" if preds else (" The DA/HOOD/NCS-style baselines are not shown: no "
                                f"`{MEDIA}/predictions/<method>.npy` was saved (they were "
                                "not run).")
    lines = [f"Test sequence `{info['seq_id']}`, first {info['frames']} frames: "
             f"{' | '.join(info['panels'])} (the models of training seed {seed}). Every "
             "predicted garment is coloured by its per-vertex distance to the simulation "
             f"(cm, shared scale {info['clim'][0]:g}-{info['clim'][1]:.2g} cm); mean over the "
             f"shown frames: {errs}.{missing}{_still(info)} Its error against run time is in "
             "the learned methods' plot above (`pareto_learned.png`).", "",
             f"[![{' | '.join(info['panels'])}]({f['png']})]({f['gif'] or f['mp4']})", "",
             links, ""]
    return lines
