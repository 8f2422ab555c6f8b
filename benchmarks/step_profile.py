"""Where a training step's time goes: GarTrans, DA-style and MGN-style steps (forward,
loss, backward, optimizer) on the CPU, per batch size and thread count, side by side in
one run, optionally against other source trees of garmentgnn (``--against DIR``, e.g. a
checkout of an earlier commit) timed alternately with this one.

Per configuration (tree x method x threads x batch size x precision) it reports:

* vertex-frames per second of the step (median over ``--repeats`` rounds of ``--steps``
  steps each, on batches loaded before the clock starts: loading is not timed);
* FLOPs per vertex-frame (the dense matmuls of forward and backward, recorded over one
  step by a ``TorchDispatchMode`` and each counted by
  :class:`torch.utils.flop_counter.FlopCounterMode`; the sparse kernels, an ``addmm`` of
  a sparse matrix among them, and element-wise work count zero) and the achieved GFLOP/s;
* the matmul rate of the step's own matmul shapes: every dense matmul the step ran,
  timed alone in the same process at the same thread count (FLOP-weighted), and the
  step's share of it (achieved / matmul rate);
* ATen calls per step (a ``TorchDispatchMode`` counting every operator the step
  dispatches, backward included);
* the time split by stage (wall time, exclusive of nested stages): static branch,
  dynamic graph and features, attention stack, post-steps, loss, backward, optimizer,
  other (the rest of the forward).

Dataset: the ``throughput-small`` stand-in of ``benchmarks/train_throughput.py`` (4
garment kinds at ~400 vertices x 3 Anny bodies x 4 motions of 32 frames; skinned garment
plus a wobble, not a simulation: what a step costs does not depend on where the cloth
is), generated once into the benchmark cache.  Each method is its packaged recipe
(``garmentgnn/recipes/``, read by :func:`~garmentgnn.training.load_recipe`): GarTrans
and DA-style train on chunks of 8 frames (history 3), MGN-style on its windows of 5
frames (stride 1, one trained step a window: a vertex-frame is one vertex of one trained
step)::

    python benchmarks/step_profile.py --commit
    python benchmarks/step_profile.py --against /path/to/old/checkout --methods gartrans da
    python benchmarks/step_profile.py --methods gartrans --precisions 32 bf16-mixed

``bf16-mixed`` runs the forward and loss under ``torch.autocast("cpu", torch.bfloat16)``,
as Lightning does.  Each tree runs in its own worker process (``PYTHONPATH=<tree>/src``);
the configurations and trees alternate within every round, so a busy machine slows them
alike.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any, Dict, List, Tuple

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from garmentgnn._argparse import (HelpFormatter, add_output_args, benchmark_cache,
                                  command_line, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.data import store
from garmentgnn.models.inputs import CHUNK, HISTORY
from garmentgnn.training import load_recipe
from scaling_parts.machine import cpu_name
from train_throughput import dataset, warm

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "step_profile"
METHODS = ("gartrans", "da", "mgn")
PRECISIONS = ("32", "bf16-mixed")  # Lightning's names
STAGES = ("static", "graph", "attention", "post", "loss", "other", "backward", "optimizer")
STAGE_NAMES = {"static": "static branch", "graph": "dynamic graph + features",
               "attention": "attention stack", "post": "post-steps", "loss": "loss",
               "other": "other forward", "backward": "backward", "optimizer": "optimizer"}


# ----------------------------------------------------------------------------- worker
class StageClock:
    """Exclusive wall time per stage label, from wrapped methods (nested calls are taken
    off their caller's stage)."""

    def __init__(self) -> None:
        self.seconds: Dict[str, float] = defaultdict(float)
        self.stack: List[str] = []

    def wrap(self, obj: Any, name: str, label: str) -> None:
        fn = getattr(obj, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            self.stack.append(label)
            try:
                return fn(*args, **kwargs)
            finally:
                self.stack.pop()
                dt = time.perf_counter() - t0
                self.seconds[label] += dt
                if self.stack:
                    self.seconds[self.stack[-1]] -= dt
        setattr(obj, name, timed)


def _stages(method: str, module: Any, clock: StageClock) -> None:
    """Wrap the methods that make each stage of ``method``'s step (DA-style's attention
    stack holds its encoder and decoder MLPs too)."""
    m = module.model
    if method == "gartrans":
        clock.wrap(m, "encode_static", "static")
        clock.wrap(m, "coarse", "graph")
        clock.wrap(m, "deform", "graph")
        clock.wrap(m.dynamic, "forward", "attention")
        clock.wrap(m, "post_steps", "post")
        clock.wrap(module, "compute_loss", "loss")
    elif method == "da":
        # (its layers are not wrapped: a compiled layer would compile the wrapper)
        clock.wrap(module, "compute_loss", "loss")
        clock.wrap(m, "forward", "attention")
        clock.wrap(m, "skin_batch", "graph")
        clock.wrap(m, "features", "graph")
    else:
        clock.wrap(module, "window_loss", "loss")
        clock.wrap(m, "scene_motion", "graph")
        clock.wrap(m, "body_edges", "graph")
        clock.wrap(m, "process", "attention")


class Worker:
    """One source tree's side of the run: modules, optimizers and batches per
    configuration, kept between rounds."""

    def __init__(self) -> None:
        self.root = dataset("small", benchmark_cache())
        self.chunks = warm(self.root)
        self.setups: Dict[Tuple[str, int], Dict[str, Any]] = {}
        self.threads = 0

    def set_threads(self, threads: int) -> None:
        """``torch.set_num_threads``; on a change, compiled code is dropped (inductor's CPU
        kernels are built for the thread count of their compile and dynamo does not
        guard on it: they would run on the old count)."""
        if threads != self.threads:
            torch.set_num_threads(threads)
            torch._dynamo.reset()
            self.threads = threads

    def setup(self, method: str, batch: int) -> Dict[str, Any]:
        key = (method, batch)
        if key in self.setups:
            return self.setups[key]
        data = ["--data.root", str(self.root), "--data.val_split", "null", "--data.seed", "0",
                "--data.batch_size", str(batch), "--data.cache_size", "64",
                "--seed_everything", "0"]
        if method == "mgn":  # every step trains (no statistics steps)
            recipe = load_recipe("mgn", args=data + [
                "--data.chunk", "5", "--data.history", "1", "--data.stride", "1",
                "--data.drop_last", "true", "--data.eval_chunk", "null"],
                set={"model.init_args.stats_steps": 0})
        else:
            recipe = load_recipe("gartrans" if method == "gartrans" else "baselines/da",
                                 args=data + ["--data.chunk", str(CHUNK),
                                              "--data.history", str(HISTORY)])
        dm, module = recipe.datamodule, recipe.module
        dm.setup("fit")
        if method != "mgn":
            dm.train_set = self.chunks  # static inputs built once (warm)
        module.log = lambda *a, **k: None  # no Trainer attached
        opt = module.configure_optimizers()
        opt = opt["optimizer"] if isinstance(opt, dict) else opt
        opt = opt[0] if isinstance(opt, (list, tuple)) else opt
        it = iter(dm.train_dataloader())
        batches = [next(it) for _ in range(3)]
        clock = StageClock()
        _stages(method, module, clock)
        s = self.setups[key] = {"module": module, "opt": opt, "batches": batches,
                                "clock": clock, "method": method, "i": 0}
        return s

    def vertex_frames(self, method: str, b: Any) -> int:
        if method == "mgn":
            return int(b.gt.shape[1])  # one trained step a window
        return int(b.gt.shape[0] * b.gt.shape[1])

    def step(self, s: Dict[str, Any], precision: str) -> Tuple[float, int]:
        """One training step on the next batch in ``precision``: (seconds, vertex-frames)."""
        b = s["batches"][s["i"] % len(s["batches"])]
        s["i"] += 1
        clock, module, opt = s["clock"], s["module"], s["opt"]
        t0 = time.perf_counter()
        with torch.autocast("cpu", torch.bfloat16, enabled=precision == "bf16-mixed"):
            out = module.training_step(b, 0)
        loss = out["loss"] if isinstance(out, dict) else out
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        opt.step()
        opt.zero_grad(set_to_none=True)
        t3 = time.perf_counter()
        clock.seconds["forward"] += t1 - t0
        clock.seconds["backward"] += t2 - t1
        clock.seconds["optimizer"] += t3 - t2
        return t3 - t0, self.vertex_frames(s["method"], b)

    def time(self, method: str, batch: int, threads: int, steps: int, warmup: int,
             precision: str = "32") -> Dict[str, Any]:
        self.set_threads(threads)
        s = self.setup(method, batch)
        for _ in range(warmup):
            self.step(s, precision)
        s["clock"].seconds.clear()
        seconds, work = 0.0, 0
        for _ in range(steps):
            dt, vf = self.step(s, precision)
            seconds, work = seconds + dt, work + vf
        sec = dict(s["clock"].seconds)
        named = sum(sec.get(k, 0.0) for k in ("static", "graph", "attention", "post", "loss"))
        sec["other"] = sec.pop("forward", 0.0) - named
        out = {"vertex_frames_per_s": work / seconds, "step_s": seconds / steps,
               "vertex_frames": work / steps,
               "stage_s": {k: sec.get(k, 0.0) / steps for k in STAGES}}
        if s.get(("mm", precision)):  # the step's matmuls timed alone, beside its steps
            mm_flops, mm_seconds = self.matmul_rate(s[("mm", precision)])
            out["mm_gflops_per_s"] = mm_flops / mm_seconds / 1e9
        return out

    def profile(self, method: str, batch: int, threads: int,
                precision: str = "32") -> Dict[str, Any]:
        """FLOPs, ATen calls and the matmul rate of one step's own matmul shapes."""
        self.set_threads(threads)
        s = self.setup(method, batch)
        self.step(s, precision)
        mm_ops = {torch.ops.aten.mm.default, torch.ops.aten.addmm.default,
                  torch.ops.aten.bmm.default, torch.ops.aten.baddbmm.default}

        class Count(TorchDispatchMode):
            def __init__(self) -> None:
                super().__init__()
                self.calls, self.mm = 0, []

            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                self.calls += 1
                tensors = [a for a in args if isinstance(a, torch.Tensor)]
                # dense matmuls only: an addmm of a sparse CSR matrix is an SpMM
                if func in mm_ops and all(t.layout == torch.strided for t in tensors):
                    self.mm.append((func, [(tuple(a.shape), str(a.dtype)[6:])
                                           if isinstance(a, torch.Tensor) else a for a in args]))
                return func(*args, **(kwargs or {}))

        count = Count()
        with count:
            _, vf = self.step(s, precision)
        s[("mm", precision)] = count.mm
        total, mm_seconds = self.matmul_rate(count.mm)
        return {"flops": total, "flops_per_vertex_frame": total / vf, "aten_calls": count.calls,
                "mm_calls": len(count.mm), "mm_gflops_per_s": total / mm_seconds / 1e9,
                "reference_mm_gflops_per_s": self.reference_rate()}

    def matmul_rate(self, calls: List[Tuple[Any, List[Any]]]) -> Tuple[float, float]:
        """(FLOPs, seconds) of the recorded matmuls, each shape timed alone (best of 3)."""
        keys = [repr(c) for c in calls]
        counts = Counter(keys)
        total_flops, total_s = 0.0, 0.0
        for key, (func, shapes) in dict(zip(keys, calls)).items():
            n = counts[key]
            args = [torch.randn(a[0], dtype=getattr(torch, a[1])) if isinstance(a, tuple)
                    else a for a in shapes]
            with FlopCounterMode(display=False) as fc:
                func(*args)
            total_flops += n * fc.get_total_flops()
            total_s += n * min(_seconds(func, args) for _ in range(3))
        return total_flops, total_s

    def reference_rate(self) -> float:
        """GFLOP/s of a [51680 x 128] @ [128 x 128] matmul (best of 5)."""
        a, b = torch.randn(51680, 128), torch.randn(128, 128)
        a @ b
        return 2 * 51680 * 128 * 128 / min(_seconds(torch.mm, (a, b)) for _ in range(5)) / 1e9

    def ready(self) -> Dict[str, Any]:
        """Answered once the dataset is there (workers start one after another: the
        dataset's generation lock admits one process at a time)."""
        return {}

    def serve(self) -> None:
        for line in sys.stdin:
            req = json.loads(line)
            try:
                fn = getattr(self, req.pop("cmd"))
                out: Dict[str, Any] = fn(**req)
            except Exception as err:  # noqa: BLE001 -- reported to the driver
                out = {"error": f"{type(err).__name__}: {err}"}
            print("RESULT " + json.dumps(out), flush=True)


def _seconds(func: Any, args: Any) -> float:
    t0 = time.perf_counter()
    func(*args)
    return time.perf_counter() - t0


# ----------------------------------------------------------------------------- driver
class Tree:
    """A worker process running ``tree``'s garmentgnn."""

    def __init__(self, tree: Path) -> None:
        self.tree = tree
        self.label = _revision(tree)
        env = dict(os.environ, PYTHONPATH=str(tree / "src"), PYTHONWARNINGS="ignore")
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker"], env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.ask(cmd="ready")

    def ask(self, **req: Any) -> Dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        for line in self.proc.stdout:
            if line.startswith("RESULT "):
                return json.loads(line[7:])
        raise RuntimeError(f"worker of {self.tree} exited")

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait()


def _revision(tree: Path) -> str:
    try:
        rev = subprocess.run(["git", "-C", str(tree), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(tree), "status", "--porcelain", "src"],
                               capture_output=True, text=True).stdout.strip()
        return rev + ("+" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return tree.name


def run(a: argparse.Namespace) -> Dict[str, Any]:
    trees = [Tree(HERE.parent)] + [Tree(Path(t).resolve()) for t in a.against]
    # thread count outermost: each change recompiles (see Worker.set_threads)
    configs = [dict(method=m, threads=th, batch=b, precision=pr) for th in a.threads
               for m in a.methods for b in a.batches for pr in a.precisions]
    rows: Dict[Tuple[Any, ...], Dict[str, Any]] = {}
    try:
        for c in configs:
            for t in trees:
                p = t.ask(cmd="profile", **c)
                rows[(t.label, *c.values())] = dict(tree=t.label, **c, profile=p, runs=[])
                print(t.label, *c.values(), p, flush=True)
        for _ in range(a.repeats):
            for c in configs:
                for t in trees:
                    row = rows[(t.label, *c.values())]
                    if "error" in row["profile"]:
                        continue
                    r = t.ask(cmd="time", steps=a.steps, warmup=a.warmup, **c)
                    row["runs"].append(r)
                    print(t.label, *c.values(), f"{r.get('vertex_frames_per_s', 0):.0f}",
                          flush=True)
    finally:
        for t in trees:
            t.close()
    out = []
    for row in rows.values():
        runs = [r for r in row["runs"] if "error" not in r]
        if not runs:
            continue
        vfs = statistics.median(r["vertex_frames_per_s"] for r in runs)
        p = row["profile"]
        row.update(vertex_frames_per_s=vfs,
                   stage_s={k: statistics.median(r["stage_s"][k] for r in runs)
                            for k in STAGES},
                   step_s=statistics.median(r["step_s"] for r in runs),
                   gflops_per_s=p["flops_per_vertex_frame"] * vfs / 1e9)
        # the matmul rate: median over the rounds (each timed beside that round's steps)
        rates = [r["mm_gflops_per_s"] for r in runs if "mm_gflops_per_s" in r]
        row["mm_gflops_per_s"] = statistics.median(rates) if rates else p["mm_gflops_per_s"]
        row["mm_share"] = row["gflops_per_s"] / row["mm_gflops_per_s"]
        out.append(row)
    base = trees[-1].label
    for row in out:
        ref = next((x for x in out if x["tree"] == base and all(
            x[k] == row[k] for k in ("method", "threads", "batch", "precision"))), None)
        row["x_against"] = row["vertex_frames_per_s"] / ref["vertex_frames_per_s"] \
            if ref else None
    return {"trees": [{"label": t.label, "path": str(t.tree)} for t in trees],
            "against": base, "rows": out}


def write(info: Dict[str, Any], out: Path) -> None:
    """``step_profile.{json,md,png}`` under ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "step_profile.json").write_text(json.dumps(info, indent=1))
    rows = sorted(info["rows"], key=lambda r: (r["method"], r["threads"], r["batch"],
                                               r["precision"] != "32",
                                               r["tree"] != info["trees"][0]["label"]))
    against = info["against"]
    lines = [f"# Training-step profile (CPU: {info['cpu']}, torch {info['torch']})", "",
             f"`{info['command']}`", "",
             f"Dataset `throughput-small`, content `{info['dataset']['content_sha256']}` "
             "(stand-in positions: skinned garment + wobble; see the script).  Steps on "
             "batches loaded beforehand (loading not timed); medians of the rounds.  "
             f"x {against}: vertex-frames/s against tree `{against}`, same configuration, "
             "same run.  MFLOP/vf: dense-matmul FLOPs of forward + backward per "
             "vertex-frame; mm rate: the step's own matmul shapes timed alone at the same "
             "thread count, in every round beside its steps (median); share: achieved GFLOP/s "
             "over that rate.", "",
             "| tree | method | threads | batch | precision | vertex-frames/s | x " + against
             + " | MFLOP/vf | GFLOP/s | mm rate | share | ATen calls | "
             + " | ".join(STAGE_NAMES[k] + " (ms)" for k in STAGES) + " |",
             "|---|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"
             + "---:|" * len(STAGES)]
    for r in rows:
        p = r["profile"]
        x = f"{r['x_against']:.2f}" if r["x_against"] is not None else "-"
        lines.append(
            f"| {r['tree']} | {r['method']} | {r['threads']} | {r['batch']} | {r['precision']} | "
            f"{r['vertex_frames_per_s']:,.0f} | {x} | {p['flops_per_vertex_frame'] / 1e6:.3f} | "
            f"{r['gflops_per_s']:.1f} | {r['mm_gflops_per_s']:.1f} | {r['mm_share']:.0%} | "
            f"{p['aten_calls']:,} | "
            + " | ".join(f"{1e3 * r['stage_s'][k]:.0f}" for k in STAGES) + " |")
    ref = {th: statistics.median(r["profile"]["reference_mm_gflops_per_s"] for r in rows
                                 if r["threads"] == th) for th in {r["threads"] for r in rows}}
    lines += ["", "Reference [51680 x 128] @ [128 x 128] matmul: " + ", ".join(
        f"{v:.1f} GFLOP/s on {th} thread(s)" for th, v in sorted(ref.items())) + "."]
    (out / "step_profile.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    plot(rows, out / "step_profile.png")


def plot(rows: List[Dict[str, Any]], path: Path) -> None:
    """Stacked bars: seconds per 10^5 vertex-frames by stage, per configuration."""
    plt = pyplot()
    threads = sorted({r["threads"] for r in rows})
    fig, axes = plt.subplots(1, len(threads), figsize=(6 + 0.5 * len(rows), 5), squeeze=False,
                             sharey=True)
    colors = plt.get_cmap("tab10").colors
    for ax, th in zip(axes[0], threads):
        sel = [r for r in rows if r["threads"] == th]
        labels = [f"{r['method']}\nb{r['batch']}\n{r['tree']}"
                  + ("" if r["precision"] == "32" else "\nbf16") for r in sel]
        bottom = [0.0] * len(sel)
        for i, k in enumerate(STAGES):
            h = [r["stage_s"][k] / r["vertex_frames"] * 1e5 if "vertex_frames" in r
                 else r["stage_s"][k] / r["step_s"] * 1e5 / r["vertex_frames_per_s"]
                 for r in sel]
            ax.bar(range(len(sel)), h, bottom=bottom, color=colors[i % 10],
                   label=STAGE_NAMES[k])
            bottom = [b + x for b, x in zip(bottom, h)]
        ax.set_xticks(range(len(sel)))
        ax.set_xticklabels(labels, fontsize=7)
        ax.set_title(f"{th} thread(s)")
        ax.set_ylabel("seconds per 10^5 vertex-frames")
    axes[0][-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # off the bars
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                    help="methods")
    ap.add_argument("--batches", nargs="+", type=int, default=[1, 4, 16],
                    help="chunks per training step")
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2], help="torch threads")
    ap.add_argument("--steps", type=int, default=3, help="timed steps a round")
    ap.add_argument("--warmup", type=int, default=1, help="untimed steps before each round")
    ap.add_argument("--repeats", type=int, default=3, help="rounds over the configurations")
    ap.add_argument("--precisions", nargs="+", choices=PRECISIONS, default=["32"],
                    help="Lightning precisions (bf16-mixed: forward and loss under autocast)")
    ap.add_argument("--against", nargs="*", default=[], metavar="DIR",
                    help="other garmentgnn source trees (a checkout's root) to time "
                         "alternately with this one; ratios are against the last")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    add_output_args(ap, RESULTS, "the profile tables")
    a = ap.parse_args()
    if a.worker:
        Worker().serve()
        return
    for flag in ("batches", "threads"):
        vals = getattr(a, flag)
        if any(v < 1 for v in vals) or len(set(vals)) != len(vals):
            ap.error(f"--{flag}: expected distinct values >= 1, got {vals}")
    if a.steps < 1 or a.warmup < 0 or a.repeats < 1:
        ap.error("--steps, --repeats: expected values >= 1; --warmup >= 0")
    for t in a.against:
        if not (Path(t) / "src" / "garmentgnn").is_dir():
            ap.error(f"--against: {t} holds no src/garmentgnn")
    out = output_path(a, RESULTS)
    root = dataset("small", benchmark_cache())
    info = run(a)
    info.update(command=command_line("benchmarks/step_profile.py"), torch=torch.__version__,
                cpu=cpu_name(), dataset={"root": str(root).replace(str(Path.home()), "~"),
                         "content_sha256": store.read_manifest(root).get("content_sha256")})
    write(info, out)


if __name__ == "__main__":
    main()
