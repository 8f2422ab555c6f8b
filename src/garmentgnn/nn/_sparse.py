"""CSR sparse kernels for dot-product graph attention, with their own backward.

With the edges in CSR order (sorted by target, then source; the layers sort
internally, see :class:`garmentgnn.nn._graph.CSRPlan`), the per-edge work of
attention maps onto two sparse kernels:

* SDDMM: the scores ``s_ij = q_i . k_j`` sampled on the graph's pattern;
* SpMM:  the aggregation ``out_i = sum_j alpha_ij v_j``.

All heads run in one call on a ``[N_dst*H, N_src*H]`` pattern (row ``i*H + h``,
column ``j*H + h``: node-major, so a layer's ``[N, H, C]`` rows are the dense operands
without a transpose), so no ``[E, H, C]`` tensor is materialised in the forward *or*
the backward pass.  PyTorch's own autograd for sparse CSR inputs is very slow on CPU (it
densifies or re-sorts), so both kernels are :class:`torch.autograd.Function`
whose gradients are again SDDMM/SpMM on the pattern or its transpose:

* SDDMM ``s = (A B^T)|_P``: ``dA = G B``, ``dB = G^T A`` (G: ``ds`` on P);
* SpMM ``Y = P(v) B``: ``dv = (dY B^T)|_P``, ``dB = P(v)^T dY``.

The backward calls the same functions, so gradients of any order work (double
backward, e.g. for gradient penalties).  Patterns and their transposes are
built once per graph and head count and cached on the graph's plan.

PyTorch warns once per process that its sparse CSR support is in beta; that
warning is silenced only around the calls here (no process-wide filter).
"""
from __future__ import annotations

import contextlib
import warnings
import weakref
from typing import Iterator, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor
from torch_geometric.index import index2ptr

from garmentgnn.nn._graph import CSRPlan

_ENABLED = True

#: dtypes PyTorch's sparse CSR kernels support on every device (no CPU half kernels);
#: :func:`sddmm` and :func:`spmm` run other operands in float32
CSR_DTYPES = (torch.float32, torch.float64)


@contextlib.contextmanager
def csr_kernels(enabled: bool) -> Iterator[None]:
    """Switch the sparse-kernel path on or off (for benchmarks and tests)::

        with csr_kernels(False):
            out = conv(x, edge_index, edge_attr)   # gather + propagate (message path)
    """
    global _ENABLED
    before, _ENABLED = _ENABLED, enabled
    try:
        yield
    finally:
        _ENABLED = before


def kernels_enabled() -> bool:
    return _ENABLED


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly")
        yield


class Pattern:
    """A fixed CSR sparsity pattern of shape ``[R, C]``; values come in pattern order.

    ``T`` is the transposed pattern; ``to_t`` maps values into its order
    (``values_T = values[to_t]``).
    """

    def __init__(self, ptr: Tensor, col: Tensor, shape: Tuple[int, int],
                 transpose: Optional[Tuple[Tensor, Tensor, Tensor]] = None) -> None:
        self.ptr, self.col, self.shape = ptr, col, shape
        self._transpose_parts = transpose  # (ptr_t, col_t, to_t), built on demand otherwise
        self._t: Optional[Pattern] = None
        self._to_t: Optional[Tensor] = None
        # a transpose refers back to the pattern it was built from weakly: a pair of
        # strong references is a cycle, whose index tensors only a full garbage
        # collection frees (RSS grew by about 20 MB a training step on `medium`)
        self._parent: Optional["weakref.ReferenceType[Pattern]"] = None
        self.rows: Optional[Tensor] = None  # row of every entry (head patterns set it)
        #: head patterns: gathers between per-edge ``[E, H]`` values in the caller's
        #: order (flattened) and the values' order (``None``: the same order)
        self.from_caller: Optional[Tensor] = None
        self.to_caller: Optional[Tensor] = None
        self._indices32: Optional[Tuple[Tensor, Tensor]] = None

    def matrix(self, values: Tensor) -> Tensor:
        ptr, col = self.kernel_indices()
        with _quiet():
            return torch.sparse_csr_tensor(ptr, col, values, self.shape, check_invariants=False)

    def kernel_indices(self) -> Tuple[Tensor, Tensor]:
        """``(ptr, col)`` as int32 where the entries fit (kept): MKL's CSR kernels take
        int32 indices and convert int64 ones on every call."""
        if self._indices32 is None:
            fits = self.col.numel() < 2 ** 31 and max(self.shape) < 2 ** 31
            self._indices32 = ((self.ptr.int(), self.col.int()) if fits
                               else (self.ptr, self.col))
        return self._indices32

    def mm(self, values: Tensor, dense: Tensor, out: Optional[Tensor] = None) -> Tensor:
        """``pattern(values) @ dense``, ``[R, C]``, written into ``out`` (a fresh tensor by
        default; its contents are ignored).  ``addmm`` with ``beta=0`` into an
        uninitialised output: ``torch.sparse.mm`` zero-fills its output, computes into
        another and copies it over (0.54 against 0.91-1.02 ms at 52,224 rows x 298,112
        entries x 16 channels, one thread)."""
        if out is None:
            out = dense.new_empty(self.shape[0], dense.size(1))
        with _quiet():
            return torch.addmm(out, self.matrix(values), dense, beta=0.0, out=out)

    def _build_transpose(self) -> Tuple[Tensor, Tensor, Tensor]:
        rows = torch.repeat_interleave(torch.arange(self.shape[0], device=self.col.device),
                                       self.ptr.diff())
        to_t = torch.argsort(self.col * self.shape[0] + rows, stable=True)
        ptr_t = index2ptr(self.col[to_t], self.shape[1])
        return ptr_t, rows[to_t], to_t

    @property
    def to_t(self) -> Tensor:
        self.T  # noqa: B018 (builds the transpose)
        assert self._to_t is not None
        return self._to_t

    @property
    @torch.inference_mode(False)
    def T(self) -> "Pattern":
        if self._t is not None:
            return self._t
        parent = self._parent() if self._parent is not None else None
        if parent is not None:
            return parent
        ptr_t, col_t, to_t = self._transpose_parts or self._build_transpose()
        t = Pattern(ptr_t, col_t, (self.shape[1], self.shape[0]))
        back = torch.empty_like(to_t)
        back[to_t] = torch.arange(to_t.numel(), device=to_t.device)
        t._parent, t._to_t = weakref.ref(self), back
        self._t, self._to_t = t, to_t
        return t

    def sample(self, a: Tensor, b: Tensor) -> Tensor:
        """``(a b^T)`` on the pattern, as a flat value vector.

        Widths that are not a multiple of 8 are zero-padded to one first: PyTorch's
        CPU ``sampled_addmm`` is several times slower on them (3 channels take ~4x
        the time of 8), and zero columns add nothing to the dot products."""
        pad = -a.size(1) % 8
        if pad and a.device.type == "cpu":
            a, b = F.pad(a, (0, pad)), F.pad(b, (0, pad))
        with _quiet():  # beta=0 must not meet garbage: zero values
            pattern = torch.sparse_csr_tensor(self.ptr, self.col, a.new_zeros(self.col.numel()),
                                              self.shape, check_invariants=False)
            return torch.sparse.sampled_addmm(pattern, a, b.t(), beta=0.0).values()


def _working_order(plan: CSRPlan, heads: int) -> Tuple[Tensor, Tensor]:
    """Where each (CSR edge ``k``, head ``h``) lives in the node-major working layout:
    ``w [E, H]``, with the block pointer ``ptr [H*N_dst + 1]`` of rows ``(i, h)``.  Row
    ``i*H + h`` holds target ``i``'s incoming edges (CSR order) for head ``h``:
    ``w[k, h] = H*ptr[i] + h*deg(i) + (k - ptr[i])``."""
    H, dev = heads, plan.src.device
    h = torch.arange(H, device=dev)
    start = plan.ptr[:-1].unsqueeze(1) * H + h.unsqueeze(0) * plan.ptr.diff().unsqueeze(1)
    ptr = torch.cat([start.reshape(-1), plan.ptr.new_full((1,), H * plan.num_edges)])
    k_in_row = torch.arange(plan.num_edges, device=dev) - plan.ptr[plan.dst]
    return start[plan.dst] + k_in_row.unsqueeze(1), ptr  # w [E, H], ptr


def _scatter_to(w: Tensor, values: Tensor) -> Tensor:
    """``out[w] = values`` for ``w``, ``values`` of one shape (a permutation)."""
    out = torch.empty(w.numel(), dtype=values.dtype, device=values.device)
    out[w.reshape(-1)] = values.reshape(-1)
    return out


@torch.inference_mode(False)  # cached patterns serve autograd calls too
def head_pattern(plan: CSRPlan, heads: int) -> Pattern:
    """Block ``[N_dst*H, N_src*H]``: the graph's pattern once per head, node-major.

    Row ``i*H + h`` holds target ``i``'s incoming edges for head ``h`` at columns
    ``j*H + h``, so node rows ``[N, H, C]`` (contiguous) are the kernels' dense operands
    as they are (``.view(N*H, C)``), with no transpose.  Values are in the working
    order of :func:`_working_order`; ``from_caller`` / ``to_caller`` gather ``[E, H]``
    per-edge values (caller's edge order, flattened) into that order and back."""
    key = ("head", heads)
    if key not in plan.patterns:
        H = heads
        w, ptr = _working_order(plan, H)
        h = torch.arange(H, device=w.device).unsqueeze(0)
        pat = Pattern(ptr, _scatter_to(w, plan.src.unsqueeze(1) * H + h),
                      (H * plan.num_dst, H * plan.num_src))
        pat.rows = _scatter_to(w, plan.dst.unsqueeze(1) * H + h)  # row of every entry
        if plan.perm is None and H == 1:
            pat.from_caller = pat.to_caller = None  # the working order is the caller's
        else:
            pat.from_caller = _scatter_to(w, plan.caller_ids.unsqueeze(1) * H + h)
            pat.to_caller = torch.empty_like(pat.from_caller)
            pat.to_caller[pat.from_caller] = torch.arange(pat.from_caller.numel(),
                                                          device=w.device)
        plan.patterns[key] = pat
    return plan.patterns[key]


@torch.inference_mode(False)
def incidence_pattern(plan: CSRPlan, heads: int) -> Pattern:
    """Per-head target-by-edge incidence ``[N_dst*H, E]``; row ``i*H + h`` holds the
    incoming edges of ``i`` as columns in the *caller's* edge order, so ``A @ Y`` sums
    the caller's edge rows ``Y [E, D]`` into ``[N_dst, H, D]`` without permuting ``Y``.
    Values in the working order of :func:`head_pattern` (the same entries, row by row)."""
    key = ("incidence", heads)
    if key not in plan.patterns:
        H, E, nd = heads, plan.num_edges, plan.num_dst
        head = head_pattern(plan, H)  # the same entries; its gathers give the columns
        dev = head.col.device
        ids = torch.arange(H * E, device=dev)
        col = (ids if head.from_caller is None else head.from_caller) // H  # caller's edge
        # transpose [E, N_dst*H]: caller edge e holds its H entries (dst[e]*H + h)
        ptr_t = torch.arange(0, H * E + 1, H, device=dev)
        col_t = (plan.to_caller(plan.dst).unsqueeze(1) * H
                 + torch.arange(H, device=dev).unsqueeze(0)).reshape(-1)
        to_t = ids if head.to_caller is None else head.to_caller
        plan.patterns[key] = Pattern(head.ptr, col, (H * nd, E), (ptr_t, col_t, to_t))
    return plan.patterns[key]


class _SDDMM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, pat: Pattern) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(a, b)
        ctx.pat = pat
        return pat.sample(a, b)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        a, b = ctx.saved_tensors
        pat: Pattern = ctx.pat
        grad = grad.contiguous()
        ga = spmm(grad, b, pat) if ctx.needs_input_grad[0] else None
        gb = spmm(grad[pat.to_t], a, pat.T) if ctx.needs_input_grad[1] else None
        return ga, gb, None


class _SpMM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values: Tensor, dense: Tensor, pat: Pattern) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(values, dense)
        ctx.pat = pat
        return pat.mm(values, dense)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        values, dense = ctx.saved_tensors
        pat: Pattern = ctx.pat
        grad = grad.contiguous()
        gv = sddmm(grad, dense, pat) if ctx.needs_input_grad[0] else None
        gd = spmm(values[pat.to_t], grad, pat.T) if ctx.needs_input_grad[1] else None
        return gv, gd, None


def _operand(t: Tensor) -> Tensor:
    """``t`` contiguous, in float32 if its dtype has no CSR kernel (half precision)."""
    return (t if t.dtype in CSR_DTYPES else t.float()).contiguous()


def sddmm(a: Tensor, b: Tensor, pat: Pattern) -> Tensor:
    """``(a @ b^T)`` sampled on ``pat``: a value vector in pattern order (differentiable;
    half-precision operands run in float32 and give float32)."""
    return _SDDMM.apply(_operand(a), _operand(b), pat)


def spmm(values: Tensor, dense: Tensor, pat: Pattern) -> Tensor:
    """``pat(values) @ dense`` (differentiable in both, to any order; half-precision
    operands run in float32 and give float32)."""
    return _SpMM.apply(_operand(values), _operand(dense), pat)
