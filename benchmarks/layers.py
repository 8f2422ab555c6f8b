"""Layer benchmark: every garmentgnn.nn layer against PyG's TransformerConv(edge_dim).

On a 10K-vertex triangle mesh (~60K directed edges), width 64 = 4 heads x 16
channels, edge features [length, direction] (4): median forward (inference,
no grad) and forward+backward times, peak extra memory, and each time as a
ratio to TransformerConv measured in the same run, rounds interleaved so that
machine noise hits every layer alike.  Runs once with torch-scatter and once
with it hidden (PyG's native scatter), each in its own process.

    python benchmarks/layers.py                  # both backends, full size
    python benchmarks/layers.py --nx 30 --reps 3 # quick look

Writes ``benchmarks/results/layers.json`` and ``layers.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _hide_scatter() -> None:
    sys.modules["torch_scatter"] = None  # `import torch_scatter` now raises ImportError


def build(nx: int, width: int, heads: int):
    import torch
    from torch_geometric.nn import TransformerConv

    from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh
    from garmentgnn.nn import LAYERS, make_layer

    pos, faces = grid_mesh(nx, nx)
    pos = pos + 0.002 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(0))
    ei = faces_to_edge_index(faces, pos.size(0))
    e = edge_features(pos, ei)
    x = torch.randn(pos.size(0), width, generator=torch.Generator().manual_seed(1))
    torch.manual_seed(0)
    C = width // heads
    layers = {"TransformerConv (PyG)": TransformerConv(width, C, heads=heads, edge_dim=e.size(1))}
    for name in sorted(LAYERS):
        # validate=False: the anchor does no input checks either
        layers[name] = make_layer(name, width, C, edge_dim=e.size(1), heads=heads, validate=False)
    # SATConv's optimisation steps, each measured beside the rest (see the README)
    layers["sat: gather + segment"] = Variant(layers["sat"], csr=False)
    layers["sat: gather + scatter (unsorted)"] = Variant(layers["sat"], csr=False, shuffle=True)
    return x, ei, e, layers


class Variant:
    """The same layer run with the CSR kernels off and/or the edges shuffled."""

    def __init__(self, layer, csr: bool, shuffle: bool = False):
        import torch

        self.layer, self.csr, self.shuffle = layer, csr, shuffle
        self.perm = None
        self._torch = torch

    def __call__(self, x, ei, e):
        from garmentgnn.nn._sparse import csr_kernels

        if self.shuffle:
            if self.perm is None or self.perm.numel() != ei.size(1):
                self.perm = self._torch.randperm(ei.size(1), generator=self._torch.Generator()
                                                 .manual_seed(0))
            ei, e = ei[:, self.perm], e[self.perm]
        with csr_kernels(self.csr):
            return self.layer(x, ei, e)

    def __getattr__(self, name):  # eval/train/zero_grad/parameters
        return getattr(self.layer, name)


def call(layer, x, ei, e):
    out = layer(x, ei, e)
    return out if isinstance(out, tuple) else (out, None)


def loss_of(outs):
    out, e_out = outs
    loss = out.square().mean()
    if e_out is not None and e_out.requires_grad:
        loss = loss + e_out.square().mean()
    return loss


def time_layers(x, ei, e, layers, reps: int, warmup: int = 2):
    import torch

    fwd = {k: [] for k in layers}
    fb = {k: [] for k in layers}
    for r in range(warmup + reps):
        for name, layer in layers.items():
            layer.eval()
            with torch.inference_mode():
                t0 = time.perf_counter()
                call(layer, x, ei, e)
                t1 = time.perf_counter()
            layer.train()
            layer.zero_grad(set_to_none=True)
            t2 = time.perf_counter()
            loss_of(call(layer, x, ei, e)).backward()
            t3 = time.perf_counter()
            if r >= warmup:
                fwd[name].append(t1 - t0)
                fb[name].append(t3 - t2)
    return fwd, fb


def peak_memory(args, name: str, mode: str) -> float:
    """Extra peak RSS (MB) of one forward or forward+backward, in a fresh process."""
    cmd = [sys.executable, __file__, "--child-memory", name, mode, "--nx", str(args.nx),
           "--width", str(args.width), "--heads", str(args.heads)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return float(res.stdout.strip().splitlines()[-1])


def _proc_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def child_memory(args) -> None:
    """Peak resident memory above the resting level during one call (Linux).

    Resets the kernel's high-water mark (``echo 5 > /proc/self/clear_refs``)
    after building the inputs and trimming the allocator, so the number is the
    layer's own transient memory: activations, saved tensors and gradients.
    """
    import ctypes
    import gc

    import torch

    x, ei, e, layers = build(args.nx, args.width, args.heads)
    layer = layers[args.child_memory[0]]
    mode = args.child_memory[1]
    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    Path("/proc/self/clear_refs").write_text("5")
    base = _proc_kb("VmRSS")
    if mode == "fwd":
        layer.eval()
        with torch.inference_mode():
            call(layer, x, ei, e)
    else:
        layer.train()
        loss_of(call(layer, x, ei, e)).backward()
    print((_proc_kb("VmHWM") - base) / 1024.0)


def run_backend(args) -> dict:
    import torch
    import torch_geometric
    import torch_geometric.typing

    torch.set_num_threads(args.threads)
    x, ei, e, layers = build(args.nx, args.width, args.heads)
    fwd, fb = time_layers(x, ei, e, layers, args.reps)
    anchor = "TransformerConv (PyG)"
    rows = []
    for name in layers:
        f, b = statistics.median(fwd[name]), statistics.median(fb[name])
        rows.append(dict(
            layer=name,
            fwd_ms=1e3 * f, fwd_iqr_ms=1e3 * (max(fwd[name]) - min(fwd[name])),
            fwd_bwd_ms=1e3 * b,
            fwd_ratio=f / statistics.median(fwd[anchor]),
            fwd_bwd_ratio=b / statistics.median(fb[anchor]),
            params=sum(p.numel() for p in layers[name].parameters()),
        ))
    if not args.skip_memory:
        for row in rows:
            row["peak_fwd_mb"] = peak_memory(args, row["layer"], "fwd")
            row["peak_fwd_bwd_mb"] = peak_memory(args, row["layer"], "fb")
    return dict(
        torch_scatter=torch_geometric.typing.WITH_TORCH_SCATTER,
        torch=torch.__version__, torch_geometric=torch_geometric.__version__,
        threads=torch.get_num_threads(), num_nodes=x.size(0), num_edges=ei.size(1),
        width=args.width, heads=args.heads, reps=args.reps, rows=rows,
    )


def _mb(v) -> str:
    return "-" if v is None else f"{v:.0f}"


def markdown(results: list) -> str:
    lines = []
    for res in results:
        tag = "with torch-scatter" if res["torch_scatter"] else "without torch-scatter (PyG native)"
        lines += [f"### {tag}", "",
                  f"{res['num_nodes']} vertices, {res['num_edges']} directed edges, width "
                  f"{res['width']} ({res['heads']} heads), {res['threads']} threads, median of "
                  f"{res['reps']}; torch {res['torch']}, PyG {res['torch_geometric']}.", "",
                  "| layer | fwd ms | fwd+bwd ms | fwd ratio | fwd+bwd ratio | peak fwd MB | "
                  "peak fwd+bwd MB | params |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in res["rows"]:
            lines.append(
                f"| {r['layer']} | {r['fwd_ms']:.1f} | {r['fwd_bwd_ms']:.1f} | "
                f"{r['fwd_ratio']:.2f} | {r['fwd_bwd_ratio']:.2f} | "
                f"{_mb(r.get('peak_fwd_mb'))} | {_mb(r.get('peak_fwd_bwd_mb'))} | {r['params']} |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nx", type=int, default=100, help="mesh is nx x nx vertices (100 -> 10K)")
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--heads", type=int, default=4)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--backend", choices=["both", "scatter", "native"], default="both")
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--child-memory", nargs=2, metavar=("LAYER", "MODE"), help=argparse.SUPPRESS)
    ap.add_argument("--child-json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()

    if os.environ.get("GARMENTGNN_NO_SCATTER") == "1":
        _hide_scatter()
    if args.child_memory:
        return child_memory(args)
    if args.child_json:
        print(json.dumps(run_backend(args)))
        return

    backends = ["scatter", "native"] if args.backend == "both" else [args.backend]
    results = []
    for b in backends:
        env = dict(os.environ)
        env.pop("GARMENTGNN_NO_SCATTER", None)
        if b == "native":
            env["GARMENTGNN_NO_SCATTER"] = "1"
        cmd = [sys.executable, __file__, "--child-json", "--nx", str(args.nx), "--width",
               str(args.width), "--heads", str(args.heads), "--reps", str(args.reps),
               "--threads", str(args.threads)] + (["--skip-memory"] if args.skip_memory else [])
        print(f"[layers] running backend={b} ...", file=sys.stderr, flush=True)
        res = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if res.returncode != 0:
            sys.stderr.write(res.stderr)
            raise SystemExit(f"benchmark child for backend={b} failed")
        results.append(json.loads(res.stdout.strip().splitlines()[-1]))
    report = dict(machine=dict(platform=platform.platform(), processor=platform.processor(),
                               cpus=os.cpu_count(), python=platform.python_version()),
                  results=results)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "layers.json").write_text(json.dumps(report, indent=2))
    md = "# Layer benchmark\n\n" + markdown(results)
    (args.out / "layers.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
