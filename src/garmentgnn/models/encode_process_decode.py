"""MeshGraphNets' network: encode, process, decode (Pfaff et al., ICLR 2021, Sec. 3).

A generic graph network for any learned simulator: it maps node inputs ``[N, node_in]`` and
mesh-edge inputs ``[E, edge_in]`` to a node output ``[N, out_channels]``, with

* **encode**: a LayerNorm'd MLP per input group into the latent width ``hidden``;
  *contact edges* (``contact_in > 0``: one-way edges from points outside the graph, such
  as MeshGraphNets' world edges or HOOD's body edges) are encoded too and summed into the
  node each points to;
* **process**: ``layers`` residual blocks, each a :mod:`garmentgnn.nn` layer over the
  mesh graph (``layer``: any name of :data:`garmentgnn.nn.LAYERS` or a layer's class path)
  with its edge features carried block to block, then a LayerNorm and a LayerNorm'd MLP
  (MeshGraphNets' node update) with a residual connection.  With ``contact_blocks``
  the contact edges are updated in every block as MeshGraphNets and HOOD do, ``c <- c +
  MLP([c, h_i])``, and summed into their node again (else they are read once, in the
  encoder);
* **coarse levels** (``levels > 0``): further edge sets over the same nodes, such as a mesh
  graph's coarse levels (:func:`garmentgnn.geometry.coarse_levels`, HOOD's hierarchy),
  each with its own encoder and edge features carried from one of its blocks to the next;
  counted from the last block, every second block runs on a coarse level (the levels in
  turn) and the others on the mesh graph, so the last block is the mesh's;
* **decode**: an MLP to ``out_channels``.
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from garmentgnn.models.blocks import freeze_edge_output, mlp
from garmentgnn.nn import layer_class, make_layer

__all__ = ["EncodeProcessDecode", "mlp_ln"]


def mlp_ln(sizes) -> nn.Sequential:
    """A ReLU MLP ending in ``LayerNorm`` (MeshGraphNets' encoder and update MLPs)."""
    return mlp(sizes, nn.ReLU(), last_act=False).append(nn.LayerNorm(sizes[-1]))


class EncodeProcessDecode(nn.Module):
    """MeshGraphNets' encode-process-decode network (module doc).

    Args:
        node_in, edge_in: node and mesh-edge input widths.
        out_channels: node output width.
        hidden: latent width of every MLP and layer.
        layers: processor blocks (MeshGraphNets: 15).
        layer: the :mod:`garmentgnn.nn` layer of each block.
        heads: attention heads of each layer (``hidden`` must be a multiple).
        contact_in: contact-edge input width (0: no contact edges).
        contact_blocks: update the contact edges in every block (module doc).
        levels: coarse edge sets (module doc; inputs of width ``edge_in`` each); needs
            ``layers >= 2 * levels``.
    """

    def __init__(self, node_in: int, edge_in: int, out_channels: int, hidden: int = 64,
                 layers: int = 8, layer: str = "sat", heads: int = 4, contact_in: int = 0,
                 contact_blocks: bool = False, levels: int = 0) -> None:
        super().__init__()
        for name, v in (("node_in", node_in), ("edge_in", edge_in),
                        ("out_channels", out_channels), ("hidden", hidden),
                        ("layers", layers), ("heads", heads)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"`{name}`: expected a positive int, got {v!r}")
        if not isinstance(contact_in, int) or isinstance(contact_in, bool) or contact_in < 0:
            raise ValueError(f"`contact_in`: expected an int >= 0, got {contact_in!r}")
        if not isinstance(levels, int) or isinstance(levels, bool) or levels < 0:
            raise ValueError(f"`levels`: expected an int >= 0, got {levels!r}")
        if 2 * levels > layers:
            raise ValueError(f"`levels`: {levels} coarse levels need {2 * levels} blocks or "
                             f"more (every second block a coarse one), got layers={layers}")
        if contact_blocks and not contact_in:
            raise ValueError("`contact_blocks`: updates contact edges, but `contact_in` is 0; "
                             "give their input width")
        try:
            layer_class(layer)
        except ValueError as err:
            raise ValueError(f"`layer`: {str(err).split(': ', 1)[1]}") from None
        if hidden % heads:
            raise ValueError(f"`heads`: {heads} heads do not divide hidden={hidden}; give a "
                             f"divisor of it")
        self.hidden, self.contact_in = hidden, contact_in
        self.node_enc = mlp_ln([node_in, hidden, hidden])
        self.edge_enc = mlp_ln([edge_in, hidden, hidden])
        self.contact_enc = mlp_ln([contact_in, hidden, hidden]) if contact_in else None
        self.convs = nn.ModuleList(
            make_layer(layer, hidden, hidden // heads, edge_dim=hidden, heads=heads,
                       concat=True, validate=False, check_finite=False)
            for _ in range(layers))
        self.conv_norms = nn.ModuleList(nn.LayerNorm(hidden) for _ in range(layers))
        self.updates = nn.ModuleList(mlp_ln([hidden, 2 * hidden, hidden])
                                     for _ in range(layers))
        self.contact_updates = (nn.ModuleList(mlp_ln([2 * hidden, hidden, hidden])
                                              for _ in range(layers))
                                if contact_blocks else None)
        self.decoder = mlp([hidden, hidden, out_channels],
                           nn.ReLU(), last_act=False)
        self.coarse_encs = nn.ModuleList(mlp_ln([edge_in, hidden, hidden])
                                         for _ in range(levels))
        #: the edge set of each block: 0 the mesh graph, l > 0 coarse level l
        self.block_levels = [0 if j % 2 == 0 else 1 + (j // 2) % levels
                             for j in reversed(range(layers))] if levels else [0] * layers
        #: the last block of each edge set: its edge output is never read (frozen)
        self.last_blocks = {lvl: i for i, lvl in enumerate(self.block_levels)}
        for i in self.last_blocks.values():
            freeze_edge_output(self.convs[i])

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor,
                contact_attr: Optional[Tensor] = None,
                contact_index: Optional[Tensor] = None,
                coarse: Sequence[Tuple[Tensor, Tensor]] = ()) -> Tensor:
        """The node output ``[N, out_channels]`` of node inputs ``x [N, node_in]``, the mesh
        graph ``edge_index [2, E]`` with ``edge_attr [E, edge_in]``, with ``contact_in``
        contact edges ``contact_attr [Ec, contact_in]`` pointing to the nodes
        ``contact_index [Ec]``, and with ``levels`` the coarse edge sets ``coarse``: one
        ``(edge_index [2, E_l], edge_attr [E_l, edge_in])`` a level."""
        if (contact_attr is None) != (self.contact_enc is None) or \
                (contact_attr is None) != (contact_index is None):
            raise ValueError(f"`contact_attr`, `contact_index`: this network reads "
                             f"{'contact edges' if self.contact_in else 'none'} "
                             f"(contact_in={self.contact_in}); give both or neither")
        if len(coarse) != len(self.coarse_encs):
            raise ValueError(f"`coarse`: this network reads {len(self.coarse_encs)} coarse "
                             f"edge sets (levels), got {len(coarse)}")
        h = self.node_enc(x)
        c = None
        if contact_attr is not None:
            c = self.contact_enc(contact_attr)
            h = h.index_add(0, contact_index, c)
        graphs = [(edge_index, self.edge_enc(edge_attr))] + [
            (ei, enc(attr)) for (ei, attr), enc in zip(coarse, self.coarse_encs)]
        return self.decoder(self.process(h, graphs, c, contact_index))

    def process(self, h: Tensor, graphs: List[Tuple[Tensor, Tensor]],
                c: Optional[Tensor] = None, contact_index: Optional[Tensor] = None) -> Tensor:
        """The processor (module doc) on latent nodes ``h``, the edge sets ``graphs``
        (``(edge_index, latent edges)``: the mesh graph's, then each coarse level's) and
        contact edges ``c``."""
        graphs = list(graphs)
        for i, (conv, norm, update) in enumerate(zip(self.convs, self.conv_norms,
                                                     self.updates)):
            if self.contact_updates is not None:
                c = c + self.contact_updates[i](torch.cat([c, h[contact_index]], 1))
                h = h.index_add(0, contact_index, c)
            lvl = self.block_levels[i]
            ei, e = graphs[lvl]
            if i < self.last_blocks[lvl]:
                h2, e = conv(h, ei, e, return_edge_attr=True)
                graphs[lvl] = (ei, e)
            else:
                h2 = conv(h, ei, e)
            h = norm(h2)
            h = h + update(h)
        return h

    def __repr__(self) -> str:
        conv = self.convs[0]
        return (f"{type(self).__name__}(hidden={self.hidden}, layers={len(self.convs)}, "
                f"layer={type(conv).__name__}, heads={getattr(conv, 'heads', None)}, "
                f"contact_in={self.contact_in}, "
                f"contact_blocks={self.contact_updates is not None}, "
                f"levels={len(self.coarse_encs)})")
