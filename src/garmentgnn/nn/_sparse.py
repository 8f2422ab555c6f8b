"""CSR sparse kernels for dot-product graph attention, with their own backward.

With the edges in CSR order (sorted by target, then source, no duplicates),
the per-edge work of attention maps onto two sparse kernels:

* SDDMM: the scores ``s_ij = q_i . k_j`` sampled on the graph's pattern;
* SpMM:  the aggregation ``out_i = sum_j alpha_ij v_j``.

All heads run in one call on a block-diagonal ``[H*N_dst, H*N_src]`` pattern,
so no ``[E, H, C]`` tensor is materialised in the forward *or* the backward
pass.  PyTorch's own autograd for sparse CSR inputs is very slow on CPU (it
densifies or re-sorts), so both kernels are :class:`torch.autograd.Function`
with explicit gradients, which are again SDDMM/SpMM:

* ``d s / d q = G k`` and ``d s / d k = G^T q`` (G: the score gradient on the pattern);
* ``d out / d alpha = (dOut . v)`` sampled on the pattern, ``d out / d v = A^T dOut``.

The transposed pattern is built once per graph and call (one ``argsort``).
First-order gradients only (``once_differentiable``); under ``torch.compile``
layers fall back to gather/scatter.
"""
from __future__ import annotations

import contextlib
import warnings
from typing import Iterator, Tuple

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable
from torch_geometric import is_compiling
from torch_geometric.index import index2ptr

from garmentgnn.nn._graph import Graph

warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")


_ENABLED = True


@contextlib.contextmanager
def csr_kernels(enabled: bool) -> Iterator[None]:
    """Switch the sparse-kernel path on or off (for benchmarks and tests)::

        with csr_kernels(False):
            out = conv(x, edge_index, edge_attr)   # gather + segment reductions
    """
    global _ENABLED
    before, _ENABLED = _ENABLED, enabled
    try:
        yield
    finally:
        _ENABLED = before


#: dtypes PyTorch's sparse CSR kernels support on every device (no CPU half kernels)
CSR_DTYPES = (torch.float32, torch.float64)


def use_csr_kernels(g: Graph, *operands: Tensor) -> bool:
    """True when the sparse-kernel path applies: CSR-ordered edges, eager mode, enabled,
    and every operand in :data:`CSR_DTYPES` (bfloat16/float16 inputs, e.g. under
    ``torch.autocast``, take the gather/scatter path)."""
    return (_ENABLED and g.csr and g.ptr is not None and not is_compiling()
            and all(t.dtype in CSR_DTYPES for t in operands))


class HeadPattern:
    """The graph's CSR pattern repeated once per head (block diagonal), and its transpose."""

    def __init__(self, g: Graph, heads: int) -> None:
        assert g.ptr is not None
        self.heads, self.num_src, self.num_dst = heads, g.num_src, g.num_dst
        self.E = E = g.edge_index.size(1)
        src, dst = g.edge_index[0], g.edge_index[1]
        off = torch.arange(heads, device=src.device).unsqueeze(1)
        self.ptr = torch.cat([(g.ptr[:-1].unsqueeze(0) + off * E).reshape(-1),
                              g.ptr.new_full((1,), heads * E)])
        self.col = (src.unsqueeze(0) + off * g.num_src).reshape(-1)
        self.shape = (heads * g.num_dst, heads * g.num_src)
        self._src, self._dst, self._off = src, dst, off
        self._t: Tuple[Tensor, Tensor, Tensor] | None = None

    def matrix(self, values: Tensor) -> Tensor:
        return torch.sparse_csr_tensor(self.ptr, self.col, values, self.shape,
                                       check_invariants=False)

    def transposed(self, values: Tensor) -> Tensor:
        """The transposed matrix ``[H*N_src, H*N_dst]`` holding ``values`` (pattern order)."""
        if self._t is None:
            perm = torch.argsort(self._src * self.num_dst + self._dst)
            ptr = index2ptr(self._src[perm], self.num_src)
            ptr_h = torch.cat([(ptr[:-1].unsqueeze(0) + self._off * self.E).reshape(-1),
                               ptr.new_full((1,), self.heads * self.E)])
            col_h = (self._dst[perm].unsqueeze(0) + self._off * self.num_dst).reshape(-1)
            perm_h = (perm.unsqueeze(0) + self._off * self.E).reshape(-1)
            self._t = (ptr_h, col_h, perm_h)
        ptr_h, col_h, perm_h = self._t
        return torch.sparse_csr_tensor(ptr_h, col_h, values[perm_h],
                                       (self.shape[1], self.shape[0]), check_invariants=False)

    def sample(self, a: Tensor, b: Tensor) -> Tensor:
        """``(a b^T)`` on the pattern, as a flat value vector ``[H*E]``."""
        pattern = self.matrix(a.new_zeros(self.col.numel()))  # beta=0 must not meet garbage
        return torch.sparse.sampled_addmm(pattern, a, b.t(), beta=0.0).values()


class IncidencePattern:
    """Per-head target-by-edge incidence ``[H*N_dst, E]``: row ``(h, i)`` holds the
    incoming edges of ``i``.  ``A @ Y`` sums edge values ``Y [E, D]`` into targets."""

    def __init__(self, g: Graph, heads: int) -> None:
        assert g.ptr is not None
        self.heads, self.num_dst = heads, g.num_dst
        self.E = E = g.edge_index.size(1)
        dst = g.edge_index[1]
        off = torch.arange(heads, device=dst.device)
        self.ptr = torch.cat([(g.ptr[:-1].unsqueeze(0) + off.unsqueeze(1) * E).reshape(-1),
                              g.ptr.new_full((1,), heads * E)])
        self.col = torch.arange(E, device=dst.device).repeat(heads)
        self.shape = (heads * g.num_dst, E)
        # transpose: row e holds its H entries (h, dst[e]), values in (E, H) order
        self.ptr_t = torch.arange(0, heads * E + 1, heads, device=dst.device)
        self.col_t = (dst.unsqueeze(1) + off.unsqueeze(0) * g.num_dst).reshape(-1)

    def matrix(self, values: Tensor) -> Tensor:
        return torch.sparse_csr_tensor(self.ptr, self.col, values, self.shape,
                                       check_invariants=False)

    def transposed(self, values: Tensor) -> Tensor:
        vt = values.view(self.heads, self.E).t().reshape(-1)
        return torch.sparse_csr_tensor(self.ptr_t, self.col_t, vt, (self.E, self.shape[0]),
                                       check_invariants=False)

    def sample(self, a: Tensor, b: Tensor) -> Tensor:
        pattern = self.matrix(a.new_zeros(self.col.numel()))
        return torch.sparse.sampled_addmm(pattern, a, b.t(), beta=0.0).values()


def head_pattern(g: Graph, heads: int, incidence: bool = False):
    """The per-head (node or incidence) pattern of ``g``, built once per graph and head count."""
    build = IncidencePattern if incidence else HeadPattern
    if g.cache is None:
        return build(g, heads)
    key = (heads, incidence)
    if key not in g.cache:
        g.cache[key] = build(g, heads)
    return g.cache[key]


class _SDDMM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, qs: Tensor, ks: Tensor, pat: HeadPattern) -> Tensor:
        ctx.save_for_backward(qs, ks)
        ctx.pat = pat
        return pat.sample(qs, ks)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        qs, ks = ctx.saved_tensors
        pat: HeadPattern = ctx.pat
        grad = grad.contiguous()
        gq = torch.sparse.mm(pat.matrix(grad), ks) if ctx.needs_input_grad[0] else None
        gk = torch.sparse.mm(pat.transposed(grad), qs) if ctx.needs_input_grad[1] else None
        return gq, gk, None


class _SpMM(torch.autograd.Function):
    """``A(values) @ vs`` for a :class:`HeadPattern` or :class:`IncidencePattern`."""

    @staticmethod
    def forward(ctx, values: Tensor, vs: Tensor, pat) -> Tensor:
        ctx.save_for_backward(values, vs)
        ctx.pat = pat
        return torch.sparse.mm(pat.matrix(values), vs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        values, vs = ctx.saved_tensors
        pat = ctx.pat
        grad = grad.contiguous()
        ga = pat.sample(grad, vs) if ctx.needs_input_grad[0] else None
        gv = torch.sparse.mm(pat.transposed(values), grad) if ctx.needs_input_grad[1] else None
        return ga, gv, None


def csr_sddmm(q: Tensor, k: Tensor, g: Graph) -> Tensor:
    """``q_i . k_j`` for every edge ``j -> i`` and head: ``[E, H]`` from ``[N, H, C]``."""
    H, C = q.size(1), q.size(2)
    qs = q.transpose(0, 1).reshape(H * g.num_dst, C)
    ks = k.transpose(0, 1).reshape(H * g.num_src, C)
    return _SDDMM.apply(qs, ks, head_pattern(g, H)).view(H, -1).t()


def csr_edge_spmm(alpha: Tensor, y: Tensor, g: Graph) -> Tensor:
    """``sum_j alpha_ij y_ij`` per head for edge values ``y [E, D]``: ``[N_dst, H, D]``."""
    H = alpha.size(1)
    out = _SpMM.apply(alpha.t().reshape(-1), y, head_pattern(g, H, incidence=True))
    return out.view(H, g.num_dst, -1).transpose(0, 1)


def csr_spmm(alpha: Tensor, v: Tensor, g: Graph) -> Tensor:
    """``sum_j alpha_ij v_j`` per head: ``[N_dst, H, C]`` from ``alpha [E, H]``, ``v [N_src, H, C]``."""
    H, C = v.size(1), v.size(2)
    vs = v.transpose(0, 1).reshape(H * g.num_src, C)
    out = _SpMM.apply(alpha.t().reshape(-1), vs, head_pattern(g, H))
    return out.view(H, g.num_dst, C).transpose(0, 1)
