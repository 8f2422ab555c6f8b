"""The README's quick start runs as written (on a smaller budget: a temporary folder, one
worker, a few steps) and scores a held-out chunk."""
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def quick_start() -> str:
    text = README.read_text()
    section = text.split("## Quick start", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_quick_start_runs(tmp_path, capsys):
    code = quick_start()
    edits = {'"data/tiny"': repr(str(tmp_path / "tiny")), "workers=2": "workers=0",
             "max_epochs=20": f"max_steps=2, enable_progress_bar=False, "
                              f"default_root_dir={str(tmp_path / 'run')!r}"}
    for old, new in edits.items():
        assert code.count(old) >= 1, old  # the README still reads as the test expects
        code = code.replace(old, new)
    scope = {}
    exec(compile(code, str(README), "exec"), scope)
    out = capsys.readouterr().out
    assert "E_dist" in out
    assert scope["pred"].shape == scope["chunk"].gt.shape
    assert list((tmp_path / "run").rglob("last.ckpt"))  # the recipe's checkpoints
