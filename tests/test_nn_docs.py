"""The code blocks of docs/layers.md run as written."""
import re
import runpy
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "layers.md"
BLOCKS = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_doc_has_the_three_ways():
    assert len(BLOCKS) == 3


@pytest.mark.parametrize("i", range(len(BLOCKS)))
def test_doc_block_runs(i, tmp_path, monkeypatch):
    # run as a user's script: PyG's Sequential compiles its forward against the
    # calling module, which must be importable
    script = tmp_path / f"layers_doc_block{i + 1}.py"
    script.write_text(BLOCKS[i])
    monkeypatch.syspath_prepend(str(tmp_path))
    runpy.run_path(str(script), run_name="__main__")
