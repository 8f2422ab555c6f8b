"""An ensemble ground truth (garmentgnn.data.ensemble, ``garmentgnn generate --ensemble
K``): which sequences, the members' perturbed inputs, resuming, a member made again bit
for bit, the scores against a numpy computation, the bench report's rows, and each bad
input as one ``error:`` line with nothing written.  The simulator is the test double of
test_data (members then differ by what the 1e-7 m moves; the torch engine's run is in
test_bench_ensemble)."""
import json
import runpy
import shutil
from pathlib import Path

import numpy as np
import pytest

from garmentgnn.bench.methods import LBS
from garmentgnn.bench.report import write_report
from garmentgnn.bench.scoring import score_ensemble
from garmentgnn.bench.tables import METRICS
from garmentgnn.cli import main as cli_main
from garmentgnn.data import SequenceChunks, generate, preset, store
from garmentgnn.data.compact import TOLERANCE, pack, unpack
from garmentgnn.data.ensemble import ENSEMBLE, load_ensemble, member_id, pick_sequences
from test_bad_input_cli import one_error
from test_data import fake_simulate

ROOT = Path(__file__).resolve().parents[1]
MGN_CKPT = ROOT / "tests" / "data" / "mgn_learn.ckpt"
FAKE = ["--workers", "0", "--no-estimate", "--no-progress",
        "--simulate-fn", "test_data:fake_simulate"]


def dataset(out, seed=0):
    assert generate(preset("tiny", seed=seed), out, workers=0, simulate_fn=fake_simulate,
                    progress=False).done == 8
    return out


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The tiny preset (test double) with 3 members of 2 test sequences."""
    out = dataset(tmp_path_factory.mktemp("ens") / "d")
    assert cli_main(["generate", "--ensemble", "3", "--sequences", "2", "--out", str(out)]
                    + FAKE) == 0
    return out


def copy(src, tmp_path):
    shutil.copytree(src, tmp_path / "c")
    return tmp_path / "c"


def test_sequences_are_spread_over_groups_then_kinds():
    def rec(i, held, kind, split="test", status="ok"):
        return {"id": i, "held_out": held, "garment": {"kind": kind}, "split": split,
                "status": status}
    records = [rec("a1", ["garment"], "dress"), rec("a2", ["garment"], "dress"),
               rec("a3", ["garment"], "jumpsuit"), rec("b1", ["motion"], "skirt"),
               rec("b2", ["motion"], "tshirt"), rec("c1", ["body", "motion"], "skirt"),
               rec("t", [], "skirt", split="train"), rec("f", ["motion"], "skirt",
                                                         status="failed")]
    # groups garment, motion, several in turn; within garment: dress, jumpsuit, dress
    assert pick_sequences(records, 4) == ["a1", "b1", "c1", "a3"]
    assert pick_sequences(records, 10) == ["a1", "b1", "c1", "a3", "b2", "a2"]


def test_members_move_the_rest_garment_by_the_perturbation(made):
    doc = store.read_manifest(made / ENSEMBLE)
    head = doc["ensemble"]
    assert head["members"] == 3 and len(head["sequences"]) == 2
    assert head["dataset"]["content_sha256"] == store.read_manifest(made)["content_sha256"]
    assert doc["counts"] == {"ok": 6}
    for sid in head["sequences"]:
        rest = store.load_sequence(made / "sequences" / f"{sid}.npz")["garment_vertices"]
        moved = [store.load_sequence(made / ENSEMBLE / "sequences" /
                                     f"{member_id(sid, k)}.npz")["garment_vertices"]
                 for k in (1, 2, 3)]
        for m in moved:
            d = np.linalg.norm(m.astype(np.float64) - rest, axis=-1)
            assert 0 < d.max() <= 2e-7 and d.mean() > 5e-8  # 1e-7 m, float32-rounded
        assert not np.array_equal(moved[0], moved[1])  # each member its own directions


def test_resume_skips_and_a_member_made_again_is_the_same_file(made, tmp_path):
    out = copy(made, tmp_path)
    folder = out / ENSEMBLE
    before = store.read_manifest(folder)
    victim = sorted((folder / "sequences").glob("*.npz"))[1]
    victim.unlink()
    assert cli_main(["generate", "--ensemble", "3", "--sequences", "2", "--out", str(out)]
                    + FAKE) == 0
    after = store.read_manifest(folder)
    assert store.file_sha256(victim) == {r["id"]: r["sha256"] for r in before["items"]}[
        victim.stem]
    assert after["content_sha256"] == before["content_sha256"]


def test_scores_against_a_numpy_computation(made):
    ens = load_ensemble(made)
    assert ens["members"] == 3 and not ens["incomplete"]
    test = SequenceChunks(made, "test", chunk=10 ** 6, ids=sorted(ens["sequences"]))
    recs = score_ensemble(lambda i, item: test[i].gt, test, ens, early=3)
    assert len(recs) == 2
    for i, r in enumerate(recs):
        sid = test.records[test.index[i][0]]["id"]
        M = np.stack([np.load(made / ENSEMBLE / "sequences" / f"{member_id(sid, k)}.npz")[
            "positions"].astype(np.float64) for k in (1, 2, 3)])
        gt = store.load_sequence(made / "sequences" / f"{sid}.npz")["positions"]
        lbs = test[i].skinned().double().numpy()
        mean = M.mean(0)

        def cm(a, b):  # per frame, the mean vertex distance in cm
            return np.linalg.norm(a - b, axis=-1).mean(-1) * 100
        e, e_lbs = cm(gt, mean), cm(lbs, mean)
        floor = np.mean([cm(m, mean) for m in M], 0)
        spread = np.mean([cm(M[a], M[b]) for a, b in ((0, 1), (0, 2), (1, 2))], 0)
        a = r["all"]
        assert a["E_mean"] == pytest.approx(e.mean(), rel=1e-9)
        assert a["floor_mean"] == pytest.approx(floor.mean(), rel=1e-9)
        assert a["spread"] == pytest.approx(spread.mean(), rel=1e-9)
        assert a["E_each"] == pytest.approx([cm(gt, m).mean() for m in M], rel=1e-9)
        assert a["skill"] == pytest.approx((e_lbs.mean() - e.mean()) /
                                           (e_lbs.mean() - floor.mean()), rel=1e-9)
        assert r["early"]["E_mean"] == pytest.approx(e[:3].mean(), rel=1e-9)
        assert r["late"]["E_mean"] == pytest.approx(e[3:].mean(), rel=1e-9)
        assert r["per_frame"]["floor_mean"] == pytest.approx(list(floor), rel=1e-9)


def test_the_bench_report_shows_the_ensemble_rows(made, tmp_path):
    ens = load_ensemble(made)
    test = SequenceChunks(made, "test", chunk=10 ** 6, ids=sorted(ens["sequences"]))
    preds = {LBS: lambda i, item: item.skinned(), "ground truth": lambda i, item: item.gt}
    base = {"kind": "learned", "case": "c", "status": "ok", "train_seconds": 0.0,
            "timing": {"latency_ms": 1.0, "throughput_fps": 1.0},
            "metrics": {m: 1.0 for m in METRICS}}
    records = [dict(base, method=m, seed=s, ensemble=score_ensemble(p, test, ens))
               for m, p in preds.items() for s in (0, 1)]
    paths = write_report(records, tmp_path / "r")
    text = paths["report"].read_text()
    section = text.split("### Against the ensemble ground truth")[1]
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in
            section.splitlines() if line.startswith("| ")}
    assert float(rows[LBS][5]) == 0  # LBS's own skill
    assert rows["ground truth"][-1].strip(" |") == "2"  # sequences
    assert "ensemble.png" in section and paths["ensemble"].is_file()
    e = [r["all"]["E_mean"] for r in records[2]["ensemble"]]
    n = [r["all"]["frames"] for r in records[2]["ensemble"]]
    assert float(rows["ground truth"][1]) == pytest.approx(np.average(e, weights=n), rel=1e-2)


def test_a_packed_ensemble_unpacks_beside_its_dataset(made, tmp_path):
    """The compact packer carries an ensemble: unpacked into a copy of its dataset it
    reads as the original, positions within the packer's tolerance."""
    out = copy(made, tmp_path)
    shutil.rmtree(out / ENSEMBLE)
    pack(made / ENSEMBLE, tmp_path / "e.zip")
    unpack(tmp_path / "e.zip", out / ENSEMBLE)
    a, b = load_ensemble(made), load_ensemble(out)
    assert a["members"] == b["members"] == 3 and a["sequences"].keys() == b["sequences"].keys()
    for sid, e in a["sequences"].items():
        assert np.abs(e["positions"] - b["sequences"][sid]["positions"]).max() <= TOLERANCE
        assert np.array_equal(e["valid"], b["sequences"][sid]["valid"])


# ------------------------------------------------------------------ bad input
def test_fewer_than_two_members_is_one_line_and_nothing_written(made, tmp_path, capsys):
    out = copy(made, tmp_path)
    shutil.rmtree(out / ENSEMBLE)
    rc = cli_main(["generate", "--ensemble", "1", "--sequences", "2", "--out", str(out)]
                  + FAKE)
    one_error(capsys, rc, "--ensemble", "K >= 2")
    assert not (out / ENSEMBLE).exists()


def test_an_ensemble_of_another_dataset_is_refused(made, tmp_path, capsys):
    other = dataset(tmp_path / "other", seed=1)
    shutil.copytree(made / ENSEMBLE, other / ENSEMBLE)
    files = sorted(p.name for p in (other / ENSEMBLE).rglob("*"))
    rc = cli_main(["generate", "--ensemble", "3", "--sequences", "2", "--out", str(other)]
                  + FAKE)
    one_error(capsys, rc, "--out", str(other / ENSEMBLE), "an ensemble of another dataset")
    assert sorted(p.name for p in (other / ENSEMBLE).rglob("*")) == files
    rc = cli_main(["bench", "--preset", "tiny", "--learned-only", "--data", str(other),
                   "--out", str(tmp_path / "b")])
    one_error(capsys, rc, "--data", "an ensemble of another dataset")
    assert not (tmp_path / "b").exists()
    with pytest.raises(SystemExit) as e:
        mgn_learn_main(["score", "--mgn", str(MGN_CKPT), "--data", str(other),
                        "--out", str(tmp_path / "s")])
    assert str(e.value.code).startswith(f"error: --data {other}:")
    assert "an ensemble of another dataset" in str(e.value.code)
    assert not (tmp_path / "s").exists()


def test_a_member_with_another_frame_count_is_refused(made, tmp_path, capsys):
    out = copy(made, tmp_path)
    folder = out / ENSEMBLE
    doc = store.read_manifest(folder)
    rec = doc["items"][0]
    path = store.sequence_path(folder, rec)
    seq = store.load_sequence(path)
    meta = seq.pop("meta")
    T = seq["positions"].shape[0]
    for k in ("positions", "converged", "newton_iterations", "residual",
              "motion_rotations", "motion_translation"):
        seq[k] = seq[k][:T - 1]
    store.write_sequence(path, seq, dict(meta, num_frames=T - 1))
    rec["sha256"] = store.file_sha256(path)  # a consistent file: only its frames differ
    (folder / store.MANIFEST).write_text(json.dumps(doc))
    rc = cli_main(["bench", "--preset", "tiny", "--learned-only", "--data", str(out),
                   "--out", str(tmp_path / "b")])
    one_error(capsys, rc, "--data", f"{path} has {T - 1} frames", f"{T} of")
    assert not (tmp_path / "b").exists()
    with pytest.raises(SystemExit) as e:
        mgn_learn_main(["score", "--mgn", str(MGN_CKPT), "--data", str(out),
                        "--out", str(tmp_path / "s")])
    assert f"has {T - 1} frames" in str(e.value.code)
    assert not (tmp_path / "s").exists()


def test_sequences_without_ensemble_is_refused(made, tmp_path, capsys):
    out = copy(made, tmp_path)
    rc = cli_main(["generate", "--sequences", "2", "--out", str(out)] + FAKE)
    one_error(capsys, rc, "--sequences", "--ensemble")
    with pytest.raises(SystemExit):
        mgn_learn_main(["score", "--mgn", str(MGN_CKPT), "--data", str(out), "--on-ensemble",
                        "--sequences", "2", "--out", str(tmp_path / "s")])
    assert "--sequences: --on-ensemble" in capsys.readouterr().err
    shutil.rmtree(out / ENSEMBLE)  # a dataset without one
    with pytest.raises(SystemExit) as e:
        mgn_learn_main(["score", "--mgn", str(MGN_CKPT), "--data", str(out), "--on-ensemble",
                        "--out", str(tmp_path / "s")])
    assert str(e.value.code).startswith("error: --on-ensemble") and "--ensemble" in str(
        e.value.code)
    assert not (tmp_path / "s").exists()


def mgn_learn_main(argv):
    return runpy.run_path(str(ROOT / "benchmarks" / "mgn_learn.py"),
                          run_name="mgn_learn_ensemble")["main"](argv)
