"""Command line: ``garmentgnn generate ...``, ``garmentgnn export ...``,
``garmentgnn manifest ...``, ``garmentgnn show ...`` (see :mod:`garmentgnn.viz`),
``garmentgnn predict ...`` (see :mod:`garmentgnn.inference`),
``garmentgnn train ...`` (Lightning's CLI, see
:mod:`garmentgnn.training.lightning_cli`), ``garmentgnn bench ...`` (see
:mod:`garmentgnn.bench`), ``garmentgnn sweep ...`` (see :mod:`garmentgnn.bench.sweep`)
(also ``python -m garmentgnn.cli``).

Each sub-command is a pair ``add_parser(subparsers)`` / ``main(args) -> exit status``
(:data:`COMMANDS`): the data commands are here, ``bench``, ``sweep`` and ``show`` in
their packages' ``cli`` modules.  Nothing in the package imports this module.

Every failure of every sub-command ends in one ``error: ...`` line naming the flag (and
the fix) and a non-zero exit status (:func:`run_command`); ``--debug`` before the
sub-command, or ``GARMENTGNN_DEBUG=1``, shows the traceback instead."""
from __future__ import annotations

import argparse
import importlib
import os
import shlex
import sys
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import garmentgnn
from garmentgnn._argparse import ArgumentParser, HelpFormatter, finite_float, nonempty_path
from garmentgnn.bench import cli as bench_cli
from garmentgnn.bench import sweep_cli
from garmentgnn.inference import cli as inference_cli
from garmentgnn.data import SpecMismatch, generate, preset
from garmentgnn.data.ensemble import ENSEMBLE_SEQUENCES, generate_ensemble
from garmentgnn.data.perturb import PERTURB_M
from garmentgnn.data.export import EXPORT_FORMATS, export_sequence
from garmentgnn.data.presets import ENGINES, PRESETS
from garmentgnn.data.spec_file import load_spec
from garmentgnn.data.store import (SEQUENCES, IntegrityError, data_root, read_manifest,
                                   rebuild_manifest)
from garmentgnn.training.integrity import CheckpointError
from garmentgnn.training.lightning_cli import main as lightning_main
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


_path = nonempty_path  # an argparse type: --out "" would write into the current folder


def add_generate_parser(sub) -> argparse.ArgumentParser:
    """The ``generate`` sub-command: simulate a dataset preset or spec into a folder."""
    g = sub.add_parser("generate", help="simulate a dataset preset or spec file into a folder "
                       "(resumable)",
                       description="Simulate a dataset preset, or a spec file of your own "
                       "garments and motions, into a folder: one sequence file per item and "
                       "a manifest; rerun to resume.",
                       formatter_class=HelpFormatter)
    which = g.add_mutually_exclusive_group()
    which.add_argument("--preset", choices=PRESETS, default=None,
                       help="dataset preset (default tiny)")
    which.add_argument("--spec", type=_path, default=None,
                       help="a YAML dataset spec: your garment meshes and BVH motions, "
                            "templates, generators (docs/own_garment.md)")
    g.add_argument("--engine", choices=("auto",) + ENGINES, default=None,
                   help="simulation engine: Blender's cloth (run in worker processes) or the "
                        "torch reference simulator; auto = blender where `bpy` is installed "
                        "(default: the spec's, else auto)")
    g.add_argument("--out", default=None, type=_path,
                   help="output folder (rerun to resume); default $GARMENTGNN_DATA_DIR/"
                        "<preset>-<engine>, $GARMENTGNN_DATA_DIR defaulting to "
                        "~/.cache/garmentgnn/datasets")
    g.add_argument("--force", action="store_true",
                   help="overwrite the spec of another dataset in --out (the records of its "
                        "sequence files stay in the manifest)")
    g.add_argument("--workers", type=int, default=1,
                   help="worker processes (0 = in this process)")
    g.add_argument("--backend", choices=("local", "ray"), default="local",
                   help="local worker processes, or one Ray task per sequence")
    g.add_argument("--address", default=None,
                   help="with --backend ray: the cluster to join (HOST:PORT); default a "
                        "local cluster of --workers CPUs")
    g.add_argument("--seed", type=int, default=None,
                   help="base seed of the spec (default: the spec file's, else 0)")
    g.add_argument("--limit", type=int, default=None,
                   help="simulate at most N pending items in this run (default: all)")
    g.add_argument("--retry-failed", action="store_true",
                   help="simulate items recorded as failed again")
    g.add_argument("--estimate", action=argparse.BooleanOptionalAction, default=True,
                   help="time a 4-frame calibration run and print a duration estimate first")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--ensemble", type=int, default=None, metavar="K",
                   help="instead of a dataset: K members of some of the dataset in --out's "
                        "test sequences, each simulated again with its rest garment moved "
                        f"by {PERTURB_M:g} m, into OUT/ensemble (an ensemble ground truth, "
                        "docs/dataset.md; rerun to resume)")
    g.add_argument("--sequences", type=int, default=None, metavar="N",
                   help=f"with --ensemble: how many test sequences (default "
                        f"{ENSEMBLE_SEQUENCES}, spread over held-out groups and garment kinds)")
    # test hook: module:function replacing garmentgnn.sim.simulate
    g.add_argument("--simulate-fn", default=None, help=argparse.SUPPRESS)
    return g


def generate_main(args: argparse.Namespace) -> int:
    """Generate (or resume) the preset; 1 when items failed, 2 for bad arguments."""
    out = args.out
    try:
        sim = _import_callable(args.simulate_fn) if args.simulate_fn else None
        if args.ensemble is not None or args.sequences is not None:
            return _ensemble_main(args, sim)
        if args.spec is not None:
            spec = load_spec(args.spec, engine=args.engine, seed=args.seed)
        else:
            spec = preset(args.preset or "tiny", seed=args.seed or 0,
                          engine=args.engine or "auto")
        out = args.out
        if out is None:
            out = data_root() / f"{spec.name}-{spec.engine}"
            print(f"writing to {out}", flush=True)
        summary = generate(spec, out, workers=args.workers, limit=args.limit,
                           simulate_fn=sim, retry_failed=args.retry_failed,
                           progress=not args.no_progress, estimate=args.estimate,
                           force=args.force, backend=args.backend, address=args.address)
    except (SpecMismatch, ValueError, RuntimeError) as exc:
        print(f"error: {_with_flag(_flag_message(str(exc), args), args)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted(out, args)
    print(summary)
    return 1 if summary.failed else 0


def _ensemble_main(args: argparse.Namespace, sim) -> int:
    """``generate --ensemble K``: the members of the dataset in ``--out``."""
    if args.ensemble is None:
        raise ValueError("--sequences: only with --ensemble K (the members per sequence)")
    given = [f for f, v in (("--preset", args.preset), ("--spec", args.spec),
                            ("--engine", args.engine), ("--seed", args.seed)) if v is not None]
    if given or args.force:
        raise ValueError(f"{(given or ['--force'])[0]}: --ensemble simulates the dataset in "
                         f"--out again with its own spec, engine and seed; drop it")
    if args.out is None:
        raise ValueError("--ensemble: name the dataset folder with --out")
    summary = generate_ensemble(
        args.out, args.ensemble, args.sequences or ENSEMBLE_SEQUENCES, workers=args.workers,
        limit=args.limit, simulate_fn=sim, retry_failed=args.retry_failed,
        progress=not args.no_progress, estimate=args.estimate, backend=args.backend,
        address=args.address)
    print(summary)
    return 1 if summary.failed else 0


def _interrupted(out, args: argparse.Namespace) -> int:
    """Ctrl-C during ``generate``: what was kept and the command that resumes (130)."""
    try:
        counts = read_manifest(out)["counts"] if out is not None else {}
    except (OSError, ValueError):
        counts = {}
    kept = counts.get("ok", 0)
    total = sum(counts.values())
    argv = getattr(args, "argv", None) or ["generate", "--out", str(out)]
    print(f"\ninterrupted: {kept} of {total} sequences are saved in {out} (finished items "
          f"are never lost); resume with: garmentgnn {shlex.join(argv)}", file=sys.stderr)
    return 130



def add_export_parser(sub) -> argparse.ArgumentParser:
    """The ``export`` sub-command: one sequence file as PC2, OBJs or glTF."""
    e = sub.add_parser("export", help="export a sequence file as PC2, an OBJ sequence, glTF, "
                       "Alembic or .blend (the last two through Blender's bpy)",
                       description="Export one sequence file of a generated dataset "
                       "(OUT/sequences/<id>.npz): the garment's per-frame positions as PC2 "
                       "point caches, one OBJ per frame, an animated glTF (.glb, with the "
                       "body), or through Blender's bpy an Alembic (.abc) or .blend scene "
                       "whose frame rate is the sequence's.",
                       formatter_class=HelpFormatter)
    e.add_argument("--seq", required=True, type=_path, help="OUT/sequences/<id>.npz")
    e.add_argument("--format", choices=EXPORT_FORMATS, required=True,
                   help="file format; abc keeps time in seconds: import it into a scene at "
                        "the sequence's fps (Blender's default is 24), the .blend opens at it")
    e.add_argument("--out", required=True, type=_path,
                   help="the .pc2 / .glb / .abc / .blend file, or a folder for OBJs")
    e.add_argument("--no-body", action="store_true",
                   help="glTF, Alembic, .blend: the garment only")
    e.add_argument("--start-frame", type=finite_float, default=None,
                   help="PC2: the frame number of the first sample (default 0)")
    return e


def export_main(args: argparse.Namespace) -> int:
    """Export one sequence file; 2 when it is missing or unreadable."""
    if not Path(args.seq).is_file():
        print(f"error: --seq {args.seq}: no such file (a sequences/<id>.npz of a "
              f"dataset made by `garmentgnn generate`)", file=sys.stderr)
        return 2
    if args.start_frame is not None and args.format != "pc2":
        print(f"error: --start-frame: only --format pc2 stores a start frame; drop it for "
              f"--format {args.format}", file=sys.stderr)
        return 2
    if args.no_body and args.format in ("pc2", "obj"):
        print(f"error: --no-body: --format {args.format} holds the garment only; drop it",
              file=sys.stderr)
        return 2
    try:
        paths = export_sequence(args.seq, args.format, args.out,
                                start_frame=args.start_frame or 0.0, body=not args.no_body)
    except (ValueError, KeyError) as exc:
        msg = _flag_message(str(exc), args)
        if msg.startswith("--") and not msg.startswith("--seq"):  # about another flag
            print(f"error: {msg}", file=sys.stderr)
        else:
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
    m = sub.add_parser("manifest", help="rebuild OUT/manifest.json from the sequence files",
                       description="Rebuild a dataset's manifest.json from its sequence "
                       "files.", formatter_class=HelpFormatter)
    m.add_argument("--out", required=True, type=_path, help="the dataset folder")
    m.add_argument("--force", action="store_true",
                   help="list sequence files of another dataset than OUT/spec.json "
                        "describes too (refused without it)")
    return m


def manifest_main(args: argparse.Namespace) -> int:
    """Rebuild the manifest from the sequence files; 2 when the folder is no dataset."""
    if not (Path(args.out) / SEQUENCES).is_dir():
        what = "no such folder" if not Path(args.out).is_dir() else f"no {SEQUENCES}/ in it"
        print(f"error: --out {args.out}: {what}; a dataset folder is made by "
              f"`garmentgnn generate --out {args.out}`", file=sys.stderr)
        return 2
    try:
        doc = rebuild_manifest(args.out, force=args.force)
    except ValueError as exc:
        print(f"error: {_with_flag(str(exc), args)}", file=sys.stderr)
        return 2
    print(f"rebuilt {args.out}/manifest.json: {doc['counts']}\n"
          f"dataset content SHA-256: {doc['content_sha256']}")
    for line in doc.get("invalid", []):
        print(f"invalid: {args.out}/sequences/{line}", file=sys.stderr)
    if doc.get("invalid"):
        print(f"error: --out {args.out}: {len(doc['invalid'])} sequence file(s) failed the "
              f"checks (listed above) and are counted as pending; delete them and rerun "
              f"`garmentgnn generate --out {args.out}` to simulate them again",
              file=sys.stderr)
        return 1
    return 0


def add_train_parser(sub) -> argparse.ArgumentParser:
    """The ``train`` sub-command: every argument after it goes to LightningCLI."""
    t = sub.add_parser("train", help="LightningCLI over every method: garmentgnn train "
                       "fit|validate|test|predict --config gartrans|ablations/NAME|"
                       "baselines/da|hood|ncs --data.root DIR (see `garmentgnn train --help`)",
                       add_help=False)
    t.add_argument("lightning_args", nargs=argparse.REMAINDER)
    return t


def train_main(args: argparse.Namespace) -> int:
    """Run LightningCLI on ``args.lightning_args``; 2 (one line naming the file and the
    fix) for a missing or damaged dataset or checkpoint."""
    try:
        with warnings.catch_warnings():  # the args *are* the command line's, after `train`
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            lightning_main(args.lightning_args, prog="garmentgnn train")
    except (FileNotFoundError, IntegrityError, CheckpointError) as exc:
        print(f"error: {_with_flag(str(exc), args)}", file=sys.stderr)  # the path, the fix
        return 2
    return 0


#: sub-command -> (``add_parser(subparsers)``, ``main(args) -> exit status``)
COMMANDS: Dict[str, Tuple[Callable, Callable[[argparse.Namespace], int]]] = {
    "generate": (add_generate_parser, generate_main),
    "export": (add_export_parser, export_main),
    "manifest": (add_manifest_parser, manifest_main),
    "bench": (bench_cli.add_parser, bench_cli.main),
    "sweep": (sweep_cli.add_parser, sweep_cli.main),
    "show": (viz_cli.add_parser, viz_cli.main),
    "predict": (inference_cli.add_parser, inference_cli.main),
    "train": (add_train_parser, train_main),
}


def build_parser() -> argparse.ArgumentParser:
    """The ``garmentgnn`` parser with every sub-command of :data:`COMMANDS`."""
    p = ArgumentParser(prog="garmentgnn", description=__doc__.splitlines()[0],
                       formatter_class=HelpFormatter)
    p.add_argument("--version", action="version", version=f"garmentgnn {garmentgnn.__version__}")
    p.add_argument("--debug", action="store_true",
                   help="show the full traceback of an error (also GARMENTGNN_DEBUG=1)")
    sub = p.add_subparsers(dest="command", required=True)
    for add_parser, _ in COMMANDS.values():
        add_parser(sub)
    return p


def _flags(args: argparse.Namespace) -> Dict[str, str]:
    """``--flag -> value`` of the parsed arguments (and of ``train``'s Lightning ones)."""
    given = {k: v for k, v in vars(args).items() if k not in ("command", "argv", "debug")}
    flags = {f"--{k.replace('_', '-')}": str(v) for k, v in given.items()
             if isinstance(v, (str, int, float, os.PathLike)) and not isinstance(v, bool)}
    for k, v in given.items():
        if isinstance(v, list) and k != "lightning_args":
            for item in v:
                flags.setdefault(f"--{k.replace('_', '-')}", str(item).split("=")[-1])
    rest = list(getattr(args, "lightning_args", None) or [])
    for i, a in enumerate(rest):
        if a.startswith("--") and "=" in a:
            flags[a.split("=", 1)[0]] = a.split("=", 1)[1]
        elif a.startswith("--") and i + 1 < len(rest) and not rest[i + 1].startswith("--"):
            flags[a] = rest[i + 1]
    return flags


def _flag_message(msg: str, args: argparse.Namespace) -> str:
    """``msg`` with a leading `` `name`: `` (the API's argument) turned into the flag
    ``--name`` when the sub-command has one."""
    if msg.startswith("`") and "`" in msg[1:]:
        name, rest = msg[1:].split("`", 1)
        flag = "--" + name.replace("_", "-")
        if flag in _flags(args):
            return flag + rest
        if getattr(args, "command", None) == "train" and name in _data_arguments():
            return f"--data.{name}" + rest  # given or not (a config's or the default)
    return msg


def _data_arguments() -> Tuple[str, ...]:
    """The arguments of the data module ``garmentgnn train`` configures (``--data.*``)."""
    import inspect  # noqa: PLC0415

    from garmentgnn.training.datamodule import GarmentDataModule  # noqa: PLC0415
    return tuple(inspect.signature(GarmentDataModule.__init__).parameters)[1:]


_OS_FIX = {PermissionError: "not writable (or readable) by you; pick another path",
           NotADirectoryError: "a file is in the way where a folder is needed; name a folder",
           FileExistsError: "a file is in the way where a folder is needed; name a folder",
           IsADirectoryError: "is a folder where a file is needed; name a file",
           FileNotFoundError: "no such file or folder"}


def _os_message(exc: OSError, args: argparse.Namespace) -> Optional[str]:
    """The flag whose path holds the file ``exc`` is about, the problem and the fix."""
    target = getattr(exc, "filename", None)
    if not target:
        return None
    target = Path(os.fspath(target)).absolute()
    for flag, value in _flags(args).items():
        try:
            path = Path(value).absolute()
        except (TypeError, ValueError):
            continue
        if path == target or path in target.parents or target in path.parents:
            fix = next((f for t, f in _OS_FIX.items() if isinstance(exc, t)), exc.strerror)
            return f"{flag} {value}: {target}: {fix}"
    return None


def _with_flag(msg: str, args: argparse.Namespace) -> str:
    """``msg`` (``"PATH: ..."`` about a flag's file) with that flag in front."""
    for flag, value in _flags(args).items():
        if len(value) > 1 and msg.startswith(value) and not msg.startswith(flag):
            return f"{flag} {msg}"
    return msg


def error_line(exc: BaseException, args: argparse.Namespace) -> str:
    """The one ``error:`` line for an exception that ended a sub-command."""
    cause = exc.__cause__
    while isinstance(cause, Exception) and str(cause) and str(cause) in str(exc):
        exc, cause = cause, cause.__cause__  # a wrapper repeating it (e.g. jsonargparse's)
    lines = str(exc).strip().splitlines()
    msg = lines[0] if lines else type(exc).__name__
    if isinstance(exc, OSError):  # ours (no errno) say what and the fix already
        msg = _os_message(exc, args) or (msg if exc.errno is None
                                         else f"{type(exc).__name__}: {msg}")
    elif not isinstance(exc, (ValueError, TypeError, RuntimeError)):
        msg = f"{type(exc).__name__}: {msg}"
    msg = _with_flag(_flag_message(msg, args), args)
    if not msg.startswith("--") and not any(flag in msg for flag in _flags(args)) \
            and not isinstance(exc, OSError):
        msg += " (rerun with --debug for the traceback)"
    return f"error: {msg}"


def run_command(args: argparse.Namespace, debug: bool = False) -> int:
    """Run ``args.command``; any exception becomes one ``error:`` line on stderr (exit
    status 2; 130 for Ctrl-C), or, with ``debug``, propagates with its traceback."""
    try:
        return COMMANDS[args.command][1](args)
    except KeyboardInterrupt:
        if debug:
            raise
        print("\nerror: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 -- the one place every failure is reported
        if debug:
            raise
        print(error_line(exc, args), file=sys.stderr)
        return 2


def main(argv: Optional[List[str]] = None) -> int:
    """Parse ``argv`` (default ``sys.argv[1:]``) and run its sub-command; the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    debug = os.environ.get("GARMENTGNN_DEBUG", "") not in ("", "0")
    while argv[:1] == ["--debug"]:
        debug, argv = True, argv[1:]
    if argv[:1] == ["train"]:  # everything after `train` belongs to LightningCLI, --help too
        args = argparse.Namespace(command="train", lightning_args=argv[1:])
    else:
        args = build_parser().parse_args(argv)
        args.argv = argv
    return run_command(args, debug or bool(getattr(args, "debug", False)))


if __name__ == "__main__":
    sys.exit(main())
