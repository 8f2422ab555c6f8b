"""The MGN-style simulator's levers trained side by side on one GPU, at equal wall time.

Each lever is today's recipe (``recipes/mgn.yaml``) with one change, trained through
``garmentgnn train fit --config mgn`` for the same ``--trainer.max_time``; all levers run at
once, as separate processes on the one GPU.  The test split is scored afterwards on any
machine with ``benchmarks/mgn_learn.py score`` (paired Wilcoxon over the sequences)::

    # here: a seeded sample of `learn`'s train and val splits that fits the device's
    # 64 MiB with the working tree, and the wheels the GPU image lacks
    python benchmarks/mgn_levers.py prepare --data ~/.cache/garmentgnn/datasets/learn-blender
    # on the GPU machine (the device tool; build/mgn_levers carried): the wheels
    # installed, then every lever for SECONDS; OUT/summary.json, and OUT/levers.tar.gz
    # with each lever's log, metrics and weights (weights-ema.ckpt, weights-raw.ckpt)
    GPU_WINDOW_SCRIPT=benchmarks/mgn_levers.py GPU_WINDOW_DIR=build/mgn_levers \\
        bash benchmarks/gpu_window.sh --seconds 330
    # a dry run on the CPU: --device cpu --seconds 60 --levers base

The EMA lever needs no run of its own: every run keeps Lightning's EMA of its weights
(the checkpoint's ``state_dict``) beside the raw weights (``current_model_state``), and
``weights-raw.ckpt`` is the same run without the average.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import random
import shlex
import shutil
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import torch

from garmentgnn._argparse import ArgumentParser, HelpFormatter, add_output_args, output_path
from garmentgnn.data import compact
from garmentgnn.data.store import read_manifest

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from gpu_window import CARRY_LIMIT, best_checkpoint, weights_only  # noqa: E402
from gpu_window_prepare import download_wheels, folder_bytes, working_tree_bytes  # noqa: E402
from mgn_parts.runs import run_steptime  # noqa: E402

DIR = REPO / "build" / "mgn_levers"
#: the committed copy (``--commit``)
RESULTS = REPO / "docs" / "results" / "mgn_learn" / "levers_gpu"
PACK = "learn.zip"
#: each lever: the flags it adds to today's recipe
LEVERS: Dict[str, List[str]] = {
    "base": [],
    # HOOD: an optimizer step after every frame, the rollout growing over training
    "per_frame": ["--model.rollout_mode", "per_frame", "--model.clip", "1.0",
                  "--model.rollout_schedule", "[[0, 1], [1500, 2], [3000, 3], [4500, 5]]",
                  "--data.chunk", "7"],
    # pushforward with a random number of free frames, the maximum growing
    "random": ["--model.rollout_mode", "random", "--model.clip", "1.0",
               "--model.rollout_schedule", "[[0, 1], [1500, 3], [3000, 6], [4500, 10]]",
               "--data.chunk", "12"],
    "anchor": ["--model.model.init_args.anchor_decay", "0.02"],
    "body_blocks": ["--model.model.init_args.body_blocks", "true"],
    "noise20": ["--model.noise", "0.02"],
    "gamma1": ["--model.noise_gamma", "1.0"],
}


def prepare(a: argparse.Namespace) -> int:
    d = Path(a.dir)
    d.mkdir(parents=True, exist_ok=True)
    info: Dict[str, Any] = {"wheels": download_wheels(d / "wheels") if a.wheels else None}
    (d / PACK).unlink(missing_ok=True)
    tree = working_tree_bytes()
    room = min(int(a.max_mb * 1e6), CARRY_LIMIT - tree - folder_bytes(d) - 2 ** 20)
    items = [r for r in read_manifest(a.data)["items"] if r.get("status") == "ok"]
    rng = random.Random(a.seed)
    ids: List[str] = []
    for split, n in (("val", a.val), ("train", None)):
        pool = sorted(r["id"] for r in items if r["split"] == split)
        rng.shuffle(pool)
        ids += pool[:n] if n is not None else pool
    # the packer keeps the smallest sequences when all do not fit: choose the sample in
    # its seeded order instead, as many as fit by their estimated packed size
    per = {r["id"]: (Path(a.data) / r["file"]).stat().st_size for r in items}
    budget = room * 0.97
    chosen, size = [], 0
    for i in ids:
        if size + 0.47 * per[i] > budget:  # packed: ~46 % of the source (learn)
            break
        chosen.append(i)
        size += 0.47 * per[i]
    res = compact.pack(a.data, d / PACK, splits=["train", "val"], max_bytes=room, ids=chosen)
    info["pack"] = {"bytes": res.bytes, "sequences": len(res.sequences), "splits": res.splits,
                    "left_out": res.left_out, "seed": a.seed,
                    "source_content_sha256": res.source_content_sha256,
                    "max_position_error_m": res.max_position_error_m}
    info.update(working_tree_bytes=tree, total_bytes=tree + folder_bytes(d),
                limit_bytes=CARRY_LIMIT)
    (d / "prepare.json").write_text(json.dumps(info, indent=1) + "\n")
    print(json.dumps(info, indent=1))
    return 0


def last_metrics(run: Path) -> Dict[str, Any]:
    """The last logged value of each metric of a run (its CSV log)."""
    out: Dict[str, Any] = {}
    for f in run.rglob("metrics.csv"):
        with open(f) as fh:
            for row in csv.DictReader(fh):
                for k, v in row.items():
                    if v not in ("", None):
                        out[k] = float(v)
    return out


def run(a: argparse.Namespace) -> int:
    t0 = time.time()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(a.work)
    data = work / "data" / "learn"
    if not (data / "manifest.json").is_file():
        compact.unpack(Path(a.dir) / PACK, data, cache_dir=work / "cache")
    env = dict(os.environ, GARMENTGNN_CACHE_DIR=str(work / "cache"), OMP_NUM_THREADS="2")
    if a.steptime:  # ms per training step against size and batch on this device
        os.environ["GARMENTGNN_CACHE_DIR"] = env["GARMENTGNN_CACHE_DIR"]
        run_steptime(argparse.Namespace(data=str(data), out=str(out), threads=[4],
                                        repeats=a.repeats, device=a.device))
        return 0
    seconds = a.seconds
    procs = {}
    for name in a.levers:
        folder = out / name
        folder.mkdir(parents=True, exist_ok=True)
        cmd = [sys.executable, "-c", "import sys; from garmentgnn.cli import main; "
               "sys.exit(main())", "train", "fit", "--config", "mgn",
               "--data.root", str(data), "--seed_everything", str(a.seed),
               "--data.num_workers", str(a.workers), "--data.val_split", "val",
               "--trainer.accelerator", "gpu" if a.device == "cuda" else "cpu",
               "--trainer.devices", "1",
               "--trainer.max_time", time.strftime("00:%H:%M:%S", time.gmtime(seconds)),
               "--trainer.max_steps", str(a.max_steps),
               "--trainer.val_check_interval", str(a.val_every),
               "--trainer.limit_val_batches", str(a.val_batches),
               "--trainer.enable_progress_bar", "false",
               "--trainer.default_root_dir", str(folder),
               "--trainer.logger.init_args.save_dir", str(folder)] + LEVERS[name] + a.extra
        log = open(folder / "log.txt", "wb")
        log.write((" ".join(cmd) + "\n").encode())
        log.flush()
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                                        cwd=REPO, start_new_session=True), time.time())
    summary: Dict[str, Any] = {"device": a.device, "seconds": seconds, "seed": a.seed,
                               "gpu": torch.cuda.get_device_name(0)
                               if torch.cuda.is_available() else None, "runs": {}}
    deadline = t0 + a.budget_s - 25
    for name, (p, started) in procs.items():
        try:
            p.wait(timeout=max(1.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            p.kill()
        folder = out / name
        # the checkpoint the validation rollouts chose, else the latest
        ckpt = best_checkpoint(folder)
        rec = {"rc": p.returncode, "wall_s": time.time() - started,
               "metrics": last_metrics(folder)}
        if ckpt is not None:
            weights_only(ckpt, folder / "weights-ema.ckpt")
            weights_only(ckpt, folder / "weights-raw.ckpt", raw=True)
            rec["checkpoint"] = ckpt.name
            rec["global_step"] = int(torch.load(ckpt, map_location="cpu",
                                                weights_only=False)["global_step"])
        for c in list(folder.rglob("*.ckpt")) + list(folder.rglob("*tfevents*")):
            if c.name not in ("weights-ema.ckpt", "weights-raw.ckpt"):
                c.unlink()
        summary["runs"][name] = rec
        (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    # one file back: the device tool returns only a few files of OUT
    with tarfile.open(out / "levers.tar.gz", "w:gz") as tar:
        for name in procs:
            tar.add(out / name, arcname=name)
    for name in procs:
        shutil.rmtree(out / name)
    print(json.dumps(summary, indent=1))
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    ap.add_argument("command", nargs="?", default="run", choices=["prepare", "run"],
                    help="prepare: the carried folder (a sample of --data, the wheels); "
                         "run: every lever at once (the GPU machine; what gpu_window.sh "
                         "calls)")
    ap.add_argument("--dir", default=str(DIR), help="the carried folder")
    ap.add_argument("--data", default=None, help="prepare: the `learn` dataset folder")
    ap.add_argument("--val", type=int, default=16, help="prepare: validation sequences carried")
    ap.add_argument("--seed", type=int, default=0,
                    help="prepare: the sample's seed; run: every lever's --seed_everything")
    ap.add_argument("--max-mb", type=float, default=30.0,
                    help="prepare: MB of packed data at most (less where the device's 64 MiB "
                         "would be exceeded)")
    ap.add_argument("--no-wheels", dest="wheels", action="store_false",
                    help="prepare: keep the wheels folder as it is (default: download them)")
    add_output_args(ap, RESULTS, "run: the folder for summary.json and levers.tar.gz")
    ap.add_argument("--work", default="/tmp/mgn_levers_work",
                    help="run: scratch folder (the unpacked data)")
    ap.add_argument("--device", default="cuda", help="run: cuda, or cpu for a dry run")
    ap.add_argument("--budget-s", type=float, default=550.0,
                    help="run: seconds for everything (gpu_window.sh passes the time left)")
    ap.add_argument("--setup-log", default=None, help="run: gpu_window.sh's set-up log")
    ap.add_argument("--seconds", type=int, default=330, help="run: each lever's training time")
    ap.add_argument("--max-steps", type=int, default=6250, help="run: each lever's step cap")
    ap.add_argument("--val-every", type=int, default=1500,
                    help="run: training batches between validations")
    ap.add_argument("--val-batches", type=float, default=1.0,
                    help="run: share (or number) of the validation sequences a check rolls out")
    ap.add_argument("--workers", type=int, default=1, help="run: loader processes a lever")
    ap.add_argument("--levers", nargs="+", default=list(LEVERS), choices=list(LEVERS),
                    help="run: the levers trained")
    ap.add_argument("--extra", type=shlex.split, default=[],
                    help="run: flags added to every lever's run, as one string")
    ap.add_argument("--steptime", action="store_true",
                    help="run: instead, ms per training step against size and batch "
                         "(mgn_learn.py steptime on this device; default: off)")
    ap.add_argument("--repeats", type=int, default=20, help="run --steptime: timed steps a size")
    a = ap.parse_args(argv)
    if a.command == "prepare":
        if a.data is None:
            ap.error("--data: prepare packs a sample of a dataset; name its folder")
        return prepare(a)
    a.out = str(output_path(a, RESULTS))
    return run(a)


if __name__ == "__main__":
    sys.exit(main())
