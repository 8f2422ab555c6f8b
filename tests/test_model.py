"""GarTrans: shapes, frame-parallel batching, static-branch reuse, leaving out unused
branches, and every registry layer in every slot."""
from dataclasses import replace

import pytest
import torch
import trimesh

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments import make_garment
from garmentgnn.geometry import (edge_lengths, faces_to_edge_index, geodesic_nystrom_features,
                                 project_edge_lengths, signed_distance, unique_edges,
                                 vertex_normals)
from garmentgnn.models import PAPER_FORM, GarTrans
from garmentgnn.motion import make_motion


@pytest.fixture(scope="module")
def scene():
    body = CapsuleBodyModel(resolution=6)("regular")
    g = make_garment("skirt", body, resolution=200)
    ei = faces_to_edge_index(g.faces, g.vertices.shape[0])
    ny = geodesic_nystrom_features(g.vertices, g.faces, k=8, num_landmarks=32).float()
    bd = torch.cdist(body.vertices, body.joints)
    m = make_motion("walk", body.skeleton, num_frames=8, rest_joints=body.joints)
    H = 3
    rots = torch.stack([m.rotations[i - H + 1:i + 1] for i in range(H - 1, 8)]).float()
    tr = torch.stack([m.translation[i - H + 1:i + 1] for i in range(H - 1, 8)]).float()
    return body, g, ei, ny, bd, rots, tr


def build(body, ny, **kw):
    torch.manual_seed(0)
    return GarTrans(body.skeleton.num_joints, body.vertices.shape[0], nystrom_dim=ny.shape[1],
                    **dict(PAPER_FORM, **kw))


def run(model, scene, static=None, rots=None, tr=None):
    body, g, ei, ny, bd, R, T = scene
    static = static or model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
    return model(static, g.vertices, g.faces, ei, body.joints, body.skeleton.parents,
                 R if rots is None else rots, T if tr is None else tr)


def test_shapes_gradients_and_frame_parallel_batching(scene):
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny).eval()
    out = run(model, scene)
    B, V, S = rots.shape[0], g.vertices.shape[0], body.skeleton.num_joints
    assert out["final"].shape == (B, V, 3) and out["weights"].shape == (B, V, S)
    torch.testing.assert_close(out["weights"].sum(-1), torch.ones(B, V))
    assert torch.isfinite(out["final"]).all()
    # frames are independent: one batch equals frame-by-frame prediction
    single = run(model, scene, rots=rots[2:3], tr=tr[2:3])
    torch.testing.assert_close(single["final"][0], out["final"][2], atol=1e-5, rtol=1e-5)
    # every branch receives gradient
    model.train()
    run(model, scene)["final"].square().mean().backward()
    for name in ("rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru", "blend", "dynamic"):
        grads = [p.grad for p in getattr(model, name).parameters() if p.grad is not None]
        assert grads and any(gr.abs().sum() > 0 for gr in grads), name


def test_static_branch_is_reused_and_unused_branches_are_skipped(scene):
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny).eval()
    calls = {"body": 0, "gru": 0}
    model.body_fc.register_forward_hook(lambda *a: calls.__setitem__("body", calls["body"] + 1))
    model.gru.register_forward_hook(lambda *a: calls.__setitem__("gru", calls["gru"] + 1))
    static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
    a = run(model, scene, static)
    b = run(model, scene, static)
    assert calls["body"] == 1  # static branch computed once, reused
    torch.testing.assert_close(a["final"], b["final"])
    # no body: the body branch is left out
    no_body = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, None)
    assert calls["body"] == 1
    # a still pose: the GRU is left out
    still_r = rots[:, -1:].expand_as(rots).contiguous()
    still_t = tr[:, -1:].expand_as(tr).contiguous()
    before = calls["gru"]
    out = run(model, scene, no_body, still_r, still_t)
    assert calls["gru"] == before and torch.isfinite(out["final"]).all()
    # still pose: zero velocity, coarse meshes of t-1 and t coincide
    torch.testing.assert_close(out["final"] - out["coarse"],
                               out["accel"] / model.fps ** 2)


@pytest.mark.parametrize("slot", ["rest_layer", "blend_layer", "dynamic_layer"])
@pytest.mark.parametrize("layer", ["sat", "gt", "gt_edge", "structure_aware", "gat"])
def test_every_registry_layer_in_every_slot(scene, slot, layer):
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny, **{slot: layer}).eval()
    with torch.no_grad():
        out = run(model, scene, rots=rots[:2], tr=tr[:2])
    assert torch.isfinite(out["final"]).all()


def test_bad_pose_history(scene):
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny)
    with pytest.raises(ValueError, match="rotations"):
        run(model, scene, rots=rots[:, :1], tr=tr[:, :1])


def test_autoregressive_rollout_feeds_back_its_own_prediction(scene):
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny).eval()
    static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
    args = (static, g.vertices, g.faces, ei, body.joints, body.skeleton.parents)
    with torch.no_grad():
        par = model(*args, rots, tr)
        ar = model.rollout(*args, rots, tr)
        # frame 0 has no prediction before it: the coarse previous frame, as in parallel mode
        torch.testing.assert_close(ar["final"][0], par["final"][0], atol=1e-5, rtol=1e-5)
        # prev_final = the coarse previous frame reproduces the default exactly
        coarse_prev = model.coarse(static, g.vertices, ei, body.joints, body.skeleton.parents,
                                   rots[2:3], tr[2:3])[0][:, 0]
        torch.testing.assert_close(model(*args, rots[2:3], tr[2:3], prev_final=coarse_prev)
                                   ["final"], par["final"][2:3])
        # frame t of the rollout = one step from frame t-1's prediction
        for t in (1, 3):
            step = model(*args, rots[t:t + 1], tr[t:t + 1], prev_final=ar["final"][t - 1:t])
            torch.testing.assert_close(step["final"][0], ar["final"][t], atol=1e-5, rtol=1e-5)
        # the feedback path is live: a different garment before frame 0 changes frame 0
        # and, through it, frame 1
        # (each step passes a change on through the velocity times dt^2: 10 cm before
        # frame 0 moves frame 0 by ~0.5 mm and frame 1 by ~1 um, 20 float32 ulps)
        first = coarse_prev[0] + 0.1
        ar2 = model.rollout(*args, rots, tr, first=first)
        assert not torch.allclose(ar2["final"][0], ar["final"][0], rtol=0, atol=1e-5)
        assert not torch.allclose(ar2["final"][1], ar["final"][1], rtol=0, atol=1e-7)
        with pytest.raises(ValueError, match="prev_final"):
            model(*args, rots[:2], tr[:2], prev_final=ar["final"][:1])


def test_skin_prior_is_the_starting_point_of_the_learned_weights(scene):
    """W^t = softmax(x3 + log prior): with the learned features zeroed, W^t is the prior."""
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny).eval()
    V, S = g.vertices.shape[0], body.skeleton.num_joints
    prior = torch.softmax(3 * torch.randn(V, S, generator=torch.Generator().manual_seed(0)), -1)
    static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd, skin_prior=prior)
    with torch.no_grad():
        W = run(model, scene, static=replace(static, x2=torch.zeros_like(static.x2)))["weights"]
        expected = prior.clamp_min(1e-4) / prior.clamp_min(1e-4).sum(-1, keepdim=True)
        torch.testing.assert_close(W, expected.expand_as(W), atol=1e-6, rtol=1e-5)
        W_free = run(model, scene)["weights"]
    assert not torch.allclose(W_free, W, atol=1e-2)
    with pytest.raises(ValueError, match="skin_prior"):
        model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd, skin_prior=prior[:, :3])


def test_lbs_start_is_exactly_lbs_until_the_gates_open(scene):
    """``lbs_start``: the untrained model is LBS of the rest garment with the prior
    weights (Eq. 1, no blend shape, no acceleration); the zero gates still get gradient,
    and once open, every branch does."""
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny, lbs_start=True)
    V, S = g.vertices.shape[0], body.skeleton.num_joints
    prior = torch.softmax(3 * torch.randn(V, S, generator=torch.Generator().manual_seed(1)), -1)
    static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd, skin_prior=prior)
    out = run(model, scene, static=static)
    A, _ = forward_kinematics(rots[:, -1], body.joints, body.skeleton.parents, tr[:, -1])
    W = prior.clamp_min(1e-4) / prior.clamp_min(1e-4).sum(-1, keepdim=True)
    torch.testing.assert_close(out["final"], linear_blend_skinning(g.vertices, W, A),
                               atol=1e-5, rtol=1e-5)
    out["final"].square().mean().backward()
    assert (model.gates.grad.abs() > 0).all()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.dynamic.parameters())
    with torch.no_grad():
        model.gates.fill_(0.5)
    model.zero_grad()
    run(model, scene, static=model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd,
                                                 skin_prior=prior))["final"].square().mean().backward()
    for name in ("rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru", "blend", "dynamic"):
        grads = [p.grad for p in getattr(model, name).parameters() if p.grad is not None]
        assert grads and any(gr.abs().sum() > 0 for gr in grads), name


def test_collision_projection_moves_only_what_is_inside_or_too_close(scene):
    """``collision_projection``: the final mesh ends ``eps`` outside the body where it was
    closer (exact signed distance as the oracle); every other vertex is the unprojected
    prediction; without a body the model is unchanged."""
    body, g, ei, ny, bd, rots, tr = scene
    plain, proj = build(body, ny), build(body, ny, collision_projection=0.004)
    proj.load_state_dict(plain.state_dict())
    with torch.no_grad():
        ref = run(plain, scene)["final"]
        # an obstacle that swallows part of the garment in every frame
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.12)
        centre = ref[:, 0]  # [B, 3], one garment vertex per frame
        bpos = torch.tensor(ball.vertices, dtype=torch.float32) + centre[:, None]
        bfaces = torch.tensor(ball.faces)
        static = proj.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
        args = (static, g.vertices, g.faces, ei, body.joints, body.skeleton.parents, rots, tr)
        out = proj(*args, body_pos=bpos, body_faces=bfaces)["final"]
        torch.testing.assert_close(proj(*args)["final"], ref)  # no body: no projection
        s_before = signed_distance(ref, bpos, bfaces).distance
        s_after = signed_distance(out, bpos, bfaces).distance
        near = s_before < 0.004
        assert (s_before < 0).sum() >= rots.shape[0] and (~near).any()
        assert (s_after[near] - 0.004).abs().max() < 1e-4
        torch.testing.assert_close(out[~near], ref[~near])
        ar = proj.rollout(*args, body_pos=bpos, body_faces=bfaces)["final"]
        assert signed_distance(ar, bpos, bfaces).distance.min() > 0.004 - 1e-4
    with pytest.raises(ValueError, match="collision_projection"):
        build(body, ny, collision_projection=-1.0)
    with pytest.raises(ValueError, match="body_faces"):
        proj(*args, body_pos=bpos)


def test_strain_limit_is_the_edge_projection_of_the_prediction(scene):
    """``strain_limit=k``: the final mesh is the unlimited prediction after ``k``
    stretch-only sweeps toward the rest garment's edge lengths (the geometry function
    as the oracle)."""
    body, g, ei, ny, bd, rots, tr = scene
    plain, lim = build(body, ny, lbs_start=True), build(body, ny, lbs_start=True, strain_limit=4)
    # the acceleration gate opened wide, so that the prediction has stretched edges
    with torch.no_grad():
        plain.gates.copy_(torch.tensor([1.0, 1.0, 100.0]))
    lim.load_state_dict(plain.state_dict())
    edges = unique_edges(g.faces, g.vertices.shape[0]).edges
    rest = edge_lengths(g.vertices, edges)
    with torch.no_grad():
        ref = run(plain, scene)["final"]
        out = run(lim, scene)["final"]
    torch.testing.assert_close(out, project_edge_lengths(ref, edges, rest, 4, stretch_only=True))

    def over(p):
        return float((edge_lengths(p, edges) / rest - 1).clamp_min(0).mean())

    assert over(out) < 0.7 * over(ref)
    with pytest.raises(ValueError, match="strain_limit"):
        build(body, ny, strain_limit=-2)


def test_strain_limit_targets_are_static(scene):
    """The strain limit's edges and rest lengths come with the static features, once
    per garment; static features made without them give the same prediction."""
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny, lbs_start=True, strain_limit=3).eval()
    with torch.no_grad():
        model.gates.copy_(torch.tensor([1.0, 1.0, 100.0]))
        static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
        edges = unique_edges(g.faces, g.vertices.shape[0]).edges
        torch.testing.assert_close(static.strain_edges, edges)
        torch.testing.assert_close(static.strain_lengths, edge_lengths(g.vertices, edges))
        bare = type(static)(x2=static.x2, log_prior=static.log_prior)
        torch.testing.assert_close(run(model, scene, bare)["final"],
                                   run(model, scene, static)["final"])


def test_blend_shape_can_be_left_out(scene):
    """``blend_shape=False``: no blend stack, the coarse mesh is LBS of the rest garment
    with the learned weights ``W^t`` (Eq. 1 with ``T^t = T``)."""
    body, g, ei, ny, bd, rots, tr = scene
    model = build(body, ny, blend_shape=False).eval()
    assert model.blend is None
    with torch.no_grad():
        out = run(model, scene)
    A, _ = forward_kinematics(rots[:, -1], body.joints, body.skeleton.parents, tr[:, -1])
    torch.testing.assert_close(out["coarse"], linear_blend_skinning(g.vertices, out["weights"], A),
                               atol=1e-5, rtol=1e-5)
    full = build(body, ny).eval()
    with torch.no_grad():
        assert not torch.allclose(run(full, scene)["coarse"],
                                  linear_blend_skinning(g.vertices, run(full, scene)["weights"], A),
                                  atol=1e-5)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, torch.pi / 2), (0.3, -0.5, 0.8)])
def test_local_frame_turns_the_dynamic_inputs_and_output_with_the_skinning(scene, rotvec):
    """``local_frame``: with every joint turned by one root rotation ``R`` (scipy's matrix
    as the oracle), every vertex's blended rotation is ``R``; the dynamic stack sees
    ``R^T v``, ``R^T n`` (= the rest garment's normals), the rest position and
    ``R^T (0, 0, -1)``, and its output ``c`` is added as ``R c`` (centimetres)."""
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    body, g, ei, ny, bd, _, _ = scene
    S, V = body.skeleton.num_joints, g.vertices.shape[0]
    model = build(body, ny, local_frame=True, accel_unit=0.01, blend_shape=False).eval()
    rots = torch.zeros(1, 3, S, 3)
    rots[:, :, 0] = torch.tensor(rotvec)
    tr = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]])
    seen = {}
    c = torch.tensor([1.0, -2.0, 0.5])

    def fake_stack(x, edge_index, edge_attr):
        seen["x"] = x
        return c.expand(x.shape[0], 3)

    model.dynamic.forward = fake_stack
    with torch.no_grad():
        out = run(model, scene, rots=rots, tr=tr)
    R = torch.from_numpy(Rotation.from_rotvec(rotvec).as_matrix()).float()
    x = seen["x"]
    assert x.shape == (V, 3 + 3 + S + 6)
    torch.testing.assert_close(x[:, :3], (R.T @ torch.tensor([3.0, 0.0, 0.0])).expand(V, 3),
                               atol=1e-4, rtol=1e-4)  # 10 cm in one frame at 30 fps
    torch.testing.assert_close(x[:, 3:6], vertex_normals(g.vertices, g.faces),
                               atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(x[:, -6:-3], g.vertices)
    torch.testing.assert_close(x[:, -3:], (R.T @ torch.tensor([0.0, 0.0, -1.0])).expand(V, 3),
                               atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["final"] - out["coarse"], (0.01 * R @ c).expand(1, V, 3),
                               atol=1e-6, rtol=1e-4)
    # without the switch the stack sees world vectors and its output is added unturned
    plain = build(body, ny, accel_unit=0.01, blend_shape=False).eval()
    plain.dynamic.forward = fake_stack
    with torch.no_grad():
        out = run(plain, scene, rots=rots, tr=tr)
    assert seen["x"].shape == (V, 3 + 3 + S)
    torch.testing.assert_close(out["final"] - out["coarse"], (0.01 * c).expand(1, V, 3))


@pytest.mark.parametrize("local_frame", [False, True])
def test_motion_history_feeds_the_earlier_velocities_newest_first(scene, local_frame):
    """``motion_history=3``: the dynamic stack also sees the coarse mesh's velocities at
    t-1 and t-2 (a turned root moved to 0, 5, 15 and 30 cm: 1.5, 3 and 4.5 m/s at 30 fps,
    newest first), turned into the local frame with ``local_frame``."""
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    body, g, ei, ny, bd, _, _ = scene
    S, V = body.skeleton.num_joints, g.vertices.shape[0]
    model = build(body, ny, local_frame=local_frame, motion_history=3,
                  blend_shape=False).eval()
    rotvec = (0.2, 0.4, -0.7)
    rots = torch.zeros(1, 4, S, 3)
    rots[:, :, 0] = torch.tensor(rotvec)
    tr = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.15, 0.0, 0.0],
                       [0.3, 0.0, 0.0]]).unsqueeze(0)
    seen = {}

    def fake_stack(x, edge_index, edge_attr):
        seen["x"] = x
        return x.new_zeros(x.shape[0], 3)

    model.dynamic.forward = fake_stack
    with torch.no_grad():
        run(model, scene, rots=rots, tr=tr)
    R = torch.from_numpy(Rotation.from_rotvec(rotvec).as_matrix()).float()
    turn = R.T if local_frame else torch.eye(3)
    x = seen["x"]
    assert x.shape == (V, 3 + 3 + S + 6 + (6 if local_frame else 0))
    for cols, speed in ((slice(0, 3), 4.5), (slice(6 + S, 9 + S), 3.0),
                        (slice(9 + S, 12 + S), 1.5)):
        torch.testing.assert_close(x[:, cols], (turn @ torch.tensor([speed, 0.0, 0.0]))
                                   .expand(V, 3), atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="motion_history"):
        run(model, scene, rots=rots[:, 1:], tr=tr[:, 1:])
    with pytest.raises(ValueError, match="motion_history"):
        build(body, ny, motion_history=0)
