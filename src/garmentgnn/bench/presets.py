"""The ``garmentgnn bench`` presets: which cases, simulator budgets, extra reports and
learned-method budget one run covers (``tiny``: the CI smoke test; ``small``: a quick
run; ``medium``, ``converge``, ``learn``: the learned methods; see docs/bench.md)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Dict, List, Optional, Tuple

from garmentgnn.bench import methods, precision
from garmentgnn.bench.sequences import case_item

__all__ = ["PRESET_NAMES", "Preset", "SimBudget", "preset"]


@dataclass(frozen=True)
class SimBudget:
    """A reference-simulator setting: ``substeps`` per frame, ``max_newton`` per substep."""

    substeps: int
    max_newton: int

    @property
    def name(self) -> str:
        return f"sim[sub={self.substeps},newton<={self.max_newton}]"


@dataclass(frozen=True)
class Preset:
    """What one ``garmentgnn bench`` run does.

    Attributes:
        name: preset name.
        cases: accuracy cases (:func:`garmentgnn.bench.sequences.case_item`).
        seeds: default number of seeds (motion jitter seeds ``0..seeds-1``).
        reference: the finest simulator budget, used as ground truth.
        budgets: cheaper simulator budgets compared against it.
        methods: further registered methods run on every accuracy case (``"lbs"``, ...).
        stability_item: the small case the stability suite perturbs.
        stability_cases: names from :data:`garmentgnn.bench.stability.CASES`.
        stability_settings: simulator settings of the stability runs.
        batches: batch sizes of the throughput sweep (batchable methods).
        warmup, repeats: timing warm-up calls and timed calls (median reported).
        threads: ``torch.set_num_threads`` during the run.
        scaling_item, scaling_resolutions: :mod:`garmentgnn.bench.scaling`'s garment
            (a case item; its resolution is replaced) and the requested resolutions.
        leaveout: run :mod:`garmentgnn.bench.leaveout` on the first accuracy case
            (supervised loss terms against its reference simulation).
        precision_methods: :data:`garmentgnn.bench.precision.METHODS` keys run in
            float32 / bfloat16 / float16 on the first accuracy case.
        long_item: the case of :func:`garmentgnn.bench.precision.run_long`.
        model_inputs: ``history``, ``nystrom_dim``, ``num_landmarks`` of the GarTrans
            inputs (the data module's settings in ``garmentgnn/recipes/gartrans.yaml``).
        dataset: the :func:`garmentgnn.data.generate.preset` the learned methods train
            and are tested on (generated under ``OUT/data`` unless ``run(data=...)``).
        learned: what :mod:`garmentgnn.bench.learned` trains (methods, seeds, epochs,
            schedule window); ``None``: no learned methods.
        engines: run :func:`garmentgnn.bench.engines.default_settings` on
            ``engine_per_group`` test sequences of each held-out group of the dataset
            (:func:`~garmentgnn.bench.engines.pick_sequences`), ``engine_frames``
            frames each (``None``: all).
        data_workers: worker processes generating the dataset.
        These extra reports run for the first seed only.
    """

    name: str
    cases: Tuple[Dict[str, Any], ...]
    seeds: int
    reference: SimBudget
    budgets: Tuple[SimBudget, ...]
    methods: Tuple[str, ...] = ("lbs",)
    stability_item: Optional[Dict[str, Any]] = None
    stability_cases: Tuple[str, ...] = ()
    stability_settings: Dict[str, Any] = field(default_factory=dict)
    batches: Tuple[int, ...] = (1, 8, 32)
    warmup: int = 2
    repeats: int = 5
    threads: int = 1
    scaling_item: Optional[Dict[str, Any]] = None
    scaling_resolutions: Tuple[int, ...] = ()
    leaveout: bool = False
    precision_methods: Tuple[str, ...] = ()
    long_item: Optional[Dict[str, Any]] = None
    model_inputs: Dict[str, int] = field(default_factory=lambda: {
        k: methods.DATA[k] for k in ("history", "nystrom_dim", "num_landmarks")})
    dataset: Optional[str] = None
    learned: Optional[methods.LearnedBudget] = None
    data_workers: int = 1
    engines: bool = False
    engine_per_group: int = 1
    engine_frames: Optional[int] = 20

    def method_names(self) -> List[str]:
        return [self.reference.name] + [b.name for b in self.budgets] + list(self.methods)

    def learned_only(self) -> "Preset":
        """This preset with its simulator parts left out: only the learned methods (and
        their stability suite, where the budget has one) run."""
        return replace(self, cases=(), budgets=(), stability_cases=(), scaling_item=None,
                       leaveout=False, precision_methods=(), long_item=None, engines=False)


def preset(name: str) -> Preset:
    """``tiny`` (a smoke test: about 5 min on 2 cores, 2 of them generating its dataset),
    ``small`` (about 70 min, half of it generating its dataset) or ``medium`` (the
    learned methods on equal wall-clock budgets, seeds and held-out groups, with the
    engines; about 150 min on 2 cores with an existing dataset) or ``converge`` (every
    learned method to a validation plateau on ``small``, learning curves, equal steps and
    equal time; about 3.2 h on 2 cores; see docs/bench.md)."""
    if name == "tiny":
        return Preset(
            name="tiny",
            cases=(case_item("skirt-walk", "skirt", 200, "walk", 4, {"length": "mini"}),),
            seeds=1,
            reference=SimBudget(8, 30),
            budgets=(SimBudget(1, 30), SimBudget(4, 5)),
            stability_item=case_item("stability", "skirt", 200, "walk", 3, {"length": "mini"}),
            stability_cases=("stiff_x1000", "fast_x5", "zero_area_face"),
            batches=(1, 8), warmup=1, repeats=3,
            scaling_item=_SCALING_ITEM, scaling_resolutions=(300, 600), leaveout=True,
            precision_methods=tuple(precision.METHODS),
            long_item=case_item("long-skirt-walk", "skirt", 200, "walk", 100,
                                {"length": "mini"}),
            dataset="tiny", data_workers=1,
            learned=methods.LearnedBudget(seeds=1, epochs=1, window=1, ncs_epochs=1,
                                              stability_cases=("zero_area_face",)))
    if name == "small":
        return Preset(
            name="small",
            cases=(case_item("skirt-walk", "skirt", 300, "walk", 10, {"length": "knee"}),
                   case_item("tank-arm_swing", "tshirt", 300, "arm_swing", 10,
                             {"sleeves": "none"})),
            seeds=2,
            reference=SimBudget(8, 50),
            budgets=(SimBudget(1, 30), SimBudget(2, 30), SimBudget(4, 30), SimBudget(4, 5),
                     SimBudget(4, 10)),
            stability_item=case_item("stability", "skirt", 200, "walk", 6, {"length": "mini"}),
            stability_cases=("baseline", "stiff_x1000", "extreme_pose", "fast_x5",
                             "sliver_face", "zero_area_face"),
            batches=(1, 4, 16, 64),
            scaling_item=_SCALING_ITEM, scaling_resolutions=(1000, 2000, 4000, 8000, 14000),
            leaveout=True, precision_methods=tuple(precision.METHODS),
            long_item=case_item("long-skirt-walk", "skirt", 200, "walk", 1000,
                                {"length": "mini"}),
            # sized in docs/bench.md ("Learned methods")
            dataset="small", data_workers=2,
            learned=methods.LearnedBudget(
                seeds=3, epochs=4, window=1, ncs_epochs=8,
                # not long_1000: over 5 min per method on this machine (docs/bench.md)
                stability_cases=("baseline", "stiff_x1000", "extreme_pose", "fast_x5",
                                 "sliver_face", "zero_area_face")))
    if name == "medium":
        # the learned methods on the Blender `medium` dataset (generate it first, pass
        # it with --data: generating it here takes hours); no simulator cases: the
        # engines are points on the learned methods' error-against-run-time plot
        return Preset(
            name="medium", cases=(), seeds=1, reference=SimBudget(8, 50), budgets=(),
            methods=(), batches=(1, 8, 32), warmup=1, repeats=3, threads=2,
            dataset="medium", data_workers=2,
            # sized in docs/bench.md ("medium"): 15 runs of 5 min + 25 min + scoring 40
            # test sequences (10 per held-out group) per run
            learned=methods.LearnedBudget(
                seeds=3, epochs=1000, window=2, ncs_epochs=1000, minutes=5.0,
                epoch_chunks=50, seed_methods=(next(iter(methods.GARTRANS)),),
                long_minutes=25.0, test_sequences=40),
            engines=True, engine_per_group=1, engine_frames=20)
    if name == "converge":
        # every learned method to a validation plateau on the Blender `small` dataset
        # (generate it with --engine blender, pass it with --data), the same wall time
        # and the same step snapshot for all: sized in docs/bench.md ("converge")
        return Preset(
            name="converge", cases=(), seeds=1, reference=SimBudget(8, 50), budgets=(),
            methods=(), batches=(1, 8, 32), warmup=1, repeats=3, threads=2,
            dataset="small", data_workers=2,
            learned=methods.LearnedBudget(
                seeds=3, epochs=1000, window=3, ncs_epochs=1000, minutes=10.0,
                seed_methods=(next(iter(methods.GARTRANS)),), curve_every=100,
                equal_steps=500))
    if name == "learn":
        # `converge`'s design on the Blender `learn` dataset (420 sequences; generate it with
        # --engine blender, pass it with --data), batched: sized in docs/bench.md ("learn");
        # hours on 2 cores, resumable across sessions
        conv = preset("converge")
        return replace(conv, name="learn", dataset="learn", learned=replace(
            conv.learned, minutes=30.0, epoch_chunks=400, batch_size=16, lr_factor=4.0,
            curve_every=400, val_sequences=8, train_sequences=8, equal_steps=200,
            test_sequences=40))
    raise ValueError(f"`preset`: unknown {name!r}; choose one of {PRESET_NAMES}")


PRESET_NAMES = ("tiny", "small", "medium", "converge", "learn")
#: the scaling garment (its resolution is replaced per size): a knee skirt, walking
_SCALING_ITEM = case_item("scaling-skirt-walk", "skirt", 1000, "walk", 8, {"length": "knee"})


# --------------------------------------------------------------------------- methods
