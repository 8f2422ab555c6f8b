"""Command-line parts shared by ``garmentgnn``'s sub-commands and the scripts in
``benchmarks/``: a help formatter that shows every option's default, the ``--out`` /
``--commit`` pair of a benchmark script (results go to a cache folder unless the
committed copy is asked for), and argument types and actions that refuse what would
otherwise run silently wrong: counts below their minimum (:func:`int_at_least`), NaN or
infinite numbers (:func:`finite_float`), a list flag given twice (:class:`Accumulate`:
the values add up instead of the last flag winning) and repeated values
(:func:`check_unique`), and a parser (:class:`ArgumentParser`) that hands a value starting
with a minus to the flag it follows, for the flag's own check to judge."""
from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Optional, Sequence


def int_at_least(low: int) -> Callable[[str], int]:
    """An argparse type: an int ``>= low`` (e.g. ``--threads 0`` is refused by the parser
    with the flag named, instead of failing later with a traceback)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {value}")
        return value
    parse.__name__ = f"int >= {low}"
    return parse


def finite_float(text: str) -> float:
    """An argparse type: a finite float (``nan``, ``inf`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def float_above(low: float) -> Callable[[str], float]:
    """An argparse type: a finite float ``> low``."""
    def parse(text: str) -> float:
        value = finite_float(text)
        if not value > low:
            raise argparse.ArgumentTypeError(f"expected a number > {low:g}, got {text!r}")
        return value
    parse.__name__ = f"float > {low:g}"
    return parse


class Accumulate(argparse.Action):
    """A list flag (``nargs="+"``) that may be repeated: ``--seed 0 --seed 1 2`` gives
    ``[0, 1, 2]`` (argparse's default action keeps the last flag's values only, silently);
    the first use replaces the default, later ones add to it."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: Optional[str] = None) -> None:
        current = getattr(namespace, self.dest, None)
        # argparse puts the default object itself in the namespace before parsing
        old = [] if current is None or current is self.default else list(current)
        new = list(values) if isinstance(values, (list, tuple)) else [values]
        setattr(namespace, self.dest, old + new)


def check_unique(parser: argparse.ArgumentParser, values: Optional[Sequence[Any]],
                 flag: str) -> None:
    """``parser.error`` (one ``error:`` line, exit status 2) when ``values`` repeat one
    (``--seed 0 0 0`` would run the same seed three times)."""
    if values is None:
        return
    seen, dup = set(), []
    for v in values:
        if v in seen and v not in dup:
            dup.append(v)
        seen.add(v)
    if dup:
        parser.error(f"{flag}: {', '.join(map(str, dup))} given more than once; give each "
                     f"value once")


def nonempty_path(text: str) -> str:
    """An argparse type: a non-empty path (``--out ""`` would write into the current
    folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path; name a folder or file")
    return text


def _existing(text: str, kind: str, is_kind: Callable[[str], bool], other: str,
              is_other: Callable[[str], bool]) -> str:
    """``text`` with ``~`` expanded where ``is_kind`` holds for that path; otherwise an
    ``ArgumentTypeError`` with ``text`` and what is there: ``a <other>, not a <kind>``
    where ``is_other`` holds, else ``no such <kind>``."""
    path = os.path.expanduser(text)
    if not text.strip():
        raise argparse.ArgumentTypeError(f"empty path; name a {kind}")
    if not is_kind(path):
        what = f"is a {other}, not a {kind}" if is_other(path) else f"no such {kind}"
        raise argparse.ArgumentTypeError(f"{text}: {what}")
    return path


def existing_file(text: str) -> str:
    """An argparse type: the path of an existing file (``~`` expanded)."""
    return _existing(text, "file", os.path.isfile, "folder", os.path.isdir)


def existing_dir(text: str) -> str:
    """An argparse type: the path of an existing folder (``~`` expanded)."""
    return _existing(text, "folder", os.path.isdir, "file", os.path.exists)


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` that reads a word starting with a minus and a digit
    (``--shard -1/2``, ``--start-frame -1e3``) as the value of the flag before it, as
    Python 3.12's argparse does; Python 3.11's takes only plain negative numbers so, and
    answered "expected one argument", which names no reason.  The flag's own type or
    check then says what is wrong with the value.  Sub-parsers are of this class too."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-\.?\d")


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
