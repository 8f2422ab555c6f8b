"""Baselines of garmentgnn.models.baselines: shapes, finiteness, gradients, invariances,
rollout, and LBS == the simulator's initial skinned state."""
import pytest
import torch

from garmentgnn.bench.sequences import build_scene
from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments import make_garment
from garmentgnn.losses import GarTransLoss, LossInputs
from garmentgnn.models.baselines import (CoarseLevel, DAStyle, HOODStyle, LBSBaseline,
                                         NCSStyle, skin)
from garmentgnn.models.inputs import GarmentInputs, build_garment
from garmentgnn.motion import make_motion
from garmentgnn.physics import MATERIALS, ClothRest
from garmentgnn.sim import SimSettings, simulate


@pytest.fixture(scope="module")
def setup():
    torch.manual_seed(0)
    model = CapsuleBodyModel(resolution=6)
    body = model("regular")
    garment = make_garment("skirt", body, resolution=200, length="mini")
    motion = make_motion("walk", model.skeleton, num_frames=4, fps=30.0, seed=0,
                         rest_joints=body.joints.double())
    scene = build_scene(garment, body)
    return body, garment, motion, scene


def _pose(motion, idx=None):
    r, t = motion.rotations, motion.translation
    return (r, t) if idx is None else (r[idx], t[idx])


def _permuted(scene: GarmentInputs, perm: torch.Tensor) -> GarmentInputs:
    """The same garment with vertex ``perm[i]`` renamed ``i``."""
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(perm.numel())
    pinned = scene.get("pinned")
    return build_garment(scene.rest_pos[perm], inv[scene.faces], scene.skin_weights[perm],
                         scene.rest_joints, scene.parents,
                         None if pinned is None else pinned[perm])


def test_scene_validates(setup):
    _, g, _, scene = setup
    with pytest.raises(ValueError, match="weights"):
        build_garment(scene.rest_pos, scene.faces, scene.skin_weights[:-1], scene.rest_joints,
                      scene.parents)
    with pytest.raises(ValueError, match="rotations"):
        LBSBaseline()(scene, torch.zeros(2, 3, 3))


def test_lbs_equals_simulator_initial_state(setup):
    body, g, motion, scene = setup
    one = type(motion)(motion.rotations[:1], motion.translation[:1], motion.joint_names,
                       motion.fps)
    res = simulate(g, body, one, MATERIALS["silk"], SimSettings())
    pred = LBSBaseline()(scene, *_pose(one))
    assert pred.shape == (1, g.num_vertices, 3)
    torch.testing.assert_close(pred.float(), res.positions[:1], atol=1e-6, rtol=0)


def test_lbs_batch_and_permutation(setup):
    _, g, motion, scene = setup
    lbs = LBSBaseline()
    rot, tr = _pose(motion)
    full = lbs(scene, rot, tr)
    assert full.shape == (motion.num_frames, g.num_vertices, 3) and torch.isfinite(full).all()
    torch.testing.assert_close(lbs(scene, rot[2:3], tr[2:3])[0], full[2])
    perm = torch.randperm(g.num_vertices, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(lbs(_permuted(scene, perm), rot, tr), full[:, perm])


def test_da_style(setup):
    _, g, motion, scene = setup
    torch.manual_seed(0)
    model = DAStyle(scene.num_joints, hidden=32, heads=2, num_layers=2)
    rot, tr = _pose(motion)
    out = model(scene, rot, tr)
    assert out.shape == (motion.num_frames, g.num_vertices, 3) and torch.isfinite(out).all()
    # batch invariance: a frame's prediction does not depend on the rest of the batch
    torch.testing.assert_close(model(scene, rot[1:2], tr[1:2])[0], out[1], atol=1e-5, rtol=1e-5)
    # vertex permutation equivariance
    perm = torch.randperm(g.num_vertices, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(model(_permuted(scene, perm), rot, tr), out[:, perm],
                               atol=1e-5, rtol=1e-5)
    # global translation: the prediction moves with the body
    shift = torch.tensor([0.3, -0.2, 0.1], dtype=tr.dtype)
    torch.testing.assert_close(model(scene, rot, tr + shift), out + shift.float(),
                               atol=1e-5, rtol=1e-5)
    # gradients reach every parameter through a supervised loss
    gt = out.detach() + 0.01
    loss, _ = GarTransLoss(enabled=("vert", "edge", "norm"))(
        LossInputs(pred=out, faces=scene.faces, gt=gt))
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert any(p.grad.abs().sum() > 0 for p in model.parameters())


def test_da_style_rejects_bad_arguments(setup):
    with pytest.raises(ValueError, match="heads"):
        DAStyle(5, hidden=30, heads=4)
    _, _, motion, scene = setup
    with pytest.raises(ValueError, match="scene"):
        DAStyle(scene.num_joints + 1)(scene, *_pose(motion))


def _physics(scene, material=MATERIALS["silk"]):
    rest = ClothRest.from_mesh(scene.rest_pos.float(), scene.faces)
    return rest, rest.vertex_masses(material.density, scene.num_vertices)


def test_hood_style_forward_invariances_and_rollout(setup):
    body, g, motion, scene = setup
    torch.manual_seed(0)
    coarse = CoarseLevel.build(scene.rest_pos, scene.faces, ratio=4, k=4)
    assert coarse.num_nodes == g.num_vertices // 4
    assert coarse.assign.shape == (g.num_vertices,)
    assert int(coarse.assign.max()) < coarse.num_nodes
    assert (coarse.assign[coarse.landmarks] == torch.arange(coarse.num_nodes)).all()
    model = HOODStyle(hidden=32)
    rot, tr = _pose(motion)
    x = LBSBaseline()(scene, rot, tr).float()
    bodies = body.pose(rot, tr)[0].float()
    acc = model(scene, coarse, x[0:2], x[1:3], bodies[2:4])
    assert acc.shape == (2, g.num_vertices, 3) and torch.isfinite(acc).all()
    torch.testing.assert_close(model(scene, coarse, x[1:2], x[2:3], bodies[3:4])[0], acc[1],
                               atol=1e-5, rtol=1e-5)
    shift = torch.tensor([0.5, 0.2, -0.1])
    torch.testing.assert_close(model(scene, coarse, x[0:2] + shift, x[1:3] + shift,
                                     bodies[2:4] + shift), acc, atol=1e-4, rtol=1e-4)
    # vertex permutation equivariance (coarse level renamed consistently)
    perm = torch.randperm(g.num_vertices, generator=torch.Generator().manual_seed(3))
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(perm.numel())
    pc = CoarseLevel(inv[coarse.landmarks], coarse.assign[perm], coarse.edge_index)
    torch.testing.assert_close(model(_permuted(scene, perm), pc, x[0:2, perm], x[1:3, perm],
                                     bodies[2:4]), acc[:, perm], atol=1e-4, rtol=1e-4)
    # rollout: T frames, first two given, pinned vertices follow their targets
    traj = model.rollout(scene, coarse, x[0], x[1], bodies, pinned_targets=x)
    assert traj.shape == (motion.num_frames, g.num_vertices, 3) and torch.isfinite(traj).all()
    torch.testing.assert_close(traj[:2], x[:2])
    pin = scene.pinned_mask()
    assert pin.any()
    torch.testing.assert_close(traj[:, pin], x[:, pin])
    with pytest.raises(ValueError, match="body_frames"):
        model.rollout(scene, coarse, x[0], x[1], bodies[:1])


def test_hood_style_trains_on_physics_losses(setup):
    body, g, motion, scene = setup
    torch.manual_seed(0)
    coarse = CoarseLevel.build(scene.rest_pos, scene.faces, ratio=4, k=4)
    model = HOODStyle(hidden=32)
    rot, tr = _pose(motion)
    x = LBSBaseline()(scene, rot, tr).float()
    bodies = body.pose(rot, tr)[0].float()
    rest, mass = _physics(scene)
    loss_fn = GarTransLoss(weights={"inertia": 1.0, "bending": 1.0},
                           enabled=("collision", "gravity", "stretch", "shear", "bending",
                                    "inertia"))

    def loss():
        nxt = model.step(scene, coarse, x[0:1], x[1:2], bodies[2:3], x[2:3])
        inp = LossInputs(pred=nxt, faces=scene.faces, body_pos=bodies[2:3],
                         body_faces=body.faces, mass=mass, rest=rest,
                         predicted=2 * x[1:2] - x[0:1], dt=model.dt)
        return loss_fn(inp)[0]

    _assert_trains(model, loss, lr=1e-3)


def test_ncs_style(setup):
    body, g, motion, scene = setup
    torch.manual_seed(0)
    model = NCSStyle(g.num_vertices, scene.num_joints, history=1, hidden=64)
    rot, tr = _pose(motion)
    hist = torch.stack([rot[:-1], rot[1:]], 1)  # [T-1, 2, S, 3]
    out = model(scene, hist, tr[1:])
    assert out.shape == (motion.num_frames - 1, g.num_vertices, 3) and torch.isfinite(out).all()
    torch.testing.assert_close(model(scene, hist[2:3], tr[3:4])[0], out[2], atol=1e-5, rtol=1e-5)
    # offsets do not depend on the root (global) orientation
    turned = hist.clone()
    turned[:, :, 0] += torch.tensor([0.0, 0.0, 0.7], dtype=hist.dtype)
    torch.testing.assert_close(model.offsets(turned), model.offsets(hist))
    # it is LBS of the offset rest shape
    torch.testing.assert_close(out, skin(scene, rot[1:], tr[1:], model.offsets(hist))[0])
    with pytest.raises(ValueError, match="rotations"):
        model(scene, rot[1:], tr[1:])
    with pytest.raises(ValueError, match="scene"):
        NCSStyle(g.num_vertices + 1, scene.num_joints)(scene, hist, tr[1:])
    # physics losses only; gradients reach every parameter and the loss goes down
    bodies = body.pose(rot, tr)[0].float()
    rest, mass = _physics(scene)
    loss_fn = GarTransLoss(enabled=("collision", "gravity", "stretch", "shear"))

    def loss():
        pred = model(scene, hist, tr[1:])
        return loss_fn(LossInputs(pred=pred, faces=scene.faces, body_pos=bodies[1:],
                                  body_faces=body.faces, mass=mass, rest=rest))[0]

    _assert_trains(model, loss, lr=1e-4)


def _assert_trains(model, loss, lr):
    """Gradients reach every parameter, are finite, and 6 Adam steps lower the loss."""
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    first = loss()
    first.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    opt.step()
    for _ in range(5):
        opt.zero_grad()
        loss().backward()
        opt.step()
    assert float(loss().detach()) < float(first.detach())


def test_to_device_is_a_copy_that_moves_the_rest_state(setup):
    """``GarmentInputs.to`` (what Lightning calls to put a batch on a GPU) returns a copy
    with every tensor, the rest state and the pinned mask on the device, and leaves the
    original where it was: PyG's ``Data.to`` moves in place, which put the bench's cached
    validation items on the GPU under a CPU prediction, and left ``rest`` on the CPU
    under a GPU loss.  The ``meta`` device stands in for a GPU."""
    scene = setup[-1].clone()
    scene.rest = _physics(scene)[0]
    del scene.pinned  # the all-False mask is made on the inputs' device
    moved = scene.to("meta")
    assert moved is not scene
    keys = [k for k, v in scene.items() if isinstance(v, torch.Tensor)]
    assert {"rest_pos", "faces", "edge_index", "skin_weights"} <= set(keys)
    for k in keys:
        assert scene[k].device.type == "cpu" and moved[k].device.type == "meta", k
    rest = [moved.rest.faces, moved.rest.uv_inverse, moved.rest.hinge_area,
            *moved.rest.adjacency]
    assert all(t.is_meta for t in rest) and not scene.rest.uv_inverse.is_meta
    assert type(moved.rest.adjacency) is type(scene.rest.adjacency)
    assert moved.pinned_mask().is_meta and not scene.pinned_mask().is_meta
    back = scene.cpu()  # cpu() and cuda() copy too (PyG's move in place)
    assert back is not scene and back.rest is not scene.rest
    only = scene.to("meta", "rest_pos")
    assert only.rest_pos.is_meta and not only.faces.is_meta and not only.rest.faces.is_meta
