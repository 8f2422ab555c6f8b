"""The bench's per-sequence scoring helpers and the seed plan: held-out groups,
frame-weighted means, the paired Wilcoxon test (exact small-sample p-values written
out here) and which methods get every seed."""
import pytest

from garmentgnn.bench import learned, learned_report, methods, scoring, tables


def seq(name, frames, held, e):
    return {"sequence": name, "frames": frames, "held_out": held,
            "metrics": {"E_dist": e, "E_len": 2 * e}}


def test_groups_and_frame_weighted_means():
    assert scoring.group_of(["motion"]) == "unseen motion"
    assert scoring.group_of(["body", "motion"]) == scoring.group_of(["garment", "body"]) \
        == "several unseen"
    assert scoring.group_of([]) is None
    with pytest.raises(ValueError, match="held_out"):
        scoring.group_of(["colour"])
    ss = [seq("a", 10, ["motion"], 1.0), seq("b", 30, ["motion"], 3.0),
          seq("c", 20, ["body"], 5.0), seq("d", 40, ["garment", "motion"], 7.0)]
    agg = scoring.aggregate(ss)
    assert set(agg) == {"all", "unseen motion", "unseen body", "several unseen"}
    assert agg["unseen motion"]["E_dist"] == pytest.approx((10 * 1 + 30 * 3) / 40)
    assert agg["all"]["E_len"] == pytest.approx(2 * (10 + 90 + 100 + 280) / 100)
    only = scoring.aggregate(ss, keep=lambda s: s["sequence"] in ("a", "c"))
    assert only["all"]["E_dist"] == pytest.approx((10 + 100) / 30)
    assert "unseen garment" not in agg and scoring.aggregate([]) == {}


def test_wilcoxon_exact_small_samples():
    # n = 5, every difference negative: the exact two-sided p is 2 / 2^5
    a = {k: float(i) for i, k in enumerate("vwxyz")}
    b = {k: v + 1 + 0.1 * i for i, (k, v) in enumerate(a.items())}
    w = scoring.wilcoxon(a, b)
    assert w["n"] == 5 and w["p"] == pytest.approx(2 / 32) and w["wins"] == 1.0
    assert w["median_diff"] == pytest.approx(-1.2)
    # ranks 1..6, the negative ones {1, 2}: W = 3; P(W <= 3) = 5/64 (subsets of 1..6
    # with sum <= 3: {}, {1}, {2}, {3}, {1,2}), two-sided 10/64
    c = {str(i): 0.0 for i in range(1, 7)}
    d = {str(i): (i if i > 2 else -i) * 1.0 for i in range(1, 7)}
    assert scoring.wilcoxon(d, c)["p"] == pytest.approx(10 / 64)
    assert scoring.wilcoxon(c, c)["p"] == 1.0
    with pytest.raises(ValueError, match="common sequences"):
        scoring.wilcoxon({"a": 1.0}, {"b": 2.0})


def test_seed_plan():
    full, abl = list(methods.GARTRANS)[0], list(methods.GARTRANS)[1:]
    b = methods.LearnedBudget(seeds=3, seed_methods=(full,))
    seed0 = {m: 10.0 for m in methods.METHOD_NAMES}
    seed0[abl[2]] = 5.0
    seed0[methods.HOOD] = 6.0
    seed0[full] = 1.0  # the full model is never "the best ablation"
    plan = methods.seed_plan(b, seed0)
    assert {m for m, n in plan.items() if n == 3} == {full, abl[2], methods.HOOD}
    assert all(n == 1 for m, n in plan.items() if m not in (full, abl[2], methods.HOOD))
    every = methods.seed_plan(methods.LearnedBudget(seeds=2), {})
    assert every[full] == 2 and every[methods.LBS] == 1
    with pytest.raises(ValueError, match="seed_methods"):
        methods.LearnedBudget(methods=(full,), seed_methods=(methods.DA,))
    with pytest.raises(ValueError, match="minutes"):
        methods.LearnedBudget(minutes=0)
    with pytest.raises(ValueError, match="epoch_chunks"):
        methods.LearnedBudget(epoch_chunks=0)


def test_stratified_subset():
    recs = [{"id": f"{g[0]}{i}", "held_out": h} for g, h in
            (("m", ["motion"]), ("b", ["body"]), ("g", ["garment"]), ("s", ["body", "motion"]))
            for i in range(3)] + [{"id": "x0", "held_out": []}]
    assert scoring.stratified(recs, 5) == ["m0", "b0", "g0", "s0", "x0"]
    assert scoring.stratified(recs, 7) == ["m0", "b0", "g0", "s0", "x0", "m1", "b1"]
    assert sorted(scoring.stratified(recs, 99)) == sorted(r["id"] for r in recs)
    with pytest.raises(ValueError, match="`n`"):
        scoring.stratified(recs, 0)


def _record(method, per_seq, seed=0):
    seqs = [{"sequence": f"s{i}", "frames": 10, "held_out": ["motion"],
             "metrics": {**{k: v for k in tables.METRICS}, "E_static": v, "E_dynamic": v}}
            for i, v in enumerate(per_seq)]
    agg = scoring.aggregate(seqs)
    return {"kind": learned.KIND, "method": method, "case": "c", "seed": seed, "status": "ok",
            "metrics": agg.pop("all"), "groups": agg, "per_sequence": seqs,
            "test_frames": 10 * len(seqs)}


def test_report_verdicts_from_paired_tests():
    """Full GarTrans lower than an ablation on all 8 sequences: the exact two-sided p is
    2/256, so the Table 1 ordering is "shown"; equal to LBS on half and higher on the
    rest: the LBS targets are "missed"."""
    full, abl = list(methods.GARTRANS)[:2]
    base = [5.0 + i for i in range(8)]
    recs = [_record(full, [v - 0.1 * (i + 1) for i, v in enumerate(base)]),
            _record(abl, base), _record(methods.LBS, [v - 1.0 for v in base])]
    text = "\n".join(learned_report.comparison_markdown(recs))
    assert f"ahead of {abl} on E_dist: **shown**" in text and "p = 0.0078" in text
    assert "at least 30% below LBS on every held-out group: **missed**" in text
    assert "lower than LBS on all five metrics: **missed**" in text
    row = next(line for line in text.splitlines() if line.startswith(f"| {abl} | E_dist"))
    assert "significant (p < 0.05)" in row and "not significant" not in row


def test_report_lower_than_lbs_needs_a_significant_difference_on_every_metric():
    """Lower than LBS on the mean of every metric is "met" only where every paired
    difference is significant: three sequences cannot give p < 0.05 (the smallest exact
    two-sided p is 2/8), eight that all agree can (2/256)."""
    full = methods.FULL
    base = [5.0 + i for i in range(8)]
    few = [_record(full, [v - 0.1 for v in base[:3]]), _record(methods.LBS, base[:3])]
    text = "\n".join(learned_report.comparison_markdown(few))
    assert "lower than LBS on all five metrics: **not significant**" in text
    assert "significantly, p < 0.05, on none" in text
    many = [_record(full, [v - 0.1 for v in base]), _record(methods.LBS, base)]
    text = "\n".join(learned_report.comparison_markdown(many))
    assert "lower than LBS on all five metrics: **met**" in text
    assert "significantly, p < 0.05, on E_dist, E_vnorm, E_fnorm, E_len, E_curv" in text
