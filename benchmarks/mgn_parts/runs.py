"""The runs of ``benchmarks/mgn_learn.py``: the sweeps' table (``sweep``), a run branched
from one of its checkpoints with pushforward (``branch``) and the cost of a training step
against size, batch and threads (``steptime``); the data, the modules and the trainer are
the packaged recipe's (``garmentgnn/recipes/mgn.yaml``, read by
:func:`~garmentgnn.training.load_recipe`)."""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from garmentgnn.training import GarmentDataModule, RolloutModule, load_recipe
from garmentgnn.training.integrity import load_checkpoint_file

__all__ = ["STEP_SIZES", "run_branch", "run_steptime", "run_sweep"]


# -- sweeps ------------------------------------------------------------------------------------
def _metrics_rows(run: Path) -> List[Dict[str, str]]:
    files = sorted(run.rglob("metrics.csv"))
    if not files:
        sys.exit(f"error: --runs: no metrics.csv under {run}")
    rows: List[Dict[str, str]] = []
    for f in files:
        with open(f) as fh:
            rows += list(csv.DictReader(fh))
    return rows


def run_sweep(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table: Dict[str, Any] = {}
    for spec in args.runs:
        name, _, run = spec.partition("=")
        rows = _metrics_rows(Path(run))
        val = [(int(r["step"]), float(r["val/E_dist"])) for r in rows if r.get("val/E_dist")]
        one = [(int(r["step"]), float(r["train/one_step_m"])) for r in rows
               if r.get("train/one_step_m")]
        table[name] = {"val_E_dist": val, "train_one_step_m": one,
                       "steps": max(int(r["step"]) for r in rows) + 1}
    (out / "sweep.json").write_text(json.dumps(table, indent=1))
    lines = ["| run | steps | val E_dist (cm) at each validation | last train one-step (mm) |",
             "|---|---:|---|---:|"]
    for name, t in table.items():
        vals = ", ".join(f"{v:.2f}@{s}" for s, v in t["val_E_dist"])
        last = t["train_one_step_m"][-1][1] * 1000 if t["train_one_step_m"] else math.nan
        lines.append(f"| {name} | {t['steps']} | {vals} | {last:.2f} |")
    (out / "sweep.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


# -- a branch with pushforward ------------------------------------------------------------------
def run_branch(args: argparse.Namespace) -> None:
    src = load_checkpoint_file(args.source)
    step0 = int(src["global_step"])
    hp = RolloutModule.saved_hparams(src)
    # the rate at step0 of the run's decay, decaying on from there at the same pace
    lr = max(hp["lr_min"], hp["lr"] * hp["decay"] ** (step0 / hp["decay_steps"]))
    module = RolloutModule.load_from_checkpoint(
        args.source, map_location="cpu", rollout=args.rollout, rollout_start=0, lr=lr,
        stats_steps=0)
    # the run's data settings (another shuffle), windows of 2 + rollout frames, with the
    # recipe's trainer (its log under --out, validation every --every steps)
    dm_hp = GarmentDataModule.settings(src.get("datamodule_hyper_parameters"))
    # the run's order: its data.seed, else the run's seed its data module kept
    order = dm_hp.get("seed")
    if order is None:
        order = (src.get(GarmentDataModule.__qualname__) or {}).get("order_seed", 0)
    data = dict(dm_hp, root=args.data, chunk=2 + args.rollout, seed=int(order) + 1)
    recipe = load_recipe("mgn", args=["--trainer.default_root_dir", str(args.out)],
                         data=data)
    trainer = recipe.trainer(max_steps=args.steps, max_epochs=-1, accelerator="cpu",
                             devices=1, val_check_interval=args.every,
                             limit_val_batches=args.val_batches, enable_progress_bar=False,
                             callbacks=[ModelCheckpoint(every_n_train_steps=args.every,
                                                        save_top_k=-1,
                                                        filename="branch-{step}")])
    trainer.fit(module, recipe.datamodule)
    print(f"branched from step {step0} at lr {lr:.3g}: {args.steps} steps with rollout "
          f"{args.rollout}; checkpoints under {args.out}")


# -- step time -------------------------------------------------------------------------------------
#: (width, blocks, garments a step) timed by ``steptime``
STEP_SIZES = ((64, 8, 1), (64, 10, 1), (128, 15, 1), (32, 8, 16), (64, 4, 16), (64, 8, 16),
              (64, 10, 16), (128, 8, 16))
#: ``--device cuda``: the recipe's size at growing batches, and MeshGraphNets' own size
GPU_STEP_SIZES = ((64, 8, 16), (64, 8, 64), (64, 8, 256), (128, 15, 16), (128, 15, 64))


def run_steptime(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # the recipe's training windows, of 3 frames (one trained step each); each size is
    # the recipe's module with that width and depth
    data = ["--data.root", str(args.data), "--data.chunk", "3", "--seed_everything", "0"]
    ds = load_recipe("mgn", args=data).datamodule.train_set
    g = torch.Generator().manual_seed(0)
    device = torch.device(getattr(args, "device", "cpu"))
    sizes = STEP_SIZES if device.type == "cpu" else GPU_STEP_SIZES
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    results: Dict[str, Any] = {"data": args.data, "sizes": {}, "torch": torch.__version__,
                               "device": torch.cuda.get_device_name(device)
                               if device.type == "cuda" else "cpu"}
    for threads in args.threads:
        torch.set_num_threads(threads)
        steps = {}
        for hidden, layers, n in sizes:
            module = load_recipe("mgn", args=data, set={  # at seed 0
                "model.init_args.model.init_args.hidden": hidden,
                "model.init_args.model.init_args.layers": layers,
                "model.init_args.stats_steps": 0, "model.init_args.rollout": 1}).module
            module.to(device).train()
            opt = torch.optim.Adam(module.parameters(), 1e-4)
            batches = [(ds[torch.randperm(len(ds), generator=g)[:n].tolist()] if n > 1 else
                        ds[int(torch.randint(len(ds), (1,), generator=g))]).to(device)
                       for _ in range(args.repeats + 2)]
            it = iter(range(10 ** 9))

            def step(module=module, opt=opt, batches=batches, it=it):
                b = batches[next(it) % len(batches)]
                loss, _ = module.window_loss(b)
                opt.zero_grad()
                loss.backward()
                opt.step()
            steps[(hidden, layers, n)] = step
        times: Dict[Any, List[float]] = {k: [] for k in steps}
        for r in range(args.repeats + 2):  # interleaved: each size in every round
            for k, fn in steps.items():
                sync()
                t0 = time.perf_counter()
                fn()
                sync()
                if r >= 2:
                    times[k].append(time.perf_counter() - t0)
        for (hidden, layers, n), ts in times.items():
            med = 1e3 * float(np.median(ts))
            results["sizes"][f"{hidden}x{layers}, {n} a step, {threads} thread(s)"] = {
                "hidden": hidden, "layers": layers, "garments": n, "threads": threads,
                "median_ms": med, "ms_per_garment_frame": med / n,
                "hours_per_1e5_garment_frames": med / n * 1e5 / 3.6e6,
                "min_ms": 1e3 * min(ts), "max_ms": 1e3 * max(ts), "repeats": len(ts)}
    (out / "steptime.json").write_text(json.dumps(results, indent=1))
    lines = ["| width x blocks | garments a step | threads | ms / step (median, min-max) | "
             "ms / garment-frame | h / 10^5 garment-frames |", "|---|---:|---:|---|---:|---:|"]
    for r in results["sizes"].values():
        lines.append(f"| {r['hidden']} x {r['layers']} | {r['garments']} | {r['threads']} | "
                     f"{r['median_ms']:.0f} ({r['min_ms']:.0f}-{r['max_ms']:.0f}) | "
                     f"{r['ms_per_garment_frame']:.1f} | "
                     f"{r['hours_per_1e5_garment_frames']:.2f} |")
    (out / "steptime.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
