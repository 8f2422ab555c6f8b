"""Row gathers and scatter-sums along the vertex axis of batched ``[..., V, C]`` tensors.

PyTorch's CPU kernels for indexing a middle dimension (``pos[..., idx, :]``,
``index_add`` along dim -2) move one ``C``-float row per index and batch entry.  On the
vertex-major copy ``[V, ... * C]`` an index moves one contiguous row holding every batch
entry.  Gathering the 9,816 face corners of 8 frames of a 4,916-vertex body
(``[8, 4916, 3]``, one thread): 0.03 ms against 0.73 for ``pos[:, idx]`` and 0.21 for
``index_select(1, idx)``; summing 29,448 corner values onto the vertices: 0.41 ms against
5.2 for ``index_add`` along dim 1.  The backward passes are the same kernels the other
way round.  Unbatched ``[V, C]`` inputs take ``index_select`` / ``index_add`` directly.
"""
from __future__ import annotations

from torch import Tensor


def gather_rows(x: Tensor, index: Tensor) -> Tensor:
    """``x[..., index, :]`` for ``x [..., V, C]`` and integer ``index`` of any shape with
    values in ``[0, V)``: ``[..., *index.shape, C]``, for a batched ``x`` a strided view
    of the vertex-major gather (element-wise operations on it are as fast as on a
    contiguous tensor; a transposing copy would cost more than the gather).  No
    validation."""
    idx = index.reshape(-1)
    if x.dim() <= 2:
        return x.index_select(0, idx).view(*index.shape, x.size(-1))
    lead, (V, C), k = x.shape[:-2], x.shape[-2:], index.dim()
    rows = x.movedim(-2, 0).reshape(V, -1).index_select(0, idx)  # [M, lead * C]
    out = rows.view(*index.shape, *lead, C)
    return out.movedim(tuple(range(k)), tuple(range(len(lead), len(lead) + k)))


def scatter_rows(src: Tensor, index: Tensor, num_rows: int) -> Tensor:
    """Sum ``src [..., *index.shape, C]`` onto ``num_rows`` rows by ``index`` (values in
    ``[0, num_rows)``): ``out[..., index[i], :] += src[..., i, :]``, ``[..., num_rows,
    C]`` (for a batched ``src`` a strided view, as :func:`gather_rows`).  No
    validation."""
    idx, k = index.reshape(-1), index.dim()
    lead, C = src.shape[:src.dim() - k - 1], src.size(-1)
    if not lead:
        return src.new_zeros(num_rows, C).index_add(0, idx, src.reshape(-1, C))
    n = len(lead)
    flat = src.movedim(tuple(range(n, n + k)), tuple(range(k))).reshape(idx.numel(), -1)
    out = src.new_zeros(num_rows, flat.size(1)).index_add(0, idx, flat)
    return out.view(num_rows, *lead, C).movedim(0, -2)
