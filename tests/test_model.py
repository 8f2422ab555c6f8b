"""GarTrans: shapes, frame-parallel batching, static-branch reuse, leaving out unused
branches, every registry layer in every slot, and batches of chunks of several garments
(one union graph) equal to each chunk alone."""
import copy
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
import trimesh

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.body.lbs import forward_kinematics, linear_blend_skinning
from garmentgnn.garments import make_garment
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.geometry import (edge_lengths, project_edge_lengths, signed_distance,
                                 unique_edges, vertex_normals)
from garmentgnn.models import GarTrans
from garmentgnn.models.inputs import GarmentInputs, build_static, with_frames
from garmentgnn.motion import make_motion

T, HISTORY = 8, 2


def garment_inputs(body, kind, motion, frames=T, resolution=200):
    """``kind`` on ``body`` under ``motion``: the model's inputs for frames ``0 .. frames-1``."""
    g = make_garment(kind, body, resolution=resolution)
    w = transfer_skinning_weights(g.vertices.float(), g.faces, body.vertices.float(),
                                  body.weights.float())
    static = build_static(g.vertices, g.faces, body, w, nystrom_dim=8, num_landmarks=32)
    m = make_motion(motion, body.skeleton, num_frames=T, rest_joints=body.joints)
    inp = with_frames(static, body, m.rotations, m.translation, torch.arange(frames), HISTORY)
    return g, inp, m


@pytest.fixture(scope="module")
def scene():
    """A skirt on a capsule body walking for 8 frames (pose histories of 3 poses)."""
    body = CapsuleBodyModel(resolution=6)("regular")
    g, inp, m = garment_inputs(body, "skirt", "walk")
    return SimpleNamespace(body=body, g=g, inputs=inp, motion=m)


def build(scene, **kw):
    """The paper's form (``kw`` override it), seeded: equal arguments, equal parameters."""
    torch.manual_seed(0)
    return GarTrans.paper(scene.body.skeleton.num_joints, scene.body.vertices.shape[0],
                          nystrom_dim=scene.inputs.nystrom.shape[1], **kw)


def with_keys(inp, **keys):
    """A shallow copy of ``inp`` with ``keys`` replaced (``None``: deleted)."""
    out = copy.copy(inp)
    for k, v in keys.items():
        if v is None:
            del out[k]
        else:
            out[k] = v
    return out


def lbs(scene, weights):
    """The oracle: Eq. 1 of the rest garment, by hand from the inputs' pose of frame t."""
    inp = scene.inputs
    A, _ = forward_kinematics(inp.rotations[:, -1], scene.body.joints,
                              scene.body.skeleton.parents, inp.translation[:, -1])
    return linear_blend_skinning(scene.g.vertices, weights, A)


def test_shapes_gradients_and_frame_parallel_batching(scene):
    inp = scene.inputs
    model = build(scene).eval()
    out = model(inp)
    B, V, S = T, scene.g.vertices.shape[0], scene.body.skeleton.num_joints
    assert out["final"].shape == (B, V, 3) and out["weights"].shape == (B, V, S)
    torch.testing.assert_close(out["weights"].sum(-1), torch.ones(B, V))
    assert torch.isfinite(out["final"]).all()
    # frames are independent: one batch equals frame-by-frame prediction
    single = model(inp.select(torch.tensor([2])))
    torch.testing.assert_close(single["final"][0], out["final"][2], atol=1e-5, rtol=1e-5)
    # every branch receives gradient
    model.train()
    model(inp)["final"].square().mean().backward()
    for name in ("rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru", "blend", "dynamic"):
        grads = [p.grad for p in getattr(model, name).parameters() if p.grad is not None]
        assert grads and any(gr.abs().sum() > 0 for gr in grads), name


def test_static_branch_is_reused_and_unused_branches_are_skipped(scene):
    inp = scene.inputs
    model = build(scene).eval()
    calls = {"body": 0, "gru": 0}
    model.body_fc.register_forward_hook(lambda *a: calls.__setitem__("body", calls["body"] + 1))
    model.gru.register_forward_hook(lambda *a: calls.__setitem__("gru", calls["gru"] + 1))
    static = model.encode_static(inp)
    a = model(inp, static)
    b = model(inp, static)
    assert calls["body"] == 1  # static branch computed once, reused
    torch.testing.assert_close(a["final"], b["final"])
    # no body: the body branch is left out (inputs without body distances, or use_body=False:
    # the learned per-joint code in its place, the same parameters from the same seed)
    no_dists = model.encode_static(with_keys(inp, body_joint_dists=None))
    assert calls["body"] == 1
    bodiless = build(scene, use_body=False).eval()
    bodiless.body_fc.register_forward_hook(lambda *a: calls.__setitem__("body",
                                                                        calls["body"] + 1))
    no_body = bodiless.encode_static(inp)
    assert calls["body"] == 1
    torch.testing.assert_close(no_dists.x2, no_body.x2)
    assert not torch.allclose(no_body.x2, static.x2, atol=1e-3)
    assert not bodiless.body_fc[0].weight.requires_grad and bodiless.body_default.requires_grad
    # a still pose: the GRU is left out
    still = with_keys(inp, rotations=inp.rotations[:, -1:].expand_as(inp.rotations).contiguous(),
                      translation=inp.translation[:, -1:].expand_as(inp.translation)
                      .contiguous())
    before = calls["gru"]
    out = model(still, no_body)
    assert calls["gru"] == before and torch.isfinite(out["final"]).all()
    # still pose: zero velocity, coarse meshes of t-1 and t coincide
    torch.testing.assert_close(out["final"] - out["coarse"], out["accel"] / model.fps ** 2)
    assert model.unit == model.fps ** -2


@pytest.mark.parametrize("slot", ["rest_layer", "blend_layer", "dynamic_layer"])
@pytest.mark.parametrize("layer", ["sat", "gt", "gt_edge", "structure_aware", "gat"])
def test_every_registry_layer_in_every_slot(scene, slot, layer):
    model = build(scene, **{slot: layer}).eval()
    with torch.no_grad():
        out = model(scene.inputs.select(torch.arange(2)))
    assert torch.isfinite(out["final"]).all()


def test_bad_pose_history(scene):
    """The inputs' builder refuses a history shorter than GarTrans needs (H >= 2)."""
    m = scene.motion
    with pytest.raises(ValueError, match="`history`"):
        with_frames(scene.inputs, scene.body, m.rotations, m.translation, torch.arange(2), 0)


def test_model_refuses_a_one_pose_history(scene):
    """A GarmentInputs with one pose per frame (``history_slot(-H)``) is refused by name."""
    model = build(scene)
    with pytest.raises(ValueError, match="rotations"):
        model(scene.inputs.select(torch.arange(2)).history_slot(-HISTORY - 1))


def test_autoregressive_rollout_feeds_back_its_own_prediction(scene):
    inp = scene.inputs
    model = build(scene).eval()
    static = model.encode_static(inp)
    with torch.no_grad():
        par = model(inp, static)
        ar = model.rollout(inp, static)
        # frame 0 has no prediction before it: the coarse previous frame, as in parallel mode
        torch.testing.assert_close(ar["final"][0], par["final"][0], atol=1e-5, rtol=1e-5)
        # prev_final = the coarse previous frame reproduces the default exactly
        two = inp.select(torch.tensor([2]))
        coarse_prev = model.coarse(two, static)[0]
        torch.testing.assert_close(model(two, static, prev_final=coarse_prev)["final"],
                                   par["final"][2:3])
        # frame t of the rollout = one step from frame t-1's prediction
        for t in (1, 3):
            step = model(inp.select(torch.tensor([t])), static,
                         prev_final=ar["final"][t - 1:t])
            torch.testing.assert_close(step["final"][0], ar["final"][t], atol=1e-5, rtol=1e-5)
        # the feedback path is live: a different garment before frame 0 changes frame 0
        # and, through it, frame 1
        # (each step passes a change on through the velocity times dt^2: 10 cm before
        # frame 0 moves frame 0 by ~0.5 mm and frame 1 by ~1 um, 20 float32 ulps)
        first = coarse_prev[0] + 0.1
        ar2 = model.rollout(inp, static, first=first)
        assert not torch.allclose(ar2["final"][0], ar["final"][0], rtol=0, atol=1e-5)
        assert not torch.allclose(ar2["final"][1], ar["final"][1], rtol=0, atol=1e-7)
        with pytest.raises(ValueError, match="prev_final"):
            model(inp.select(torch.arange(2)), static, prev_final=ar["final"][:1])


def test_skin_prior_is_the_starting_point_of_the_learned_weights(scene):
    """W^t = softmax(x3 + log prior): with the learned features zeroed, W^t is the prior
    (the inputs' skinning weights)."""
    model = build(scene, skin_prior=True).eval()
    V, S = scene.g.vertices.shape[0], scene.body.skeleton.num_joints
    prior = torch.softmax(3 * torch.randn(V, S, generator=torch.Generator().manual_seed(0)), -1)
    inp = with_keys(scene.inputs, skin_weights=prior)
    static = model.encode_static(inp)
    with torch.no_grad():
        W = model(inp, replace(static, x2=torch.zeros_like(static.x2)))["weights"]
        expected = prior.clamp_min(1e-4) / prior.clamp_min(1e-4).sum(-1, keepdim=True)
        torch.testing.assert_close(W, expected.expand_as(W), atol=1e-6, rtol=1e-5)
        W_free = build(scene, skin_prior=False).eval()(inp)["weights"]
    assert not torch.allclose(W_free, W, atol=1e-2)
    with pytest.raises(ValueError, match="skin_weights"):
        model.encode_static(with_keys(inp, skin_weights=prior[:, :3]))


def test_lbs_start_is_exactly_lbs_until_the_gates_open(scene):
    """``lbs_start``: the untrained model is LBS of the rest garment with the prior
    weights (Eq. 1, no blend shape, no acceleration); the zero gates still get gradient,
    and once open, every branch does."""
    model = build(scene, skin_prior=True, lbs_start=True)
    V, S = scene.g.vertices.shape[0], scene.body.skeleton.num_joints
    prior = torch.softmax(3 * torch.randn(V, S, generator=torch.Generator().manual_seed(1)), -1)
    inp = with_keys(scene.inputs, skin_weights=prior)
    out = model(inp)
    W = prior.clamp_min(1e-4) / prior.clamp_min(1e-4).sum(-1, keepdim=True)
    torch.testing.assert_close(out["final"], lbs(scene, W), atol=1e-5, rtol=1e-5)
    out["final"].square().mean().backward()
    assert (model.gates.grad.abs() > 0).all()
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.dynamic.parameters())
    with torch.no_grad():
        model.gates.fill_(0.5)
    model.zero_grad()
    model(inp)["final"].square().mean().backward()
    for name in ("rest_fc", "rest_attn", "nystrom_fc", "body_fc", "gru", "blend", "dynamic"):
        grads = [p.grad for p in getattr(model, name).parameters() if p.grad is not None]
        assert grads and any(gr.abs().sum() > 0 for gr in grads), name
    with pytest.raises(ValueError, match="lbs_start"):
        build(scene, lbs_start=True, skin_prior=False)


def test_collision_projection_moves_only_what_is_inside_or_too_close(scene):
    """``collision_projection``: the final mesh ends ``eps`` outside the body where it was
    closer (exact signed distance as the oracle); every other vertex is the unprojected
    prediction; without a body the model is unchanged."""
    plain, proj = build(scene), build(scene, collision_projection=0.004)
    proj.load_state_dict(plain.state_dict())
    with torch.no_grad():
        ref = plain(scene.inputs)["final"]
        # an obstacle that swallows part of the garment in every frame
        ball = trimesh.creation.icosphere(subdivisions=3, radius=0.12)
        centre = ref[:, 0]  # [B, 3], one garment vertex per frame
        bpos = torch.tensor(ball.vertices, dtype=torch.float32) + centre[:, None]
        bfaces = torch.tensor(ball.faces)
        inp = with_keys(scene.inputs, body_pos=bpos, body_faces=bfaces)
        out = proj(inp)["final"]
        torch.testing.assert_close(proj(with_keys(inp, body_pos=None))["final"],
                                   ref)  # no body: no projection
        s_before = signed_distance(ref, bpos, bfaces).distance
        s_after = signed_distance(out, bpos, bfaces).distance
        near = s_before < 0.004
        assert (s_before < 0).sum() >= T and (~near).any()
        assert (s_after[near] - 0.004).abs().max() < 1e-4
        torch.testing.assert_close(out[~near], ref[~near])
        ar = proj.rollout(inp)["final"]
        assert signed_distance(ar, bpos, bfaces).distance.min() > 0.004 - 1e-4
    with pytest.raises(ValueError, match="collision_projection"):
        build(scene, collision_projection=-1.0)
    # a body without its faces is refused by name, not skipped (PyG's storage raises
    # an AttributeError naming the key: the model has no check of its own)
    with pytest.raises((ValueError, AttributeError), match="body_faces"):
        proj(with_keys(inp, body_faces=None))


def test_strain_limit_is_the_edge_projection_of_the_prediction(scene):
    """``strain_limit=k``: the final mesh is the unlimited prediction after ``k``
    stretch-only sweeps toward the rest garment's edge lengths (the geometry function
    as the oracle)."""
    g = scene.g
    plain = build(scene, skin_prior=True, lbs_start=True)
    lim = build(scene, skin_prior=True, lbs_start=True, strain_limit=4)
    # the acceleration gate opened wide, so that the prediction has stretched edges
    with torch.no_grad():
        plain.gates.copy_(torch.tensor([1.0, 1.0, 100.0]))
    lim.load_state_dict(plain.state_dict())
    edges = unique_edges(g.faces, g.vertices.shape[0]).edges
    rest = edge_lengths(g.vertices, edges)
    with torch.no_grad():
        ref = plain(scene.inputs)["final"]
        out = lim(scene.inputs)["final"]
    torch.testing.assert_close(out, project_edge_lengths(ref, edges, rest, 4, stretch_only=True))

    def over(p):
        return float((edge_lengths(p, edges) / rest - 1).clamp_min(0).mean())

    assert over(out) < 0.8 * over(ref)
    with pytest.raises(ValueError, match="strain_limit"):
        build(scene, strain_limit=-2)


def test_strain_limit_targets_are_static(scene):
    """The strain limit's edges and rest lengths come with the static features, once
    per garment (the rest garment's unique edges and lengths)."""
    g = scene.g
    model = build(scene, skin_prior=True, lbs_start=True, strain_limit=3).eval()
    with torch.no_grad():
        static = model.encode_static(scene.inputs)
    edges = unique_edges(g.faces, g.vertices.shape[0]).edges
    torch.testing.assert_close(static.strain_edges, edges)
    torch.testing.assert_close(static.strain_lengths, edge_lengths(g.vertices, edges))


def test_static_features_without_strain_targets_give_the_same_prediction(scene):
    """Static features made without the strain targets (e.g. by a model without the strain
    limit) give the same prediction as those with them."""
    model = build(scene, skin_prior=True, lbs_start=True, strain_limit=3).eval()
    inp = scene.inputs.select(torch.arange(2))
    with torch.no_grad():
        model.gates.copy_(torch.tensor([1.0, 1.0, 100.0]))
        static = model.encode_static(inp)
        bare = type(static)(x2=static.x2, log_prior=static.log_prior)
        torch.testing.assert_close(model(inp, bare)["final"], model(inp, static)["final"])


def test_blend_shape_can_be_left_out(scene):
    """``blend_shape=False``: no blend stack, the coarse mesh is LBS of the rest garment
    with the learned weights ``W^t`` (Eq. 1 with ``T^t = T``)."""
    model = build(scene, blend_shape=False).eval()
    assert model.blend is None
    with torch.no_grad():
        out = model(scene.inputs)
    torch.testing.assert_close(out["coarse"], lbs(scene, out["weights"]), atol=1e-5, rtol=1e-5)
    full = build(scene).eval()
    with torch.no_grad():
        out = full(scene.inputs)
    assert not torch.allclose(out["coarse"], lbs(scene, out["weights"]), atol=1e-5)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, torch.pi / 2), (0.3, -0.5, 0.8)])
def test_local_frame_turns_the_dynamic_inputs_and_output_with_the_skinning(scene, rotvec):
    """``local_frame``: with every joint turned by one root rotation ``R`` (scipy's matrix
    as the oracle), every vertex's blended rotation is ``R``; the dynamic stack sees
    ``R^T v``, ``R^T n`` (= the rest garment's normals), the rest position and
    ``R^T (0, 0, -1)``, and its output ``c`` is added as ``R c`` (centimetres)."""
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    g = scene.g
    S, V = scene.body.skeleton.num_joints, g.vertices.shape[0]
    model = build(scene, local_frame=True, accel_unit=0.01, blend_shape=False).eval()
    rots = torch.zeros(1, HISTORY + 1, S, 3)
    rots[:, :, 0] = torch.tensor(rotvec)
    tr = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]])
    inp = with_keys(scene.inputs.select(torch.tensor([0])), rotations=rots, translation=tr)
    seen = {}
    c = torch.tensor([1.0, -2.0, 0.5])

    def fake_stack(x, edge_index, edge_attr):
        seen["x"] = x
        return c.expand(x.shape[0], 3)

    model.dynamic.forward = fake_stack
    with torch.no_grad():
        out = model(inp)
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
    plain = build(scene, accel_unit=0.01, blend_shape=False).eval()
    plain.dynamic.forward = fake_stack
    with torch.no_grad():
        out = plain(inp)
    assert seen["x"].shape == (V, 3 + 3 + S)
    torch.testing.assert_close(out["final"] - out["coarse"], (0.01 * c).expand(1, V, 3))


# -- batches of chunks: one union graph ------------------------------------------------------
CHUNK = 4  # frames per chunk of the batch tests


@pytest.fixture(scope="module")
def chunks(scene):
    """Two chunks of the same frame count: the skirt walking (200 vertices) and a t-shirt
    twirling (another vertex count, another motion)."""
    a = scene.inputs.select(torch.arange(CHUNK))
    _, b, _ = garment_inputs(scene.body, "tshirt", "twirl", frames=CHUNK)
    assert a.num_vertices != b.num_vertices
    return a, b


def gradients(model, inp):
    """``d (final ** 2).sum() / d p`` of every trainable parameter (``None``: no gradient)."""
    model.zero_grad()
    (model(inp)["final"] ** 2).sum().backward()
    return {n: None if p.grad is None else p.grad.clone()
            for n, p in model.named_parameters() if p.requires_grad}


@pytest.mark.parametrize("form", ["default", "paper"])
def test_a_batch_of_chunks_equals_each_chunk_alone(scene, chunks, form):
    """``GarmentInputs.collate([a, b])`` of two garments (different vertex counts) under two
    motions is one union graph: every output on each chunk's vertex slice equals the chunk
    predicted alone (its own joints, transforms, body and collision projection), and the
    gradient of a sum over the batch is the sum of the chunks' gradients."""
    a, b = chunks
    Va = a.num_vertices
    S, Vb = scene.body.skeleton.num_joints, scene.body.vertices.shape[0]
    torch.manual_seed(0)
    if form == "paper":
        model = GarTrans.paper(S, Vb, nystrom_dim=a.nystrom.shape[1])
    else:
        model = GarTrans(S, Vb, nystrom_dim=a.nystrom.shape[1])
        assert model.collision_projection and model.input_norm and model.local_frame
        model.train()  # the running normalisers: statistics of one chunk, then frozen
        with torch.no_grad():
            model(with_keys(b, body_pos=None))
    model.eval()
    batch = GarmentInputs.collate([a, b])
    assert batch.num_chunks == 2 and batch.num_frames == CHUNK
    assert batch.num_vertices == Va + b.num_vertices
    with torch.no_grad():
        out = model(batch)
        alone = model(a), model(b)
    assert set(out) == {"final", "coarse", "accel", "weights"}
    for k in out:
        assert out[k].shape[:2] == (CHUNK, Va + b.num_vertices), k
        torch.testing.assert_close(out[k][:, :Va], alone[0][k], atol=1e-5, rtol=1e-5, msg=k)
        torch.testing.assert_close(out[k][:, Va:], alone[1][k], atol=1e-5, rtol=1e-5, msg=k)
    # the chunks really differ (a mix-up of chunks would not pass unseen)
    assert not torch.allclose(alone[0]["weights"][:, :1], alone[1]["weights"][:, :1], atol=1e-3)
    if form == "default":
        # the projection acts (on the t-shirt, the second chunk, against its own body)
        with torch.no_grad():
            free = model(with_keys(batch, body_pos=None))["final"]
        assert (free[:, Va:] - out["final"][:, Va:]).abs().max() > 1e-4
    # gradients: the batch's equal the sum of the chunks' (relative to each parameter's
    # largest, floored at 1e-4 of the largest overall: the attention key biases get a
    # gradient of exactly zero up to round-off, the softmax being invariant to them)
    g_batch = gradients(model, batch)
    g_a, g_b = gradients(model, a), gradients(model, b)
    top = max(float(g.abs().max()) for g in g_batch.values() if g is not None)
    live = 0
    for n, gb in g_batch.items():
        parts = [g[n] for g in (g_a, g_b) if g[n] is not None]
        if gb is None:
            assert not parts, n
            continue
        expected = sum(parts)
        scale = float(expected.abs().max())
        torch.testing.assert_close(gb, expected, rtol=1e-4, atol=1e-4 * max(scale, 1e-4 * top),
                                   msg=n)
        live += scale > 1e-6 * top
    assert live > 0.8 * len(g_batch)
    # a batch is refused where one chunk is meant
    with pytest.raises(ValueError, match="`inputs`"):
        model.rollout(batch)
    with pytest.raises(ValueError, match="`inputs`"):
        model.predict_sequence(batch)


def test_collate_refuses_chunks_of_different_frame_counts(chunks):
    a, b = chunks
    with pytest.raises(ValueError, match=r"`items`.*same frame count.*\[3, 4\].*"
                                         r"cut sequences into chunks of one length"):
        GarmentInputs.collate([a, b.select(torch.arange(3))])


def test_select_of_a_batch_selects_the_same_frames_of_every_chunk(chunks):
    """The oracle: the batch of each chunk's own selection (per-frame keys of a batch
    are stacked ``[N, B, ...]`` or concatenated ``[B, sum V, ...]``)."""
    a, b = chunks
    idx = torch.tensor([3, 1])
    got = GarmentInputs.collate([a, b]).select(idx)
    want = GarmentInputs.collate([a.select(idx), b.select(idx)])
    for k in ("rotations", "translation", "body_pos", "frames"):
        torch.testing.assert_close(got[k], want[k], msg=k)
    assert got.num_frames == 2 and got.rotations.shape[:2] == (2, 2)
