"""GarTrans's garment states (``models/state.py``) against oracles computed by hand: the
autoregressive offsets, teacher-forced rollouts and their noise; the recurrent latent's
causality, a state carried from call to call equal to one call, batches equal to each
chunk alone; the motion code reaching the dynamic stack; bad arguments."""
from unittest import mock

import pytest
import torch

from garmentgnn.models import GarTrans
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.models.state import TeacherForcing
from garmentgnn.training import GarTransModule
from test_model import T, chunks, scene, with_keys  # noqa: F401  (module-scoped fixtures)


def build(sc, **kw):
    """The project's form with ``kw`` for scene ``sc``, seeded; no post-steps unless
    ``kw`` asks."""
    torch.manual_seed(0)
    kw = {"strain_limit": 0, "collision_projection": None, **kw}
    return GarTrans(sc.body.skeleton.num_joints, sc.body.vertices.shape[0],
                    nystrom_dim=sc.inputs.nystrom.shape[1], **kw).eval()


def fake_gt(inp, seed=1):
    """A made-up simulated garment: the rest garment moved by a smooth per-frame field."""
    g = torch.Generator().manual_seed(seed)
    B, V = inp.num_frames, inp.num_vertices
    return inp.skinned() + 0.02 * torch.randn(B, 1, 3, generator=g) \
        + 0.01 * torch.randn(B, V, 3, generator=g)


def silenced(model):
    """``model`` with the dynamic output's gate shut: ``M^{t,d} = M^{t,c} + d_{t-1}``."""
    with torch.no_grad():
        model.gates[2] = 0.0
    return model


# ----------------------------------------------------------------------- batched select
def test_select_of_a_batch_selects_the_same_frames_of_every_chunk(chunks):  # noqa: F811
    """The oracle: the batch of each chunk's own selection (per-frame keys of a batch
    are stacked ``[N, B, ...]`` or concatenated ``[B, sum V, ...]``)."""
    a, b = chunks
    idx = torch.tensor([3, 1])
    got = GarmentInputs.collate([a, b]).select(idx)
    want = GarmentInputs.collate([a.select(idx), b.select(idx)])
    for k in ("rotations", "translation", "body_pos", "frames"):
        torch.testing.assert_close(got[k], want[k], msg=k)
    assert got.num_frames == 2 and got.rotations.shape[:2] == (2, 2)


# --------------------------------------------------------------------- autoregressive
def test_autoregressive_carries_the_previous_offset_by_the_skinned_motion(scene):  # noqa: F811
    """Gate shut, no post-steps: a test rollout stays on the coarse mesh (zero offsets
    from no state), and from a given state every frame is ``M^{t,c} + d_{t-1}``."""
    inp = scene.inputs
    model = silenced(build(scene, autoregressive=True))
    with torch.no_grad():
        out = model(inp)
        torch.testing.assert_close(out["final"], out["coarse"])
        d = torch.randn(2, inp.num_vertices, 3) * 0.01
        out = model(inp, state=d)
    torch.testing.assert_close(out["final"], out["coarse"] + d[1])
    torch.testing.assert_close(out["state"], d[1].expand(2, -1, -1))  # d_{t-1} each frame


@pytest.mark.parametrize("k", [1, 2, 3, T])
def test_teacher_rollouts_start_from_the_simulated_offsets(scene, k):  # noqa: F811
    """Rollouts of ``k`` frames start at frames 0, k, 2k, ...; the one at ``s`` from the
    simulated offsets at ``s-1`` (zero before the chunk), and each later frame carries its
    rollout's own last offset, so frame ``t`` of the rollout at ``s`` is
    ``M^{t,c} + gt[s-1] - M^{s-1,c}`` (gate shut)."""
    inp = scene.inputs
    gt = fake_gt(inp)
    model = silenced(build(scene, autoregressive=True))
    with torch.no_grad():
        out = model(inp, teacher=TeacherForcing(gt, k))
    cur = out["coarse"]
    for t in range(T):
        s = t - t % k
        want = cur[t] if s == 0 else cur[t] + gt[s - 1] - cur[s - 1]
        torch.testing.assert_close(out["final"][t], want, msg=f"frame {t}")


def test_teacher_noise_is_gaussian_of_the_given_metres(scene):  # noqa: F811
    inp = scene.inputs
    gt = fake_gt(inp)
    model = silenced(build(scene, autoregressive=True))
    with torch.no_grad():
        clean = model(inp, teacher=TeacherForcing(gt, 1))["final"]
        torch.manual_seed(3)
        noisy = model(inp, teacher=TeacherForcing(gt, 1, noise=0.003))["final"]
    diff = (noisy - clean)[1:]  # frame 0 starts from no state
    assert abs(float(diff.std()) - 0.003) < 0.0003 and abs(float(diff.mean())) < 0.0003


def test_a_rollout_backpropagates_through_its_own_frames(scene):  # noqa: F811
    """Which simulated frames frame 3's output has a gradient with respect to.  Rollouts
    of 1: the two before it, 1 and 2.  Rollouts of 2: frame 3 follows its rollout's own
    frame 2 (not the simulated one), which started from the simulated 0 and 1, so 0
    and 1.  Never frame 3 or later."""
    inp = scene.inputs
    for k, reached in ((1, [False, True, True]), (2, [True, True, False])):
        gt = fake_gt(inp).requires_grad_(True)
        model = build(scene, autoregressive=True)  # eval: frozen normalisers
        out = model(inp, teacher=TeacherForcing(gt, k))
        g = torch.autograd.grad(out["final"][3].sum(), gt)[0].abs().sum((1, 2))
        assert (g[:3] > 0).tolist() == reached, k
        assert float(g[3:].max()) == 0.0, k


# -------------------------------------------------------------------- recurrent latent
def test_the_recurrent_latent_is_causal_and_carries_the_past(scene):  # noqa: F811
    """Another pose history at frame 0 alone (its rows of the inputs) leaves frames 1..
    of a frame-parallel model as they were but changes every later frame of the
    recurrent one; a change at frame 5 never reaches frames 0..4."""
    inp = scene.inputs

    def changed_at(t):
        rot = inp.rotations.clone()
        rot[t] = rot[t] + 0.3
        return with_keys(inp, rotations=rot)

    for L, later in ((0, False), (8, True)):
        model = build(scene, vertex_state=L)
        with torch.no_grad():
            base = model(inp)["final"]
            f0 = model(changed_at(0))["final"]
            f5 = model(changed_at(5))["final"]
        moved = (f0 - base).abs().amax((1, 2))
        assert bool(moved[0] > 1e-5)
        if later:
            assert bool((moved[1:] > 1e-6).all())
        else:
            assert float(moved[1:].max()) < 1e-6
        torch.testing.assert_close(f5[:5], base[:5])


@pytest.mark.parametrize("kw", [{"vertex_state": 8}, {"autoregressive": True}])
def test_a_state_carried_between_calls_equals_one_call(scene, kw):  # noqa: F811
    """The oracle: the whole chunk in one call; frames 0-2 then 3-7 from the first call's
    ``state``, and ``predict_sequence`` two frames a call, give the same frames."""
    inp = scene.inputs
    model = build(scene, **kw)
    with torch.no_grad():
        whole = model(inp)
        first = model(inp.select(torch.arange(3)))
        rest = model(inp.select(torch.arange(3, T)), state=first["state"])
        fresh = model(inp.select(torch.arange(3, T)))
    torch.testing.assert_close(torch.cat([first["final"], rest["final"]]), whole["final"])
    torch.testing.assert_close(rest["state"], whole["state"])
    assert (fresh["final"] - rest["final"]).abs().max() > 1e-6  # the state matters
    seq = model.predict_sequence(inp, batch_size=2)["final"]
    torch.testing.assert_close(seq, whole["final"])


@pytest.mark.parametrize("kw", [{"vertex_state": 8}, {"autoregressive": True},
                                {"dynamic_code": True}])
def test_a_batch_with_a_state_equals_each_chunk_alone(scene, chunks, kw):  # noqa: F811
    a, b = chunks
    model = build(scene, **kw)
    batch = GarmentInputs.collate([a, b])
    with torch.no_grad():
        out = model(batch)["final"]
        alone = model(a)["final"], model(b)["final"]
    Va = a.num_vertices
    torch.testing.assert_close(out[:, :Va], alone[0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out[:, Va:], alone[1], atol=1e-5, rtol=1e-5)
    if kw.get("autoregressive"):  # teacher-forced, too
        gt = torch.cat([fake_gt(a, 1), fake_gt(b, 2)], 1)
        with torch.no_grad():
            out = model(batch, teacher=TeacherForcing(gt, 2))["final"]
            one = model(a, teacher=TeacherForcing(gt[:, :Va], 2))["final"]
        torch.testing.assert_close(out[:, :Va], one, atol=1e-5, rtol=1e-5)


# ------------------------------------------------------------------------ motion code
def test_the_motion_code_reaches_the_dynamic_stack(scene):  # noqa: F811
    """Skinning-logit gate shut: the GRU's only way to the output is the dynamic stack,
    which ``dynamic_code`` opens (the GRU then gets a gradient; without it none)."""
    inp = scene.inputs
    for on in (False, True):
        model = build(scene, dynamic_code=on)
        with torch.no_grad():
            model.gates[0] = 0.0
        model(inp)["final"].sum().backward()
        g = sum(float(p.grad.abs().sum()) for p in model.gru.parameters() if p.grad is not None)
        assert (g > 0) == on, on


# --------------------------------------------------------------------------- training
@pytest.mark.slow
def test_the_module_ramps_the_rollout_and_trains_each_state(scene):  # noqa: F811
    inp = with_keys(scene.inputs, gt=fake_gt(scene.inputs))
    module = GarTransModule(build(scene, autoregressive=True).train(), rollout=5,
                            rollout_ramp=100, rollout_noise=0.0)
    for step, k in ((0, 1), (50, 3), (100, 5), (400, 5)):
        with mock.patch.object(GarTransModule, "global_step", step):
            assert module.teacher(inp).rollout == k
    assert GarTransModule(build(scene)).teacher(inp) is None
    with pytest.raises(ValueError, match="`batch`: an autoregressive GarTrans trains from"):
        module.teacher(with_keys(inp, gt=None))
    for kw in ({"autoregressive": True}, {"vertex_state": 4}, {"dynamic_code": True}):
        module = GarTransModule(build(scene, **kw).train())
        opt = torch.optim.Adam(module.parameters(), lr=1e-3)
        before = [p.detach().clone() for p in module.model.dynamic.parameters()]
        for _ in range(2):
            with mock.patch.object(GarTransModule, "log_training_step"):
                loss = module.training_step(inp, 0)["loss"]
            assert torch.isfinite(loss)
            opt.zero_grad()
            loss.backward()
            opt.step()
        assert any(not torch.equal(p, q) for p, q in
                   zip(module.model.dynamic.parameters(), before)), kw


# ------------------------------------------------------------------------ bad arguments
def test_bad_state_arguments_name_themselves(scene):  # noqa: F811
    inp = scene.inputs
    with pytest.raises(ValueError, match="`vertex_state`: expected a latent width"):
        build(scene, vertex_state=-1)
    with pytest.raises(ValueError, match="one garment state at a time"):
        build(scene, vertex_state=4, autoregressive=True)
    with pytest.raises(ValueError, match="`rollout`: expected frames >= 1"):
        TeacherForcing(inp.skinned(), 0)
    with pytest.raises(ValueError, match="`rollout_noise`"):
        GarTransModule(build(scene), rollout_noise=-1.0)
    with pytest.raises(ValueError, match="`rollout_ramp`"):
        GarTransModule(build(scene), rollout_ramp=-2)
    with pytest.raises(ValueError, match="`state`, `teacher`: for a model with a garment"):
        build(scene)(inp, state=torch.zeros(2, inp.num_vertices, 3))
    model = build(scene, autoregressive=True)
    with pytest.raises(ValueError, match="`prev_final`: a model with a garment state"):
        model.rollout(inp)
    with pytest.raises(ValueError, match=r"`state`: expected \(2, "):
        model(inp, state=torch.zeros(inp.num_vertices, 3))
    with pytest.raises(ValueError, match="`teacher.gt`"):
        model(inp, teacher=TeacherForcing(inp.skinned()[:2], 1))
    with pytest.raises(ValueError, match="`teacher`: a recurrent latent"):
        build(scene, vertex_state=2)(inp, teacher=TeacherForcing(inp.skinned(), 1))
