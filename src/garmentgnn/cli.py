"""Command line: ``garmentgnn generate ...``, ``garmentgnn export ...``,
``garmentgnn manifest ...``, ``garmentgnn show ...`` (see :mod:`garmentgnn.viz`),
``garmentgnn train ...`` (Lightning's CLI, see
:mod:`garmentgnn.training.lightning_cli`), ``garmentgnn bench ...`` (see
:mod:`garmentgnn.bench`) (also ``python -m garmentgnn.cli``)."""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from typing import List, Optional


def _import_callable(spec: str):
    mod, _, attr = spec.partition(":")
    try:
        fn = getattr(importlib.import_module(mod), attr)
    except (ImportError, AttributeError, ValueError, TypeError) as exc:
        raise ValueError(f"--simulate-fn {spec!r}: cannot import it ({exc}); give "
                         f"module:function") from None
    if not callable(fn):
        raise ValueError(f"--simulate-fn {spec!r}: not a function; give module:function")
    return fn


def _path(text: str) -> str:
    """An argparse type: a non-empty path (``--out ""`` would write into the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path; name a folder or file")
    return text


def build_parser() -> argparse.ArgumentParser:
    import garmentgnn
    from garmentgnn.data.generate import ENGINES, PRESETS
    p = argparse.ArgumentParser(prog="garmentgnn", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"garmentgnn {garmentgnn.__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="simulate a dataset preset into a folder (resumable)")
    g.add_argument("--preset", choices=PRESETS, default="tiny")
    g.add_argument("--engine", choices=("auto",) + ENGINES, default="auto",
                   help="simulation engine: Blender's cloth (run in worker processes) or the "
                        "torch reference simulator; auto = blender where `bpy` is installed")
    g.add_argument("--out", default=None, type=_path,
                   help="output folder (rerun to resume); default $GARMENTGNN_DATA_DIR/"
                        "<preset>-<engine>, $GARMENTGNN_DATA_DIR defaulting to "
                        "~/.cache/garmentgnn/datasets")
    g.add_argument("--force", action="store_true",
                   help="overwrite the spec and manifest of another dataset in --out")
    g.add_argument("--workers", type=int, default=1,
                   help="worker processes (0 = in this process); default 1")
    g.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local worker processes, or one Ray task per sequence")
    g.add_argument("--address", default=None,
                   help="with --backend ray: the cluster to join (HOST:PORT); default a "
                        "local cluster of --workers CPUs")
    g.add_argument("--seed", type=int, default=0, help="base seed of the spec (default 0)")
    g.add_argument("--limit", type=int, default=None,
                   help="simulate at most N pending items in this run")
    g.add_argument("--retry-failed", action="store_true",
                   help="simulate items recorded as failed again")
    g.add_argument("--estimate", action=argparse.BooleanOptionalAction, default=True,
                   help="time a 4-frame calibration run and print a duration estimate first")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    # test hook: module:function replacing garmentgnn.sim.simulate
    g.add_argument("--simulate-fn", default=None, help=argparse.SUPPRESS)

    e = sub.add_parser("export", help="export a sequence file as PC2, an OBJ sequence or glTF")
    e.add_argument("--seq", required=True, type=_path, help="OUT/sequences/<id>.npz")
    e.add_argument("--format", choices=("pc2", "obj", "gltf"), required=True)
    e.add_argument("--out", required=True, type=_path,
                   help="the .pc2 / .glb file, or a folder for OBJs")
    e.add_argument("--no-body", action="store_true", help="glTF: the garment only")
    e.add_argument("--start-frame", type=float, default=0.0, help="PC2 start frame")

    m = sub.add_parser("manifest", help="rebuild OUT/manifest.json from the sequence files")
    m.add_argument("--out", required=True, type=_path, help="the dataset folder")
    from garmentgnn.bench.cli import add_parser as add_bench_parser
    add_bench_parser(sub)
    from garmentgnn.viz.cli import add_parser as add_show_parser
    add_show_parser(sub)
    t = sub.add_parser("train", help="LightningCLI: garmentgnn train fit --config "
                       "gartrans --data.root DIR (see `garmentgnn train --help`)",
                       add_help=False)
    t.add_argument("lightning_args", nargs=argparse.REMAINDER)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["train"]:  # everything after `train` belongs to LightningCLI
        from garmentgnn.data.store import IntegrityError
        from garmentgnn.training.integrity import CheckpointError
        from garmentgnn.training.lightning_cli import main as train_main
        saved = sys.argv
        sys.argv = [f"{Path(saved[0]).name} train"] + argv[1:]  # LightningCLI reads argv
        try:
            train_main()
        except (FileNotFoundError, IntegrityError, CheckpointError) as exc:
            print(f"error: {exc}", file=sys.stderr)  # one line: the path and the fix
            return 2
        finally:
            sys.argv = saved
        return 0
    args = build_parser().parse_args(argv)
    if args.command == "generate":
        from garmentgnn.data.generate import SpecMismatch, generate, preset
        try:
            sim = _import_callable(args.simulate_fn) if args.simulate_fn else None
            spec = preset(args.preset, seed=args.seed, engine=args.engine)
            out = args.out
            if out is None:
                from garmentgnn.data.store import data_root
                out = data_root() / f"{spec.name}-{spec.engine}"
                print(f"writing to {out}", flush=True)
            summary = generate(spec, out, workers=args.workers, limit=args.limit,
                               simulate_fn=sim, retry_failed=args.retry_failed,
                               progress=not args.no_progress, estimate=args.estimate,
                               force=args.force, backend=args.backend, address=args.address)
        except (SpecMismatch, ValueError, RuntimeError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(summary)
        return 1 if summary.failed else 0
    if args.command == "bench":
        from garmentgnn.bench.cli import main as bench_main
        return bench_main(args)
    if args.command == "show":
        from garmentgnn.viz.cli import main as show_main
        return show_main(args)
    if args.command == "export":
        from garmentgnn.data.store import export_sequence
        if not Path(args.seq).is_file():
            print(f"error: --seq {args.seq}: no such file (a sequences/<id>.npz of a "
                  f"dataset made by `garmentgnn generate`)", file=sys.stderr)
            return 2
        try:
            paths = export_sequence(args.seq, args.format, args.out,
                                    start_frame=args.start_frame, body=not args.no_body)
        except (ValueError, KeyError, OSError) as exc:
            print(f"error: --seq {args.seq}: not a readable sequence file ({exc})",
                  file=sys.stderr)
            return 2
        print(f"wrote {len(paths)} file(s): {paths[0]}" + (" ..." if len(paths) > 1 else ""))
        return 0
    if args.command == "manifest":
        from garmentgnn.data.store import SEQUENCES, rebuild_manifest
        if not (Path(args.out) / SEQUENCES).is_dir():
            what = "no such folder" if not Path(args.out).is_dir() else f"no {SEQUENCES}/ in it"
            print(f"error: --out {args.out}: {what}; a dataset folder is made by "
                  f"`garmentgnn generate --out {args.out}`", file=sys.stderr)
            return 2
        try:
            doc = rebuild_manifest(args.out)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        print(f"rebuilt {args.out}/manifest.json: {doc['counts']}")
        return 0
    return 2


if __name__ == "__main__":
    sys.exit(main())
