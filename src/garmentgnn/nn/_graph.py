"""Input handling shared by every layer in :mod:`garmentgnn.nn`.

Every layer accepts the adjacency in the forms PyG layers accept:

* a ``[2, E]`` ``LongTensor`` (or :class:`torch_geometric.EdgeIndex`) of
  ``source -> target`` pairs, in any order, with ``edge_attr`` of shape
  ``[E, edge_dim]`` in the same order;
* a transposed sparse adjacency ``adj_t`` of shape ``[N_dst, N_src]``
  (:class:`torch.sparse` COO/CSR/CSC or :class:`torch_sparse.SparseTensor`),
  where a stored entry ``adj_t[i, j]`` is the edge ``j -> i``.  Edge features
  are then either passed as ``edge_attr`` in the adjacency's row-major
  (coalesced) order, or stored as the values of a hybrid sparse tensor of
  shape ``[N_dst, N_src, edge_dim]``.  Returned edge features follow that same
  row-major order.

:func:`prepare_graph` turns all of these into one ``edge_index`` in the
caller's order plus, outside ``torch.compile``, a :class:`CSRPlan`: the
permutation that sorts the edges by (target, source) and the CSR pointer.  The
plan is built once per ``edge_index`` tensor and cached (keyed by the tensor's
identity and version counter, dropped when the tensor is freed), so layers get
their sorted fast path whatever order the caller's edges are in, and a stack
of layers on one graph sorts it once.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Any, Dict, Hashable, NamedTuple, Optional, Tuple, Union

import torch
from torch import Tensor
from torch_geometric import EdgeIndex, is_compiling
from torch_geometric.index import index2ptr
from torch_geometric.typing import PairTensor, SparseTensor
from torch_geometric.utils import is_sparse, to_edge_index


@dataclass(eq=False)
class CSRPlan:
    """The edges of one graph in CSR order of ``adj_t`` (sorted by target, then source).

    ``perm[k]`` is the caller's index of the ``k``-th edge in CSR order
    (``None`` when the caller's edges already are in that order), ``inv`` its
    inverse.  ``patterns`` caches the sparse patterns the kernels of
    :mod:`garmentgnn.nn._sparse` build from the plan (per head count).
    """

    src: Tensor  # [E] sources, CSR order
    dst: Tensor  # [E] targets, CSR order
    ptr: Tensor  # [num_dst + 1]
    perm: Optional[Tensor]
    inv: Optional[Tensor]
    num_src: int
    num_dst: int
    validated: bool = False
    patterns: Dict[Any, Any] = field(default_factory=dict)

    @property
    def num_edges(self) -> int:
        return self.src.numel()

    def to_caller(self, t: Tensor) -> Tensor:
        """Per-edge rows from CSR order back to the caller's order."""
        return t if self.inv is None else t.index_select(0, self.inv)

    @property
    def caller_ids(self) -> Tensor:
        """``[E]``: the caller's index of each edge in CSR order."""
        if self.perm is None:
            return torch.arange(self.num_edges, device=self.src.device)
        return self.perm


class Graph(NamedTuple):
    """A validated graph as the layers consume it."""

    edge_index: Tensor  # [2, E] source -> target, in the caller's order
    edge_attr: Optional[Tensor]  # [E, D] (caller's order) or None
    num_src: int
    num_dst: int
    plan: Optional[CSRPlan]  # None under torch.compile


def _fail(arg: str, msg: str) -> None:
    raise ValueError(f"`{arg}`: {msg}")


def _channels(name: str, val: Any, lazy: bool) -> None:
    ok = isinstance(val, int) and not isinstance(val, bool) and (val > 0 or (lazy and val == -1))
    if not ok:
        extra = " (or -1 to infer it from the first input)" if lazy else ""
        raise ValueError(f"`{name}` must be a positive int{extra}, got {val!r}")


def check_layer_args(
    in_channels: Union[int, Tuple[int, int]],
    out_channels: int,
    heads: int,
    edge_dim: Optional[int],
    dropout: float,
    *,
    edge_dim_required: bool,
) -> Tuple[int, int]:
    """Check the constructor arguments every layer shares; return ``(in_src, in_dst)``.

    ``in_channels`` is an int or a ``(src, dst)`` pair of positive ints, where
    ``-1`` means "infer from the first input" (lazy initialisation, as in
    PyG); ``out_channels`` and ``heads`` must be positive ints, ``edge_dim`` a
    positive int (or ``None`` unless ``edge_dim_required``), and ``dropout``
    lie in ``[0, 1)``.
    """
    if isinstance(in_channels, (tuple, list)) and len(in_channels) == 2:
        in_src, in_dst = in_channels
    elif isinstance(in_channels, int):
        in_src = in_dst = in_channels
    else:
        raise ValueError(f"`in_channels` must be an int or a (src, dst) pair of ints, "
                         f"got {in_channels!r}")
    _channels("in_channels", in_src, lazy=True)
    _channels("in_channels", in_dst, lazy=True)
    _channels("out_channels", out_channels, lazy=False)
    _channels("heads", heads, lazy=False)
    if edge_dim_required and edge_dim is None:
        raise ValueError("`edge_dim`: this layer needs edge features; pass their width, "
                         "e.g. edge_dim=4")
    if edge_dim is not None:
        _channels("edge_dim", edge_dim, lazy=False)
    if not (isinstance(dropout, (int, float)) and 0.0 <= dropout < 1.0):
        raise ValueError(f"`dropout` must lie in [0, 1), got {dropout!r}")
    return in_src, in_dst


def check_edge_out_channels(edge_out_channels: Optional[int]) -> None:
    if edge_out_channels is not None:
        _channels("edge_out_channels", edge_out_channels, lazy=False)


# --------------------------------------------------------------------------- tensor caches
def tensor_version(t: Tensor) -> Optional[int]:
    """``t``'s version counter (bumped by every in-place edit); ``None`` for inference
    tensors, which carry none."""
    try:
        return t._version
    except RuntimeError:
        return None


class TensorCache(Dict[Hashable, Tuple["weakref.ref", int, Any]]):
    """Values derived from a tensor, keyed by its identity (plus optional ``extra`` key
    parts) and checked against its version counter: an in-place edit of the tensor
    misses, and its entries are dropped when it is freed.  At most ``maxsize`` entries,
    oldest dropped first; inference tensors (no version counter) are never stored.

    The dict maps ``id(t)`` (or ``(id(t), *extra)``) to ``(weakref to t, version,
    value)``."""

    def __init__(self, maxsize: int) -> None:
        super().__init__()
        self.maxsize = maxsize

    @staticmethod
    def key(t: Tensor, extra: Tuple[Hashable, ...]) -> Hashable:
        return (id(t),) + extra if extra else id(t)

    def lookup(self, t: Tensor, *extra: Hashable) -> Optional[Any]:
        """The value stored for ``t`` (and ``extra``), or ``None`` when there is none or
        ``t`` was edited in place since."""
        entry = self.get(self.key(t, extra))
        if entry is None:
            return None
        ref, version, value = entry
        return value if ref() is t and version == tensor_version(t) else None

    def store(self, t: Tensor, value: Any, *extra: Hashable) -> None:
        version = tensor_version(t)
        if version is None:
            return
        key = self.key(t, extra)
        while len(self) >= self.maxsize:
            self.pop(next(iter(self)))
        self[key] = (weakref.ref(t, lambda _, k=key: self.pop(k, None)), version, value)


#: CSR plans of ``edge_index`` tensors (see :func:`prepare_graph`)
_PLANS = TensorCache(maxsize=32)


def _cached_plan(obj: Tensor, num_src: int, num_dst: int) -> Optional[CSRPlan]:
    plan = _PLANS.lookup(obj)
    if plan is None or (plan.num_src, plan.num_dst) != (num_src, num_dst):
        return None
    return plan


@torch.inference_mode(False)  # a plan built in inference mode is reused with autograd later
def build_plan(edge_index: Tensor, num_src: int, num_dst: int, sorted_: bool = False) -> CSRPlan:
    """Sort ``edge_index`` by (target, source) unless it already is (or ``sorted_``)."""
    src, dst = edge_index[0], edge_index[1]
    perm = inv = None
    if not sorted_ and src.numel() > 1:
        key = dst * num_src + src
        if not bool((key[1:] >= key[:-1]).all()):
            perm = torch.argsort(key, stable=True)
            inv = torch.empty_like(perm)
            inv[perm] = torch.arange(perm.numel(), device=perm.device)
            src, dst = src.index_select(0, perm), dst.index_select(0, perm)
    return CSRPlan(src, dst, index2ptr(dst, num_dst), perm, inv, num_src, num_dst)


def _check_range(edge_index: Tensor, num_src: int, num_dst: int) -> None:
    """Every index in ``[0, num_nodes)``: one ``aminmax`` pass and one host sync."""
    if edge_index.size(1) == 0 or edge_index.device.type == "meta":
        return
    lo, hi = torch.aminmax(edge_index, dim=1)
    (lo_s, lo_d), (hi_s, hi_d) = lo.tolist(), hi.tolist()
    if lo_s < 0 or hi_s >= num_src:
        _fail("edge_index", f"source indices span [{lo_s}, {hi_s}] but x has {num_src} nodes; "
                            "indices must lie in [0, num_nodes)")
    if lo_d < 0 or hi_d >= num_dst:
        _fail("edge_index", f"target indices span [{lo_d}, {hi_d}] but x has {num_dst} nodes; "
                            "indices must lie in [0, num_nodes)")


def _width(name: str, t: Tensor, want: Any, what: str) -> None:
    if isinstance(want, int) and want > 0 and t.size(-1) != want:
        _fail(name, f"has {t.size(-1)} columns but the layer was built with {what}={want}; "
                    f"pass [num_nodes, {want}] features or build the layer with "
                    f"{what}={t.size(-1)} (or -1 to infer it)")


def check_inputs(layer: Any, x: Any, edge_index: Any, edge_attr: Any) -> None:
    """The feature checks every layer runs before :func:`prepare_graph`: floating-point
    ``x`` of the layer's ``in_channels`` width, ``edge_attr`` of ``x``'s dtype, and every
    tensor on the parameters' device (metadata only: no pass over the values).

    Raises ``TypeError`` / ``ValueError`` naming the argument and the expected width or
    dtype, where torch would say ``mat1 and mat2 must have the same dtype`` or
    ``shapes cannot be multiplied``.  Non-tensor arguments are left to
    :func:`prepare_graph`."""
    xs = tuple(x) if isinstance(x, (tuple, list)) else (x,)
    if not all(isinstance(t, Tensor) and t.dim() == 2 for t in xs) or len(xs) > 2:
        return  # prepare_graph names the problem
    param = next(layer.parameters(), None)
    for t in xs:
        if not t.is_floating_point():
            raise TypeError(f"`x`: expected floating-point node features, got {t.dtype}; "
                            f"convert them, e.g. x.float()")
    if xs[0].dtype != xs[-1].dtype:
        raise TypeError(f"`x`: source features are {xs[0].dtype} but target features are "
                        f"{xs[-1].dtype}; give both the same dtype")
    in_ch = getattr(layer, "in_channels", -1)
    in_src, in_dst = in_ch if isinstance(in_ch, (tuple, list)) else (in_ch, in_ch)
    _width("x", xs[0], in_src, "in_channels")
    _width("x", xs[-1], in_dst, "in_channels")
    dtype = xs[0].dtype
    try:  # under autocast the ops pick their dtypes: any mix works
        autocast = torch.is_autocast_enabled(xs[0].device.type)
    except RuntimeError:  # a device type without autocast (meta)
        autocast = False
    if param is not None and param.dtype != dtype and param.dtype.is_floating_point \
            and not autocast:
        raise TypeError(f"`x`: features are {dtype} but the layer's weights are {param.dtype}; "
                        f"convert one, e.g. x.to({param.dtype}) or layer.to({dtype})")
    tensors = [("x", t) for t in xs]
    if isinstance(edge_index, Tensor):
        tensors.append(("edge_index", edge_index))
    if getattr(layer, "edge_dim", None) is not None and isinstance(edge_attr, Tensor):
        tensors.append(("edge_attr", edge_attr))
        if not edge_attr.is_floating_point():
            raise TypeError(f"`edge_attr`: expected floating-point edge features, got "
                            f"{edge_attr.dtype}; convert them, e.g. edge_attr.float()")
        if edge_attr.dtype != dtype and not autocast:
            raise TypeError(f"`edge_attr`: dtype {edge_attr.dtype} differs from x's {dtype}; "
                            f"give both the same dtype, e.g. edge_attr.to({dtype})")
    device = param.device if param is not None else xs[0].device
    for name, t in tensors:
        if t.device != device:
            raise ValueError(f"`{name}`: on {t.device} but the layer's weights are on "
                             f"{device}; move the inputs and the layer to one device "
                             f"(e.g. {name}.to('{device}'))")


def prepare_graph(
    x: Union[Tensor, PairTensor],
    edge_index: Union[Tensor, SparseTensor],
    edge_attr: Optional[Tensor],
    edge_dim: Optional[int],
    *,
    require_edge_attr: bool,
    validate: bool,
) -> Graph:
    """Normalise ``(x, edge_index, edge_attr)`` and check them.

    Args:
        x: node features ``[N, F]`` or a bipartite pair ``(x_src, x_dst)``.
        edge_index: ``[2, E]`` indices or a sparse ``adj_t`` (see module doc).
        edge_attr: ``[E, edge_dim]`` edge features, or ``None``.
        edge_dim: the layer's declared edge feature width (``None`` = ignores edges).
        require_edge_attr: raise if the layer needs edge features and none came.
        validate: kept for the layers' signature: outside ``torch.compile`` the index
            range is checked whenever a graph's CSR plan is built (once per cached
            graph), whatever ``validate`` says, because the sparse kernels index memory
            unchecked; under ``torch.compile`` no check runs (a host sync) and torch's
            own gather raises on a bad index.
    """
    if isinstance(x, (tuple, list)):
        if len(x) != 2:
            raise TypeError(f"`x`: expected a Tensor or a (Tensor, Tensor) pair, got "
                            f"{len(x)} items")
        x_src, x_dst = x
    else:
        x_src = x_dst = x
    for t in (x_src, x_dst):
        if not isinstance(t, Tensor):
            raise TypeError(f"`x`: expected a Tensor or a (Tensor, Tensor) pair, got "
                            f"{type(t).__name__}")
        if t.dim() != 2:
            _fail("x", f"expected shape [num_nodes, channels], got {tuple(t.shape)}")
    num_src, num_dst = x_src.size(0), x_dst.size(0)
    compiling = is_compiling()

    key_obj = edge_index
    plan: Optional[CSRPlan] = None
    if isinstance(edge_index, SparseTensor) or (isinstance(edge_index, Tensor)
                                                and is_sparse(edge_index)):
        if isinstance(edge_index, Tensor):
            # [num_dst, num_src] sparse, at most the edge features dense: a third sparse
            # dimension would be read as rows of the index (and the kernels index memory
            # unchecked with them), a batch dimension as a pointer row
            sparse, dense = edge_index.sparse_dim(), edge_index.dense_dim()
            batch = edge_index.dim() - sparse - dense
            if sparse != 2 or dense > 1 or batch:
                _fail("edge_index", f"a sparse adj_t needs 2 sparse dimensions [num_dst, "
                                    f"num_src] and at most 1 dense one (edge features: "
                                    f"[num_dst, num_src, edge_dim]); got {sparse} sparse, "
                                    f"{dense} dense{f' and {batch} batch' if batch else ''} "
                                    f"of shape {tuple(edge_index.shape)}; give one graph's "
                                    f"adjacency (a batch as one block-diagonal graph)")
        if tuple(edge_index.size()[:2]) != (num_dst, num_src):
            _fail("edge_index", f"sparse adj_t has shape {tuple(edge_index.size()[:2])}, expected "
                                f"[num_dst, num_src] = [{num_dst}, {num_src}]")
        if isinstance(edge_index, Tensor) and edge_index.layout == torch.sparse_coo:
            edge_index = edge_index.coalesce()  # row-major order; to_edge_index does not sort
        ij, values = to_edge_index(edge_index)
        if edge_attr is None and values is not None and values.dim() == 2:
            edge_attr = values  # hybrid sparse tensor [N, N, D] carries the edge features
        edge_index = ij.flip(0)  # adj_t[i, j] is the edge j -> i
        if not compiling:  # row-major adj_t order is CSR order: nothing to sort
            plan = build_plan(edge_index, num_src, num_dst, sorted_=True)
            plan.validated = True
    elif isinstance(edge_index, Tensor):
        if edge_index.dim() != 2 or edge_index.size(0) != 2:
            _fail("edge_index", f"expected shape [2, num_edges], got {tuple(edge_index.shape)}")
        if edge_index.dtype not in (torch.long, torch.int32):
            raise TypeError(f"`edge_index`: expected an integer (long) tensor, got "
                            f"{edge_index.dtype}")
        if isinstance(edge_index, EdgeIndex):
            edge_index = edge_index.as_tensor()
        if edge_index.dtype != torch.long:
            edge_index = edge_index.long()
        if not compiling:
            plan = _cached_plan(key_obj, num_src, num_dst)
            if plan is None:
                # always, validate or not: the CSR kernels index memory without bound
                # checks, and an index out of range would crash the interpreter
                _check_range(edge_index, num_src, num_dst)
                plan = build_plan(edge_index, num_src, num_dst)
                plan.validated = True
                _PLANS.store(key_obj, plan)
    else:
        raise TypeError(f"`edge_index`: expected a LongTensor [2, E] or a sparse adjacency, "
                        f"got {type(edge_index).__name__}")
    num_edges = edge_index.size(1)

    if edge_dim is None or edge_attr is None:
        if edge_dim is not None and require_edge_attr:
            _fail("edge_attr", f"this layer was built with edge_dim={edge_dim} and needs edge "
                               f"features of shape [num_edges, {edge_dim}]; got None")
        return Graph(edge_index, edge_attr if edge_dim is not None else None, num_src, num_dst,
                     plan)
    if not isinstance(edge_attr, Tensor):
        raise TypeError(f"`edge_attr`: expected a Tensor, got {type(edge_attr).__name__}")
    if edge_attr.dim() == 1 and edge_dim == 1:
        edge_attr = edge_attr.unsqueeze(-1)
    if edge_attr.dim() != 2 or edge_attr.size(1) != edge_dim:
        _fail("edge_attr", f"expected shape [num_edges, edge_dim={edge_dim}], got "
                           f"{tuple(edge_attr.shape)}; build the layer with the right edge_dim")
    if edge_attr.size(0) != num_edges:
        _fail("edge_attr", f"has {edge_attr.size(0)} rows but edge_index has {num_edges} edges; "
                           "one feature row per edge, in edge_index order")
    return Graph(edge_index, edge_attr, num_src, num_dst, plan)


def check_outputs(layer: str, outputs: Tuple[Optional[Tensor], ...],
                  inputs: Tuple[Tuple[str, Optional[Tensor]], ...]) -> None:
    """Raise a ``ValueError`` when an output holds NaN/inf, naming the cause.

    One host sync per call in the common (finite) case; when an output is not
    finite the inputs are inspected to say which argument was bad, or that
    finite inputs overflowed (e.g. features around 1e20, whose attention
    scores exceed the float range).
    """
    present = [t for t in outputs if t is not None and t.numel() > 0]
    if not present:
        return
    total = sum(t.sum() for t in present)  # NaN/inf anywhere make the sum non-finite
    if bool(torch.isfinite(total)) or all(bool(torch.isfinite(t).all()) for t in present):
        return  # (the second test: finite values whose sum overflowed)
    for name, t in inputs:
        if t is not None and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            _fail(name, f"contains {bad} NaN/inf value(s), which reached {layer}'s output; "
                        "clean the input or find where they were produced (check_finite=False "
                        "skips this check)")
    peaks = ", ".join(f"max |{n}| = {float(t.abs().max()):.3g}" for n, t in inputs
                      if t is not None and t.is_floating_point() and t.numel() > 0)
    _fail("x", f"the inputs are finite ({peaks}) but {layer}'s output is not: the attention "
               "scores overflowed the floating-point range; normalise the features (e.g. a "
               "LayerNorm before the layer) or pass check_finite=False to get the raw values")
