"""The learned methods of ``garmentgnn bench`` and their settings, read from the packaged
YAML configurations (:mod:`garmentgnn.training.configs`) that ``garmentgnn train`` uses:
nothing here restates a hyper-parameter.

* GarTrans and the Table 1 variants (:data:`GARTRANS`): ``configs/gartrans.yaml`` and
  one ``configs/ablations/<name>.yaml`` each (its ``model:`` overrides and, where it
  lists callbacks, its :class:`ProgressiveSchedule` arguments);
* the DA-, HOOD- and NCS-style baselines (:data:`BASELINES`):
  ``configs/baselines/<name>.yaml``, trained by
  :class:`~garmentgnn.training.BaselineModule`;
* the MGN-style learned simulator (:data:`MGN`): ``configs/mgn.yaml``, trained by
  :class:`~garmentgnn.training.SimulatorModule` on that file's data settings (windows of
  frames, :data:`MGN_DATA`);
* ``LBS only``: the rest garment skinned with the stored skinning weights, no learning.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Any, Dict, Optional, Tuple

from garmentgnn.bench import stability as stab
from garmentgnn.training.configs import load_config, module_spec
from garmentgnn.training.datamodule import GarmentDataModule
from garmentgnn.training.schedule import ProgressiveSchedule

__all__ = ["BASELINES", "BASELINE_CONFIGS", "DATA", "GARTRANS", "GARTRANS_MODULE", "LBS",
           "LONG", "METHOD_NAMES", "MGN", "MGN_DATA", "MGN_MODULE", "NCS", "HOOD", "DA",
           "SEED_FREE", "LearnedBudget", "Variant", "seed_plan", "variant_settings"]

_BASE = load_config("gartrans")
#: ``configs/gartrans.yaml``'s module (its ``model:`` entry: ``class_path`` and
#: ``init_args``, the GarTrans it trains nested in them)
GARTRANS_MODULE: Dict[str, Any] = module_spec("gartrans")
#: the data settings GarTrans trains on: the data module's (its defaults, under
#: ``configs/gartrans.yaml``'s ``data:`` section) chunk length, history and Nyström sizes
DATA: Dict[str, Any] = {k: v for k, v in dict(
    {k: p.default for k, p in inspect.signature(GarmentDataModule.__init__).parameters.items()},
    **_BASE["data"]).items() if k in ("chunk", "history", "nystrom_dim", "num_landmarks")}
#: the schedule arguments that the bench budget sets (the module's belong to its epochs)
_WINDOWS = ("window", "window2")
_SCHEDULE_DEFAULTS = {k: p.default for k, p in
                      inspect.signature(ProgressiveSchedule.__init__).parameters.items()
                      if k != "self"}


@dataclass(frozen=True)
class Variant:
    """A GarTrans row: ``config`` names the ``configs/ablations/<config>.yaml`` it is
    (``None``: ``configs/gartrans.yaml`` itself)."""

    config: Optional[str]


GARTRANS: Dict[str, Variant] = {
    "GarTrans (SAT)": Variant(None),
    "GarTrans w/o edge processing": Variant("wo_edge"),
    "GarTrans w/o edge gating": Variant("wo_gating"),
    "GarTrans structure-aware transformer": Variant("structure_aware"),
    "GarTrans GAT": Variant("gat"),
    "GarTrans w/o unsupervised loss": Variant("wo_unsup"),
}
#: full GarTrans, the variant every comparison is made against
FULL = next(iter(GARTRANS))
NCS, HOOD, DA, MGN, LBS = "NCS-style", "HOOD-style", "DA-style", "MGN-style", "LBS only"
METHOD_NAMES: Tuple[str, ...] = tuple(GARTRANS) + (NCS, HOOD, DA, MGN, LBS)
#: methods without training or randomness: run for the first seed only
SEED_FREE: Tuple[str, ...] = (LBS,)
#: each baseline's packaged configuration
BASELINE_CONFIGS: Dict[str, str] = {DA: "baselines/da", HOOD: "baselines/hood",
                                    NCS: "baselines/ncs"}
#: each baseline's module (its configuration's ``model:`` entry: a
#: :class:`~garmentgnn.training.BaselineModule` handed the model it names)
BASELINES: Dict[str, Dict[str, Any]] = {name: module_spec(cfg)
                                        for name, cfg in BASELINE_CONFIGS.items()}
#: the MGN-style simulator's module (``configs/mgn.yaml``'s ``model:`` entry) and data
#: settings (its ``data:`` section without ``root``, ``num_workers`` and ``batch_size``,
#: which the bench sets)
MGN_MODULE: Dict[str, Any] = module_spec("mgn")
MGN_DATA: Dict[str, Any] = {k: v for k, v in load_config("mgn")["data"].items()
                            if k not in ("root", "num_workers", "batch_size")}


def variant_settings(method: str) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """``(module spec, ProgressiveSchedule arguments without the windows)`` of GarTrans
    variant ``method``: ``gartrans.yaml`` merged with its ablation file the way
    LightningCLI merges two ``--config`` files (a list, like ``callbacks``, replaces);
    :func:`~garmentgnn.training.configs.instantiate` builds the module.  The schedule is
    the module's own (its ``schedule`` argument; :func:`with_schedule` sets it)."""
    v = GARTRANS[method]
    model = module_spec("gartrans", *([f"ablations/{v.config}"] if v.config else []))
    sched = (model.get("init_args") or {}).get("schedule", True)
    full = dict(_SCHEDULE_DEFAULTS, **(sched if isinstance(sched, dict) else {}))
    return model, {k: val for k, val in full.items() if k not in _WINDOWS}


def with_schedule(spec: Dict[str, Any], schedule: Dict[str, Any]) -> Dict[str, Any]:
    """A GarTrans module ``spec`` that trains with the :class:`ProgressiveSchedule` of
    arguments ``schedule``."""
    return dict(spec, init_args=dict(spec.get("init_args") or {}, schedule=dict(schedule)))


#: the long run of full GarTrans (:attr:`LearnedBudget.long_minutes`)
LONG = "GarTrans (SAT), long budget"


@dataclass(frozen=True)
class LearnedBudget:
    """What the learned part of a bench preset trains.

    Attributes:
        seeds: training seeds ``0..seeds-1`` (``lightning.seed_everything(seed)``).
        epochs: passes over the ``train`` split (GarTrans variants, DA, HOOD); with
            ``minutes``, the most epochs a run may take.
        window: :class:`ProgressiveSchedule` window in epochs.
        ncs_epochs: passes of each NCS model over its own garment's test poses.
        methods: the names of :data:`METHOD_NAMES` to run.
        stability_cases: :data:`garmentgnn.bench.stability.CASES` run by each method
            (first seed's model) and the simulator on the first test sequence.
        minutes: the wall-clock training budget of every (method, seed) run
            (:class:`~garmentgnn.training.TimeBudget`: stop when spent, learning rate
            annealed over it); NCS-style splits it evenly over its per-garment models.
            ``None``: train ``epochs`` epochs instead.
        epoch_chunks: chunks per epoch (Lightning's ``limit_train_batches`` is this over
            ``batch_size``, rounded up), so that a budget on a large dataset still has
            epochs for the schedule and checkpoints; ``None``: the whole train split.
        batch_size: training chunks per optimizer step (``GarmentDataModule``'s
            ``batch_size``: chunks of other sequences collated as one batch); NCS-style's
            per-garment models, on a few sequences each, train one chunk per step.
        lr_factor: every method's learning rate multiplied by this (e.g. ``batch_size **
            0.5`` to keep the step's noise scale with larger batches).
        seed_methods: the methods trained with every seed; the other methods get seed
            0 only, except the best GarTrans ablation and the best baseline (lowest
            seed-0 test E_dist), which get every seed too.  ``None``: every method
            gets every seed.
        long_minutes: the budget of one more run of full GarTrans, seed 0
            (:data:`LONG`): where it goes with more time; ``None``: no such run.
        test_sequences: score every method on this many test sequences, the same for
            all, drawn evenly from the held-out groups
            (:func:`garmentgnn.bench.scoring.stratified`); ``None``: all of them.
        curve_every: record the validation E_dist every this many training chunks, in
            whole optimizer steps of ``batch_size`` chunks (at least one)
            (:class:`garmentgnn.bench.curves.LearningCurve`; needs a ``val`` split);
            ``None``: no learning curves.
        val_sequences: the learning curves' validation sequences, drawn evenly from the
            held-out groups like ``test_sequences``; ``None``: all of them.
        train_sequences: the learning curves also score this many training sequences
            (evenly spaced in id order), the fit beside the validation error; ``None``:
            not.
        equal_steps: also score every method trained on the train split (not NCS-style)
            with its weights after this many optimizer steps, so that the methods are
            compared at equal steps as well as at equal time (needs ``curve_every``);
            ``None``: not.
    """

    seeds: int = 1
    epochs: int = 1
    window: int = 1
    ncs_epochs: int = 1
    methods: Tuple[str, ...] = METHOD_NAMES
    stability_cases: Tuple[str, ...] = ()
    minutes: Optional[float] = None
    epoch_chunks: Optional[int] = None
    batch_size: int = 1
    lr_factor: float = 1.0
    seed_methods: Optional[Tuple[str, ...]] = None
    long_minutes: Optional[float] = None
    test_sequences: Optional[int] = None
    curve_every: Optional[int] = None
    val_sequences: Optional[int] = None
    train_sequences: Optional[int] = None
    equal_steps: Optional[int] = None

    def __post_init__(self) -> None:
        for name in ("seeds", "epochs", "window", "ncs_epochs", "batch_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"`{name}`: expected a positive int, got {v!r}")
        for name in ("minutes", "long_minutes"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and 0 < v < float("inf")):
                raise ValueError(f"`{name}`: expected a positive number of minutes or None, "
                                 f"got {v!r}")
        if not (isinstance(self.lr_factor, (int, float)) and not isinstance(self.lr_factor, bool)
                and 0 < self.lr_factor < float("inf")):
            raise ValueError(f"`lr_factor`: expected a positive number, got {self.lr_factor!r}")
        for name in ("epoch_chunks", "test_sequences", "curve_every", "val_sequences",
                     "train_sequences", "equal_steps"):
            c = getattr(self, name)
            if c is not None and (not isinstance(c, int) or isinstance(c, bool) or c < 1):
                raise ValueError(f"`{name}`: expected a positive int or None, got {c!r}")
        if self.equal_steps is not None and self.curve_every is None:
            raise ValueError("`equal_steps`: the snapshot is taken by the learning curve; "
                             "set `curve_every` too")
        unknown = [m for m in self.methods if m not in METHOD_NAMES]
        if unknown or not self.methods:
            raise ValueError(f"`methods`: unknown {unknown} or empty; choose from {METHOD_NAMES}")
        unknown = [m for m in (self.seed_methods or ()) if m not in self.methods]
        if unknown:
            raise ValueError(f"`seed_methods`: {unknown} are not in `methods`")
        unknown = [c for c in self.stability_cases if c not in stab.CASES]
        if unknown:
            raise ValueError(f"`stability_cases`: unknown {unknown}; choose from "
                             f"{list(stab.CASES)}")


def seed_plan(budget: LearnedBudget, seed0: Dict[str, float]) -> Dict[str, int]:
    """How many seeds each method of ``budget`` gets, given its methods' seed-0 test
    E_dist (``seed0``; methods missing there count as worst): ``budget.seeds`` for
    the ``seed_methods``, the best GarTrans ablation and the best baseline, 1 for the
    rest (every method gets ``budget.seeds`` when ``seed_methods`` is ``None``)."""
    n = budget.seeds
    if budget.seed_methods is None:
        return {m: (1 if m in SEED_FREE else n) for m in budget.methods}
    full = set(budget.seed_methods)
    for pool in ([m for m in budget.methods if m in GARTRANS and m != FULL],
                 [m for m in budget.methods if m in BASELINES or m == MGN]):
        if pool:
            full.add(min(pool, key=lambda m: seed0.get(m, float("inf"))))
    return {m: (n if m in full and m not in SEED_FREE else 1) for m in budget.methods}
