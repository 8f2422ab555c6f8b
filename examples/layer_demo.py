"""Layer demo: every garmentgnn.nn layer learns a mesh operator on a bumpy sheet.

The task needs the mesh structure: from vertex heights z_i and edge features
(length, direction) predict the umbrella Laplacian ``z_i - mean_{j in N(i)} z_j``
of a randomly bumped 20x20 sheet.  Each registry layer is dropped into the same
small PyG model (two layers, ELU between) and trained for a few hundred steps;
the table shows held-out error against the trivial "predict the mean" baseline.

    python examples/layer_demo.py [--steps 800]
"""
from __future__ import annotations

import argparse
import time

import torch
from torch import nn
from torch_geometric.utils import scatter

from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh
from garmentgnn.nn import LAYERS, make_layer


def bumpy_sheet(seed: int, n: int = 20):
    """A sheet with random Gaussian bumps; returns features, graph and target."""
    g = torch.Generator().manual_seed(seed)
    pos, faces = grid_mesh(n, n)
    centres, widths = torch.rand(4, 2, generator=g), 0.1 + 0.2 * torch.rand(4, generator=g)
    amps = 0.3 * torch.randn(4, generator=g)
    d2 = ((pos[:, None, :2] - centres[None]) ** 2).sum(-1)
    pos[:, 2] = (amps * torch.exp(-d2 / widths**2)).sum(-1)
    ei = faces_to_edge_index(faces, pos.size(0))
    z = pos[:, 2:]
    target = z - scatter(z[ei[0]], ei[1], dim=0, dim_size=z.size(0), reduce="mean")
    return z * 10, ei, edge_features(pos, ei), target * 100


class TwoLayerNet(nn.Module):
    """Any registry layer inside a plain PyG-style model."""

    def __init__(self, name: str, hidden: int = 16, heads: int = 4, edge_dim: int = 4):
        super().__init__()
        self.enc = nn.Linear(1, hidden)
        self.conv1 = make_layer(name, hidden, hidden // heads, heads=heads, edge_dim=edge_dim)
        self.conv2 = make_layer(name, hidden, hidden // heads, heads=heads, edge_dim=edge_dim)
        self.head = nn.Linear(hidden, 1)

    def forward(self, z, edge_index, edge_attr):
        x = self.enc(z)
        # the edge-carrying form: layers that ignore edges hand edge_attr back unchanged
        x, e = self.conv1(x, edge_index, edge_attr, return_edge_attr=True)
        x = nn.functional.elu(x)
        x = self.conv2(x, edge_index, e)
        return self.head(nn.functional.elu(x))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=800)
    args = ap.parse_args()
    torch.manual_seed(0)
    train = [bumpy_sheet(s) for s in range(8)]
    test = [bumpy_sheet(100 + s) for s in range(4)]
    base = torch.stack([t[3].pow(2).mean() for t in test]).mean().item()
    print(f"task: umbrella Laplacian of a bumpy 20x20 sheet; baseline MSE (predict 0) = {base:.4f}")
    print(f"{'layer':<16} {'params':>7} {'test MSE':>9} {'vs baseline':>12} {'train s':>8}")
    for name in sorted(LAYERS):
        torch.manual_seed(0)
        model = TwoLayerNet(name)
        opt = torch.optim.Adam(model.parameters(), lr=3e-3)
        t0 = time.perf_counter()
        for step in range(args.steps):
            z, ei, e, y = train[step % len(train)]
            loss = (model(z, ei, e) - y).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        dt = time.perf_counter() - t0
        with torch.no_grad():
            mse = torch.stack([(model(z, ei, e) - y).pow(2).mean() for z, ei, e, y in test]).mean()
        if not torch.isfinite(mse):
            raise SystemExit(f"{name}: non-finite test error")
        params = sum(p.numel() for p in model.parameters())
        print(f"{name:<16} {params:>7} {mse.item():>9.4f} {mse.item() / base:>11.1%} {dt:>8.1f}")


if __name__ == "__main__":
    main()
