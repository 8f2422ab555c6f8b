"""GarTrans's recurrent vertex latent (``vertex_state``, ``models/state.py``) against
oracles: causality, a state carried from call to call equal to one call, a batch equal
to each chunk alone, training moves the stack; bad arguments."""
from unittest import mock

import pytest
import torch

from garmentgnn.models import GarTrans
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training import GarTransModule
from test_model import T, chunks, scene, with_keys  # noqa: F401  (module-scoped fixtures)


def build(sc, **kw):
    """The project's form with ``kw`` for scene ``sc``, seeded; no post-steps unless
    ``kw`` asks."""
    torch.manual_seed(0)
    kw = {"strain_limit": 0, "collision_projection": None, **kw}
    return GarTrans(sc.body.skeleton.num_joints, sc.body.vertices.shape[0],
                    nystrom_dim=sc.inputs.nystrom.shape[1], **kw).eval()


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


def test_a_state_carried_between_calls_equals_one_call(scene):  # noqa: F811
    """The oracle: the whole chunk in one call; frames 0-2 then 3-7 from the first call's
    ``state``, and ``predict_sequence`` two frames a call, give the same frames."""
    inp = scene.inputs
    model = build(scene, vertex_state=8)
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


def test_a_batch_with_a_state_equals_each_chunk_alone(scene, chunks):  # noqa: F811
    a, b = chunks
    model = build(scene, vertex_state=8)
    with torch.no_grad():
        out = model(GarmentInputs.collate([a, b]))["final"]
        alone = model(a)["final"], model(b)["final"]
    Va = a.num_vertices
    torch.testing.assert_close(out[:, :Va], alone[0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out[:, Va:], alone[1], atol=1e-5, rtol=1e-5)


def test_the_module_trains_the_recurrent_stack(scene):  # noqa: F811
    g = torch.Generator().manual_seed(1)
    inp = scene.inputs
    inp = with_keys(inp, gt=inp.skinned() + 0.01 * torch.randn(inp.skinned().shape,
                                                                 generator=g))
    module = GarTransModule(build(scene, vertex_state=4).train())
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
               zip(module.model.dynamic.parameters(), before))


def test_bad_state_arguments_name_themselves(scene):  # noqa: F811
    inp = scene.inputs
    with pytest.raises(ValueError, match="`vertex_state`: expected a latent width"):
        build(scene, vertex_state=-1)
    with pytest.raises(ValueError, match="`state`: for a model with a `vertex_state`"):
        build(scene)(inp, state=torch.zeros(inp.num_vertices, 4))
    model = build(scene, vertex_state=4)
    with pytest.raises(ValueError, match="`prev_final`: a model with a `vertex_state`"):
        model.rollout(inp)
    with pytest.raises(ValueError, match=r"`state`: expected \(\d+, 4\)"):
        model(inp, state=torch.zeros(inp.num_vertices, 3))
