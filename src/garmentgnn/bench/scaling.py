"""Scaling: GarTrans inference cost against garment vertex count, with and without the
cached static branch.

For each requested template resolution a garment is built on the capsule body
(:func:`garmentgnn.bench.sequences.make_sequence`; the real vertex count is recorded,
templates do not hit the request exactly), driven by a procedural motion, and an
**untrained** GarTrans (:func:`garmentgnn.bench.model_inputs.untrained_module`; the
weights' values do not change the amount of computation, so an untrained model costs
what a trained one does) predicts one frame (batch 1, pose history of the data module's
``history``) of it:

* **cached** (how GarTrans is meant to run): the static inputs and
  ``encode_static`` are computed once per garment and body; only ``forward`` is timed
  per frame;
* **uncached**: every frame recomputes the data module's static inputs
  (``SequenceChunks._build_static``: Nyström features, edge index, cloth rest state,
  skinning-weight transfer, body distances), ``encode_static`` and ``forward``.

Both, plus their parts (Nyström features alone, all static inputs, ``encode_static``
alone), are timed interleaved with :func:`garmentgnn.bench.timing.side_by_side`
(median ms of ``repeats`` calls, batch 1); peak memory of one call of each with
:func:`garmentgnn.bench.timing.peak_memory` (RSS growth, a lower bound).  Each record
also holds the largest difference between the cached and the uncached prediction
(the static branch is deterministic, so it is 0 up to float round-off).
"""
from __future__ import annotations

import copy
import time
from typing import Any, Dict, List, Optional, Sequence

import torch

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn._plotting import pyplot
from garmentgnn.bench.model_inputs import BenchChunks, untrained_module
from garmentgnn.bench.records import failure, section
from garmentgnn.bench.sequences import make_sequence
from garmentgnn.bench.tables import save_figure, table
from garmentgnn.bench.timing import peak_memory, side_by_side
from garmentgnn.geometry import geodesic_nystrom_features

#: the method name of scaling records
METHOD = "GarTrans (untrained)"
#: what the ``components`` of a record's timing are
COMPONENTS = ("nystrom", "static_inputs", "encode_static", "forward")


def scaling_items(template: Dict[str, Any], resolutions: Sequence[int]) -> List[Dict[str, Any]]:
    """One :func:`~garmentgnn.bench.sequences.case_item` per resolution: ``template`` with
    the garment's ``resolution`` replaced and ``name`` ``"<template name>@<resolution>"``."""
    if not isinstance(template, dict) or "garment" not in template:
        raise ValueError(f"`template`: expected a case_item dict, got {template!r}")
    out = []
    for r in resolutions:
        if not isinstance(r, int) or isinstance(r, bool) or r < 1:
            raise ValueError(f"`resolutions`: expected positive ints, got {r!r}")
        it = copy.deepcopy(template)
        it["garment"]["resolution"] = r
        it["name"] = f"{template['name']}@{r}"
        out.append(it)
    return out


def run_record(item: Dict[str, Any], seed: int = 0, warmup: int = 2, repeats: int = 5,
               history: int = HISTORY, nystrom_dim: int = NYSTROM_DIM,
               num_landmarks: int = NUM_LANDMARKS,
               module_kwargs: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """Time one garment size; a ``kind="scaling"`` record (``status="failed"`` with the
    message when building or running raised).

    Args:
        item: a :func:`~garmentgnn.bench.sequences.case_item` (e.g. from
            :func:`scaling_items`); its motion needs at least 2 frames.
        seed: motion seed and model initialisation seed.
        warmup, repeats: :func:`side_by_side` settings.
        history, nystrom_dim, num_landmarks: data-module settings
            (``garmentgnn/recipes/gartrans.yaml``).
        module_kwargs: further :class:`GarTransModule` arguments.
    """
    rec: Dict[str, Any] = {"kind": "scaling", "method": METHOD, "case": item.get("name"),
                           "seed": seed, "resolution": item["garment"]["resolution"]}
    t0 = time.perf_counter()
    try:
        seq = make_sequence(item, seed)
        T = seq.num_frames
        if T < 2:
            raise ValueError(f"`item`: the motion needs >= 2 frames, got {T}")
        ds = BenchChunks(seq, chunk=1, history=history, nystrom_dim=nystrom_dim,
                         num_landmarks=num_landmarks)
        frame = T // 2
        item_t = ds[frame]
        module = untrained_module(item_t, seed, **(module_kwargs or {}))
        rec.update(num_vertices=seq.garment.num_vertices,
                   num_faces=int(seq.garment.faces.shape[0]),
                   num_body_vertices=int(item_t["body_joint_dists"].shape[0]),
                   num_joints=int(item_t["rest_joints"].shape[0]), frame=frame,
                   history=history, nystrom_dim=nystrom_dim, num_landmarks=num_landmarks,
                   module_kwargs=dict(module_kwargs or {}))

        with torch.inference_mode():
            static = module.encode_static(item_t)

        def static_inputs() -> Dict[str, Any]:
            st, _ = ds._build_static(0)  # the data module's own static pre-processing
            fresh = copy.copy(item_t)
            fresh.update(st)
            return fresh

        def cached():
            return module(item_t, static)["final"]

        def uncached():
            return module(static_inputs())["final"]

        fns = {"nystrom": lambda: geodesic_nystrom_features(
                   item_t["rest_pos"].double(), item_t["faces"], k=nystrom_dim,
                   num_landmarks=num_landmarks),
               "static_inputs": static_inputs,
               "encode_static": lambda: module.encode_static(item_t),
               "forward": cached,
               "uncached": uncached}
        times = side_by_side(fns, warmup, repeats)
        with torch.inference_mode():
            mem_c = peak_memory(cached)
            mem_u = peak_memory(uncached)
        diff = float((mem_c["result"] - mem_u["result"]).abs().max())
        rec["timing"] = {
            "cached": {"latency_ms": times["forward"]["median_ms"],
                       "min_ms": times["forward"]["min_ms"],
                       "max_ms": times["forward"]["max_ms"], "peak_mem_mb": mem_c["peak_mb"]},
            "uncached": {"latency_ms": times["uncached"]["median_ms"],
                         "min_ms": times["uncached"]["min_ms"],
                         "max_ms": times["uncached"]["max_ms"], "peak_mem_mb": mem_u["peak_mb"]},
            "components": {f"{k}_ms": times[k]["median_ms"] for k in COMPONENTS},
            "repeats": repeats, "warmup": warmup, "threads": torch.get_num_threads(),
            "memory_method": mem_c["method"], "batch": 1}
        rec["timing"]["static_share"] = 1.0 - (rec["timing"]["cached"]["latency_ms"]
                                               / rec["timing"]["uncached"]["latency_ms"])
        rec["max_abs_diff_cached_vs_uncached_m"] = diff
        rec.update(status="ok", message="ok")
    except Exception as err:
        rec.update(failure(err))
    rec["seconds"] = time.perf_counter() - t0
    return rec


# --------------------------------------------------------------------------- report
def _ok(records: Sequence[Dict[str, Any]]) -> List[Dict[str, Any]]:
    rs = [r for r in records if r["kind"] == "scaling" and r["status"] == "ok"]
    return sorted(rs, key=lambda r: r["num_vertices"])


def markdown(records: Sequence[Dict[str, Any]], png: Optional[str] = None) -> List[str]:
    """The report's "Scaling" section (lines)."""
    recs, lines = section(records, "scaling", "Scaling: latency and memory against vertex count")
    if not recs:
        return lines
    lines += ["Untrained GarTrans (the weights' values do not change the cost), one frame at "
              "batch 1 on the capsule body.  *cached*: `encode_static` once, only `forward` "
              "per frame; *uncached*: the data module's static inputs (Nyström features, "
              "edge index, cloth rest state, skinning-weight transfer, body distances) + "
              "`encode_static` + `forward` every frame.  Median of the timed calls; memory: "
              "RSS growth during one call (a lower bound, `garmentgnn.bench.timing`).  "
              "Vertices: the count the template produced for the requested resolution.", ""]
    rows = []
    for r in sorted(recs, key=lambda r: r.get("num_vertices") or r["resolution"]):
        if r["status"] != "ok":
            rows.append([str(r["resolution"]), "—", "failed"] + ["—"] * 7 +
                        [str(r.get("message", ""))[:120].replace("|", "/")])
            continue
        t = r["timing"]
        c = t["components"]
        rows.append([str(r["resolution"]), str(r["num_vertices"]), "ok",
                     f"{t['cached']['latency_ms']:.3g}", f"{t['uncached']['latency_ms']:.3g}",
                     f"{c['nystrom_ms']:.3g}", f"{c['static_inputs_ms']:.3g}",
                     f"{c['encode_static_ms']:.3g}", f"{t['cached']['peak_mem_mb']:.3g}",
                     f"{t['uncached']['peak_mem_mb']:.3g}",
                     f"{r['max_abs_diff_cached_vs_uncached_m']:.2g}"])
    hdr = ["requested", "vertices", "status", "cached (ms)", "uncached (ms)", "Nyström (ms)",
           "all static inputs (ms)", "encode_static (ms)", "cached mem (MB)",
           "uncached mem (MB)", "max abs. cached - uncached (m)"]
    lines += table(hdr, rows) + [""]
    ok = _ok(recs)
    if ok:
        t0 = ok[0]["timing"]
        lines += [f"Threads: {t0['threads']}; {t0['repeats']} timed calls after {t0['warmup']} "
                  f"warm-up; memory: {t0['memory_method']}.", ""]
    if png:
        lines += [f"![Scaling]({png})", "",
                  "(log-log; a memory reading of 0 MB cannot be drawn on a log axis and is "
                  "left out of the plot)", ""]
    return lines


def plot(records: Sequence[Dict[str, Any]], path) -> Optional[Any]:
    """``scaling.png``: latency and peak memory against vertices (log-log), cached and
    uncached; ``None`` when there are fewer than one ok record."""
    ok = _ok(records)
    if not ok:
        return None
    plt = pyplot()

    V = [r["num_vertices"] for r in ok]
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 4.0))
    for ax, key, label in ((axes[0], "latency_ms", "latency per frame (ms)"),
                           (axes[1], "peak_mem_mb", "peak memory growth (MB)")):
        for mode, style in (("cached", "o-"), ("uncached", "s--")):
            pts = [(v, r["timing"][mode][key]) for v, r in zip(V, ok)
                   if r["timing"][mode][key] > 0]
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], style,
                        label=f"{mode} static branch")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("garment vertices (log)")
        ax.set_ylabel(label + " (log)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("GarTrans (untrained) inference, batch 1, against vertex count")
    fig.tight_layout()
    return save_figure(fig, path)
