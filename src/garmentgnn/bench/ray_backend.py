"""``garmentgnn bench --backend ray``: each learned (method, seed) run is a Ray task.

The driver (the process running :func:`garmentgnn.bench.runner.run`) keeps ``OUT``:
it hands each task what its run needs -- the dataset's description, the budget, the
files already in ``OUT/models/<method>--s<seed>/`` (so a run cut off before resumes
from its last checkpoint) and, where the dataset may not be on the task's node, the
dataset's files -- and the task trains and scores the run with
:meth:`garmentgnn.bench.learned.LearnedRunner.record` in a folder of its own, then
returns the record and every file it wrote (checkpoints, ``run.json``, the report's
prediction panels) as bytes.  The driver writes them under ``OUT`` as the local bench
would, so no shared file system is assumed and the report folder is the same.

A run whose record comes back failed, or whose task raised or lost its worker, is run
once more (Ray's ``max_retries`` and ``retry_exceptions``); a second failure is the
record, marked failed with what happened.  Everything else the bench runs (the
stability suite on the trained models, the simulator cases) runs in the driver, as
before.  The cluster: :func:`garmentgnn._ray.cluster`.
"""
from __future__ import annotations

import argparse
import copy
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence, Tuple

from garmentgnn._argparse import finite_float, int_at_least
from garmentgnn._files import atomic_write_bytes
from garmentgnn._ray import cluster
from garmentgnn.bench.dataset import DatasetInfo, prepare_dataset
from garmentgnn.bench.learned import KIND, LearnedRunner
from garmentgnn.bench.methods import LearnedBudget
from garmentgnn.bench.tables import slug
from garmentgnn.bench.timing import num_threads


__all__ = ["RayBackend", "add_cluster_args", "local_dataset", "pack", "task_runner", "unpack"]

#: a folder's files: relative path -> bytes, or ``{"link": target}`` for a symbolic link
#: (Lightning's ``last.ckpt`` links to the latest checkpoint)
Files = Dict[str, Any]


def pack(root: Path) -> Files:
    """Every file under ``root`` (none when it does not exist)."""
    root, out = Path(root), {}
    if root.is_dir():
        for p in sorted(root.rglob("*")):
            rel = p.relative_to(root).as_posix()
            if p.is_symlink():
                out[rel] = {"link": os.readlink(p)}
            elif p.is_file():
                out[rel] = p.read_bytes()
    return out


def unpack(files: Files, root: Path) -> None:
    """Write ``files`` (:func:`pack`) under ``root``, each file whole or not at all."""
    root = Path(root)
    for rel, data in files.items():
        path = root / rel
        if isinstance(data, dict):
            path.parent.mkdir(parents=True, exist_ok=True)
            if path.is_symlink() or path.exists():
                path.unlink()
            os.symlink(data["link"], path)
        else:
            atomic_write_bytes(path, data)


def _rebase(obj: Any, old: str, new: str) -> Any:
    """``obj`` with every string that starts with the folder ``old`` moved under ``new``."""
    if isinstance(obj, dict):
        return {k: _rebase(v, old, new) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rebase(v, old, new) for v in obj]
    if isinstance(obj, str) and (obj == old or obj.startswith(old + os.sep)):
        return new + obj[len(old):]
    return obj


class RunFailed(RuntimeError):
    """A run whose record came back failed: raised in the task so that Ray runs it once
    more; ``result`` is the task's result (the failed record, the files)."""

    def __init__(self, result: Dict[str, Any]) -> None:
        super().__init__(result["record"].get("message", "failed"))
        self.result = result

    def __reduce__(self):
        return (RunFailed, (self.result,))


# --------------------------------------------------------------------------- the task
_RUNNERS: Dict[Tuple, LearnedRunner] = {}  # per worker process: one per dataset and budget


def local_dataset(info: DatasetInfo, files: Optional[Files]) -> DatasetInfo:
    """``info``'s dataset on this node: at its own path when that holds the same dataset
    (same fingerprint), else ``files`` unpacked once into this node's cache folder."""
    try:
        here = prepare_dataset(info.root)
        if here.fingerprint == info.fingerprint:
            return here
    except ValueError:
        pass
    if files is None:
        raise RuntimeError(f"the dataset {info.root} is not on this node and the driver sent "
                           "none; run the bench with --ship-data or put the dataset at that "
                           "path on every node")
    root = Path(tempfile.gettempdir()) / "garmentgnn-ray" / f"data-{info.fingerprint[:16]}"
    if not root.exists():  # unpacked beside it, then moved into place whole
        tmp = root.with_name(f".{root.name}.tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        unpack(files, tmp)
        try:
            os.rename(tmp, root)
        except OSError:  # another task on this node was first
            shutil.rmtree(tmp, ignore_errors=True)
    here = prepare_dataset(root)
    if here.fingerprint != info.fingerprint:
        raise RuntimeError(f"the dataset unpacked to {root} is not the driver's "
                           f"({here.fingerprint[:8]} != {info.fingerprint[:8]})")
    return here


def task_runner(info: DatasetInfo, budget: LearnedBudget, timing: Tuple[Sequence[int], int, int],
                data_files: Optional[Files], work: Path) -> LearnedRunner:
    """A :class:`LearnedRunner` of ``info``'s dataset on this node (:func:`local_dataset`)
    writing under ``work``; built once per worker process and dataset, budget and timing
    (its scored splits and compiled search are kept), copied for each run."""
    data = local_dataset(info, data_files)
    key = (data.root, data.fingerprint, budget, tuple(timing[0]), *timing[1:])
    if key not in _RUNNERS:
        _RUNNERS.clear()
        _RUNNERS[key] = LearnedRunner(data, budget, work, *timing)
    runner = copy.copy(_RUNNERS[key])
    runner.out, runner._trained = Path(work), {}
    return runner


def _task(method: str, seed: int, info: DatasetInfo, budget: LearnedBudget,
          timing: Tuple[Sequence[int], int, int], threads: int, model_files: Files,
          data_files: Optional[Files]) -> Dict[str, Any]:
    """A Ray task: one learned (method, seed) run in a folder of its own; returns its
    record and the files it wrote.  A failed record raises :class:`RunFailed`."""
    with num_threads(threads):
        work = Path(tempfile.mkdtemp(prefix="garmentgnn-run-"))
        try:
            unpack(model_files, work / "models" / f"{slug(method)}--s{seed}")
            rec = task_runner(info, budget, timing, data_files, work).record(method, seed)
            result = {"record": rec, "files": pack(work), "work": str(work)}
        finally:
            shutil.rmtree(work, ignore_errors=True)
    if rec.get("status") != "ok":
        raise RunFailed(result)
    return result


# --------------------------------------------------------------------------- the driver
@dataclass(frozen=True)
class RayBackend:
    """Where ``bench --backend ray`` runs: a local cluster of ``workers`` CPUs (``None``:
    all of this machine's) or the cluster at ``address``; ``gpus`` per run (a fraction
    shares one); ``ship_data``: send the dataset's files with every run (``None``: when
    joining a cluster by ``address``, whose nodes may not have it); ``max_retries``:
    reruns of a failed run."""

    workers: Optional[int] = None
    address: Optional[str] = None
    gpus: float = 0.0
    ship_data: Optional[bool] = None
    max_retries: int = 1

    def __post_init__(self) -> None:
        if self.workers is not None and (not isinstance(self.workers, int)
                                         or self.workers < 1):
            raise ValueError(f"`workers` (--workers): expected a positive number of CPUs, "
                             f"got {self.workers!r}")
        if not (isinstance(self.gpus, (int, float)) and 0 <= self.gpus < float("inf")):
            raise ValueError(f"`gpus` (--gpus): expected a number >= 0 of GPUs per run, got "
                             f"{self.gpus!r}")
        if self.workers is not None and self.address:
            raise ValueError("--workers sizes a local cluster; with --address the cluster "
                             "has its own CPUs: give one of them")

    def run(self, runner: LearnedRunner, todo: Sequence[Tuple[str, int]], threads: int,
            save: Callable[[Dict[str, Any]], None]) -> int:
        """Run the learned ``(method, seed)`` runs ``todo`` of ``runner`` (the driver's),
        ``threads`` CPUs each; ``save(record)`` each as it arrives, after writing its
        files under ``runner.out``.  Returns how many ran."""
        if not todo:
            return 0
        out = Path(runner.out)
        ship = bool(self.address) if self.ship_data is None else self.ship_data
        budget = runner.budget
        timing = (runner.batches, runner.warmup, runner.repeats)
        with cluster(self.workers, self.address) as ray:
            data_ref = ray.put(pack(runner.data.root)) if ship else None
            remote = ray.remote(_task).options(num_cpus=threads, num_gpus=self.gpus,
                                               max_retries=self.max_retries,
                                               retry_exceptions=True)
            refs = {remote.remote(m, s, runner.data, budget, timing, threads,
                                  pack(out / "models" / f"{slug(m)}--s{s}"), data_ref): (m, s)
                    for m, s in todo}
            pending = list(refs)
            try:
                while pending:
                    ready, pending = ray.wait(pending, num_returns=1)
                    for ref in ready:
                        save(self._arrived(ray, ref, refs[ref], runner, out))
            except BaseException:
                for ref in pending:
                    ray.cancel(ref, force=True)
                raise
        return len(todo)

    def _arrived(self, ray, ref, run: Tuple[str, int], runner: LearnedRunner,
                 out: Path) -> Dict[str, Any]:
        """The record of the finished task ``ref``, its files written under ``out``."""
        tries = f"failed {self.max_retries + 1} times on Ray"
        try:
            result = ray.get(ref)
        except Exception as err:
            cause = getattr(err, "cause", None)
            if not isinstance(cause, RunFailed):
                method, seed = run
                return {"kind": KIND, "method": method, "case": runner.data.case,
                        "seed": seed, "dataset": runner.data.to_json(), "status": "failed",
                        "message": f"{tries}: {type(err).__name__}: "
                                   f"{str(err).strip().splitlines()[-1][:500]}"}
            result = cause.result
            result["record"]["message"] = f"{tries}: {result['record']['message']}"
        unpack(result["files"], out)
        rec = _rebase(result["record"], result["work"], str(out))
        rec["dataset"] = runner.data.to_json()
        return rec


def add_cluster_args(parser, what: str, when: str = "") -> None:
    """The Ray cluster flags of ``garmentgnn bench`` and ``sweep`` (``--address``,
    ``--workers``, ``--gpus``, ``--ship-data``): ``what`` asks for GPUs and gets the
    dataset (``"each learned run"``, ``"each trial"``); ``when`` prefixes each help text
    (``"with --backend ray: "``)."""
    parser.add_argument("--address", default=None, metavar="HOST:PORT",
                        help=f"{when}the Ray cluster to join (a `ray start --head`); "
                             f"default: a local cluster of --workers CPUs")
    parser.add_argument("--workers", type=int_at_least(1), default=None, metavar="N",
                        help=f"{when}without --address: the local cluster's CPUs (default: "
                             f"all of this machine's)")
    parser.add_argument("--gpus", type=finite_float, default=0.0, metavar="G",
                        help=f"{when}GPUs {what} asks for (a fraction shares one)")
    parser.add_argument("--ship-data", action=argparse.BooleanOptionalAction, default=None,
                        help=f"{when}send the dataset's files to {what}, for nodes without "
                             f"it at the same path (default: with --address)")
