"""Training speed of GarTrans, before and after, side by side in one run.

Each *variant* is a git revision of garmentgnn (``--before``, default the last commit
before the training speed-ups; ``HEAD``'s working tree for ``after``) with data-module
overrides.  Every variant runs in its own child process (``PYTHONPATH`` pointing at that
revision's ``src``), trains GarTrans with the revision's own recipe
(``garmentgnn/recipes/gartrans.yaml``, read by :func:`~garmentgnn.training.load_recipe`,
and the recipe's Lightning ``Trainer``; a revision from before the recipes: its
``configs/gartrans.yaml``'s model and data sections and Lightning's ``Trainer``) on the
same dataset, seed and chunk order, and reports:

* frames/s of the training steps after ``--warmup`` steps (compile and cache warm-up
  excluded; their time is reported apart), wall clock from Lightning's
  ``on_train_batch_start`` of the first timed step to ``on_train_batch_end`` of the last;
* the loss of every step: with the same seed, data and chunk order, an unchanged
  computation gives the same training trajectory, which is the "equal accuracy" check
  (largest relative difference of the per-step loss against the first variant).

Variants alternate (``--repeats`` rounds of all of them) so a busy machine slows each
alike; the median frames/s per variant and its ratio to the first are printed and
written to ``train_speed.{json,md}`` in a cache folder (``--out`` elsewhere; ``--commit``:
the committed ``docs/results/benchmarks/train_speed.*``)::

    python benchmarks/train_speed.py --data ~/.cache/garmentgnn/datasets/medium-blender
    python benchmarks/train_speed.py --data DATA --steps 20 --repeats 1   # quick look
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
#: the last commit before the training speed-ups
BEFORE = "098489e"
RESULTS = HERE.parent / "docs" / "results" / "benchmarks" / "train_speed"


def _before_recipes(args: argparse.Namespace) -> Tuple[Any, Any]:
    """(module, data module) of a revision from before the recipes, from its own
    ``configs/gartrans.yaml`` and loader (``garmentgnn.training.configs``), at seed 0."""
    import lightning as L  # noqa: PLC0415

    from garmentgnn.training import GarmentDataModule, GarTransModule  # noqa: PLC0415
    from garmentgnn.training.configs import load_config  # noqa: PLC0415

    cfg = load_config("gartrans")
    data = {k: v for k, v in cfg["data"].items() if k != "root"}
    data.update(json.loads(args.data_overrides))
    L.seed_everything(0, verbose=False)
    dm = GarmentDataModule(args.data, val_split=None, seed=0, **data)
    init = cfg["model"].get("init_args", cfg["model"])
    if isinstance(init.get("model"), dict):  # a revision whose module is handed its model
        from garmentgnn.training.configs import instantiate  # noqa: PLC0415
        return instantiate(cfg["model"], dm.dims), dm
    return GarTransModule(**dm.dims, **init), dm


def child(args: argparse.Namespace) -> None:
    """Runs inside a variant's process: train ``warmup + steps`` steps, print JSON."""
    # imported here: the child runs the variant's checkout (its PYTHONPATH), whose
    # garmentgnn may lack what the parent imports
    import lightning as L  # noqa: PLC0415
    import torch  # noqa: PLC0415

    torch.set_num_threads(args.threads)
    try:
        from garmentgnn.training import load_recipe  # noqa: PLC0415
    except ImportError:  # a revision from before the recipes
        load_recipe = None
    recipe = None
    if load_recipe is not None:
        recipe = load_recipe("gartrans", args=["--seed_everything", "0"],
                             data=dict(root=args.data, val_split=None, seed=0,
                                       **json.loads(args.data_overrides)))
        module, dm = recipe.module, recipe.datamodule
    else:
        module, dm = _before_recipes(args)

    class Clock(L.Callback):
        def __init__(self) -> None:
            self.t: List[float] = []
            self.frames: List[int] = []
            self.loss: List[float] = []

        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
            self.t.append(time.perf_counter())
            self.frames.append(int(batch.gt.shape[0]))

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
            self.t.append(time.perf_counter())
            self.loss.append(float(outputs["loss"]))

    clock = Clock()
    settings = dict(max_steps=args.warmup + args.steps, max_epochs=-1, accelerator="cpu",
                    devices=1, logger=False, enable_checkpointing=False,
                    enable_progress_bar=False, enable_model_summary=False,
                    limit_val_batches=0, num_sanity_val_steps=0, callbacks=[clock],
                    default_root_dir=tempfile.mkdtemp(prefix="train_speed_"))
    # the recipe's Trainer; a revision from before the recipes has none: Lightning's
    trainer = recipe.trainer(**settings) if recipe is not None else L.Trainer(**settings)
    trainer.fit(module, dm)
    w = args.warmup
    # step k spans t[2k] (start) .. t[2k+1] (end); the timed span includes data loading
    # between steps
    seconds = clock.t[-1] - clock.t[2 * w]
    frames = sum(clock.frames[w:])
    print(json.dumps({"frames_per_s": frames / seconds, "frames": frames, "seconds": seconds,
                      "warmup_seconds": clock.t[2 * w] - clock.t[0], "loss": clock.loss}))


def checkout(rev: str, dest: Path) -> Path:
    """``rev``'s tree exported to ``dest`` (``git archive``); returns its ``src``."""
    dest.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest / "src"


def run_variant(src: Path, data: str, v: Dict[str, Any], a: argparse.Namespace) -> Dict[str, Any]:
    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS=str(a.threads))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--data", data,
           "--steps", str(a.steps), "--warmup", str(a.warmup), "--threads", str(a.threads),
           "--data-overrides", json.dumps(v["data"])]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"variant {v['name']} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a generated dataset folder")
    # the child runs this file under another revision's src: no garmentgnn import here
    d = " (default: %(default)s)"
    ap.add_argument("--before", default=BEFORE,
                    help="git revision of the 'before' variant" + d)
    ap.add_argument("--steps", type=int, default=40, help="timed training steps" + d)
    ap.add_argument("--warmup", type=int, default=4, help="untimed first steps" + d)
    ap.add_argument("--repeats", type=int, default=2, help="rounds over the variants" + d)
    ap.add_argument("--threads", type=int, default=2, help="torch threads per variant" + d)
    out = ap.add_mutually_exclusive_group()
    out.add_argument("--out", default=None,
                     help="writes OUT.json and OUT.md; default "
                          "~/.cache/garmentgnn/benchmarks/train_speed (the committed copy "
                          "only with --commit)")
    out.add_argument("--commit", action="store_true",
                     help=f"write the committed results, {RESULTS}" + d)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--data-overrides", default="{}", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        return child(a)
    from garmentgnn._argparse import output_path  # noqa: PLC0415  (parent only: see child)
    a.out = str(output_path(a, RESULTS))
    if a.steps < 1 or a.warmup < 1 or a.repeats < 1 or a.threads < 1:
        ap.error("--steps, --warmup, --repeats and --threads must be positive")
    if not (Path(a.data).expanduser() / "manifest.json").is_file():
        ap.error(f"--data {a.data}: no manifest.json there; make the dataset with "
                 f"`garmentgnn generate --out {a.data}`")
    tmp = Path(tempfile.mkdtemp(prefix="train_speed_src_"))
    try:
        before_src = checkout(a.before, tmp / "before")
        variants = [
            {"name": f"before ({a.before})", "src": before_src, "data": {}},
            {"name": "after", "src": REPO / "src", "data": {}},
            {"name": "after, loader worker", "src": REPO / "src", "data": {"num_workers": 1}},
        ]
        runs: Dict[str, List[Dict[str, Any]]] = {v["name"]: [] for v in variants}
        for r in range(a.repeats):
            for v in variants:
                res = run_variant(v["src"], a.data, v, a)
                runs[v["name"]].append(res)
                print(f"round {r + 1}: {v['name']}: {res['frames_per_s']:.2f} frames/s "
                      f"(warm-up {res['warmup_seconds']:.1f} s)", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    base = variants[0]["name"]
    fps0 = statistics.median(x["frames_per_s"] for x in runs[base])
    loss0 = runs[base][0]["loss"]
    rows = []
    for v in variants:
        fps = statistics.median(x["frames_per_s"] for x in runs[v["name"]])
        loss = runs[v["name"]][0]["loss"]
        dev = max(abs(x - y) / max(abs(y), 1e-12) for x, y in zip(loss, loss0))
        rows.append({"variant": v["name"], "data_overrides": v["data"],
                     "frames_per_s": fps, "speedup": fps / fps0,
                     "all_frames_per_s": [x["frames_per_s"] for x in runs[v["name"]]],
                     "warmup_seconds": [x["warmup_seconds"] for x in runs[v["name"]]],
                     "max_rel_loss_diff": dev, "loss": loss})
    md = ["| variant | frames/s (median) | speed-up | runs | warm-up s | max rel. loss diff vs "
          "before |", "|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['variant']} | {r['frames_per_s']:.2f} | {r['speedup']:.2f}x | "
                  + ", ".join(f"{x:.2f}" for x in r["all_frames_per_s"]) + " | "
                  + ", ".join(f"{x:.1f}" for x in r["warmup_seconds"])
                  + f" | {r['max_rel_loss_diff']:.1e} |")
    meta = {"data": a.data, "steps": a.steps, "warmup": a.warmup, "repeats": a.repeats,
            "threads": a.threads, "before": a.before, "python": platform.python_version(),
            "machine": platform.machine(), "cpus": os.cpu_count(),
            "command": " ".join(["python", "benchmarks/train_speed.py"] + sys.argv[1:])}
    text = "\n".join(md)
    print(text)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    out.with_suffix(".md").write_text(f"`{meta['command']}`\n\n{text}\n")


if __name__ == "__main__":
    main()
