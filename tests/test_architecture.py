"""Dependencies point one way (the layout rules in the README), checked on the source's imports.

Each rule is a function of a package folder that returns its violations; the tests run
it on ``src/garmentgnn`` and, to show that it can fail, on small packages written to a
temporary folder that break it.  Imports inside functions count like module-level ones.
The size rule holds for the scripts in ``benchmarks/`` and the packages of their parts too.
"""
from __future__ import annotations

import ast
import functools
import re
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterable, List, Set, Tuple

import numpy as np
import pytest
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

SRC = Path(__file__).resolve().parents[1] / "src" / "garmentgnn"
#: the benchmark scripts (a folder of scripts, not a package) and their parts' packages
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

#: the most lines a module may have (one equation's home may be longer)
MAX_LINES = 500
#: modules over MAX_LINES today, relative to the package folder: to be split
OVERSIZED = {
    "motion/generators.py",  # 524 lines: the procedural motion families and their mixes
}
#: benchmark files over MAX_LINES today, relative to ``benchmarks/``: to be split
OVERSIZED_BENCHMARKS: Set[str] = set()
#: import cycles present today (each a set of modules): to be removed
KNOWN_CYCLES: List[Set[str]] = []


# --------------------------------------------------------------------------- the import graph
@dataclass(frozen=True)
class Import:
    importer: str  #: the importing module
    target: str  #: the module imported (the most specific one that exists in the package)
    names: Tuple[str, ...]  #: names taken from ``target`` by ``from target import ...``
    line: int
    in_function: bool  #: inside a function (run on call, not on import)


def modules(root: Path) -> Dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under the package folder ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = (root.name,) + path.relative_to(root).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


@functools.lru_cache(maxsize=None)
def _parse(text: str) -> ast.Module:
    return ast.parse(text)


def _walk(node: ast.AST, in_function: bool = False):
    """``(node, in_function)`` for ``node`` and everything under it."""
    yield node, in_function
    inner = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
    for child in ast.iter_child_nodes(node):
        yield from _walk(child, inner)


def imports(root: Path) -> List[Import]:
    """Every import of one of the package's own modules, relative imports resolved."""
    mods = modules(root)
    found: List[Import] = []
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        found += _module_imports(mod, package, path.read_text(), frozenset(mods))
    return found


@functools.lru_cache(maxsize=None)
def _module_imports(mod: str, package: str, text: str, mods: frozenset) -> Tuple[Import, ...]:
    """The imports of one module (``package``: the package its relative imports start
    from; ``mods``: every module of the package)."""
    top = mod.split(".")[0]
    found = []

    def existing(name: str) -> str:
        while name not in mods and "." in name:
            name = name.rsplit(".", 1)[0]
        return name

    for node, in_function in _walk(_parse(text)):
        pairs: List[Tuple[str, Tuple[str, ...]]] = []
        if isinstance(node, ast.Import):
            pairs = [(a.name, ()) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                pairs.append((sub, ()) if sub in mods else (base, (a.name,)))
        for name, names in pairs:
            if name.split(".")[0] == top and existing(name) in mods:
                found.append(Import(mod, existing(name), names, node.lineno, in_function))
    return tuple(found)


def subpackage(module: str) -> str:
    """``garmentgnn.data.store`` -> ``data``; ``garmentgnn.cli`` -> ``cli``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


# --------------------------------------------------------------------------- the rules
def imported_packages(root: Path, package: str) -> Set[str]:
    """Sub-packages imported by the modules of sub-package ``package``."""
    return {subpackage(i.target) for i in imports(root)
            if subpackage(i.importer) == package} - {""}


def import_cycles(root: Path) -> List[Set[str]]:
    """Strongly connected components (more than one module) of the import graph."""
    names = sorted(modules(root))
    index = {n: k for k, n in enumerate(names)}
    edges = {(index[i.importer], index[i.target]) for i in imports(root)
             if i.importer != i.target}
    rows, cols = (np.array(x, dtype=np.int64) for x in zip(*edges)) if edges else ([], [])
    graph = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    count, label = connected_components(graph, directed=True, connection="strong")
    comps = [{names[k] for k in np.flatnonzero(label == c)} for c in range(count)]
    return sorted((c for c in comps if len(c) > 1), key=sorted)


def wrong_way_imports(root: Path, importer: str, target: str) -> List[str]:
    """Imports of sub-package (or module) ``target`` from sub-package ``importer``
    (``"*"``: from anywhere else)."""
    return [f"{i.importer}:{i.line} imports {i.target}" for i in imports(root)
            if subpackage(i.target) == target and subpackage(i.importer) != target
            and importer in ("*", subpackage(i.importer))]


#: name -> the one module (relative to the package) that defines and exports it
BODY_CONSTRUCTION = {"build_body": "body.factory", "body_model": "body.factory"}


def body_construction_elsewhere(root: Path) -> List[str]:
    """Body builders defined, or imported from, anywhere but their home in ``body/``."""
    pkg = root.name
    homes = {n: f"{pkg}.{m}" for n, m in BODY_CONSTRUCTION.items()}
    bad = []
    for mod, path in modules(root).items():
        for node in ast.walk(_parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name in homes \
                    and mod != homes[node.name] and node.col_offset == 0:
                bad.append(f"{mod}:{node.lineno} defines {node.name}")
    for i in imports(root):
        for name in i.names:
            home = homes.get(name)
            if home and i.target not in (home, home.rpartition(".")[0]):
                bad.append(f"{i.importer}:{i.line} imports {name} from {i.target}")
    return bad


def function_level_imports(root: Path, package: str) -> List[str]:
    """The package's own modules imported inside functions of sub-package ``package``."""
    return [f"{i.importer}:{i.line} imports {i.target} in a function" for i in imports(root)
            if i.in_function and subpackage(i.importer) == package]


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def private_imports(root: Path) -> List[str]:
    """Private names (``_x``) taken from another module, and private modules (``a/_x.py``)
    imported from outside their package."""
    bad = []
    for i in imports(root):
        bad += [f"{i.importer}:{i.line} imports {n} from {i.target}" for n in i.names
                if _private(n) and i.target != i.importer]
        parts = i.target.split(".")
        for k, part in enumerate(parts):
            owner = ".".join(parts[:k])
            if _private(part) and not (i.importer == owner or i.importer.startswith(owner + ".")):
                bad.append(f"{i.importer}:{i.line} imports the private module {i.target}")
    return bad


#: Lightning internals (private names) the package must not touch: they change without
#: notice between Lightning releases; each has a public way (docs/model.md)
LIGHTNING_PRIVATE = ("_trainer", "_accelerator_connector", "_parse_ckpt_path",
                     "_subcommand_parsers")
_LIGHTNING_PRIVATE_RE = re.compile(r"\.(%s)\b|\bdef (%s)\b" % (
    "|".join(LIGHTNING_PRIVATE), "|".join(LIGHTNING_PRIVATE)))


def lightning_private_names(root: Path) -> List[str]:
    """Attribute uses (``x._trainer``) and overrides (``def _parse_ckpt_path``) of
    :data:`LIGHTNING_PRIVATE` in the package's source."""
    bad = []
    for path in sorted(root.rglob("*.py")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for m in _LIGHTNING_PRIVATE_RE.finditer(line.split("#")[0]):
                bad.append(f"{path.relative_to(root).as_posix()}:{n} uses "
                           f"{m.group(1) or m.group(2)}")
    return bad


def oversized(root: Path, limit: int = MAX_LINES) -> Dict[str, int]:
    """Modules (relative paths) over ``limit`` lines, with their line counts."""
    sizes = {p.relative_to(root).as_posix(): len(p.read_text().splitlines())
             for p in root.rglob("*.py")}
    return {p: n for p, n in sorted(sizes.items()) if n > limit}


# --------------------------------------------------------------------------- the package
@pytest.mark.parametrize("package,allowed", [
    ("nn", {"nn"}),
    ("geometry", {"geometry"}),
    ("physics", {"physics", "geometry"}),
    ("models", {"models", "nn", "geometry", "body", "physics"}),
    ("losses", {"losses", "geometry", "physics"}),
    ("_files", {"_files"}),  # the files written whole: the ground floor every writer uses
])
def test_layer_rules(package, allowed):
    found = imported_packages(SRC, package)
    assert found <= allowed, found - allowed


def test_no_import_cycles_between_modules():
    cycles = import_cycles(SRC)
    new = [sorted(c) for c in cycles if c not in KNOWN_CYCLES]
    gone = [sorted(c) for c in KNOWN_CYCLES if c not in cycles]
    assert not new, f"import cycles: {new}"
    assert not gone, f"no longer a cycle, remove it from KNOWN_CYCLES: {gone}"


@pytest.mark.parametrize("importer,target", [
    ("models", "sim"),  # models never import the simulator
    ("losses", "metrics"),  # a loss never depends on a metric
    ("*", "cli"),  # nothing imports the command line
    ("training", "viz"),  # viz draws trained models: it imports training, not the reverse
    ("data", "training"),  # the dataset reader (data.SequenceChunks) comes before training
])
def test_no_wrong_way_imports(importer, target):
    assert not wrong_way_imports(SRC, importer, target)


def test_bodies_are_built_in_one_place():
    assert not body_construction_elsewhere(SRC)


def test_sim_imports_at_module_level():
    assert not function_level_imports(SRC, "sim")


def test_no_private_imports_across_modules_outside_the_bench():
    assert not [v for v in private_imports(SRC) if not v.startswith("garmentgnn.bench.")]


def test_bench_modules_do_not_import_each_others_private_names():
    assert not [v for v in private_imports(SRC) if v.startswith("garmentgnn.bench.")]


def test_lightning_public_api_only():
    assert not lightning_private_names(SRC)


@pytest.mark.parametrize("root,known", [(SRC, OVERSIZED), (BENCHMARKS, OVERSIZED_BENCHMARKS)],
                         ids=["package", "benchmarks"])
def test_module_size(root, known):
    big = oversized(root)
    assert set(big) <= known, {p: n for p, n in big.items() if p not in known}
    assert known <= set(big), \
        f"split already, remove it from the known list: {sorted(known - set(big))}"


def test_the_model_reads_as_the_paper_in_300_lines():
    """GarTrans's file holds its pipeline; what any frame-wise model shares (batch
    layout, sequence prediction, rollout) lives beside it in models/sequence.py."""
    assert not oversized(SRC / "models", limit=300).keys() & {"gartrans.py"}


# --------------------------------------------------------------------------- each rule can fail
def make_package(tmp_path: Path, files: Dict[str, str]) -> Path:
    """A package ``pkg`` under ``tmp_path`` with ``files`` (relative path -> source) and
    an empty ``__init__.py`` in every folder."""
    root = tmp_path / "pkg"
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    for folder in [root, *(p for p in root.rglob("*") if p.is_dir())]:
        (folder / "__init__.py").touch()
    return root


def _names(found: Iterable[str]) -> List[str]:
    return sorted(v.split(":")[0] for v in found)


def test_checker_finds_cycles_through_function_level_and_relative_imports(tmp_path):
    root = make_package(tmp_path, {
        "a/x.py": "from pkg.b import y\n",
        "b/y.py": "def f():\n    from ..a import x\n",
        "c/z.py": "from pkg.a import x\n",  # depends on the cycle, is not in it
    })
    assert import_cycles(root) == [{"pkg.a.x", "pkg.b.y"}]
    (root / "b" / "y.py").write_text("import pkg.c\n")  # the package, not c.z
    assert import_cycles(root) == []


def test_checker_finds_layer_violations(tmp_path):
    root = make_package(tmp_path, {"losses/l.py": "import math\nfrom pkg.metrics import m\n",
                                   "metrics/m.py": "", "models/net.py": "",
                                   "sim/s.py": "", "tool.py": "def main():\n    import pkg.cli\n",
                                   "cli.py": "from pkg.models import net\n"})
    assert imported_packages(root, "losses") == {"metrics"}
    assert wrong_way_imports(root, "losses", "metrics") == ["pkg.losses.l:2 imports pkg.metrics.m"]
    assert _names(wrong_way_imports(root, "*", "cli")) == ["pkg.tool"]
    assert wrong_way_imports(root, "models", "sim") == []
    (root / "models" / "net.py").write_text("from pkg import sim\n")
    assert _names(wrong_way_imports(root, "models", "sim")) == ["pkg.models.net"]


def test_checker_finds_bodies_built_outside_body(tmp_path):
    ok = {"body/factory.py": "def build_body(spec):\n    pass\n\ndef body_model(name):\n    pass\n",
          "body/__init__.py": "from pkg.body.factory import body_model, build_body\n",
          "data/dataset.py": "from pkg.body import build_body\n",
          "training/dm.py": "from pkg.body.factory import body_model\n"}
    assert body_construction_elsewhere(make_package(tmp_path / "ok", ok)) == []
    root = make_package(tmp_path / "bad", dict(ok, **{
        "data/generate.py": "def build_body(spec):\n    pass\n",
        "training/dm.py": "from pkg.data.generate import build_body\n"}))
    assert _names(body_construction_elsewhere(root)) == ["pkg.data.generate",
                                                         "pkg.training.dm"]


def test_checker_finds_function_level_imports(tmp_path):
    root = make_package(tmp_path, {
        "sim/s.py": "from pkg.garments import g\n\nclass S:\n    def run(self):\n"
                    "        import numpy\n        from pkg.garments.g import f\n",
        "garments/g.py": "def f():\n    pass\n"})
    assert function_level_imports(root, "sim") == [
        "pkg.sim.s:6 imports pkg.garments.g in a function"]
    assert function_level_imports(root, "garments") == []


def test_checker_finds_private_imports(tmp_path):
    root = make_package(tmp_path, {
        "geometry/normals.py": "def _face_angles():\n    pass\n",
        "geometry/distance.py": "from .normals import _face_angles\n",
        "data/_lifeline.py": "",
        "data/generate.py": "from pkg.data._lifeline import watch\nfrom . import _lifeline\n",
        "sim/s.py": "import pkg.data._lifeline\n",
        "bench/report.py": "def _table():\n    pass\n__all__ = ['__version__']\n",
        "bench/scaling.py": "from pkg.bench.report import _table\n"})
    assert _names(private_imports(root)) == ["pkg.bench.scaling", "pkg.geometry.distance",
                                             "pkg.sim.s"]


def test_checker_finds_oversized_modules(tmp_path):
    root = make_package(tmp_path, {"a/long.py": "x = 1\n" * 12, "a/short.py": "x = 1\n" * 10})
    assert oversized(root, limit=10) == {"a/long.py": 12}


def test_checker_finds_oversized_scripts_and_parts(tmp_path):
    """A folder of scripts like ``benchmarks/``: no ``__init__.py``, a package of one
    script's parts beside it, results that are not code."""
    files = {"long.py": 12, "short.py": 10, "long_parts/__init__.py": 1,
             "long_parts/table.py": 11, "results/long.md": 20}
    for rel, n in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("x = 1\n" * n)
    assert oversized(tmp_path, limit=10) == {"long.py": 12, "long_parts/table.py": 11}


def test_checker_finds_lightning_private_names(tmp_path):
    root = make_package(tmp_path, {
        "training/m.py": "class M:\n    def f(self):\n        return self._trainer is None\n"
                         "    def g(self):\n"
                         "        return self._trainer_kwargs  # _trainer\n",
        "training/cli.py": "class C:\n    def _parse_ckpt_path(self):\n        pass\n",
        "training/dm.py": "x = t._accelerator_connector.use_distributed_sampler\n"
                          "y = cli._subcommand_parsers['fit']\n"})
    assert lightning_private_names(root) == [
        "training/cli.py:2 uses _parse_ckpt_path", "training/dm.py:1 uses _accelerator_connector",
        "training/dm.py:2 uses _subcommand_parsers", "training/m.py:3 uses _trainer"]
