"""``--help`` of ``garmentgnn`` and of every script in ``benchmarks/`` and
``benchmarks/experiments/``: each option has help text, and the help shows its default
(argparse's own formatter output is the oracle); benchmark scripts write into a cache
folder unless ``--commit`` or ``--out`` is given."""
import argparse
import runpy
import shlex
from pathlib import Path

import pytest

from garmentgnn._argparse import add_output_args, benchmark_cache, command_line, output_path
from garmentgnn.cli import build_parser

_BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted([*_BENCHMARKS.glob("*.py"), *(_BENCHMARKS / "experiments").glob("*.py")])


def walk(parser: argparse.ArgumentParser, name: str):
    """(parser name, parser) for ``parser`` and every sub-command parser under it."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from walk(p, f"{name} {sub}")


def help_problems(name: str, parser: argparse.ArgumentParser) -> list:
    """The options of ``parser`` whose help is missing or does not give the default."""
    bad = []
    formatter = parser._get_formatter()
    for action in parser._actions:
        if action.help == argparse.SUPPRESS or not action.option_strings:
            continue
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        flag = f"{name} {action.option_strings[-1]}"
        if not (action.help or "").strip():
            bad.append(f"{flag}: no help")
        elif not action.required and "default" not in formatter._get_help_string(action):
            bad.append(f"{flag}: default not shown")
    return bad


class _Parsed(Exception):
    def __init__(self, parser):
        self.parser = parser


def script_parser(path: Path, monkeypatch) -> argparse.ArgumentParser:
    """The parser ``path``'s ``main()`` builds, caught at its ``parse_args`` call."""
    def catch(self, args=None, namespace=None):
        raise _Parsed(self)
    ns = runpy.run_path(str(path), run_name="benchmark_help_check")
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", catch)
    monkeypatch.setattr("sys.argv", [path.name])
    with pytest.raises(_Parsed) as caught:
        ns["main"]()
    return caught.value.parser


def test_every_cli_option_has_help_with_its_default():
    parsers = list(walk(build_parser(), "garmentgnn"))
    names = {n for n, _ in parsers}
    assert {"garmentgnn show", "garmentgnn export", "garmentgnn bench"} <= names
    bad = [b for n, p in parsers for b in help_problems(n, p)]
    assert bad == []
    for name, p in parsers:
        if name != "garmentgnn" and name != "garmentgnn train":  # train: Lightning's own
            assert p.description, f"{name} has no description"
    show = dict(parsers)["garmentgnn show"].format_help()
    # --history, --num-landmarks: the checkpoints' own (viz.compare.data_settings)
    assert " ".join(show.split()).count("default: as the checkpoints were trained") == 2, show


def test_help_checker_finds_a_missing_help():
    p = argparse.ArgumentParser()
    p.add_argument("--a", default=1)
    p.add_argument("--b", default=None, help="something")
    p.add_argument("--c", required=True, help="required: no default to show")
    assert help_problems("x", p) == ["x --a: no help", "x --b: default not shown"]


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_benchmark_flags_have_help_with_defaults(path, monkeypatch):
    parser = script_parser(path, monkeypatch)
    assert help_problems(path.name, parser) == []
    # never the committed results by default: --commit asks for them
    assert any("--commit" in a.option_strings for a in parser._actions), path.name


def test_benchmark_output_goes_to_the_cache_unless_asked(tmp_path, monkeypatch):
    monkeypatch.setenv("GARMENTGNN_CACHE_DIR", str(tmp_path))
    committed = Path("docs") / "results" / "benchmarks" / "inference"
    ap = argparse.ArgumentParser()
    add_output_args(ap, committed, "writes OUT.json")
    assert output_path(ap.parse_args([]), committed) == tmp_path / "benchmarks" / "inference"
    assert benchmark_cache() == tmp_path / "benchmarks"
    assert output_path(ap.parse_args(["--commit"]), committed) == committed
    assert output_path(ap.parse_args(["--out", "x/y"]), committed) == Path("x/y")
    with pytest.raises(SystemExit):  # not both
        ap.parse_args(["--commit", "--out", "x"])


def test_command_line_records_the_command_as_the_shell_reads_it(monkeypatch):
    """Paths under the home folder from ``~``, words with spaces or quotes quoted so that
    ``shlex.split`` gives the arguments back."""
    home = str(Path.home())
    argv = ["curves", "--data", f"{home}/d", "--variants", "HOOD-style, lr 1e-4", "it's",
            f"/x{home}"]
    line = command_line("benchmarks/x.py", argv)
    assert line.startswith("python benchmarks/x.py curves --data ~/d --variants ")
    assert shlex.split(line)[2:] == ["curves", "--data", "~/d", "--variants",
                                     "HOOD-style, lr 1e-4", "it's", f"/x{home}"]
    monkeypatch.setattr("sys.argv", ["x.py", "grad"])
    assert command_line("benchmarks/x.py") == "python benchmarks/x.py grad"
