"""Leave-out report: what GarTrans and its loss actually skip when a scene lacks a body,
a moving pose or material coordinates, and how much time that saves.

Scenes (built from one chunk of a bench sequence, every frame in one frame-parallel
batch, as in training):

===============  =================================================================
``full``         body (vertex-to-joint distances, posed body), moving pose, UVs
``no_body``      no body: ``body_joint_dists``, ``body_pos``, ``body_faces`` = None
``static_pose``  the first frame's pose held for every frame and history entry
``no_uvs``       no material coordinates: ``rest`` (the ClothRest) = None
===============  =================================================================

**What runs** is measured, not assumed: a forward hook on every child module of
:class:`~garmentgnn.models.GarTrans` (``rest_fc``, ``body_fc``, ``gru``, ...) counts its
calls during one training-style step (:meth:`GarTransModule.forward`: ``encode_static``
+ ``forward``, then :meth:`GarTransModule.compute_loss` with every term of the last
training phase, :data:`garmentgnn.training.PHASE_TERMS` ``[3]``), and the loss terms
are the ones :class:`~garmentgnn.losses.gartrans_loss.GarTransLoss` returned.
:data:`SHOULD_SKIP` holds what each scene's missing input makes unneeded; each entry is
reported as ``skipped`` or ``computed`` from the measurement.

**Time saved**: the wall time of that step (forward + loss) on the scene against the
same step on the scene with the left-out input put back (which is the ``full``
scene); all scenes are timed interleaved in one
:func:`garmentgnn.bench.timing.side_by_side` run.
"""
from __future__ import annotations

import copy
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.bench.model_inputs import BenchChunks, untrained_module
from garmentgnn.bench.records import failure, section
from garmentgnn.bench.sequences import BenchSequence
from garmentgnn.bench.tables import table
from garmentgnn.bench.timing import side_by_side
from garmentgnn.training import PHASE_TERMS

#: the method name of leave-out records
METHOD = "GarTrans (untrained)"

SCENES: Dict[str, str] = {
    "full": "body + moving pose + material UVs",
    "no_body": "no body (no body distances, no posed body)",
    "static_pose": "the first frame's pose held still",
    "no_uvs": "no material coordinates (no ClothRest)",
}

#: what each scene should skip, its input being missing: model branches (GarTrans child
#: modules) and loss terms.  This is the specification checked; what runs is measured.
SHOULD_SKIP: Dict[str, Tuple[str, ...]] = {
    "full": (),
    "no_body": ("body_fc", "collision"),
    "static_pose": ("gru",),
    "no_uvs": ("stretch", "shear"),
}


def scene_item(base: Dict[str, Any], scene: str) -> Dict[str, Any]:
    """``base`` (a :class:`~garmentgnn.bench.model_inputs.BenchChunks` item of the full
    scene) turned into leave-out ``scene`` (a shallow copy: tensors are shared; a part the
    scene does not have is removed)."""
    if scene not in SCENES:
        raise ValueError(f"`scene`: unknown {scene!r}; choose one of {sorted(SCENES)}")
    item = copy.copy(base)
    if scene == "no_body":
        for k in ("body_joint_dists", "body_pos", "body_faces"):
            del item[k]
    elif scene == "static_pose":
        r, t = base["rotations"], base["translation"]
        item.update({"rotations": r[:1, :1].expand_as(r).contiguous(),
                     "translation": t[:1, :1].expand_as(t).contiguous(),
                     "body_pos": base["body_pos"][:1].expand_as(base["body_pos"]).contiguous()})
    elif scene == "no_uvs":
        del item["rest"]
    return item


def step(module, item: Dict[str, Any]) -> Tuple[Dict[str, Tensor], Tensor, Dict[str, Tensor]]:
    """One training-style step without the backward pass: ``(prediction, total loss,
    loss terms)``."""
    out = module(item)
    total, terms = module.compute_loss(item, out)
    return out, total, terms


def active(module, item: Dict[str, Any]) -> Dict[str, Any]:
    """Run :func:`step` once with a forward hook on every child module of the model;
    ``{"branches": {name: calls}, "loss_terms": [names returned]}``."""
    calls = {name: 0 for name, _ in module.model.named_children()}
    handles = []
    for name, child in module.model.named_children():
        def hook(_m, _i, _o, name=name):
            calls[name] += 1
        handles.append(child.register_forward_hook(hook))
    try:
        with torch.no_grad():
            _, _, terms = step(module, item)
    finally:
        for h in handles:
            h.remove()
    return {"branches": calls, "loss_terms": sorted(terms)}


def run_record(seq: BenchSequence, gt: Tensor, seed: int = 0, warmup: int = 2,
               repeats: int = 5, history: int = HISTORY, nystrom_dim: int = NYSTROM_DIM,
               num_landmarks: int = NUM_LANDMARKS, module_kwargs: Optional[Dict[str, Any]] = None
               ) -> Dict[str, Any]:
    """The leave-out report of one sequence; a ``kind="leaveout"`` record.

    Args:
        seq: the sequence (every frame goes in one frame-parallel batch).
        gt: ``[T, V, 3]`` target positions for the supervised loss terms (the bench
            passes the reference simulation); their values do not change which terms
            run or what they cost.
        seed: model initialisation seed; the rest as :func:`scaling.run_record`.
    """
    rec: Dict[str, Any] = {"kind": "leaveout", "method": METHOD, "case": seq.name,
                           "seed": seed}
    t0 = time.perf_counter()
    try:
        base = BenchChunks(seq, history=history, nystrom_dim=nystrom_dim,
                           num_landmarks=num_landmarks, gt=gt)[0]
        module = untrained_module(base, seed, **(module_kwargs or {}))
        module.loss_fn.set_enabled(PHASE_TERMS[3])
        rec.update(num_vertices=seq.garment.num_vertices, frames=int(base["gt"].shape[0]),
                   loss_terms_enabled=sorted(PHASE_TERMS[3]),
                   module_kwargs=dict(module_kwargs or {}))
        items = {name: scene_item(base, name) for name in SCENES}
        times = side_by_side({name: (lambda it=it: step(module, it)) for name, it in items.items()},
                             warmup, repeats)
        forced = times["full"]["median_ms"]  # every scene with its input put back is "full"
        scenes: Dict[str, Any] = {}
        for name, desc in SCENES.items():
            act = active(module, items[name])
            ran = {k for k, v in act["branches"].items() if v > 0} | set(act["loss_terms"])
            entry: Dict[str, Any] = {
                "description": desc, "branches": act["branches"],
                "active_branches": sorted(k for k, v in act["branches"].items() if v > 0),
                "loss_terms": act["loss_terms"], "should_skip": list(SHOULD_SKIP[name]),
                "check": {k: ("computed" if k in ran else "skipped") for k in SHOULD_SKIP[name]}}
            entry["all_left_out"] = all(v == "skipped" for v in entry["check"].values())
            lo = times[name]["median_ms"]
            entry["timing"] = ({"forward_loss_ms": lo} if name == "full" else
                               {"left_out_ms": lo, "forced_ms": forced, "saved_ms": forced - lo,
                                "saved_pct": 100.0 * (forced - lo) / forced})
            scenes[name] = entry
        rec["scenes"] = scenes
        rec["timing"] = {"repeats": repeats, "warmup": warmup,
                         "threads": torch.get_num_threads()}
        rec["not_left_out"] = sorted(f"{s}: {k}" for s, e in scenes.items()
                                     for k, v in e["check"].items() if v == "computed")
        rec.update(status="ok", message="ok")
    except Exception as err:
        rec.update(failure(err))
    rec["seconds"] = time.perf_counter() - t0
    return rec


def markdown(records: Sequence[Dict[str, Any]]) -> List[str]:
    """The report's "Leave-out" section (lines)."""
    recs, lines = section(records, "leaveout",
                          "Leave-out: what a scene without body / motion / UVs skips")
    if not recs:
        return lines
    lines += ["Measured with forward hooks on every GarTrans child module and the loss terms "
              "`GarTransLoss` returned (all terms of the last training phase enabled), on one "
              "frame-parallel step (encode_static + forward + loss, no backward).  "
              "*should skip*: what the scene does not need; *skipped* / **computed**: what the "
              "code did.  Time saved: the step on the scene against the step with the left-out "
              "input put back (the full scene), all scenes timed interleaved; untrained model.", ""]
    for r in recs:
        lines += [f"### {r['case']} ({r.get('frames', '?')} frames, "
                  f"{r.get('num_vertices', '?')} vertices)", ""]
        if r["status"] != "ok":
            lines += [f"failed: {str(r.get('message', ''))[:300]}", ""]
            continue
        rows = []
        for name, e in r["scenes"].items():
            check = ", ".join(f"{k}: {'skipped' if v == 'skipped' else '**computed**'}"
                              for k, v in e["check"].items()) or "—"
            t = e["timing"]
            if "saved_ms" in t:
                tt = [f"{t['left_out_ms']:.3g}", f"{t['forced_ms']:.3g}",
                      f"{t['saved_ms']:.3g} ({t['saved_pct']:.2g}%)"]
            else:
                tt = [f"{t['forward_loss_ms']:.3g}", "—", "—"]
            rows.append([name, e["description"], ", ".join(e["active_branches"]),
                         ", ".join(e["loss_terms"]), check] + tt)
        lines += table(["scene", "what is missing", "branches run", "loss terms computed",
                         "should skip → measured", "step (ms)", "with input put back (ms)",
                         "saved (ms)"], rows) + [""]
        if r["not_left_out"]:
            lines += ["Not left out by the current code: " + "; ".join(r["not_left_out"]) + ".",
                      ""]
        else:
            lines += ["Every part the scene does not need is skipped.", ""]
    return lines
