"""Blender's cloth against the torch reference simulator, side by side in one run.

Cases (the same meshes, material and frame rate for both engines):

- ``hang``: a square silk sheet pinned along its top edge swings down under gravity
  (``--sizes`` vertices, turned 30 degrees about the pinned edge, unstrained; no
  collider, so it isolates the cloth solve; the torch simulator only up to
  ``--torch-max-vertices``);
- ``drape``: a 1 m sheet falls onto a sphere of radius 0.3 m (Blender: an icosphere
  collider mesh; torch: the analytic :class:`~garmentgnn.sim.Sphere`; both with the
  silk preset's friction; the torch simulator only up to ``--torch-max-vertices``);
- ``anny``: the first ``medium`` item's garment on its anny body and motion, shortened to
  ``--frames`` frames, with each engine's dataset settings.

Each row: seconds per simulated frame, vertex-substeps per second, penetration of the
collider at the end of every frame (exact signed distance: max and mean depth, share of
vertex-frames inside), edge strain against the rest mesh (mean and max over all frames),
kinetic energy at the last frame (per kg of cloth, so sizes compare), and for ``anny``
and ``drape`` the distance between the two engines' garments.  Sizes above
``--torch-max-vertices`` get a torch row saying ``skipped: cost``.  Writes
``engines.{json,md}`` in a cache folder (``--out`` elsewhere; ``--commit``: the committed
``docs/results/benchmarks/engines.*``).

    python benchmarks/engines.py                          # 300, 1K, 4K vertices, 30 frames
    python benchmarks/engines.py --sizes 300 --frames 10 --cases hang
    python benchmarks/engines.py --cases drape --keep   # rerun drape, keep the other rows
"""
from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, int_at_least, output_path)
from garmentgnn.data.store import read_json
from garmentgnn.data.presets import BLENDER_SETTINGS, build_inputs, preset
from garmentgnn.garments import Garment
from garmentgnn.geometry import grid_mesh, signed_distance, unique_edges
from garmentgnn.motion import Motion
from garmentgnn.physics import material
from garmentgnn.sim import SimSettings, Sphere, simulate
from garmentgnn.sim.blender import BlenderSettings, blender_config, run_worker, simulate_blender
from garmentgnn.sim.simulator import trajectories

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "benchmarks" / "engines"
TORCH = SimSettings(fps=30.0, substeps=4, friction=True)


def hanging_sheet(num_vertices: int, size: float = 0.5, tilt_deg: float = 30.0) -> Garment:
    """A square sheet pinned along its top edge, turned ``tilt_deg`` about that edge so it
    swings.  Turned rigidly: its edge lengths equal its pattern's, so both engines start
    unstrained (Blender takes its rest lengths from the mesh, the torch simulator from
    the pattern ``face_uv``)."""
    n = max(2, int(round(math.sqrt(num_vertices))))
    pos, faces = grid_mesh(n, n, (size, size))
    uv = pos[:, :2].clone()
    a = math.radians(tilt_deg)
    down = size - pos[:, 1]  # distance below the pinned edge
    pos = torch.stack([pos[:, 0], down * math.sin(a), 1.0 - down * math.cos(a)], 1)
    return Garment(pos, faces, uv, pinned=down < 1e-6)


def metrics(P: torch.Tensor, rest: torch.Tensor, faces: torch.Tensor, fps: float,
            body=None) -> dict:
    """``P [T, V, 3]``; ``body``: ``(frames [T, Vb, 3], faces)`` or ``None``."""
    P = P.double()
    e = unique_edges(faces).edges
    L0 = (rest[e[:, 0]] - rest[e[:, 1]]).double().norm(dim=-1)
    strain = ((P[:, e[:, 0]] - P[:, e[:, 1]]).norm(dim=-1) / L0 - 1).abs()
    v = (P[-1] - P[-2]) * fps
    out = {"strain_mean_pct": 100 * float(strain.mean()),
           "strain_max_pct": 100 * float(strain.max()),
           "kinetic_J_per_kg": 0.5 * float((v * v).sum(-1).mean()),
           "finite": bool(torch.isfinite(P).all())}
    if body is not None:
        frames, bf = body
        depth = torch.stack([(-signed_distance(P[t], frames[t].double(), bf).distance).clamp_min(0)
                             for t in range(P.shape[0])])
        inside = depth > 0
        out.update(pen_max_mm=1e3 * float(depth.max()),
                   pen_mean_mm=1e3 * float(depth[inside].mean()) if inside.any() else 0.0,
                   pen_share_pct=100 * float(inside.double().mean()))
    return out


def row(case, engine, V, substeps, seconds, frames, m, **extra):
    per = seconds / frames
    return dict(case=case, engine=engine, vertices=V, substeps=substeps, frames=frames,
                seconds_per_frame=per, vertex_substeps_per_s=V * substeps / per, **m, **extra)


def still(frames: int) -> Motion:
    return Motion(torch.zeros(frames, 1, 3), torch.zeros(frames, 3), ["root"], 30.0)


def skipped(case: str, V: int) -> dict:
    return dict(case=case, engine="torch", vertices=V, note="skipped: cost")


def engines_apart(out: list, P: dict) -> None:
    """Mean distance between the two engines' vertices, over all frames and at the last."""
    gap = (P["torch"].double() - P["blender"].double()).norm(dim=-1)
    for r in out:
        r["engines_apart_cm_mean"] = 100 * float(gap.mean())
        r["engines_apart_cm_last"] = 100 * float(gap[-1].mean())


def case_hang(V: int, frames: int, mat, torch_max: int) -> list:
    g = hanging_sheet(V)
    out = []
    if g.num_vertices > torch_max:
        out.append(skipped("hang", g.num_vertices))
    else:
        t0 = time.perf_counter()
        res = simulate(g, None, still(frames + 1), mat, TORCH)
        out.append(row("hang", "torch", g.num_vertices, TORCH.substeps,
                       time.perf_counter() - t0, frames,
                       metrics(res.positions, g.vertices, g.faces, 30.0), ok=res.ok))
    st = BlenderSettings(preroll_frames=1)
    t0 = time.perf_counter()
    res = simulate_blender(g, None, still(frames + 1), mat, st)
    out.append(row("hang", "blender", g.num_vertices, st.quality, time.perf_counter() - t0,
                   frames, metrics(res.positions, g.vertices, g.faces, 30.0), ok=res.ok))
    return out


def case_drape(V: int, frames: int, mat, torch_max: int) -> list:
    n = max(2, int(round(math.sqrt(V))))
    pos, faces = grid_mesh(n, n, (1.0, 1.0))
    pos = pos - torch.tensor([0.5, 0.5, -0.35])
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    bv = torch.tensor(sphere.vertices, dtype=torch.float32)
    bf = torch.tensor(sphere.faces, dtype=torch.long)
    st = BlenderSettings(preroll_frames=1)
    N = frames + 1
    t0 = time.perf_counter()
    res = run_worker({"garment_frames": pos.expand(N, -1, -1).numpy(), "faces": faces.numpy(),
                      "pinned": np.zeros(pos.shape[0], bool),
                      "body_frames": bv.expand(N, -1, -1).numpy(), "body_faces": bf.numpy()},
                     blender_config(mat, pos, faces, st))
    P = {"blender": torch.from_numpy(res["positions"][1:])}
    collider = (bv.expand(frames, -1, -1), bf)
    out = [row("drape", "blender", pos.shape[0], st.quality, time.perf_counter() - t0, frames,
               metrics(P["blender"], pos, faces, 30.0, collider), ok=True)]
    if pos.shape[0] > torch_max:
        return out + [skipped("drape", pos.shape[0])]
    g = Garment(pos, faces, pos[:, :2] + 0.5)
    t0 = time.perf_counter()
    res = simulate(g, None, still(N), mat, TORCH, colliders=Sphere((0.0, 0.0, 0.0), 0.3))
    P["torch"] = res.positions[1:]  # Blender's frame k is the state after k frames
    out.append(row("drape", "torch", pos.shape[0], TORCH.substeps, time.perf_counter() - t0,
                   frames, metrics(P["torch"], pos, faces, 30.0, collider), ok=res.ok))
    engines_apart(out, P)
    return out


def case_anny(frames: int) -> list:
    item = preset("medium", engine="blender").items()[0]
    g, body, motion, mat = build_inputs(item, num_frames=frames)
    out, P = [], {}
    specs = (("torch", dict(preroll_frames=6)), ("blender", dict(BLENDER_SETTINGS)))
    for engine, kw in specs:
        t0 = time.perf_counter()
        if engine == "torch":
            st = SimSettings(fps=30.0, substeps=TORCH.substeps, friction=True, **kw)
            res = simulate(g, body, motion, mat, st)
            sub = st.substeps
        else:
            st = BlenderSettings(**kw)
            res = simulate_blender(g, body, motion, mat, st)
            sub = st.quality
        seconds = time.perf_counter() - t0
        _, bframes = trajectories(g, body, motion, st.preroll_frames)
        P[engine] = res.positions
        m = metrics(res.positions, g.vertices, g.faces, 30.0,
                    (bframes[st.preroll_frames:], body.faces))
        out.append(row("anny", engine, g.num_vertices, sub, seconds, frames - 1, m, ok=res.ok,
                       item=item["id"]))
    engines_apart(out, P)
    return out


COLUMNS = [("case", "{}"), ("engine", "{}"), ("vertices", "{}"), ("seconds_per_frame", "{:.3f}"),
           ("vertex_substeps_per_s", "{:,.0f}"), ("pen_max_mm", "{:.1f}"),
           ("pen_mean_mm", "{:.2f}"),
           ("pen_share_pct", "{:.3f}"), ("strain_mean_pct", "{:.4f}"), ("strain_max_pct", "{:.3f}"),
           ("kinetic_J_per_kg", "{:.2e}"), ("engines_apart_cm_mean", "{:.2f}"),
           ("engines_apart_cm_last", "{:.2f}"), ("note", "{}")]


def table(rows) -> str:
    head = "| " + " | ".join(c for c, _ in COLUMNS) + " |"
    lines = [head, "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(f.format(r[c]) if c in r else "–" for c, f in COLUMNS)
                     + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--sizes", type=int_at_least(4), nargs="+", default=[300, 1000, 4000],
                    action=Accumulate,
                    help="sheet sizes (vertices) of the hang and drape cases")
    ap.add_argument("--frames", type=int_at_least(1), default=30,
                    help="simulated frames per case")
    ap.add_argument("--torch-max-vertices", type=int_at_least(0), default=1500,
                    help="skip the torch simulator above this size (5K vertices: ~2 min/frame)")
    ap.add_argument("--cases", nargs="+", default=["hang", "anny", "drape"], action=Accumulate,
                    choices=["hang", "drape", "anny"], help="scenes to simulate")
    ap.add_argument("--threads", type=int_at_least(1), default=2,
                    help="torch threads (Blender uses all cores)")
    add_output_args(ap, RESULTS, "writes OUT.json and OUT.md")
    ap.add_argument("--keep", action="store_true",
                    help="keep the rows of the cases not rerun from the existing JSON (marked "
                         "with the command that measured them)")
    args = ap.parse_args(argv)
    check_unique(ap, args.sizes, "--sizes")
    check_unique(ap, args.cases, "--cases")
    args.out = str(output_path(args, RESULTS))
    torch.set_num_threads(args.threads)
    mat = material("silk")
    rows = []
    old = Path(args.out + ".json")
    if args.keep and old.exists():
        try:
            doc = read_json(old, "delete it, or run without --keep")
        except ValueError as err:
            ap.error(f"--keep: {err}")
        if not isinstance(doc.get("rows"), list) or "command" not in doc:
            ap.error(f"--keep: {old}: not the results of benchmarks/engines.py; delete it, or "
                     f"run without --keep")
        for r in doc["rows"]:
            if r["case"] not in args.cases:
                r.setdefault("measured_by", doc["command"])
                rows.append(r)
    for case in args.cases:
        for V in (args.sizes if case != "anny" else [None]):
            new = {"hang": lambda: case_hang(V, args.frames, mat, args.torch_max_vertices),
                   "drape": lambda: case_drape(V, args.frames, mat, args.torch_max_vertices),
                   "anny": lambda: case_anny(args.frames)}[case]()
            for r in new:
                print(json.dumps({k: (round(v, 5) if isinstance(v, float) else v)
                                  for k, v in r.items()}), flush=True)
            rows.extend(new)
            write(args, argv, rows)
    md = write(args, argv, rows)
    print(md)
    return 0


def write(args, argv, rows) -> str:
    doc = {"command": " ".join(["python", "benchmarks/engines.py"] + (argv or sys.argv[1:])),
           "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                       "torch_threads": args.threads},
           "material": "silk", "fps": 30.0, "rows": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out + ".json").write_text(json.dumps(doc, indent=1))
    md = f"`{doc['command']}` on {doc['machine']['platform']}, {doc['machine']['cpus']} CPUs\n\n"
    kept = sorted({(r["case"], r["measured_by"]) for r in rows if "measured_by" in r})
    for case, cmd in kept:
        md += f"Rows of `{case}` kept from an earlier run: `{cmd}`.\n\n"
    md += table(rows) + "\n"
    Path(args.out + ".md").write_text(md)
    return md


if __name__ == "__main__":
    sys.exit(main())
