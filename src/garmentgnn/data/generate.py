"""Dataset generation: simulate a spec's items (:mod:`garmentgnn.data.presets`) with
parallel workers, resumably, into a dataset folder (sequence files + manifest).

Each item is simulated on its own (:func:`garmentgnn.data.worker.run_item`, in a pool
worker or a Ray task) with the seed its spec gave it, so an item's content never depends
on which other items exist or on the order they run in.
"""
from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import torch
from tqdm.auto import tqdm

from garmentgnn.data import store
from garmentgnn.data.presets import Spec, build_inputs
from garmentgnn.data.ray_backend import run_on_ray
from garmentgnn.data.worker import (default_simulate, engine_info, init_worker, item_settings,
                                    plain_settings, run_item)
from garmentgnn.garments import RESOLUTIONS
from garmentgnn.sim.blender import require_blender


# --------------------------------------------------------------------------- estimate

def _changed_files(old_items: List[Dict[str, Any]], new_items: List[Dict[str, Any]]
                   ) -> List[Tuple[str, str, str]]:
    """``(path, old sha256, new sha256)`` of every garment or motion file that both item
    lists name with other content: why a spec read again names another dataset."""
    def files(items):
        out: Dict[str, str] = {}
        for it in items:
            for part in ("garment", "motion"):
                e = it.get(part) if isinstance(it, dict) else None
                if isinstance(e, dict) and e.get("path") and e.get("sha256"):
                    out[str(e["path"])] = str(e["sha256"])
        return out
    a, b = files(old_items), files(new_items)
    return [(p, a[p], b[p]) for p in sorted(a.keys() & b.keys()) if a[p] != b[p]]

def estimate_seconds(items: Sequence[Dict[str, Any]], workers: int,
                     simulate_fn: Optional[Callable] = None, frames: int = 3
                     ) -> Tuple[float, float]:
    """Time a short run (``frames`` motion frames; frame 0 is the initial state, so
    ``frames - 1`` simulated ones) of the item with the largest garment resolution in
    ``items``, in this process with one thread, and extrapolate:
    ``sum(T - 1) * seconds_per_frame / workers``.  Returns ``(estimate_s,
    seconds_per_frame)``.  Ignores per-item setup and worker start-up; over-estimates for
    garments smaller than the calibration one."""
    if not items:
        return 0.0, 0.0

    def res(it):
        r = it["garment"]["resolution"]
        return RESOLUTIONS[r] if isinstance(r, str) else int(r)

    probe = max(items, key=res)
    sim = simulate_fn or default_simulate(probe.get("engine", "torch"))
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        garment, body, motion, material = build_inputs(probe, num_frames=frames)
        settings = (item_settings if simulate_fn is None else plain_settings)(probe)
        t0 = time.perf_counter()
        sim(garment, body, motion, material, settings=settings, progress=None)
        per_frame = (time.perf_counter() - t0) / max(1, frames - 1)
    finally:
        torch.set_num_threads(n_threads)
    if probe.get("engine", "torch") == "blender":  # pre-roll frames and worker start-up count
        preroll = int(probe["settings"].get("preroll_frames", 0))
        per_frame *= (frames - 1) / (frames + preroll)
        total_frames = sum(it["motion"]["num_frames"] + preroll for it in items)
    else:
        total_frames = sum(max(1, it["motion"]["num_frames"] - 1) for it in items)
    return total_frames * per_frame / max(1, workers), per_frame


# --------------------------------------------------------------------------- driver
@dataclass
class Summary:
    total: int
    done: int = 0
    skipped: int = 0
    failed: int = 0
    pending: int = 0
    seconds: float = 0.0
    failures: List[str] = field(default_factory=list)
    #: the manifest's :func:`garmentgnn.data.store.content_sha256` after the run
    content_sha256: Optional[str] = None

    def __str__(self) -> str:
        s = (f"{self.total} items: {self.done} simulated, {self.skipped} skipped (already "
             f"done), {self.failed} failed, {self.pending} pending; {self.seconds:.1f} s"
             f"\ndataset content SHA-256: {self.content_sha256}")
        for f in self.failures[:10]:
            s += f"\n  FAILED {f}"
        return s


class SpecMismatch(RuntimeError):
    pass


def _load_existing(out: Path, spec_json: Dict[str, Any], force: bool = False
                   ) -> Dict[str, Dict[str, Any]]:
    """Check ``OUT/spec.json`` (or, without it, ``OUT/manifest.json``) and the sequence
    files under ``OUT/sequences`` (:func:`store.foreign_sequence_files`) hold this
    dataset; return previous manifest records by id.  ``force``: replace another
    dataset's spec instead of refusing (its files' records stay in the manifest)."""
    spec_path = out / store.SPEC
    ids = [it["id"] for it in spec_json["items"]]
    if force:
        store.atomic_write_json(spec_path, spec_json)
    elif not spec_path.exists() and (out / store.MANIFEST).exists():
        try:
            other = [r["id"] for r in store.read_manifest(out)["items"]]
        except (ValueError, KeyError, TypeError):
            other = None
        if other is None or not set(other) <= set(ids):
            raise SpecMismatch(f"{out} holds another dataset's {store.MANIFEST}; use another "
                               f"--out, or --force to overwrite it")
    accepted: set = set()
    if spec_path.exists():
        old = store.read_json(spec_path, "--force to overwrite it")
        if [it.get("id") for it in old.get("items", [])] != ids:
            changed = _changed_files(old.get("items", []), spec_json["items"])
            why = "".join(f"; {p} changed since it was made (SHA-256 {new[:12]}, the "
                          f"dataset's {was[:12]}), and a changed file is another dataset"
                          for p, was, new in changed[:3])
            raise SpecMismatch(
                f"{out} holds a different dataset (spec {old.get('name')!r}, seed "
                f"{old.get('seed')}){why}; use another --out, or --force to overwrite it")
        # another dataset's files kept by an earlier --force (a manifest of this spec's)
        accepted = store.listed_ok(out, spec_json["items"])
    if not force:  # sequence files of another dataset, whatever spec or manifest is there
        foreign = store.foreign_sequence_files(out, spec_json["items"], accepted)
        if foreign:
            raise SpecMismatch(store.foreign_message(
                out, foreign, f"the one being generated ({spec_json.get('name')!r}, seed "
                f"{spec_json.get('seed')}, engine {spec_json.get('engine')})",
                "nothing was written"))
    if not spec_path.exists():
        store.atomic_write_json(spec_path, spec_json)
    prev = {}
    if (out / store.MANIFEST).exists():
        try:
            prev = {r["id"]: r for r in store.read_manifest(out)["items"]}
        except (ValueError, KeyError):
            prev = {}
    return prev


def generate(spec: Spec, out, workers: int = 1, limit: Optional[int] = None,
             simulate_fn: Optional[Callable] = None, settings_fn: Optional[Callable] = None,
             retry_failed: bool = False, progress: bool = True, estimate: bool = False,
             log: Optional[Callable[[str], None]] = None, force: bool = False,
             backend: str = "local", address: Optional[str] = None) -> Summary:
    """Generate (or resume generating) ``spec`` into ``out``.

    Items whose sequence file exists and validates are skipped; failed items are kept
    as failed unless ``retry_failed``.  ``workers=0`` runs in this process (debugging,
    tests); ``workers>=1`` uses a spawn-context process pool, one torch thread each.
    ``limit``: simulate at most this many (pending) items in this call.
    ``simulate_fn``/``settings_fn``: dependency injection for tests (picklable,
    module-level callables); default ``garmentgnn.sim.simulate`` / ``SimSettings``.
    The manifest is rewritten atomically after every finished item.  A folder holding
    another dataset raises :class:`SpecMismatch` unless ``force``.  Pool workers end
    when this process does, even when it is killed with ``SIGKILL``.
    ``backend="ray"`` runs one Ray task per item instead (:mod:`garmentgnn.data.ray_backend`;
    ``workers`` CPUs of a local cluster, or the cluster at ``address``; ``address``
    without ``backend="ray"``, negative ``workers`` or ``limit`` are a ``ValueError``).
    The run holds :func:`output_lock` on ``out``: a second run into the same folder
    is refused while this one works.
    """
    if backend not in ("local", "ray"):
        raise ValueError(f"`backend`: 'local' or 'ray', got {backend!r}")
    if address is not None and backend != "ray":
        raise ValueError(f"`address`: {address!r} names a Ray cluster, which only "
                         f"backend='ray' joins; add --backend ray, or drop --address")
    if not isinstance(workers, int) or workers < 0:
        raise ValueError(f"`workers`: expected 0 (in this process) or more worker "
                         f"processes, got {workers!r}")
    if limit is not None and (not isinstance(limit, int) or limit < 0):
        raise ValueError(f"`limit`: expected 0 or more items to simulate in this run, got "
                         f"{limit!r}; leave it out to simulate every pending item")
    if not str(out).strip():
        raise ValueError("`out`: empty path; name the output folder, e.g. --out data/tiny")
    if Path(out).exists() and not Path(out).is_dir():
        raise ValueError(f"`out`: {out} is a file; name a folder for the dataset")
    if spec.engine == "blender" and simulate_fn is None:
        require_blender()  # before any file is written: say how to install `bpy`
    Path(out, store.SEQUENCES).mkdir(parents=True, exist_ok=True)
    with output_lock(out):
        return _generate(spec, Path(out), workers, limit, simulate_fn, settings_fn,
                         retry_failed, progress, estimate, log, force, backend, address)


#: the lock file a running ``generate`` holds in its output folder
LOCK = ".generate.lock"


@contextlib.contextmanager
def output_lock(out) -> Iterator[None]:
    """An exclusive ``flock`` on ``OUT/.generate.lock`` for the duration: a second run
    into the same folder is refused (``RuntimeError`` naming the folder and the other
    run's pid) instead of simulating the same items.  The kernel drops the lock when the
    holder ends, even by ``SIGKILL``, so a stale lock file never blocks a resume."""
    try:
        import fcntl  # noqa: PLC0415 (POSIX only)
    except ImportError:  # no flock (Windows): no lock
        yield
        return
    path = Path(out) / LOCK
    with open(path, "a+") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            pid = f.read().strip() or "?"
            raise RuntimeError(f"--out {out}: another `garmentgnn generate` (pid {pid}) is "
                               f"writing to this folder; wait for it to finish (rerun then "
                               f"to resume), or use another --out") from None
        try:
            f.seek(0)
            f.truncate()
            f.write(f"{os.getpid()}\n")
            f.flush()
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _generate(spec: Spec, out: Path, workers: int, limit: Optional[int],
              simulate_fn: Optional[Callable], settings_fn: Optional[Callable],
              retry_failed: bool, progress: bool, estimate: bool,
              log: Optional[Callable[[str], None]], force: bool, backend: str,
              address: Optional[str]) -> Summary:
    t_start = time.perf_counter()
    if log is None:
        def log(msg: str) -> None:
            print(msg, flush=True)
    store.remove_stale_temporaries(out)
    store.remove_stale_temporaries(out / store.SEQUENCES)
    spec_json = spec.to_json()
    items = spec_json["items"]
    prev = _load_existing(out, spec_json, force)
    header = {k: v for k, v in spec_json.items() if k != "items"}
    header["code"] = store.code_version()
    header["engine"] = engine_info(spec.engine, spec.settings)

    records: Dict[str, Dict[str, Any]] = {}
    todo: List[Dict[str, Any]] = []
    summary = Summary(total=len(items))
    for it in items:
        path = out / store.SEQUENCES / f"{it['id']}.npz"
        old = prev.get(it["id"])
        if path.exists():
            msg = store.validate_sequence(path, it["id"])
            if msg is None and old and old.get("sha256") \
                    and store.file_sha256(path) != old["sha256"]:
                msg = "SHA-256 differs from the manifest's"
            if msg is None:
                records[it["id"]] = (old if old and old.get("status") == "ok"
                                     else dict(store.record_from_meta(store.read_meta(path)),
                                               sha256=store.file_sha256(path)))
                summary.skipped += 1
                continue
            log(f"warning: {path.name} is invalid ({msg}); simulating it again")
            path.unlink()
        if old and old.get("status") == "failed" and not retry_failed:
            records[it["id"]] = old
            summary.skipped += 1
            summary.failed += 1
            summary.failures.append(f"{it['id']}: {old.get('message', '').splitlines()[:1]}")
            continue
        records[it["id"]] = store.pending_record(it)
        todo.append(it)
    if limit is not None:
        todo = todo[:limit]
    # another dataset's files (kept with --force, now or before): listed after this
    # spec's items, so no record of a file that exists is dropped
    outside = store.outside_records(out, records, prev)
    if outside:
        log(f"warning: {len(outside)} sequence file(s) of another dataset in {out} are "
            f"listed in the manifest beside this dataset's (kept by --force)")

    def flush():
        store.write_manifest(out, [records[it["id"]] for it in items] + outside, header)

    flush()
    if estimate and todo:
        est, per = estimate_seconds(todo, max(1, workers), simulate_fn)
        log(f"estimate: {len(todo)} items, "
            f"{sum(i['motion']['num_frames'] - 1 for i in todo)} simulated frames at "
            f"{per:.3f} s/frame on {max(1, workers)} worker(s) -> ~{est / 60:.1f} min")

    bar = None
    if progress and todo:
        bar = tqdm(total=len(todo), desc=f"generate {spec.name}", unit="seq",
                   file=sys.stderr)

    def finish(rec):
        records[rec["id"]] = rec
        if rec["status"] == "ok":
            summary.done += 1
        else:
            summary.failed += 1
            summary.failures.append(f"{rec['id']}: {rec['message'].splitlines()[0]}")
        flush()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(failed=summary.failed)

    try:
        if backend == "ray":
            run_on_ray(todo, str(out), finish, simulate_fn, settings_fn, workers=workers,
                       address=address)
        elif workers <= 0:
            n_threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                for it in todo:
                    finish(run_item(it, str(out), simulate_fn, settings_fn))
            finally:
                torch.set_num_threads(n_threads)
        else:
            ctx = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=ctx,
                                     initializer=init_worker,
                                     initargs=(os.getpid(),)) as pool:
                pending = {pool.submit(run_item, it, str(out), simulate_fn, settings_fn)
                           for it in todo}
                try:
                    while pending:
                        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for fut in finished:
                            finish(fut.result())
                except BaseException:
                    for fut in pending:
                        fut.cancel()
                    raise
    except BrokenProcessPool as e:
        raise RuntimeError(f"a worker process died ({e}); finished items are saved in "
                           f"{out}; rerun the same command to resume") from e
    finally:
        if bar is not None:
            bar.close()
        flush()
        summary.seconds = time.perf_counter() - t_start
        summary.pending = sum(r["status"] == "pending" for r in records.values())
        summary.content_sha256 = store.content_sha256(list(records.values()) + outside)
    return summary
