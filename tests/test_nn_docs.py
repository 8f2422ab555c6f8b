"""The code blocks of docs/layers.md run as written."""
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parent.parent / "docs" / "layers.md"
BLOCKS = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_doc_has_the_three_ways():
    assert len(BLOCKS) == 3


@pytest.mark.parametrize("i", range(len(BLOCKS)))
def test_doc_block_runs(i):
    exec(compile(BLOCKS[i], f"{DOC.name}[python block {i + 1}]", "exec"), {"__name__": "doc"})
