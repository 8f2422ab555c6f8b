"""Skinning weights for a garment, transferred from the body it is dressed on."""
from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.utils import scatter

from garmentgnn.geometry.mesh import faces_to_edge_index


def transfer_skinning_weights(garment_vertices: Tensor, garment_faces: Tensor,
                              body_vertices: Tensor, body_weights: Tensor, k: int = 4,
                              smooth_iters: int = 10, chunk: int = 4096) -> Tensor:
    """Garment LBS weights ``[V_g, S]`` from the body's: an inverse-distance blend of the
    ``k`` nearest body vertices, then ``smooth_iters`` steps of averaging over the
    garment's mesh neighbours (so a skirt between the legs does not tear along the
    line where the nearest leg switches).  Rows sum to 1.

    This is the usual initialisation for garment skinning; GarTrans learns its
    skinning weights ``W^t`` on top of such a template (Eqs. 1-2).
    """
    if garment_vertices.dim() != 2 or garment_vertices.shape[1] != 3:
        raise ValueError(f"`garment_vertices`: expected [V, 3], got "
                         f"{tuple(garment_vertices.shape)}")
    if body_weights.shape[0] != body_vertices.shape[0]:
        raise ValueError("`body_weights`: one row per body vertex expected")
    k = min(k, body_vertices.shape[0])
    bv = body_vertices.to(garment_vertices.dtype)
    rows = []
    for start in range(0, garment_vertices.shape[0], chunk):
        d = torch.cdist(garment_vertices[start:start + chunk], bv)  # [c, Vb]
        dist, idx = d.topk(k, dim=1, largest=False)
        w = 1.0 / dist.clamp_min(1e-6)
        w = w / w.sum(1, keepdim=True)
        rows.append((body_weights.to(w.dtype)[idx] * w.unsqueeze(-1)).sum(1))
    W = torch.cat(rows)
    if smooth_iters > 0 and garment_faces.numel():
        ei = faces_to_edge_index(garment_faces, garment_vertices.shape[0])
        for _ in range(smooth_iters):
            avg = scatter(W[ei[0]], ei[1], dim=0, dim_size=W.shape[0], reduce="mean")
            W = 0.5 * W + 0.5 * avg
    return W / W.sum(1, keepdim=True).clamp_min(1e-12)
