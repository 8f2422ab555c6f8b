"""Make the folder that ``benchmarks/gpu_window.sh`` reads on the GPU machine
(docs/bench.md, "A GPU window"): the packed datasets (:mod:`garmentgnn.data.compact`)
and the wheels the GPU image lacks, in ``build/gpu_window/`` (ignored by git; the device
tool carries it), sized so that it travels with the working tree under the tool's
64 MiB::

    python benchmarks/gpu_window_prepare.py                      # throughput-small only
    python benchmarks/gpu_window_prepare.py --train DATASET      # and a dataset to train on

It prints the sizes (also into ``prepare.json``: ``--out``, ``--commit``) and the ``run``
call.  ``throughput-small`` is made by
``python benchmarks/train_throughput.py --sizes small`` (once, in the benchmark cache).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any, Dict, List, Optional

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args, benchmark_cache,
                                  output_path)
from garmentgnn.data import compact

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from gpu_window import (CARRY_LIMIT, DIR, REPO, RESULTS, THROUGHPUT_PACK,  # noqa: E402
                        TRAIN_PACK, WHEELS)


def working_tree_bytes() -> int:
    """Bytes of what the device tool sends besides the carried paths: tracked files and
    untracked ones git does not ignore."""
    names = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                            "--exclude-standard"], cwd=REPO, capture_output=True,
                           check=True).stdout.decode().split("\0")
    return sum((REPO / n).stat().st_size for n in names if n and (REPO / n).is_file())


def download_wheels(folder: Path) -> Dict[str, Any]:
    """The wheels of :data:`WHEELS` at the versions installed here (CPython 3.12,
    manylinux x86-64: the GPU image's), into ``folder``; other versions there removed."""
    folder.mkdir(parents=True, exist_ok=True)
    want = {n: metadata.version(n) for n in WHEELS}
    prefixes = tuple(f"{n.replace('-', '_')}-{v}-" for n, v in want.items())
    for w in folder.glob("*.whl"):
        if not w.name.lower().startswith(tuple(p.lower() for p in prefixes)):
            w.unlink()
    missing = []
    for name, version in want.items():
        r = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps",
                            "--only-binary=:all:", "--python-version", "3.12",
                            "--implementation", "cp", "--platform", "manylinux_2_28_x86_64",
                            "--platform", "manylinux_2_17_x86_64", "--platform", "any",
                            "-d", str(folder), f"{name}=={version}"],
                           capture_output=True, text=True)
        if r.returncode != 0:
            missing.append(f"{name}=={version}: {r.stderr.strip().splitlines()[-1:]}")
    wheels = sorted(folder.glob("*.whl"))
    return {"wheels": [w.name for w in wheels], "bytes": sum(w.stat().st_size for w in wheels),
            "missing": missing}


def folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def prepare(a: argparse.Namespace) -> int:
    d = Path(a.dir)
    d.mkdir(parents=True, exist_ok=True)
    info: Dict[str, Any] = {"wheels": download_wheels(d / "wheels") if a.wheels else None}
    for name in (THROUGHPUT_PACK, TRAIN_PACK):
        (d / name).unlink(missing_ok=True)
    tree = working_tree_bytes()
    room = min(int(a.max_mb * 1e6), CARRY_LIMIT - tree - folder_bytes(d) - 2 ** 20)
    for key, src, name in (("throughput", a.throughput, THROUGHPUT_PACK),
                           ("train", a.train, TRAIN_PACK)):
        if src is None:
            continue
        if not (Path(src) / "manifest.json").is_file():
            print(f"error: --{key} {src}: no dataset there (manifest.json); make it with "
                  + ("`python benchmarks/train_throughput.py --sizes small`" if key ==
                     "throughput" else "`garmentgnn generate`"), file=sys.stderr)
            return 2
        res = compact.pack(src, d / name, max_bytes=room)
        room -= res.bytes
        info[key] = {"file": name, "bytes": res.bytes, "sequences": len(res.sequences),
                     "left_out": res.left_out, "splits": res.splits,
                     "max_position_error_m": res.max_position_error_m,
                     "source_content_sha256": res.source_content_sha256,
                     "missing_bodies": res.missing_bodies}
    info.update(working_tree_bytes=tree, carried_bytes=folder_bytes(d),
                total_bytes=tree + folder_bytes(d), limit_bytes=CARRY_LIMIT)
    text = json.dumps(info, indent=1)
    print(text)
    out = output_path(a, RESULTS)
    out.mkdir(parents=True, exist_ok=True)
    (out / "prepare.json").write_text(text + "\n")
    print(f"carry {d.relative_to(REPO) if d.is_relative_to(REPO) else d}: "
          f"{info['carried_bytes'] / 2 ** 20:.1f} MiB, with the working tree "
          f"{info['total_bytes'] / 2 ** 20:.1f} of {CARRY_LIMIT / 2 ** 20:.0f} MiB\n"
          "run: command 'bash benchmarks/gpu_window.sh', carry ['build/gpu_window'], "
          "timeout_s 600")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--dir", default=str(DIR), help="the folder to carry")
    ap.add_argument("--throughput", default=str(benchmark_cache() / "throughput-small"),
                    help="the training-throughput dataset (train_throughput.py --sizes small)")
    ap.add_argument("--train", default=None,
                    help="a dataset to train on (default: the throughput dataset)")
    ap.add_argument("--max-mb", type=float, default=40.0,
                    help="MB (10^6 bytes) of packed datasets at most; less where the "
                         "device's 64 MiB would be exceeded")
    ap.add_argument("--no-wheels", dest="wheels", action="store_false",
                    help="keep the wheels folder as it is")
    add_output_args(ap, RESULTS, "the folder for prepare.json (the sizes printed)")
    a = ap.parse_args(argv)
    if not a.max_mb > 0:
        ap.error(f"--max-mb: expected a positive size, got {a.max_mb}")
    return prepare(a)


if __name__ == "__main__":
    sys.exit(main())
