"""Model size against error and speed: GarTrans, DA-style and MGN-style each at half, the
default and double its width and depth, trained for the same wall time by the bench and
scored on the dataset's test split.

    # the study on the Blender `learn` dataset (docs/results/size_study): 9 runs of
    # 20 min, two 1-thread runs at a time on a local Ray cluster, about 2 h on 2 cores;
    # resumable (rerun the same command)
    python benchmarks/size_study.py --data ~/.cache/garmentgnn/datasets/learn-blender \\
        --out size_study --backend ray --workers 2 --threads 1 --minutes 20
    # one run after another here, each on the preset's threads (about 3 h on 2 cores)
    python benchmarks/size_study.py --data DATA --out size_study
    # a smoke test: the tiny preset's dataset, 3 epochs of at most 15 s each, on a local
    # Ray cluster of 2 CPUs (about 2.5 min on 2 cores)
    garmentgnn generate --preset tiny --engine torch --out tiny_data
    python benchmarks/size_study.py --data tiny_data --preset tiny --epochs 3 --minutes 0.25 \\
        --out size_smoke --backend ray --workers 2

Each size is a recipe written under ``OUT/recipes/`` (the method's packaged recipe with
its size settings, :func:`garmentgnn.bench.sweep.trial_recipe`): the width and depth are
the recipe's values, or the model's defaults where the recipe sets none, times the
factor (GarTrans: its ``width`` and ``depth`` arguments; DA-style: ``hidden`` and
``num_layers``; MGN-style: ``hidden`` and ``layers``).  The bench (the preset's learned
budget with ``--minutes`` for every run, one seed, no learning curves) trains and scores
them in ``OUT/bench/``, with LBS on the same test sequences.  Written:
``OUT/size_study.json``, ``.md`` (per run: parameters, training vertex-frames/s,
inference ms/frame, test E_dist, its ratio to LBS's and the paired Wilcoxon test against
the method's default size over the test sequences) and ``.png`` (test E_dist against
training time per vertex-frame and against inference time, the Pareto front of each).
"""
from __future__ import annotations

import dataclasses
import inspect
import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import yaml

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args,
                                  command_line, existing_dir, float_above, int_at_least,
                                  output_path)
from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn._plotting import pyplot
from garmentgnn.bench import methods, presets, runner, scoring
from garmentgnn.bench.curves import quiet_lightning
from garmentgnn.bench.dataset import prepare_dataset
from garmentgnn.bench.ray_backend import RayBackend
from garmentgnn.bench.sweep import trial_recipe
from garmentgnn.data.store import read_manifest
from garmentgnn.training import load_recipe
from garmentgnn.training.recipes import import_class, recipe_path

#: the sizes, as factors of the default width and depth
SIZES: Dict[str, float] = {"0.5x": 0.5, "1x": 1.0, "2x": 2.0}
DEFAULT = "1x"
#: method -> (its packaged recipe, the model settings that are its width and its depth;
#: ``None``: the model's ``width`` / ``depth`` factors themselves)
STUDIED: Dict[str, tuple] = {
    methods.FULL: (methods.RECIPES[methods.FULL], None, None),
    methods.DA: (methods.RECIPES[methods.DA], "hidden", "num_layers"),
    methods.MGN: (methods.RECIPES[methods.MGN], "hidden", "layers"),
}
MODEL = "model.init_args.model.init_args"
#: the plot's top: this times the lowest error (runs above it are drawn hollow there)
OFF_SCALE = 1.6
#: the committed results (``--commit``)
RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results" / "size_study"


def model_default(recipe: str, name: str) -> Any:
    """The recipe's value of the model setting ``name``, else the model's default."""
    model = yaml.safe_load(recipe_path(recipe).read_text())["model"]["init_args"]["model"]
    given = model.get("init_args") or {}
    if name in given:
        return given[name]
    return inspect.signature(import_class(model["class_path"])).parameters[name].default


def size_settings(method: str, factor: float) -> Dict[str, Any]:
    """The dotted settings that make ``method`` ``factor`` times its default size."""
    recipe, width, depth = STUDIED[method]
    if width is None:
        return {f"{MODEL}.width": factor, f"{MODEL}.depth": factor}
    return {f"{MODEL}.{width}": max(1, round(model_default(recipe, width) * factor)),
            f"{MODEL}.{depth}": max(1, round(model_default(recipe, depth) * factor))}


def write_recipes(out: Path, data: Path, budget) -> Dict[str, Dict[str, Any]]:
    """Every (method, size) recipe under ``out/recipes``: ``{path: {method, size,
    settings}}``."""
    runs = {}
    for method, (recipe, _, _) in STUDIED.items():
        for size, factor in SIZES.items():
            settings = size_settings(method, factor)
            path = out / "recipes" / f"{method.split(' ')[0].lower()}-{size}.yaml"
            text = trial_recipe(recipe, settings, data, 0, budget)
            if not path.exists() or path.read_text() != text:
                atomic_write_bytes(path, text.encode())
            runs[str(path)] = {"method": method, "size": size, "settings": settings}
    return runs


def study_preset(name: str, minutes: float, runs: Sequence[str],
                 epochs: Optional[int] = None, threads: Optional[int] = None
                 ) -> presets.Preset:
    """Preset ``name``'s learned part: ``runs`` for ``minutes`` each (at most ``epochs``;
    ``None``: the preset's) on ``threads`` threads each (``None``: the preset's), one seed,
    nothing else (no learning curves, stability suite or seed plan)."""
    p = presets.preset(name).learned_only()
    if threads is not None:
        p = dataclasses.replace(p, threads=threads)
    return dataclasses.replace(p, learned=dataclasses.replace(
        p.learned, methods=tuple(runs), minutes=minutes, seeds=1, stability_cases=(),
        epochs=p.learned.epochs if epochs is None else epochs,
        seed_methods=None, long_minutes=None, curve_every=None, equal_steps=None,
        val_sequences=None, train_sequences=None))


def parameters(recipe: str, data: Path) -> int:
    """The parameter count of the model ``recipe`` builds on the dataset ``data``."""
    with quiet_lightning():
        module = load_recipe(recipe, data={"root": str(data), "val_split": None}).module
    return sum(p.numel() for p in module.model.parameters())


def lbs_reference(records: List[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """LBS's test E_dist and inference time on the same test sequences (``None``: not
    scored)."""
    r = next((r for r in records if r["kind"] == "learned" and r["method"] == methods.LBS
              and r["status"] == "ok"), None)
    if r is None:
        return None
    return {"E_dist": r["metrics"]["E_dist"], "inference_ms_per_frame":
            r["timing"]["latency_ms"], "test_sequences": len(r.get("per_sequence", []))}


def rows(records: List[Dict[str, Any]], runs: Dict[str, Dict[str, Any]],
         mean_vertices: float, data: Path) -> List[Dict[str, Any]]:
    """One row per (method, size): the scores, the speeds and the paired Wilcoxon test of
    its per-sequence E_dist against the method's default size."""
    by = {r["method"]: r for r in records if r["kind"] == "learned"}
    per = {k: {s["sequence"]: s["metrics"]["E_dist"] for s in r.get("per_sequence", [])}
           for k, r in by.items() if r["status"] == "ok"}
    base = {runs[k]["method"]: k for k in runs if runs[k]["size"] == DEFAULT}
    out = []
    for path, run in runs.items():
        r = by.get(path)
        row = dict(run, recipe=path, status="not run" if r is None else r["status"])
        if r is not None and r["status"] == "ok":
            settings = r["config"]["data"]
            frames = r["steps"] * settings.get("batch_size", 1) * settings.get("chunk", 1)
            row.update(E_dist=r["metrics"]["E_dist"], train_seconds=r["train_seconds"],
                       steps=r["steps"], parameters=parameters(path, data),
                       # None: no optimizer step in the budget (MGN-style's first epoch
                       # gathers its input statistics)
                       train_vertex_frames_per_s=frames * mean_vertices / r["train_seconds"]
                       if frames else None,
                       inference_ms_per_frame=r["timing"]["latency_ms"],
                       test_sequences=len(per[path]))
            ref = base[run["method"]]
            if path != ref and ref in per and len(set(per[path]) & set(per[ref])) >= 2:
                row["wilcoxon_vs_default"] = scoring.wilcoxon(per[path], per[ref])
        elif r is not None:
            row["message"] = r.get("message")
        out.append(row)
    return out


def table(res: Dict[str, Any]) -> str:
    scored = {r["test_sequences"] for r in res["rows"] if "E_dist" in r}
    lbs = res.get("lbs")
    lines = ["# Model size study", "", f"`{res['command']}`", "",
             f"Dataset {res['dataset']['name']}: {' / '.join(map(str, sorted(scored)))} of "
             f"its {res['dataset']['sequences']['test']} test sequences (the preset's "
             f"sample); {res['minutes']} min of training per run on {res['threads']} "
             "thread(s); E_dist in cm on those sequences; x LBS: E_dist over LBS's on the "
             "same sequences; p: paired Wilcoxon over the sequences against the method's 1x "
             "(median difference, negative: this size lower).", "",
             "| method | size | parameters | training vertex-frames/s | inference ms/frame | "
             "test E_dist | x LBS | vs 1x (p, median diff) |",
             "|---|---|---|---|---|---|---|---|"]
    if lbs is not None:
        lines.append(f"| {methods.LBS} | | 0 | | {lbs['inference_ms_per_frame']:.3g} | "
                     f"{lbs['E_dist']:.4f} | 1 | |")
    for r in res["rows"]:
        if "E_dist" not in r:
            lines.append(f"| {r['method']} | {r['size']} | | | | {r['status']} | | |")
            continue
        ratio = "" if lbs is None else f"{r['E_dist'] / lbs['E_dist']:.3f}"
        w = r.get("wilcoxon_vs_default")
        vs = "—" if w is None else f"p={w['p']:.3g}, {w['median_diff']:+.3f}"
        speed = r["train_vertex_frames_per_s"]
        lines.append(f"| {r['method']} | {r['size']} | {r['parameters']:,} | "
                     f"{'no step' if speed is None else f'{speed:.3g}'} | "
                     f"{r['inference_ms_per_frame']:.3g} | {r['E_dist']:.4f} | {ratio} | "
                     f"{vs} |")
    return "\n".join(lines) + "\n"


def front(points: List[tuple]) -> List[tuple]:
    """The Pareto front of ``(x, y)`` points, both lower better, by ``x``."""
    best, out = float("inf"), []
    for x, y in sorted(points):
        if y < best:
            best = y
            out.append((x, y))
    return out


def plot(res: Dict[str, Any], path: Path) -> None:
    plt = pyplot()
    from matplotlib.ticker import NullFormatter  # noqa: PLC0415 (after the backend is set)
    ok = [r for r in res["rows"] if "E_dist" in r]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    xs = (("training time per vertex-frame (µs)",
           lambda r: 1e6 / r["train_vertex_frames_per_s"]
           if r["train_vertex_frames_per_s"] else None),
          ("inference time per frame (ms)", lambda r: r["inference_ms_per_frame"]))
    colours = dict(zip(STUDIED, ("tab:blue", "tab:orange", "tab:green")))
    marker = {"0.5x": "v", "1x": "o", "2x": "^"}
    # a run that diverged would squash the others: drawn hollow at the top, its value beside
    cap = OFF_SCALE * min(r["E_dist"] for r in ok) if ok else float("inf")
    for ax, (label, x) in zip(axes, xs):
        n_off = 0
        for r in (r for r in ok if x(r) is not None):
            off = r["E_dist"] > cap
            c = colours[r["method"]]
            ax.scatter(x(r), min(r["E_dist"], cap), marker=marker[r["size"]], s=60,
                       facecolors="none" if off else c, edgecolors=c,
                       label=f"{r['method']} {r['size']}")
            if off:
                ax.annotate(f"{r['E_dist']:.0f} cm", (x(r), cap), xytext=(-6, -12 * n_off - 12),
                            textcoords="offset points", fontsize=7, color=c, ha="right")
                n_off += 1
        f = front([(x(r), r["E_dist"]) for r in ok if x(r) is not None])
        if f:
            ax.step(*zip(*f), where="post", c="0.4", lw=1, ls="--", label="Pareto front")
        if res.get("lbs") is not None:
            ax.axhline(res["lbs"]["E_dist"], c="k", lw=1, ls=":", label=methods.LBS)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("test E_dist (cm)")
    legend: Dict[str, Any] = {}  # every point once (a run without a step is on one panel)
    for ax in axes:
        legend.update(zip(*reversed(ax.get_legend_handles_labels())))
    fig.legend(list(legend.values()), list(legend), loc="center right", fontsize=7)
    fig.suptitle(f"Model size: {res['dataset']['name']}, {res['minutes']} min of training "
                 f"each on {res['threads']} thread(s); hollow: above the scale, its value "
                 "beside it")
    fig.tight_layout(rect=(0, 0, 0.8, 0.95))
    buf = path.with_suffix(".tmp.png")
    fig.savefig(buf, dpi=120)
    plt.close(fig)
    buf.replace(path)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = ArgumentParser(description=__doc__.splitlines()[0], formatter_class=HelpFormatter)
    ap.add_argument("--data", required=True, type=existing_dir,
                    help="a generated dataset (the study: the Blender `learn` dataset)")
    ap.add_argument("--preset", choices=presets.PRESET_NAMES, default="learn",
                    help="the bench preset whose learned budget every run gets")
    ap.add_argument("--minutes", type=float_above(0), default=20.0,
                    help="training wall time of every run")
    ap.add_argument("--epochs", type=int_at_least(1), default=None,
                    help="the most epochs of every run (default: the preset's)")
    ap.add_argument("--threads", type=int_at_least(1), default=None,
                    help="torch threads (and Ray CPUs) of every run (default: the "
                         "preset's)")
    ap.add_argument("--backend", choices=("local", "ray"), default="local",
                    help="the runs one after another here, or each a Ray task")
    ap.add_argument("--workers", type=int_at_least(1), default=None,
                    help="with --backend ray: the local cluster's CPUs")
    ap.add_argument("--address", default=None, help="with --backend ray: HOST:PORT")
    add_output_args(ap, RESULTS, "the study's folder (rerun to resume)")
    args = ap.parse_args(argv)
    out = output_path(args, RESULTS)
    budget = presets.preset(args.preset).learned
    if args.epochs is not None:
        budget = dataclasses.replace(budget, epochs=args.epochs)
    data = prepare_dataset(args.data)
    runs = write_recipes(out, data.root, budget)
    p = study_preset(args.preset, args.minutes, [*runs, methods.LBS], args.epochs,
                     args.threads)
    backend = RayBackend(args.workers, args.address) if args.backend == "ray" else None
    summary = runner.run(p, out / "bench",
                         seeds=1, data=data.root, progress=False, backend=backend,
                         command=command_line("benchmarks/size_study.py", argv))
    print(summary)
    records = json.loads((out / "bench" / "results.json").read_text())["records"]
    train = [r for r in read_manifest(data.root)["items"]
             if r["status"] == "ok" and r["split"] == "train"]
    res = {"command": command_line("benchmarks/size_study.py", argv),
           "dataset": data.to_json(), "minutes": args.minutes, "preset": args.preset,
           "threads": p.threads,
           "sizes": SIZES, "mean_train_vertices": sum(r["num_vertices"] for r in train)
           / len(train)}
    res["rows"] = rows(records, runs, res["mean_train_vertices"], data.root)
    res["lbs"] = lbs_reference(records)
    atomic_write_json(out / "size_study.json", res)
    atomic_write_bytes(out / "size_study.md", table(res).encode())
    plot(res, out / "size_study.png")
    print(f"table: {out / 'size_study.md'}; plot: {out / 'size_study.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
