"""Bad arguments to the scripts in ``benchmarks/``: a list flag given twice kept only its
last values, a value given twice ran twice, a count of 0 or a missing file ended in a
traceback, a merge of a corrupt file did not name it.  Each is now one ``error:`` line
naming the flag (exit status 2) or, for a repeated flag, the values added up
(:mod:`garmentgnn._argparse`)."""
import argparse
import json
import runpy
from pathlib import Path

import pytest
import torch

from garmentgnn._argparse import existing_dir, existing_file

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
_SCRIPTS = {}


def script(name):
    """The functions of ``benchmarks/<name>.py`` or ``benchmarks/experiments/<name>.py``
    (loaded once)."""
    if name not in _SCRIPTS:
        path = BENCHMARKS / f"{name}.py"
        path = path if path.is_file() else BENCHMARKS / "experiments" / f"{name}.py"
        _SCRIPTS[name] = runpy.run_path(str(path), run_name=f"{name}_args_check")
    return _SCRIPTS[name]


def _ran(*args, **kwargs):
    raise AssertionError("the benchmark ran with these arguments")


def refused(capsys, fn, argv, *words):
    """``fn(argv)`` exits with status 2 and one last ``error:`` line naming ``words``
    (before it chooses its output folder: the benchmark would run after that)."""
    saved = fn.__globals__.get("output_path")
    fn.__globals__["output_path"] = _ran
    try:
        with pytest.raises(SystemExit) as e:
            fn(argv)
    finally:
        fn.__globals__["output_path"] = saved
    err = capsys.readouterr().err.strip()
    # argparse prints its error and exits with 2; a script's own check exits with the line
    last = err.splitlines()[-1] if e.value.code == 2 else str(e.value.code)
    assert "error: " in last and "Traceback" not in err, err[-800:]
    assert all(w in last for w in words), last
    return last


@pytest.fixture
def data(tmp_path):
    """A folder that passes as a dataset (a manifest without items): the arguments are
    checked before anything is read from it."""
    (tmp_path / "manifest.json").write_text('{"items": []}')
    return str(tmp_path)


# ------------------------------------------------------------------ learning.py
def test_learning_repeated_seed_flags_add_up(data):
    """`--seed 0 --seed 1 --seed 2` ran seed 2 only."""
    parse = script("learning")["parse_args"]
    assert parse(["curves", "--data", data, "--seed", "0", "--seed", "1", "--seed", "2"]
                 ).seed == [0, 1, 2]
    assert parse(["curves", "--data", data, "--seed", "3", "4"]).seed == [3, 4]
    assert parse(["curves", "--data", data]).seed == [0]
    v = parse(["curves", "--data", data, "--variants", "config", "--variants", "DA-style"])
    assert v.variants == ["config", "DA-style"]


@pytest.mark.parametrize("argv, words", [
    (["--seed", "0", "0", "0"], ["--seed: 0 given more than once"]),
    (["--seed", "1", "--seed", "1"], ["--seed: 1 given more than once"]),
    (["--threads", "0"], ["argument --threads: expected an integer >= 1, got 0"]),
    (["--steps", "10", "--every", "50"], ["--every 50: more than --steps 10"]),
    (["--steps", "0"], ["argument --steps: expected an integer >= 1"]),
    (["--variants", "config", "config"], ["--variants: config given more than once"]),
])
def test_learning_bad_counts_and_repeats_are_refused(capsys, data, argv, words):
    refused(capsys, script("learning")["parse_args"], ["curves", "--data", data] + argv,
            *words)


def test_learning_missing_dataset_is_one_line(capsys, tmp_path):
    """A missing --data printed a traceback."""
    refused(capsys, script("learning")["main"], ["curves", "--data", str(tmp_path / "typo"),
                                                 "--out", str(tmp_path / "o")],
            f"--data {tmp_path / 'typo'}", "garmentgnn generate")


def test_learning_merge_names_a_missing_or_corrupt_file(capsys, tmp_path):
    """merge on a corrupt JSON said "Expecting value" without the file; a missing one
    printed a traceback."""
    main = script("learning")["main"]
    out = ["--out", str(tmp_path / "o")]
    refused(capsys, main, ["merge", "--curves", str(tmp_path / "none.json")] + out,
            "argument --curves", "none.json: no such file")
    bad = tmp_path / "bad.json"
    bad.write_text('{"variants": {')
    refused(capsys, main, ["merge", "--curves", str(bad)] + out,
            f"--curves {bad}: not valid JSON")
    grad = tmp_path / "grad.json"
    grad.write_text(json.dumps({"command": "python benchmarks/learning.py grad"}))
    refused(capsys, main, ["merge", "--curves", str(grad)] + out,
            f"--curves: {grad}: no 'variants'")
    with pytest.raises(FileNotFoundError, match="none.json: no such file"):
        script("learning")["merge_curves"]([tmp_path / "none.json"])


RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def test_learning_merge_reads_the_first_curves_layout(tmp_path):
    """`merge --curves docs/results/learning/curves.json` (a file of the first layout: one
    seed, each variant's curve beside its settings) ended in `KeyError: 'runs'`."""
    merge = script("learning")["merge_curves"]
    old = RESULTS / "learning" / "curves.json"
    doc = json.loads(old.read_text())
    assert "seed" in doc and all("curve" in v for v in doc["variants"].values())
    res = merge([old])
    assert res["seeds"] == [doc["seed"]]
    for name, v in doc["variants"].items():
        (run,) = res["variants"][name]["runs"]
        assert run["curve"] == v["curve"] and run["seed"] == doc["seed"]
    assert script("learning")["curves_markdown"](res)  # the table reads it too
    new = RESULTS / "learning" / "curves_seeds.json"  # today's layout, several seeds
    assert merge([new])["variants"] == json.loads(new.read_text())["variants"]


def test_learning_merge_refuses_another_results_file_before_merging(capsys, tmp_path):
    """Every file is read and checked before anything is merged; one that holds no
    learning curve (an oracle result has 'variants' too) is named."""
    main = script("learning")["main"]
    oracle = RESULTS / "learning" / "oracle.json"
    refused(capsys, main, ["merge", "--curves", str(RESULTS / "learning" / "curves_seeds.json"),
                           str(oracle), "--out", str(tmp_path / "o")],
            f"--curves: {oracle}", "holds no learning curve")
    assert not (tmp_path / "o").exists()


def test_mgn_learn_merge_checks_its_files_before_scoring(capsys, tmp_path):
    """`mgn_learn.py score --merge X.json` read X only after scoring every method, and a
    file of another kind ended in `KeyError: 'methods'`."""
    run_score = script("mgn_learn")["run_score"]
    other = RESULTS / "mgn_learn" / "curves.json"
    for path, words in ((other, [f"--merge: {other}", "no 'methods'"]),
                        (tmp_path / "none.json", ["--merge", "none.json: no such file"])):
        args = argparse.Namespace(merge=[str(path)], merge_names=None, out=str(tmp_path / "o"),
                                  mgn=None, data=None, other=[], starts=[], split="test",
                                  sequences=None)
        with pytest.raises(SystemExit) as e:
            run_score(args)
        assert all(w in str(e.value.code) for w in words), e.value.code
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ the other scripts
CASES = [
    ("engine_ladder", ["--data", "{typo}"], ["argument --data", "garmentgnn generate"]),
    ("engine_ladder", ["--data", "{data}", "--per-group", "0"], ["--per-group"]),
    ("engines", ["--sizes", "300", "--sizes", "300"], ["--sizes: 300 given more than once"]),
    ("engines", ["--threads", "0"], ["argument --threads"]),
    ("engines", ["--cases", "hang", "hang"], ["--cases: hang given more than once"]),
    ("error_split", ["--data", "{data}", "--split", "tset"], ["--split tset"]),
    ("gt_noise", ["--scales", "nan"], ["argument --scales: expected a finite number"]),
    ("gt_noise", ["--scales", "0"], ["argument --scales: expected a number > 0"]),
    ("gt_noise", ["--engines", "torch", "torch"], ["--engines: torch given more than once"]),
    ("inference", ["--batches", "0"], ["argument --batches"]),
    ("inference", ["--sizes", "1000", "--sizes", "1000"], ["--sizes: 1000 given"]),
    ("layers", ["--threads", "0"], ["argument --threads"]),
    ("layers", ["--baseline", "{typo}"], ["argument --baseline", "no such folder"]),
    ("layers", ["--layers", "sat", "--layers", "sat"], ["--layers: sat given"]),
    ("simulator", ["--stiffness", "inf"], ["argument --stiffness"]),
    ("simulator", ["--threads", "1", "1"], ["--threads: 1 given more than once"]),
    ("static_drape_steps", ["--data", "{data}", "--minutes", "0"], ["argument --minutes"]),
    ("static_drape_steps", ["--data", "{data}", "--reference", "{typo}"],
     ["--reference", "no such file"]),
]


@pytest.mark.parametrize("name, argv, words", CASES)
def test_other_benchmark_arguments_are_checked(capsys, tmp_path, data, name, argv, words):
    """Each ran with the last of a repeated list flag, ran a value twice, or failed late
    with a traceback (a thread count of 0, a missing file, ``--minutes 0``:
    ``ValueError``), or, for ``error_split --split tset``, divided by zero."""
    argv = [a.format(data=data, typo=str(tmp_path / "typo")) for a in argv]
    refused(capsys, script(name)["main"], argv + ["--out", str(tmp_path / "o")], *words)


# ------------------------------------------------------------------ the path types
@pytest.mark.parametrize("check, good, bad, messages", [
    (existing_file, "f", "d", ["is a folder, not a file", "no such file",
                               "empty path; name a file"]),
    (existing_dir, "d", "f", ["is a file, not a folder", "no such folder",
                              "empty path; name a folder"]),
])
def test_existing_path_types_name_the_path_and_what_is_there(tmp_path, monkeypatch, check, good,
                                                              bad, messages):
    """The path with ``~`` expanded where it is what the flag wants; otherwise the path as
    given and what is there instead."""
    (tmp_path / "f").write_text("")
    (tmp_path / "d").mkdir()
    monkeypatch.setenv("HOME", str(tmp_path))
    assert check(f"~/{good}") == str(tmp_path / good)
    wrong, missing, empty = messages
    for text, message in [(f"~/{bad}", f"~/{bad}: {wrong}"),
                          (str(tmp_path / "x"), f"{tmp_path / 'x'}: {missing}"), (" ", empty)]:
        with pytest.raises(argparse.ArgumentTypeError) as e:
            check(text)
        assert str(e.value) == message


@pytest.mark.skipif(torch.cuda.is_available(), reason="refused only where torch sees no GPU")
def test_inference_on_a_missing_gpu_is_refused(capsys, tmp_path):
    refused(capsys, script("inference")["main"], ["--device", "cuda", "--out",
                                                  str(tmp_path / "o")],
            "--device cuda: torch sees no CUDA device")


# ------------------------------------------------------------------ train_scaling.py
@pytest.mark.parametrize("argv, words", [
    (["--layouts", "2"], ["argument --layouts", "PROCESSESxTHREADS such as 2x1"]),
    (["--layouts", "0x1"], ["argument --layouts", "PROCESSESxTHREADS >= 1"]),
    (["--batches", "0"], ["argument --batches: expected an integer >= 1, got 0"]),
    (["--batches", "4", "4"], ["--batches: 4 given more than once"]),
    (["--steps", "8", "--warmup", "8"], ["--steps 8: not more than --warmup 8"]),
    (["--layouts", "2x1", "--batches", "3"], ["--batches: none divides"]),
    (["--against", "/nonexistent/tree"], ["argument --against", "/nonexistent/tree"]),
])
def test_train_scaling_bad_arguments_are_refused(capsys, argv, words):
    refused(capsys, script("train_scaling")["parse_args"], argv, *words)


def test_train_scaling_resumes_an_interrupted_run(tmp_path, monkeypatch, data):
    """Each run is kept as it ends: after an interruption the same command reruns only
    what had not ended, and the tables hold both."""
    ns = script("train_scaling")
    calls, stop = [], [True]

    def fit_once(tree, method, root, procs, threads, batch, *rest):
        calls.append((method, procs, threads, batch))
        if stop[0] and len(calls) == 2:
            raise KeyboardInterrupt
        return {"vertex_frames_per_s": 100.0 * batch}

    module = ns["run"].__globals__  # the script's own globals (``ns`` is a copy)
    monkeypatch.setitem(module, "fit_once", fit_once)
    monkeypatch.setitem(module, "dataset", lambda *args: Path(data))
    monkeypatch.setitem(module, "_revision", lambda tree: "rev")
    a = ns["parse_args"](["--methods", "da", "--layouts", "1x1", "--batches", "4", "8",
                          "--repeats", "1"])
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        ns["run"](a, out)
    assert calls == [("da", 1, 1, 4), ("da", 1, 1, 8)]
    calls.clear()
    stop[0] = False
    info = ns["run"](a, out)
    assert calls == [("da", 1, 1, 8)]
    assert sorted(r["vertex_frames_per_s"] for r in info["rows"]) == [400.0, 800.0]


# ------------------------------------------------------------------ data_loading.py
@pytest.mark.parametrize("argv, words", [
    (["--cache-sizes", "0"], ["argument --cache-sizes: expected an integer >= 1, got 0"]),
    (["--cache-sizes", "4", "4"], ["--cache-sizes: 4 given more than once"]),
    (["--epochs", "0"], ["argument --epochs: expected an integer >= 1, got 0"]),
])
def test_data_loading_bad_arguments_are_refused(capsys, argv, words):
    refused(capsys, script("data_loading")["parse_args"], argv, *words)


# ------------------------------------------------------------------ the MGN-style scripts
GARTRANS_CKPT = Path(__file__).resolve().parent / "data" / "gartrans_learn.ckpt"
MGN_CKPT = Path(__file__).resolve().parent / "data" / "mgn_learn.ckpt"


@pytest.mark.parametrize("argv, words", [
    (["score", "--data", "{data}", "--mgn", str(GARTRANS_CKPT)],
     ["--mgn", "a checkpoint of GarTrans", "not of MGN-style"]),
    (["stability", "--data", "{data}", "--mgn", str(GARTRANS_CKPT)],
     ["--mgn", "not of MGN-style"]),
    (["score", "--data", "{data}", "--other", "m"], ["--other m", "expected NAME=CKPT"]),
    (["score", "--data", "{data}", "--mgn", "{tmp}/none.ckpt"], ["--mgn", "none.ckpt"]),
    (["score", "--data", "{data}"], ["--mgn", "give --mgn CKPT"]),
    (["score", "--data", "{data}", "--mgn", str(MGN_CKPT), "--starts", "gt", "DA"],
     ["--starts DA", "expected one of gt, drape, lbs, preroll or the NAME of an --other"]),
    (["score", "--data", "{data}", "--mgn", str(MGN_CKPT), "--merge", "{tmp}/none.json",
      "--merge-names", "A"], ["--merge", "none.json: no such file"]),
    (["score", "--data", "{tmp}", "--mgn", str(MGN_CKPT)], ["argument --data", "manifest"]),
    (["branch", "--data", "{data}", "--from", str(MGN_CKPT), "--steps", "5", "--rollout",
      "0"], ["argument --rollout", "expected an integer >= 1, got 0"]),
])
def test_mgn_learn_refuses_in_one_line_before_its_output(capsys, tmp_path, argv, words):
    """A checkpoint of another method, a missing --mgn or --other, a folder that is not
    a dataset, --rollout 0: tracebacks, after `--out` was made."""
    data = tmp_path / "d"
    data.mkdir()
    (data / "manifest.json").write_text('{"items": []}')
    argv = [a.format(data=data, tmp=tmp_path) for a in argv] + ["--out", str(tmp_path / "o")]
    refused(capsys, script("mgn_learn")["main"], argv, *words)
    assert not (tmp_path / "o").exists()


def test_resolution_names_an_empty_cache_and_the_command_that_fills_it(capsys, tmp_path):
    """An empty --cache ended in a traceback suggesting `garmentgnn generate --preset`."""
    cache = tmp_path / "cache"
    cache.mkdir()
    last = refused(capsys, script("resolution")["main"],
                   ["score", "--cache", str(cache), "--out", str(tmp_path / "o" / "r.json")],
                   f"--cache {cache}", "no dataset learn_res400-blender",
                   "python benchmarks/resolution.py generate --cache")
    assert "--preset" not in last and not (tmp_path / "o").exists()


def test_resolution_refuses_a_checkpoint_of_another_method(capsys, tmp_path, monkeypatch):
    resolution = script("resolution")
    args = argparse.Namespace(gartrans=str(MGN_CKPT), da=None, mgn=str(MGN_CKPT))
    with pytest.raises(SystemExit) as e:
        resolution["methods"](args)
    assert e.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("error: --gartrans") and "not of GarTrans" in last, last
