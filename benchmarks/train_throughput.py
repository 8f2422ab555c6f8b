"""Training throughput against batch size: vertex-frames per second of GarTrans and
DA-style training steps (``--data.batch_size`` chunks per step), side by side in one run.

For each garment size (``--sizes``: ``small`` ~400 and ``medium`` ~1.5K vertices) a
dataset is generated once into the benchmark cache: 4 garment kinds x 3 Anny bodies x 4
motions of 32 frames (192 chunks of 8 frames).  Its positions are the garment skinned to
the body plus a smooth wobble (:func:`garmentgnn.sim.stand_in.skinned_wobble`), not a
cloth simulation: what a step costs does not depend
on where the cloth is, and a Blender dataset of this size would take hours here.

Every configuration (method x threads x batch size) trains its packaged recipe
(``garmentgnn/recipes/gartrans.yaml``, ``baselines/da.yaml``, read by
:func:`~garmentgnn.training.load_recipe`) through the recipe's Lightning ``Trainer`` on
the data module's batches (loading included), ``--warmup`` steps untimed,
then enough steps for about ``--chunks`` chunks; vertex-frames/s = the vertices x frames
of the timed steps over their wall time.  Configurations alternate over ``--repeats``
rounds (a busy machine slows each alike); the median per configuration and its ratio to
batch 1 (same method, threads and size) are written to ``train_throughput.{json,md}``::

    python benchmarks/train_throughput.py --commit            # CPU, 1 and 2 threads
    python benchmarks/train_throughput.py --device cuda --threads 2 --commit
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import lightning as L
import torch

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, benchmark_cache,
                                  command_line, output_path)
from garmentgnn.data import Spec, generate, store
from garmentgnn.bench.methods import DATA
from garmentgnn.data import SequenceChunks
from garmentgnn.sim.stand_in import skinned_wobble
from garmentgnn.models.inputs import CHUNK, HISTORY
from garmentgnn.training import Recipe, load_recipe

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "train_throughput"
SIZES = {"small": 400, "medium": 1500}
METHODS = ("gartrans", "da")
#: each method's packaged recipe
RECIPES = {"gartrans": "gartrans", "da": "baselines/da"}


def dataset(size: str, cache: Path) -> Path:
    """The throughput dataset of garments of ``size`` (generated once, resumable)."""
    res = SIZES[size]
    out = cache / f"throughput-{size}"
    garments = [{"kind": k, "params": {}, "resolution": res}
                for k in ("skirt", "dress", "tshirt", "trousers")]
    bodies = [{"model": "anny", "shape": s} for s in ("thin", "regular", "fat")]
    motions = [{"name": n, "num_frames": 32, "speed": 1.0, "amplitude": 1.0}
               for n in ("walk", "run", "twirl", "kick")]
    spec = Spec(f"throughput-{size}", garments, bodies, motions, ["silk"], held_out={})
    generate(spec, out, workers=0, simulate_fn=skinned_wobble, progress=False)
    return out


def recipe_for(method: str, chunks: SequenceChunks, batch: int, workers: int = 0,
               compile_stack: Optional[str] = None) -> Recipe:
    """``method``'s recipe on ``chunks``' dataset (chunks of 8 frames, history 3, ``batch``
    chunks a step, ``workers`` loader processes, no validation), built at seed 0, its
    data module reading ``chunks`` (every sequence's static inputs built once:
    :func:`warm`); GarTrans with ``compile_stack`` (its dynamic stack compiled on a
    padded graph: ``GarTrans(compile_stack=...)``)."""
    recipe = load_recipe(RECIPES[method], args=[
        "--data.root", str(chunks.root), "--data.chunk", str(CHUNK), "--data.history", str(HISTORY),
        "--data.val_split", "null", "--data.seed", "0", "--data.batch_size", str(batch),
        "--data.num_workers", str(workers), "--seed_everything", "0"],
        set={"model.init_args.model.init_args.compile_stack": compile_stack}
        if method == "gartrans" and compile_stack else None)
    recipe.datamodule.train_set = chunks
    return recipe


class Clock(L.Callback):
    """Wall time and vertex-frames of every training step."""

    def __init__(self) -> None:
        self.t: List[float] = []
        self.work: List[int] = []
        self.loss: List[float] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        self.t.append(time.perf_counter())
        self.work.append(int(batch.gt.shape[0] * batch.gt.shape[1]))

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        self.t.append(time.perf_counter())
        self.loss.append(float(outputs["loss"]))


def measure(chunks: SequenceChunks, method: str, batch: int, threads: int,
            a: argparse.Namespace, precision: str = "32-true") -> Dict[str, Any]:
    torch.set_num_threads(threads)
    recipe = recipe_for(method, chunks, batch, a.workers, a.compile_stack)
    steps = a.warmup + max(3, -(-a.chunks // batch))
    clock = Clock()
    tr = recipe.trainer(max_steps=steps, max_epochs=-1, accelerator=a.device, devices=1,
                        logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0, callbacks=[clock], precision=precision,
                        default_root_dir=tempfile.mkdtemp(prefix="throughput_"))
    tr.fit(recipe.module, recipe.datamodule)
    w = a.warmup
    seconds = clock.t[-1] - clock.t[2 * w]
    work = sum(clock.work[w:])
    # the first step's loss: same weights and batch in every precision (seed 0)
    return {"vertex_frames_per_s": work / seconds, "steps": len(clock.work) - w,
            "seconds": seconds, "first_loss": clock.loss[0]}


def warm(root: Path) -> SequenceChunks:
    """The training chunks with every sequence's file and static inputs (Nyström
    features, rest state) loaded once: a cost of the first epoch, not of a step."""
    chunks = SequenceChunks(root, "train", chunk=DATA["chunk"], history=DATA["history"],
                            static_cache=64)
    for i in range(len(chunks.records)):
        chunks.static(i)
        chunks.sequence(i)
    return chunks


def main() -> None:
    # here, not at the top: step_profile's workers import this file beside older trees
    from garmentgnn.models.blocks import COMPILE_MODES  # noqa: PLC0415
    ap = ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--sizes", nargs="+", choices=sorted(SIZES), default=["small", "medium"],
                    help="garment sizes")
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                    help="methods")
    ap.add_argument("--batches", nargs="+", type=int, default=[1, 4, 16, 64],
                    help="chunks per training step")
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2], help="torch threads")
    ap.add_argument("--chunks", type=int, default=64,
                    help="chunks trained per timed configuration (at least 3 steps)")
    ap.add_argument("--warmup", type=int, default=2, help="untimed first steps")
    ap.add_argument("--repeats", type=int, default=2, help="rounds over the configurations")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="accelerator")
    ap.add_argument("--bf16", action="store_true",
                    help="also bf16 autocast rows (GPU), with the relative difference of "
                         "their first step's loss from float32's")
    ap.add_argument("--workers", type=int, default=0,
                    help="data loader worker processes (0: loading in the training process)")
    ap.add_argument("--compile-stack", choices=[m for m in COMPILE_MODES if m], default=None,
                    help="GarTrans's dynamic stack compiled in this torch.compile mode on its "
                         "graph padded to bucket sizes (reduce-overhead: CUDA graphs on a "
                         "GPU); default eager")
    add_output_args(ap, RESULTS, "the throughput tables")
    a = ap.parse_args()
    for flag in ("batches", "threads"):
        bad = [v for v in getattr(a, flag) if v < 1]
        if bad or len(set(getattr(a, flag))) != len(getattr(a, flag)):
            ap.error(f"--{flag}: expected distinct values >= 1, got {getattr(a, flag)}")
    if a.chunks < 1 or a.warmup < 1 or a.repeats < 1:
        ap.error("--chunks, --warmup and --repeats: expected values >= 1")
    if a.workers < 0:
        ap.error(f"--workers: expected 0 or more loader processes, got {a.workers}")
    out = output_path(a, RESULTS)
    cache = benchmark_cache()
    roots = {s: dataset(s, cache) for s in a.sizes}
    chunks = {s: warm(r) for s, r in roots.items()}
    for size in roots:  # compile the face search, fill the allocator: untimed
        for method in a.methods:
            measure(chunks[size], method, min(a.batches), max(a.threads), a)
    precisions = ["32-true"] + (["bf16-mixed"] if a.bf16 else [])
    runs: Dict[str, List[Dict[str, Any]]] = {}
    for _ in range(a.repeats):
        for size in roots:
            for method in a.methods:
                for threads in a.threads:
                    for prec in precisions:
                        for b in a.batches:
                            key = json.dumps([size, method, threads, prec, b])
                            runs.setdefault(key, []).append(
                                measure(chunks[size], method, b, threads, a, prec))
                            print(key, f"{runs[key][-1]['vertex_frames_per_s']:.0f}",
                                  flush=True)
    rows = []
    for key, rs in runs.items():
        size, method, threads, prec, b = json.loads(key)
        rows.append({"size": size, "method": method, "threads": threads, "precision": prec,
                     "batch": b, "vertex_frames_per_s": statistics.median(
                         r["vertex_frames_per_s"] for r in rs), "runs": rs})
    for r in rows:
        one = next(x for x in rows if x["batch"] == min(a.batches) and all(
            x[k] == r[k] for k in ("size", "method", "threads", "precision")))
        r["x_batch1"] = r["vertex_frames_per_s"] / one["vertex_frames_per_s"]
        fp32 = next(x for x in rows if x["precision"] == "32-true" and all(
            x[k] == r[k] for k in ("size", "method", "threads", "batch")))
        first = [statistics.median(x["first_loss"] for x in q["runs"]) for q in (r, fp32)]
        r["loss_rel_diff"] = abs(first[0] - first[1]) / max(abs(first[1]), 1e-12)
    info = {"command": command_line("benchmarks/train_throughput.py"), "device": a.device,
            "loader_workers": a.workers, "compile_stack": a.compile_stack,
            "device_name": torch.cuda.get_device_name() if a.device == "cuda"
            else platform.processor() or platform.machine(),
            "torch": torch.__version__, "datasets": {
                s: {"root": str(r).replace(str(Path.home()), "~"),
                    "content_sha256": store.read_manifest(r).get("content_sha256")}
                for s, r in roots.items()}, "rows": rows}
    out.mkdir(parents=True, exist_ok=True)
    stem = f"train_throughput_{a.device}"
    (out / f"{stem}.json").write_text(json.dumps(info, indent=1))
    lines = [f"# Training throughput ({a.device}: {info['device_name']})", "",
             f"`{info['command']}`", "",
             "Vertex-frames per second of training steps (median of the rounds); x batch 1:"
             " against the same method, threads and size at batch 1, measured in the same"
             f" run; loss vs fp32: the relative difference of the first step's loss from"
             f" float32's (same weights and batch).  Loader workers: {a.workers}.  GarTrans's"
             f" dynamic stack: {a.compile_stack or 'eager'}.", "",
             "| size | method | threads | precision | batch | vertex-frames/s | x batch 1 |"
             " loss vs fp32 |",
             "|---|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['size']} | {r['method']} | {r['threads']} | {r['precision']} | "
                     f"{r['batch']} | {r['vertex_frames_per_s']:.0f} | {r['x_batch1']:.2f} | "
                     f"{r['loss_rel_diff']:.1e} |")
    lines += ["", "Datasets (positions: skinned garment + wobble, see the script): " + ", ".join(
        f"{s} `{(d['content_sha256'] or '?')[:12]}`" for s, d in info["datasets"].items())]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
