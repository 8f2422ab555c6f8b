"""Command line: ``garmentgnn generate ...``, ``garmentgnn export ...``,
``garmentgnn manifest ...``, ``garmentgnn show ...`` (see :mod:`garmentgnn.viz`),
``garmentgnn train ...`` (Lightning's CLI, see
:mod:`garmentgnn.training.lightning_cli`), ``garmentgnn bench ...`` (see
:mod:`garmentgnn.bench`) (also ``python -m garmentgnn.cli``).

Each sub-command is a pair ``add_parser(subparsers)`` / ``main(args) -> exit status``
(:data:`COMMANDS`): the data commands are here, ``bench`` and ``show`` in their
packages' ``cli`` modules.  Nothing in the package imports this module."""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

from garmentgnn.bench import cli as bench_cli
from garmentgnn.viz import cli as viz_cli


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


def add_generate_parser(sub) -> argparse.ArgumentParser:
    """The ``generate`` sub-command: simulate a dataset preset into a folder."""
    from garmentgnn.data.presets import ENGINES, PRESETS
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
    return g


def generate_main(args: argparse.Namespace) -> int:
    """Generate (or resume) the preset; 1 when items failed, 2 for bad arguments."""
    from garmentgnn.data import SpecMismatch, generate, preset
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


def add_export_parser(sub) -> argparse.ArgumentParser:
    """The ``export`` sub-command: one sequence file as PC2, OBJs or glTF."""
    e = sub.add_parser("export", help="export a sequence file as PC2, an OBJ sequence, glTF, "
                       "Alembic or .blend (the last two through Blender's bpy)")
    e.add_argument("--seq", required=True, type=_path, help="OUT/sequences/<id>.npz")
    from garmentgnn.data.export import EXPORT_FORMATS
    e.add_argument("--format", choices=EXPORT_FORMATS, required=True)
    e.add_argument("--out", required=True, type=_path,
                   help="the .pc2 / .glb / .abc / .blend file, or a folder for OBJs")
    e.add_argument("--no-body", action="store_true",
                   help="glTF, Alembic, .blend: the garment only")
    e.add_argument("--start-frame", type=float, default=0.0, help="PC2 start frame")
    return e


def export_main(args: argparse.Namespace) -> int:
    """Export one sequence file; 2 when it is missing or unreadable."""
    from garmentgnn.data.export import export_sequence
    if not Path(args.seq).is_file():
        print(f"error: --seq {args.seq}: no such file (a sequences/<id>.npz of a "
              f"dataset made by `garmentgnn generate`)", file=sys.stderr)
        return 2
    if args.format in ("abc", "blend") and Path(args.out).suffix.lower() != f".{args.format}":
        print(f"error: --out {args.out}: --format {args.format} writes a file whose "
              f"name must end in .{args.format}", file=sys.stderr)
        return 2
    try:
        paths = export_sequence(args.seq, args.format, args.out,
                                start_frame=args.start_frame, body=not args.no_body)
    except (ValueError, KeyError, OSError) as exc:
        print(f"error: --seq {args.seq}: not a readable sequence file ({exc})",
              file=sys.stderr)
        return 2
    except RuntimeError as exc:  # Blender missing or failed (abc, blend)
        print(f"error: --format {args.format}: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} file(s): {paths[0]}" + (" ..." if len(paths) > 1 else ""))
    return 0


def add_manifest_parser(sub) -> argparse.ArgumentParser:
    """The ``manifest`` sub-command: rebuild a dataset's manifest from its files."""
    m = sub.add_parser("manifest", help="rebuild OUT/manifest.json from the sequence files")
    m.add_argument("--out", required=True, type=_path, help="the dataset folder")
    return m


def manifest_main(args: argparse.Namespace) -> int:
    """Rebuild the manifest from the sequence files; 2 when the folder is no dataset."""
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
    print(f"rebuilt {args.out}/manifest.json: {doc['counts']}\n"
          f"dataset content SHA-256: {doc['content_sha256']}")
    return 0


def add_train_parser(sub) -> argparse.ArgumentParser:
    """The ``train`` sub-command: every argument after it goes to LightningCLI."""
    t = sub.add_parser("train", help="LightningCLI: garmentgnn train fit --config "
                       "gartrans --data.root DIR (see `garmentgnn train --help`)",
                       add_help=False)
    t.add_argument("lightning_args", nargs=argparse.REMAINDER)
    return t


def train_main(args: argparse.Namespace) -> int:
    """Run LightningCLI on ``args.lightning_args``; 2 (one line naming the file and the
    fix) for a missing or damaged dataset or checkpoint."""
    from garmentgnn.data.store import IntegrityError
    from garmentgnn.training.integrity import CheckpointError
    from garmentgnn.training.lightning_cli import main as lightning_main
    try:
        with warnings.catch_warnings():  # the args *are* the command line's, after `train`
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            lightning_main(args.lightning_args, prog="garmentgnn train")
    except (FileNotFoundError, IntegrityError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)  # one line: the path and the fix
        return 2
    return 0


#: sub-command -> (``add_parser(subparsers)``, ``main(args) -> exit status``)
COMMANDS: Dict[str, Tuple[Callable, Callable[[argparse.Namespace], int]]] = {
    "generate": (add_generate_parser, generate_main),
    "export": (add_export_parser, export_main),
    "manifest": (add_manifest_parser, manifest_main),
    "bench": (bench_cli.add_parser, bench_cli.main),
    "show": (viz_cli.add_parser, viz_cli.main),
    "train": (add_train_parser, train_main),
}


def build_parser() -> argparse.ArgumentParser:
    """The ``garmentgnn`` parser with every sub-command of :data:`COMMANDS`."""
    import garmentgnn
    p = argparse.ArgumentParser(prog="garmentgnn", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"garmentgnn {garmentgnn.__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add_parser, _ in COMMANDS.values():
        add_parser(sub)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and run its sub-command; the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["train"]:  # everything after `train` belongs to LightningCLI, --help too
        return train_main(argparse.Namespace(command="train", lightning_args=argv[1:]))
    args = build_parser().parse_args(argv)
    return COMMANDS[args.command][1](args)


if __name__ == "__main__":
    sys.exit(main())
