"""Test rollouts of MGN-style trained in bf16-mixed against float32, over seeds: per seed
and pooled (each test sequence's E_dist averaged over the seeds), paired Wilcoxon
signed-rank tests (scipy) over the sequences.  Reads ``benchmarks/mgn_learn.py score``
files whose ``--mgn`` is the bf16-mixed checkpoint and whose ``--other`` is ``float32``."""
import argparse
import json

import numpy as np
from scipy.stats import wilcoxon

ap = argparse.ArgumentParser(description=__doc__)
ap.add_argument("scores", nargs="+", help="score.json of each seed")
runs = [json.load(open(p)) for p in ap.parse_args().scores]


def e_dist(run, name):
    return {s["sequence"]: s["metrics"]["E_dist"] for s in run["methods"][name]}


seqs = sorted(e_dist(runs[0], "float32"))
bf = np.array([[e_dist(r, "MGN-style (gt)")[s] for s in seqs] for r in runs])
fp = np.array([[e_dist(r, "float32")[s] for s in seqs] for r in runs])
lbs = np.array([e_dist(runs[0], "LBS only")[s] for s in seqs])
print(f"LBS: mean E_dist {lbs.mean():.3f} cm over {len(seqs)} sequences")
for i, (b, f) in enumerate(zip(bf, fp)):
    print(f"seed {i}: x LBS bf16-mixed {b.mean() / lbs.mean():.3f}, float32 "
          f"{f.mean() / lbs.mean():.3f}; bf16-mixed lower on {100 * (b < f).mean():.0f}% "
          f"of the sequences, p = {wilcoxon(b, f).pvalue:.2g}")
b, f = bf.mean(0), fp.mean(0)
print(f"pooled over seeds: x LBS bf16-mixed {b.mean() / lbs.mean():.3f}, float32 "
      f"{f.mean() / lbs.mean():.3f}; median difference {np.median(b - f):.3f} cm, "
      f"bf16-mixed lower on {100 * (b < f).mean():.0f}%, p = {wilcoxon(b, f).pvalue:.2g}")
