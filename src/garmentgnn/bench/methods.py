"""The learned methods of ``garmentgnn bench``: each is a recipe
(:mod:`garmentgnn.training.recipes`), the file ``garmentgnn train`` trains, read by the
same loader (:func:`~garmentgnn.training.load_recipe`); nothing here restates a
hyper-parameter.

* the packaged methods, by their table names: GarTrans and the Table 1 variants
  (:data:`GARTRANS`), the DA-, HOOD- and NCS-style baselines (:data:`BASELINES`) and the
  MGN-style learned simulator (:data:`MGN`), each its packaged recipe (:data:`RECIPES`);
* any other recipe, named by its packaged name or its file's path (a new layer's
  ablation, say): it trains the way its module does (:func:`kind`);
* ``LBS only``: the rest garment skinned with the stored skinning weights, no learning.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from garmentgnn.bench import stability as stab
from garmentgnn.models.inputs import CHUNK, HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.training.recipes import model_of, recipe_path

__all__ = ["BASELINES", "DATA", "GARTRANS", "KINDS", "LBS", "LONG", "METHOD_NAMES", "MGN",
           "NCS", "HOOD", "DA", "RECIPES", "SEED_FREE", "LearnedBudget", "is_method", "kind",
           "recipe_of", "seed_plan"]

#: the data settings the frame-parallel methods train and every method is scored on:
#: the data module's defaults (the sizes of :mod:`garmentgnn.models.inputs`), which the
#: packaged recipes keep
DATA: Dict[str, int] = {"chunk": CHUNK, "history": HISTORY, "nystrom_dim": NYSTROM_DIM,
                        "num_landmarks": NUM_LANDMARKS}

NCS, HOOD, DA, MGN, LBS = "NCS-style", "HOOD-style", "DA-style", "MGN-style", "LBS only"
#: the GarTrans rows (full GarTrans first, the variant every comparison is made
#: against) and their packaged recipes
GARTRANS: Dict[str, str] = {
    "GarTrans (SAT)": "gartrans",
    "GarTrans w/o edge processing": "ablations/wo_edge",
    "GarTrans w/o edge gating": "ablations/wo_gating",
    "GarTrans structure-aware transformer": "ablations/structure_aware",
    "GarTrans GAT": "ablations/gat",
    "GarTrans w/o unsupervised loss": "ablations/wo_unsup",
}
#: full GarTrans
FULL = next(iter(GARTRANS))
#: the baselines' packaged recipes
BASELINES: Dict[str, str] = {NCS: "baselines/ncs", HOOD: "baselines/hood",
                             DA: "baselines/da"}
#: every packaged method's recipe
RECIPES: Dict[str, str] = {**GARTRANS, **BASELINES, MGN: "mgn"}
METHOD_NAMES: Tuple[str, ...] = tuple(RECIPES) + (LBS,)
#: methods without training or randomness: run for the first seed only
SEED_FREE: Tuple[str, ...] = (LBS,)
#: how a recipe's method trains and predicts, by its module (and for a baseline, its
#: model): frame-parallel GarTrans on chunks with its schedule; a frame-parallel or
#: autoregressive baseline on chunks; NCS-style, one model per test garment on its
#: poses; a learned simulator on windows of frames, rolled out
KINDS = {"GarTransModule": "gartrans", "BaselineModule": "baseline",
         "NCSStyle": "ncs", "SimulatorModule": "simulator"}


def recipe_of(method: str) -> str:
    """The recipe that trains ``method``: a packaged method's (:data:`RECIPES`; full
    GarTrans's for :data:`LONG`), or
    ``method`` itself, a recipe's packaged name or file path; ``ValueError`` naming the
    choices when it is neither (or ``LBS only``, which trains nothing)."""
    if method in RECIPES or method == LONG:
        return RECIPES[FULL if method == LONG else method]
    try:
        recipe_path(method)
    except (ValueError, TypeError):
        raise ValueError(f"`methods`: {method!r} is neither a method ({', '.join(METHOD_NAMES)}) "
                         f"nor a recipe (a packaged name or a YAML file)") from None
    return str(method)


def kind(method: str) -> str:
    """``"gartrans"``, ``"baseline"``, ``"ncs"``, ``"simulator"`` (:data:`KINDS`) or
    ``"lbs"``: how ``method`` trains and predicts."""
    if method == LBS:
        return "lbs"
    names = {k: str(v or "").rsplit(".", 1)[-1] for k, v in model_of(recipe_of(method)).items()}
    found = KINDS.get(names["model"]) if names["module"] == "BaselineModule" else None
    found = found or KINDS.get(names["module"])
    if found is None:
        raise ValueError(f"`methods`: the recipe {method!r} trains {names['module'] or 'no'} "
                         f"module; the bench trains {', '.join(k for k in KINDS if 'Module' in k)}")
    return found


def is_method(method: str) -> bool:
    """Whether the bench can run ``method``: a packaged method or a recipe."""
    if method in METHOD_NAMES:
        return True
    try:
        kind(method)
    except (ValueError, TypeError):
        return False
    return True


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
        methods: the methods to run: names of :data:`METHOD_NAMES`, or recipes (a
            packaged name such as ``ablations/paper``, or a YAML file's path).
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
        unknown = [m for m in self.methods if not is_method(m)]
        if unknown or not self.methods:
            raise ValueError(f"`methods`: unknown {unknown} or empty; choose from "
                             f"{METHOD_NAMES} or give a recipe (a packaged name or a YAML "
                             f"file, e.g. ablations/gat)")
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
    kinds = {m: kind(m) for m in budget.methods}
    for pool in ([m for m in budget.methods if kinds[m] == "gartrans" and m != FULL],
                 [m for m in budget.methods if kinds[m] in ("baseline", "ncs", "simulator")]):
        if pool:
            full.add(min(pool, key=lambda m: seed0.get(m, float("inf"))))
    return {m: (n if m in full and m not in SEED_FREE else 1) for m in budget.methods}
