"""Motions: joint limits, procedural generators, BVH import/export, retargeting."""
import math

import numpy as np
import pytest
import torch

from garmentgnn.body import Skeleton, forward_kinematics
from garmentgnn.body.capsule import CapsuleBodyModel
from garmentgnn.geometry.rotations import (axis_angle_to_matrix, euler_to_matrix,
                                           matrix_to_axis_angle, matrix_to_euler)
from garmentgnn.motion import (JOINT_LIMITS, MOTIONS, Motion, blend, clamp_to_limits,
                               concat, guess_roles, jump, limit_violation, load_bvh,
                               make_motion, retarget, run, save_bvh, sit_stand, twirl, walk,
                               within_limits)
WALK_PERIOD, RUN_PERIOD = 1.1, 0.7  # seconds per gait cycle at speed 1 (33 / 21 frames at 30 fps)


@pytest.fixture(scope="module")
def capsule():
    model = CapsuleBodyModel(resolution=6)
    return model, model.skeleton, model.rest_joints()


def deg(*xyz):
    return torch.deg2rad(torch.tensor(xyz, dtype=torch.float64))


def pose_one(skeleton, **angles):
    """[1, S, 3] axis-angle: role -> (x, y, z) degrees about the world axes in order XYZ."""
    rot = torch.zeros(1, skeleton.num_joints, 3, dtype=torch.float64)
    for role, xyz in angles.items():
        rot[0, skeleton.index(role)] = matrix_to_axis_angle(euler_to_matrix(deg(*xyz), "XYZ"))
    return rot


def fk(rot, rest, skeleton, translation=None):
    return forward_kinematics(rot.double(), rest.double(), skeleton.parents,
                              None if translation is None else translation.double())[1]


def mats(aa):
    return axis_angle_to_matrix(aa.double())


# ----------------------------------------------------------------------------- limits


def test_limit_sign_conventions_via_fk(capsule):
    """The documented signs: knee +X sends the foot back (+Y), hip -X brings the knee
    forward, elbow -X the hand forward, spine +X the head forward, shoulder -Y raises
    the left arm and its mirror (+Y) the right one; all these poses are within limits."""
    _, sk, J = capsule
    rest = fk(pose_one(sk), J, sk)[0]

    def moved(joint, **angles):
        rot = pose_one(sk, **angles)
        assert within_limits(rot, sk)
        return fk(rot, J, sk)[0, sk.index(joint)] - rest[sk.index(joint)]

    assert moved("l_ankle", l_knee=(60, 0, 0))[1] > 0.3
    assert moved("l_knee", l_hip=(-60, 0, 0))[1] < -0.3
    assert moved("l_wrist", l_elbow=(-90, 0, 0))[1] < -0.2
    assert moved("head", spine=(30, 0, 0))[1] < -0.2
    up_l = moved("l_wrist", l_shoulder=(0, -90, 0))
    up_r = moved("r_wrist", r_shoulder=(0, 90, 0))
    assert up_l[2] > 0.3 and up_l[0] > 0.1 and up_r[2] > 0.3 and up_r[0] < -0.1
    assert torch.allclose(up_l * torch.tensor([-1.0, 1, 1], dtype=up_l.dtype), up_r, atol=1e-6)


def test_mirrored_limits():
    for side in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist"):
        lo, hi = JOINT_LIMITS["l_" + side], JOINT_LIMITS["r_" + side]
        assert lo.order == hi.order
        assert (lo.lower[0], lo.upper[0]) == (hi.lower[0], hi.upper[0])
        for a in (1, 2):
            assert (lo.lower[a], lo.upper[a]) == (-hi.upper[a], -hi.lower[a])
    assert JOINT_LIMITS["l_knee"].lower == (0.0, 0.0, 0.0)
    assert JOINT_LIMITS["l_knee"].upper == (150.0, 0.0, 0.0)
    assert "pelvis" not in JOINT_LIMITS


def test_clamp_to_limits(capsule):
    _, sk, _ = capsule
    # knee hyperextension and knee abduction are removed; within-range is kept bit for bit
    rot = pose_one(sk, l_knee=(-30, 0, 0), r_knee=(40, 20, 0), l_hip=(-40, -20, 10),
                   r_hip=(0, -40, 0), pelvis=(170, 60, -120))
    assert not within_limits(rot, sk)
    v = limit_violation(rot, sk)[0]
    assert v[sk.index("l_knee")] == pytest.approx(30.0, abs=1e-4)
    # right hip: Y mirrored, so -40 deg is 40 deg of adduction (limit 30)
    assert v[sk.index("r_hip")] == pytest.approx(10.0, abs=1e-4)
    out = clamp_to_limits(rot, sk)
    assert within_limits(out, sk)
    assert torch.allclose(mats(out[0, sk.index("l_knee")]), torch.eye(3, dtype=torch.float64),
                          atol=1e-9)
    assert torch.allclose(mats(out[0, sk.index("r_knee")]),
                          euler_to_matrix(deg(40, 0, 0), "XYZ"), atol=1e-9)
    assert torch.allclose(mats(out[0, sk.index("r_hip")]),
                          euler_to_matrix(deg(0, -30, 0), "XYZ"), atol=1e-9)
    for role in ("l_hip", "pelvis", "head"):  # untouched: within limits or unlimited
        assert torch.equal(out[0, sk.index(role)], rot[0, sk.index(role)])
    # batched over any leading dims, dtype preserved
    out2 = clamp_to_limits(rot.float().expand(2, 3, -1, -1), sk)
    assert out2.shape == (2, 3, sk.num_joints, 3) and out2.dtype == torch.float32


def test_limits_bad_input(capsule):
    _, sk, _ = capsule
    bad = torch.zeros(2, sk.num_joints, 3)
    bad[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        clamp_to_limits(bad, sk)
    with pytest.raises(ValueError, match="joints"):
        within_limits(torch.zeros(2, 5, 3), sk)
    with pytest.raises(ValueError, match="rotations"):
        clamp_to_limits(torch.zeros(2, sk.num_joints, 4), sk)


# ----------------------------------------------------------------------------- generators


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_generator_contract(capsule, name):
    model, sk, J = capsule
    m = make_motion(name, sk, num_frames=48, fps=24.0)
    assert isinstance(m, Motion) and m.fps == 24.0 and m.joint_names == sk.joint_names
    assert m.rotations.shape == (48, sk.num_joints, 3) and m.translation.shape == (48, 3)
    assert torch.isfinite(m.rotations).all() and torch.isfinite(m.translation).all()
    assert within_limits(m.rotations, sk)
    big = make_motion(name, sk, num_frames=48, fps=24.0, amplitude=5.0)
    assert within_limits(big.rotations, sk)  # clamped
    assert not torch.allclose(big.rotations, m.rotations)
    # smooth: no jumps between frames (axis-angle kept continuous too)
    assert (m.rotations[1:] - m.rotations[:-1]).norm(dim=-1).max() < 0.5
    assert (mats(m.rotations[1:]) - mats(m.rotations[:-1])).abs().max() < 0.5
    # deterministic without seed, reproducible and varied with one
    assert torch.equal(make_motion(name, sk, num_frames=48, fps=24.0).rotations, m.rotations)
    s1 = make_motion(name, sk, num_frames=48, seed=1)
    assert torch.equal(s1.rotations, make_motion(name, sk, num_frames=48, seed=1).rotations)
    assert not torch.allclose(s1.rotations, make_motion(name, sk, num_frames=48, seed=2).rotations)
    # joints without a role stay at rest
    sk2 = Skeleton(sk.joint_names + ["Tail"], torch.cat([sk.parents, torch.tensor([0])]),
                   sk.roles)
    m2 = make_motion(name, sk2, num_frames=10)
    assert (m2.rotations[:, -1] == 0).all()


@pytest.mark.parametrize("name", sorted(MOTIONS))
def test_posed_capsule_keeps_bone_lengths(capsule, name):
    model, sk, J = capsule
    m = make_motion(name, sk, num_frames=30, amplitude=2.0, seed=3)
    verts, joints = model("regular").pose(m.rotations, m.translation)
    assert verts.shape[0] == 30 and torch.isfinite(verts).all()
    par = sk.parents[1:]
    rest_len = (J[1:] - J[par]).norm(dim=-1)
    posed_len = (joints[:, 1:] - joints[:, par]).norm(dim=-1)
    assert torch.allclose(posed_len, rest_len.expand_as(posed_len), atol=1e-5)
    # the root goes where the translation says
    assert torch.allclose(joints[:, 0], J[0] + m.translation, atol=1e-5)


def test_walk_is_periodic(capsule):
    _, sk, _ = capsule
    for fps in (30.0, 60.0):
        m = walk(sk, num_frames=80, fps=fps)
        p = round(WALK_PERIOD * fps)
        R = mats(m.rotations)
        assert torch.allclose(R[p], R[0], atol=1e-5)
        assert torch.allclose(R[p + 7], R[7], atol=1e-5)
        assert not torch.allclose(R[p // 2], R[0], atol=1e-2)
        if fps == 60.0:  # half a period later the right knee does what the left one did
            assert torch.allclose(R[p // 2, sk.index("r_knee")], R[0, sk.index("l_knee")],
                                  atol=1e-5)


def _cadence(m, sk):
    """Dominant frequency (Hz) of the left hip's flexion angle."""
    x = matrix_to_euler(mats(m.rotations[:, sk.index("l_hip")]), "XYZ")[:, 0].numpy()
    spec = np.abs(np.fft.rfft(x - x.mean()))
    freqs = np.fft.rfftfreq(len(x), 1.0 / m.fps)
    return freqs[spec.argmax()]


def test_run_has_higher_cadence_than_walk(capsule):
    _, sk, _ = capsule
    w = walk(sk, num_frames=330, speed=1.0)
    r = run(sk, num_frames=330, speed=1.0)
    fw, fr = _cadence(w, sk), _cadence(r, sk)
    assert fw == pytest.approx(1.0 / WALK_PERIOD, rel=0.05)
    assert fr == pytest.approx(1.0 / RUN_PERIOD, rel=0.05)
    assert fr > 1.3 * fw
    assert _cadence(walk(sk, num_frames=330, speed=2.0), sk) == pytest.approx(2 * fw, rel=0.05)


def _velocity(m):
    t = np.arange(m.num_frames) / m.fps
    return np.polyfit(t, m.translation.double().numpy(), 1)[0]  # [3] slope


@pytest.mark.parametrize("gen", [walk, run])
def test_speed_scales_root_velocity(capsule, gen):
    _, sk, _ = capsule
    v1 = _velocity(gen(sk, num_frames=231))
    v2 = _velocity(gen(sk, num_frames=231, speed=2.0))
    assert v1[1] < -0.8  # forward is -Y, at least a slow walking pace
    assert v2[1] == pytest.approx(2.0 * v1[1], rel=1e-4)
    assert abs(v1[0]) < 0.01 and abs(v1[2]) < 0.01


def test_walk_legs_alternate(capsule):
    _, sk, J = capsule
    m = walk(sk, num_frames=34)
    P = fk(m.rotations, J, sk, m.translation)
    quarter = round(WALK_PERIOD * 30 / 4)  # phase pi/2: left leg forward
    rel = P[:, [sk.index("l_ankle"), sk.index("r_ankle")], 1] - P[:, :1, 1]
    assert rel[quarter, 0] < -0.15 and rel[quarter, 1] > 0.15
    assert rel[3 * quarter, 0] > 0.15 and rel[3 * quarter, 1] < -0.15
    # the arm swings with the opposite leg
    hand = P[quarter, [sk.index("l_wrist"), sk.index("r_wrist")], 1] - P[quarter, 0, 1]
    assert hand[1] < hand[0]


def test_jump_is_ballistic(capsule):
    _, sk, J = capsule
    m = jump(sk, num_frames=120, fps=60.0, height=0.3)
    P = fk(m.rotations, J, sk, m.translation)
    z = (P[:, 0, 2] - J[0, 2]).numpy()
    t = np.arange(m.num_frames) / m.fps
    air = z > 1e-6
    assert air.any()
    first = np.flatnonzero(air)
    run_end = first[0] + np.argmin(air[first[0]:]) if not air[first[0]:].all() else len(z)
    idx = np.arange(first[0], run_end)
    assert len(idx) >= 20  # flight of 2 v0 / g = 0.49 s
    a, b, c = np.polyfit(t[idx], z[idx], 2)
    assert a == pytest.approx(-9.81 / 2, rel=1e-3)
    assert np.abs(np.polyval([a, b, c], t[idx]) - z[idx]).max() < 1e-5
    assert z.max() == pytest.approx(0.3, abs=0.01)
    assert z.min() < -0.1  # crouch
    # feet stay put while on the ground
    ground = z <= 0
    ankles = P[ground][:, [sk.index("l_ankle"), sk.index("r_ankle")]]
    assert torch.allclose(ankles, J[[sk.index("l_ankle"), sk.index("r_ankle")]].double()
                          .expand_as(ankles), atol=1e-3)


def test_sit_stand_lowers_pelvis_with_feet_planted(capsule):
    _, sk, J = capsule
    m = sit_stand(sk, num_frames=120, rest_joints=J)
    P = fk(m.rotations, J, sk, m.translation)
    assert m.translation[:, 2].min() < -0.35  # sits down
    assert m.translation[0, 2].abs() < 1e-6 and m.translation[-1, 2].abs() < 1e-3  # stands up
    for role in ("l_ankle", "r_ankle"):
        k = sk.index(role)
        assert (P[:, k] - J[k]).abs().max() < 1e-6


def test_feet_planted_in_arm_swing_and_kick_support(capsule):
    _, sk, J = capsule
    m = make_motion("arm_swing", sk, num_frames=45)
    P = fk(m.rotations, J, sk, m.translation)
    for role in ("l_ankle", "r_ankle"):
        assert (P[:, sk.index(role)] - J[sk.index(role)]).abs().max() < 1e-6
    k = make_motion("kick", sk, num_frames=48)  # first kick (1.6 s) is the right leg's
    P = fk(k.rotations, J, sk, k.translation)
    la, ra = sk.index("l_ankle"), sk.index("r_ankle")
    assert (P[:, la] - J[la]).abs().max() < 1e-6
    assert (P[:, ra, 1] - P[:, 0, 1]).min() < -0.5  # the kick reaches forward


def test_twirl_spins_about_z(capsule):
    _, sk, J = capsule
    m = twirl(sk, num_frames=91, speed=1.0)
    R = mats(m.rotations[:, 0])
    front = R @ torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    assert front[:, 2].abs().max() < 1e-6
    heading = np.unwrap(np.arctan2(front[:, 1].numpy(), front[:, 0].numpy()))
    assert (np.diff(heading) >= -1e-9).all()
    # after the 0.5 s ease-in: 0.5 rev/s = pi rad/s
    assert heading[90] - heading[60] == pytest.approx(math.pi, abs=1e-4)
    assert m.translation.abs().max() == 0
    fast = twirl(sk, num_frames=91, speed=2.0)
    R2 = mats(fast.rotations[:, 0])
    ang = matrix_to_axis_angle(R2[60].T @ R2[75])
    assert abs(ang[2].item()) == pytest.approx(math.pi, abs=1e-4)  # +pi and -pi are one rotation


def test_generator_bad_arguments(capsule):
    _, sk, _ = capsule
    with pytest.raises(ValueError, match="moonwalk"):
        make_motion("moonwalk", sk)
    with pytest.raises(ValueError, match="`height`"):
        make_motion("walk", sk, height=0.5)  # only jump has a height
    assert make_motion("jump", sk, num_frames=5, height=0.5).num_frames == 5
    for kw, arg in (({"num_frames": 0}, "num_frames"), ({"fps": -30.0}, "fps"),
                    ({"speed": 0.0}, "speed"), ({"amplitude": float("nan")}, "amplitude"),
                    ({"seed": 1.5}, "seed"), ({"rest_joints": torch.zeros(3, 3)}, "rest_joints")):
        with pytest.raises(ValueError, match=arg):
            walk(sk, **kw)
    with pytest.raises(ValueError, match="skeleton"):
        walk("capsule")
    with pytest.raises(ValueError, match="height"):
        jump(sk, height=-1.0)


def test_concat_blend_resample(capsule):
    _, sk, _ = capsule
    a, b = walk(sk, num_frames=30), run(sk, num_frames=20)
    c = concat([a, b], blend_frames=5)
    assert c.num_frames == 45
    step = (c.translation[1:] - c.translation[:-1]).norm(dim=-1)
    assert step.max() < 0.2  # the run continues from where the walk went
    assert torch.equal(c.rotations[:25], a.rotations[:25])
    assert torch.allclose(mats(c.rotations[-1]), mats(b.rotations[-1]), atol=1e-5)
    assert torch.allclose(blend(a, walk(sk, num_frames=30, amplitude=2.0), 0.0).rotations,
                          a.rotations, atol=1e-5)
    with pytest.raises(ValueError, match="lengths"):
        blend(a, b)
    r = a.resample(60.0)
    assert r.num_frames == 59 and r.fps == 60.0
    assert torch.allclose(mats(r.rotations[::2]), mats(a.rotations), atol=1e-5)
    assert torch.allclose(r.translation[1], (a.translation[0] + a.translation[1]) / 2, atol=1e-6)


# ----------------------------------------------------------------------------- BVH


HAND_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Chest
  {
    OFFSET 0 1 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 1 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 0.5 0
      }
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
0 0 0 0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 90 0 0 0 0
0 0 0 90 90 0 0 0 0 0 0 0
"""


def _bvh_positions(text, **kw):
    h, m = load_bvh(text, **kw)
    return h, m, forward_kinematics(m.rotations.double(), h.rest_joints.double(), h.parents,
                                    m.translation.double())[1]


def test_hand_written_bvh_positions():
    h, m, P = _bvh_positions(HAND_BVH, up="Z")
    assert h.joint_names == ["Hips", "Chest", "Head"] and h.parents.tolist() == [-1, 0, 1]
    assert h.rotation_orders == ["ZXY"] * 3 and m.fps == 30.0 and m.num_frames == 3
    assert torch.allclose(h.end_sites["Head"].double(), torch.tensor([0.0, 0.5, 0.0],
                                                                     dtype=torch.float64))
    # frame 0: rest; frame 1: root at (1,2,3) turned 90 deg about Z, so the chest
    # offset (0,1,0) points along -X; the chest's 90 deg about X then lifts the head
    # offset (0,1,0) to +Z (Rz Rx (0,1,0) = Rz (0,0,1) = (0,0,1)).  Frame 2: channels
    # Z=90 X=90 at the root mean R = Rz Rx (intrinsic), which takes (0,1,0) to +Z too
    # (the extrinsic Rx Rz would give -X).
    expected = torch.tensor([[[0, 0, 0], [0, 1, 0], [0, 2, 0]],
                             [[1, 2, 3], [0, 2, 3], [0, 2, 4]],
                             [[0, 0, 0], [0, 0, 1], [0, 0, 2]]], dtype=torch.float64)
    assert torch.allclose(P, expected, atol=1e-5)
    # the usual Y-up file: (x, y, z) -> (x, -z, y); centimetres
    _, _, Py = _bvh_positions(HAND_BVH, up="Y", scale=0.01)
    conv = expected[..., [0, 2, 1]] * torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)
    assert torch.allclose(Py, conv * 0.01, atol=1e-7)
    assert torch.allclose(Py[1, 2], torch.tensor([0.0, -0.04, 0.02], dtype=torch.float64),
                          atol=1e-7)


def test_bvh_y_up_figure_becomes_z_up_facing_minus_y():
    text = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0.9 0
  CHANNELS 3 Zrotation Xrotation Yrotation
  JOINT Head
  {
    OFFSET 0 0.8 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 0.1 0
    }
  }
  JOINT Nose
  {
    OFFSET 0 0.7 0.1
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 0 0.05
    }
  }
  JOINT LeftHand
  {
    OFFSET 0.7 0.2 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0.1 0 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.008333333
0 0 0 0 0 0 0 0 0 0 0 0
0 0 90 0 0 0 0 0 0 0 0 0
"""
    h, m = load_bvh(text)  # up="Y" by default
    J = h.rest_joints.double()
    assert m.fps == 120.0
    assert torch.allclose(J[0], torch.tensor([0.0, 0.0, 0.9], dtype=torch.float64))
    assert J[1, 2] > J[0, 2] + 0.7  # head above the hips
    assert J[2, 1] < -0.05  # nose in front: -Y
    assert J[3, 0] > 0.5  # left hand at +X
    # turning left (+90 deg about the file's up axis) is +90 deg about our Z
    assert torch.allclose(m.rotations[1, 0].double(),
                          torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64), atol=1e-6)
    assert torch.allclose(m.translation, torch.zeros(2, 3))  # no position channels


def test_bvh_round_trip(capsule, tmp_path):
    _, sk, J = capsule
    motions = [walk(sk, num_frames=40, seed=4), twirl(sk, num_frames=60, amplitude=2.0),
               jump(sk, num_frames=40)]
    for (order, up, scale), m in zip([("ZXY", "Y", 1.0), ("XYZ", "Z", 0.01), ("YZX", "Y", 0.0254)],
                                     motions):
        path = tmp_path / f"m_{order}.bvh"
        text = save_bvh(path, m, sk, J, order=order, up=up, scale=scale)
        assert path.read_text() == text and f"CHANNELS 3 {order[0]}rotation" in text
        h, loaded = load_bvh(path, up=up, scale=scale)
        # BVH stores the tree depth-first: same joints and parents, file order
        assert sorted(h.joint_names) == sorted(sk.joint_names)
        parent_of = {n: (h.joint_names[p] if p >= 0 else None)
                     for n, p in zip(h.joint_names, h.parents.tolist())}
        assert parent_of == {n: (sk.joint_names[p] if p >= 0 else None)
                             for n, p in zip(sk.joint_names, sk.parents.tolist())}
        order_ = [h.joint_names.index(n) for n in sk.joint_names]
        assert torch.allclose(h.rest_joints[order_], J, atol=1e-5)
        m2 = retarget(loaded, sk)  # back to the skeleton's joint order, by name
        assert m2.fps == pytest.approx(m.fps) and m2.joint_names == m.joint_names
        assert torch.allclose(mats(loaded.rotations[:, order_]), mats(m.rotations), atol=1e-5)
        assert torch.allclose(mats(m2.rotations), mats(m.rotations), atol=1e-5)
        assert torch.allclose(m2.translation, m.translation, atol=1e-5)
        assert set(h.end_sites) == {"Head", "LeftFoot", "RightFoot", "LeftHand", "RightHand"}
        assert h.to_skeleton().roles == sk.roles
        # and, read in float64, the file is written back identically
        h64, m64 = load_bvh(text, up=up, scale=scale, dtype=torch.float64)
        assert save_bvh(None, m64, h64.to_skeleton(), h64.rest_joints, order=order, up=up,
                        scale=scale, end_sites=h64.end_sites) == text


@pytest.mark.parametrize("edit,match", [
    (("CHANNELS 3 Zrotation Xrotation Yrotation", "CHANNELS 3 Zrotation Wrotation Yrotation"),
     r"line 9: unknown channel 'Wrotation'"),
    (("Frames: 3", "Frames: 4"), r"line 22: 'Frames: 4' but the file has 3"),
    (("1 2 3 90 0 0 0 90", "1 2 x 90 0 0 0 90"), r"line 25: .*non-numeric"),
    (("1 2 3 90 0 0 0 90", "1 2 nan 90 0 0 0 90"), r"line 25: .*NaN"),
    (("0 0 0 0 0 0 0 0 0 0 0 0", "0 0 0 0 0 0 0 0 0 0 0"), r"line 24: frame 0 has 11 values"),
    (("CHANNELS 6", "CHANNELS 5"), r"line 5: CHANNELS says 5"),
    (("    OFFSET 0 1 0\n    CHANNELS 3", "    OFFSET 0 1\n    CHANNELS 3"), r"line 8: OFFSET"),
    (("Frame Time: 0.0333333", "Frame Time: 0"), r"line 23: Frame Time"),
    (("MOTION", "MOTON"), r"no MOTION"),
    (("HIERARCHY", "HIERARCH"), r"line 1: expected 'HIERARCHY'"),
    (("      End Site", "      Edn Site"), r"line 14: unknown keyword 'Edn'"),
    (("  }\n}\nMOTION", "  }\nMOTION"), r"line 20: MOTION before"),
])
def test_corrupt_bvh_names_the_line(edit, match):
    old, new = edit
    assert old in HAND_BVH
    with pytest.raises(ValueError, match=match):
        load_bvh(HAND_BVH.replace(old, new, 1))


def test_bvh_bad_arguments(capsule, tmp_path):
    _, sk, J = capsule
    with pytest.raises(ValueError, match="no such BVH file"):
        load_bvh(tmp_path / "missing.bvh")
    with pytest.raises(ValueError, match="up"):
        load_bvh(HAND_BVH, up="X")
    with pytest.raises(ValueError, match="scale"):
        load_bvh(HAND_BVH, scale=0)
    _, m = load_bvh(HAND_BVH)
    with pytest.raises(ValueError, match="retarget"):
        save_bvh(None, m, sk, J)
    w = walk(sk, num_frames=3)
    with pytest.raises(ValueError, match="rest_joints"):
        save_bvh(None, w, sk, J[:5])
    with pytest.raises(ValueError, match="order"):
        save_bvh(None, w, sk, J, order="ZZY")


# ----------------------------------------------------------------------------- retargeting


def _global_rotations(rot, parents):
    R = mats(rot)
    G = [R[:, 0]]
    for k in range(1, R.shape[1]):
        G.append(G[int(parents[k])] @ R[:, k])
    return torch.stack(G, 1)


def test_retarget_identity(capsule):
    _, sk, J = capsule
    m = walk(sk, num_frames=20)
    for kw in ({}, {"source_skeleton": sk}, {"source_skeleton": sk, "source_rest": J,
                                             "target_rest": J}):
        r = retarget(m, sk, **kw)
        assert r.joint_names == sk.joint_names and r.fps == m.fps
        assert torch.allclose(mats(r.rotations), mats(m.rotations), atol=1e-5)
        assert torch.allclose(r.translation, m.translation, atol=1e-5)


def test_retarget_drops_and_keeps_joints(capsule):
    _, sk, _ = capsule
    m = make_motion("kick", sk, num_frames=30)
    # a target with a subset of the joints plus one the source lacks
    tgt = Skeleton(["Hips", "Tail", "RightUpLeg", "RightLeg"], torch.tensor([-1, 0, 0, 2]))
    r = retarget(m, tgt)
    assert r.joint_names == tgt.joint_names and r.rotations.shape == (30, 4, 3)
    assert (r.rotations[:, 1] == 0).all()  # Tail: not in the source -> rest
    for name in ("Hips", "RightUpLeg", "RightLeg"):
        assert torch.equal(r.rotations[:, tgt.index(name)], m.rotations[:, sk.index(name)])
    # an explicit map renames and maps only what it lists
    tgt2 = Skeleton(["root", "thigh", "shin"], torch.tensor([-1, 0, 1]))
    r2 = retarget(m, tgt2, {"Hips": "root", "RightUpLeg": "thigh"})
    assert torch.equal(r2.rotations[:, 1], m.rotations[:, sk.index("RightUpLeg")])
    assert (r2.rotations[:, 2] == 0).all()
    with pytest.raises(ValueError, match="'Tibia'"):
        retarget(m, tgt2, {"Tibia": "shin"})
    with pytest.raises(ValueError, match="'knee'"):
        retarget(m, tgt2, {"RightLeg": "knee"})
    with pytest.raises(ValueError, match="no target joint"):
        retarget(m, Skeleton(["a", "b"], torch.tensor([-1, 0])))


def test_retarget_by_roles_preserves_global_orientations(capsule):
    _, sk, J = capsule
    m = make_motion("arm_swing", sk, num_frames=20, amplitude=1.5)
    # SMPL-like names, no LowerBack: the chest hangs directly under the pelvis
    names = ["pelvis", "spine3", "left_shoulder", "left_elbow", "left_hip", "left_knee"]
    parents = torch.tensor([-1, 0, 1, 2, 0, 4])
    roles = {"pelvis": "pelvis", "chest": "spine3", "l_shoulder": "left_shoulder",
             "l_elbow": "left_elbow", "l_hip": "left_hip", "l_knee": "left_knee"}
    tgt = Skeleton(names, parents, roles)
    with pytest.raises(ValueError, match="no target joint"):
        retarget(m, tgt)  # roles need the source skeleton
    r = retarget(m, tgt, source_skeleton=sk)
    Gs, Gt = _global_rotations(m.rotations, sk.parents), _global_rotations(r.rotations, parents)
    for role in roles:
        assert torch.allclose(Gt[:, tgt.index(role)], Gs[:, sk.index(role)], atol=1e-5)
    # copying local rotations instead would lose the LowerBack's twist
    local = retarget(m, tgt, {sk.roles[k]: v for k, v in roles.items()})
    G_local = _global_rotations(local.rotations, parents)
    assert not torch.allclose(G_local[:, 1], Gs[:, sk.index("chest")], atol=1e-3)


def test_retarget_rest_pose_and_scale(capsule):
    _, sk, J = capsule
    # a T-pose source: upper arms horizontal
    src_rest = J.clone().double()
    for side, sign in (("l", 1.0), ("r", -1.0)):
        s, e, w = (sk.index(f"{side}_{j}") for j in ("shoulder", "elbow", "wrist"))
        src_rest[e] = src_rest[s] + torch.tensor([sign * 0.286, 0, 0], dtype=torch.float64)
        src_rest[w] = src_rest[e] + torch.tensor([sign * 0.253, 0, 0], dtype=torch.float64)
    still = Motion(torch.zeros(3, sk.num_joints, 3), torch.zeros(3, 3), sk.joint_names)
    r = retarget(still, sk, source_skeleton=sk, source_rest=src_rest, target_rest=J)
    P = fk(r.rotations, J, sk, r.translation)
    s, e, w = sk.index("l_shoulder"), sk.index("l_elbow"), sk.index("l_wrist")
    arm = (P[0, e] - P[0, s]) / (P[0, e] - P[0, s]).norm()
    assert torch.allclose(arm, torch.tensor([1.0, 0, 0], dtype=torch.float64), atol=1e-6)
    fore = (P[0, w] - P[0, e]) / (P[0, w] - P[0, e]).norm()
    assert torch.allclose(fore, torch.tensor([1.0, 0, 0], dtype=torch.float64), atol=1e-6)
    legs = [sk.index(n) for n in ("l_knee", "r_ankle")]
    assert torch.allclose(P[0, legs], J[legs].double(), atol=1e-9)  # same rest: untouched
    # a body twice as tall: absolute root positions double (the floor stays at z = 0)
    m = walk(sk, num_frames=20)
    big = retarget(m, sk, source_skeleton=sk, source_rest=J, target_rest=2 * J)
    assert torch.allclose(big.translation + 2 * J[0], 2 * (m.translation + J[0]), atol=1e-5)
    half = retarget(m, sk, translation_scale=0.5)
    assert torch.allclose(half.translation, 0.5 * m.translation)
    with pytest.raises(ValueError, match="translation_scale"):
        retarget(m, sk, translation_scale=-1.0)
    with pytest.raises(ValueError, match="source_rest"):
        retarget(m, sk, source_rest=J, target_rest=J)


def test_guess_roles():
    cmu = ["Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LowerBack", "Spine",
           "Spine1", "Neck", "Neck1", "Head", "LeftShoulder", "LeftArm", "LeftForeArm",
           "LeftHand"]
    g = guess_roles(cmu)
    assert g["spine"] == "LowerBack" and g["chest"] == "Spine1"
    assert g["l_shoulder"] == "LeftArm" and g["l_knee"] == "LeftLeg" and "r_hip" not in g
    mixamo = guess_roles(["mixamorig:Hips", "mixamorig:Spine", "mixamorig:LeftUpLeg"])
    assert mixamo == {"pelvis": "mixamorig:Hips", "spine": "mixamorig:Spine",
                      "l_hip": "mixamorig:LeftUpLeg"}
    smpl = guess_roles(["pelvis", "left_hip", "spine1", "spine2", "spine3", "left_collar",
                        "left_shoulder", "left_elbow"])
    assert smpl["chest"] == "spine3" and smpl["spine"] == "spine1"
    assert smpl["l_shoulder"] == "left_shoulder"


def test_motion_rejects_nan():
    rot = torch.zeros(2, 3, 3)
    rot[0, 1, 2] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        Motion(rot, torch.zeros(2, 3), ["a", "b", "c"])


def test_make_motion_mixes_two_generators_evenly():
    sk = CapsuleBodyModel().skeleton
    kw = dict(num_frames=20, fps=30.0, speed=1.2, seed=3)
    mix = make_motion("walk+arm_swing", sk, **kw)
    ref = blend(make_motion("walk", sk, **kw), make_motion("arm_swing", sk, **kw), 0.5)
    assert torch.equal(mix.rotations, ref.rotations)
    assert torch.equal(mix.translation, ref.translation)
    assert not torch.allclose(mix.rotations, make_motion("walk", sk, **kw).rotations)
    for bad in ("walk+walk", "walk+arm_swing+run", "walk+moonwalk"):
        with pytest.raises(ValueError, match="`name`"):
            make_motion(bad, sk, **kw)
