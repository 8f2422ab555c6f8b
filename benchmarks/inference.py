"""Inference speed: GarTrans against the Blender engine, LBS and the torch simulator,
side by side in one run, on the same garment, body and motion at ~1K, ~4K, ~10K vertices.

The scene of each size is the scaling bench's: a knee-length skirt at the requested
template resolution on the capsule body, walking (``garmentgnn.bench.sequences``);
the real vertex count is recorded.  Methods:

- **GarTrans** (untrained weights: the cost does not depend on their values):
  :meth:`GarTrans.predict_sequence` over the whole motion, static branch computed once
  (its cost, ``encode_static``, reported apart); *latency* = ms per frame at batch 1,
  *throughput* = frames/s at the best batch of ``--batches``; also the model without the
  blend-shape branch (``blend_shape=False``, the leave-out path).
- **LBS**: the rest garment skinned to every frame (``LBSBaseline``), all frames in one
  batch (throughput) and one frame per call (latency).
- **Blender** (``bpy`` worker, the dataset's cloth settings, pre-roll shortened):
  seconds per recorded frame as the worker times them (its start-up and ``import bpy``
  excluded); one frame follows the other, so latency = 1 / throughput.
- **torch simulator** (only up to ``--torch-max-vertices``, a few frames: it is slow).

``--device cuda`` runs the GarTrans rows on the GPU (each timed call ends with a device
synchronisation; their peak memory is the CUDA allocator's peak over what was allocated
before the call); LBS and the simulators stay on the CPU.

Peak memory: :func:`garmentgnn.bench.timing.peak_memory` (RSS growth of one call, a lower
bound) for the in-process methods; the Blender worker's peak RSS (whole process, from
``getrusage`` of the children).  ``--profile`` adds a by-module and by-operator
``torch.profiler`` breakdown of one GarTrans frame per size (static branch cached and
not); ``--experiments`` times bfloat16 and ``torch.compile`` at the smallest size.
Writes ``inference.{json,md,png}`` into a cache folder (``--out`` elsewhere; ``--commit``:
the committed ``docs/results/benchmarks/inference.*``).

    OMP_NUM_THREADS=2 python benchmarks/inference.py --profile --experiments
    # docs/inference.md's run (one core each; the machine was shared):
    OMP_NUM_THREADS=1 python benchmarks/inference.py --profile --threads 1 --frames 16 \
        --batches 1 4 16 --repeats 2 --torch-frames 2
    python benchmarks/inference.py --sizes 300 --frames 8 --no-blender   # quick look
"""
from __future__ import annotations

import contextlib
import copy
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List

import numpy as np
import torch
from torch.profiler import ProfilerActivity, profile, record_function

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, int_at_least, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.bench.model_inputs import BenchChunks, untrained_module
from garmentgnn.bench.sequences import case_item, make_sequence
from garmentgnn.bench.timing import device_peak_memory, measure, peak_memory, synchronised
from garmentgnn.data.presets import BLENDER_SETTINGS
from garmentgnn.models import gartrans as gartrans_mod
from garmentgnn.models.baselines import LBSBaseline
from garmentgnn.models.inputs import HISTORY
from garmentgnn.motion import Motion
from garmentgnn.sim import SimSettings, simulate
from garmentgnn.sim.blender import BlenderSettings, blender_available, blender_config, run_worker
from garmentgnn.sim.simulator import trajectories

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "benchmarks" / "inference"
#: the paper's GPU figures (10K vertices)
PAPER = {"latency_ms": 29.0, "throughput_fps": 280.0}


def scene(resolution: int, frames: int, seed: int = 0):
    item = case_item(f"inference-skirt-walk@{resolution}", "skirt", resolution, "walk", frames,
                     {"length": "knee"})
    seq = make_sequence(item, seed)
    it = BenchChunks(seq, chunk=frames, history=HISTORY)[0]
    return seq, it


def motion_tensors(seq):
    return seq.motion.rotations.float(), seq.motion.translation.float()


# --------------------------------------------------------------------------- GarTrans
def without_body(it):
    """``it`` without the posed body (the frame-parallel model without its collision
    projection, as these rows have always been timed)."""
    out = copy.copy(it)
    del out.body_pos
    return out


def gartrans_rows(seq, it, batches: List[int], repeats: int, device: str = "cpu",
                  **module_kw) -> Dict[str, Any]:
    module = untrained_module(it, 0, **module_kw).to(device)
    model = module.model
    it = without_body(it)
    if device != "cpu":
        it = it.to(device)
    T = it.num_frames
    with torch.inference_mode():
        static = module.encode_static(it)

    def run(b):
        return synchronised(
            lambda: model.predict_sequence(it, batch_size=b, static=static)["final"], device)

    enc = measure(synchronised(lambda: module.encode_static(it), device), 1, repeats)
    sweep = []
    for b in sorted(set(min(b, T) for b in batches)):
        m = measure(run(b), 1, repeats)
        sweep.append({"batch": b, "ms_per_frame": m["median_ms"] / T,
                      "fps": T * 1e3 / m["median_ms"]})
    best = max(sweep, key=lambda r: r["fps"])
    with torch.inference_mode():
        mem_best = device_peak_memory(run(best["batch"]), device)
        mem_one = device_peak_memory(run(1), device)
        mem_default = device_peak_memory(run(None), device)
    lat = sweep[0]["ms_per_frame"]
    return {"latency_ms": lat, "throughput_fps": best["fps"], "best_batch": best["batch"],
            "encode_static_ms": enc["median_ms"], "uncached_latency_ms": lat + enc["median_ms"],
            "peak_mb": mem_best["peak_mb"], "peak_mb_batch1": mem_one["peak_mb"],
            "peak_mb_default_chunk": mem_default["peak_mb"],
            "default_chunk": max(1, model.CHUNK_VERTICES // it["rest_pos"].shape[0]),
            "sweep": sweep, "frames": T, "device": device}


# --------------------------------------------------------------------------- others
def lbs_row(seq, repeats: int) -> Dict[str, Any]:
    lbs, sc = LBSBaseline(), seq.scene
    rot, tr = seq.motion.rotations, seq.motion.translation
    T = rot.shape[0]
    whole = measure(lambda: lbs(sc, rot, tr), 1, repeats)
    one = measure(lambda: lbs(sc, rot[:1], tr[:1]), 2, max(repeats, 5))
    mem = peak_memory(lambda: lbs(sc, rot, tr))
    return {"latency_ms": one["median_ms"], "throughput_fps": T * 1e3 / whole["median_ms"],
            "best_batch": T, "peak_mb": mem["peak_mb"]}


def blender_row(seq, frames: int, preroll: int, cores: int) -> Dict[str, Any]:
    st = BlenderSettings(**dict(BLENDER_SETTINGS, preroll_frames=preroll))
    motion = seq.motion
    g, body = seq.garment, seq.body
    skinned, bframes = trajectories(g, body, motion, st.preroll_frames)
    n = st.preroll_frames + min(frames, motion.num_frames)
    arrays = {"garment_frames": skinned[:n].float().numpy(), "faces": g.faces.long().numpy(),
              "pinned": (np.zeros(g.num_vertices, bool) if g.pinned is None
                         else g.pinned.bool().numpy()),
              "body_frames": bframes[:n].float().numpy(), "body_faces": body.faces.long().numpy()}
    t0 = time.perf_counter()
    res = run_worker(arrays, blender_config(seq.material, g.vertices, g.faces, st), threads=cores)
    wall = time.perf_counter() - t0
    sec = np.asarray(res["seconds_per_frame"])[st.preroll_frames:]
    per = float(np.mean(sec))
    return {"latency_ms": 1e3 * per, "throughput_fps": 1.0 / per, "best_batch": 1,
            "median_ms": 1e3 * float(np.median(sec)), "frames": int(sec.size),
            "preroll_frames": st.preroll_frames, "wall_s": wall, "quality": st.quality,
            "cores": cores,
            "peak_mb_process": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}


def torch_sim_row(seq, frames: int) -> Dict[str, Any]:
    m = seq.motion
    short = Motion(m.rotations[:frames], m.translation[:frames], m.joint_names, m.fps)
    st = SimSettings(fps=m.fps, substeps=4, preroll_frames=1)
    t0 = time.perf_counter()
    mem = peak_memory(lambda: simulate(seq.garment, seq.body, short, seq.material, st))
    per = (time.perf_counter() - t0) / (frames + st.preroll_frames)
    return {"latency_ms": 1e3 * per, "throughput_fps": 1.0 / per, "best_batch": 1,
            "frames": frames + st.preroll_frames, "peak_mb": mem["peak_mb"]}


# --------------------------------------------------------------------------- profile
STAGES = ("vertex_normals", "edge_features", "forward_kinematics", "project_edge_lengths",
          "push_outside")
MODULES = ("rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru", "gru_out", "blend",
           "dynamic")


@contextlib.contextmanager
def labelled(model):
    """Name the model's submodules and the geometry steps of ``gartrans`` in the profile."""
    handles, saved = [], {}
    for name in MODULES:
        mod = getattr(model, name, None)
        if mod is None:
            continue
        ctx: Dict[str, Any] = {}
        handles.append(mod.register_forward_pre_hook(
            lambda m, a, n=name, c=ctx: c.__setitem__("r", record_function(f"## {n}").__enter__())))
        handles.append(mod.register_forward_hook(
            lambda m, a, o, c=ctx: c["r"].__exit__(None, None, None)))

    def wrap(fn: Callable, name: str) -> Callable:
        def inner(*a, **k):
            with record_function(f"## {name}"):
                return fn(*a, **k)
        return inner

    for name in STAGES:
        saved[name] = getattr(gartrans_mod, name)
        setattr(gartrans_mod, name, wrap(saved[name], name))
    try:
        yield
    finally:
        for h in handles:
            h.remove()
        for name, fn in saved.items():
            setattr(gartrans_mod, name, fn)


def profile_rows(it, seq) -> Dict[str, Any]:
    module = untrained_module(it, 0)
    model = module.model
    it = without_body(it)
    out: Dict[str, Any] = {}
    with torch.inference_mode():
        static = module.encode_static(it)
        one = it.select(torch.tensor([it.num_frames // 2]))  # one frame, mid-motion
        fns = {"cached": lambda: model(one, static), "uncached": lambda: model(one)}
        for mode, fn in fns.items():
            for _ in range(2):
                fn()
            with labelled(model), profile(activities=[ProfilerActivity.CPU]) as p:
                for _ in range(3):
                    fn()
            ev = p.key_averages()
            total = sum(e.self_cpu_time_total for e in ev) / 3e3
            mods = {e.key[3:]: e.cpu_time_total / 3e3 for e in ev if e.key.startswith("## ")}
            ops = sorted((e for e in ev if not e.key.startswith("## ")),
                         key=lambda e: -e.self_cpu_time_total)[:12]
            out[mode] = {"total_ms": total, "modules_ms": mods,
                         "ops": [{"op": e.key, "self_ms": e.self_cpu_time_total / 3e3,
                                  "calls": e.count / 3} for e in ops]}
    return out


# --------------------------------------------------------------------------- experiments
def experiments(seq, it, repeats: int) -> Dict[str, Any]:
    """bfloat16 and ``torch.compile`` against float32, one batch of frames."""
    res: Dict[str, Any] = {}
    # lbs_start=False: every branch reaches the output (zero gates would hide the
    # blend shape's and the dynamic branch's rounding error)
    module = untrained_module(it, 0, lbs_start=False)
    model = module.model
    it = without_body(it)
    T = it.num_frames
    with torch.inference_mode():
        static = module.encode_static(it)
        base = lambda: model(it, static)["final"]  # noqa: E731
        ref = base()
        res["float32_ms_per_frame"] = measure(base, 1, repeats)["median_ms"] / T
    # bfloat16: weights and inputs cast (the layers take their message route in half types)
    try:
        m16 = copy.deepcopy(model).to(torch.bfloat16)
        cast = lambda x: x.to(torch.bfloat16) if x.is_floating_point() else x  # noqa: E731
        st16 = type(static)(**{k: (None if v is None else cast(v))
                               for k, v in vars(static).items()})
        it16 = copy.copy(it)
        for k in ("rest_pos", "rotations", "translation"):
            it16[k] = cast(it[k])
        with torch.inference_mode():
            f16 = lambda: m16(it16, st16)["final"]  # noqa: E731
            err = (f16().float() - ref).abs()
            res["bfloat16_ms_per_frame"] = measure(f16, 1, repeats)["median_ms"] / T
        res["bfloat16_max_err_mm"] = 1e3 * float(err.max())
        res["bfloat16_mean_err_mm"] = 1e3 * float(err.mean())
    except Exception as e:  # report, do not hide
        res["bfloat16_error"] = f"{type(e).__name__}: {e}"[:300]
    try:
        comp = torch.compile(model.dynamic, dynamic=False)
        x_dyn = {}

        def capture(mod, a, o):
            x_dyn["a"] = a

        h = model.dynamic.register_forward_hook(capture)
        with torch.inference_mode():
            base()
        h.remove()
        a = x_dyn["a"]
        with torch.inference_mode():
            eager_out = model.dynamic(*a)
            t0 = time.perf_counter()
            comp_out = comp(*a)
            res["compile_seconds"] = time.perf_counter() - t0
            res["compile_dynamic_max_diff"] = float((comp_out - eager_out).abs().max())
            res["eager_dynamic_ms_per_frame"] = measure(lambda: model.dynamic(*a), 1,
                                                        repeats)["median_ms"] / T
            res["compiled_dynamic_ms_per_frame"] = measure(lambda: comp(*a), 1,
                                                           repeats)["median_ms"] / T
    except Exception as e:
        res["compile_error"] = f"{type(e).__name__}: {e}"[:300]
    return res


# --------------------------------------------------------------------------- report
def table(rows: List[Dict[str, Any]]) -> str:
    head = ["vertices", "method", "latency, batch 1 (ms/frame)", "throughput (frames/s)",
            "best batch", "peak memory (MB)", "throughput / Blender"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        mem = r.get("peak_mb", r.get("peak_mb_process"))
        memtxt = "–" if mem is None else (f"{mem:.0f}" + (" (process)" if "peak_mb_process" in r
                                                         else ""))
        ratio = r.get("vs_blender")
        lines.append(f"| {r['vertices']} | {r['method']} | {r['latency_ms']:.1f} | "
                     f"{r['throughput_fps']:.1f} | {r['best_batch']} | {memtxt} | "
                     f"{'–' if ratio is None else f'{ratio:.1f}×'} |")
    return "\n".join(lines)


def plot(rows: List[Dict[str, Any]], path: Path, device: str = "cpu") -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method, style in (("GarTrans", "o-"), ("GarTrans, no blend shape", "o--"),
                          ("Blender", "s-"), ("LBS", "^-"), ("torch simulator", "x")):
        pts = sorted((r["vertices"], r) for r in rows if r["method"] == method)
        if not pts:
            continue
        V = [p[0] for p in pts]
        axes[0].plot(V, [p[1]["latency_ms"] for p in pts], style, label=method)
        axes[1].plot(V, [p[1]["throughput_fps"] for p in pts], style, label=method)
    for ax, lab in ((axes[0], "latency at batch 1 (ms/frame)"),
                    (axes[1], "throughput at best batch (frames/s)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("garment vertices")
        ax.set_ylabel(lab)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    where = "CPU" if device == "cpu" else "GPU (GarTrans; the others on the CPU)"
    fig.suptitle(f"Inference on {where} ({torch.get_num_threads()} torch thread(s)), skirt on a "
                 "walking capsule body")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--sizes", type=int_at_least(4), nargs="+", default=[1000, 4000, 10000],
                    action=Accumulate,
                    help="template resolutions (requested vertex counts)")
    ap.add_argument("--frames", type=int_at_least(2), default=32,
                    help="motion frames (GarTrans, LBS)")
    ap.add_argument("--batches", type=int_at_least(1), nargs="+", default=[1, 4, 8, 16, 32],
                    action=Accumulate,
                    help="GarTrans batch sizes (frames per call) for the throughput")
    ap.add_argument("--repeats", type=int_at_least(1), default=3,
                    help="timed repeats (the best is kept)")
    ap.add_argument("--blender-frames", type=int_at_least(2), default=8,
                    help="frames Blender records")
    ap.add_argument("--blender-preroll", type=int_at_least(0), default=3,
                    help="Blender's pre-roll frames (shortened from the dataset's)")
    ap.add_argument("--no-blender", action="store_true", help="leave out the Blender engine")
    ap.add_argument("--blender-cores", type=int_at_least(1), default=None,
                    help="CPU cores of the Blender worker (its affinity); default: --threads")
    ap.add_argument("--torch-frames", type=int_at_least(2), default=3,
                    help="frames of the torch simulator")
    ap.add_argument("--torch-max-vertices", type=int_at_least(0), default=1500,
                    help="time the torch simulator only up to this many vertices")
    ap.add_argument("--profile", action="store_true",
                    help="add a torch.profiler breakdown of one GarTrans frame per size")
    ap.add_argument("--experiments", action="store_true",
                    help="time bfloat16 and torch.compile at the smallest size")
    ap.add_argument("--threads", type=int_at_least(1), default=2, help="torch threads")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="where the GarTrans rows run (LBS and the simulators: the CPU)")
    add_output_args(ap, RESULTS, "writes OUT.json, OUT.md and OUT.png")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: torch sees no CUDA device here; use --device cpu")
    check_unique(ap, args.sizes, "--sizes")
    check_unique(ap, args.batches, "--batches")
    args.out = str(output_path(args, RESULTS))
    torch.set_num_threads(args.threads)
    args.blender_cores = args.blender_cores or args.threads
    have_blender = not args.no_blender and blender_available()
    doc: Dict[str, Any] = {
        "command": " ".join(["python", "benchmarks/inference.py"] + (argv or sys.argv[1:])),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "torch_threads": torch.get_num_threads(), "blender_cores": args.blender_cores,
                    "load_average_start": os.getloadavg(), "gpu": torch.cuda.is_available(),
                    "device": args.device, "device_name": torch.cuda.get_device_name()
                    if args.device == "cuda" else platform.processor() or platform.machine()},
        "history": HISTORY, "paper_gpu": PAPER, "rows": [], "profile": {}}
    for res in args.sizes:
        seq, it = scene(res, args.frames)
        V = seq.garment.num_vertices
        print(f"--- {V} vertices (requested {res})", flush=True)
        new = []
        g = gartrans_rows(seq, it, args.batches, args.repeats, args.device)
        new.append(dict(method="GarTrans", **g))
        g2 = gartrans_rows(seq, it, args.batches, args.repeats, args.device, blend_shape=False)
        new.append(dict(method="GarTrans, no blend shape", **g2))
        new.append(dict(method="LBS", **lbs_row(seq, args.repeats)))
        if V <= args.torch_max_vertices:
            new.append(dict(method="torch simulator", **torch_sim_row(seq, args.torch_frames)))
        if have_blender:
            try:
                new.append(dict(method="Blender", **blender_row(
                    seq, args.blender_frames, args.blender_preroll, args.blender_cores)))
            except RuntimeError as e:
                print(f"Blender failed: {e}", flush=True)
        bl = next((r for r in new if r["method"] == "Blender"), None)
        for r in new:
            r["vertices"] = V
            r["requested"] = res
            if bl is not None:
                r["vs_blender"] = r["throughput_fps"] / bl["throughput_fps"]
            print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v)
                              for k, v in r.items() if k != "sweep"}), flush=True)
        doc["rows"].extend(new)
        if args.profile:
            doc["profile"][str(V)] = profile_rows(it, seq)
        write(args, doc)
    if args.experiments:
        seq, it = scene(args.sizes[0], 16)
        doc["experiments"] = dict(vertices=seq.garment.num_vertices,
                                  **experiments(seq, it, args.repeats))
        print(json.dumps(doc["experiments"]), flush=True)
    doc["machine"]["load_average_end"] = os.getloadavg()
    md = write(args, doc)
    print(md)
    return 0


def markdown(doc: Dict[str, Any]) -> str:
    m = doc["machine"]
    lines = [f"`{doc['command']}` on {m['platform']}, {m['cpus']} CPUs, {m['torch_threads']} "
             f"torch threads, Blender worker on {m.get('blender_cores', '?')} core(s), GPU: "
             f"{'yes' if m['gpu'] else 'none'}" +
             (f" (GarTrans rows on {m.get('device_name')}, the others on the CPU)"
              if m.get("device", "cpu") != "cpu" else "") + "; load average at start "
             f"{m['load_average_start'][0]:.2f}" +
             (f", at end {m['load_average_end'][0]:.2f}" if "load_average_end" in m else ""),
             "", table(doc["rows"]), ""]
    lines += ["GarTrans details (ms): `encode_static` once per garment and body; uncached = "
              "batch-1 latency + `encode_static`; peak memory at batch 1 and at the default "
              "chunk (`CHUNK_VERTICES // V` frames).", "",
              "| vertices | model | encode_static (ms) | uncached latency (ms/frame) | "
              "peak MB batch 1 | peak MB default chunk (frames) | sweep: batch → frames/s |",
              "|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        if r["method"].startswith("GarTrans"):
            sw = ", ".join(f"{s['batch']}→{s['fps']:.0f}" for s in r["sweep"])
            lines.append(f"| {r['vertices']} | {r['method']} | {r['encode_static_ms']:.1f} | "
                         f"{r['uncached_latency_ms']:.1f} | {r['peak_mb_batch1']:.0f} | "
                         f"{r['peak_mb_default_chunk']:.0f} ({r['default_chunk']}) | {sw} |")
    for V, prof in doc.get("profile", {}).items():
        for mode, p in prof.items():
            lines += ["", f"Profile, {V} vertices, one frame, static branch {mode}: "
                          f"{p['total_ms']:.1f} ms (profiled)", "",
                      "| module / step | ms (incl. children) |", "|---|---|"]
            lines += [f"| {k} | {v:.2f} |" for k, v in sorted(p["modules_ms"].items(),
                                                             key=lambda kv: -kv[1])]
            lines += ["", "| operator | self ms | calls |", "|---|---|---|"]
            lines += [f"| {o['op']} | {o['self_ms']:.2f} | {o['calls']:.0f} |" for o in p["ops"]]
    if "experiments" in doc:
        lines += ["", "Experiments (" + str(doc["experiments"]["vertices"]) + " vertices, one "
                  "batch of 16 frames): " + json.dumps(
                      {k: (round(v, 4) if isinstance(v, float) else v)
                       for k, v in doc["experiments"].items()})]
    return "\n".join(lines) + "\n"


def write(args, doc) -> str:
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1))
    md = markdown(doc)
    out.with_suffix(".md").write_text(md)
    if doc["rows"]:
        plot(doc["rows"], out.with_suffix(".png"), doc["machine"].get("device", "cpu"))
    return md


if __name__ == "__main__":
    sys.exit(main())
