"""Bad input on the command line: every failure of every verb is one ``error:`` line that
names the flag (and the fix), with a non-zero exit status; ``--debug`` shows the
traceback.  Each test runs one exact input through ``garmentgnn.cli.main``."""
import fcntl
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from garmentgnn.bench.methods import METHOD_NAMES
from garmentgnn.cli import build_parser
from garmentgnn.cli import main as cli_main
from garmentgnn.data import Spec, generate, preset, read_manifest, store
from garmentgnn.viz.compare import comparison
from test_data import fake_simulate, files_of

ROOT = Path(__file__).resolve().parents[1]
CONFIG = str(ROOT / "src" / "garmentgnn" / "recipes" / "gartrans.yaml")
GEN = ["--engine", "torch", "--no-estimate", "--no-progress",
       "--simulate-fn", "test_data:fake_simulate"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """The tiny preset made with the simulator double (8 sequences, 3 s)."""
    out = tmp_path_factory.mktemp("ref")
    assert generate(preset("tiny"), out, workers=0, simulate_fn=fake_simulate,
                    progress=False).done == 8
    return out


def copy(dataset, tmp_path) -> Path:
    out = tmp_path / "d"
    shutil.copytree(dataset, out)
    return out


def one_error(capsys, rc, *words):
    """Exit status non-zero, stderr's last line an ``error:`` naming ``words``, and no
    traceback anywhere."""
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert rc != 0 and last.startswith("error: "), err[-800:]
    assert "Traceback" not in err
    assert all(w in last for w in words), last
    return last


def edit_sequence(path: Path, **arrays):
    """Rewrite a sequence file with some arrays replaced (the manifest's hash then
    differs: these tests run `manifest`, which rebuilds it, or `export`, which has none)."""
    seq = store.load_sequence(path)
    meta = seq.pop("meta")
    seq.update(arrays)
    store.write_sequence(path, seq, meta)


def first_file(out: Path) -> Path:
    return sorted((out / store.SEQUENCES).glob("*.npz"))[0]


# ------------------------------------------------------------------ show
@pytest.mark.parametrize("argv, flag", [(["--index", "99"], "--index"),
                                        (["--split", "nosuch"], "--split")])
def test_show_with_a_bad_index_or_split_is_one_line(dataset, tmp_path, capsys, argv, flag):
    rc = cli_main(["show", "--data", str(dataset), "--out", str(tmp_path / "s")] + argv)
    one_error(capsys, rc, flag)


@pytest.mark.parametrize("content", [b"junk\n", b"PK\x03\x04" + b"\0" * 40])
def test_show_with_a_foreign_or_truncated_checkpoint_blames_ckpt(dataset, tmp_path, capsys,
                                                                 content):
    ckpt = tmp_path / "model.ckpt"
    ckpt.write_bytes(content)
    rc = cli_main(["show", "--data", str(dataset), "--out", str(tmp_path / "s"),
                   "--ckpt", str(ckpt)])
    one_error(capsys, rc, f"--ckpt {ckpt}", "unreadable checkpoint")


@pytest.mark.slow  # renders before it writes (~15 s)
def test_show_out_below_a_file_blames_out(dataset, tmp_path, capsys):
    """A file where --out needs a folder: a NotADirectoryError traceback before."""
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "cmp"
    rc = cli_main(["show", "--data", str(dataset), "--out", str(out), "--no-gif", "--no-gltf",
                   "--max-frames", "2", "--height", "720"])
    one_error(capsys, rc, f"--out {out}", "a file is in the way", "name a folder")


def test_debug_flag_and_variable_show_the_traceback(dataset, tmp_path, monkeypatch):
    argv = ["show", "--data", str(dataset), "--out", str(tmp_path / "s"), "--index", "99"]
    with pytest.raises(ValueError, match="`index`"):
        cli_main(["--debug"] + argv)
    monkeypatch.setenv("GARMENTGNN_DEBUG", "1")
    with pytest.raises(ValueError, match="`index`"):
        cli_main(argv)


# ------------------------------------------------------------------ train, manifests
def test_train_on_a_manifest_with_duplicate_ids_names_them(dataset, tmp_path, capsys):
    """The same ids listed twice: the data module trained on the duplicates."""
    out = copy(dataset, tmp_path)
    doc = json.loads((out / store.MANIFEST).read_text())
    doc["items"] = doc["items"] + doc["items"][:2]
    (out / store.MANIFEST).write_text(json.dumps(doc))
    rc = cli_main(["train", "fit", "--config", CONFIG, "--data.root", str(out),
                   "--trainer.max_epochs", "1"])
    last = one_error(capsys, rc, "--data.root", "listed more than once",
                     "garmentgnn manifest --out")
    assert doc["items"][0]["id"] in last


# ------------------------------------------------------------------ export
def test_export_out_pointing_at_a_file_blames_out(dataset, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x")
    seq = str(first_file(dataset))
    rc = cli_main(["export", "--seq", seq, "--format", "obj", "--out", str(afile)])
    one_error(capsys, rc, f"--out {afile}", "name a folder")
    rc = cli_main(["export", "--seq", seq, "--format", "pc2", "--out", str(afile / "x.pc2")])
    last = one_error(capsys, rc, f"--out {afile / 'x.pc2'}")
    assert "--seq" not in last


def test_export_obj_of_positions_one_vertex_short_is_refused(dataset, tmp_path, capsys):
    """Exit 0 and OBJs whose faces pointed past the vertex list before."""
    seq = tmp_path / "s.npz"
    shutil.copy(first_file(dataset), seq)
    edit_sequence(seq, positions=store.load_sequence(seq)["positions"][:, :-1])
    rc = cli_main(["export", "--seq", str(seq), "--format", "obj", "--out",
                   str(tmp_path / "objs")])
    one_error(capsys, rc, f"--seq {seq}", "positions have shape")
    assert not (tmp_path / "objs").exists()


# ------------------------------------------------------------------ manifest
def test_manifest_names_shuffled_vertex_order_and_nan_frames(dataset, tmp_path, capsys):
    """A shuffled vertex order came back `ok`; NaN frames quietly `pending`."""
    out = copy(dataset, tmp_path)
    a, b = sorted((out / store.SEQUENCES).glob("*.npz"))[:2]
    P = store.load_sequence(a)["positions"]
    edit_sequence(a, positions=P[:, np.random.default_rng(0).permutation(P.shape[1])])
    Q = store.load_sequence(b)["positions"].copy()
    Q[3:5, 7] = np.nan
    edit_sequence(b, positions=Q)
    rc = cli_main(["manifest", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and err.strip().splitlines()[-1].startswith("error: --out")
    assert f"{a.name}: vertex order of positions does not match" in err
    assert f"{b.name}: positions contain NaN/inf in 2 of 8 frames (first: frame 3)" in err
    status = {r["id"]: r["status"] for r in read_manifest(out)["items"]}
    assert status[a.stem] == status[b.stem] == "pending"
    assert sum(s == "ok" for s in status.values()) == 6


# ------------------------------------------------------------------ generate
@pytest.mark.parametrize("argv, flag", [
    (["--backend", "local", "--address", "127.0.0.1:6379"], "--address"),
    (["--limit", "-2"], "--limit"),
    (["--workers", "-3"], "--workers"),
])
def test_generate_flags_out_of_range_are_errors(tmp_path, capsys, argv, flag):
    rc = cli_main(["generate", "--out", str(tmp_path / "g")] + GEN + argv)
    one_error(capsys, rc, flag)
    assert not (tmp_path / "g" / store.MANIFEST).exists()


def test_second_generate_into_one_folder_is_refused(tmp_path, capsys):
    """Both runs simulated the same items before."""
    out = tmp_path / "g"
    out.mkdir()
    argv = ["generate", "--out", str(out), "--workers", "0", "--limit", "1"] + GEN
    with open(out / ".generate.lock", "a+") as f:  # a run in progress holds this lock
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        f.write("4242\n")
        f.flush()
        rc = cli_main(argv)
        one_error(capsys, rc, f"--out {out}", "another `garmentgnn generate` (pid 4242)")
        assert not (out / store.MANIFEST).exists()
    assert cli_main(argv) == 0  # the lock goes with its holder


def test_interrupted_generate_says_what_was_kept_and_how_to_resume(dataset, tmp_path, capsys,
                                                                   monkeypatch):
    out = tmp_path / "g"
    monkeypatch.setenv("GG_CALLS", str(tmp_path / "calls.txt"))
    monkeypatch.setenv("GG_CRASH_AFTER", "3")  # Ctrl-C during the 4th item
    argv = ["generate", "--out", str(out), "--workers", "0"] + GEN
    rc = cli_main(argv)
    err = capsys.readouterr().err
    assert rc == 130 and "Traceback" not in err
    assert f"interrupted: 3 of 8 sequences are saved in {out}" in err
    resume = err.split("resume with: ", 1)[1].strip()
    assert resume.startswith("garmentgnn generate --out")
    monkeypatch.delenv("GG_CRASH_AFTER")
    assert cli_main(resume.split()[1:]) == 0
    assert files_of(out) == files_of(dataset)  # nothing lost: as an uninterrupted run


def test_generate_and_manifest_refuse_sequence_files_of_another_dataset(dataset, tmp_path,
                                                                        capsys):
    """A folder holding another dataset's sequence files but no spec.json or
    manifest.json: `generate` wrote its own manifest without them (exit 0), and `manifest`
    with a spec listed them as this dataset's."""
    other = Spec("x", preset("tiny").garments[:1], preset("tiny").bodies[:1],
                 preset("tiny").motions[:1], ["silk"], seed=7)
    out = tmp_path / "d"
    assert generate(other, out, workers=0, simulate_fn=fake_simulate, progress=False).done == 1
    (foreign,) = (out / store.SEQUENCES).glob("*.npz")
    (out / store.SPEC).unlink()
    (out / store.MANIFEST).unlink()
    argv = ["generate", "--out", str(out), "--workers", "0", "--limit", "1"] + GEN
    one_error(capsys, cli_main(argv), f"--out {out}", "1 sequence file(s)",
              "belong to another dataset", foreign.name, "--force")
    assert not (out / store.MANIFEST).exists() and not (out / store.SPEC).exists()
    # --force: this dataset beside it, and the other file's record is kept
    assert cli_main(argv + ["--force"]) == 0
    status = {r["id"]: r["status"] for r in read_manifest(out)["items"]}
    assert status[foreign.stem] == "ok" and len(status) == 9
    assert cli_main(argv) == 0  # a resume keeps it without --force again
    assert read_manifest(out)["counts"] == {"ok": 3, "pending": 6}
    # `manifest` on tiny's spec with a file of yet another dataset copied in
    shutil.copy(first_file(dataset), out / store.SEQUENCES / "copied.npz")
    capsys.readouterr()
    one_error(capsys, cli_main(["manifest", "--out", str(out)]), f"--out {out}",
              "belong to another dataset", "--force")
    assert read_manifest(out)["counts"] == {"ok": 3, "pending": 6}  # not rewritten
    cli_main(["manifest", "--out", str(out), "--force"])
    assert "copied" not in {r["id"] for r in read_manifest(out)["items"]}  # invalid: other id


def test_manifest_marks_nan_in_any_array(dataset, tmp_path, capsys):
    """NaN motion rotations: recorded `ok` by `manifest` before."""
    out = copy(dataset, tmp_path)
    a = first_file(out)
    rot = store.load_sequence(a)["motion_rotations"].copy()
    rot[2, 1, 0] = np.nan
    edit_sequence(a, motion_rotations=rot)
    rc = cli_main(["manifest", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and f"{a.name}: motion_rotations contain NaN/inf in 1 of" in err
    assert {r["id"]: r["status"] for r in read_manifest(out)["items"]}[a.stem] == "pending"


def test_export_start_frame_nan_blames_start_frame(dataset, tmp_path, capsys):
    """`--start-frame nan` was blamed on --seq."""
    argv = ["export", "--seq", str(first_file(dataset)), "--format", "pc2", "--out",
            str(tmp_path / "x.pc2"), "--start-frame", "nan"]
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --start-frame: expected a finite number" in err
    assert "--seq" not in err.splitlines()[-1] and not (tmp_path / "x.pc2").exists()


@pytest.mark.parametrize("content", [b"\xff\xfe\x00 not text", b"", b"console.log(1)"])
def test_show_html_with_a_broken_viewer_bundle_fails_before_rendering(dataset, tmp_path,
                                                                      capsys, monkeypatch,
                                                                      content):
    """A damaged bundle failed after the MP4, PNG and glTF were written, with a raw
    UnicodeDecodeError."""
    bundle = tmp_path / "viewer.bundle.js"
    bundle.write_bytes(content)
    monkeypatch.setenv("GARMENTGNN_VIEWER_BUNDLE", str(bundle))
    rc = cli_main(["show", "--data", str(dataset), "--out", str(tmp_path / "s" / "cmp"),
                   "--html", "--max-frames", "2", "--height", "720"])
    last = one_error(capsys, rc, f"the viewer bundle {bundle}", "make install")
    assert not (tmp_path / "s").exists()  # nothing rendered
    # the variable that chose the file is named, and the file (anyone's) never offered
    # for deletion
    assert "set by GARMENTGNN_VIEWER_BUNDLE" in last and "delete" not in last
    assert "point GARMENTGNN_VIEWER_BUNDLE at the viewer's bundle, or unset it" in last


# ------------------------------------------------------------------ found by fuzzing
@pytest.mark.parametrize("argv, words", [
    (["--format", "pc2", "--out", "{tmp}/x.glb"], ["--out", "must end in .pc2"]),
    (["--format", "gltf", "--out", "{tmp}/x.gltf"], ["--out", "must end in .glb"]),
    (["--format", "obj", "--out", "{tmp}/objs", "--start-frame", "3"],
     ["--start-frame: only --format pc2"]),
    (["--format", "pc2", "--out", "{tmp}/x.pc2", "--no-body"], ["--no-body", "garment only"]),
])
def test_export_flags_the_format_ignores_are_refused(dataset, tmp_path, capsys, argv, words):
    """A PC2 written into x.glb, a binary glTF into x.gltf, --start-frame on OBJs and
    --no-body on PC2: exit 0 with the flag ignored or the file misnamed."""
    argv = [a.format(tmp=tmp_path) for a in argv]
    rc = cli_main(["export", "--seq", str(first_file(dataset))] + argv)
    one_error(capsys, rc, *words)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("argv, words", [
    (["bench", "--out", ""], ["argument --out: empty path"]),
    (["show", "--data", "{data}", "--out", ""], ["argument --out: empty path"]),
    (["show", "--data", "{data}", "--out", "{tmp}/s", "--max-frames", "-3"],
     ["argument --max-frames: expected an integer >= 1, got -3"]),
])
def test_empty_out_and_negative_max_frames_are_refused(dataset, tmp_path, capsys, monkeypatch,
                                                       argv, words):
    """`bench --out ""` wrote its records and report into the current folder;
    `show --max-frames -3` dropped the last 3 frames."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        cli_main([a.format(data=dataset, tmp=tmp_path) for a in argv])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and all(w in last for w in words), last
    assert not list(tmp_path.iterdir())


def test_show_with_two_panels_of_one_name_is_refused(dataset, tmp_path, capsys):
    """`--ckpt run1/last.ckpt --ckpt run2/last.ckpt`: both panels were named 'last' and
    the second silently replaced the first."""
    a, b = str(tmp_path / "run1" / "last.ckpt"), str(tmp_path / "run2" / "last.ckpt")
    rc = cli_main(["show", "--data", str(dataset), "--out", str(tmp_path / "s"), "--ckpt", a,
                   "--ckpt", b])
    one_error(capsys, rc, "--ckpt", "two panels named 'last'", f"--ckpt A={a} --ckpt B={b}")
    with pytest.raises(ValueError, match="`max_frames`: expected an int >= 1"):
        comparison(dataset, {}, max_frames=-3)


def test_bench_methods_given_twice_add_up():
    """`bench --methods A --methods B` ran B only."""
    a, b = METHOD_NAMES[:2]
    args = build_parser().parse_args(["bench", "--out", "x", "--methods", a, "--methods", b])
    assert args.methods == [a, b]


# ------------------------------------------------------------------ what a run leaves out
LEARN_CKPT = str(ROOT / "tests" / "data" / "gartrans_learn.ckpt")


def test_show_a_checkpoint_of_another_skeleton_names_the_sizes(dataset, tmp_path, capsys):
    """`show` answered "`inputs.rest_joints`: a skeleton of 17 joints, this model has 31
    (`num_joints`)": now the words `train` uses for the same checkpoint."""
    rc = cli_main(["show", "--data", str(dataset), "--ckpt", LEARN_CKPT,
                   "--out", str(tmp_path / "s")])
    last = one_error(capsys, rc, f"--ckpt {LEARN_CKPT}", "other sizes", "num_joints 31 (the data:",
                     "use it on data of its body model")
    assert "`inputs" not in last and not list(tmp_path.iterdir())


@pytest.mark.parametrize("flag, value, trained", [("--num-landmarks", "32", "num_landmarks 64"),
                                                  ("--history", "2", "history 3")])
def test_show_data_settings_other_than_the_checkpoints_are_refused(dataset, tmp_path, capsys,
                                                                   flag, value, trained):
    """`show --num-landmarks 32` on a model trained with 64 landmarks fed it other Nyström
    features than it learned from, silently (and the default 64 did so for a model trained
    with 32): the settings now follow the checkpoint."""
    rc = cli_main(["show", "--data", str(dataset), "--ckpt", LEARN_CKPT, flag, value,
                   "--out", str(tmp_path / "s")])
    one_error(capsys, rc, f"{flag} {value}", f"was trained with {trained}", "drop the flag")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("fmt, name", [("blend", "scene.blend"), ("abc", "scene.abc"),
                                       ("gltf", "scene.glb"), ("pc2", "scene.pc2")])
def test_export_to_an_existing_folder_is_refused_before_any_work(dataset, tmp_path, capsys,
                                                                  fmt, name):
    """`export --format blend --out DIR` (an existing folder) ended in Blender's own
    traceback."""
    out = tmp_path / name
    out.mkdir()
    rc = cli_main(["export", "--seq", str(first_file(dataset)), "--format", fmt,
                   "--out", str(out)])
    one_error(capsys, rc, f"--out {out}", "is a folder", "name a file")
    assert not list(out.iterdir())


def test_export_below_a_file_is_refused(dataset, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "x.glb"
    rc = cli_main(["export", "--seq", str(first_file(dataset)), "--format", "gltf",
                   "--out", str(out)])
    one_error(capsys, rc, f"--out {out}", f"{tmp_path / 'afile'} is a file")


def test_bench_that_would_run_nothing_is_refused(tmp_path, capsys):
    """`bench --preset converge --no-learned` wrote a report whose every section was
    empty, exit 0."""
    rc = cli_main(["bench", "--preset", "converge", "--no-learned", "--no-progress",
                   "--out", str(tmp_path / "b")])
    one_error(capsys, rc, "--no-learned", "'converge'", "nothing would run")
    assert not (tmp_path / "b").exists()


def test_a_value_starting_with_a_minus_reaches_its_flag(dataset, tmp_path, capsys):
    """`bench --shard -1/2` answered argparse's "expected one argument"; the shard's own
    check now says what is wrong.  A negative start frame in exponent form is a value."""
    rc = cli_main(["bench", "--preset", "tiny", "--out", str(tmp_path / "b"), "--shard", "-1/2"])
    one_error(capsys, rc, "--shard", "0 <= I < N", "'-1/2'")
    rc = cli_main(["export", "--seq", str(first_file(dataset)), "--format", "pc2",
                   "--out", str(tmp_path / "x.pc2"), "--start-frame", "-1e3"])
    assert rc == 0
    head = pc2_header(tmp_path / "x.pc2")
    assert head[3] == -1000.0


def pc2_header(path):
    from garmentgnn.data import export  # noqa: PLC0415
    return export.PC2_HEADER.unpack(path.read_bytes()[:export.PC2_HEADER.size])
