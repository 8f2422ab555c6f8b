"""Every data size has one home: the pose history and the chunk length in
``models/inputs.py`` (``HISTORY``, ``CHUNK``), the Nyström width and its landmarks in
``geometry/geodesic.py`` (``NYSTROM_DIM``, ``NUM_LANDMARKS``).  Everywhere else in
``src/`` and ``benchmarks/`` imports them; this test reads the code (its syntax tree,
so comments and docstrings may still say "16 eigenvectors") for the literal values
written in those meanings, as ``test_architecture.py`` reads the imports.
"""
from __future__ import annotations

import ast
import textwrap
from pathlib import Path
from typing import Dict, FrozenSet, Iterator, List, Tuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "garmentgnn"
BENCHMARKS = ROOT / "benchmarks"

#: each size's name (an argument, a dictionary key, a ``--data.`` flag) -> the values
#: that restate it; ``num_landmarks`` 128 was the geodesic features' own default
SIZES: Dict[str, FrozenSet[int]] = {
    "history": frozenset({3}),
    "chunk": frozenset({8}),
    "nystrom_dim": frozenset({16}),
    "num_landmarks": frozenset({64, 128}),
}
#: where each size is defined (relative to ``src/garmentgnn``), the one place it may be
#: written as a number
HOMES = {"models/inputs.py": {"HISTORY", "CHUNK"},
         "geometry/geodesic.py": {"NYSTROM_DIM", "NUM_LANDMARKS"}}
#: restatements present today (``path: what``, as :func:`found` words them, less the
#: line): to be replaced by an import of the size's home
KNOWN: set = set()


def _int(node: ast.AST):
    """The int a node writes literally (``16``, ``{16}``, ``"16"``), else ``None``."""
    if isinstance(node, ast.Set) and len(node.elts) == 1:
        node = node.elts[0]
    if isinstance(node, ast.Constant):
        v = node.value
        if isinstance(v, str) and v.isdigit():
            return int(v)
        if isinstance(v, int) and not isinstance(v, bool):
            return v
    return None


def _size(name: str):
    """The size ``name`` stands for (``nystrom_dim``, ``NUM_LANDMARKS``, ``--data.chunk``),
    else ``None``."""
    key = name.lower().rsplit(".", 1)[-1].lstrip("-")
    return key if key in SIZES else None


def _restated(name: str, node: ast.AST) -> bool:
    size = _size(name)
    return size is not None and _int(node) in SIZES[size]


def restatements(source: str) -> Iterator[Tuple[int, str]]:
    """``(line, what)`` for each place ``source`` writes one of :data:`SIZES` as a number:
    a keyword argument or default (``chunk=8``, ``history: int = 3``), an assignment
    (``HISTORY = 3``), a dictionary entry or lookup (``{"nystrom_dim": 16}``,
    ``d.get("num_landmarks", 64)``), a fallback (``module.nystrom_dim or 16``) and a
    command line's flag and value (``"--data.chunk", "8"``)."""
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.keyword) and node.arg and _restated(node.arg, node.value):
            yield node.value.lineno, f"{node.arg}={ast.unparse(node.value)}"
        elif isinstance(node, ast.arguments):
            args = node.posonlyargs + node.args
            pairs = list(zip(args[len(args) - len(node.defaults):], node.defaults))
            pairs += [(a, d) for a, d in zip(node.kwonlyargs, node.kw_defaults) if d]
            for arg, default in pairs:
                if _restated(arg.arg, default):
                    yield default.lineno, f"{arg.arg}={ast.unparse(default)}"
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for t in targets:
                if isinstance(t, ast.Name) and node.value is not None \
                        and _restated(t.id, node.value):
                    yield node.lineno, f"{t.id} = {ast.unparse(node.value)}"
        elif isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values):
                if isinstance(k, ast.Constant) and isinstance(k.value, str) \
                        and _restated(k.value, v):
                    yield v.lineno, f"{k.value!r}: {ast.unparse(v)}"
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr == "get" and len(node.args) == 2 \
                and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str) and _restated(node.args[0].value,
                                                                      node.args[1]):
            yield node.lineno, ast.unparse(node)
        elif isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or):
            names = {n.attr for v in node.values for n in ast.walk(v)
                     if isinstance(n, ast.Attribute)} | {
                n.id for v in node.values for n in ast.walk(v) if isinstance(n, ast.Name)} | {
                n.value for v in node.values for n in ast.walk(v)
                if isinstance(n, ast.Constant) and isinstance(n.value, str)}
            if any(_restated(name, v) for name in names for v in node.values):
                yield node.lineno, ast.unparse(node)
        elif isinstance(node, (ast.List, ast.Tuple)):
            for flag, value in zip(node.elts, node.elts[1:]):
                if isinstance(flag, ast.Constant) and isinstance(flag.value, str) \
                        and flag.value.startswith("--") and _restated(flag.value, value):
                    yield value.lineno, f"{flag.value} {ast.unparse(value)}"


def found(root: Path, homes: Dict[str, set]) -> List[str]:
    """``path:line: what`` for each restatement under ``root`` outside the homes (where
    only the constant's own definition is allowed)."""
    out = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        for line, what in restatements(path.read_text()):
            own = what.split(" = ")[0] if " = " in what else None
            if own is not None and own in homes.get(rel, set()):
                continue
            out.append(f"{path.relative_to(ROOT).as_posix()}:{line}: {what}")
    return out


def _new(hits: List[str]) -> List[str]:
    return [h for h in hits if f"{h.split(':')[0]}: {h.split(': ', 1)[1]}" not in KNOWN]


def test_the_sizes_are_written_once_in_the_package():
    assert _new(found(SRC, HOMES)) == []


def test_the_benchmarks_import_the_sizes():
    hits = found(BENCHMARKS, {})
    assert _new(hits) == []
    gone = KNOWN - {f"{h.split(':')[0]}: {h.split(': ', 1)[1]}" for h in hits}
    assert not gone, f"fixed: strike {sorted(gone)} from KNOWN"


@pytest.mark.parametrize("code", [
    "def f(chunk: int = 8): pass",
    "def f(*, num_landmarks=128): pass",
    "f(nystrom_dim=16)",
    "HISTORY = 3",
    "x: int = 16\nNYSTROM_DIM: int = 16",
    "d = {'num_landmarks': 64}",
    "h = data.get('history', 3)",
    "ny = module.nystrom_dim or 16",
    "nys = {m.nystrom_dim for m in ms} or {16}",
    "args = ['--data.chunk', '8', '--data.history', '3']",
])
def test_each_way_of_restating_a_size_is_found(code):
    assert list(restatements(textwrap.dedent(code)))


@pytest.mark.parametrize("code", [
    "def f(chunk: int = CHUNK, history: int = 1): pass",  # 1: another meaning
    "f(nystrom_dim=NYSTROM_DIM, k=16, heads=8)",
    "args = ['--data.chunk', str(CHUNK), '--data.batch_size', '8']",
    "ny = module.nystrom_dim or NYSTROM_DIM",
    "'''16 eigenvectors over 64 landmarks, chunk=8'''  # history=3 in a comment",
])
def test_a_size_read_from_its_home_is_not_found(code):
    assert list(restatements(textwrap.dedent(code))) == []


def test_the_homes_define_them():
    from garmentgnn.geometry.geodesic import NUM_LANDMARKS, NYSTROM_DIM  # noqa: PLC0415
    from garmentgnn.models import inputs  # noqa: PLC0415
    assert (inputs.HISTORY, inputs.CHUNK, NYSTROM_DIM, NUM_LANDMARKS) == (3, 8, 16, 64)
    assert (inputs.NYSTROM_DIM, inputs.NUM_LANDMARKS) == (NYSTROM_DIM, NUM_LANDMARKS)
