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


# 8: a spec file's values converted unchecked
@pytest.fixture(scope="module")
def own_files(tmp_path_factory):
    """A skirt file made on anny's regular body and a walk take (test_own_garment's)."""
    import trimesh  # noqa: PLC0415

    from garmentgnn.body.factory import build_body  # noqa: PLC0415
    from garmentgnn.garments import make_garment  # noqa: PLC0415
    from garmentgnn.motion import make_motion  # noqa: PLC0415
    from garmentgnn.motion.bvh import save_bvh  # noqa: PLC0415
    d = tmp_path_factory.mktemp("own")
    body = build_body({"model": "anny", "shape": "regular"})
    g = make_garment("skirt", body, resolution=200, length="mini")
    trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False).export(d / "skirt.obj")
    m = make_motion("walk", body.skeleton, num_frames=24, fps=120.0,
                    rest_joints=body.joints.double())
    save_bvh(d / "walk.bvh", m, body.skeleton, body.joints, scale=0.01)
    return d


@FUZZ
@given(key=st.sampled_from(["scale", "start", "fps", "mapping", "up"]),
       value=st.sampled_from(["cm", "-2", "nan", "[1, 2]", "{a: 1}", "true", "-0.5", "0",
                              "1e999", "''"]))
def test_spec_values_name_their_key(own_files, tmp_path_factory, capsys, key, value):
    """Any value of a BVH entry's key: accepted, or one error line naming the key (never
    Python's conversion words, never a spec written before the refusal)."""
    spec = own_files / f"fuzz-{key}.yaml"
    spec.write_text(f"name: f\nengine: torch\nfps: 30\nframes: 3\nbodies: [regular]\n"
                    f"garments:\n  - file: skirt.obj\nmotions:\n"
                    f"  - {{file: walk.bvh, scale: 0.01, {key}: {value}}}\n")
    out = tmp_path_factory.mktemp("spec") / "out"
    from garmentgnn.data.spec_file import load_spec  # noqa: PLC0415
    try:
        load_spec(spec)
    except ValueError as exc:
        msg = str(exc)
        assert f"`motions[0].{key}`" in msg or "fps" in msg, msg
        assert "could not convert" not in msg and "invalid literal" not in msg, msg
        rc = cli_main(["generate", "--spec", str(spec), "--out", str(out), "--no-estimate",
                       "--no-progress", "--workers", "0"])
        one_error_line(capsys, rc, spec.name)
        assert not out.exists()
        TALLY["spec values", "clear error"] += 1
        return
    TALLY["spec values", "result"] += 1


# 9: a sparse adjacency of another layout than [num_dst, num_src(, edge_dim)]
@FUZZ
@given(sparse=st.integers(1, 4), dense=st.integers(0, 2), batch=st.booleans())
def test_sparse_adjacency_layouts_are_named(sparse, dense, batch):
    import torch  # noqa: PLC0415

    from garmentgnn.nn import SATConv  # noqa: PLC0415
    conv = SATConv(8, 4, heads=2, edge_dim=3).eval()
    x = torch.randn(5, 8)
    if batch:
        adj = torch.ones(2, 5, 5).to_sparse_csr()
    else:
        size = (5,) * sparse + (3,) * dense
        idx = torch.tensor([[0, 1, 3, 4, 2]] * sparse)
        idx[min(1, sparse - 1)] = torch.tensor([1, 2, 4, 0, 2])
        adj = torch.sparse_coo_tensor(idx, torch.randn((5,) + (3,) * dense), size)
    good = not batch and sparse == 2 and dense <= 1
    try:
        out = conv(x, adj, None if dense == 1 else torch.randn(5, 3))
    except ValueError as exc:
        assert not good, exc
        assert str(exc).startswith("`edge_index`: "), exc
        TALLY["sparse adjacency layouts", "clear error"] += 1
        return
    assert good and torch.isfinite(out).all()
    TALLY["sparse adjacency layouts", "result"] += 1
