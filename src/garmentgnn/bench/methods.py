"""The learned methods of ``garmentgnn bench``: each is a recipe
(:mod:`garmentgnn.training.recipes`), the file ``garmentgnn train`` trains, read by the
same loader (:func:`~garmentgnn.training.load_recipe`); nothing here restates a
hyper-parameter.

* the packaged methods, by their table names: GarTrans and the Table 1 variants
  (:data:`GARTRANS`), the DA-, HOOD- and NCS-style baselines (:data:`BASELINES`) and the
  MGN-style learned simulator (:data:`MGN`), each its packaged recipe (:data:`RECIPES`);
* any other recipe, named by its packaged name or its file's path (a new layer's
  ablation, a new method): it trains and predicts the way its module says (the method
  protocol of :class:`~garmentgnn.training.GarmentModule`; :func:`module_class`);
* ``LBS only``: the rest garment skinned with the stored skinning weights, no learning.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Tuple

from garmentgnn.bench import stability as stab
from garmentgnn.models.inputs import CHUNK, HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.training.base import GarmentModule
from garmentgnn.training.recipes import import_class, model_of, recipe_path

__all__ = ["BASELINES", "DATA", "GARTRANS", "LBS", "LONG", "METHOD_NAMES", "MGN",
           "NCS", "HOOD", "DA", "RECIPES", "SEED_FREE", "LearnedBudget", "is_method",
           "module_class", "per_garment", "recipe_of", "seed_plan"]

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


def module_class(method: str) -> type:
    """The :class:`~garmentgnn.training.GarmentModule` class that trains ``method`` (its
    recipe's ``model: class_path``), whose method protocol says how the bench trains,
    predicts and times it; ``ValueError`` naming the choices where it is none."""
    recipe = recipe_of(method)
    path = model_of(recipe)["module"]
    try:
        cls = import_class(str(path)) if path else None
    except ValueError:
        cls = None
    if not (isinstance(cls, type) and issubclass(cls, GarmentModule)):
        raise ValueError(f"`methods`: the recipe {method!r} trains {path or 'no'} module, "
                         f"which is not a garmentgnn method (a GarmentModule subclass "
                         f"importable from its class_path)")
    return cls


def per_garment(method: str) -> bool:
    """Whether ``method`` trains one model per (garment, body) (its module's
    ``trains_per_garment`` of its recipe's model class)."""
    model = model_of(recipe_of(method))["model"]
    return bool(model) and module_class(method).trains_per_garment(import_class(str(model)))


def is_method(method: str) -> bool:
    """Whether the bench can run ``method``: a packaged method or a recipe."""
    if method in METHOD_NAMES:
        return True
    try:
        module_class(method)
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
    the ``seed_methods`` and the best method of each family (its module's ``family``: the
    best GarTrans ablation, full GarTrans aside, and the best baseline), 1 for the rest
    (every method gets ``budget.seeds`` when ``seed_methods`` is ``None``)."""
    n = budget.seeds
    if budget.seed_methods is None:
        return {m: (1 if m in SEED_FREE else n) for m in budget.methods}
    full = set(budget.seed_methods)
    family = {m: module_class(m).family for m in budget.methods if m not in SEED_FREE}
    for name in sorted(set(family.values())):
        pool = [m for m, f in family.items() if f == name and m != FULL]
        if pool:
            full.add(min(pool, key=lambda m: seed0.get(m, float("inf"))))
    return {m: (n if m in full and m not in SEED_FREE else 1) for m in budget.methods}
