"""The nearest-body-face search with and without a ``NearestFaceCache``, side by side.

Scene: a t-shirt (``--sizes`` target vertex counts) skinned to the capsule body (2.5K
vertices, 4.9K faces) walking at 30 fps, plus a 3 mm wobble, float32; a chunk is
``--frames`` consecutive frames, ``[B, V, 3]`` garment with ``[B, Vb, 3]`` body, as one
training step sees it.  Every row times one :func:`garmentgnn.geometry.signed_distance`
call on the chunk (search plus the differentiable pass), in milliseconds per frame:

* ``candidates=8``: today's default search (faces around the 8 nearest body vertices;
  approximate), eager and ``compiled``;
* ``exact (candidates=None)``: the brute force over every face (timed once);
* ``cache: build``: a fresh cache's first call (searches every point);
* ``cache: moved 1 mm`` / ``moved 5 mm``: the same frames with the garment displaced
  (Gaussian, per coordinate) from where the cache was built: a later training step on
  the same chunk, or the loss after the collision projection; eager and ``compiled``;
* ``cache: next chunk``: built on frames ``0..B-1``, queried on ``B..2B-1`` (the body
  moved on);
* ``cache: from frame 0``: built on the chunk's first frame alone, queried on the chunk.

Each row also has the *refresh rate* (share of point-frames searched again over all
faces, :class:`~garmentgnn.geometry.FaceCacheStats`), and the share of faces / the
largest distance error against the brute force (the cache's must be 0, up to exact
ties).  Variants alternate over ``--repeats`` rounds (median), on 1 and 2 threads, and
every time is also given as a ratio to ``candidates=8`` eager on the same garment and
thread count.  Writes ``face_cache.{json,md}`` in a cache folder (``--out`` elsewhere;
``--commit``: the committed ``docs/results/face_cache/face_cache.*``)::

    python benchmarks/experiments/face_cache.py --commit
    python benchmarks/experiments/face_cache.py --sizes 400 --repeats 1      # quick look
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any, Callable, Dict, List

import torch

from garmentgnn import geometry as G
from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, command_line,
                                  output_path)
from garmentgnn.body.factory import build_body
from garmentgnn.garments import make_garment
from garmentgnn.motion import make_motion
from garmentgnn.sim.stand_in import wobbling_frames

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "docs" / "results" / "face_cache" / "face_cache"


def scene(size: int, frames: int):
    """Garment ``[T, V, 3]``, body ``[T, Vb, 3]`` (float32) and body faces over
    ``frames`` frames of a walk (:func:`garmentgnn.sim.stand_in.wobbling_frames`, in
    float64)."""
    body = build_body({"model": "capsule", "shape": "regular"})
    g = make_garment("tshirt", body, resolution=size)
    m = make_motion("walk", body.skeleton, num_frames=frames, fps=30.0, seed=0,
                    rest_joints=body.joints)
    P, X = wobbling_frames(g, body, m, torch.float64)
    return P.float(), X.float(), body.faces


def variants(P, X, F, B: int) -> Dict[str, Callable[[], Any]]:
    """Name -> a call returning ``(SignedDistance, query points, body, cache or None)``;
    each call builds what it needs apart from the timed part (``setup``)."""
    gen = torch.Generator().manual_seed(0)

    def moved(sigma: float) -> torch.Tensor:
        return P[:B] + sigma * torch.randn(P[:B].shape, generator=gen)

    def cached(build, query, compiled=False):
        def setup():
            c = G.NearestFaceCache(compiled=compiled)
            if build is not None:
                c.nearest(*build)
            q = query()
            return (lambda: G.signed_distance(q[0], q[1], F, cache=c)), q, c
        return setup

    chunk = (P[:B], X[:B], F)
    return {
        "candidates=8": lambda: ((lambda: G.signed_distance(P[:B], X[:B], F, candidates=8)),
                                 chunk[:2], None),
        "candidates=8, compiled": lambda: (
            (lambda: G.signed_distance(P[:B], X[:B], F, candidates=8, compiled=True)),
            chunk[:2], None),
        "cache: build": cached(None, lambda: chunk[:2]),
        "cache: moved 1 mm": cached(chunk, lambda: (moved(1e-3), X[:B])),
        "cache: moved 1 mm, compiled": cached(chunk, lambda: (moved(1e-3), X[:B]), True),
        "cache: moved 5 mm": cached(chunk, lambda: (moved(5e-3), X[:B])),
        "cache: next chunk": cached(chunk, lambda: (P[B:2 * B], X[B:2 * B])),
        "cache: from frame 0": cached((P[:1], X[:1], F), lambda: chunk[:2]),
    }


def run_size(size: int, a: argparse.Namespace) -> List[Dict[str, Any]]:
    B = a.frames
    P, X, F = scene(size, 2 * B)
    V = P.size(1)
    print(f"t-shirt {size}: V={V}, body {X.size(1)} vertices / {F.size(0)} faces", flush=True)
    vs = variants(P, X, F, B)
    oracle: Dict[int, Any] = {}  # id of the query tensor -> brute-force result
    times: Dict[tuple, List[float]] = {}
    checks: Dict[str, Dict[str, float]] = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for make in vs.values():  # warm-up (and compile) outside the timing
            make()[0]()
        for _ in range(a.repeats):
            for name, make in vs.items():
                fn, q, cache = make()
                t0 = time.perf_counter()
                out = fn()
                times.setdefault((threads, name), []).append((time.perf_counter() - t0) / B)
                if threads == 1 and name not in checks:
                    key = (q[0].data_ptr(), q[1].data_ptr())
                    if key not in oracle:
                        t1 = time.perf_counter()
                        oracle[key] = G.signed_distance(q[0], q[1], F, candidates=None)
                        if "exact" not in checks:
                            times[(1, "exact (candidates=None)")] = [
                                (time.perf_counter() - t1) / B]
                            checks["exact"] = {}
                    ref = oracle[key]
                    err = (out.distance - ref.distance).abs()
                    tie = (out.face != ref.face) & (err <= 1e-6)
                    checks[name] = {
                        "faces_differ": float(((out.face != ref.face) & ~tie).float().mean()),
                        "max_distance_error_m": float(err.max()),
                        "refresh_rate": (cache.stats.searched
                                         - (0 if name == "cache: build" else _built(name, V, B))
                                         ) / (B * V) if cache is not None else None,
                    }
    rows = []
    for threads in (1, 2):
        base = statistics.median(times[(threads, "candidates=8")])
        for name in ["exact (candidates=None)", *vs]:
            if (threads, name) not in times:
                continue
            ms = statistics.median(times[(threads, name)])
            c = checks.get("exact" if name.startswith("exact") else name, {})
            rows.append({"garment_vertices": V, "threads": threads, "variant": name,
                         "ms_per_frame": 1e3 * ms, "ratio_to_candidates8": ms / base,
                         "refresh_rate": c.get("refresh_rate"),
                         "faces_differ": c.get("faces_differ", 0.0),
                         "max_distance_error_m": c.get("max_distance_error_m", 0.0)})
    return rows


def _built(name: str, V: int, B: int) -> int:
    """Point-frames searched while building a variant's cache, before the timed call."""
    return V if name == "cache: from frame 0" else B * V


def markdown(rows: List[Dict[str, Any]], meta: Dict[str, Any]) -> str:
    out = ["# Nearest-body-face search: cached against per-call candidates", "",
           f"Command: `{meta['command']}`", "",
           f"{meta['machine']}; torch {meta['torch']}; t-shirt on the capsule body "
           f"(2.5K vertices, 4.9K faces), walk at 30 fps, chunks of {meta['frames']} frames, "
           f"float32; median of {meta['repeats']} alternating rounds.  Times are one "
           "`signed_distance` call per frame of the chunk; *ratio*: to `candidates=8` "
           "(eager) on the same garment and thread count.  *refresh*: share of "
           "point-frames searched again over all faces; *faces wrong*, *max error*: "
           "against the brute force (`candidates=None`), exact ties aside.", "",
           "| garment V | threads | variant | ms / frame | ratio | refresh | faces wrong "
           "| max error (m) |",
           "|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        rr = "" if r["refresh_rate"] is None else f"{r['refresh_rate']:.3f}"
        out.append(f"| {r['garment_vertices']} | {r['threads']} | {r['variant']} | "
                   f"{r['ms_per_frame']:.1f} | {r['ratio_to_candidates8']:.2f} | {rr} | "
                   f"{r['faces_differ']:.4f} | {r['max_distance_error_m']:.2g} |")
    return "\n".join(out) + "\n"


def main() -> None:
    ap = ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    d = " (default: %(default)s)"
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 1500],
                    help="t-shirt target vertex counts" + d)
    ap.add_argument("--frames", type=int, default=8, help="frames per chunk" + d)
    ap.add_argument("--repeats", type=int, default=5, help="alternating rounds" + d)
    add_output_args(ap, RESULTS, "writes OUT.json and OUT.md")
    a = ap.parse_args()
    if a.frames < 1 or a.repeats < 1:
        ap.error("--frames and --repeats must be positive")
    out = output_path(a, RESULTS)
    rows = [r for s in a.sizes for r in run_size(s, a)]
    meta = {"command": command_line("benchmarks/experiments/face_cache.py"), "frames": a.frames,
            "repeats": a.repeats, "torch": torch.__version__,
            "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}"}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    md = markdown(rows, meta)
    out.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
