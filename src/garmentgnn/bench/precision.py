"""Reduced precision (bfloat16 / float16) and a long autoregressive sequence.

**Precision** (:func:`run_record`): GarTrans (frame-parallel, every frame of one
sequence in one call, static branch included) and the LBS baseline run in

* ``float32`` (the reference: run again and compared with the first float32 run, so
  its deviation is 0 exactly unless the computation is not deterministic);
* ``bfloat16`` and ``float16``, each two ways: ``autocast`` (``torch.autocast("cpu",
  dtype)``: weights stay float32, autocast-eligible ops such as matmul run in the low
  precision) and ``cast`` (model and floating-point inputs cast to the dtype).

Whether a dtype/mode is supported is found by trying: an exception is recorded as
``status="unsupported"`` with its message (verdict failed), never raised.  Per row:
non-finite output count, the largest absolute deviation from the float32 output
(metres), latency (median ms of one call / frames), and a verdict from
:class:`PrecisionThresholds`.

GarTrans here is untrained and in the paper's form (:data:`~garmentgnn.models.PAPER_FORM`:
no gates, whose small start would hide the networks' own round-off), so the deviations
are those of randomly initialised weights; a trained model's can differ.

**Long sequence** (:func:`run_long`): an autoregressive :meth:`GarTrans.rollout` over
a long procedural motion (1000 frames in the ``small`` preset) on a small garment:
non-finite count, max vertex speed (finite differences), and the drift of the mean
displacement of the prediction from its coarse LBS mesh ``M^{t,c}`` (first window
vs last window of frames), verdict from :class:`LongThresholds`.  The reference
simulator is not run on the long sequence (seconds per frame here: a 1000-frame run
would hold the machine for a quarter of an hour or more per garment); the report says
so, with the per-frame cost the bench measured for the reference budget.
"""
from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from garmentgnn.models.inputs import HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.bench import stability as stab
from garmentgnn.bench.model_inputs import BenchChunks, untrained_module
from garmentgnn.bench.records import failure, section
from garmentgnn.bench.sequences import BenchSequence, make_sequence
from garmentgnn.bench.tables import table
from garmentgnn.bench.timing import measure
from garmentgnn.models import PAPER_FORM
from garmentgnn.models.baselines import LBSBaseline
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training.evaluate import predict

DTYPES: Dict[str, torch.dtype] = {"float32": torch.float32, "bfloat16": torch.bfloat16,
                                  "float16": torch.float16}
MODES = ("autocast", "cast")
#: method names of the precision records
METHODS = {"gartrans": "GarTrans (untrained)", "lbs": "lbs"}
#: method name of the long-sequence records
LONG_METHOD = "GarTrans (untrained, autoregressive)"
#: the untrained GarTrans of this module: the paper's form (no gates, no projection or
#: strain limit; with the skinning prior)
MODULE_KWARGS: Dict[str, Any] = dict(PAPER_FORM)


@dataclass(frozen=True)
class PrecisionThresholds:
    """Verdict of one reduced-precision row (``failed`` checked first).

    failed when: the dtype/mode raised (unsupported); any non-finite output; the max
    absolute deviation from float32 > ``fail_deviation`` (m) -- an error as large as
    the learned methods' own errors (E_dist of about a centimetre).

    degraded when: the deviation > ``degrade_deviation`` (m), a visible millimetre.
    Else stable.
    """

    fail_deviation: float = 0.01
    degrade_deviation: float = 1e-3


PRECISION_THRESHOLDS = PrecisionThresholds()


@dataclass(frozen=True)
class LongThresholds:
    """Verdict of a long autoregressive rollout (``failed`` checked first).

    failed when: any non-finite coordinate; max vertex speed > ``fail_speed`` (m/s);
    displacement growth > ``fail_growth``.

    degraded when: max vertex speed > ``speed_factor`` x the body's max vertex speed +
    ``speed_slack`` (m/s); displacement growth > ``degrade_growth``.

    Displacement growth = mean over the last ``window`` frames of the mean distance of
    the prediction from its coarse LBS mesh, divided by the same over the first
    ``window`` frames (at least ``displacement_floor`` m); ``window`` is capped at half
    the sequence.  The speed limits are those of :class:`stability.Thresholds`.
    """

    fail_speed: float = stab.THRESHOLDS.fail_speed
    speed_factor: float = stab.THRESHOLDS.speed_factor
    speed_slack: float = stab.THRESHOLDS.speed_slack
    degrade_growth: float = 2.0
    fail_growth: float = 10.0
    window: int = 100
    displacement_floor: float = 1e-4


LONG_THRESHOLDS = LongThresholds()


# --------------------------------------------------------------------------- precision
def precision_verdict(row: Dict[str, Any], th: PrecisionThresholds = PRECISION_THRESHOLDS
                      ) -> Tuple[str, str]:
    """``(verdict, reason)`` of a row per :class:`PrecisionThresholds`."""
    if row["status"] != "ok":
        return "failed", str(row.get("message", row["status"]))
    if row["nonfinite"] > 0:
        return "failed", f"{row['nonfinite']} non-finite coordinates"
    dev = row["max_dev_m"]
    if dev > th.fail_deviation:
        return "failed", f"deviation {1e3 * dev:.3g} mm > {1e3 * th.fail_deviation:.3g} mm"
    if dev > th.degrade_deviation:
        return "degraded", f"deviation {1e3 * dev:.3g} mm > {1e3 * th.degrade_deviation:.3g} mm"
    return "stable", ""


def _cast_floats(item: GarmentInputs, dtype: torch.dtype) -> GarmentInputs:
    """A copy of ``item`` with its floating-point tensors in ``dtype``."""
    return item.clone().apply(lambda t: t.to(dtype) if t.is_floating_point() else t)


def _predictors(seq: BenchSequence, method: str, seed: int, history: int, nystrom_dim: int,
                num_landmarks: int, module_kwargs: Optional[Dict[str, Any]]
                ) -> Tuple[Callable[[], Tensor], Callable[[torch.dtype], Callable[[], Tensor]],
                           Dict[str, Any]]:
    """``(float32 predictor, dtype -> cast-mode predictor, facts)`` of ``method``."""
    if method == "gartrans":
        item = BenchChunks(seq, history=history, nystrom_dim=nystrom_dim,
                           num_landmarks=num_landmarks)[0]
        kw = dict(MODULE_KWARGS, **(module_kwargs or {}))
        module = untrained_module(item, seed, **kw)

        def cast(dt: torch.dtype) -> Callable[[], Tensor]:
            m, it = copy.deepcopy(module).to(dt), _cast_floats(item, dt)
            return lambda: predict(m, it, "gartrans")
        return lambda: predict(module, item, "gartrans"), cast, {"module_kwargs": kw}
    if method == "lbs":
        lbs = LBSBaseline()
        rot, tr = seq.motion.rotations, seq.motion.translation

        def cast_lbs(dt: torch.dtype) -> Callable[[], Tensor]:
            scene = _cast_floats(seq.scene, dt)
            return lambda: lbs(scene, rot.to(dt), tr.to(dt))
        return lambda: lbs(seq.scene, rot, tr), cast_lbs, {}
    raise ValueError(f"`method`: expected one of {sorted(METHODS)}, got {method!r}")


def run_record(seq: BenchSequence, method: str, seed: int = 0, warmup: int = 2,
               repeats: int = 5, history: int = HISTORY, nystrom_dim: int = NYSTROM_DIM,
               num_landmarks: int = NUM_LANDMARKS, module_kwargs: Optional[Dict[str, Any]] = None,
               thresholds: PrecisionThresholds = PRECISION_THRESHOLDS) -> Dict[str, Any]:
    """float32 / bfloat16 / float16 rows of ``method`` (``"gartrans"`` or ``"lbs"``) on
    ``seq``; a ``kind="precision"`` record."""
    if method not in METHODS:
        raise ValueError(f"`method`: expected one of {sorted(METHODS)}, got {method!r}")
    rec: Dict[str, Any] = {"kind": "precision", "method": METHODS[method], "case": seq.name,
                           "seed": seed, "thresholds": asdict(thresholds)}
    t0 = time.perf_counter()
    try:
        fp32, cast, facts = _predictors(seq, method, seed, history, nystrom_dim,
                                        num_landmarks, module_kwargs)
        rec.update(facts)
        with torch.inference_mode():
            ref = fp32().float()
        T = ref.shape[0]
        rec.update(num_vertices=seq.garment.num_vertices, frames=T)
        rows = []
        for dname, dt in DTYPES.items():
            for mode in (("reference",) if dt == torch.float32 else MODES):
                row: Dict[str, Any] = {"dtype": dname, "mode": mode}
                try:
                    if mode == "reference":
                        fn = fp32
                    elif mode == "cast":
                        fn = cast(dt)
                    else:
                        def fn(dt=dt):
                            with torch.autocast("cpu", dtype=dt):
                                return fp32()
                    with torch.inference_mode():
                        out = fn()
                    if not isinstance(out, Tensor) or out.shape != ref.shape:
                        raise RuntimeError(f"output of shape {getattr(out, 'shape', None)}")
                    out = out.float()
                    bad = int((~torch.isfinite(out)).sum())
                    row.update(status="ok", message="ok", out_dtype=str(out.dtype),
                               nonfinite=bad,
                               max_dev_m=None if bad else float((out - ref).abs().max()),
                               ms_per_frame=measure(fn, warmup, repeats)["median_ms"] / T)
                except Exception as err:  # the dtype/mode is not supported here
                    row.update(status="unsupported",
                               message=f"unsupported: {type(err).__name__}: {err}"[:400])
                row["verdict"], row["reason"] = precision_verdict(row, thresholds)
                rows.append(row)
        rec["rows"] = rows
        rec["timing"] = {"repeats": repeats, "warmup": warmup,
                         "threads": torch.get_num_threads(),
                         "note": "median ms of one call predicting every frame / frames"}
        rec.update(status="ok", message="ok")
    except Exception as err:
        rec.update(failure(err))
    rec["seconds"] = time.perf_counter() - t0
    return rec


# --------------------------------------------------------------------------- long sequence
def long_metrics(positions: Tensor, coarse: Tensor, body_frames: Tensor, fps: float,
                 thresholds: LongThresholds = LONG_THRESHOLDS) -> Dict[str, float]:
    """Numbers of a rollout ``positions [T, V, 3]`` with its coarse meshes ``[T, V, 3]``
    and the posed body ``[T, Vb, 3]`` (see :class:`LongThresholds`)."""
    if positions.shape != coarse.shape or positions.dim() != 3:
        raise ValueError(f"`positions`/`coarse`: expected equal [T, V, 3] shapes, got "
                         f"{tuple(positions.shape)} and {tuple(coarse.shape)}")
    pos, T = positions.detach().double(), positions.shape[0]
    if T < 2:
        raise ValueError(f"`positions`: at least 2 frames, got {T}")
    body = body_frames.detach().double()[:T]
    nonfinite = int((~torch.isfinite(pos)).sum())
    out: Dict[str, float] = {
        "frames": float(T), "nonfinite": float(nonfinite),
        "body_max_speed": float(((body[1:] - body[:-1]).norm(dim=-1) * fps).max())}
    if nonfinite:
        return out
    out["max_speed"] = float(((pos[1:] - pos[:-1]).norm(dim=-1) * fps).max())
    disp = (pos - coarse.detach().double()).norm(dim=-1).mean(-1)  # [T]
    w = max(1, min(thresholds.window, T // 2))
    first, last = float(disp[:w].mean()), float(disp[-w:].mean())
    out.update(window=float(w), disp_first_m=first, disp_last_m=last,
               disp_max_m=float(disp.max()),
               disp_growth=last / max(first, thresholds.displacement_floor))
    return out


def long_verdict(m: Dict[str, float], thresholds: LongThresholds = LONG_THRESHOLDS
                 ) -> Tuple[str, str]:
    """``(verdict, reason)`` per :class:`LongThresholds`."""
    th = thresholds
    if m.get("nonfinite", 0) > 0:
        return "failed", f"{int(m['nonfinite'])} non-finite coordinates"
    fails = [(m["max_speed"] > th.fail_speed, f"max speed {m['max_speed']:.3g} m/s"),
             (m["disp_growth"] > th.fail_growth, f"displacement growth x{m['disp_growth']:.3g}")]
    bad = [r for c, r in fails if c]
    if bad:
        return "failed", "; ".join(bad)
    limit = th.speed_factor * m["body_max_speed"] + th.speed_slack
    degr = [(m["max_speed"] > limit, f"max speed {m['max_speed']:.3g} > {limit:.3g} m/s"),
            (m["disp_growth"] > th.degrade_growth,
             f"displacement growth x{m['disp_growth']:.3g}")]
    bad = [r for c, r in degr if c]
    return ("degraded", "; ".join(bad)) if bad else ("stable", "")


def run_long(item: Dict[str, Any], seed: int = 0, history: int = HISTORY,
             nystrom_dim: int = NYSTROM_DIM, num_landmarks: int = NUM_LANDMARKS,
             module_kwargs: Optional[Dict[str, Any]] = None,
             thresholds: LongThresholds = LONG_THRESHOLDS) -> Dict[str, Any]:
    """Autoregressive rollout of an untrained GarTrans over ``item``'s whole motion (a
    :func:`~garmentgnn.bench.sequences.case_item`); a ``kind="long_sequence"`` record."""
    rec: Dict[str, Any] = {"kind": "long_sequence", "method": LONG_METHOD,
                           "case": item.get("name"), "seed": seed,
                           "thresholds": asdict(thresholds)}
    t0 = time.perf_counter()
    try:
        seq = make_sequence(item, seed)
        x = BenchChunks(seq, history=history, nystrom_dim=nystrom_dim,
                        num_landmarks=num_landmarks)[0]
        kw = dict(MODULE_KWARGS, **(module_kwargs or {}))
        module = untrained_module(x, seed, **kw)
        rec.update(num_vertices=seq.garment.num_vertices, module_kwargs=kw,
                   motion=item["motion"])
        t1 = time.perf_counter()
        with torch.inference_mode():
            out = module(x, autoregressive=True)
        wall = time.perf_counter() - t1
        m = long_metrics(out["final"], out["coarse"], seq.body_frames, float(seq.motion.fps),
                         thresholds)
        m["ms_per_frame"] = 1e3 * wall / seq.num_frames
        v, reason = long_verdict(m, thresholds)
        rec.update(status="ok", message="ok", metrics=m, verdict=v, reason=reason)
    except Exception as err:
        rec.update(failure(err), verdict="failed", metrics={}, reason=f"raised: {err}")
    rec["seconds"] = time.perf_counter() - t0
    return rec


# --------------------------------------------------------------------------- report
def _th_line(th: Optional[Dict[str, Any]], cls: str) -> List[str]:
    return (["Thresholds: " + ", ".join(f"{k}={v}" for k, v in th.items()) +
             f" (see `garmentgnn.bench.precision.{cls}`).", ""] if th else [])


def markdown(records: Sequence[Dict[str, Any]]) -> List[str]:
    """The report's "Reduced precision" section (lines)."""
    recs, lines = section(records, "precision", "Reduced precision (bfloat16 / float16)")
    if not recs:
        return lines
    lines += ["Every frame of the sequence in one call (GarTrans: static branch included; "
              "untrained, paper form).  *autocast*: `torch.autocast(\"cpu\", "
              "dtype)`; *cast*: model and inputs cast.  Deviation: max |output - float32 "
              "output| over all frames and vertices.", ""]
    lines += _th_line(next((r.get("thresholds") for r in recs if r.get("thresholds")), None),
                      "PrecisionThresholds")
    rows = []
    for r in recs:
        if r["status"] != "ok":
            rows.append([r["method"], "—", "—", "failed", "—", "—", "—", "**failed**",
                         str(r.get("message", ""))[:160].replace("|", "/")])
            continue
        for w in r["rows"]:
            ok = w["status"] == "ok"
            dev = w.get("max_dev_m")
            rows.append([r["method"], w["dtype"], w["mode"], w["status"],
                         str(w["nonfinite"]) if ok else "—",
                         "—" if dev is None else f"{1e3 * dev:.3g}",
                         f"{w['ms_per_frame']:.3g}" if ok else "—", f"**{w['verdict']}**",
                         (w.get("reason") or "").replace("|", "/")[:160]])
    lines += table(["method", "dtype", "mode", "status", "non-finite", "max deviation (mm)",
                     "ms / frame", "verdict", "reason"], rows) + [""]
    return lines


def long_markdown(records: Sequence[Dict[str, Any]]) -> List[str]:
    """The report's "Long sequence" section (lines)."""
    recs = [r for r in records if r["kind"] == "long_sequence"]
    lines = ["## Long sequence (autoregressive)", ""]
    ref = [r for r in records if r["kind"] == "accuracy" and r.get("reference")
           and r["status"] == "ok" and r.get("timing", {}).get("latency_ms")]
    cost = ""
    if ref and recs:
        ms = ref[0]["timing"]["latency_ms"]
        n = max(int(r.get("metrics", {}).get("frames", 0)) for r in recs)
        cost = (f"; the reference budget took {ms / 1e3:.3g} s per frame on "
                f"`{ref[0]['case']}` here, about {ms * n / 6e4:.3g} min for {n} frames")
    lines += [f"Reference simulator on the long sequence: **not run** (the bench never "
              f"simulates it{cost}; see docs/simulator.md).", ""]
    if not recs:
        return lines + ["Learned model: not run in this preset.", ""]
    lines += ["`GarTrans.rollout` (each frame's dynamic graph velocity from the model's own "
              "previous prediction), untrained, paper form.  Displacement: mean distance of "
              "the prediction from its coarse LBS mesh; growth: last window over first "
              "window.", ""]
    lines += _th_line(next((r.get("thresholds") for r in recs if r.get("thresholds")), None),
                      "LongThresholds")
    rows = []
    for r in recs:
        m = r.get("metrics", {})

        def g(k: str, scale: float = 1.0) -> str:
            v = m.get(k)
            return "—" if v is None else f"{scale * v:.3g}"
        rows.append([r["method"], r["case"], g("frames"), r.get("num_vertices", "—"),
                     f"**{r.get('verdict', 'failed')}**", g("nonfinite"), g("max_speed"),
                     g("body_max_speed"), g("disp_first_m", 1e3), g("disp_last_m", 1e3),
                     g("disp_growth"), g("ms_per_frame"),
                     (r.get("reason") or r.get("message") or "").replace("|", "/")[:160]])
    rows = [[str(c) for c in row] for row in rows]
    lines += table(["method", "case", "frames", "vertices", "verdict", "non-finite",
                     "max speed (m/s)", "body max speed (m/s)", "disp. first window (mm)",
                     "disp. last window (mm)", "growth", "ms / frame", "reason"], rows) + [""]
    return lines
