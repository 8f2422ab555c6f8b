"""Scores against an ensemble ground truth (garmentgnn.bench.ensemble) against hand
computations on points along one axis, where every distance is a difference of
coordinates."""
import pytest
import torch

from garmentgnn.bench.ensemble import ensemble_frames, ensemble_scores, pooled_skill


def along_x(xs):
    """``[T, 1, 3]`` one vertex per frame at ``(x, 0, 0)`` metres."""
    out = torch.zeros(len(xs), 1, 3, dtype=torch.float64)
    out[:, 0, 0] = torch.tensor(xs, dtype=torch.float64)
    return out


def test_two_members_against_the_hand_computation():
    d, a, b = 0.01, 0.02, 0.05  # members at +-d, the prediction at a, LBS at b (m)
    members = torch.stack([along_x([d] * 3), along_x([-d] * 3)])
    f = ensemble_frames(along_x([a] * 3), members, along_x([b] * 3))
    cm = {"E_mean": 2.0, "E_members": (1.0 + 3.0) / 2, "E_LBS": 5.0, "floor_mean": 1.0,
          "spread": 2.0}
    for k, v in cm.items():
        torch.testing.assert_close(f[k], torch.full((3,), v, dtype=torch.float64))
    s = ensemble_scores(along_x([a] * 3), members, along_x([b] * 3))["all"]
    assert s["skill"] == pytest.approx((5.0 - 2.0) / (5.0 - 1.0))
    assert s["frames"] == 3


def test_three_members_spread_and_floor():
    members = torch.stack([along_x([0.0]), along_x([0.01]), along_x([0.03])])
    f = ensemble_frames(along_x([0.0]), members, along_x([0.0]))
    mean = 4.0 / 3  # cm
    assert float(f["spread"][0]) == pytest.approx((1.0 + 3.0 + 2.0) / 3)
    assert float(f["floor_mean"][0]) == pytest.approx(
        (mean + abs(1 - mean) + abs(3 - mean)) / 3)
    assert float(f["E_members"][0]) == pytest.approx((0 + 1 + 3) / 3)


def test_early_and_late_frames_and_the_pooled_skill():
    members = torch.stack([along_x([0.01] * 4), along_x([-0.01] * 4)])
    pred = along_x([0.09, 0.02, 0.04, 0.03])  # frame 0 is not scored
    valid = torch.tensor([False, True, True, True])
    s = ensemble_scores(pred, members, along_x([0.05] * 4), valid, early=1)
    assert s["early"]["E_mean"] == pytest.approx(2.0) and s["early"]["frames"] == 1
    assert s["late"]["E_mean"] == pytest.approx(3.5) and s["late"]["frames"] == 2
    assert s["all"]["E_mean"] == pytest.approx(3.0) and s["all"]["frames"] == 3
    other = {"E_LBS": 4.0, "E_mean": 4.0, "floor_mean": 2.0, "frames": 1}  # skill 0
    # pooled: (3 * (5 - 3) + 1 * 0) / (3 * (5 - 1) + 1 * 2)
    assert pooled_skill([s["all"], other]) == pytest.approx(6.0 / 14.0)
    assert ensemble_scores(pred, members, pred, valid, early=0)["early"] == {}


def test_bad_input_is_named():
    one = along_x([0.0, 0.0])
    with pytest.raises(ValueError, match="K >= 2"):
        ensemble_frames(one, one.unsqueeze(0), one)
    two = torch.stack([one, one])
    with pytest.raises(ValueError, match="`pred`"):
        ensemble_frames(along_x([0.0]), two, one)
    with pytest.raises(ValueError, match="`valid`"):
        ensemble_scores(one, two, one, torch.tensor([True]))
    with pytest.raises(ValueError, match="`early`"):
        ensemble_scores(one, two, one, early=-1)


# ------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_torch_engine_ensemble_scored_by_the_bench(tmp_path):
    """The tiny preset's test split, 2 sequences x 3 members simulated by the torch engine
    (about 1.5 min on one core), scored by ``garmentgnn bench`` (LBS only): the report's
    row against a numpy computation from the member files."""
    import json  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415

    from garmentgnn.bench.methods import LBS  # noqa: PLC0415
    from garmentgnn.cli import main as cli_main  # noqa: PLC0415
    from garmentgnn.data import SequenceChunks, generate, preset  # noqa: PLC0415
    from garmentgnn.data.ensemble import ENSEMBLE, member_id  # noqa: PLC0415
    from test_data import fake_simulate  # noqa: PLC0415

    data = tmp_path / "d"  # the dataset's own sequences: the test double (inputs, LBS)
    assert generate(preset("tiny"), data, workers=0, simulate_fn=fake_simulate,
                    progress=False).done == 8
    assert cli_main(["generate", "--ensemble", "3", "--sequences", "2", "--out", str(data),
                     "--workers", "0", "--no-estimate", "--no-progress"]) == 0
    assert cli_main(["bench", "--preset", "tiny", "--learned-only", "--methods", LBS,
                     "--data", str(data), "--out", str(tmp_path / "b"), "--no-progress"]) == 0
    rec = next(r for r in json.loads((tmp_path / "b" / "results.json").read_text())["records"]
               if r["kind"] == "learned")
    ens = {r["sequence"]: r for r in rec["ensemble"]}
    assert len(ens) == 2
    test = SequenceChunks(data, "test", chunk=10 ** 6, ids=sorted(ens))
    for i in range(len(test)):
        item = test[i]
        M = np.stack([np.load(data / ENSEMBLE / "sequences" /
                              f"{member_id(item.seq_id, k)}.npz")["positions"]
                      for k in (1, 2, 3)]).astype(np.float64)
        mean = M.mean(0)
        d = [np.linalg.norm(m - mean, axis=-1).mean(-1) * 100 for m in M]
        assert 0 < np.mean(d) < 1  # the members differ, by less than 1 cm in 8 frames
        lbs = np.linalg.norm(item.skinned().double().numpy() - mean, axis=-1).mean() * 100
        got = ens[item.seq_id]["all"]
        assert got["floor_mean"] == pytest.approx(np.mean(d), rel=1e-6)
        assert got["E_mean"] == pytest.approx(lbs, rel=1e-6) and got["skill"] == 0
    text = (tmp_path / "b" / "report.md").read_text()
    assert "### Against the ensemble ground truth" in text
    assert (tmp_path / "b" / "ensemble.png").is_file()


def test_a_gap_is_chaos_where_its_sign_depends_on_the_member():
    from garmentgnn.bench.ensemble_report import gap  # noqa: PLC0415

    def rec(seq, e_mean, each, frames):
        return {"sequence": seq, "all": {"E_mean": e_mean, "E_each": each, "frames": frames}}
    a = [rec("s1", 2.0, [1.0, 3.0], 1), rec("s2", 4.0, [4.0, 4.0], 3)]
    b = [rec("s1", 3.0, [2.0, 2.0], 1), rec("s2", 5.0, [5.5, 4.5], 3),
         rec("s3", 1.0, [1.0, 1.0], 9)]  # s3: only b scored it
    g = gap(a, b)
    assert g["sequences"] == 2 and g["gap"] == pytest.approx((1 * -1 + 3 * -1) / 4)
    # against member 1: (1 * (1 - 2) + 3 * (4 - 5.5)) / 4, member 2: (1 * 1 + 3 * -0.5) / 4
    assert g["gap_each"] == pytest.approx([-5.5 / 4, -0.5 / 4])
    assert not g["chaos"] and g["flipped"] == 1  # s1: a ahead on member 1, b on member 2
    assert gap(b, a)["gap_each"] == pytest.approx([5.5 / 4, 0.5 / 4])
    a[1]["all"]["E_each"] = [4.0, 5.0]  # member 2 now puts b ahead overall
    g = gap(a, b)
    assert g["chaos"] and g["gap_each"][1] == pytest.approx((1 + 3 * 0.5) / 4)
