"""``benchmarks/mgn_learn.py score``: the rows of the ``--mgn`` model take the name
``--mgn-name`` gives, one a start (and a start with the projection); ``--merge`` adds
the methods (``--merge-names``: only those) of earlier scores of the same sequences, and
alone reports them."""
import argparse
import json
import runpy
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
MGN_CKPT = ROOT / "tests" / "data" / "mgn_learn.ckpt"
GARTRANS_CKPT = ROOT / "tests" / "data" / "gartrans_learn.ckpt"


@pytest.mark.parametrize("inextensible,how", [(0, "projected"), (7, "inextensible 7")])
def test_score_names_the_mgn_rows_as_given(inextensible, how):
    """``--project SWEEPS MARGIN [--inextensible N]``: the second model's rows are named
    after its projection, which it has (the checkpoint's own: the eval default)."""
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_names")
    args = argparse.Namespace(mgn=str(MGN_CKPT), other=[], starts=["gt", "drape"],
                              project=["2", "0.002"], inextensible=inextensible,
                              mgn_name="One-step to step 15,000")
    methods, modules = script["score_methods"](args)
    assert list(methods) == [f"One-step to step 15,000 ({s})" for s in
                             ("gt", "drape", f"gt, {how}", f"drape, {how}")]
    assert list(modules) == list(methods)
    own, projected = (modules[f"One-step to step 15,000 ({s})"].model
                      for s in ("gt", f"gt, {how}"))
    assert (own.strain_limit, own.inextensible, own.collision_projection) == (10, 100, 0.002)
    assert (projected.strain_limit, projected.inextensible,
            projected.collision_projection) == (2, inextensible, 0.002)


def test_a_start_named_after_another_method_rolls_out_from_its_frames():
    """``--starts NAME``: the rollout starts from the --other method's frames 0 and 1,
    which is scored first (its frames kept by ``run_score``)."""
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_start")
    args = argparse.Namespace(mgn=str(MGN_CKPT), starts=["gt", "G"], project=None,
                              mgn_name="MGN-style", other=[f"G={GARTRANS_CKPT}"])
    methods, modules = script["score_methods"](args)
    assert list(methods) == ["G", "MGN-style (gt)", "MGN-style (G)"]
    assert args.start_frames == {"G": {}}
    mgn = modules["MGN-style (G)"]
    given, seen = torch.full((2, 5, 3), 0.5), []
    mgn.rollout = lambda item, start: seen.append(start) or start
    args.start_frames["G"]["seq"] = given
    assert methods["MGN-style (G)"](argparse.Namespace(seq_id="seq")) is given
    assert methods["MGN-style (gt)"](argparse.Namespace(seq_id="seq")) == "gt"
    assert seen[0] is given


def _scores(**methods):
    """A score of two sequences whose methods have these E_dist values."""
    def rows(values):
        return [{"sequence": s, "metrics": {"E_dist": v}} for s, v in zip("ab", values)]
    return {"content_sha256": "d", "split": "test",
            "methods": {name: rows(v) for name, v in methods.items()},
            "per_frame": {name: {} for name in methods},
            "seconds": {name: 1.0 for name in methods if name != "LBS only"}}


def test_merge_adds_only_the_named_methods_and_keeps_the_scored_ones():
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_merge")
    results = _scores(**{"LBS only": [5, 6], "New": [4, 4]})
    earlier = {"old.json": _scores(**{"LBS only": [5, 6], "New": [9, 9], "A": [1, 2],
                                      "B": [3, 3]})}
    script["merge_scores"](results, earlier, ["A", "New"])
    assert list(results["methods"]) == ["LBS only", "New", "A"]
    assert [r["metrics"]["E_dist"] for r in results["methods"]["New"]] == [4, 4]
    assert list(results["seconds"]) == ["New", "A"]
    script["merge_scores"](results, earlier)  # every method
    assert list(results["methods"]) == ["LBS only", "New", "A", "B"]


def test_merge_refuses_a_score_of_other_sequences_or_a_name_it_lacks(tmp_path, capsys):
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_merge")
    other = {"old.json": _scores(**{"LBS only": [5, 7], "A": [1, 2]})}
    with pytest.raises(SystemExit, match="--merge: old.json scored other sequences"):
        script["merge_scores"](_scores(**{"LBS only": [5, 6]}), other)
    path = tmp_path / "old.json"
    path.write_text(json.dumps(other["old.json"]))
    with pytest.raises(SystemExit, match="--merge-names: 'B' is in no --merge file; give "
                                         r"one of \['A', 'LBS only'\]"):
        script["read_scores"]([str(path)], ["A", "B"])
    assert script["read_scores"]([str(path)], ["A"]) == {str(path): other["old.json"]}


def _full(values):
    """Per-sequence rows of every metric the table reads (E_dist as given, the rest
    proportional), for sequences a, b, c, ..."""
    return [{"sequence": s, "frames": 10, "held_out": ["motion"],
             "metrics": {m: v for m in ("E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv",
                                        "collision_rate")}}
            for s, v in zip("abcdefgh", values)]


def test_merge_alone_reports_the_earlier_scores_and_pairs_mgn_rows_of_a_model_or_start(
        tmp_path):
    """``score --merge A B`` alone: one report of both files, nothing rolled out; the
    paired tests (scipy's Wilcoxon as the oracle) include MGN-style rows against each
    other where they share the model or the start, never across both."""
    from scipy.stats import wilcoxon as scipy_wilcoxon  # noqa: PLC0415
    script = runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"), run_name="mgn_alone")
    lbs = [5, 6, 7, 5, 6, 7, 5, 6]
    x = [4, 5, 6, 4.5, 5.5, 6.5, 4.2, 5.1]
    y = [4.1, 5.2, 5.7, 4.4, 5.9, 6.1, 4.3, 5.0]

    def doc(methods):
        return {"content_sha256": "d", "split": "test", "methods": methods,
                "per_frame": {n: {"a": [1.0, 2.0]} for n in methods},
                "seconds": {n: 1.0 for n in methods if n != "LBS only"}}
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    a.write_text(json.dumps(doc({"MGN-style, A (gt)": _full(x), "LBS only": _full(lbs),
                                 "MGN-style, A (lbs)": _full(y)})))
    b.write_text(json.dumps(doc({"MGN-style, B (gt)": _full(y), "LBS only": _full(lbs),
                                 "MGN-style, B (lbs)": _full(x)})))
    results = script["combined"](script["read_scores"]([str(a), str(b)]))
    assert list(results["methods"]) == ["LBS only", "MGN-style, A (gt)",
                                        "MGN-style, A (lbs)", "MGN-style, B (gt)",
                                        "MGN-style, B (lbs)"]
    text = script["write_score"](results, tmp_path)
    assert (tmp_path / "score.md").read_text() == text and (tmp_path / "per_frame.png").is_file()
    pairs = {line.split(" | ")[0][2:] for line in text.splitlines() if " vs " in line}
    assert pairs == {"MGN-style, A (gt) vs LBS only", "MGN-style, A (lbs) vs LBS only",
                     "MGN-style, B (gt) vs LBS only", "MGN-style, B (lbs) vs LBS only",
                     "MGN-style, A (gt) vs MGN-style, A (lbs)",
                     "MGN-style, A (gt) vs MGN-style, B (gt)",
                     "MGN-style, A (lbs) vs MGN-style, B (lbs)",
                     "MGN-style, B (gt) vs MGN-style, B (lbs)"}
    row = next(line for line in text.splitlines()
               if line.startswith("| MGN-style, A (gt) vs MGN-style, B (gt) | E_dist"))
    assert float(row.split(" | ")[-1].rstrip(" |")) == pytest.approx(
        scipy_wilcoxon(x, y).pvalue, rel=0.05)  # printed to 2 digits
