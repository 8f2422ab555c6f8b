"""The physics-trained baselines' own objective: on the models a ``garmentgnn bench`` run
trained (``energy``) and on the trajectory that minimises it frame by frame, what a
perfect fit of it would reach (``oracle``)."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence

import torch

from garmentgnn.data.keys import body_key, garment_key
from garmentgnn.bench import scoring
from garmentgnn.bench.methods import HOOD, NCS
from garmentgnn.bench.tables import table
from garmentgnn.metrics.garment_metrics import vertex_distance
from garmentgnn.training import BaselineModule, load_checkpoint
from garmentgnn.training.module import loss_inputs

from .train import baseline, evenly, predict, whole_sequences
from .variants import VARIANTS


def own_objective(module: BaselineModule, item: Any, pred: torch.Tensor) -> Dict[str, float]:
    """A physics-trained baseline's own training loss (its physics terms, inertia against
    ``2 p_{t-1} - p_{t-2}``) on the garment trajectory ``pred [T, V, 3]`` of ``item``'s
    frames, mean over frames ``2..T-1``: ``{"total": ..., term: ...}``."""
    frames = item.select(torch.arange(2, pred.shape[0]))
    with torch.no_grad():
        total, terms = module.loss_fn(loss_inputs(frames, pred[2:], module.dt,
                                                  predicted=2 * pred[1:-1] - pred[:-2],
                                                  ground_truth=False))
    return {"total": float(total), **{k: float(v) for k, v in terms.items()}}


def weighted_mean(rows: Sequence[Dict[str, Any]], key: Callable[[Dict[str, Any]], float],
                  weight: str = "frames") -> float:
    """``key`` of each sequence's row, averaged over sequences weighted by ``weight``
    (frames)."""
    return sum(key(r) * r[weight] for r in rows) / sum(r[weight] for r in rows)


def part_energy(root: Path, bench: Path, seed: int) -> Dict[str, Any]:
    """The HOOD- and NCS-style models a ``garmentgnn bench`` run left in ``bench/models``
    (seed ``seed``), on the test split: their own objective on their predictions against
    the same objective on the LBS garment, beside E_dist."""
    test = whole_sequences(root, "test")
    groups = sorted({(garment_key(r["garment"]), body_key(r["body"])) for r in test.records})
    res: Dict[str, Any] = {"bench": str(bench), "seed": seed, "methods": {}}
    for method in (HOOD, NCS):
        folder = bench / "models" / f"{method}--s{seed}"
        rows, loaded = [], {}
        for i in range(len(test)):
            r = test.records[test.index[i][0]]
            ckpt = (folder / "last.ckpt" if method == HOOD else folder /
                    f"garment{groups.index((garment_key(r['garment']), body_key(r['body'])))}"
                    / "last.ckpt")
            if not ckpt.is_file():
                continue
            if ckpt not in loaded:
                loaded[ckpt] = load_checkpoint(ckpt)
            module, item = loaded[ckpt].eval(), test[i]
            pred, lbs = predict(module, item), item.skinned()
            ok = item.get("valid")  # E_dist as the bench scores it: valid frames
            ok = torch.ones(item.num_frames, dtype=torch.bool) if ok is None else ok
            rows.append({"sequence": item.seq_id, "frames": item.num_frames,
                         "scored": int(ok.sum()),
                         "method": own_objective(module, item, pred),
                         "lbs": own_objective(module, item, lbs),
                         "E_dist": float(vertex_distance(pred[ok], item.gt[ok]).mean()),
                         "E_dist_lbs": float(vertex_distance(lbs[ok], item.gt[ok]).mean())})
        res["methods"][method] = rows
    lines = [f"Each method's own objective (its physics terms, mean per frame) on its test "
             f"predictions and on the LBS garment; E_dist in cm over the valid frames "
             f"(converged, the garment not inside the body), as the bench scores it; "
             f"bench `{bench.name}`, seed {seed}:", ""]
    out = []
    for method, rows in res["methods"].items():
        if not rows:
            out.append([method, "0", "—", "—", "—", "—", "—", "no checkpoint"])
            continue
        own = weighted_mean(rows, lambda r: r["method"]["total"])
        base = weighted_mean(rows, lambda r: r["lbs"]["total"])
        lower = sum(r["method"]["total"] < r["lbs"]["total"] for r in rows)
        out.append([method, str(len(rows)), f"{own:.4g}", f"{base:.4g}", f"{own / base:.3f}",
                    f"{lower} of {len(rows)}",
                    f"{weighted_mean(rows, lambda r: r['E_dist'], 'scored'):.3f}",
                    f"{weighted_mean(rows, lambda r: r['E_dist_lbs'], 'scored'):.3f}"])
    lines += table(["method", "sequences", "objective", "objective, LBS", "ratio",
                    "sequences below LBS", "E_dist", "E_dist, LBS"], out)
    return {"results": res, "markdown": lines}


def objective_rollout(module: BaselineModule, item: Any, max_iter: int = 200) -> torch.Tensor:
    """The garment trajectory ``[T, V, 3]`` that minimises ``module``'s own objective
    (:func:`own_objective`'s) frame by frame: from the LBS garment of frames 0 and 1,
    each frame's free vertices by L-BFGS from the inertial prediction ``2 x_{t-1} -
    x_{t-2}``, the pinned ones on the LBS garment.  What a physics-trained model that
    fitted its objective exactly at every state would roll out: one implicit-Euler step
    of its objective's cloth a frame."""
    lbs, free = item.skinned(), ~item.pinned_mask()
    xs = [lbs[0].double(), lbs[1].double()]
    for t in range(2, lbs.shape[0]):
        frame, inertial = item.select(torch.tensor([t])), 2 * xs[-1] - xs[-2]
        body = frame.body_pos.double()  # in float64: the line search needs its resolution
        var = inertial[free].clone().requires_grad_(True)
        fixed = lbs[t].double()

        def place(v: torch.Tensor) -> torch.Tensor:
            return fixed.masked_scatter(free.unsqueeze(-1), v)

        opt = torch.optim.LBFGS([var], max_iter=max_iter, history_size=20,
                                tolerance_grad=1e-9, tolerance_change=1e-12,
                                line_search_fn="strong_wolfe")

        def closure() -> torch.Tensor:
            opt.zero_grad()
            total, _ = module.loss_fn(dataclasses.replace(loss_inputs(
                frame, place(var)[None], module.dt, predicted=inertial[None],
                ground_truth=False), body_pos=body))
            total.backward()
            return total

        opt.step(closure)
        x = place(var.detach())
        if not torch.isfinite(x).all():
            raise FloatingPointError(f"`objective_rollout`: frame {t} of {item.seq_id} is not "
                                     f"finite")
        xs.append(x)
    return torch.stack(xs).to(lbs.dtype)


def part_oracle(root: Path, variants: Sequence[str], test_sequences: Optional[int],
                max_iter: int = 200) -> Dict[str, Any]:
    """For each physics-trained variant (its objective: the loss terms and weights of
    its recipe), :func:`objective_rollout` on the test sequences against the
    LBS garment: E_dist (the valid frames, as the bench scores it),
    its objective and how far it is from LBS at the last frame."""
    wrong = [name for name in variants if VARIANTS[name].get("baseline") != HOOD]
    if wrong:
        raise ValueError(f"`variants`: {wrong} not trained on a physics objective; give "
                         f"HOOD-style variants")
    test = whole_sequences(root, "test")
    picked = evenly(list(range(len(test))), test_sequences or len(test))
    res: Dict[str, Any] = {"max_iter": max_iter, "variants": {}}
    out = []
    for name in variants:
        v = VARIANTS[name]
        # the same face search, not compiled per shape
        module = baseline(v["baseline"], root, dict(v.get("module") or {},
                                                    compile_search=False)).module.eval()
        rows = []
        for i in picked:
            item, t = test[i], time.perf_counter()
            pred, lbs = objective_rollout(module, item, max_iter), item.skinned()
            ok = item.get("valid")
            ok = torch.ones(item.num_frames, dtype=torch.bool) if ok is None else ok
            rows.append({"sequence": item.seq_id, "frames": item.num_frames,
                         "scored": int(ok.sum()), "seconds": time.perf_counter() - t,
                         "oracle": own_objective(module, item, pred),
                         "lbs": own_objective(module, item, lbs),
                         "E_dist": float(vertex_distance(pred[ok], item.gt[ok]).mean()),
                         "E_dist_lbs": float(vertex_distance(lbs[ok], item.gt[ok]).mean()),
                         "from_lbs_last": float((pred[-1] - lbs[-1]).norm(dim=-1).mean())})
            r = rows[-1]
            print(f"oracle {name}, {item.seq_id}: E_dist {r['E_dist']:.3f} cm, LBS "
                  f"{r['E_dist_lbs']:.3f} cm ({r['seconds']:.0f} s)", flush=True)
        res["variants"][name] = {"settings": v, "rows": rows}
        e = weighted_mean(rows, lambda r: r["E_dist"], "scored")
        el = weighted_mean(rows, lambda r: r["E_dist_lbs"], "scored")
        try:
            w = scoring.wilcoxon({r["sequence"]: r["E_dist"] for r in rows},
                                 {r["sequence"]: r["E_dist_lbs"] for r in rows})
            p = f"{w['p']:.2g}"
        except ValueError:
            p = "—"
        objective = (sum(r["oracle"]["total"] for r in rows)
                     / sum(r["lbs"]["total"] for r in rows))
        out.append([name, str(len(rows)), f"{e:.3f}", f"{el:.3f}", f"{e / el:.3f}",
                    f"{sum(r['E_dist'] < r['E_dist_lbs'] for r in rows)} of {len(rows)}", p,
                    f"{objective:.3f}",
                    f"{100 * sum(r['from_lbs_last'] for r in rows) / len(rows):.1f}"])
    lines = [f"The trajectory that minimises each objective frame by frame (L-BFGS, at most "
             f"{max_iter} iterations a frame, from the LBS garment of frames 0 and 1) on "
             f"{len(picked)} of {len(test)} test sequences; E_dist in cm over the valid frames "
             f"(converged, the garment not inside the body), frame-weighted; p: paired "
             f"Wilcoxon test against LBS over sequences:", ""]
    lines += table(["objective of", "sequences", "E_dist", "E_dist, LBS", "x LBS",
                    "sequences below LBS", "p", "objective / LBS's",
                    "from LBS at the last frame (cm)"], out)
    return {"results": res, "markdown": lines}
