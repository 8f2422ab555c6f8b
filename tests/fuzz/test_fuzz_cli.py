"""The command line under odd arguments and damaged dataset folders, and generation
jobs interrupted at any point and then resumed."""
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from _fuzz import EXAMPLES, FUZZ, TALLY, mutations
from garmentgnn.cli import main as cli_main
from garmentgnn.data import Spec, export, generate, preset, read_manifest, store
from test_data import fake_simulate, files_of

DOUBLE = "test_data:fake_simulate"
#: the whole-job tests run (and resume) generation jobs: fewer examples
JOBS = settings(FUZZ, max_examples=max(3, EXAMPLES // 3))
_T = preset("tiny")
#: 4 items of the tiny preset: enough to kill a job part-way through
SMALL = Spec("small4", _T.garments[:1], _T.bodies, _T.motions, ["silk"])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """The tiny preset made with the simulator double (the reference for resumes)."""
    out = tmp_path_factory.mktemp("ref")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert s.done == 8
    return out


def run_cli(argv, capsys, target):
    """Run the CLI in-process; exit 0 is a result, anything else must end in a one-line
    ``error:`` (ours) or argparse's ``usage ... error:`` message."""
    try:
        rc = cli_main(argv)
    except SystemExit as e:  # argparse: --help / --version (0) or a usage error (2)
        rc = e.code
    cap = capsys.readouterr()
    assert isinstance(rc, int), f"{argv}: exit status {rc!r}"
    if rc == 0:
        TALLY[target, "result"] += 1
    else:
        last = cap.err.strip().splitlines()[-1] if cap.err.strip() else ""
        failed_items = rc == 1 and "FAILED" in cap.out
        assert failed_items or "error:" in last, f"{argv}: rc={rc}, stderr={cap.err[-500:]!r}"
        TALLY[target, "clear error"] += 1
    return rc, cap


@st.composite
def generate_args(draw, tmp: Path, other: Path):
    out = draw(st.sampled_from(["new", "other", "", "file", "nested/deeper"]))
    path = {"other": str(other), "": "", "file": str(tmp / "afile")}.get(out, str(tmp / out))
    args = ["generate", "--out", path, "--no-estimate", "--no-progress",
            "--simulate-fn", draw(st.sampled_from([DOUBLE, "nomodule:x", "test_data:nothing",
                                                   "test_data"]))]
    for flag, values in (("--preset", ["tiny", "bogus"]), ("--workers", ["0", "-3", "x"]),
                         ("--seed", ["0", "-5", str(2 ** 70), "1.5"]),
                         ("--limit", ["0", "1", "-1", "y"])):
        if draw(st.booleans()):
            args += [flag, draw(st.sampled_from(values))]
    for flag in ("--retry-failed", "--force"):
        if draw(st.booleans()):
            args.append(flag)
    if "--workers" not in args:
        args += ["--workers", "0"]  # in-process: a worker pool costs seconds to start
    if "--limit" not in args or "-1" in args:
        args += ["--limit", "1"]  # bounded work per example
    return args


@JOBS
@given(data=st.data())
def test_cli_generate(tmp_path_factory, dataset, capsys, monkeypatch, data):
    tmp = tmp_path_factory.mktemp("gen")
    monkeypatch.chdir(tmp)
    (tmp / "afile").write_text("not a folder")
    other = tmp / "other"  # another dataset (the tiny preset with a different seed)
    shutil.copytree(dataset, other)
    spec = json.loads((other / store.SPEC).read_text())
    spec["items"] = spec["items"][::-1]
    (other / store.SPEC).write_text(json.dumps(spec))
    before = (other / store.MANIFEST).read_bytes()
    args = data.draw(generate_args(tmp, other))
    run_cli(args, capsys, "cli generate")
    if "--force" not in args:  # another dataset is never clobbered without --force
        assert (other / store.MANIFEST).read_bytes() == before


@FUZZ
@given(seq=st.sampled_from(["good", "missing", "corrupt", "empty", "", "shuffled", "short",
                            "nan"]),
       fmt=st.sampled_from(["pc2", "obj", "xyz"]), out=st.sampled_from(["x.pc2", "objs", ""]),
       start=st.sampled_from(["0", "nan", "inf", "-2", "z"]), data=st.data())
def test_cli_export(tmp_path_factory, dataset, capsys, seq, fmt, out, start, data):
    tmp = tmp_path_factory.mktemp("exp")
    good = sorted((Path(dataset) / store.SEQUENCES).glob("*.npz"))[0]
    path = {"good": good, "missing": tmp / "none.npz", "": ""}.get(seq, tmp / "s.npz")
    if seq == "corrupt":
        path.write_bytes(data.draw(mutations(good.read_bytes())))
    elif seq == "empty":
        path.write_bytes(b"")
    elif seq in ("shuffled", "short", "nan"):  # valid files whose arrays do not fit together
        arrays = store.load_sequence(good)
        meta, P = arrays.pop("meta"), arrays["positions"].copy()
        n = P.shape[1]
        if seq == "shuffled":
            P = P[:, np.random.default_rng(data.draw(st.integers(0, 99))).permutation(n)]
        elif seq == "short":
            P = P[:, :n - data.draw(st.integers(1, 3))]
        else:
            P[data.draw(st.integers(0, len(P) - 1)), data.draw(st.integers(0, n - 1))] = np.nan
        store.write_sequence(path, dict(arrays, positions=P), meta)
    args = ["export", "--seq", str(path), "--format", fmt, "--out",
            str(tmp / out) if out else "", "--start-frame", start]
    rc, cap = run_cli(args, capsys, "cli export")
    if seq in ("shuffled", "short", "nan"):  # never exported: a silent wrong answer
        assert rc != 0 and any(f in cap.err for f in ("--seq", "--format", "--out")), cap.err
    if rc == 0 and fmt == "pc2":
        assert (tmp / out).stat().st_size > export.PC2_HEADER.size


@FUZZ
@given(state=st.sampled_from(["missing", "empty", "spec_only", "corrupt_file", "bad_json",
                              "good"]), data=st.data())
def test_cli_manifest(tmp_path_factory, dataset, capsys, state, data):
    tmp = tmp_path_factory.mktemp("man") / "d"
    if state != "missing":
        tmp.mkdir()
    if state in ("spec_only", "corrupt_file", "bad_json", "good"):
        (tmp / store.SEQUENCES).mkdir()
        (tmp / store.SPEC).write_bytes((Path(dataset) / store.SPEC).read_bytes())
        for p in sorted((Path(dataset) / store.SEQUENCES).glob("*.npz"))[:2]:
            (tmp / store.SEQUENCES / p.name).write_bytes(p.read_bytes())
    if state == "corrupt_file":
        p = sorted((tmp / store.SEQUENCES).glob("*.npz"))[0]
        p.write_bytes(data.draw(mutations(p.read_bytes())))
    if state == "bad_json":
        (tmp / store.SPEC).write_bytes(b"{not json")
    rc, cap = run_cli(["manifest", "--out", str(tmp)], capsys, "cli manifest")
    if rc == 0:
        man = read_manifest(tmp)
        ok = [r for r in man["items"] if r["status"] == "ok"]
        assert len(ok) + len(man["invalid"]) == 2 or len(ok) == 2


@FUZZ
@given(argv=st.lists(st.sampled_from(["--version", "--help", "export", "manifest", "-x",
                                      "--out", "--seq", "", "train", "predict", "generate",
                                      "bench"]), max_size=3))
def test_cli_odd_argv(capsys, tmp_path_factory, monkeypatch, argv):
    monkeypatch.chdir(tmp_path_factory.mktemp("cwd"))
    if argv[:1] == ["train"]:
        argv = ["train", "predict"]  # the one train case cheap enough to fuzz
    if argv[:1] in (["generate"], ["bench"]):  # never start a real simulation or benchmark
        argv = argv[:1] + ["--help" if "--help" in argv else "--preset", "bogus"]
    run_cli(argv, capsys, "cli argv")


# ------------------------------------------------------------------ interrupted jobs
@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref4")
    assert generate(SMALL, out, workers=0, simulate_fn=fake_simulate, progress=False).done == 4
    return out


@JOBS
@given(crash_after=st.integers(0, 3),
       damage=st.sampled_from(["none", "truncate", "stale_tmp", "manifest_json", "no_manifest",
                               "flip"]),
       cut=st.integers(0, 10_000))
def test_interrupted_generate_resumes_exactly(tmp_path_factory, small_dataset, monkeypatch,
                                              crash_after, damage, cut):
    tmp = tmp_path_factory.mktemp("job")
    out, log = tmp / "run", tmp / "calls.txt"
    monkeypatch.setenv("GG_CALLS", str(log))
    monkeypatch.setenv("GG_CRASH_AFTER", str(crash_after))
    with pytest.raises(KeyboardInterrupt):  # killed after `crash_after` items
        generate(SMALL, out, workers=0, simulate_fn=fake_simulate, progress=False)
    monkeypatch.delenv("GG_CRASH_AFTER")
    files = sorted((out / store.SEQUENCES).glob("*.npz"))
    if damage in ("truncate", "flip") and files:
        f = files[cut % len(files)]
        b = f.read_bytes()
        if damage == "truncate":
            f.write_bytes(b[:cut % len(b)])
        else:
            k = cut % len(b)
            f.write_bytes(b[:k] + bytes([b[k] ^ 0x04]) + b[k + 1:])
    elif damage == "stale_tmp":
        (out / store.SEQUENCES / f".x.npz.tmp-{cut}").write_bytes(b"partial")
    elif damage == "manifest_json":
        (out / store.MANIFEST).write_text('{"items": [')
    elif damage == "no_manifest":
        (out / store.MANIFEST).unlink()
    s = generate(SMALL, out, workers=0, simulate_fn=fake_simulate, progress=False)
    assert s.failed == 0 and s.pending == 0
    assert files_of(out) == files_of(small_dataset)  # byte-identical to an uninterrupted run
    assert read_manifest(out)["counts"] == {"ok": 4}
    TALLY["interrupted generate + resume", "result"] += 1
    assert not list((out / store.SEQUENCES).glob(".*.tmp-*"))
    assert all(json.loads((out / store.MANIFEST).read_text())["items"][i]["sha256"]
               for i in range(4))
    assert os.environ.get("GG_CRASH_AFTER") is None
