"""``garmentgnn predict`` / :func:`garmentgnn.inference.predict_garment_motion`: a trained
method on a garment mesh, a body and a BVH take of one's own, without simulating.
Oracles: ``garmentgnn train predict`` on a dataset sequence of the same garment, body and
motion (to 1e-6 m), the garment file's own vertices (LBS at rest), the files read back
(PC2 bytes, OBJ vertices, the glTF's meshes through trimesh)."""
import struct
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
import trimesh

from garmentgnn.body.factory import build_body
from garmentgnn.cli import main as cli_main
from garmentgnn.data import generate
from garmentgnn.data.spec_file import load_spec
from garmentgnn.inference import predict_garment_motion
from garmentgnn.data.chunks import static_inputs
from garmentgnn.models.inputs import with_frames
from garmentgnn.training.checkpoints import load_checkpoint
from garmentgnn.models.baselines import NCSStyle
from garmentgnn.motion.sequence import Motion
from garmentgnn.training.baselines import BaselineModule
from garmentgnn.viz.animate import renderer_unavailable
from test_data import fake_simulate
from test_own_garment import files, one_error, write_spec  # noqa: F401 (a fixture)

ROOT = Path(__file__).resolve().parents[1]
GARTRANS = ROOT / "tests" / "data" / "gartrans_learn.ckpt"
MGN = ROOT / "tests" / "data" / "mgn_learn.ckpt"
CONFIG = str(ROOT / "src" / "garmentgnn" / "recipes" / "gartrans.yaml")


def read_pc2(path: Path) -> np.ndarray:
    raw = Path(path).read_bytes()
    assert raw[:12] == b"POINTCACHE2\0"
    _, points, _, _, samples = struct.unpack("<iiffi", raw[12:32])
    return np.frombuffer(raw[32:], "<f4").reshape(samples, points, 3)


def test_predict_is_train_predict_on_the_same_inputs(files, tmp_path, capsys):  # noqa: F811
    """A dataset of the skirt file walking and twirling (the twirl held out for test);
    `train predict` of the committed GarTrans on it, and `predict` of the same checkpoint
    on the skirt file, the regular body and the twirl take: the same garment."""
    data = tmp_path / "data"
    spec = load_spec(write_spec(files))
    assert generate(spec, data, workers=0, simulate_fn=fake_simulate, progress=False).done == 2
    assert cli_main(["train", "predict", "--config", CONFIG, "--data.root", str(data),
                     "--ckpt_path", str(GARTRANS), "--trainer.default_root_dir", str(tmp_path),
                     "--trainer.logger", "false", "--trainer.enable_progress_bar",
                     "false"]) == 0
    (npz,) = tmp_path.rglob("predictions/*.npz")
    trained = np.load(npz)["positions"]
    capsys.readouterr()
    out = tmp_path / "pred" / "twirl"
    assert cli_main(["predict", "--ckpt", str(GARTRANS), "--garment",
                     str(files / "skirt.obj"), "--body", "regular", "--motion",
                     str(files / "twirl.bvh"), "--scale", "0.01", "--frames", "5",
                     "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "frames 0-4: " in printed and "set-up and any compilation included" in printed
    assert "GarTrans (sat), frame-parallel: 5 frames" in printed and "one call" in printed
    assert "nearest-face search eager" in printed  # 5 x 192 vertex-frames: not worth it
    got = read_pc2(out.with_suffix(".pc2"))
    assert got.shape == trained.shape == (5, 192, 3)
    assert np.abs(got - trained).max() <= 1e-6
    objs = sorted((tmp_path / "pred" / "twirl_obj").glob("*.obj"))
    assert len(objs) == 5
    first = trimesh.load(objs[0], process=False)
    assert np.abs(np.asarray(first.vertices) - trained[0]).max() <= 1e-6
    scene = trimesh.load(out.with_suffix(".glb"))
    counts = sorted(len(g.vertices) for g in scene.geometry.values())
    assert counts == [192, 1229]  # the garment and the body


def test_lbs_at_rest_is_the_garment_file(files, tmp_path):  # noqa: F811
    body = build_body({"model": "anny", "shape": "regular"})
    S = body.skeleton.num_joints
    rest = Motion(torch.zeros(3, S, 3), torch.zeros(3, 3), list(body.skeleton.joint_names))
    pred = predict_garment_motion(files / "skirt.obj", "regular", rest, method="lbs")
    want = np.asarray(trimesh.load(files / "skirt.obj", process=False).vertices)
    assert pred.positions.shape == (3, len(want), 3)
    assert np.abs(pred.positions - want).max() <= 1e-5


def test_mgn_style_rolls_out_from_the_skinned_garment(files):  # noqa: F811
    kw = dict(frames=4, scale=0.01)
    pred = predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                                  ckpt=MGN, **kw)
    lbs = predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                                 method="lbs", **kw)
    assert pred.autoregressive and pred.method == "MGN-style"
    assert pred.positions.shape == lbs.positions.shape == (4, 192, 3)
    assert np.isfinite(pred.positions).all()
    assert np.abs(pred.positions[:2] - lbs.positions[:2]).max() <= 1e-6  # its two start frames
    assert len(pred.frame_seconds) == 4


def test_mgn_style_rolls_out_from_a_frame_parallel_methods_first_frames(files):  # noqa: F811
    """With ``start_from``, frames 0 and 1 are what the frame-parallel checkpoint predicts
    on its own, and the rest is the simulator's rollout from them (oracle: the module's
    ``rollout`` from those frames on inputs built here, and the skinned-garment start,
    which differs)."""
    kw = dict(frames=5, scale=0.01)
    pred = predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                                  ckpt=MGN, start_from=GARTRANS, **kw)
    alone = predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                                   ckpt=GARTRANS, **kw)
    skinned = predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                                     ckpt=MGN, **kw)
    assert pred.autoregressive and pred.method == "MGN-style from GarTrans (sat)"
    assert pred.positions.shape == (5, 192, 3) and len(pred.frame_seconds) == 5
    assert np.abs(pred.positions[:2] - alone.positions[:2]).max() <= 1e-6
    module = load_checkpoint(MGN)
    static, body = static_inputs(pred.seq, pred.seq["meta"], 16, 64)
    item = with_frames(static, body, torch.as_tensor(pred.seq["motion_rotations"]).float(),
                       torch.as_tensor(pred.seq["motion_translation"]).float(),
                       torch.arange(5), 1)
    with torch.no_grad():
        want = module.rollout(item, start=torch.from_numpy(alone.positions[:2])).numpy()
    assert np.abs(pred.positions - want).max() <= 1e-5
    assert np.abs(pred.positions[2:] - skinned.positions[2:]).max() > 1e-3


def test_start_from_is_refused_where_it_cannot_apply(files, tmp_path, capsys):  # noqa: F811
    base = ["predict", "--garment", str(files / "skirt.obj"), "--motion", "walk",
            "--frames", "4", "--out", str(tmp_path / "out" / "p")]
    one_error(capsys, cli_main(base + ["--ckpt", str(GARTRANS), "--start-from", str(MGN)]),
              "--start-from", "predicts every frame itself", "MGN-style")
    one_error(capsys, cli_main(base + ["--method", "lbs", "--start-from", str(GARTRANS)]),
              "--start-from", "lbs predicts every frame itself")
    one_error(capsys, cli_main(base + ["--ckpt", str(MGN), "--start-from", str(MGN)]),
              "--start-from", "MGN-style checkpoint", "frame-parallel")
    one_error(capsys, cli_main(base + ["--ckpt", str(MGN), "--start-from",
                                       str(tmp_path / "none.ckpt")]),
              "--start-from", "no such file")
    assert not (tmp_path / "out").exists()


@pytest.fixture
def ncs_ckpt(tmp_path):
    """An NCS-style checkpoint of a 50-vertex garment (untrained: only its size counts)."""
    module = BaselineModule(NCSStyle(50, 31, history=1, hidden=8))
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    trainer.strategy.connect(module)
    path = tmp_path / "ncs.ckpt"
    trainer.save_checkpoint(path)
    return path


def test_refusals_are_one_error_line_and_write_nothing(files, tmp_path, capsys,  # noqa: F811
                                                       ncs_ckpt):
    out = tmp_path / "out"
    base = ["predict", "--garment", str(files / "skirt.obj"), "--motion", "walk",
            "--frames", "4", "--out", str(out / "p")]
    one_error(capsys, cli_main(base[:-2] + ["--ckpt", str(ncs_ckpt), "--out", str(out / "p")]),
              "--ckpt", "NCS-style", "specific to the garment", "50 vertices", "has 192",
              "train NCS-style on this garment")
    one_error(capsys, cli_main(["predict", "--method", "lbs", "--garment", "cape",
                                "--motion", "walk", "--out", str(out / "p")]),
              "cape", "neither a mesh file nor a template", "skirt")
    one_error(capsys, cli_main(["predict", "--method", "lbs", "--garment",
                                str(files / "skirt.obj"), "--motion", str(files / "hand.bvh"),
                                "--out", str(out / "p")]),
              "hand.bvh", "mapping")
    (tmp_path / "file").write_text("x")
    one_error(capsys, cli_main(base[:-2] + ["--method", "lbs", "--out",
                                            str(tmp_path / "file" / "p")]),
              "--out", "is a file")
    if not torch.cuda.is_available():
        one_error(capsys, cli_main(base + ["--method", "lbs", "--device", "cuda"]),
                  "--device cuda", "--device cpu")
    assert not out.exists()


def test_predict_help_lists_its_inputs(capsys):
    with pytest.raises(SystemExit):
        cli_main(["predict", "--help"])
    text = capsys.readouterr().out
    assert all(f in text for f in ("--ckpt", "--method", "--garment", "--body", "--motion",
                                   "--mapping", "--device", "--show",
                                   "--start-from"))


def test_show_renders_the_prediction_on_the_body(tmp_path, capsys):
    why = renderer_unavailable()
    if why:
        pytest.skip(why)
    assert cli_main(["predict", "--method", "lbs", "--garment", "skirt", "--body", "thin",
                     "--motion", "walk", "--frames", "3", "--out", str(tmp_path / "w"),
                     "--show"]) == 0
    for suffix in (".glb", ".pc2", ".mp4", ".gif", ".png"):
        assert (tmp_path / f"w{suffix}").stat().st_size > 0, suffix
    assert len(list((tmp_path / "w_obj").glob("*.obj"))) == 3


def test_a_garment_far_from_the_training_resolution_is_warned_about():
    """``predict`` on a garment of many more (or fewer) vertices than the checkpoint's
    training garments warns with the measured trend; within a factor 2 it does not."""
    import types  # noqa: PLC0415
    import warnings  # noqa: PLC0415

    from garmentgnn.inference.predict import ResolutionWarning, check_resolution  # noqa: PLC0415
    module = types.SimpleNamespace(trained_on={"num_vertices": [300, 500]})
    for v in (4000, 100):
        with pytest.warns(ResolutionWarning, match=f"{v:,} vertices.*300-500.*resolution"):
            check_resolution(v, module, "GarTrans")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for v in (150, 300, 1000):
            check_resolution(v, module, "GarTrans")
        check_resolution(4000, types.SimpleNamespace(), "LBS")  # nothing to compare with


def test_the_committed_checkpoints_say_what_they_were_trained_on():
    from garmentgnn.training import load_checkpoint  # noqa: PLC0415
    for name in ("gartrans_learn.ckpt", "mgn_learn.ckpt"):
        module = load_checkpoint(Path(__file__).parent / "data" / name)
        assert module.trained_on["num_vertices"] == [296, 512]


def test_a_padded_last_chunk_predicts_what_the_unpadded_eager_one_does(files, monkeypatch):  # noqa: F811
    """With the search compiled, the last, shorter chunk is padded to the chunk's frames
    (its last frame repeated, those outputs dropped) so that it needs no second
    compilation (it cost as long as the first: 0.6 s a frame).  ``torch.compile`` is
    the identity here, so only the padding differs from the eager run."""
    import garmentgnn.training.module as gm  # noqa: PLC0415
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: fn)
    sizes = []
    call = gm.GarTransModule.predict_garment
    monkeypatch.setattr(gm.GarTransModule, "predict_garment",
                        lambda self, b: sizes.append(b["body_pos"].shape[0]) or call(self, b))
    kw = dict(frames=12, scale=0.01, ckpt=GARTRANS)  # chunks of 8: 8 + 4 frames
    eager = predict_garment_motion(files / "skirt.obj", "regular", "walk", compile=False, **kw)
    assert sizes == [8, 4] and not eager.compiled
    sizes.clear()
    padded = predict_garment_motion(files / "skirt.obj", "regular", "walk", compile=True, **kw)
    assert sizes == [8, 8] and padded.compiled  # the last chunk padded to the first's shape
    assert padded.positions.shape == eager.positions.shape == (12, 192, 3)
    np.testing.assert_allclose(padded.positions, eager.positions, rtol=0, atol=1e-5)
    assert padded.chunks == eager.chunks == [(0, 8), (8, 4)]
    assert padded.setup_seconds is not None and padded.steady_frame_seconds > 0
    # the rule: short takes eager on the CPU, long ones compiled
    from garmentgnn.inference.predict import COMPILE_WORK, compile_pays  # noqa: PLC0415
    module = type("M", (), {"model": type("G", (), {"compile_search": True})})
    assert not compile_pays(module, 60, 288) and compile_pays(module, COMPILE_WORK // 288 + 1, 288)
    assert compile_pays(module, 60, 288, "cuda")
    assert not compile_pays(None, 10 ** 6, 288)


def test_train_test_compiles_the_search_only_where_the_split_pays_it_back():
    """`train test` and `predict` of a GarTrans checkpoint compiled its face search for
    any split (10-20 s per process); now only from COMPILE_WORK vertex-frames on (CPU),
    by the records of the split it evaluates, and a fit compiles as configured."""
    from types import SimpleNamespace  # noqa: PLC0415

    from garmentgnn.training.base import COMPILE_WORK  # noqa: PLC0415
    from garmentgnn.training import load_checkpoint  # noqa: PLC0415
    module = load_checkpoint(GARTRANS)
    assert module.hparams.compile_search and module.model.compile_search
    small = SimpleNamespace(records=[{"num_frames": 60, "num_vertices": 288}] * 9)
    large = SimpleNamespace(records=[{"num_frames": 60, "num_vertices": 400}] * 40)
    assert 9 * 60 * 288 < COMPILE_WORK <= 40 * 60 * 400
    assert not module.evaluation_compile(small) and not module.model.compile_search
    assert module.evaluation_compile(large) and module.model.compile_search
    assert module.evaluation_compile(None)  # nothing to count: as configured
    module.hparams.compile_search = False
    assert not module.evaluation_compile(large)
