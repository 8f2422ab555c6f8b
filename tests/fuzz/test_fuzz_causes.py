"""One fuzz case per cause of a silent or unclear answer found on the command line:
each draws other inputs of the same kind than the regression tests' exact ones
(``tests/test_bad_input_*.py``) and checks for one ``error:`` line, no traceback and
the flag or file named, or, for an integer flag, that it stays a count."""
import json
import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _fuzz import FUZZ, TALLY
from garmentgnn.cli import main as cli_main
from garmentgnn.data import export, generate, preset, store
from garmentgnn.training.lightning_cli import main as train_main
from test_bad_input_benchmarks import RESULTS, script
from test_data import fake_simulate
from test_training import NY, root  # noqa: F401  (module-scoped toy dataset: train + val)
from test_training_cli import fast_args

#: the cases that build a run (a few seconds each): fewer examples
RUNS = settings(FUZZ, max_examples=3)
CKPT = str(Path(__file__).resolve().parents[1] / "data" / "gartrans_learn.ckpt")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    return out


def one_error_line(capsys, rc, *names):
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1] if err.strip() else ""
    assert rc != 0 and "error: " in last, err[-800:]  # ours, or argparse's "PROG: error:"
    assert "Traceback" not in err and "expected one argument" not in last, err[-800:]
    assert all(n in last for n in names), last
    return last


# 1: an integer flag read as a fraction
@RUNS
@given(flag=st.sampled_from(["limit_train_batches", "limit_val_batches", "limit_test_batches",
                             "limit_predict_batches"]),
       value=st.one_of(st.integers(1, 9), st.sampled_from([0.25, 0.5, 1.0])))
def test_trainer_counts_stay_counts(root, tmp_path_factory, flag, value):  # noqa: F811
    cli = train_main(["--config", "baselines/da"] + fast_args(root, tmp_path_factory.mktemp("c"))
                     + [f"--trainer.{flag}", str(value)], run=False)
    got = getattr(cli.trainer, flag)
    assert got == value and type(got) is type(value), (flag, value, got)
    for action in cli.parser._actions:  # wherever a union holds both, int is tried first
        args = getattr(getattr(action, "_typehint", None), "__args__", ())
        if int in args and float in args:
            assert args.index(int) < args.index(float), (action.dest, args)
    TALLY["trainer count flags", "result"] += 1


# 2: a run that does nothing
@FUZZ
@given(case=st.sampled_from([("fit", "max_steps"), ("fit", "max_epochs"),
                             ("fit", "limit_train_batches"), ("validate", "limit_val_batches"),
                             ("test", "limit_test_batches"),
                             ("predict", "limit_predict_batches")]),
       zero=st.sampled_from(["0", "0.0"]))
def test_runs_that_would_do_nothing_name_the_flag(root, tmp_path_factory, capsys, case,  # noqa: F811
                                                  zero):
    sub, flag = case
    if flag in ("max_steps", "max_epochs") and zero == "0.0":
        zero = "0"  # integer flags
    ckpt = [] if sub == "fit" else ["--ckpt_path", CKPT]
    rc = cli_main(["train", sub, "--config", "baselines/da"] + ckpt
                  + fast_args(root, tmp_path_factory.mktemp("z")) + [f"--trainer.{flag}", zero])
    one_error_line(capsys, rc, f"--trainer.{flag}", "would")
    TALLY["runs doing nothing", "clear error"] += 1


# 3: a checkpoint's mismatch described in the user's terms
@FUZZ
@given(flag=st.sampled_from(["--history", "--num-landmarks"]), value=st.integers(1, 200))
def test_show_settings_follow_the_checkpoint(dataset, tmp_path_factory, capsys, flag, value):
    out = tmp_path_factory.mktemp("s")
    rc = cli_main(["show", "--data", str(dataset), "--ckpt", CKPT, flag, str(value),
                   "--out", str(out / "s")])
    last = one_error_line(capsys, rc)
    assert (f"{flag} {value}" in last or f"--ckpt {CKPT}" in last), last
    assert "`inputs" not in last and "`scene`" not in last and not list(out.iterdir())
    TALLY["show mismatch", "clear error"] += 1


# 4: a method's need checked when the run is built
@RUNS
@given(case=st.sampled_from([("baselines/hood", 1), ("baselines/ncs", 1),
                             ("baselines/ncs", 2)]))
def test_history_below_a_methods_need_names_the_flag(root, tmp_path_factory, capsys,  # noqa: F811
                                                     case):
    config, history = case
    tmp = tmp_path_factory.mktemp("h")
    rc = cli_main(["train", "fit", "--config", config]
                  + fast_args(root, tmp, history=history, train_batches=1))
    one_error_line(capsys, rc, f"--data.history {history}", "or more")
    assert not list(tmp.rglob("*.ckpt"))
    TALLY["method needs", "clear error"] += 1


# 5: a tool's failure before the tool starts
@FUZZ
@given(fmt=st.sampled_from(list(export.EXPORT_SUFFIX)),
       where=st.sampled_from(["folder", "below_file"]))
def test_export_paths_are_checked_before_any_work(dataset, tmp_path_factory, capsys, fmt,
                                                  where):
    tmp = tmp_path_factory.mktemp("x")
    (tmp / "afile").write_text("x")
    out = tmp / f"scene{export.EXPORT_SUFFIX[fmt]}"
    if where == "folder":
        out.mkdir()
    else:
        out = tmp / "afile" / out.name
    seq = sorted((Path(dataset) / store.SEQUENCES).glob("*.npz"))[0]
    rc = cli_main(["export", "--seq", str(seq), "--format", fmt, "--out", str(out)])
    one_error_line(capsys, rc, f"--out {out}")
    assert sorted(p.name for p in tmp.iterdir()) == sorted(["afile"] + [out.name] * (
        where == "folder"))
    TALLY["export paths", "clear error"] += 1


# 6: a reader that assumes one layout
@FUZZ
@given(source=st.sampled_from(["curves.json", "curves_seeds.json", "curves_hood.json"]),
       damage=st.sampled_from(["none", "no_runs", "runs_not_list", "no_curve", "variant_list",
                               "no_seed", "run_not_dict"]), data=st.data())
def test_curves_reader_reads_each_layout_or_names_the_file(tmp_path_factory, source, damage,
                                                           data):
    doc = json.loads((RESULTS / "learning" / source).read_text())
    name = data.draw(st.sampled_from(sorted(doc["variants"])))
    v = doc["variants"][name]
    runs = v.get("runs")
    if damage == "no_runs":
        v.pop("runs", None), v.pop("curve", None)
    elif damage == "runs_not_list":
        v["runs"] = {"0": runs}
    elif damage == "no_curve":
        (runs[0] if runs else v).pop("curve")
    elif damage == "variant_list":
        doc["variants"][name] = [v]
    elif damage == "no_seed" and runs:
        runs[0].pop("seed")
    elif damage == "run_not_dict" and runs:
        runs[0] = [runs[0]]
    path = tmp_path_factory.mktemp("c") / source
    path.write_text(json.dumps(doc))
    try:
        res = script("learning")["merge_curves"]([path])
    except (ValueError, FileNotFoundError) as e:
        assert str(path) in str(e) and "\n" not in str(e), e
        TALLY["curves layouts", "clear error"] += 1
        return
    assert all(isinstance(r["curve"], list) and "seed" in r
               for v in res["variants"].values() for r in v["runs"])
    TALLY["curves layouts", "result"] += 1


# 7: a value starting with a minus handed to its flag
@FUZZ
@given(case=st.sampled_from([("bench", "--shard"), ("bench", "--seeds"),
                             ("bench", "--minutes"), ("export", "--start-frame")]),
       value=st.sampled_from(["-1/2", "-1", "-0.5", "-.5", "-1e3", "-3/-4"]))
def test_values_starting_with_a_minus_reach_their_flag(dataset, tmp_path_factory, capsys,
                                                       case, value):
    verb, flag = case
    tmp = tmp_path_factory.mktemp("m")
    if verb == "bench":
        argv = ["bench", "--preset", "converge", "--out", str(tmp / "b"), "--no-progress",
                flag, value]
    else:
        seq = sorted((Path(dataset) / store.SEQUENCES).glob("*.npz"))[0]
        argv = ["export", "--seq", str(seq), "--format", "pc2", "--out", str(tmp / "x.pc2"),
                flag, value]
    try:
        rc = cli_main(argv)
    except SystemExit as e:
        rc = e.code
    if rc == 0:  # a negative start frame is one
        assert verb == "export"
        TALLY["minus values", "result"] += 1
        return
    one_error_line(capsys, rc, flag)
    shutil.rmtree(tmp, ignore_errors=True)
    TALLY["minus values", "clear error"] += 1
