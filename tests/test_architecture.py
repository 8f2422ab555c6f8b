"""Dependencies point one way (the layout rules in the README), checked on the source's imports."""
import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "garmentgnn"


def imported_packages(package: str):
    """garmentgnn sub-packages imported anywhere under ``package``."""
    found = set()
    for path in (SRC / package).rglob("*.py") if (SRC / package).is_dir() else [SRC / package]:
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for n in names:
                parts = n.split(".")
                if parts[0] == "garmentgnn" and len(parts) > 1:
                    found.add(parts[1])
    return found


@pytest.mark.parametrize("package,allowed", [
    ("nn", {"nn"}),
    ("geometry", {"geometry"}),
    ("physics", {"physics", "geometry"}),
    ("models", {"models", "nn", "geometry", "body", "physics"}),
])
def test_layer_rules(package, allowed):
    assert imported_packages(package) <= allowed, imported_packages(package) - allowed


def test_models_never_import_the_simulator_and_nothing_imports_cli():
    assert "sim" not in imported_packages("models")
    for top in SRC.iterdir():
        if top.name != "cli.py" and (top.is_dir() or top.suffix == ".py"):
            assert "cli" not in imported_packages(top.name), top.name
