"""Bad input to ``garmentgnn predict`` and the BVH reader it shares with ``generate
--spec``: each exact input that once ran without a word, now refused in one line naming
the flag or file (or, for a rerun, its leftovers removed)."""
from pathlib import Path

import numpy as np
import pytest

from garmentgnn.cli import main as cli_main
from garmentgnn.data.export import write_obj_sequence
from garmentgnn.inference import predict_garment_motion
from garmentgnn.motion import load_bvh
from test_own_garment import files, one_error  # noqa: F401 (a fixture)

ROOT = Path(__file__).resolve().parents[1]
MGN = ROOT / "tests" / "data" / "mgn_learn.ckpt"


def test_predict_at_another_rate_than_the_mgn_model_learned_is_refused(files, tmp_path,  # noqa: F811
                                                                       capsys):
    out = tmp_path / "out"
    one_error(capsys, cli_main(["predict", "--ckpt", str(MGN), "--garment",
                                str(files / "skirt.obj"), "--motion", str(files / "walk.bvh"),
                                "--scale", "0.01", "--fps", "60", "--out", str(out / "p")]),
              "--fps", "60", "learned its dynamics at 30 fps", "give fps 30")
    assert not out.exists()


def test_a_rerun_with_fewer_frames_leaves_no_frames_of_the_earlier_run(files, tmp_path,  # noqa: F811
                                                                       capsys):
    out = tmp_path / "p"
    base = ["predict", "--method", "lbs", "--garment", str(files / "skirt.obj"),
            "--motion", "walk", "--out", str(out)]
    assert cli_main(base + ["--frames", "6"]) == 0
    (tmp_path / "p_obj" / "notes.txt").write_text("mine")  # not the command's: kept
    assert cli_main(base + ["--frames", "3"]) == 0
    names = sorted(p.name for p in (tmp_path / "p_obj").iterdir())
    assert names == ["frame_0000.obj", "frame_0001.obj", "frame_0002.obj", "notes.txt"]


def test_write_obj_sequence_removes_only_its_own_later_frames(tmp_path):
    pos, faces = np.zeros((4, 3, 3)), np.array([[0, 1, 2]])
    write_obj_sequence(tmp_path, pos, faces)
    (tmp_path / "other_0009.obj").write_text("x")
    write_obj_sequence(tmp_path, pos[:2], faces)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "frame_0000.obj", "frame_0001.obj", "other_0009.obj"]


def _latin1_joint(files, tmp_path):  # noqa: F811
    """walk.bvh with its joint 'LeftLeg' renamed 'Left\\xe9eg' (one latin-1 byte)."""
    raw = (files / "walk.bvh").read_bytes()
    assert b"JOINT LeftLeg" in raw
    bad = tmp_path / "latin1.bvh"
    bad.write_bytes(raw.replace(b"JOINT LeftLeg", b"JOINT Left\xe9eg"))
    offset = raw.index(b"JOINT LeftLeg") + len(b"JOINT Left")
    line = raw[:offset].count(b"\n") + 1
    return bad, offset, line


def test_a_bvh_joint_name_with_a_byte_that_is_not_utf8_is_refused(files, tmp_path,  # noqa: F811
                                                                   capsys):
    bad, offset, line = _latin1_joint(files, tmp_path)
    with pytest.raises(ValueError, match=rf"latin1.bvh: byte 0xE9 at offset {offset} "
                                         rf"\(BVH line {line}\) is not UTF-8"):
        load_bvh(bad, scale=0.01)
    with pytest.raises(ValueError, match=rf"`source`: byte 0xE9 at offset {offset}"):
        load_bvh(bad.read_bytes(), scale=0.01)
    # text already decoded with replacement characters: the joint is named
    text = bad.read_bytes().decode("utf-8", errors="replace")
    with pytest.raises(ValueError, match=rf"BVH line {line}: joint name 'Left\ufffdeg'"):
        load_bvh(text, scale=0.01)
    one_error(capsys, cli_main(["predict", "--method", "lbs", "--garment",
                                str(files / "skirt.obj"), "--motion", str(bad),
                                "--out", str(tmp_path / "out" / "p")]),
              "latin1.bvh", f"offset {offset}", f"line {line}", "UTF-8")
    assert not (tmp_path / "out").exists()


def test_a_negative_start_is_refused(files):  # noqa: F811
    with pytest.raises(ValueError, match=r"^`start`: expected a first frame >= 0.*-2"):
        predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                               method="lbs", scale=0.01, start=-2)


def test_a_start_beyond_the_take_names_start(files, tmp_path, capsys):  # noqa: F811
    # walk.bvh: 24 frames at 120 fps, 7 at 30 (0 to 0.2 s)
    one_error(capsys, cli_main(["predict", "--method", "lbs", "--garment",
                                str(files / "skirt.obj"), "--motion", str(files / "walk.bvh"),
                                "--scale", "0.01", "--start", "9",
                                "--out", str(tmp_path / "out" / "p")]),
              "walk.bvh", "--start 9 is beyond the take", "7 frames at 30 fps",
              "below 7")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("mapping", [["Hips", "pelvis"], {"Hips": 3}, "Hips=pelvis"])
def test_a_mapping_of_the_wrong_type_names_mapping(files, mapping):  # noqa: F811
    """A list, a non-text joint or a string as `mapping` failed inside `dict()`."""
    with pytest.raises(TypeError, match=r"^`mapping`: expected a mapping of file joint"):
        predict_garment_motion(files / "skirt.obj", "regular", files / "walk.bvh",
                               method="lbs", scale=0.01, mapping=mapping)
