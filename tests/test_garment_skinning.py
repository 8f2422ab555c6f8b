import pytest
import torch

from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments.skinning import transfer_skinning_weights


def test_transfer_copies_coincident_vertices_and_normalises():
    body = CapsuleBodyModel()("regular")
    idx = torch.tensor([0, 100, 1500])
    pts = body.vertices[idx]
    faces = torch.tensor([[0, 1, 2]])
    W = transfer_skinning_weights(pts, faces, body.vertices, body.weights, k=1, smooth_iters=0)
    torch.testing.assert_close(W, body.weights[idx])
    W = transfer_skinning_weights(pts + 0.01, faces, body.vertices, body.weights)
    torch.testing.assert_close(W.sum(1), torch.ones(3))
    assert (W >= 0).all()


def test_transfer_rejects_bad_shapes():
    body = CapsuleBodyModel()("regular")
    with pytest.raises(ValueError, match="garment_vertices"):
        transfer_skinning_weights(torch.zeros(3, 2), torch.zeros(0, 3, dtype=torch.long),
                                  body.vertices, body.weights)
