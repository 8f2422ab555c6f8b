"""Resolution transfer: models trained on ``learn``'s ~400-vertex garments, scored on the
same garments made at ~1.5K and ~4K vertices.

The datasets (:func:`spec`): ``learn``'s two held-out test garments (a dress and a
jumpsuit), one of its held-out test bodies and a training body, its held-out motion and
a training motion, in cotton, 60 frames: 8 sequences per resolution, all in the test
split, simulated by Blender as ``learn`` is (its engine settings), at 400 (``learn``'s
own), 1,500 and 4,000 vertices.  Each method scores the 8 sequences of each resolution
from frame 2 on (the learned simulator is given frames 0 and 1, as in
``benchmarks/mgn_learn.py``): E_dist and the surface metrics, frame-weighted, its E_dist
as a multiple of LBS's on the same frames, and a paired Wilcoxon test over the 8
sequences of that ratio against the same sequences at 400 vertices::

    python benchmarks/resolution.py generate                 # Blender, ~10 min, resumable
    python benchmarks/resolution.py score --da DA.ckpt --commit

The methods: GarTrans (``tests/data/gartrans_learn.ckpt``), DA-style (``--da``: the
``learn`` bench's), the MGN-style learned simulator (``tests/data/mgn_learn.ckpt``,
rolled out from the LBS garment) and LBS.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Dict

from garmentgnn._argparse import (ArgumentParser, HelpFormatter, add_output_args,
                                  command_line, existing_file, output_path)
from garmentgnn._plotting import pyplot
from garmentgnn.data import Spec, generate, preset, read_manifest
from garmentgnn.data.keys import body_key, garment_key, motion_key
from garmentgnn.bench.scoring import aggregate, score, wilcoxon

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "benchmarks") not in sys.path:  # the scoring of benchmarks/mgn_learn.py
    sys.path.append(str(ROOT / "benchmarks"))
from mgn_learn import (Scored, checkpoint_of,  # noqa: E402  (first GIVEN frames unscored)
                       read_settings)

RESULTS = ROOT / "docs" / "results" / "resolution" / "resolution.json"
#: the garment resolutions (target vertex counts of the templates)
RESOLUTIONS = (400, 1500, 4000)


def spec(resolution: int) -> Spec:
    """The 8 sequences at ``resolution`` (module doc), all held out for test."""
    base = preset("learn", engine="blender")
    garments = [dict(g, resolution=resolution) for g in (base.garments[7], base.garments[23])]
    bodies, motions = [base.bodies[3], base.bodies[1]], [base.motions[6], base.motions[0]]
    return Spec(name=f"learn_res{resolution}", garments=garments, bodies=bodies,
                motions=motions, materials=["cotton"], settings=base.settings,
                held_out={"test": {"garments": [garment_key(g) for g in garments],
                                   "bodies": [body_key(bodies[0])],
                                   "motions": [motion_key(motions[0])]}},
                seed=base.seed, engine=base.engine)


def dataset(cache: Path, resolution: int) -> Path:
    return cache / f"learn_res{resolution}-blender"


def methods(args: argparse.Namespace) -> Dict[str, Any]:
    """``{name: (module or None, predict(item) -> [T, V, 3])}``."""
    out: Dict[str, Any] = {}
    gartrans = checkpoint_of(args.gartrans, "--gartrans", "gartrans")
    out["GarTrans (SAT)"] = (gartrans, gartrans.predict_garment)
    if args.da:
        da = checkpoint_of(args.da, "--da", "da")
        out["DA-style"] = (da, da.predict_garment)
    mgn = checkpoint_of(args.mgn, "--mgn", "mgn")
    out["MGN-style (LBS start)"] = (mgn, lambda item: mgn.rollout(item, start="lbs"))
    out["LBS only"] = (None, lambda item: item.skinned())
    return out


def run_score(args: argparse.Namespace) -> None:
    cache = Path(args.cache).expanduser()
    roots = {r: dataset(cache, r) for r in RESOLUTIONS}
    make = f"python benchmarks/resolution.py generate --cache {args.cache}"
    for r, root in roots.items():  # every dataset finished before any scoring
        try:
            man = read_manifest(root)
        except (OSError, ValueError):
            print(f"error: --cache {args.cache}: no dataset {root.name} in it (of "
                  f"{', '.join(dataset(cache, x).name for x in RESOLUTIONS)}); make them "
                  f"with `{make}`", file=sys.stderr)
            sys.exit(2)
        if man["counts"] != {"ok": 8}:
            print(f"error: --cache {args.cache}: {root}: {man['counts']}, not 8 ok "
                  f"sequences; finish them with `{make}`", file=sys.stderr)
            sys.exit(2)
    models = methods(args)  # every checkpoint read before the output is chosen
    out_json = output_path(args, RESULTS)
    res: Dict[str, Any] = {"command": command_line("benchmarks/resolution.py"),
                           "datasets": {}, "rows": {}}
    per_seq: Dict[str, Dict[int, Dict[str, float]]] = {}
    for name, (module, predict) in models.items():
        for r, root in roots.items():
            test = Scored(root, "test", chunk=10 ** 6, cache_size=2, static_cache=2,
                          **read_settings(module))
            t0 = time.perf_counter()
            seqs = score(lambda i, item: predict(item), test)
            res["rows"].setdefault(name, {})[str(r)] = dict(
                aggregate(seqs)["all"], seconds=time.perf_counter() - t0,
                vertices=statistics.fmean(test[i].num_vertices for i in range(len(test))))
            per_seq.setdefault(name, {})[r] = {s["sequence"]: s["metrics"]["E_dist"]
                                               for s in seqs}
            print(f"{name} @ {r}: E_dist {res['rows'][name][str(r)]['E_dist']:.3f} cm",
                  flush=True)
            res["datasets"][str(r)] = {"root": str(root), "content_sha256": read_manifest(
                root).get("content_sha256")}
    lbs = per_seq["LBS only"]
    for name, by_res in per_seq.items():
        ratio = {r: {q: e / lbs[r][q] for q, e in seqs.items()} for r, seqs in by_res.items()}
        for r in RESOLUTIONS:
            row = res["rows"][name][str(r)]
            row["E_dist_over_lbs"] = statistics.fmean(ratio[r].values())
            if r != RESOLUTIONS[0] and name != "LBS only":
                # the same 8 (garment, body, motion) at 400 vertices: match by parts
                here = {_parts(q): v for q, v in ratio[r].items()}
                base = {_parts(q): v for q, v in ratio[RESOLUTIONS[0]].items()}
                row["vs_400"] = wilcoxon(here, base)
    out_json.parent.mkdir(parents=True, exist_ok=True)
    out_json.write_text(json.dumps(res, indent=1))
    out_json.with_suffix(".md").write_text(table(res))
    plot(res, out_json.with_suffix(".png"))
    print(table(res))


def _parts(seq_id: str) -> str:
    """A sequence id without its garment resolution: ``<kind>-<body>-<shape>-<motion>-
    <material>`` (the digest differs with the resolution)."""
    return seq_id.rsplit("-", 1)[0]


def table(res: Dict[str, Any]) -> str:
    head = ["method", "vertices", "E_dist (cm)", "E_dist / LBS", "p vs 400 (median)",
            "E_vnorm", "E_fnorm", "E_len (%)", "E_curv", "collision (%)", "s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, rows in res["rows"].items():
        for r, row in rows.items():
            w = row.get("vs_400")
            p = f"{w['p']:.2g} ({w['median_diff']:+.3f})" if w else "—"
            lines.append("| " + " | ".join([
                name, f"{row['vertices']:.0f}", f"{row['E_dist']:.3f}",
                f"{row['E_dist_over_lbs']:.3f}", p, f"{row['E_vnorm']:.2f}",
                f"{row['E_fnorm']:.2f}", f"{row['E_len']:.2f}", f"{row['E_curv']:.4g}",
                f"{row['collision_rate']:.2f}", f"{row['seconds']:.0f}"]) + " |")
    return "\n".join(lines) + "\n"


def plot(res: Dict[str, Any], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name, rows in res["rows"].items():
        xs = [rows[r]["vertices"] for r in rows]
        ax.plot(xs, [rows[r]["E_dist_over_lbs"] for r in rows], "o-", label=name)
    ax.axhline(1.0, color="0.6", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_xlabel("garment vertices (trained at ~400)")
    ax.set_ylabel("E_dist / LBS's, mean over 8 sequences")
    ax.set_title("Resolution transfer on learn's held-out garments")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_generate(args: argparse.Namespace) -> None:
    cache = Path(args.cache).expanduser()
    for r in RESOLUTIONS:
        print(f"learn_res{r}: {generate(spec(r), dataset(cache, r), workers=args.workers)}",
              flush=True)


def main(argv=None) -> None:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    ap.add_argument("command", choices=("generate", "score"))
    ap.add_argument("--cache", default="~/.cache/garmentgnn/datasets",
                    help="where the three datasets are (made)")
    ap.add_argument("--workers", type=int, default=1, help="generate: Blender workers")
    ap.add_argument("--gartrans", type=existing_file,
                    default=str(ROOT / "tests" / "data" / "gartrans_learn.ckpt"),
                    help="a GarTrans checkpoint trained on learn")
    ap.add_argument("--mgn", type=existing_file,
                    default=str(ROOT / "tests" / "data" / "mgn_learn.ckpt"),
                    help="an MGN-style checkpoint trained on learn")
    ap.add_argument("--da", type=existing_file, default=None,
                    help="a DA-style checkpoint trained on learn (default: none)")
    add_output_args(ap, RESULTS, "the results JSON (with .md and .png beside it)")
    args = ap.parse_args(argv)
    {"generate": run_generate, "score": run_score}[args.command](args)


if __name__ == "__main__":
    main()

