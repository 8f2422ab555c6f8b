"""The GPU window's driver (``benchmarks/gpu_window.py``): its time plan, the time-boxed
stage processes, the partial results of a stage cut short, the bundles under the device's
file limit, and a run whose stages fail or are skipped still writing every summary."""
import csv
import json
import os
import runpy
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GW = runpy.run_path(str(ROOT / "benchmarks" / "gpu_window.py"), run_name="gpu_window_test")


def test_allot_shares_the_time_left_by_weight():
    names = list(GW["WEIGHTS"])
    left, spent = 500.0, []
    for i in range(len(names)):
        s = GW["allot"](left, names[i:])
        spent.append(s)
        left -= s
    assert left == pytest.approx(0.0, abs=1e-9)  # every second planned, none twice
    w = GW["WEIGHTS"]
    assert spent[0] == pytest.approx(500.0 * w[names[0]] / sum(w.values()))
    # time a stage leaves unused goes to the later ones, by their weights
    assert GW["allot"](100.0, names[-2:]) == pytest.approx(
        100.0 * w[names[-2]] / (w[names[-2]] + w[names[-1]]))
    assert GW["allot"](-5.0, names) == 0.0
    with pytest.raises(ValueError, match="`names`: unknown stages \\['nope'\\]"):
        GW["allot"](10.0, ["nope"])
    with pytest.raises(ValueError, match="`names`"):
        GW["allot"](10.0, [])


@pytest.mark.parametrize("stage_s, startup_s", [(200.0, 45.0), (40.0, 45.0), (600.0, 0.0)])
def test_split_training_keeps_time_to_start_and_to_test(stage_s, startup_s):
    t = GW["split_training"](stage_s, startup_s)
    assert t["fit"] + t["test"] == pytest.approx(stage_s)
    assert t["test"] >= 0.25 * stage_s
    assert 5.0 <= t["max_time"] <= max(5.0, t["fit"] - startup_s + 1e-9)


def test_hms():
    assert GW["hms"](3725.9) == "00:01:02:05"
    assert GW["hms"](90061) == "01:01:01:01"
    assert GW["hms"](0.2) == "00:00:00:01"


def test_run_command_kills_the_whole_process_group(tmp_path):
    marker = tmp_path / "child_alive"
    child = tmp_path / "child.py"
    child.write_text(f"import time\ntime.sleep(3)\nopen({str(marker)!r}, 'w').close()\n")
    parent = tmp_path / "parent.py"  # starts the child, then waits for it
    parent.write_text(f"import subprocess, sys, time\n"
                      f"subprocess.Popen([sys.executable, {str(child)!r}])\ntime.sleep(30)\n")
    t = time.perf_counter()
    r = GW["run_command"]([sys.executable, str(parent)], 1.5, tmp_path / "log.txt",
                          dict(os.environ))
    assert r["timed_out"] and r["rc"] is not None and r["rc"] < 0
    assert 1.5 <= time.perf_counter() - t < 10
    time.sleep(3)
    assert not marker.exists()
    r = GW["run_command"]([sys.executable, "-c", "print('hi'); raise SystemExit(3)"], 30,
                          tmp_path / "log.txt", dict(os.environ))
    assert r == dict(r, rc=3, timed_out=False)
    log = (tmp_path / "log.txt").read_text()
    assert log.count("$ ") == 2 and "hi" in log


def test_throughput_rows_of_a_finished_and_of_a_cut_run(tmp_path):
    log = tmp_path / "log.txt"
    log.write_text('results: x\n["small", "gartrans", 8, "32-true", 1] 1234\nnoise\n'
                   '["small", "gartrans", 8, "bf16-mixed", 4] 56789\n')
    rows = GW["throughput_rows"](tmp_path, log, "cuda")
    assert [(r["precision"], r["batch"], r["vertex_frames_per_s"]) for r in rows] == \
        [("32-true", 1, 1234.0), ("bf16-mixed", 4, 56789.0)]
    row = {"size": "small", "method": "da", "threads": 8, "precision": "32-true", "batch": 4,
           "vertex_frames_per_s": 10.0, "x_batch1": 2.0, "loss_rel_diff": 0.0, "runs": []}
    (tmp_path / "train_throughput_cuda.json").write_text(json.dumps({"rows": [row]}))
    rows = GW["throughput_rows"](tmp_path, log, "cuda")  # the results file wins
    assert rows == [{k: v for k, v in row.items() if k != "runs"}]


def test_training_summary_reads_the_metrics(tmp_path):
    logs = tmp_path / "fit" / "logs" / "version_0"
    (logs / "checkpoints").mkdir(parents=True)
    for name in ("best-epoch=1.ckpt", "last.ckpt"):
        (logs / "checkpoints" / name).write_bytes(b"x")
    with open(logs / "metrics.csv", "w", newline="") as f:
        w = csv.DictWriter(f, ["epoch", "step", "train/loss_epoch", "val/E_dist"])
        w.writeheader()
        w.writerows([{"epoch": 0, "step": 3, "val/E_dist": 0.5},
                     {"epoch": 0, "step": 3, "train/loss_epoch": 2.0},
                     {"epoch": 1, "step": 7, "val/E_dist": 0.25},
                     {"epoch": 1, "step": 7, "train/loss_epoch": 1.5}])
    test = tmp_path / "test.log"
    test.write_text("noise\ntest split 'test', frame-weighted means:\n| method | E_dist |\n")
    s = GW["training_summary"](tmp_path / "fit", test)
    assert s["epochs"] == 2 and s["steps"] == 7
    assert s["train_loss"] == {"epoch": 1, "value": 1.5}
    assert s["val_E_dist"] == {"epoch": 1, "value": 0.25}
    assert s["checkpoints"] == ["best-epoch=1.ckpt", "last.ckpt"]
    assert s["test_table"] == ["test split 'test', frame-weighted means:", "| method | E_dist |"]
    assert GW["best_checkpoint"](tmp_path / "fit").name == "best-epoch=1.ckpt"
    assert GW["best_checkpoint"](tmp_path / "none") is None


def test_bundle_leaves_checkpoints_out_and_stays_under_the_limit(tmp_path):
    folder = tmp_path / "stage"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "metrics.csv").write_text("a,b\n1,2\n")
    (folder / "sub" / "big.ckpt").write_bytes(os.urandom(4000))
    extra = []
    for name in ("weights-best.ckpt", "weights-last.ckpt"):
        (tmp_path / name).write_bytes(os.urandom(3000))
        extra.append(tmp_path / name)
    b = GW["bundle"](folder, tmp_path / "out.tar.gz", extra, limit=5000)
    assert b["dropped"] == ["weights-last.ckpt"] and not b["over_limit"]
    with tarfile.open(tmp_path / "out.tar.gz") as tar:
        names = sorted(tar.getnames())
    assert names == ["stage/sub/metrics.csv", "stage/weights-best.ckpt"]
    assert b["bytes"] == (tmp_path / "out.tar.gz").stat().st_size <= 5000
    b = GW["bundle"](folder, tmp_path / "out.tar.gz", extra, limit=100)
    assert b["dropped"] == ["weights-last.ckpt", "weights-best.ckpt"] and b["over_limit"]


def test_a_failing_stage_does_not_stop_the_others(tmp_path, monkeypatch):
    """No pack carried: the throughput and training stages are skipped; the inference
    stage's process fails; a stage that raises is reported: every stage is in the
    summary, and each has its bundle."""
    ns = runpy.run_path(str(ROOT / "benchmarks" / "gpu_window.py"), run_name="gw_run")
    calls = []

    def fake_run(cmd, timeout_s, log, env):
        calls.append((cmd, timeout_s))
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text("boom\n")
        return {"cmd": " ".join(cmd), "rc": 1, "wall_s": 0.1, "timed_out": False}

    ns["run_command"] = fake_run
    ns["main"].__globals__["run_command"] = fake_run

    def broken(self, name, seconds, folder):
        raise RuntimeError("broken stage")

    monkeypatch.setattr(ns["Window"], "throughput", broken)
    out = tmp_path / "out"
    assert ns["main"](["--dir", str(tmp_path / "carry"), "--out", str(out), "--work",
                       str(tmp_path / "work"), "--device", "cpu", "--budget-s", "100"]) == 0
    s = json.loads((out / "summary.json").read_text())
    stages = {r["name"]: r for r in s["stages"]}
    assert list(stages) == list(ns["WEIGHTS"])
    assert stages["throughput_gartrans"]["status"] == "failed"
    assert "broken stage" in stages["throughput_gartrans"]["note"]
    assert stages["inference"]["status"] == "failed" and stages["inference"]["rc"] == 1
    assert stages["train_gartrans"]["status"] == stages["train_da"]["status"] == "skipped"
    assert s["datasets"]["throughput"]["status"] == "not carried"
    assert len(calls) == 1 and "benchmarks/inference.py" in calls[0][0]
    assert 0 < calls[0][1] <= 100
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{n}.tar.gz" for n in stages] + ["summary.json", "summary.md"])
    assert len(list(out.iterdir())) <= 8  # the device tool returns 8 files at most
    md = (out / "summary.md").read_text()
    assert "| inference |" in md and "failed (RuntimeError: broken stage)" in md


def test_a_training_stage_fits_then_tests_its_best_checkpoint(tmp_path, monkeypatch):
    ns = runpy.run_path(str(ROOT / "benchmarks" / "gpu_window.py"), run_name="gw_train")
    calls = []

    def fake_run(cmd, timeout_s, log, env):
        calls.append((cmd, timeout_s))
        if "fit" in cmd:  # cut short by its hard limit, after two epochs' checkpoints
            root = Path(cmd[cmd.index("--trainer.default_root_dir") + 1])
            ck = root / "logs" / "version_0" / "checkpoints"
            ck.mkdir(parents=True)
            for name in ("best-epoch=0.ckpt", "last.ckpt"):
                (ck / name).write_bytes(b"not a checkpoint")
            return {"cmd": "fit", "rc": -15, "wall_s": timeout_s, "timed_out": True}
        log.write_text("test split 'test', frame-weighted means:\n| GarTrans | 1.0 |\n")
        return {"cmd": "test", "rc": 0, "wall_s": 1.0, "timed_out": False}

    ns["main"].__globals__["run_command"] = fake_run
    data = {"file": "train.zip", "root": str(tmp_path / "data"), "splits": ["test", "train"],
            "train_chunks": 4}
    monkeypatch.setattr(ns["Window"], "dataset", lambda self, key: data)
    out = tmp_path / "out"
    ns["main"](["--out", str(out), "--work", str(tmp_path / "work"), "--device", "cpu",
                "--budget-s", "215", "--stages", "train_gartrans", "--startup-s", "30"])
    (fit, fit_s), (test, test_s) = calls
    opt = {k: v for k, v in zip(fit, fit[1:]) if k.startswith("--")}
    assert opt["--config"] == "gartrans" and opt["--data.root"] == data["root"]
    assert opt["--data.batch_size"] == "4"  # 8 asked, 4 training chunks
    assert opt["--data.val_split"] == "train" and "--trainer.limit_val_batches" in opt
    assert opt["--trainer.accelerator"] == "cpu"
    plan = GW["split_training"](200.0, 30.0)  # 215 s less the margin
    assert fit_s == pytest.approx(plan["fit"], abs=5)  # less what the start-up took
    assert opt["--trainer.max_time"] == GW["hms"](fit_s - 30.0)  # the fit less its start
    topt = {k: v for k, v in zip(test, test[1:]) if k.startswith("--")}
    assert Path(topt["--ckpt_path"]).name == "best-epoch=0.ckpt"
    assert topt["--data.test_split"] == "test" and "--trainer.limit_test_batches" not in topt
    # the test gets what the stage has left (here the fit returned at once: all of it)
    assert plan["test"] - 5 < test_s <= fit_s + plan["test"] + 1
    r = json.loads((out / "summary.json").read_text())["stages"][0]
    assert r["status"] == "timed out" and r["note"] == "fit timed out"
    assert r["test_table"][1] == "| GarTrans | 1.0 |"
    assert "| GarTrans | 1.0 |" in (out / "summary.md").read_text()


def test_bad_arguments(capsys):
    for argv, words in ((["--budget-s", "0"], "--budget-s"),
                        (["--stages", "nope"], "--stages"),
                        (["--batches", "0"], "--batches"),
                        (["--startup-s", "-1"], "--startup-s")):
        with pytest.raises(SystemExit) as e:
            GW["main"](argv)
        assert e.value.code == 2 and words in capsys.readouterr().err


@pytest.mark.slow
def test_the_shell_script_runs_the_driver_on_the_cpu(tmp_path):
    """``gpu_window.sh`` end to end with nothing carried (its stages skipped): the set-up,
    the hand-over of the time left and the summary in OUT."""
    env = dict(os.environ, GPU_WINDOW_BUDGET_S="300", DEVICE="cpu", OUT=str(tmp_path / "out"),
               PYTHON=sys.executable, GPU_WINDOW_DIR=str(tmp_path / "carry"))
    r = subprocess.run(["bash", "benchmarks/gpu_window.sh", "--stages", "train_da"], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert "garmentgnn 0.1.0" in s["setup_log"] and "set-up:" in s["setup_log"]
    assert 0 < s["budget_s"] <= 300
    assert [r["name"] for r in s["stages"]] == ["train_da"]
    assert s["stages"][0]["status"] == "skipped"
