"""GarTrans batched whole-sequence inference (``predict_sequence``): the same numbers as
predicting each frame's pose history alone, whatever the chunk size; bad arguments."""
import copy
from types import SimpleNamespace

import pytest
import torch

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments import make_garment
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.models import GarTrans
from garmentgnn.models.blocks import batch_edges, cached_batch_edges
from garmentgnn.models.inputs import (GarmentInputs, build_static, check_history,
                                      history_frames, with_frames)
from garmentgnn.motion import make_motion

T, HISTORY = 7, 2
OUTPUTS = ("final", "coarse", "accel", "weights")


@pytest.fixture(scope="module")
def scene():
    body = CapsuleBodyModel(resolution=6)("regular")
    g = make_garment("skirt", body, resolution=200)
    w = transfer_skinning_weights(g.vertices.float(), g.faces, body.vertices.float(),
                                  body.weights.float())
    garment = build_static(g.vertices, g.faces, body, w, nystrom_dim=8, num_landmarks=32)
    m = make_motion("walk", body.skeleton, num_frames=T, rest_joints=body.joints)
    rots, tr = m.rotations.float(), m.translation.float()
    seq = with_frames(garment, body, rots, tr, torch.arange(T), HISTORY)  # the whole motion
    torch.manual_seed(0)
    model = GarTrans.paper(body.skeleton.num_joints, body.vertices.shape[0],
                           nystrom_dim=garment.nystrom.shape[1]).eval()
    with torch.no_grad():
        static = model.encode_static(seq)
    return SimpleNamespace(model=model, body=body, garment=garment, seq=seq, static=static,
                           rots=rots, tr=tr)


@pytest.fixture(scope="module")
def reference(scene):
    """The oracle: plain ``forward`` on each frame alone (B = 1), its pose history built by
    hand from the raw motion, its static branch computed afresh."""
    outs = []
    with torch.no_grad():
        for t in range(T):
            idx = [max(0, t - k) for k in range(HISTORY, -1, -1)]  # t-history .. t, clamped
            one = copy.copy(scene.seq.select(torch.tensor([t])))
            one.rotations = scene.rots[idx].unsqueeze(0)
            one.translation = scene.tr[idx].unsqueeze(0)
            outs.append(scene.model(one))
    return {k: torch.cat([o[k] for o in outs]) for k in outs[0]}


@pytest.mark.parametrize("batch_size", [1, 3, T, 64, None])  # 3 does not divide T = 7
def test_batched_sequence_equals_per_frame_prediction(scene, reference, batch_size):
    ref = reference
    out = scene.model.predict_sequence(scene.seq, batch_size=batch_size, outputs=OUTPUTS,
                                       static=scene.static)
    assert out["final"].shape == ref["final"].shape == (T, scene.seq.num_vertices, 3)
    for k in OUTPUTS:
        torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5, msg=k)
    # the frames really differ (a constant output would pass trivially)
    assert (ref["final"][1:] - ref["final"][:-1]).abs().max() > 1e-4
    if batch_size == 3:  # its own static branch (no cached one): the same numbers
        own = scene.model.predict_sequence(scene.seq, batch_size=batch_size)
        assert set(own) == {"final"}
        torch.testing.assert_close(own["final"], ref["final"], atol=1e-5, rtol=1e-5)


def test_first_frame_code_does_not_depend_on_its_batch(scene):
    """Frame 0's history is one pose repeated (no motion): Θ = 1 for it alone and inside a
    batch of moving frames."""
    model, rots, tr = scene.model, scene.rots, scene.tr
    hist = torch.tensor([[0, 0, 0], [2, 3, 4]])
    with torch.no_grad():
        both = model.motion_code(rots[hist], tr[hist])
        one = model.motion_code(rots[hist[1:]], tr[hist[1:]])
    torch.testing.assert_close(both[0], torch.ones_like(both[0]))
    torch.testing.assert_close(both[1], one[0])
    assert not torch.allclose(one[0], torch.ones_like(one[0]))


def test_cached_batched_graph_is_reused_and_correct():
    ei = torch.tensor([[1, 2, 0], [0, 1, 2]])
    a = cached_batch_edges(ei, 3, 3)
    assert cached_batch_edges(ei, 3, 3) is a
    torch.testing.assert_close(a, batch_edges(ei, 3, 3))
    torch.testing.assert_close(a[:, 3:6], ei + 3)
    ei.add_(0)  # an in-place change (version bump) invalidates the entry
    assert cached_batch_edges(ei, 3, 3) is not a
    assert cached_batch_edges(ei, 1, 3) is ei


def _frames(scene, **kw):
    """``with_frames`` of the whole motion, ``kw`` replacing its arguments."""
    call = dict(rotations=scene.rots, translation=scene.tr, frames=torch.arange(T),
                history=HISTORY)
    call.update(kw)
    return with_frames(scene.garment, scene.body, **call)


def _predict(scene, inputs=None, **kw):
    return scene.model.predict_sequence(scene.seq if inputs is None else inputs, **kw)


def _with_body_pos(scene, body_pos):
    out = copy.copy(scene.seq)
    out.body_pos = body_pos
    return out


# each case: what is called with the bad argument, and the argument its error names; the
# motion and history go to the inputs' builder, ``with_frames``, the rest to predict_sequence
BAD = [
    pytest.param(lambda s: _frames(s, rotations=torch.zeros(5, 3), frames=torch.arange(5)),
                 "rotations", id="rotations-shape"),
    pytest.param(lambda s: _predict(s, _frames(s, rotations=s.rots[:0], translation=s.tr[:0],
                                               frames=torch.arange(0))),
                 "inputs", id="no-frames"),
    pytest.param(lambda s: _frames(s, translation=torch.zeros(4, 3)), "translation",
                 id="translation-length"),
    pytest.param(lambda s: _frames(s, history=0), "history", id="history-0"),
    pytest.param(lambda s: _frames(s, history=1.5), "history", id="history-float"),
    pytest.param(lambda s: _predict(s, batch_size=0), "batch_size", id="batch_size-0"),
    pytest.param(lambda s: _predict(s, batch_size=True), "batch_size", id="batch_size-bool"),
    pytest.param(lambda s: _predict(s, outputs=("final", "nope")), "outputs",
                 id="outputs-unknown"),
    pytest.param(lambda s: _predict(s, outputs="final"), "outputs", id="outputs-str"),
    pytest.param(lambda s: _predict(s, GarmentInputs.collate([s.seq, s.seq])), "inputs",
                 id="inputs-batch"),
    pytest.param(lambda s: _predict(s, _with_body_pos(s, torch.zeros(3, 10, 3))),
                 "inputs.body_pos", id="body_pos-frames"),
]


@pytest.mark.parametrize("call, arg", BAD)
def test_bad_arguments_name_the_argument(scene, call, arg):
    with pytest.raises(ValueError, match=f"`{arg}`"):
        call(scene)


def test_history_frames_are_the_clamped_window_before_each_frame():
    frames = torch.tensor([0, 1, 5])
    expected = [[max(0, t - k) for k in range(HISTORY, -1, -1)] for t in frames.tolist()]
    assert history_frames(frames, HISTORY).tolist() == expected


@pytest.mark.parametrize("history", [0, -1, 1.0, True, "2"])
def test_check_history_names_the_argument(history):
    with pytest.raises(ValueError, match="`history`"):
        check_history(history)


def test_inputs_of_another_skeleton_or_motion_length_name_the_key(scene):
    """A pose history of another joint count, a skeleton the model was not built for and
    a translation of another length are ValueErrors naming the inputs' key, not torch's
    size errors."""
    model = scene.model
    one = scene.seq.select(torch.arange(2))
    bad = copy.copy(one)
    bad.rotations = one.rotations[..., :-1, :]
    with pytest.raises(ValueError, match="`inputs.rotations`"):
        model(bad)
    bad = copy.copy(one)
    bad.translation = one.translation[:, :-1]
    with pytest.raises(ValueError, match="`inputs.translation`"):
        model(bad)
    bad = copy.copy(one)
    bad.rest_joints = one.rest_joints[:-1]
    with pytest.raises(ValueError, match="`inputs.rest_joints`"):
        model(bad)
