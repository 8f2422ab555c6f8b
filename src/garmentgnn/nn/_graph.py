"""Input handling shared by every layer in :mod:`garmentgnn.nn`.

Every layer accepts the adjacency in the forms PyG layers accept:

* a ``[2, E]`` ``LongTensor`` (or :class:`torch_geometric.EdgeIndex`) of
  ``source -> target`` pairs, with ``edge_attr`` of shape ``[E, edge_dim]``
  in the same order;
* a transposed sparse adjacency ``adj_t`` of shape ``[N_dst, N_src]``
  (:class:`torch.sparse` COO/CSR/CSC or :class:`torch_sparse.SparseTensor`),
  where a stored entry ``adj_t[i, j]`` is the edge ``j -> i``.  Edge features
  are then either passed as ``edge_attr`` in the adjacency's row-major
  (coalesced) order, or stored as the values of a hybrid sparse tensor of
  shape ``[N_dst, N_src, edge_dim]``.  Returned edge features follow that same
  row-major order.

:func:`prepare_graph` turns all of these into one ``edge_index`` plus, when
the edges are sorted by target, the CSR pointer ``ptr`` that lets the layers
use segment reductions instead of scatters.
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Tuple, Union

import torch
from torch import Tensor
from torch_geometric import EdgeIndex, is_compiling
from torch_geometric.index import index2ptr
from torch_geometric.typing import SparseTensor
from torch_geometric.utils import is_sparse, scatter, segment, softmax, to_edge_index

PairTensor = Tuple[Tensor, Tensor]


class Graph(NamedTuple):
    """A validated graph as the layers consume it."""

    edge_index: Tensor  # [2, E] source -> target
    edge_attr: Optional[Tensor]  # [E, D] or None
    ptr: Optional[Tensor]  # CSR pointer over targets when sorted, else None
    num_src: int
    num_dst: int
    csr: bool = False  # sorted by (target, source) without duplicates: valid CSR of adj_t
    cache: Optional[dict] = None  # per-call scratch for sparse patterns (prepare_graph sets one)


def _fail(arg: str, msg: str) -> None:
    raise ValueError(f"`{arg}`: {msg}")


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

    ``in_channels`` is an int or a ``(src, dst)`` pair; it, ``out_channels``
    and ``heads`` must be positive ints, ``edge_dim`` a positive int (or
    ``None`` unless ``edge_dim_required``), and ``dropout`` lie in ``[0, 1)``.
    """
    if isinstance(in_channels, int):
        in_src = in_dst = in_channels
    else:
        in_src, in_dst = in_channels
    checks = [("in_channels", in_src), ("in_channels", in_dst), ("out_channels", out_channels),
              ("heads", heads)]
    if edge_dim_required:
        checks.append(("edge_dim", edge_dim))
    for name, val in checks:
        if not isinstance(val, int) or val <= 0:
            raise ValueError(f"`{name}` must be a positive int, got {val!r}")
    if edge_dim is not None and (not isinstance(edge_dim, int) or edge_dim <= 0):
        raise ValueError(f"`edge_dim` must be a positive int or None, got {edge_dim!r}")
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"`dropout` must lie in [0, 1), got {dropout}")
    return in_src, in_dst


def check_finite(name: str, t: Optional[Tensor]) -> None:
    """Raise a ``ValueError`` naming ``name`` if ``t`` holds NaN or inf."""
    if t is not None and t.is_floating_point() and not bool(torch.isfinite(t).all()):
        bad = int((~torch.isfinite(t)).sum())
        _fail(name, f"contains {bad} NaN/inf value(s); clean the input or find where they "
                    "were produced (pass validate=False to the layer to skip this check)")


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
        validate: run the O(N + E) checks (finite values, index range).
    """
    x_src, x_dst = (x, x) if isinstance(x, Tensor) else x
    for name, t in (("x", x_src), ("x", x_dst)):
        if not isinstance(t, Tensor):
            raise TypeError(f"`x`: expected a Tensor or a (Tensor, Tensor) pair, got {type(t).__name__}")
        if t.dim() != 2:
            _fail(name, f"expected shape [num_nodes, channels], got {tuple(t.shape)}")
    num_src, num_dst = x_src.size(0), x_dst.size(0)

    ptr: Optional[Tensor] = None
    if isinstance(edge_index, SparseTensor) or (isinstance(edge_index, Tensor) and is_sparse(edge_index)):
        if tuple(edge_index.size()[:2]) != (num_dst, num_src):
            _fail("edge_index", f"sparse adj_t has shape {tuple(edge_index.size()[:2])}, expected "
                                f"[num_dst, num_src] = [{num_dst}, {num_src}]")
        if isinstance(edge_index, Tensor) and edge_index.layout == torch.sparse_coo:
            edge_index = edge_index.coalesce()  # row-major order; to_edge_index does not sort
        ij, values = to_edge_index(edge_index)
        if edge_attr is None and values is not None and values.dim() == 2:
            edge_attr = values  # hybrid sparse tensor [N, N, D] carries the edge features
        edge_index = ij.flip(0)  # adj_t[i, j] is the edge j -> i
        # row-major adj_t order is sorted by target: a CSR pointer comes for free
        ptr = index2ptr(edge_index[1], num_dst)
    elif isinstance(edge_index, Tensor):
        if edge_index.dim() != 2 or edge_index.size(0) != 2:
            _fail("edge_index", f"expected shape [2, num_edges], got {tuple(edge_index.shape)}")
        if edge_index.dtype not in (torch.long, torch.int32):
            raise TypeError(f"`edge_index`: expected an integer (long) tensor, got {edge_index.dtype}")
        if isinstance(edge_index, EdgeIndex):
            edge_index = edge_index.as_tensor()
        if edge_index.dtype != torch.long:
            edge_index = edge_index.long()
    else:
        raise TypeError(f"`edge_index`: expected a LongTensor [2, E] or a sparse adjacency, "
                        f"got {type(edge_index).__name__}")

    num_edges = edge_index.size(1)
    if validate and num_edges > 0:
        lo_s, hi_s = int(edge_index[0].min()), int(edge_index[0].max())
        lo_d, hi_d = int(edge_index[1].min()), int(edge_index[1].max())
        if lo_s < 0 or hi_s >= num_src:
            _fail("edge_index", f"source indices span [{lo_s}, {hi_s}] but x has {num_src} nodes; "
                                "indices must lie in [0, num_nodes)")
        if lo_d < 0 or hi_d >= num_dst:
            _fail("edge_index", f"target indices span [{lo_d}, {hi_d}] but x has {num_dst} nodes; "
                                "indices must lie in [0, num_nodes)")
    if validate:
        check_finite("x", x_src)
        if x_dst is not x_src:
            check_finite("x", x_dst)
    if ptr is None:
        dst = edge_index[1]
        if num_edges == 0 or bool((dst[1:] >= dst[:-1]).all()):
            # sorted by target (the usual CSR layout): segment reductions replace scatters
            ptr = index2ptr(dst, num_dst)

    csr = False
    if ptr is not None:
        key = edge_index[1] * num_src + edge_index[0]
        csr = num_edges == 0 or bool((key[1:] > key[:-1]).all())

    if edge_dim is None:
        return Graph(edge_index, edge_attr, ptr, num_src, num_dst, csr, {})

    if edge_attr is None:
        if require_edge_attr:
            _fail("edge_attr", f"this layer was built with edge_dim={edge_dim} and needs edge "
                               f"features of shape [num_edges, {edge_dim}]; got None")
        return Graph(edge_index, None, ptr, num_src, num_dst, csr, {})
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
    if validate:
        check_finite("edge_attr", edge_attr)
    return Graph(edge_index, edge_attr, ptr, num_src, num_dst, csr, {})


def segment_sum(src: Tensor, index: Tensor, ptr: Optional[Tensor], dim_size: int) -> Tensor:
    """Sum ``src`` rows into ``dim_size`` buckets: CSR segments when ``ptr`` is known."""
    if ptr is not None:
        return segment(src, ptr, reduce="sum")
    return scatter(src, index, dim=0, dim_size=dim_size, reduce="sum")


def keep_one_mask(mask: Tensor, index: Tensor, num_nodes: int) -> Tensor:
    """Random attention mask that never removes every incoming edge of a node.

    ``mask`` is a boolean ``[E, H]`` tensor of edges to drop.  For every
    (target, head) one incoming edge -- drawn uniformly at random -- is always
    kept, so a softmax over the masked scores never sees only ``-inf``.
    """
    r = torch.rand(mask.shape, device=mask.device)
    r_max = scatter(r, index, dim=0, dim_size=num_nodes, reduce="max")
    keep = r == r_max.index_select(0, index)
    return mask & ~keep



def edge_softmax(src: Tensor, g: Graph) -> Tensor:
    """Softmax of ``src [E, ...]`` over the incoming edges of each target node.

    With a CSR pointer this runs on :func:`torch.segment_reduce`, which measured
    about 4x faster on CPU than PyG's ``softmax(ptr=...)`` backed by
    torch-scatter's ``segment_csr`` (0.6 ms vs 2.5 ms for 60K edges x 4 heads)
    and gives the same values; otherwise it is PyG's :func:`softmax`.  Entries
    of ``-inf`` get weight 0 as long as their segment holds a finite one.
    """
    if g.ptr is None or is_compiling():
        return softmax(src, g.edge_index[1], g.ptr, g.num_dst)
    index = g.edge_index[1]
    peak = torch.segment_reduce(src.detach(), "max", offsets=g.ptr, axis=0, unsafe=True)
    out = (src - peak.index_select(0, index)).exp()
    total = torch.segment_reduce(out, "sum", offsets=g.ptr, axis=0, unsafe=True)
    return out / (total.index_select(0, index) + 1e-16)
