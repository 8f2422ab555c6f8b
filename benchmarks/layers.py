"""Layer benchmark: SATConv (and the other garmentgnn.nn layers) against PyG's
TransformerConv and GATv2Conv, side by side in one run.

A ~10K-vertex triangle mesh (nx x nx grid, ~59K directed edges), input width 64,
edge features of width 4 (length and direction) and 64; for every configuration of heads x
channels (4x16, 1x64, 4x64), edge order (sorted by target as
``faces_to_edge_index`` gives it, and randomly shuffled) and thread count (1, 2),
every layer is timed forward (inference, no autograd) and forward+backward
(training mode, loss on the node output), rounds interleaved so machine noise
hits every layer alike (every other round in the opposite order).  Each time is also
given as a ratio to ``TransformerConv(64, C, heads=H, edge_dim=D)`` measured in the same
round-robin.
Layers run with their defaults (input checks and the finite-output check on).

    python benchmarks/layers.py                   # full size
    python benchmarks/layers.py --nx 30 --reps 3  # quick look
    python benchmarks/layers.py --threads 1 --baseline /tmp/old/src  # before / after

``--baseline SRC`` imports ``garmentgnn.nn`` a second time from another source tree (e.g.
``git archive <commit> src | tar -x -C /tmp/old``) and times its layers beside these, as
``name@label`` rows with the same weights; ``max_abs_diff`` in the JSON is the largest
forward difference between the two versions of a layer.

Writes ``layers.json`` and ``layers.md`` into a cache folder (``--out`` elsewhere); with
``--commit`` into the committed ``docs/results/benchmarks/``, and it replaces the table between
the ``<!-- bench:layers -->`` markers in ``docs/layers.md``.
"""
from __future__ import annotations

import importlib
import itertools
import json
import os
import platform
import re
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, Optional

import torch
import torch_geometric
import torch_geometric.typing
from torch_geometric.nn import GATv2Conv, TransformerConv

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, existing_dir, int_at_least, output_path)
from garmentgnn.geometry import edge_features, faces_to_edge_index, grid_mesh
from garmentgnn.nn import LAYERS, make_layer

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "docs" / "results" / "benchmarks"
DOCS = HERE.parent / "docs" / "layers.md"
ANCHOR = "TransformerConv"
CONFIGS = [(4, 16), (1, 64), (4, 64)]
MARK = "<!-- bench:layers -->"


def mesh(nx: int, width: int, edge_dim: int):
    pos, faces = grid_mesh(nx, nx)
    pos = pos + 0.002 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(0))
    ei = faces_to_edge_index(faces, pos.size(0))
    gen = torch.Generator().manual_seed(1)
    geo = edge_features(pos, ei)  # length and direction, repeated up to edge_dim
    e = geo.repeat(1, -(-edge_dim // geo.size(1)))[:, :edge_dim]
    e = e + 0.01 * torch.randn(e.shape, generator=gen)
    x = torch.randn(pos.size(0), width, generator=gen)
    perm = torch.randperm(ei.size(1), generator=gen)
    return x, {"sorted": (ei, e), "unsorted": (ei[:, perm], e[perm])}


def baseline_registry(src: Path) -> dict:
    """``LAYERS`` of the ``garmentgnn.nn`` found in source tree ``src``, imported beside
    the current one (its modules are swapped out of ``sys.modules`` again afterwards)."""
    def ours() -> Dict[str, object]:
        return {k: m for k, m in sys.modules.items()
                if k == "garmentgnn" or k.startswith("garmentgnn.")}

    saved = ours()
    for k in saved:
        del sys.modules[k]
    sys.path.insert(0, str(src))
    try:
        nn = importlib.import_module("garmentgnn.nn")
        registry, found = dict(nn.LAYERS), Path(nn.__file__).resolve().parents[2]
    finally:
        sys.path.remove(str(src))
        for k in ours():
            del sys.modules[k]
        sys.modules.update(saved)
    if found != src.resolve():
        raise ValueError(f"`--baseline`: {src} holds no garmentgnn package (expected "
                         f"{src}/garmentgnn/nn)")
    return registry


def build_layers(width: int, heads: int, channels: int, edge_dim: int, ours: list,
                 baseline: Optional[dict] = None, label: str = "base"):
    torch.manual_seed(0)
    layers = {ANCHOR: TransformerConv(width, channels, heads, edge_dim=edge_dim),
              "GATv2Conv": GATv2Conv(width, channels, heads, edge_dim=edge_dim,
                                     add_self_loops=False)}
    for name in ours:
        layers[name] = make_layer(name, width, channels, heads=heads, edge_dim=edge_dim)
        if baseline is not None:  # the same layer from the other source tree, same weights
            old = baseline[name](width, channels, heads=heads, edge_dim=edge_dim)
            old.load_state_dict(layers[name].state_dict())
            layers[f"{name}@{label}"] = old
    return layers


def time_round(layers: dict, x, ei, e, fwd: dict, fb: dict, record: bool,
               reverse: bool = False) -> None:
    """One timed call of every layer; ``reverse`` runs them in the opposite order (every
    other round), so that no layer always follows the same one."""
    for name in reversed(list(layers)) if reverse else list(layers):
        layer = layers[name]
        layer.eval()
        with torch.inference_mode():
            t0 = time.perf_counter()
            layer(x, ei, e)
            t1 = time.perf_counter()
        layer.train()
        layer.zero_grad(set_to_none=True)
        t2 = time.perf_counter()
        layer(x, ei, e).square().mean().backward()
        t3 = time.perf_counter()
        if record:
            fwd[name].append(t1 - t0)
            fb[name].append(t3 - t2)


def max_abs_diff(layers: dict, x, ei, e) -> Dict[str, float]:
    """Per ``name@label`` layer: the largest forward difference to ``name``."""
    out = {}
    with torch.inference_mode():
        for name, layer in layers.items():
            if "@" in name:
                ref = layers[name.split("@")[0]].eval()(x, ei, e)
                out[name] = float((layer.eval()(x, ei, e) - ref).abs().max())
    return out


def run(args) -> dict:
    load_before = os.getloadavg()[0]
    rows = []
    baseline = baseline_registry(Path(args.baseline)) if args.baseline else None
    for edge_dim, (heads, channels) in itertools.product(args.edge_dims, CONFIGS):
        x, graphs = mesh(args.nx, args.width, edge_dim)
        layers = build_layers(args.width, heads, channels, edge_dim, args.layers, baseline,
                              args.baseline_label)
        for order, (ei, e) in graphs.items():
            diffs = max_abs_diff(layers, x, ei, e)
            for threads in args.threads:
                torch.set_num_threads(threads)
                fwd = {k: [] for k in layers}
                fb = {k: [] for k in layers}
                for r in range(args.warmup + args.reps):
                    time_round(layers, x, ei, e, fwd, fb, r >= args.warmup, r % 2 == 1)
                f0, b0 = statistics.median(fwd[ANCHOR]), statistics.median(fb[ANCHOR])
                f0_min, b0_min = min(fwd[ANCHOR]), min(fb[ANCHOR])
                for name in layers:
                    f, b = statistics.median(fwd[name]), statistics.median(fb[name])
                    rows.append(dict(layer=name, edge_dim=edge_dim, heads=heads,
                                     channels=channels, order=order,
                                     threads=threads, fwd_ms=1e3 * f, fwd_bwd_ms=1e3 * b,
                                     fwd_ratio=f / f0, fwd_bwd_ratio=b / b0,
                                     fwd_min_ratio=min(fwd[name]) / f0_min,
                                     fwd_bwd_min_ratio=min(fb[name]) / b0_min,
                                     max_abs_diff=diffs.get(name)))
                sat = rows[-len(layers) + list(layers).index("sat")] if "sat" in layers else None
                if sat is not None:
                    print(f"[layers] D={edge_dim} {heads}x{channels} {order:8s} {threads}t: "
                          f"sat fwd "
                          f"{sat['fwd_ratio']:.2f}x ({sat['fwd_min_ratio']:.2f}x best)  fwd+bwd "
                          f"{sat['fwd_bwd_ratio']:.2f}x ({sat['fwd_bwd_min_ratio']:.2f}x best) TC",
                          flush=True)
    return dict(torch=torch.__version__, torch_geometric=torch_geometric.__version__,
                torch_scatter=torch_geometric.typing.WITH_TORCH_SCATTER,
                num_nodes=x.size(0), num_edges=graphs["sorted"][0].size(1), width=args.width,
                edge_dims=args.edge_dims, reps=args.reps, baseline=args.baseline,
                machine=dict(platform=platform.platform(), cpus=os.cpu_count(),
                             python=platform.python_version(),
                             load_average=[load_before, os.getloadavg()[0]]),
                rows=rows)


def markdown(res: dict) -> str:
    diffs = any(r.get("max_abs_diff") is not None for r in res["rows"])
    lines = [f"{res['num_nodes']} vertices, {res['num_edges']} directed edges, input width "
             f"{res['width']}; median of {res['reps']} interleaved "
             f"rounds; torch {res['torch']}, PyG {res['torch_geometric']}, torch-scatter "
             f"{'on' if res['torch_scatter'] else 'off'}; {res['machine']['cpus']} CPUs, load "
             "average {:.1f} at the start and {:.1f} at the end (other work on the machine "
             "adds noise, most to the 2-thread rows). ".format(*res["machine"]["load_average"]) +
             "Ratios are to `TransformerConv(64, C, heads=H, edge_dim=D)` in the same rounds: "
             "of the medians, and (in brackets) of the best times.",
             "",
             "| edge_dim | H x C | edges | threads | layer | fwd ms | fwd+bwd ms | fwd / TC | "
             "fwd+bwd / TC |" + (" max abs diff |" if diffs else ""),
             "|---:|---|---|---:|---|---:|---:|---:|---:|" + ("---:|" if diffs else "")]
    for r in res["rows"]:
        lines.append(f"| {r['edge_dim']} | {r['heads']}x{r['channels']} | {r['order']} | "
                     f"{r['threads']} | "
                     f"{r['layer']} | {r['fwd_ms']:.1f} | {r['fwd_bwd_ms']:.1f} | "
                     f"{r['fwd_ratio']:.2f} ({r['fwd_min_ratio']:.2f}) | "
                     f"{r['fwd_bwd_ratio']:.2f} ({r['fwd_bwd_min_ratio']:.2f}) |"
                     + (f" {r['max_abs_diff']:.1e} |" if r.get("max_abs_diff") is not None
                        else (" |" if diffs else "")))
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--nx", type=int_at_least(2), default=100,
                    help="mesh is nx x nx vertices (100 -> 10K)")
    ap.add_argument("--width", type=int_at_least(1), default=64, help="node feature width")
    ap.add_argument("--edge-dims", type=int_at_least(1), nargs="+", default=[4, 64],
                    action=Accumulate,
                    help="edge feature widths (4: the mesh's length and direction)")
    ap.add_argument("--reps", type=int_at_least(1), default=9,
                    help="timed repetitions (median kept)")
    ap.add_argument("--warmup", type=int_at_least(0), default=2,
                    help="untimed first repetitions")
    ap.add_argument("--threads", type=int_at_least(1), nargs="+", default=[1, 2],
                    action=Accumulate, help="torch thread counts")
    ap.add_argument("--layers", nargs="+", default=["sat"], choices=sorted(LAYERS),
                    action=Accumulate,
                    help="garmentgnn layers to time beside TransformerConv and GATv2Conv")
    ap.add_argument("--baseline", default=None, metavar="SRC", type=existing_dir,
                    help="source folder (holding garmentgnn/) of another version whose "
                         "layers are timed beside these, with the same weights")
    ap.add_argument("--baseline-label", default="base",
                    help="suffix of the other version's rows (name@label)")
    add_output_args(ap, RESULTS, "folder for layers.json and layers.md")
    ap.add_argument("--docs", default=None,
                    help=f"file whose table between the markers is replaced; default: none, "
                         f"{DOCS} with --commit")
    args = ap.parse_args(argv)
    for flag in ("edge_dims", "threads", "layers"):
        check_unique(ap, getattr(args, flag), "--" + flag.replace("_", "-"))
    if args.baseline is not None and not (Path(args.baseline) / "garmentgnn").is_dir():
        ap.error(f"--baseline {args.baseline}: no garmentgnn/ in it; name the src/ folder of "
                 f"the other version")
    if args.docs is not None and not Path(args.docs).is_file():
        ap.error(f"--docs {args.docs}: no such file")
    args.out = output_path(args, RESULTS)
    if args.docs is None and args.commit:
        args.docs = str(DOCS)

    res = run(args)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "layers.json").write_text(json.dumps(res, indent=2))
    md = markdown(res)
    (args.out / "layers.md").write_text("# Layer benchmark\n\n" + md)
    docs = Path(args.docs) if args.docs else None
    if docs is not None and docs.exists():
        text = docs.read_text()
        block = f"{MARK}\n{md}{MARK}"
        if text.count(MARK) == 2:
            text = re.sub(f"{MARK}.*{MARK}", lambda _: block, text, flags=re.S)
            docs.write_text(text)
    print(md)


if __name__ == "__main__":
    main()
