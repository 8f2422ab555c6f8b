"""GarTrans batched whole-sequence inference (``predict_sequence``): the same numbers as
predicting each frame's pose history alone, whatever the chunk size; bad arguments."""
import pytest
import torch

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments import make_garment
from garmentgnn.geometry import faces_to_edge_index, geodesic_nystrom_features
from garmentgnn.models import PAPER_FORM, GarTrans
from garmentgnn.models.blocks import batch_edges, cached_batch_edges
from garmentgnn.models.inputs import check_history, history_frames
from garmentgnn.motion import make_motion

T, HISTORY = 7, 2


@pytest.fixture(scope="module")
def scene():
    body = CapsuleBodyModel(resolution=6)("regular")
    g = make_garment("skirt", body, resolution=200)
    ei = faces_to_edge_index(g.faces, g.vertices.shape[0])
    ny = geodesic_nystrom_features(g.vertices, g.faces, k=8, num_landmarks=32).float()
    bd = torch.cdist(body.vertices, body.joints)
    m = make_motion("walk", body.skeleton, num_frames=T, rest_joints=body.joints)
    torch.manual_seed(0)
    model = GarTrans(body.skeleton.num_joints, body.vertices.shape[0],
                     nystrom_dim=ny.shape[1], **PAPER_FORM).eval()
    with torch.no_grad():
        static = model.encode_static(g.vertices, g.faces, ei, body.joints, ny, bd)
    args = (static, g.vertices, g.faces, ei, body.joints, body.skeleton.parents)
    return model, args, m.rotations.float(), m.translation.float()


def per_frame(model, args, rots, tr):
    """The oracle: plain ``forward`` on each frame's history alone (B = 1), built by hand."""
    outs = []
    with torch.no_grad():
        for t in range(rots.shape[0]):
            idx = [max(0, t - k) for k in range(HISTORY, -1, -1)]  # t-history .. t, clamped
            outs.append(model(*args, rots[idx].unsqueeze(0), tr[idx].unsqueeze(0)))
    return {k: torch.cat([o[k] for o in outs]) for k in outs[0]}


@pytest.mark.parametrize("batch_size", [1, 3, T, 64, None])  # 3 does not divide T = 7
def test_batched_sequence_equals_per_frame_prediction(scene, batch_size):
    model, args, rots, tr = scene
    ref = per_frame(model, args, rots, tr)
    out = model.predict_sequence(*args, rots, tr, history=HISTORY, batch_size=batch_size,
                                 outputs=("final", "coarse", "accel", "weights"))
    assert out["final"].shape == ref["final"].shape == (T, args[1].shape[0], 3)
    for k in ("final", "coarse", "accel", "weights"):
        torch.testing.assert_close(out[k], ref[k], atol=1e-5, rtol=1e-5, msg=k)
    # the frames really differ (a constant output would pass trivially)
    assert (ref["final"][1:] - ref["final"][:-1]).abs().max() > 1e-4


def test_first_frame_code_does_not_depend_on_its_batch(scene):
    """Frame 0's history is one pose repeated (no motion): Θ = 1 for it alone and inside a
    batch of moving frames."""
    model, args, rots, tr = scene
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


@pytest.mark.parametrize("kw, arg", [
    (dict(rotations=torch.zeros(5, 3)), "rotations"),
    (dict(rotations="no frames"), "rotations"),
    (dict(translation=torch.zeros(4, 3)), "translation"),
    (dict(history=0), "history"),
    (dict(history=1.5), "history"),
    (dict(batch_size=0), "batch_size"),
    (dict(batch_size=True), "batch_size"),
    (dict(outputs=("final", "nope")), "outputs"),
    (dict(outputs="final"), "outputs"),
    (dict(body_pos=torch.zeros(3, 10, 3)), "body_pos"),
])
def test_bad_arguments_name_the_argument(scene, kw, arg):
    model, args, rots, tr = scene
    call = dict(rotations=rots, translation=tr)
    call.update(kw)
    if isinstance(kw.get("rotations"), str):
        call["rotations"] = rots[:0]
    with pytest.raises(ValueError, match=f"`{arg}`"):
        model.predict_sequence(*args, **call)


def test_history_frames_are_the_clamped_window_before_each_frame():
    frames = torch.tensor([0, 1, 5])
    expected = [[max(0, t - k) for k in range(HISTORY, -1, -1)] for t in frames.tolist()]
    assert history_frames(frames, HISTORY).tolist() == expected


@pytest.mark.parametrize("history", [0, -1, 1.0, True, "2"])
def test_check_history_names_the_argument(history):
    with pytest.raises(ValueError, match="`history`"):
        check_history(history)
