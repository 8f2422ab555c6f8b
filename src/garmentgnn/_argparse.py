"""Command-line parts shared by ``garmentgnn``'s sub-commands and the scripts in
``benchmarks/``: a help formatter that shows every option's default, and the
``--out`` / ``--commit`` pair of a benchmark script (results go to a cache folder unless
the committed copy is asked for)."""
from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Optional, Sequence


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default: ``(default: X)`` is appended unless the
    help text already says what the default is (it mentions "default") or the option is
    required."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.required or "default" in text.lower():
            return text
        return super()._get_help_string(action)


def benchmark_cache() -> Path:
    """Where benchmark scripts write without ``--out`` / ``--commit``:
    ``$GARMENTGNN_CACHE_DIR/benchmarks``, ``$GARMENTGNN_CACHE_DIR`` defaulting to
    ``~/.cache/garmentgnn`` (outside any work tree)."""
    root = os.environ.get("GARMENTGNN_CACHE_DIR") or Path.home() / ".cache" / "garmentgnn"
    return Path(root) / "benchmarks"


def add_output_args(parser: argparse.ArgumentParser, committed: Path, what: str) -> None:
    """``--out`` (``what`` says what it names) and ``--commit`` (write ``committed``, the
    copy kept in the repository); without either, the results go under
    :func:`benchmark_cache`, named as ``committed`` is."""
    g = parser.add_mutually_exclusive_group()
    g.add_argument("--out", default=None,
                   help=f"{what}; default {benchmark_cache() / committed.name} "
                        f"(the committed copy only with --commit)")
    g.add_argument("--commit", action="store_true",
                   help=f"write the committed results, {committed}")


def output_path(args: argparse.Namespace, committed: Path) -> Path:
    """The path ``--out`` / ``--commit`` chose (:func:`add_output_args`); prints it."""
    if args.out:
        out = Path(args.out)
    elif args.commit:
        out = committed
    else:
        out = benchmark_cache() / committed.name
    print(f"results: {out}", flush=True)
    return out


def command_line(script: str, argv: Optional[Sequence[str]] = None) -> str:
    """The command that ran ``script`` with ``argv`` (default ``sys.argv[1:]``), as a
    results file records it: ``python <script> ...``, a path under the home folder
    written from ``~``, a word the shell would split quoted."""
    home = str(Path.home())
    words = [w.replace(home, "~", 1) if w.startswith(home) else w
             for w in (sys.argv[1:] if argv is None else argv)]
    return " ".join(["python", script] + [
        w if re.fullmatch(r"[\w@%+=:,./~-]+", w) else shlex.quote(w) for w in words])
