"""One GPU window: the measurements and training runs that need a GPU, in one command of
under ten minutes on a bare machine that reaches no network (docs/bench.md, "A GPU
window").  ``benchmarks/gpu_window_prepare.py`` makes its carried folder here;
``benchmarks/gpu_window.sh`` installs the wheels there and calls this driver, which
unpacks the datasets, then runs each stage as its own process with a share of the time
left (a stage that fails or runs out of time loses only its own results):

1. ``throughput_{gartrans,static,da}``: ``benchmarks/train_throughput.py`` at batch 1/4/16/64 on
   ``throughput-small`` (bf16 on a GPU; ``static``: GarTrans's stack compiled, CUDA graphs);
2. ``inference``: ``benchmarks/inference.py`` at 1K/4K/10K vertices, batch 1 and batched;
3. ``train_gartrans``, ``train_da``: ``garmentgnn train fit`` for the stage's time
   (``--trainer.max_time``), then ``train test`` of its best checkpoint.

Each stage's folder goes to ``OUT/<stage>.tar.gz`` as soon as it ends (checkpoints without
the optimizer state, under the device's 16 MiB a file); ``OUT/summary.{md,json}`` are
rewritten after every stage.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

from garmentgnn.models.inputs import CHUNK  # the recipes' frames per chunk
from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, int_at_least,
                                  output_path)
HERE = Path(__file__).resolve().parent
REPO = HERE.parent
#: the carried folder (``build/`` is ignored by git)
DIR = REPO / "build" / "gpu_window"
#: the committed copy (``--commit``; its bundles are ignored by git)
RESULTS = HERE.parent / "docs" / "results" / "benchmarks" / "gpu_window"
THROUGHPUT_PACK = "throughput-small.zip"
TRAIN_PACK = "train.zip"
#: what garmentgnn imports that the GPU image lacks (its list: /work/.library/device)
WHEELS = ("trimesh", "meshio", "jsonargparse", "docstring_parser", "typeshed_client")
#: the device tool's limits: a working tree with its carried paths, a file back from OUT
CARRY_LIMIT = 64 * 2 ** 20
FILE_LIMIT = 16 * 2 ** 20 - 2 ** 16
#: seconds kept after the last stage for the last bundle and summary
MARGIN_S = 20.0
#: each stage's share of the time left when it starts (unused time goes to the later ones)
#: (set from the first H200 window's stage times, docs/results/gpu_window_h200)
WEIGHTS = {"throughput_gartrans": 0.17, "throughput_static": 0.10, "throughput_da": 0.10,
           "inference": 0.11, "train_gartrans": 0.30, "train_da": 0.22}
RECIPES = {"train_gartrans": "gartrans", "train_da": "baselines/da"}  # each stage's --config

# --------------------------------------------------------------------------- planning
def allot(remaining_s: float, names: List[str]) -> float:
    """The seconds the first of ``names`` (the stages still to run) gets of
    ``remaining_s``: its weight's share of the weights left."""
    if not names:
        raise ValueError("`names`: expected the stages still to run, got none")
    unknown = [n for n in names if n not in WEIGHTS]
    if unknown:
        raise ValueError(f"`names`: unknown stages {unknown}; choose from {list(WEIGHTS)}")
    return max(0.0, remaining_s) * WEIGHTS[names[0]] / sum(WEIGHTS[n] for n in names)


def split_training(stage_s: float, startup_s: float) -> Dict[str, float]:
    """A training stage's seconds: ``fit`` (its hard limit), the ``max_time`` Lightning
    trains for (``fit`` less the start-up: imports, static inputs, compilation) and what
    is kept for ``test``."""
    test = max(0.25 * stage_s, min(startup_s, 0.5 * stage_s))
    fit = stage_s - test
    return {"fit": fit, "max_time": max(5.0, fit - startup_s), "test": test}


def hms(seconds: float) -> str:
    """Lightning's ``max_time`` string ``DD:HH:MM:SS``."""
    s = max(1, int(seconds))
    return f"{s // 86400:02d}:{s // 3600 % 24:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


# --------------------------------------------------------------------------- processes
def run_command(cmd: List[str], timeout_s: float, log: Path, env: Dict[str, str]
                ) -> Dict[str, Any]:
    """Run ``cmd`` (its own process group, output to ``log``), killed after
    ``timeout_s``: ``{cmd, rc, wall_s, timed_out}``."""
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    timed_out = False
    with open(log, "ab") as f:
        f.write(f"$ {shlex.join(cmd)}\n".encode())
        f.flush()
        if timeout_s < 1:
            return {"cmd": shlex.join(cmd), "rc": None, "wall_s": 0.0, "timed_out": True}
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=REPO,
                             start_new_session=True)
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
            for sig, wait in ((signal.SIGTERM, 3), (signal.SIGKILL, 5)):
                try:
                    os.killpg(p.pid, sig)
                    p.wait(timeout=wait)
                    break
                except (subprocess.TimeoutExpired, ProcessLookupError):
                    continue
    return {"cmd": shlex.join(cmd), "rc": p.returncode, "wall_s": time.perf_counter() - t0,
            "timed_out": timed_out}


# --------------------------------------------------------------------------- results
THROUGHPUT_LINE = re.compile(r'^(\[".*\]) (\d+)$')


def throughput_rows(folder: Path, log: Path, device: str) -> List[Dict[str, Any]]:
    """The rows of ``train_throughput_<device>.json``, else (a run cut short) the
    configurations its log printed as they finished."""
    path = folder / f"train_throughput_{device}.json"
    if path.is_file():
        return [{k: r.get(k) for k in ("size", "method", "threads", "precision", "batch",
                                       "vertex_frames_per_s", "x_batch1", "loss_rel_diff")}
                for r in json.loads(path.read_text())["rows"]]
    rows = []
    for line in log.read_text(errors="replace").splitlines() if log.is_file() else []:
        m = THROUGHPUT_LINE.match(line.strip())
        if m:
            size, method, threads, prec, batch = json.loads(m.group(1))
            rows.append({"size": size, "method": method, "threads": threads, "precision": prec,
                         "batch": batch, "vertex_frames_per_s": float(m.group(2)),
                         "x_batch1": None, "loss_rel_diff": None})
    return rows


def training_summary(fit_dir: Path, test_log: Path) -> Dict[str, Any]:
    """Epochs, steps, the last training loss and validation E_dist of a fit's
    ``metrics.csv``, its checkpoints and the test's metrics table."""
    out: Dict[str, Any] = {}
    metrics = sorted(fit_dir.glob("logs/version_*/metrics.csv"))
    if metrics:
        with open(metrics[-1], newline="") as f:
            rows = list(csv.DictReader(f))

        def last(key):
            vals = [(r.get("epoch"), r[key]) for r in rows if r.get(key)]
            return {"epoch": int(vals[-1][0]), "value": float(vals[-1][1])} if vals else None
        out.update(epochs=1 + max((int(r["epoch"]) for r in rows if r.get("epoch")),
                                  default=-1),
                   steps=max((int(r["step"]) for r in rows if r.get("step")), default=0),
                   train_loss=last("train/loss_epoch"), val_E_dist=last("val/E_dist"))
    out["checkpoints"] = sorted(p.name for p in fit_dir.glob("logs/version_*/checkpoints/*"))
    if test_log.is_file():
        text = test_log.read_text(errors="replace").splitlines()
        out["test_table"] = [s for s in text if s.startswith(("|", "test split"))]
    return out


def best_checkpoint(fit_dir: Path) -> Optional[Path]:
    """The fit's ``best-*`` checkpoint, else its ``last.ckpt``, else none."""
    ckpts = sorted(fit_dir.glob("logs/version_*/checkpoints/*.ckpt"),
                   key=lambda p: p.stat().st_mtime)
    best = [p for p in ckpts if p.name.startswith("best-")]
    last = [p for p in ckpts if p.name == "last.ckpt"]
    return (best or last or [None])[-1]


def weights_only(ckpt: Path, dest: Path, raw: bool = False) -> Path:
    """``ckpt`` without its optimizer and scheduler state, re-stamped (what ``train test``
    reads): of a run that averages its weights, the average (``raw``: as trained)."""
    import torch  # noqa: PLC0415 (the driver itself runs without importing torch)

    from garmentgnn.training.integrity import stamp_checkpoint  # noqa: PLC0415 (likewise)
    c = torch.load(ckpt, map_location="cpu", weights_only=False)
    if raw:  # the weights as trained, where the run kept their average beside them
        c["state_dict"] = c.get("current_model_state", c["state_dict"])
    for key in ("optimizer_states", "lr_schedulers", "current_model_state", "averaging_state"):
        c.pop(key, None)
    stamp_checkpoint(c)
    torch.save(c, dest)
    return dest


def bundle(folder: Path, dest: Path, extra: List[Path], limit: int = FILE_LIMIT
           ) -> Dict[str, Any]:
    """``folder`` (its ``*.ckpt`` left out) and the files ``extra`` as ``dest`` (tar.gz),
    dropping ``extra`` files from the last while it is over ``limit`` bytes."""
    kept = list(extra)
    dropped: List[str] = []
    while True:
        tmp = dest.with_name(f".{dest.name}.tmp")
        with tarfile.open(tmp, "w:gz") as tar:
            for p in sorted(folder.rglob("*")) if folder.is_dir() else []:
                if p.is_file() and p.suffix != ".ckpt":
                    tar.add(p, arcname=str(Path(folder.name) / p.relative_to(folder)))
            for p in kept:
                tar.add(p, arcname=str(Path(folder.name) / p.name))
        if tmp.stat().st_size <= limit or not kept:
            os.replace(tmp, dest)
            return {"file": dest.name, "bytes": dest.stat().st_size,
                    "over_limit": dest.stat().st_size > limit, "dropped": dropped}
        dropped.append(kept.pop().name)


# --------------------------------------------------------------------------- stages
class Window:
    """One run: its folders, environment, deadline and summary."""

    def __init__(self, a: argparse.Namespace) -> None:
        self.a = a
        self.t0 = time.perf_counter()
        self.deadline = self.t0 + a.budget_s
        self.out = Path(a.out)
        self.work = Path(a.work or tempfile.mkdtemp(prefix="gpu_window_"))
        self.env = dict(os.environ, PYTHONUNBUFFERED="1",
                        GARMENTGNN_CACHE_DIR=str(self.work / "cache"),
                        PYTHONPATH=os.pathsep.join(
                            [str(REPO / "src")] + [p for p in os.environ.get(
                                "PYTHONPATH", "").split(os.pathsep) if p]))
        self.summary: Dict[str, Any] = {
            "device": a.device, "budget_s": a.budget_s, "stages": [], "datasets": {},
            "setup_log": (Path(a.setup_log).read_text(errors="replace")[-4000:]
                          if a.setup_log and Path(a.setup_log).is_file() else None)}
        self.threads = min(8, os.cpu_count() or 1) if a.device == "cuda" else \
            (os.cpu_count() or 1)

    def left(self) -> float:
        return self.deadline - time.perf_counter() - MARGIN_S

    def py(self, *args: str) -> List[str]:
        return [sys.executable, *args]

    # -- datasets -------------------------------------------------------------------
    def unpack(self) -> None:
        from garmentgnn.data import compact  # noqa: PLC0415 (after the wheels' install)

        cache = self.work / "cache"
        for key, name, root in (("throughput", THROUGHPUT_PACK,
                                 cache / "benchmarks" / "throughput-small"),
                                ("train", TRAIN_PACK, self.work / "data" / "train")):
            file = Path(self.a.dir) / name
            if not file.is_file():
                self.summary["datasets"][key] = {"file": name, "status": "not carried"}
                continue
            t = time.perf_counter()
            try:
                res = compact.unpack(file, root, cache_dir=cache)
                man = json.loads((root / "manifest.json").read_text())
                self.summary["datasets"][key] = {
                    "file": name, "root": str(root), "seconds": time.perf_counter() - t,
                    "sequences": res.sequences, "source_content_sha256":
                        res.source_content_sha256, "content_sha256": res.content_sha256,
                    "splits": sorted({r["split"] for r in man["items"]}),
                    "train_chunks": sum(-(-int(r["num_frames"]) // CHUNK) for r in man["items"]
                                        if r["split"] == "train" and r["status"] == "ok"),
                    "max_position_error_m": man["compact"]["max_position_error_m"],
                    "left_out": len(man["compact"]["left_out"])}
            except Exception as e:  # a bad pack loses its stages, not the run
                self.summary["datasets"][key] = {"file": name, "status": f"failed: {e}"}

    def dataset(self, key: str) -> Optional[Dict[str, Any]]:
        d = self.summary["datasets"].get(key, {})
        return d if "root" in d else None

    # -- stages ---------------------------------------------------------------------
    def throughput(self, name: str, seconds: float, folder: Path) -> Dict[str, Any]:
        if self.dataset("throughput") is None:
            return {"status": "skipped", "note": f"no {THROUGHPUT_PACK} carried"}
        method = "gartrans" if name == "throughput_static" else name.split("_", 1)[1]
        cmd = self.py("benchmarks/train_throughput.py", "--sizes", "small", "--methods",
                      method, "--threads", str(self.threads), "--device", self.a.device,
                      "--batches", *map(str, self.a.batches), "--chunks", str(self.a.chunks),
                      "--repeats", "1", "--warmup", "2", "--workers", str(self.a.loader_workers),
                      "--out", str(folder))
        cmd += (["--compile-stack", "reduce-overhead"] if name == "throughput_static"
                else ["--bf16"] if self.a.device == "cuda" else [])
        r = run_command(cmd, seconds, folder / "log.txt", self.env)
        return dict(r, rows=throughput_rows(folder, folder / "log.txt", self.a.device))

    def inference(self, seconds: float, folder: Path) -> Dict[str, Any]:
        cmd = self.py("benchmarks/inference.py", "--device", self.a.device, "--sizes",
                      *map(str, self.a.sizes), "--frames", str(self.a.frames), "--batches",
                      *map(str, self.a.infer_batches), "--repeats", "3", "--no-blender",
                      "--torch-max-vertices", "0", "--threads", str(self.threads),
                      "--out", str(folder / "inference"))
        r = run_command(cmd, seconds, folder / "log.txt", self.env)
        md = folder / "inference.md"
        table = [s for s in md.read_text().splitlines() if s.startswith("|")] \
            if md.is_file() else []
        return dict(r, table=table[:2 + 4 * len(self.a.sizes)])

    def train(self, name: str, seconds: float, folder: Path) -> Dict[str, Any]:
        data = self.dataset("train") or self.dataset("throughput")
        if data is None:
            return {"status": "skipped", "note": "no dataset carried"}
        splits = data["splits"]
        val = "val" if "val" in splits else "train"
        test = next(s for s in ("test", "val", "train") if s in splits)
        times = split_training(seconds, self.a.startup_s)
        batch = max(1, min(self.a.train_batch, data.get("train_chunks") or 1))
        accel = "cuda" if self.a.device == "cuda" else "cpu"
        common = ["--config", RECIPES[name], "--data.root", data["root"],
                  "--trainer.accelerator", accel, "--trainer.enable_progress_bar", "false"]
        fit = self.py("-m", "garmentgnn.cli", "train", "fit", *common,
                      "--data.batch_size", str(batch), "--data.val_split", val,
                      "--data.num_workers", str(self.a.loader_workers),
                      "--trainer.max_time", hms(times["max_time"]),
                      "--trainer.max_epochs", "100000",
                      "--trainer.default_root_dir", str(folder / "fit"))
        if val == "train":  # validation on training sequences: a quarter of them
            fit += ["--trainer.limit_val_batches", "0.25"]
        stop = time.perf_counter() + seconds
        r = run_command(fit, times["fit"], folder / "fit.log", self.env)
        res: Dict[str, Any] = dict(r, plan=times, val_split=val, test_split=test,
                                   dataset=data["file"], batch=batch)
        ckpt = best_checkpoint(folder / "fit")
        if ckpt is not None:
            cmd = self.py("-m", "garmentgnn.cli", "train", "test", *common,
                          "--data.test_split", test, "--ckpt_path", str(ckpt),
                          "--data.num_workers", str(self.a.loader_workers),
                          "--trainer.default_root_dir", str(folder / "test"))
            if test == "train":  # scored on training sequences: a quarter of them
                cmd += ["--trainer.limit_test_batches", "0.25"]
            t = run_command(cmd, stop - time.perf_counter(), folder / "test.log", self.env)
            res["test"] = {k: t[k] for k in ("rc", "wall_s", "timed_out")}
            res["wall_s"] += t["wall_s"]
        parts = {"fit": r, **({"test": res["test"]} if "test" in res else {})}
        late = [k for k, v in parts.items() if v["timed_out"]]
        failed = [k for k, v in parts.items() if not v["timed_out"] and v["rc"] != 0]
        res["status"] = "failed" if failed else "timed out" if late else \
            "ok" if ckpt is not None else "failed"
        notes = [f"{k} timed out" for k in late] + [f"{k} failed" for k in failed]
        if ckpt is None:
            notes.append("no checkpoint to test")
        if notes:
            res["note"] = "; ".join(notes)
        res.update(training_summary(folder / "fit", folder / "test.log"))
        return res

    def checkpoints(self, folder: Path) -> List[Path]:
        """Weights-only copies of the fit's best and last checkpoints (best first)."""
        out = []
        ckpts = sorted((folder / "fit").glob("logs/version_*/checkpoints/*.ckpt"))
        for pick in ([p for p in ckpts if p.name.startswith("best-")],
                     [p for p in ckpts if p.name == "last.ckpt"]):
            if pick:
                dest = folder / f"weights-{pick[-1].name}"
                try:
                    out.append(weights_only(pick[-1], dest))
                except Exception as e:  # noqa: BLE001 - reported, the logs still go back
                    (folder / "bundle.log").write_text(f"{pick[-1]}: {e}\n")
        return out

    def stage(self, name: str, names_left: List[str]) -> None:
        seconds = allot(self.left(), names_left)
        folder = self.work / name
        folder.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        try:
            if name.startswith("throughput_"):
                res = self.throughput(name, seconds, folder)
            elif name == "inference":
                res = self.inference(seconds, folder)
            else:
                res = self.train(name, seconds, folder)
        except Exception as e:  # one stage's failure is reported, the next one runs
            res = {"status": "failed", "note": f"{type(e).__name__}: {e}"}
        res.setdefault("status", "timed out" if res.get("timed_out") else
                       "ok" if res.get("rc") == 0 else "failed")
        res.update(name=name, planned_s=seconds, stage_wall_s=time.perf_counter() - t)
        extra = self.checkpoints(folder) if name in RECIPES else []
        res["bundle"] = bundle(folder, self.out / f"{name}.tar.gz", extra)
        self.summary["stages"].append(res)
        self.write()

    def write(self) -> None:
        self.summary["wall_s"] = time.perf_counter() - self.t0
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "summary.json").write_text(json.dumps(self.summary, indent=1))
        (self.out / "summary.md").write_text(markdown(self.summary))


def markdown(s: Dict[str, Any]) -> str:
    """The summary as a page: datasets, stages, and each stage's results."""
    name = f", {s['device_name']}" if s.get("device_name") else ""
    lines = [f"# GPU window ({s['device']}{name})",
             "", f"Budget {s['budget_s']:.0f} s, wall {s.get('wall_s', 0):.0f} s.", ""]
    for key, d in s["datasets"].items():
        if "root" in d:
            lines.append(f"- dataset `{d['file']}` ({key}): {d['sequences']} sequences, splits "
                         f"{', '.join(d['splits'])}, source "
                         f"`{str(d['source_content_sha256'])[:12]}`"
                         f", positions within {1e3 * d['max_position_error_m']:.3f} mm, "
                         f"{d['left_out']} left out, unpacked in {d['seconds']:.1f} s")
        else:
            lines.append(f"- dataset `{d['file']}` ({key}): {d['status']}")
    lines += ["", "| stage | planned (s) | wall (s) | status | bundle |", "|---|---:|---:|---|---|"]
    for r in s["stages"]:
        b = r.get("bundle", {})
        lines.append(f"| {r['name']} | {r['planned_s']:.0f} | {r['stage_wall_s']:.0f} | "
                     f"{r['status']}{' (' + r['note'] + ')' if r.get('note') else ''} | "
                     f"{b.get('file', '-')} {b.get('bytes', 0) / 2 ** 20:.1f} MiB"
                     f"{' dropped ' + ', '.join(b['dropped']) if b.get('dropped') else ''} |")
    rows = [row for r in s["stages"] for row in r.get("rows", [])]
    if rows:
        lines += ["", "Training throughput (vertex-frames/s):", "",
                  "| method | precision | batch | vertex-frames/s | x batch 1 | loss vs fp32 |",
                  "|---|---|---:|---:|---:|---:|"]
        lines += [f"| {r['method']} | {r['precision']} | {r['batch']} | "
                  f"{r['vertex_frames_per_s']:.0f} | "
                  f"{'-' if r['x_batch1'] is None else format(r['x_batch1'], '.2f')} | "
                  f"{'-' if r.get('loss_rel_diff') is None else format(r['loss_rel_diff'], '.1e')}"
                  " |" for r in rows]
    for r in s["stages"]:
        if r.get("table"):
            lines += ["", "Inference:", ""] + r["table"]
        if r["name"] in RECIPES and r["status"] != "skipped":
            lines += ["", f"{r['name']}: {r.get('epochs', 0)} epochs, {r.get('steps', 0)} "
                      f"steps of {r.get('batch')} chunks on `{r.get('dataset')}` (val split "
                      f"{r.get('val_split')}, test split {r.get('test_split')}); "
                      f"last train loss {r.get('train_loss')}, val E_dist {r.get('val_E_dist')}",
                      ""] + r.get("test_table", [])
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- run
def gpu_name() -> Optional[str]:
    try:
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=20)
        return r.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def run(a: argparse.Namespace) -> int:
    w = Window(a)
    w.summary["device_name"] = gpu_name() if a.device == "cuda" else None
    w.unpack()
    w.write()
    names = [n for n in WEIGHTS if n in a.stages]
    for i, name in enumerate(names):
        w.stage(name, names[i:])
    w.write()
    print(markdown(w.summary))
    if not a.keep_work:
        shutil.rmtree(w.work, ignore_errors=True)
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--dir", default=str(DIR), help="the carried folder")
    add_output_args(ap, RESULTS, "the folder for summary.{md,json} and the stages' bundles "
                    "(gpu_window.sh passes the device tool's $OUT)")
    ap.add_argument("--work", default=None,
                    help="scratch folder (default: a new temporary one)")
    ap.add_argument("--device", choices=["cuda", "cpu"], default="cuda", help="accelerator")
    ap.add_argument("--budget-s", type=float, default=540.0,
                    help="seconds for everything after the set-up")
    ap.add_argument("--setup-log", default=None, help="the set-up's log, quoted in the summary")
    ap.add_argument("--keep-work", action="store_true",
                    help="keep the scratch folder (unpacked datasets, full checkpoints)")
    ap.add_argument("--stages", nargs="+", choices=list(WEIGHTS), default=list(WEIGHTS),
                    help="stages to run (in the order of the default)")
    ap.add_argument("--batches", type=int_at_least(1), nargs="+", default=[1, 4, 16, 64],
                    help="training throughput: chunks per step")
    ap.add_argument("--chunks", type=int_at_least(1), default=32,
                    help="training throughput: chunks per timed configuration")
    ap.add_argument("--sizes", type=int_at_least(4), nargs="+", default=[1000, 4000, 10000],
                    help="inference: garment resolutions")
    ap.add_argument("--frames", type=int_at_least(2), default=32, help="inference: frames")
    ap.add_argument("--infer-batches", type=int_at_least(1), nargs="+",
                    default=[1, 4, 16, 32], help="inference: frames per call")
    ap.add_argument("--train-batch", type=int_at_least(1), default=8,
                    help="training: chunks per step")
    ap.add_argument("--loader-workers", type=int_at_least(0), default=None,
                    help="data loader processes of every stage (default: 6 on cuda, 0 on cpu)")
    ap.add_argument("--startup-s", type=float, default=45.0,
                    help="training: seconds a fit needs before its first step (imports, "
                         "static inputs, compilation), kept out of its max_time")
    a = ap.parse_args(argv)
    if not a.budget_s > 0:
        ap.error(f"--budget-s: expected a positive number of seconds, got {a.budget_s}")
    if not a.startup_s >= 0:
        ap.error(f"--startup-s: expected seconds >= 0, got {a.startup_s}")
    if a.loader_workers is None:  # the GPU machine has 16 cores; here loading shares 2
        a.loader_workers = 6 if a.device == "cuda" else 0
    a.out = str(output_path(a, RESULTS))
    return run(a)


if __name__ == "__main__":
    sys.exit(main())
