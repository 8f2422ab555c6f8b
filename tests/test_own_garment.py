"""Datasets of your own files (``garmentgnn generate --spec``): garment meshes and BVH
takes the tests write themselves (a template saved as OBJ through trimesh, generated
motions saved with ``save_bvh``, one hand-written BVH of another skeleton), their checks,
and the bad input each is refused for (one ``error:`` line naming the file and the fix,
nothing written).  Oracles: the generators at the dataset's rate, scipy's Slerp, the
thigh's angle set in the hand-written file, hashlib."""
import hashlib
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from garmentgnn.body.factory import build_body
from garmentgnn.body.lbs import forward_kinematics
from garmentgnn.cli import main as cli_main
from garmentgnn.data import SpecMismatch, generate, read_manifest, store
from garmentgnn.data.presets import build_inputs
from garmentgnn.data.spec_file import load_spec
from garmentgnn.garments import make_garment
from garmentgnn.motion import make_motion
from garmentgnn.motion.bvh import save_bvh
from garmentgnn.motion.sequence import Motion, match_joints
from test_data import fake_simulate

GEN = ["--no-estimate", "--no-progress", "--workers", "0", "--simulate-fn",
       "test_data:fake_simulate"]
#: the hand-written take's joints -> the body's roles
HAND_MAPPING = {"hip_root": "pelvis", "leg_up_L": "l_hip", "leg_lo_L": "l_knee",
                "leg_up_R": "r_hip", "leg_lo_R": "r_knee", "trunk": "spine",
                "arm_L": "l_shoulder", "arm_R": "r_shoulder"}


#: a small Y-up, centimetre BVH hierarchy of another skeleton's joint names
HAND_HIERARCHY = """\
HIERARCHY
ROOT hip_root
{
  OFFSET 0 95 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT leg_up_L
  {
    OFFSET 9 -5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT leg_lo_L
    {
      OFFSET 0 -42 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 -42 0
      }
    }
  }
  JOINT leg_up_R
  {
    OFFSET -9 -5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT leg_lo_R
    {
      OFFSET 0 -42 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 -42 0
      }
    }
  }
  JOINT trunk
  {
    OFFSET 0 20 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT arm_L
    {
      OFFSET 18 25 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 28 0 0
      }
    }
    JOINT arm_R
    {
      OFFSET -18 25 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET -28 0 0
      }
    }
  }
}
"""
#: its one frame: the left thigh swung 20 degrees, the left knee bent 40
HAND_FRAME = "0 95 0 0 0 0 0 -20 0 0 40 0" + " 0" * 15


def hand_bvh(frames=(HAND_FRAME,) * 3, frame_time="0.0333333") -> str:
    """The hand-written take: :data:`HAND_HIERARCHY` and ``frames`` (lines of values)."""
    return (HAND_HIERARCHY + f"MOTION\nFrames: {len(frames)}\nFrame Time: {frame_time}\n"
            + "".join(f"{f}\n" for f in frames))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A skirt (OBJ) made on anny's regular body; walk and twirl at 120 fps (24 frames:
    6 at 30 fps) as centimetre BVH; the hand-written take."""
    d = tmp_path_factory.mktemp("own")
    body = build_body({"model": "anny", "shape": "regular"})
    g = make_garment("skirt", body, resolution=200, length="mini")
    trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False).export(d / "skirt.obj")
    for name in ("walk", "twirl"):
        m = make_motion(name, body.skeleton, num_frames=24, fps=120.0,
                        rest_joints=body.joints.double())
        save_bvh(d / f"{name}.bvh", m, body.skeleton, body.joints, scale=0.01)
    (d / "hand.bvh").write_text(hand_bvh())
    return d


def write_spec(folder: Path, garments=("- file: skirt.obj",), motions=None, extra="",
               frames=5, name="spec.yaml") -> Path:
    motions = motions or ["- {file: walk.bvh, scale: 0.01}",
                          "- {file: twirl.bvh, scale: 0.01, held_out: test}"]
    text = textwrap.dedent(f"""\
        name: mine
        engine: torch
        fps: 30
        frames: {frames}
        bodies: [regular]
        materials: [silk]
        """) + extra + "garments:\n" + "".join(f"  {g}\n" for g in garments) \
        + "motions:\n" + "".join(f"  {m}\n" for m in motions)
    path = folder / name
    path.write_text(text)
    return path


def one_error(capsys, rc, *words):
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert rc == 2 and last.startswith("error: "), err[-800:]
    assert "Traceback" not in err
    assert all(w in last for w in words), last
    return last


# --------------------------------------------------------------------------- the spec
def test_spec_items_name_files_by_content_not_place(files, tmp_path):
    spec = load_spec(write_spec(files))
    items = spec.items()
    assert [it["split"] for it in items] == ["train", "test"]
    g = items[0]["garment"]
    assert g["path"] == str(files / "skirt.obj")
    assert g["sha256"] == hashlib.sha256((files / "skirt.obj").read_bytes()).hexdigest()
    moved = tmp_path / "moved"
    shutil.copytree(files, moved)
    assert [it["id"] for it in load_spec(moved / "spec.yaml").items()] == \
        [it["id"] for it in items]  # the same files elsewhere: the same dataset
    with open(moved / "skirt.obj", "a") as f:
        f.write("# edited\n")
    assert not {it["id"] for it in load_spec(moved / "spec.yaml").items()} & \
        {it["id"] for it in items}  # a changed mesh: a changed dataset


def test_bvh_take_at_120_fps_is_the_generator_at_30(files):
    """Saved at 120 fps, read back, retargeted and resampled to 30 fps: the generator's
    motion made at 30 fps (the generators are functions of time)."""
    spec = load_spec(write_spec(files))
    item = spec.items()[0]
    _, body, motion, _ = build_inputs(item)
    want = make_motion("walk", body.skeleton, num_frames=5, fps=30.0,
                       rest_joints=body.joints.double())
    assert motion.fps == 30.0 and motion.num_frames == 5
    assert torch.allclose(match_joints(motion, want.joint_names).double(),
                          want.rotations.double(),
                          atol=1e-6)
    assert torch.allclose(motion.translation.double(), want.translation.double(), atol=1e-6)


def test_resample_slerps_between_frames():
    rots = torch.tensor([[[0.0, 0.0, 0.0]], [[1.2, -0.7, 2.0]]], dtype=torch.float64)
    m = Motion(rots, torch.zeros(2, 3, dtype=torch.float64), ["a"], fps=10.0)
    out = m.resample(40.0)  # 0, 1/4, 1/2, 3/4, 1 of the way
    want = Slerp([0, 1], Rotation.from_rotvec(rots[:, 0].numpy()))([0, .25, .5, .75, 1])
    assert np.allclose(out.rotations[:, 0].numpy(), want.as_rotvec(), atol=1e-9)


def test_hand_written_take_needs_a_mapping_and_then_drives_the_body(files, capsys):
    spec = write_spec(files, motions=["- {file: hand.bvh, scale: 0.01}"], frames=3,
                      name="hand.yaml")
    one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out",
                                str(files / "never")] + GEN),
              "hand.bvh", "match none of the body's", "pelvis", "mapping")
    assert not (files / "never").exists()
    mapped = "- {file: hand.bvh, scale: 0.01, mapping: {%s}}" % ", ".join(
        f"{k}: {v}" for k, v in HAND_MAPPING.items())
    item = load_spec(write_spec(files, motions=[mapped], frames=3, name="hand.yaml")).items()[0]
    _, body, motion, _ = build_inputs(item)
    _, J = forward_kinematics(match_joints(motion, body.skeleton.joint_names).double(),
                              body.joints.double(), body.skeleton.parents,
                              motion.translation.double())
    names = list(body.skeleton.joint_names)
    thigh = J[:, names.index("LeftLeg")] - J[:, names.index("LeftUpLeg")]
    angle = torch.rad2deg(torch.acos(-thigh[:, 2] / thigh.norm(dim=1)))
    assert torch.allclose(angle, torch.full_like(angle, 20.0), atol=1e-3)  # as in the file


def test_generate_spec_resumes_and_is_exclusive_with_preset(files, tmp_path, capsys):
    out = tmp_path / "d"
    argv = ["generate", "--spec", str(write_spec(files)), "--out", str(out)] + GEN
    assert cli_main(argv) == 0
    assert read_manifest(out)["counts"] == {"ok": 2}
    assert cli_main(argv) == 0 and "2 skipped" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli_main(argv + ["--preset", "tiny"])
    assert "not allowed with argument" in capsys.readouterr().err


def test_a_file_changed_after_the_spec_was_read_is_refused_by_the_worker(files, tmp_path):
    d = tmp_path / "f"
    shutil.copytree(files, d)
    item = load_spec(write_spec(d)).items()[0]
    (d / "walk.bvh").write_text((d / "walk.bvh").read_text().replace("0.008333", "0.0083"))
    with pytest.raises(ValueError, match="walk.bvh: changed since the spec was read"):
        build_inputs(item)


# --------------------------------------------------------------------------- bad input
def _obj(path: Path, V, F) -> Path:
    path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in V)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    return path


def _bad_files(d: Path):
    skirt = trimesh.load(d / "skirt.obj", process=False)
    V, F = np.asarray(skirt.vertices), np.asarray(skirt.faces)
    centre = V.mean(0)
    _obj(d / "far.obj", V + [2.0, 0.0, 0.0], F)
    _obj(d / "inside.obj", centre + 0.6 * (V - centre), F)
    _obj(d / "fan.obj", [[0, 0, 1], [0.2, 0, 1], [0.1, 0.2, 1], [0.1, -0.2, 1],
                         [0.1, 0.0, 1.2]], [[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    n = 448  # 200,704 vertices
    with open(d / "huge.obj", "w") as f:
        g = np.linspace(0, 1, n)
        np.savetxt(f, np.stack(np.meshgrid(g, g, [1.0]), -1).reshape(-1, 3), fmt="v %.4f %.4f %.4f")
        f.write("f 1 2 3\n")
    (d / "nan.bvh").write_text(hand_bvh((HAND_FRAME, HAND_FRAME.replace("40", "nan"))))
    (d / "empty.bvh").write_text(hand_bvh(()))


BAD = {  # name: (garment, motion, extra spec text, words of the error line)
    "non-manifold mesh": ("- file: fan.obj", None, "", ("fan.obj", "non-manifold", "split")),
    "200K vertices": ("- file: huge.obj", None, "", ("huge.obj", "200,704 vertices",
                                                    "decimate")),
    "far from the body": ("- file: far.obj", None, "", ("far.obj", "m away from the body",
                                                        "translate it")),
    "inside the body": ("- file: inside.obj", None, "", ("inside.obj", "inside the body",
                                                         "cm deep", "model the garment")),
    "NaN channels": (None, "- {file: nan.bvh, scale: 0.01}", "", ("nan.bvh", "NaN",
                                                                 "export the take")),
    "zero frames": (None, "- {file: empty.bvh, scale: 0.01}", "", ("empty.bvh", "no frames",
                                                                  "export the take")),
    "fps of the take": (None, "- {file: walk.bvh, scale: 0.01, fps: 60}", "",
                        ("walk.bvh", "gives 120 fps", "says fps 60", "correct")),
    "fps of the spec": (None, None, "settings: {fps: 24}\n", ("spec.yaml", "`fps` 30",
                                                              "settings.fps` 24", "once")),
    "too few frames": (None, None, "", ("walk.bvh", "7 frames at 30 fps", "from 24 at 120",
                                        "asks for 40", "lower `frames`")),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_files_are_one_error_line_and_nothing_written(files, tmp_path, capsys, case):
    d = tmp_path / "in"
    shutil.copytree(files, d)
    _bad_files(d)
    garment, motion, extra, words = BAD[case]
    spec = write_spec(d, garments=[garment] if garment else ("- file: skirt.obj",),
                      motions=[motion] if motion else None, extra=extra,
                      frames=40 if case == "too few frames" else 5)
    out = tmp_path / "out"
    one_error(capsys, cli_main(["generate", "--spec", str(spec), "--out", str(out)] + GEN),
              *words)
    assert not out.exists()


def test_a_spec_copied_beside_another_datasets_files_is_refused(files, tmp_path, capsys):
    """Dataset A's folder with B's spec.json copied in: `generate` and `manifest` listed
    A's files as ok beside B's pending items; both refuse them now without --force."""
    a, b = tmp_path / "a", tmp_path / "b"
    spec_a = load_spec(write_spec(files))
    spec_b = load_spec(write_spec(files, motions=["- {file: walk.bvh, scale: 0.01}"],
                                  name="b.yaml"), seed=3)
    assert generate(spec_a, a, workers=0, simulate_fn=fake_simulate, progress=False).done == 2
    assert generate(spec_b, b, workers=0, simulate_fn=fake_simulate, progress=False,
                    limit=0).total == 1
    shutil.copy(b / store.SPEC, a / store.SPEC)
    before = sorted(p.name for p in a.rglob("*"))
    with pytest.raises(SpecMismatch, match="belong to another dataset"):
        generate(spec_b, a, workers=0, simulate_fn=fake_simulate, progress=False)
    one_error(capsys, cli_main(["manifest", "--out", str(a)]), "2 sequence file(s)",
              "another dataset", "--force")
    assert sorted(p.name for p in a.rglob("*")) == before
    assert generate(spec_b, a, workers=0, simulate_fn=fake_simulate, progress=False,
                    force=True).done == 1  # --force: B's item beside A's kept files
    assert read_manifest(a)["counts"] == {"ok": 3}
    assert generate(spec_b, a, workers=0, simulate_fn=fake_simulate,
                    progress=False).skipped == 1  # and a resume keeps them without it
