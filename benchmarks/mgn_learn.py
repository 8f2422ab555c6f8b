"""The MGN-style learned simulator on a generated dataset: learning curves, rollout scores
against LBS and the frame-parallel methods, error per frame, and the sweeps' table.

    # one-step and 60-frame rollout error of every step checkpoint of a run, on train and
    # validation sequences
    python benchmarks/mgn_learn.py curves --run RUN --data DATA --out OUT [--sequences 8]
    # every test sequence rolled out (from the first two simulated frames and from a
    # settled drape) beside LBS and other checkpoints, paired Wilcoxon tests, per group
    python benchmarks/mgn_learn.py score --mgn CKPT --data DATA --out OUT \\
        [--other "GarTrans (SAT)=CKPT" ...] [--split test] [--on-ensemble]
    # the sweep runs' last validation (rollout E_dist) and training one-step error
    python benchmarks/mgn_learn.py sweep --runs NAME=RUN ... --out OUT
    # a branch of a run from one of its checkpoints with pushforward rollouts (the
    # learning rate continues the run's decay from that step)
    python benchmarks/mgn_learn.py branch --from CKPT --data DATA --out OUT --rollout 3 \
        --steps N
    # ms per training step against width, depth and batch on one and two threads, every
    # size timed interleaved with the others (side by side)
    python benchmarks/mgn_learn.py steptime --data DATA --out OUT
    # the stability suite (stiff, extreme pose, 5x speed, 1000 frames, degenerate faces)
    # on the first test sequence, rolled out from the LBS garment of its first two frames
    python benchmarks/mgn_learn.py stability --mgn CKPT --data DATA --out OUT

Every method is scored on the same frames: the valid ground-truth frames from frame 2 on
(the rollout is given frames 0 and 1).  Outputs: ``OUT/<command>.json``, ``.md`` and
``.png``.  ``score`` on a dataset with an ensemble ground truth (``garmentgnn generate
--ensemble K``) also scores the ensemble's sequences against it (``score.json``'s
``ensemble``, a section of ``score.md``, ``ensemble.png``); ``--on-ensemble`` scores only
those sequences.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import torch

from garmentgnn.data import SequenceChunks
from garmentgnn.data.store import dataset_dir, read_manifest
from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args,
                                  int_at_least, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.bench import ensemble_report
from garmentgnn.bench import stability as stab
from garmentgnn.bench.model_inputs import BenchChunks
from garmentgnn.bench.scoring import score, score_ensemble, stratified
from garmentgnn.data.ensemble import MEMBERS, load_ensemble
from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.training import RolloutModule
from garmentgnn.training.rollout import START_STATES
from garmentgnn.training.base import GarmentModule
from garmentgnn.training.lightning_cli import method_name
from garmentgnn.training.checkpoints import load_checkpoint

#: the folder of this script and its parts (``mgn_parts``): on ``sys.path`` when it is
#: imported from elsewhere (tests)
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.append(str(HERE))
from mgn_parts.report import (GIVEN, combined, merge_scores, read_scores,  # noqa: E402
                               write_score)
from mgn_parts.runs import run_branch, run_steptime, run_sweep  # noqa: E402



class Scored(SequenceChunks):
    """Whole sequences whose first :data:`GIVEN` frames are not scored."""

    def valid(self, idx: int) -> torch.Tensor:
        v = super().valid(idx).clone()
        v[:GIVEN] = False
        return v


def sequences(module: GarmentModule, data: str, split: str,
              ids: Optional[Sequence[str]] = None) -> Scored:
    """``split``'s whole sequences as ``module`` reads them (its pose history and Nyström
    width)."""
    return Scored(data, split, chunk=10 ** 6, cache_size=2, static_cache=2, ids=ids,
                  **read_settings(module))


def read_settings(module: GarmentModule) -> Dict[str, int]:
    """The pose history and Nyström sizes ``module`` was trained to read: its
    checkpoint's data settings (the data module's defaults where it has none)."""
    trained = getattr(module, "trained_data", None) or {}
    return {"history": trained.get("history", HISTORY),
            "nystrom_dim": trained.get("nystrom_dim", NYSTROM_DIM),
            "num_landmarks": trained.get("num_landmarks", NUM_LANDMARKS)}


def per_frame(pred: torch.Tensor, item) -> List[Optional[float]]:
    """E_dist (cm) of each frame (``None`` where the frame is not scored)."""
    d = (pred - item.gt).norm(dim=-1).mean(-1) * 100.0
    return [float(x) for x in d]


#: what a flag's checkpoint must hold: the method's name, and the test of its module
KINDS = {"mgn": ("MGN-style", lambda m: m.table_name == "MGN-style"),
         "gartrans": ("GarTrans", lambda m: m.family == "gartrans"),
         "da": ("DA-style", lambda m: m.table_name == "DA-style")}


def checkpoint_of(path: str, flag: str, kind: Optional[str] = None) -> GarmentModule:
    """The trained method of checkpoint ``path`` (given as ``flag``); one ``error:``
    line naming the flag (exit status 2) where the file cannot be read or holds
    another method than ``kind`` (:data:`KINDS`), before any output is made."""
    try:
        m = load_checkpoint(path)
    except (OSError, ValueError, TypeError) as e:
        print(f"error: {flag} {path}: {e}", file=sys.stderr)
        sys.exit(2)
    if kind is not None and not KINDS[kind][1](m):
        print(f"error: {flag} {path}: a checkpoint of {method_name(m)}, not of "
              f"{KINDS[kind][0]}; give {flag} a checkpoint of that method", file=sys.stderr)
        sys.exit(2)
    return m


def score_methods(args: argparse.Namespace):
    """``(methods, modules)`` that ``score`` rolls out, every checkpoint read and
    checked (:func:`checkpoint_of`); kept on ``args`` (the command reads them before it
    chooses its output folder)."""
    if getattr(args, "scored", None) is not None:
        return args.scored
    if not args.mgn and not args.other and not args.merge:
        print("error: --mgn: score needs a model to roll out: give --mgn CKPT (and/or "
              "--other NAME=CKPT), or --merge SCORE.json ... alone", file=sys.stderr)
        sys.exit(2)
    methods: Dict[str, Callable[[Any], torch.Tensor]] = {}
    modules: Dict[str, GarmentModule] = {}
    others = dict(spec.partition("=")[::2] for spec in args.other)
    for start in args.starts:
        if start not in START_STATES and start not in others:
            print(f"error: --starts {start}: expected one of {', '.join(START_STATES)} or "
                  f"the NAME of an --other NAME=CKPT", file=sys.stderr)
            sys.exit(2)
    # a start named after an --other method: that method's frames 0 and 1 of the sequence
    # (scored before the rollouts that start from them)
    args.start_frames = {s: {} for s in args.starts if s not in START_STATES}
    mgn = checkpoint_of(args.mgn, "--mgn", "mgn") if args.mgn else None

    def rollout(m: RolloutModule, s: str) -> Callable[[Any], torch.Tensor]:
        if s in args.start_frames:  # the other method's frames of this sequence
            return lambda item: m.rollout(item, start=args.start_frames[s][item.seq_id])
        return lambda item: m.rollout(item, start=s)
    for start in args.starts if mgn is not None else ():
        name = f"{args.mgn_name} ({start})"
        modules[name] = mgn
        methods[name] = rollout(mgn, start)
    if mgn is not None and args.project:  # the same model with the projection after each step
        sweeps, margin = int(args.project[0]), float(args.project[1])
        projected = load_checkpoint(args.mgn)
        projected.model.strain_limit, projected.model.collision_projection = sweeps, margin
        projected.model.inextensible = args.inextensible
        how = f"inextensible {args.inextensible}" if args.inextensible else "projected"
        for start in args.starts:
            name = f"{args.mgn_name} ({start}, {how})"
            modules[name] = projected
            methods[name] = rollout(projected, start)
    for spec in args.other:
        name, eq, path = spec.partition("=")
        if not eq or not name or not path:
            print(f"error: --other {spec}: expected NAME=CKPT", file=sys.stderr)
            sys.exit(2)
        m = checkpoint_of(path, "--other")
        modules[name] = m
        methods[name] = m.predict_sequence  # from what a user has, as the bench scores
    # the methods a start is named after first
    order = sorted(methods, key=lambda n: n not in args.start_frames)
    methods = {n: methods[n] for n in order}
    args.scored = methods, modules
    return args.scored


def run_score(args: argparse.Namespace) -> None:
    earlier = read_scores(args.merge, args.merge_names)  # checked before any work
    methods, modules = score_methods(args)
    out = Path(args.out)  # made once every checkpoint has been read
    out.mkdir(parents=True, exist_ok=True)
    if not methods:  # --merge alone: the report of those scores, nothing rolled out
        print(write_score(combined(earlier, args.merge_names), out))
        return
    manifest = read_manifest(args.data)
    ensemble = args.ensemble
    ids = sorted(ensemble["sequences"]) if args.on_ensemble else None
    if args.sequences and ids is None:
        ids = stratified([r for r in manifest["items"]
                          if r["split"] == args.split and r["status"] == "ok"], args.sequences)
    results: Dict[str, Any] = {"data": str(args.data),
                               "content_sha256": manifest.get("content_sha256"),
                               "split": args.split, "methods": {}, "per_frame": {},
                               "seconds": {}}
    if ensemble is not None:
        results["ensemble"] = {"members": ensemble["members"], "dataset": ensemble["dataset"],
                               "incomplete": ensemble["incomplete"], "methods": {}}
    lbs_done = False
    for name, predict in methods.items():
        test = sequences(modules[name], args.data, args.split, ids)
        frames: Dict[str, List[float]] = {}
        t0 = time.perf_counter()

        kept: Dict[str, torch.Tensor] = {}

        def pred(i, item, predict=predict, frames=frames, kept=kept, name=name):
            p = predict(item)
            frames[item.seq_id] = per_frame(p, item)
            if name in args.start_frames:  # a start of the MGN-style rollouts
                args.start_frames[name][item.seq_id] = p[:2].detach().clone()
            if ensemble is not None and item.seq_id in ensemble["sequences"]:
                kept[item.seq_id] = p.detach().cpu()
            return p
        results["methods"][name] = score(pred, test)
        if ensemble is not None:
            results["ensemble"]["methods"][name] = score_ensemble(
                lambda i, item, kept=kept: kept[item.seq_id], test, ensemble)
        results["seconds"][name] = time.perf_counter() - t0
        results["per_frame"][name] = frames
        print(f"{name}: {len(test)} sequences in {results['seconds'][name]:.0f} s",
              flush=True)
        if not lbs_done:
            lbs_frames: Dict[str, List[float]] = {}

            def lbs(i, item):
                p = item.skinned()
                lbs_frames[item.seq_id] = per_frame(p, item)
                return p
            results["methods"]["LBS only"] = score(lbs, test)
            results["per_frame"]["LBS only"] = lbs_frames
            if ensemble is not None:
                results["ensemble"]["methods"]["LBS only"] = score_ensemble(
                    lambda i, item: item.skinned(), test, ensemble)
            lbs_done = True
    results["valid"] = {s["sequence"]: [bool(v) for v in test.valid(i)]
                        for i, s in enumerate(results["methods"]["LBS only"])} \
        if len(results["methods"]["LBS only"]) == len(test) else {}
    merge_scores(results, earlier, args.merge_names)
    extra = ""
    if ensemble is not None:
        by_method = results["ensemble"]["methods"]
        results["ensemble"]["summary"] = ensemble_report.results(by_method)
        png = ensemble_report.plot(by_method, out / "ensemble.png",
                                   f"{len(by_method['LBS only'])} {args.split} sequences "
                                   f"against the ensemble of dataset "
                                   f"{str(results['content_sha256'])[:8]}")
        extra = "\n" + "\n".join(ensemble_report.markdown(
            by_method, png.name if png else None, "##", ensemble["members"])) + "\n"
    print(write_score(results, out, extra))


def read_ensemble(data: str, required: bool) -> Optional[Dict[str, Any]]:
    """The ensemble ground truth of ``data`` (``None`` without one); one ``error:`` line
    (exit status 2) where it is not this dataset's or not an ensemble, or where
    ``required`` (``--on-ensemble``) and there is none."""
    try:
        ensemble = load_ensemble(data)
    except (OSError, ValueError) as e:
        sys.exit(f"error: --data {data}: {str(e).split(': ', 1)[-1]}")
    if required and not (ensemble and ensemble["sequences"]):
        sys.exit(f"error: --on-ensemble: {data} has no ensemble ground truth; make one with "
                 f"`garmentgnn generate --ensemble {MEMBERS} --out {data}`")
    return ensemble


def one_step_and_rollout(module: RolloutModule, test: Scored) -> Dict[str, float]:
    """Mean over ``test``'s sequences of the one-step error (each frame predicted from the
    two simulated frames before it) and the rollout E_dist (from frames 0 and 1), cm, on
    the scored frames."""
    model = module.model
    one, roll, n = 0.0, 0.0, 0
    with torch.no_grad():
        for i in range(len(test)):
            item = test[i]
            keep = test.valid(i)
            if not bool(keep.any()):
                continue
            m = model.scene_motion(item)
            gt = item.gt
            steps = [gt[0], gt[1]] + [model.step(item, m, t, gt[t - 2], gt[t - 1])
                                      for t in range(2, gt.shape[0])]
            d1 = (torch.stack(steps) - gt).norm(dim=-1).mean(-1)[keep].mean()
            roll_out = model.rollout(item, gt[0], gt[1], m)  # the same motion, once
            d2 = (roll_out - gt).norm(dim=-1).mean(-1)[keep].mean()
            one, roll, n = one + float(d1), roll + float(d2), n + 1
    return {"one_step_cm": 100 * one / n, "rollout_cm": 100 * roll / n, "sequences": n}


def run_curves(args: argparse.Namespace) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpts = sorted((p for p in Path(args.run).rglob("*step=*.ckpt")
                    if not p.name.startswith(("best", "latest"))),
                   key=lambda p: int(p.stem.split("=")[-1].split("-")[0]))
    if not ckpts:
        sys.exit(f"error: --run: no step checkpoints (*step=N.ckpt) under {args.run}")
    manifest = read_manifest(args.data)
    picks = {}
    for split in ("train", "val"):
        recs = [r for r in manifest["items"] if r["split"] == split and r["status"] == "ok"]
        picks[split] = sorted(r["id"] for r in recs)[::max(1, len(recs) // args.sequences)][
            :args.sequences] if split == "train" else stratified(recs, args.sequences)
    path = out / "curves.json"
    curves = json.loads(path.read_text()) if path.exists() else {"points": []}
    done = {p["step"] for p in curves["points"]}
    lbs: Dict[str, float] = curves.get("lbs", {})
    for ck in ckpts:
        step = int(ck.stem.split("=")[-1].split("-")[0]) + args.step_offset
        if step in done:
            continue
        module = load_checkpoint(str(ck))
        point: Dict[str, Any] = {"step": step}
        for split, ids in picks.items():
            test = sequences(module, args.data, split, ids)
            point[split] = one_step_and_rollout(module, test)
            if split not in lbs:
                tot = 0.0
                for i in range(len(test)):
                    item, keep = test[i], test.valid(i)
                    tot += float((item.skinned() - item.gt).norm(dim=-1).mean(-1)[keep].mean())
                lbs[split] = 100 * tot / len(test)
        curves["points"].append(point)
        curves["points"].sort(key=lambda p: p["step"])
        curves.update(lbs=lbs, picks=picks, content_sha256=manifest.get("content_sha256"))
        path.write_text(json.dumps(curves, indent=1))
        print(json.dumps(point), flush=True)
    plot_curves(curves, out / "curves.png")


def plot_curves(curves: Dict[str, Any], path: Path) -> None:
    plt = pyplot()
    pts = curves["points"]
    steps = [p["step"] for p in pts]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, title in ((axes[0], "one_step_cm", "one-step error"),
                           (axes[1], "rollout_cm", "rollout E_dist (from frames 0, 1)")):
        for split, style in (("train", "-"), ("val", "--")):
            ax.plot(steps, [p[split][key] for p in pts], style, marker="o", ms=3,
                    label=f"{split}")
            if key == "rollout_cm":
                ax.axhline(curves["lbs"][split], ls=style, color="grey", lw=0.8,
                           label=f"LBS ({split})")
        ax.set_xlabel("optimizer step")
        ax.set_ylabel("cm")
        ax.set_title(title)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -- stability ----------------------------------------------------------------------------------
def run_stability(args: argparse.Namespace) -> None:
    mgn = getattr(args, "mgn_module", None) or checkpoint_of(args.mgn, "--mgn", "mgn")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    test = SequenceChunks(args.data, "test", chunk=10 ** 6, **read_settings(mgn))
    base = test.records[0]
    item = {k: base[k] for k in ("garment", "body", "motion", "material", "settings")}

    def inputs(seq):
        ds = BenchChunks(seq, **read_settings(mgn))
        return ds[0]

    predictors = {"MGN-style (from LBS)": lambda seq: mgn.rollout(inputs(seq), start="lbs"),
                  "LBS only": lambda seq: inputs(seq).skinned()}
    records = []
    for case in args.cases:
        for name, predict in predictors.items():
            def run(seq, predict=predict):
                with torch.no_grad():
                    return predict(seq)
            rec = stab.run_case(case, dict(item, name=case), int(base["seed"]), run, name)
            rec["sequence"] = base["id"]
            records.append(rec)
            m = rec.get("metrics", {})
            print(f"{case:15s} {name:22s} {rec['verdict']:9s} {rec.get('reason', '')}  "
                  f"max speed {m.get('max_speed', float('nan')):.3g} m/s  "
                  f"growth {m.get('energy_growth', float('nan')):.3g}  "
                  f"penetration {m.get('max_penetration_m', float('nan')):.3g} m", flush=True)
    (out / "stability.json").write_text(json.dumps(records, indent=1, default=str))
    lines = [f"Stability suite on test sequence `{base['id']}` (rollout from the LBS garment "
             f"of its first two frames; verdict rules: `garmentgnn.bench.stability`).", "",
             "| case | method | verdict | non-finite | max speed (m/s) | energy growth | "
             "deepest penetration (mm) | reason |", "|---|---|---|---:|---:|---:|---:|---|"]
    for r in records:
        m = r.get("metrics", {})
        lines.append(f"| {r['case']} | {r['method']} | {r['verdict']} | "
                     f"{m.get('nonfinite', float('nan')):.0f} | "
                     f"{m.get('max_speed', float('nan')):.3g} | "
                     f"{m.get('energy_growth', float('nan')):.3g} | "
                     f"{1000 * m.get('max_penetration_m', float('nan')):.3g} | "
                     f"{r.get('reason', '')} |")
    (out / "stability.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


#: the committed copy of the results (``--commit``)
RESULTS = Path("docs/results/mgn_learn")
#: what each command needs besides ``--out``
NEEDS = {"score": ("data",), "curves": ("run", "data"), "sweep": ("runs",),
         "branch": ("source", "data", "steps"), "steptime": ("data",),
         "stability": ("mgn", "data")}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = ArgumentParser(description=__doc__.split("\n\n")[0],
                       formatter_class=HelpFormatter)
    p.add_argument("command", choices=list(NEEDS),
                   help="score: rollouts of a split beside LBS and other checkpoints; "
                        "curves: one-step and rollout error of each step checkpoint of a "
                        "run; sweep: the sweep runs' validation table; branch: a run "
                        "continued from a checkpoint with pushforward; steptime: ms per "
                        "training step against size and threads; stability: the stability "
                        "suite, rolled out from LBS")
    p.add_argument("--data", type=dataset_dir, default=None,
                   help="generated dataset folder")
    add_output_args(p, RESULTS, "folder for <command>.json, .md and .png")
    p.add_argument("--mgn", default=None, help="the MGN-style checkpoint (score, stability)")
    p.add_argument("--mgn-name", default="MGN-style", help="score: the --mgn model's name in "
                   "the tables (paired tests: each name starting MGN-style against the rest, "
                   "and against another such of its model or its start)")
    p.add_argument("--split", default="test", help="score: the split rolled out")
    p.add_argument("--starts", nargs="+", default=["gt", "drape"],
                   help=f"score: where the rollouts start: {', '.join(START_STATES)}, or "
                        f"the NAME of an --other method (its prediction of frames 0 and 1)")
    p.add_argument("--project", nargs=2, default=None, metavar=("SWEEPS", "MARGIN_M"),
                   help="score: also the MGN-style model with the strain limit (SWEEPS) and "
                        "the collision projection (MARGIN_M metres) after each step")
    p.add_argument("--inextensible", type=int, default=0, metavar="SWEEPS",
                   help="score: --project's model with this many inextensible sweeps "
                        "(MGNStyle's `inextensible`; default 0: the strain limit alone)")
    p.add_argument("--other", nargs="*", default=[], metavar="NAME=CKPT",
                   help="score: other checkpoints scored beside it")
    p.add_argument("--merge", nargs="*", default=[], metavar="SCORE.json",
                   help="score: add the methods of earlier scores of the same sequences "
                        "(alone, without --mgn or --other: their report, nothing rolled out)")
    p.add_argument("--merge-names", nargs="+", default=None, metavar="NAME",
                   help="score: only these methods of the --merge files (default: all)")
    p.add_argument("--on-ensemble", action="store_true",
                   help="score: only the sequences of --data's ensemble ground truth")
    p.add_argument("--sequences", type=int, default=None,
                   help="score: only this many, drawn evenly from the held-out groups "
                        "(default: all); curves: per split (default there: 8)")
    p.add_argument("--run", default=None, help="curves: the run folder (its checkpoints)")
    p.add_argument("--step-offset", type=int, default=0,
                   help="curves: added to the checkpoints' steps (a branch: the step it "
                        "left at)")
    p.add_argument("--runs", nargs="+", default=None, metavar="NAME=RUN",
                   help="sweep: the runs")
    p.add_argument("--from", dest="source", default=None, metavar="CKPT",
                   help="branch: the checkpoint it continues from")
    p.add_argument("--rollout", type=int_at_least(1), default=3,
                   help="branch: frames a window rolls")
    p.add_argument("--steps", type=int, default=None, help="branch: optimizer steps")
    p.add_argument("--every", type=int, default=500,
                   help="branch: steps between validations and checkpoints")
    p.add_argument("--val-batches", type=int, default=16,
                   help="branch: validation sequences")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                   help="steptime: torch threads")
    p.add_argument("--repeats", type=int, default=8, help="steptime: timed steps per size")
    p.add_argument("--cases", nargs="+", default=["baseline", "stiff_x1000", "extreme_pose",
                                                  "fast_x5", "long_1000", "sliver_face",
                                                  "zero_area_face"],
                   help="stability: the cases")
    args = p.parse_args(argv)
    missing = [k for k in NEEDS[args.command] if getattr(args, k) in (None, [])]
    if missing:
        flag = {"source": "--from"}.get(missing[0], f"--{missing[0]}")
        p.error(f"{args.command}: give {flag}")
    if args.command == "curves" and args.sequences is None:
        args.sequences = 8
    # the checkpoints read and checked before the output folder is chosen
    if args.command == "score":
        if args.on_ensemble and args.sequences:
            p.error("--sequences: --on-ensemble scores the ensemble's sequences; drop one")
        read_scores(args.merge, args.merge_names)
        score_methods(args)
        args.ensemble = read_ensemble(args.data, args.on_ensemble)
    elif args.command == "stability":
        args.mgn_module = checkpoint_of(args.mgn, "--mgn", "mgn")
    args.out = output_path(args, RESULTS)
    if args.command != "steptime":
        torch.set_num_threads(1)
    {"score": run_score, "curves": run_curves, "sweep": run_sweep, "branch": run_branch,
     "steptime": run_steptime, "stability": run_stability}[args.command](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
