"""``benchmarks/mgn_learn.py score``: the rows of the ``--mgn`` model take the name
``--mgn-name`` gives, one a start (and a start with the projection)."""
import argparse
import runpy
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MGN_CKPT = ROOT / "tests" / "data" / "mgn_learn.ckpt"


def test_score_names_the_mgn_rows_as_given():
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_names")
    args = argparse.Namespace(mgn=str(MGN_CKPT), other=[], starts=["gt", "drape"],
                              project=["2", "0.002"], mgn_name="One-step to step 15,000")
    methods, modules = script["score_methods"](args)
    assert list(methods) == [f"One-step to step 15,000 ({s})" for s in
                             ("gt", "drape", "gt, projected", "drape, projected")]
    assert list(modules) == list(methods)
