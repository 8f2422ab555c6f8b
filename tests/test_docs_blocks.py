"""Every code block in the README and docs/ runs as a test, or is marked as output.

* ``text`` blocks are output (layouts, synopses, transcripts): not run; ``yaml`` blocks
  are parsed.  A fence that names a file (```python toy_conv.py) holds that file, which
  the doc's bash blocks find beside them.
* ``bash`` blocks run under bash, in a folder of their own, with the project's commands
  (``garmentgnn``, ``python``, ``make``) and the tools they name (``pip``, ``apt-get``,
  ``cp``, ``tensorboard``) stubbed to record their arguments, and no other program on the
  ``PATH``: the shell's own loops, variables and functions run for real.  Each recorded
  ``garmentgnn`` command is then parsed by the command line itself (``train``: by
  LightningCLI, every flag and value checked against the classes), each ``python
  benchmarks/X.py`` and ``python -m MODULE`` by that script's own parser, each ``make``
  target looked up in the Makefile.  Nothing is simulated or trained: a block of
  hour-long runs is checked for what it says, not for its results.
* ``python`` blocks run as written, in a folder holding what they name: ``data/tiny`` (the
  ``tiny`` preset made with the simulator double), ``data/small`` and ``data/learn`` (the
  same), ``model.ckpt`` (GarTrans trained one step on it), ``seq.glb`` (one of its
  sequences), and docs/own_garment.md's ``skirt.obj``, ``twirl.bvh`` and ``last.ckpt``
  (a skirt made on anny's regular body, a centimetre take, the committed ``learn``
  checkpoint); a block that renders is skipped where no renderer is, one that writes the
  HTML viewer where its bundle is not built.  The README's quick start
  (``tests/test_readme.py``) and docs/layers.md (``tests/test_nn_docs.py``) have tests of
  their own.
* Code written inline that builds a model from a data module's sizes
  (``GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))``), in the docs, a docstring,
  an error message or a recipe's comment, runs on the ``tiny`` data module.
"""
import argparse
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```", re.S | re.M)
#: the languages a block may have: run (bash, python), parsed (yaml) or output (text)
LANGUAGES = ("bash", "python", "yaml", "text")
#: python blocks with a test of their own
OWN_TESTS = {("README.md", 0): "tests/test_readme.py", ("docs/layers.md", 0):
             "tests/test_nn_docs.py", ("docs/layers.md", 1): "tests/test_nn_docs.py",
             ("docs/layers.md", 2): "tests/test_nn_docs.py"}
#: the commands a bash block may call, stubbed (the project's are parsed afterwards)
STUBS = ("garmentgnn", "python", "make", "pip", "apt-get", "cp", "tensorboard")


def blocks():
    """``(doc, index among its language, language, code)`` of every fenced block; a block
    whose fence names a file (```python toy_conv.py) is that file's content
    (:data:`FILES`), written beside the doc's bash blocks when they run."""
    out = []
    for doc in DOCS:
        seen = {}
        for info, code in FENCE.findall(doc.read_text()):
            lang, _, name = info.strip().partition(" ")
            i = seen[lang] = seen.get(lang, -1) + 1
            out.append((str(doc.relative_to(ROOT)), i, lang, code, name.strip()))
    return out


BLOCKS = blocks()
#: doc -> {file name: content} of its file blocks
FILES = {}
for _doc, _, _, _code, _name in BLOCKS:
    if _name:
        FILES.setdefault(_doc, {})[_name] = _code
BASH = [b[:4] for b in BLOCKS if b[2] == "bash"]
PYTHON = [b[:4] for b in BLOCKS
          if b[2] == "python" and not b[4] and (b[0], b[1]) not in OWN_TESTS]


def test_every_block_says_what_it_is():
    """A block is run (bash, python) or marked as output (text); none is left unmarked."""
    bad = [f"{doc} block {i + 1}: ```{lang}" for doc, i, lang, _, _ in BLOCKS
           if lang not in LANGUAGES]
    assert not bad, bad
    import yaml  # noqa: PLC0415
    for doc, i, lang, code, _ in BLOCKS:
        if lang == "yaml":
            assert yaml.safe_load(code) is not None, f"{doc} yaml block {i + 1}"
    assert len(BASH) > 20 and len(PYTHON) >= 5
    for (doc, i), test in OWN_TESTS.items():
        assert any(b[:3] == (doc, i, "python") and not b[4] for b in BLOCKS), (doc, i)
        assert (ROOT / test).is_file()


# ------------------------------------------------------------------ bash
def run_bash(code: str, tmp: Path):
    """Run ``code`` with the stubs; the recorded commands, as argument lists."""
    tmp.mkdir(parents=True, exist_ok=True)
    log = tmp / "commands.log"
    # one write per command: backgrounded calls (``cmd &``) do not interleave their lines
    stubs = "".join(f"{name}() {{ local l; l=$(printf '%s\\x1f' {name} \"$@\"); "
                    f"printf '%s\\n' \"$l\" >> \"$LOG\"; }}\n" for name in STUBS)
    empty = tmp / "bin"
    empty.mkdir()
    (tmp / "block.sh").write_text(stubs + code)
    env = {"PATH": str(empty), "HOME": str(tmp / "home"), "LOG": str(log)}
    run = subprocess.run(["/bin/bash", "--noprofile", "--norc", "-e", str(tmp / "block.sh")],
                         cwd=tmp, env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    lines = log.read_text().splitlines() if log.exists() else []
    return [line.split("\x1f")[:-1] for line in lines]


class Parsed(Exception):
    pass


def parse_train(args):
    """LightningCLI's parse of ``garmentgnn train`` ``args`` (the packaged recipe
    names resolved), without checking files or building anything."""
    from lightning.pytorch.cli import LightningCLI  # noqa: PLC0415
    from garmentgnn.training.recipes import named_module, resolve_config_args  # noqa: PLC0415
    from garmentgnn.training.lightning_cli import GarmentCLI  # noqa: PLC0415

    class ParseOnly(GarmentCLI):
        def parse_arguments(self, parser, argv):
            LightningCLI.parse_arguments(self, parser, argv)
            raise Parsed

    from garmentgnn.training import GarmentDataModule, GarmentModule  # noqa: PLC0415
    args = resolve_config_args(args)
    try:
        ParseOnly(GarmentModule, GarmentDataModule, args=args, default_model=named_module(args))
    except Parsed:
        return
    except SystemExit as e:  # --print_config: parsed, printed, exit 0
        if e.code != 0:
            raise
        return
    raise AssertionError(f"train {shlex.join(args)}: not parsed")


def files_exist(m: pytest.MonkeyPatch) -> None:
    """Within ``m``: every path a parser checks exists (a documented command names the
    outputs of the commands before it, or of runs made elsewhere): the parse judges the
    flags and values, not what is on this disk."""
    from garmentgnn.data import store  # noqa: PLC0415
    for name in ("is_file", "is_dir", "exists"):
        m.setattr(Path, name, lambda self: True)
    for name in ("isfile", "isdir", "exists"):
        m.setattr(os.path, name, lambda path: True)
    m.setattr(store, "dataset_dir", lambda text: os.path.expanduser(text))


def parse_script(argv, monkeypatch):
    """``python`` ``argv`` run up to its first ``parse_args`` (its parser's verdict)."""
    real = argparse.ArgumentParser.parse_known_args

    def parse_known_args(self, args=None, namespace=None):
        out = real(self, args, namespace)
        raise Parsed(out)

    if argv[0] == "-m":
        name, rest = argv[1], argv[2:]
    else:
        name, rest = ROOT / argv[0], argv[1:]
        assert name.is_file(), f"no such script: {argv[0]}"
    with monkeypatch.context() as m:
        if argv[0] != "-m":
            m.syspath_prepend(str(name.parent))
        m.setattr(sys, "argv", [str(name)] + rest)
        files_exist(m)
        m.setattr(argparse.ArgumentParser, "parse_known_args", parse_known_args)
        with pytest.raises(Parsed):
            if argv[0] == "-m":
                runpy.run_module(name, run_name="__main__", alter_sys=True)
            else:
                runpy.run_path(str(name), run_name="__main__")


def check_command(cmd, monkeypatch, capsys):
    name, args = cmd[0], cmd[1:]
    if name == "garmentgnn":
        if args[:1] == ["train"]:
            parse_train(args[1:])
        else:
            from garmentgnn.cli import build_parser  # noqa: PLC0415
            try:
                build_parser().parse_args(args)
            except SystemExit as e:
                raise AssertionError(f"{shlex.join(cmd)}: {capsys.readouterr().err}") from e
    elif name == "python":
        try:
            parse_script(args, monkeypatch)
        except SystemExit as e:
            raise AssertionError(f"{shlex.join(cmd)}: {capsys.readouterr().err}") from e
    elif name == "make":
        targets = re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), re.M)
        assert set(args) <= set(targets), (cmd, targets)


@pytest.mark.parametrize("doc, i, code", [(d, i, c) for d, i, _, c in BASH],
                         ids=[f"{d}#{i + 1}" for d, i, _, _ in BASH])
def test_bash_block_runs(doc, i, code, tmp_path, monkeypatch, capsys):
    for name, content in FILES.get(doc, {}).items():  # the files the doc writes out
        (tmp_path / name).write_text(content)
    commands = run_bash(code, tmp_path)
    assert commands, f"{doc} bash block {i + 1} ran no command"
    # commands run from the repository's root, beside the doc's files where it has some
    # (on the Python path, as the doc's `export PYTHONPATH=$PWD` puts them)
    monkeypatch.chdir(tmp_path if doc in FILES else ROOT)
    if doc in FILES:
        monkeypatch.syspath_prepend(str(tmp_path))
    for cmd in commands:
        check_command(cmd, monkeypatch, capsys)


# ------------------------------------------------------------------ python
@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A folder with what the python blocks name (module doc)."""
    import lightning as L  # noqa: PLC0415
    from garmentgnn.data import export_sequence, generate, preset, store  # noqa: PLC0415
    from garmentgnn.models import GarTrans  # noqa: PLC0415
    from garmentgnn.training import GarmentDataModule, GarTransModule  # noqa: PLC0415
    from test_data import fake_simulate  # noqa: PLC0415
    tmp = tmp_path_factory.mktemp("docs")
    tiny = tmp / "data" / "tiny"
    generate(preset("tiny"), tiny, workers=0, simulate_fn=fake_simulate, progress=False)
    for name in ("small", "learn"):
        (tmp / "data" / name).symlink_to(tiny)
    dm = GarmentDataModule(tiny, val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)), schedule=False)
    trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        default_root_dir=str(tmp))
    trainer.fit(module, dm)
    trainer.save_checkpoint(tmp / "model.ckpt")
    seq = sorted((tiny / store.SEQUENCES).glob("*.npz"))[0]
    export_sequence(seq, "gltf", tmp / "seq.glb")
    # docs/own_garment.md's: a skirt made on anny's regular body as OBJ, a twirl as a
    # centimetre BVH, and a checkpoint trained on anny bodies (the committed one)
    import trimesh  # noqa: PLC0415
    from garmentgnn.body.factory import build_body  # noqa: PLC0415
    from garmentgnn.garments import make_garment  # noqa: PLC0415
    from garmentgnn.motion import make_motion  # noqa: PLC0415
    from garmentgnn.motion.bvh import save_bvh  # noqa: PLC0415
    body = build_body({"model": "anny", "shape": "regular"})
    g = make_garment("skirt", body, resolution=200, length="mini")
    trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False).export(
        tmp / "skirt.obj")
    save_bvh(tmp / "twirl.bvh", make_motion("twirl", body.skeleton, num_frames=24, fps=120.0,
                                            rest_joints=body.joints.double()),
             body.skeleton, body.joints, scale=0.01)
    (tmp / "last.ckpt").symlink_to(ROOT / "tests" / "data" / "gartrans_learn.ckpt")
    return tmp


@pytest.mark.parametrize("doc, i, code", [(d, i, c) for d, i, _, c in PYTHON],
                         ids=[f"{d}#{i + 1}" for d, i, _, _ in PYTHON])
def test_python_block_runs(doc, i, code, folder, monkeypatch):
    if "render_animation" in code or "show(" in code:
        from garmentgnn.viz.animate import renderer_unavailable  # noqa: PLC0415
        reason = renderer_unavailable()
        if reason is not None:
            pytest.skip(f"no renderer here: {reason}")
    if "write_viewer" in code:
        from garmentgnn.viz.viewer import viewer_bundle  # noqa: PLC0415
        try:
            viewer_bundle()
        except (OSError, ValueError) as e:
            pytest.skip(f"the viewer bundle is not built here ({e})")
    monkeypatch.chdir(folder)
    exec(compile(code, f"{doc} python block {i + 1}", "exec"), {"__name__": "__main__"})


# ------------------------------------------------------------------ inline code
#: a model built from a data module's sizes, written inline (in prose, a docstring, an
#: error message or a recipe's comment): ``**dm.``, ``**datamodule.`` or ``**data.``
INLINE = re.compile(r"\*\*(?:dm|datamodule|data)\.")
#: the files that write such code: of the docs, the package's sources and its recipes
INLINE_FILES = [p for p in [*DOCS, *sorted((ROOT / "src" / "garmentgnn").rglob("*.py")),
                            *sorted((ROOT / "src" / "garmentgnn" / "recipes").rglob("*.yaml"))]
                if INLINE.search(p.read_text())]


def inline_builds(text: str):
    """``(line, expression)`` of each call in ``text`` whose arguments unpack a data
    module (:data:`INLINE`): from the outermost call's name to its closing parenthesis,
    on one line; an expression cut by the end of its line comes back unbalanced, for
    the test to name."""
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        for m in INLINE.finditer(line):
            head = re.search(r"[A-Za-z_][\w.]*\((?:[A-Za-z_][\w.]*\()*$", line[:m.start()])
            start = head.start() if head else m.start()
            depth, end = 0, len(line)
            for j in range(start, len(line)):
                depth += {"(": 1, ")": -1}.get(line[j], 0)
                if line[j] == ")" and depth == 0:
                    end = j + 1
                    break
            out.append((n, line[start:end]))
    return out


def test_inline_builds_are_found_whole():
    """The finder takes the whole call, and names one cut by a line break."""
    assert inline_builds("see `GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))`.") == [
        (1, "GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))")]
    assert inline_builds("x\n``GarTrans(**datamodule.dims)``, y") == [
        (2, "GarTrans(**datamodule.dims)")]
    assert inline_builds("``GarTrans(**dm.model_sizes(\n    GarTrans))``") == [
        (1, "GarTrans(**dm.model_sizes(")]


def _inline_scope(folder):
    """The names an inline build may use: the package's models and modules, and the
    ``tiny`` data module as ``dm``, ``datamodule`` and ``data``."""
    import garmentgnn.models as models  # noqa: PLC0415
    import garmentgnn.models.baselines as baselines  # noqa: PLC0415
    import garmentgnn.training as training  # noqa: PLC0415
    dm = training.GarmentDataModule(folder / "data" / "tiny", val_split=None)
    return {**{k: getattr(m, k) for m in (models, baselines, training) for k in dir(m)
               if not k.startswith("_")}, "dm": dm, "datamodule": dm, "data": dm}


def test_the_former_inline_build_fails(folder):
    """The check can fail: the former text raises, naming the size GarTrans does not take."""
    with pytest.raises(TypeError, match="num_vertices"):
        eval("GarTransModule(GarTrans(**datamodule.dims))", _inline_scope(folder))  # noqa: S307


@pytest.mark.parametrize("path", INLINE_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_inline_model_builds_run(path, folder):
    """Each inline build in ``path`` runs on the ``tiny`` data module (``dm``,
    ``datamodule`` and ``data`` name it), with the package's models and modules in
    scope: ``GarTrans(**datamodule.dims)`` stood in 7 docstrings, messages and docs, and
    raised a TypeError (``dims`` holds ``num_vertices`` too)."""
    scope, where = _inline_scope(folder), path.relative_to(ROOT)
    for line, code in inline_builds(path.read_text()):
        try:
            built = eval(code, dict(scope))  # noqa: S307  (the project's own text)
        except Exception as e:  # noqa: BLE001  (any failure is the finding)
            raise AssertionError(f"{where}:{line}: {code!r} does not run: "
                                 f"{type(e).__name__}: {e}") from None
        assert isinstance(built, torch.nn.Module), f"{where}:{line}: {code!r} -> {built!r}"


def test_bash_stubs_see_what_bash_expands(tmp_path):
    """The bench itself: loops, brace expansion, functions and backgrounded calls reach
    the stubs as a shell would pass them; an unknown program fails the block."""
    got = run_bash('for i in 0 1; do garmentgnn bench --shard $i/2 & done; wait\n'
                   'run() { make "$@"; }; run test\ncp a/{x,y}.md b/\n', tmp_path / "a")
    assert sorted(got) == sorted([["garmentgnn", "bench", "--shard", "0/2"],
                                  ["garmentgnn", "bench", "--shard", "1/2"],
                                  ["make", "test"], ["cp", "a/x.md", "a/y.md", "b/"]])
    (tmp_path / "b").mkdir()
    with pytest.raises(AssertionError, match="command not found"):
        run_bash("ls\n", tmp_path / "b")


def test_parsers_refuse_a_stale_flag(monkeypatch, capsys):
    """The checks can fail: a flag the command no longer has is an error."""
    with pytest.raises(AssertionError):
        check_command(["garmentgnn", "bench", "--preset", "tiny", "--out", "x", "--no-such"],
                      monkeypatch, capsys)
    with pytest.raises(SystemExit):
        parse_train(["fit", "--config", "gartrans", "--model.init_args.no_such", "1"])
    with pytest.raises(AssertionError):
        check_command(["make", "no-such-target"], monkeypatch, capsys)
