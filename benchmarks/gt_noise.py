"""The ground truth's noise floor: each engine simulates a few sequences again with its
input moved by a rounding error, and the distance to the unperturbed run is measured per
frame (:mod:`garmentgnn.bench.noise_floor`).

Per sequence: the unperturbed run, a plain rerun (must be 0: the engines are
deterministic), then the rest garment's vertices and, separately, the body motion's root
translation moved by each ``--scales`` distance (default 1e-7 and 1e-4 m) in random
directions.  Blender runs ``small`` sequences (fast; ``--preset`` another, e.g.
``learn``), the torch simulator ``tiny`` ones (slow).  Each run keeps which frames are
valid ground truth (:mod:`garmentgnn.data.validity`: converged, the garment at most 1 cm
inside the body), and the floor is measured on the frames valid in both runs, as every
score is.  Writes JSON, markdown and a PNG of divergence against frame into a cache
folder; ``--commit`` writes the committed ``docs/results/benchmarks/gt_noise.{json,md,png}``
(``gt_noise_<preset>`` for another Blender preset) instead, which the bench report of a
dataset of that preset reads::

    OMP_NUM_THREADS=1 python benchmarks/gt_noise.py                      # both engines
    OMP_NUM_THREADS=1 python benchmarks/gt_noise.py --engines torch --sequences 1
    OMP_NUM_THREADS=1 python benchmarks/gt_noise.py --commit
    OMP_NUM_THREADS=1 python benchmarks/gt_noise.py --engines blender --preset learn \
        --sequences 12 --scales 1e-7 --commit
"""
from __future__ import annotations

import platform
import random
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from garmentgnn._argparse import (Accumulate, ArgumentParser, HelpFormatter, add_output_args,
                                  check_unique, float_above, int_at_least, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.bench import noise_floor as nf
from garmentgnn.bench.tables import save_figure, table
from garmentgnn.data import preset
from garmentgnn.data.presets import PRESETS as DATA_PRESETS
from garmentgnn.data.presets import build_inputs
from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn.data.store import code_version
from garmentgnn.data.validity import valid_frames
from garmentgnn.data.worker import default_simulate, item_settings

HERE = Path(__file__).resolve().parent
COMMITTED = HERE.parent / "docs" / "results" / "benchmarks" / "gt_noise"
PRESETS = {"blender": "small", "torch": "tiny"}


def pick(engine: str, n: int, name: Optional[str] = None):
    """``n`` items of the engine's preset (``name``: another), spread over garment kinds
    (the first of each kind in spec order, then the next ones), each with its ``preset``."""
    name = name or PRESETS[engine]
    items = [dict(it, preset=name) for it in preset(name, engine=engine).items()]
    by_kind = {}
    for it in items:
        by_kind.setdefault(it["garment"]["kind"], []).append(it)
    out, i = [], 0
    while len(out) < n and any(i < len(v) for v in by_kind.values()):
        out += [v[i] for v in by_kind.values() if i < len(v)]
        i += 1
    return out[:n]


def simulate(item, garment, body, motion, material):
    """The item's engine at the item's settings, seeded as the dataset worker seeds it."""
    seed = item["seed"]
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)
    t0 = time.perf_counter()
    res = default_simulate(item.get("engine", "torch"))(garment, body, motion, material,
                                                        settings=item_settings(item),
                                                        progress=None)
    if not getattr(res, "ok", True):
        raise RuntimeError(getattr(res, "message", "not ok"))
    conv = getattr(res, "converged", None)
    pos = torch.as_tensor(res.positions).detach().double()
    pen = getattr(res, "penetration", None)
    valid = valid_frames(None if conv is None else torch.as_tensor(conv).numpy(),
                         None if pen is None else torch.as_tensor(pen).numpy(), pos.shape[0])
    return (pos, time.perf_counter() - t0,
            None if conv is None else int((~torch.as_tensor(conv).bool()).sum()), valid)


def runs_of(engine: str, item, scales, log=print):
    """The run records of one item: the rerun, then every (input, scale)."""
    garment, body, motion, material = build_inputs(item)
    base, secs, nonconv, base_valid = simulate(item, garment, body, motion, material)
    log(f"{engine:7s} {item['id']}: unperturbed {secs:.1f} s ({base.shape[0]} frames, "
        f"{base.shape[1]} vertices, {nonconv} non-converged, "
        f"{int((~base_valid).sum())} not valid ground truth)")
    cases = [("repeat", 0.0)] + [(w, s) for w in ("garment", "body") for s in scales]
    out = []
    for k, (what, scale) in enumerate(cases):
        g, m = garment, motion
        if what == "garment":
            g = nf.perturbed_garment(garment, scale, seed=1000 + k)
        elif what == "body":
            m = nf.perturbed_motion(motion, scale, seed=1000 + k)
        rec = {"engine": engine, "preset": item["preset"], "sequence": item["id"],
               "what": what, "scale_m": scale, "frames": int(base.shape[0]),
               "vertices": int(base.shape[1])}
        try:
            pos, secs, nc, valid = simulate(item, g, body, m, material)
            mean, mx = nf.divergence(pos, base)
            rec.update(status="ok", seconds=round(secs, 2), mean_cm=mean, max_cm=mx,
                       nonconverged_frames=nc, base_nonconverged_frames=nonconv,
                       valid=(valid & base_valid).tolist())
            log(f"{engine:7s} {item['id']}: {what:7s} {scale:g} m -> mean "
                f"{sum(mean) / len(mean):.4f} cm, max {max(mx):.3f} cm ({secs:.1f} s)")
        except Exception as e:  # a run that fails is a result too (recorded, not fatal)
            rec.update(status="failed", message=f"{type(e).__name__}: {e}")
            log(f"{engine:7s} {item['id']}: {what} {scale:g} m FAILED {e}")
        out.append(rec)
    return out


def markdown(runs, floor, header, name="gt_noise.json"):
    rows = []
    for r in runs:
        if r["status"] != "ok":
            rows.append([nf.ENGINE_NAMES[r["engine"]], r["sequence"], r["what"],
                         f"{r['scale_m']:g}", "-", "-", "-", "failed: " + r["message"][:80]])
            continue
        per = r["max_cm"]
        marks = sorted({0, len(per) // 4, len(per) // 2, 3 * len(per) // 4, len(per) - 1})
        rows.append([nf.ENGINE_NAMES[r["engine"]], r["sequence"], r["what"],
                     f"{r['scale_m']:g}", f"{sum(r['mean_cm']) / len(r['mean_cm']):.4f}",
                     f"{max(per):.3f}",
                     " / ".join(f"{per[i]:.2f}" for i in marks) +
                     f" (frames {', '.join(map(str, marks))})", f"{r['seconds']:.1f}"])
    lines = [header, "", "Per run: mean over frames of the mean per-vertex distance to the "
             "unperturbed run, the largest per-vertex distance over the sequence, and that "
             "largest distance at a few frames (cm).", ""]
    lines += table(["engine", "sequence", "perturbed", "by (m)", "mean (cm)", "max (cm)",
                    "max at frames (cm)", "s"], rows)
    lines += [""] + nf.markdown({"path": name, "floor": floor})[2:]
    return "\n".join(lines) + "\n"


def plot(runs, path):
    """Per frame, the mean over sequences of the mean distance (solid) and the largest
    distance over sequences (dashed), one panel per engine, a colour per perturbation;
    log distance axis."""
    plt = pyplot()

    engines = sorted({r["engine"] for r in runs})
    fig, axes = plt.subplots(1, len(engines), figsize=(5.4 * len(engines) + 2.4, 4.4),
                             squeeze=False)
    keys = sorted({(r["what"], r["scale_m"]) for r in runs if r["what"] != "repeat"})
    colours = {k: plt.get_cmap("tab10")(i) for i, k in enumerate(keys)}
    for ax, engine in zip(axes[0], engines):
        for key in keys:
            rs = [r for r in runs if r["engine"] == engine and (r["what"], r["scale_m"]) == key
                  and r["status"] == "ok"]
            if not rs:
                continue
            n = min(len(r["mean_cm"]) for r in rs)
            mean = np.mean([r["mean_cm"][:n] for r in rs], axis=0)
            mx = np.max([r["max_cm"][:n] for r in rs], axis=0)
            lab = f"{key[0]} ±{key[1]:g} m"
            ax.plot(range(n), np.maximum(mean, 1e-7), color=colours[key], lw=1.5,
                    label=lab + " (mean)")
            ax.plot(range(n), np.maximum(mx, 1e-7), color=colours[key], lw=1.0, ls="--",
                    alpha=0.8, label=lab + " (max)")
        seqs = len({r["sequence"] for r in runs if r["engine"] == engine})
        ax.set_yscale("log")
        ax.set_xlabel("frame")
        ax.set_ylabel("distance to the unperturbed run (cm, log)")
        name = next(r["preset"] for r in runs if r["engine"] == engine)
        ax.set_title(f"{nf.ENGINE_NAMES[engine]} ({name}, {seqs} sequence"
                     f"{'s' if seqs > 1 else ''})")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(*axes[0][0].get_legend_handles_labels(), fontsize=7, loc="upper left",
                       bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    fig.suptitle("Divergence from a perturbed input per frame: mean over vertices and "
                 "sequences (solid), largest (dashed)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.splitlines()[0],
                        formatter_class=HelpFormatter)
    ap.add_argument("--engines", nargs="+", choices=tuple(PRESETS), default=list(PRESETS),
                    action=Accumulate,
                    help="the engines to perturb and simulate again")
    ap.add_argument("--sequences", type=int_at_least(1), default=None,
                    help="sequences per engine (default 6 for Blender, 2 for torch)")
    ap.add_argument("--scales", type=float_above(0.0), nargs="+", default=[1e-7, 1e-4],
                    action=Accumulate,
                    help="perturbation distances (m)")
    ap.add_argument("--preset", default=PRESETS["blender"],
                    choices=DATA_PRESETS,
                    help="the dataset preset whose sequences Blender simulates again")
    add_output_args(ap, COMMITTED, "writes OUT.json, OUT.md and OUT.png (with another "
                    "--preset, the committed name is gt_noise_<preset>)")
    a = ap.parse_args(argv)
    check_unique(ap, a.engines, "--engines")
    check_unique(ap, a.scales, "--scales")
    own = COMMITTED if a.preset == PRESETS["blender"] else \
        COMMITTED.with_name(f"gt_noise_{a.preset}")
    out = output_path(a, own)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    runs = []
    for engine in a.engines:
        n = a.sequences or (6 if engine == "blender" else 2)
        for item in pick(engine, n, a.preset if engine == "blender" else None):
            runs += runs_of(engine, item, a.scales)
    floor = nf.summarize(runs)
    command = "python benchmarks/gt_noise.py " + " ".join(argv if argv is not None else
                                                           __import__("sys").argv[1:])
    meta = {"command": command.strip(), "machine": platform.processor() or platform.machine(),
            "torch_threads": torch.get_num_threads(), "code": code_version(),
            "seconds": round(time.perf_counter() - t0, 1)}
    header = (f"`{meta['command']}`: {len(runs)} runs in {meta['seconds']:.0f} s, "
              f"{meta['torch_threads']} torch thread(s), {platform.machine()}.")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out.with_suffix(".json"), {"meta": meta, "floor": floor, "runs": runs})
    text = markdown(runs, floor, header, out.with_suffix(".json").name)
    atomic_write_bytes(out.with_suffix(".md"), text.encode())
    plot(runs, out.with_suffix(".png"))
    print(text)
    print(f"wrote {out}.json, .md, .png")


if __name__ == "__main__":
    main()
