"""The learned methods inside ``garmentgnn bench``: every method trained and evaluated on
the same generated dataset and data split.

One bench run (:func:`garmentgnn.bench.harness.run`) with a preset that has a
:class:`LearnedBudget`:

1. uses a generated dataset (:func:`prepare_dataset`: ``garmentgnn.data.generate``'s
   preset of the bench preset, generated -- resumably -- under ``OUT/data``, or an
   existing folder given by ``--data``);
2. trains each method of the budget for each training seed on the ``train`` split with
   the budget's fixed number of epochs (:class:`LearnedRunner`), resuming an interrupted
   training from its checkpoint under ``OUT/models/<method>--s<seed>/``;
3. scores it on the ``test`` split with :func:`garmentgnn.metrics.evaluate`
   (frame-weighted means over every frame of every test sequence, as
   :func:`garmentgnn.training.evaluate.evaluate_split`), times it
   (:func:`~garmentgnn.bench.timing.batch_sweep`, :func:`~garmentgnn.bench.timing.peak_memory`)
   and returns one record of kind ``"learned"`` per (method, seed); the harness writes
   it atomically and a rerun skips it.

Methods (:data:`METHOD_NAMES`):

* GarTrans and the Table 1 variants (:data:`GARTRANS`): :class:`GarTransModule` with
  ``configs/gartrans.yaml``'s hyperparameters (:data:`GARTRANS_MODEL`, :data:`DATA`,
  :data:`SCHEDULE`; the ablations override what ``configs/ablations/*.yaml`` override),
  trained by a Lightning ``Trainer`` with the :class:`ProgressiveSchedule` callback (its
  window from the budget) and ``ModelCheckpoint(save_last=True)``.  Evaluated
  frame-parallel (the paper's mode, ``training.evaluate.predict(..., "gartrans")``).
* ``DA-style`` (:class:`~garmentgnn.models.baselines.DAStyle`): supervised, the
  supervised terms of :class:`GarTransLoss` against the simulated garment.
* ``HOOD-style`` (:class:`~garmentgnn.models.baselines.HOODStyle`): physics terms only
  (:data:`PHYSICS_LOSS`, inertia included); trained one step at a time on its own
  rollout of each training chunk (started from the LBS garment of the two frames before
  the chunk, inputs detached between steps); tested by an autoregressive rollout over
  the whole sequence from the LBS garment of frames 0 and 1, pinned vertices driven by LBS.
* ``NCS-style`` (:class:`~garmentgnn.models.baselines.NCSStyle`): garment-specific and
  self-supervised, so one model per (garment, body) of the *test* split, trained with
  the physics terms only on the poses of that garment's own test sequences -- never
  on their simulated positions (the items' ``gt`` is removed before the loss).
* ``LBS only``: the rest garment skinned with the simulator's transferred weights,
  no learning: the reference row of the table.

Each plain-PyTorch baseline is trained with Adam (:data:`BASELINES`), one chunk per
step, the chunk order of :class:`EpochShuffleSampler` seeded by the training seed.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import re
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import lightning as L
import torch
from torch import Tensor, nn

from garmentgnn.bench import stability as stab
from garmentgnn.bench.model_inputs import BenchChunks
from garmentgnn.bench.report import METRICS, UNITS, _fmt, _mean_std, _table, plot_summary
from garmentgnn.bench.timing import batch_sweep, peak_memory
from garmentgnn.data import store
from garmentgnn.data.keys import body_key, garment_key
from garmentgnn.losses.gartrans_loss import PHYSICS, SUPERVISED, GarTransLoss, LossInputs
from garmentgnn.metrics import evaluate
from garmentgnn.models.baselines import CoarseLevel, DAStyle, GarmentScene, HOODStyle, NCSStyle
from garmentgnn.training import (EpochShuffleSampler, GarmentDataModule, GarTransModule,
                                 ProgressiveSchedule, SequenceChunks)
from garmentgnn.training.evaluate import lbs_coarse
from garmentgnn.training.evaluate import predict as gartrans_predict

KIND = "learned"
#: the record kind of :meth:`LearnedRunner.stability_record`
STABILITY_KIND = "learned_stability"

# --------------------------------------------------------------------------- methods
#: ``configs/gartrans.yaml``'s ``model:`` section (a test compares them with the file)
GARTRANS_MODEL: Dict[str, Any] = {
    "rest_layer": "gt", "blend_layer": "gt", "dynamic_layer": "sat", "heads": 4,
    "fps": 30.0, "lr": 0.003, "edge_reduction": "sum", "collision_margin": 0.002,
    "collision_projection": 0.002, "loss_weights": {"edge": 150.0, "curv": 200.0},
    "blend_shape": False, "strain_limit": 10, "use_body": True}
#: ``configs/gartrans.yaml``'s ``data:`` section (without ``root`` and ``num_workers``)
DATA: Dict[str, int] = {"chunk": 8, "history": 3, "nystrom_dim": 16, "num_landmarks": 64}
#: the ``ProgressiveSchedule`` arguments of ``configs/gartrans.yaml`` except the windows
#: (``window``, ``window2``), which the budget scales (the config's 4 and 3 belong to its
#: 30 epochs; ``window2`` defaults to ``window``)
SCHEDULE: Dict[str, Any] = {"threshold": 0.03, "threshold2": 0.1, "supervised_scale": 0.05,
                            "extra_terms": ["curv"], "extra_from": 1}


@dataclass(frozen=True)
class Variant:
    """A GarTrans row: ``config`` names the ``configs/ablations/<config>.yaml`` it mirrors
    (``None``: ``configs/gartrans.yaml`` itself); ``model`` / ``schedule`` are its
    overrides of :data:`GARTRANS_MODEL` / :data:`SCHEDULE`."""

    config: Optional[str]
    model: Dict[str, Any] = field(default_factory=dict)
    schedule: Dict[str, Any] = field(default_factory=dict)


GARTRANS: Dict[str, Variant] = {
    "GarTrans (SAT)": Variant(None),
    "GarTrans w/o edge processing": Variant("wo_edge", {"dynamic_layer": "gt"}),
    "GarTrans w/o edge gating": Variant("wo_gating", {"dynamic_layer": "gt_edge"}),
    "GarTrans structure-aware transformer": Variant("structure_aware",
                                                    {"dynamic_layer": "structure_aware"}),
    "GarTrans GAT": Variant("gat", {"dynamic_layer": "gat"}),
    "GarTrans w/o unsupervised loss": Variant("wo_unsup", schedule={"max_phase": 1}),
}
NCS, HOOD, DA, LBS = "NCS-style", "HOOD-style", "DA-style", "LBS only"
METHOD_NAMES: Tuple[str, ...] = tuple(GARTRANS) + (NCS, HOOD, DA, LBS)
#: methods without training or randomness: run for the first seed only
SEED_FREE: Tuple[str, ...] = (LBS,)
#: the reference simulator, with the dataset's settings, in the learned stability suite
SIMULATOR = "simulator (dataset settings)"
#: stability cases the simulator leaves out there (``long_1000``: about 50 min)
SIMULATOR_SKIPS: Tuple[str, ...] = ("long_1000",)
#: frames per call of a frame-parallel method in the stability suite (memory: GarTrans on
#: all 1000 frames of ``long_1000`` at once needs over 24 GB); HOOD-style rolls out the
#: whole sequence in one call
STABILITY_CHUNK = 50

#: the physics-only objective of HOOD and NCS (as ``tests/test_baselines.py`` trains HOOD)
PHYSICS_LOSS: Dict[str, Any] = {"weights": {"inertia": 1.0, "bending": 1.0},
                                "enabled": tuple(PHYSICS)}
#: model arguments and Adam learning rate of each baseline
BASELINES: Dict[str, Dict[str, Any]] = {
    DA: {"model": {"hidden": 64, "heads": 2, "num_layers": 3}, "lr": 1e-3},
    HOOD: {"model": {"hidden": 64, "fine_blocks": 1, "coarse_blocks": 2}, "lr": 1e-3,
           "coarse": {"ratio": 4, "k": 6}},
    NCS: {"model": {"history": 1, "hidden": 128}, "lr": 1e-4},
}


@dataclass(frozen=True)
class LearnedBudget:
    """What the learned part of a bench preset trains.

    Attributes:
        seeds: training seeds ``0..seeds-1`` (``lightning.seed_everything(seed)``).
        epochs: passes over the ``train`` split (GarTrans variants, DA, HOOD).
        window: :class:`ProgressiveSchedule` window in epochs.
        ncs_epochs: passes of each NCS model over its own garment's test poses.
        methods: the names of :data:`METHOD_NAMES` to run.
        stability_cases: :data:`garmentgnn.bench.stability.CASES` run by each method
            (first seed's model) and the simulator on the first test sequence
            (:meth:`LearnedRunner.stability_record`).
    """

    seeds: int = 1
    epochs: int = 1
    window: int = 1
    ncs_epochs: int = 1
    methods: Tuple[str, ...] = METHOD_NAMES
    stability_cases: Tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for name in ("seeds", "epochs", "window", "ncs_epochs"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"`{name}`: expected a positive int, got {v!r}")
        unknown = [m for m in self.methods if m not in METHOD_NAMES]
        if unknown or not self.methods:
            raise ValueError(f"`methods`: unknown {unknown} or empty; choose from {METHOD_NAMES}")
        unknown = [c for c in self.stability_cases if c not in stab.CASES]
        if unknown:
            raise ValueError(f"`stability_cases`: unknown {unknown}; choose from {list(stab.CASES)}")


# --------------------------------------------------------------------------- dataset
@dataclass
class DatasetInfo:
    """A generated dataset's folder, spec name, fingerprint (of its ok items' ids,
    splits, frame counts and generating code versions) and ok sequence / frame counts
    per split."""

    root: Path
    name: str
    fingerprint: str
    sequences: Dict[str, int]
    frames: Dict[str, int]

    @property
    def case(self) -> str:
        """The records' ``case``: another dataset gives other records."""
        return f"{self.name}-{self.fingerprint[:8]}/test"

    def to_json(self) -> Dict[str, Any]:
        return {"root": str(self.root), "name": self.name, "fingerprint": self.fingerprint,
                "sequences": dict(self.sequences), "frames": dict(self.frames)}


def prepare_dataset(root, preset_name: Optional[str] = None, workers: int = 1,
                    progress: bool = True) -> DatasetInfo:
    """The dataset under ``root``; with ``preset_name``, first generate (or finish
    generating) that :func:`garmentgnn.data.generate.preset` there.

    Raises ``ValueError`` naming ``data`` when ``root`` holds no manifest or no ok
    ``train`` / ``test`` sequences."""
    root = Path(root)
    if preset_name is not None:
        from garmentgnn.data import generate, preset
        if not isinstance(workers, int) or workers < 0:
            raise ValueError(f"`workers`: expected a non-negative int, got {workers!r}")
        generate(preset(preset_name), root, workers=workers, progress=progress,
                 log=None if progress else (lambda msg: None))
    try:
        man = store.read_manifest(root)
    except (OSError, ValueError) as err:
        raise ValueError(f"`data`: {root} is not a generated dataset (no readable "
                         f"manifest.json: {err})") from err
    ok = [r for r in man.get("items", []) if r.get("status") == "ok"]
    seqs = {s: sum(r["split"] == s for r in ok) for s in ("train", "val", "test")}
    frames = {s: sum(int(r["num_frames"]) for r in ok if r["split"] == s)
              for s in ("train", "val", "test")}
    for s in ("train", "test"):
        if not seqs[s]:
            raise ValueError(f"`data`: {root} has no ok {s!r} sequences ({man.get('counts')})")
    digest = hashlib.sha1(json.dumps(sorted(
        (r["id"], r["split"], int(r["num_frames"]), str((r.get("code") or {}).get("version")))
        for r in ok)).encode())
    return DatasetInfo(root, str(man.get("name", root.name)), digest.hexdigest(), seqs, frames)


# --------------------------------------------------------------------------- helpers
_FRAME_KEYS = ("rotations", "translation", "gt", "body_pos", "frames")


def frames_of(item: Dict[str, Any], idx: Tensor) -> Dict[str, Any]:
    """The :class:`SequenceChunks` item restricted to frames ``idx`` (per-frame keys
    indexed, static keys shared)."""
    return dict(item, **{k: item[k][idx] for k in _FRAME_KEYS if k in item})


def history_slot(item: Dict[str, Any], j: int) -> Dict[str, Any]:
    """The item whose current pose is history slot ``j`` (``-1``: the frame itself,
    ``-2``: one frame earlier, ...), for :func:`lbs_coarse` and the pose models."""
    H = item["rotations"].shape[1]
    if not -H <= j <= -1:
        raise ValueError(f"`j`: expected -{H} <= j <= -1, got {j}")
    end = H + j + 1
    return dict(item, rotations=item["rotations"][:, :end],
                translation=item["translation"][:, :end])


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", s).strip("_")


def _save(path: Path, obj: Dict[str, Any]) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    store.atomic_write_bytes(path, buf.getvalue())


@contextlib.contextmanager
def _quiet_lightning() -> Iterator[None]:
    """Lightning's info messages and possible-user warnings off inside the block."""
    logger = logging.getLogger("lightning.pytorch")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", module=r"lightning\..*")
            warnings.filterwarnings("ignore", message=r".*(num_workers|does not have many "
                                                      r"workers|Checkpoint directory).*")
            yield
    finally:
        logger.setLevel(level)


class TrainClock(L.Callback):
    """Wall time of the training epochs and their count, kept in the checkpoint (so a
    resumed run reports the total); ``restored_epochs``: epochs done before this fit."""

    def __init__(self) -> None:
        self.seconds, self.epochs, self.restored_epochs = 0.0, 0, 0
        self._t0 = 0.0

    def state_dict(self) -> Dict[str, Any]:
        return {"seconds": self.seconds, "epochs": self.epochs}

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.seconds = float(state["seconds"])
        self.epochs = self.restored_epochs = int(state["epochs"])

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._t0 = time.perf_counter()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.seconds += time.perf_counter() - self._t0
        self.epochs += 1


@dataclass
class _Predictor:
    """A trained method: ``predict(ds, i, item)`` the garment ``[T, V, 3]`` of ``item``,
    item ``i`` of ``ds`` (the whole-sequence test set, or the :class:`BenchChunks` of a
    stability case); ``make_batch(item, b)`` a function predicting ``b`` frames of
    ``item`` per call (inputs prepared outside it) for the timing sweep."""

    predict: Callable[[SequenceChunks, int, Dict[str, Any]], Tensor]
    make_batch: Callable[[Dict[str, Any], int], Callable[[], Any]]
    note: str


def _cycled(item: Dict[str, Any], b: int) -> Dict[str, Any]:
    return frames_of(item, torch.arange(b) % item["gt"].shape[0])


# --------------------------------------------------------------------------- runner
class LearnedRunner:
    """Trains and scores the learned methods on one dataset (see the module doc).

    Args:
        data: from :func:`prepare_dataset`.
        budget: epochs, schedule window, methods.
        out: the bench folder (checkpoints under ``out/models``).
        batches, warmup, repeats: the preset's timing settings.
    """

    def __init__(self, data: DatasetInfo, budget: LearnedBudget, out, batches: Sequence[int],
                 warmup: int, repeats: int) -> None:
        if not isinstance(data, DatasetInfo):
            raise ValueError(f"`data`: expected a DatasetInfo, got {type(data).__name__}")
        if not isinstance(budget, LearnedBudget):
            raise ValueError(f"`budget`: expected a LearnedBudget, got {type(budget).__name__}")
        self.data, self.budget, self.out = data, budget, Path(out)
        self.batches, self.warmup, self.repeats = tuple(batches), warmup, repeats
        kw = dict(history=DATA["history"], nystrom_dim=DATA["nystrom_dim"],
                  num_landmarks=DATA["num_landmarks"], cache_size=64)
        self.train = SequenceChunks(data.root, "train", chunk=DATA["chunk"], **kw)
        self.test = SequenceChunks(data.root, "test", chunk=10 ** 9, **kw)  # whole sequences
        self.test_chunks = SequenceChunks(data.root, "test", chunk=DATA["chunk"], **kw)  # NCS
        self._scenes: Dict[str, Tuple[GarmentScene, Optional[CoarseLevel]]] = {}
        self._trained: Dict[Tuple[str, int], Tuple[_Predictor, Dict[str, Any]]] = {}

    # -- records ----------------------------------------------------------------------
    def record(self, method: str, seed: int) -> Dict[str, Any]:
        """Train (or resume) ``method`` with ``seed``, evaluate and time it; exceptions
        (e.g. :class:`NonFiniteLossError`) give a failed record with their message."""
        if method not in METHOD_NAMES:
            raise ValueError(f"`method`: unknown {method!r}; choose from {METHOD_NAMES}")
        rec: Dict[str, Any] = {"kind": KIND, "method": method, "case": self.data.case,
                               "seed": seed, "dataset": self.data.to_json()}
        t0 = time.perf_counter()
        try:
            pred, info = self.trained(method, seed)
            rec.update(info)
            rec["metrics"], rec["test_frames"] = self.evaluate(pred)
            rec["timing"] = self.timing(pred)
            rec.update(status="ok", message="ok")
        except Exception as err:
            rec.update(status="failed", message=f"{type(err).__name__}: {err}",
                       traceback=traceback.format_exc(limit=6))
        rec["seconds"] = time.perf_counter() - t0
        return rec

    def trained(self, method: str, seed: int) -> Tuple[_Predictor, Dict[str, Any]]:
        """``method`` trained with ``seed`` (trained, or resumed from its checkpoint, on
        the first call; kept for the next)."""
        key = (method, seed)
        if key not in self._trained:
            L.seed_everything(seed, workers=True, verbose=False)
            if method in GARTRANS:
                self._trained[key] = self._gartrans(method, seed)
            elif method == DA:
                self._trained[key] = self._da(seed)
            elif method == HOOD:
                self._trained[key] = self._hood(seed)
            elif method == NCS:
                self._trained[key] = self._ncs(seed)
            else:
                self._trained[key] = self._lbs()
        return self._trained[key]

    def stability_record(self, method: str, seed: int, case: str) -> Dict[str, Any]:
        """Stability ``case`` (:mod:`garmentgnn.bench.stability`) built on the first test
        sequence of the dataset (its body, garment, motion and motion seed), predicted by
        ``method`` trained with ``seed`` -- or by :data:`SIMULATOR` with the dataset's
        simulator settings -- and scored like the simulator's cases.  The model sees the
        case as the data module would present it (:class:`BenchChunks`); no learned
        method takes the material as input, so ``stiff_x1000`` changes only how its
        output is scored."""
        if method not in METHOD_NAMES + (SIMULATOR,):
            raise ValueError(f"`method`: unknown {method!r}; choose from "
                             f"{METHOD_NAMES + (SIMULATOR,)}")
        base = self.test.records[0]
        item = {k: v for k, v in base.items() if k in ("garment", "body", "motion", "material",
                                                        "settings")}
        if method == SIMULATOR:
            predict = stab.simulator_predictor(**item["settings"])
        else:
            def predict(seq) -> Tensor:
                pred, _ = self.trained(method, seed)
                ds = BenchChunks(seq, chunk=None if method == HOOD else STABILITY_CHUNK,
                                 history=DATA["history"], nystrom_dim=DATA["nystrom_dim"],
                                 num_landmarks=DATA["num_landmarks"])
                with torch.no_grad():
                    return torch.cat([pred.predict(ds, i, ds[i]) for i in range(len(ds))])
        rec = stab.run_case(case, dict(item, name=case), int(base["seed"]), predict, method)
        rec.update(kind=STABILITY_KIND, seed=seed, motion_seed=int(base["seed"]),
                   sequence=base["id"])
        return rec

    def evaluate(self, pred: _Predictor) -> Tuple[Dict[str, float], int]:
        """Means of :func:`garmentgnn.metrics.evaluate` over every frame of every test
        sequence (``collision`` renamed ``collision_rate``).  Scored one frame at a time
        (the metrics are per-frame means, so this equals scoring a sequence at once; the
        exact body distance search runs 1.5x faster per frame than batched)."""
        sums: Dict[str, float] = {}
        frames = 0
        for i in range(len(self.test)):
            item = self.test[i]
            with torch.no_grad():
                P = pred.predict(self.test, i, item)
            B, V = item["gt"].shape[:2]
            if tuple(P.shape) != (B, V, 3):
                raise RuntimeError(f"predicted {tuple(P.shape)} for {item['seq_id']}, expected "
                                   f"{(B, V, 3)}")
            if not torch.isfinite(P).all():
                raise RuntimeError(f"{int((~torch.isfinite(P)).sum())} non-finite coordinates "
                                   f"predicted for {item['seq_id']}")
            for t in range(B):
                res = evaluate(P[t:t + 1].float(), item["gt"][t:t + 1], item["faces"],
                               item["body_pos"][t:t + 1], item["body_faces"])
                for k, v in res.items():
                    sums[k] = sums.get(k, 0.0) + v
            frames += B
        m = {k: v / frames for k, v in sums.items()}
        m["collision_rate"] = m.pop("collision")
        return m, frames

    def timing(self, pred: _Predictor) -> Dict[str, Any]:
        """Latency at batch 1, throughput at the best batch, peak memory of predicting
        the first test sequence."""
        item = self.test[0]
        with torch.no_grad():
            mem = peak_memory(lambda: pred.predict(self.test, 0, item))
        t = batch_sweep(lambda b: pred.make_batch(item, b), self.batches, self.warmup,
                        self.repeats)
        t.update(peak_mem_mb=mem["peak_mb"], memory_method=mem["method"],
                 timed_sequence=item["seq_id"], note=pred.note,
                 memory_note=f"one prediction of all {item['gt'].shape[0]} frames of the "
                             "timed sequence")
        return t

    # -- shared pieces -----------------------------------------------------------------
    def _scene(self, ds: SequenceChunks, idx: int, coarse: bool = False
               ) -> Tuple[GarmentScene, Optional[CoarseLevel]]:
        """The baselines' scene of chunk ``idx`` (the data module's static inputs and the
        sequence file's pinned mask), with HOOD's coarse level when asked (cached)."""
        i = ds.index[idx][0]
        sid = ds.records[i]["id"]
        scene, level = self._scenes.get(sid, (None, None))
        if scene is None:
            st, seq = ds.static(i), ds.sequence(i)
            pinned = torch.as_tensor(seq["garment_pinned"]).bool()
            scene = GarmentScene(st["rest_pos"], st["faces"], st["skin_weights"],
                                 st["rest_joints"], st["parents"],
                                 pinned if bool(pinned.any()) else None)
        if coarse and level is None:
            c = BASELINES[HOOD]["coarse"]
            level = CoarseLevel.build(scene.rest_pos, scene.faces, ratio=c["ratio"], k=c["k"])
        self._scenes[sid] = (scene, level)
        return scene, level

    def _folder(self, method: str, seed: int, config: Dict[str, Any]) -> Path:
        """``OUT/models/<method>--s<seed>/``; ``run.json`` there names the dataset and
        configuration, and a folder of another run is refused (``ValueError``)."""
        folder = self.out / "models" / f"{_slug(method)}--s{seed}"
        desc = json.loads(json.dumps({"method": method, "seed": seed, "config": config,
                                      "dataset": self.data.fingerprint}))
        path = folder / "run.json"
        if path.exists():
            try:
                old = json.loads(path.read_text())
            except ValueError:
                old = None
            if old != desc:
                raise ValueError(f"`out`: {folder} holds a training run of another dataset or "
                                 "configuration; delete that folder to train again")
        else:
            store.atomic_write_json(path, desc)
        return folder

    def _fit_plain(self, model: nn.Module, step: Callable[[int], Tensor], n: int, epochs: int,
                   lr: float, seed: int, path: Path) -> Dict[str, Any]:
        """Adam over ``n`` chunk indices per epoch (seeded order), ``step(idx)`` the loss;
        ``path`` holds model, optimiser and clock after every epoch (resumed from)."""
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        state = {"epochs": 0, "seconds": 0.0}
        if path.exists():
            ck = torch.load(path, weights_only=True)
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["opt"])
            state = {"epochs": int(ck["epochs"]), "seconds": float(ck["seconds"])}
        resumed = state["epochs"]
        sampler = EpochShuffleSampler(n, seed)
        model.train()
        for epoch in range(resumed, epochs):
            t0 = time.perf_counter()
            sampler.set_epoch(epoch)
            for idx in sampler:
                opt.zero_grad(set_to_none=True)
                loss = step(idx)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"training loss is {float(loss)} (epoch {epoch})")
                loss.backward()
                opt.step()
            state = {"epochs": epoch + 1, "seconds": state["seconds"] + time.perf_counter() - t0}
            _save(path, {"model": model.state_dict(), "opt": opt.state_dict(), **state})
        model.eval()
        return {"epochs": state["epochs"], "train_seconds": state["seconds"],
                "resumed_from_epoch": resumed}

    # -- GarTrans ---------------------------------------------------------------------
    def _gartrans(self, method: str, seed: int) -> Tuple[_Predictor, Dict[str, Any]]:
        v = GARTRANS[method]
        hp = dict(GARTRANS_MODEL, **v.model)
        sched_kw = dict(SCHEDULE, window=self.budget.window, **v.schedule)
        E = self.budget.epochs
        config = {"model": hp, "schedule": sched_kw, "data": DATA, "epochs": E,
                  "mirrors": f"configs/ablations/{v.config}.yaml" if v.config
                  else "configs/gartrans.yaml"}
        folder = self._folder(method, seed, config)
        from lightning.pytorch.callbacks import ModelCheckpoint
        dm = GarmentDataModule(self.data.root, val_split=None, seed=seed, **DATA)
        dm.train_set = self.train
        module = GarTransModule(**dm.dims, **hp)
        sched, clock = ProgressiveSchedule(**sched_kw), TrainClock()
        # save_top_k=1 without a monitor keeps the latest epoch's checkpoint; last.ckpt
        # links to it (Lightning writes last.ckpt only along with a top-k checkpoint)
        ckpt = ModelCheckpoint(dirpath=folder, save_last="link", save_top_k=1,
                               save_on_train_epoch_end=True)
        last = folder / "last.ckpt"
        if last.exists():
            try:  # a checkpoint cut off by a kill is set aside, not resumed
                torch.load(last, map_location="cpu", weights_only=False)
            except Exception:
                last.replace(folder / "last.ckpt.unreadable")
        with _quiet_lightning():
            trainer = L.Trainer(max_epochs=E, accelerator="cpu", devices=1, logger=False,
                                enable_checkpointing=True, enable_progress_bar=False,
                                enable_model_summary=False, callbacks=[sched, clock, ckpt],
                                limit_val_batches=0, num_sanity_val_steps=0,
                                default_root_dir=folder)
            trainer.fit(module, dm, ckpt_path=str(last) if last.exists() else None)
        module.eval()
        m = module.model

        def make_batch(item: Dict[str, Any], b: int) -> Callable[[], Any]:
            it = _cycled(item, b)
            with torch.no_grad():
                static = module.encode_static(it)
            args = (static, it["rest_pos"], it["faces"], it["edge_index"], it["rest_joints"],
                    it["parents"], it["rotations"], it["translation"])
            return lambda: m(*args, body_pos=it.get("body_pos"),
                             body_faces=it.get("body_faces"))["final"]

        info = {"epochs": clock.epochs, "train_seconds": clock.seconds,
                "resumed_from_epoch": clock.restored_epochs, "phase": sched.phase,
                "transitions": {str(k): e for k, e in sched.transitions.items()},
                "config": config, "checkpoint": str(last)}
        return _Predictor(lambda ds, i, item: gartrans_predict(module, item, "gartrans"),
                          make_batch,
                          "frame-parallel forward of `batch` frames, static branch "
                          "(encode_static) computed once per garment outside the timed call"
                          ), info

    # -- baselines --------------------------------------------------------------------
    def _da(self, seed: int) -> Tuple[_Predictor, Dict[str, Any]]:
        cfg = BASELINES[DA]
        S = self.train.static(0)["rest_joints"].shape[0]
        model = DAStyle(S, **cfg["model"])
        loss_fn = GarTransLoss(enabled=SUPERVISED, edge_reduction=GARTRANS_MODEL["edge_reduction"])
        config = {"model": cfg["model"], "lr": cfg["lr"], "loss": {"enabled": list(SUPERVISED)},
                  "epochs": self.budget.epochs}
        folder = self._folder(DA, seed, config)

        def step(idx: int) -> Tensor:
            item = self.train[idx]
            scene, _ = self._scene(self.train, idx)
            pred = model(scene, item["rotations"][:, -1], item["translation"][:, -1])
            return loss_fn(LossInputs(pred=pred, faces=item["faces"], gt=item["gt"]))[0]

        info = self._fit_plain(model, step, len(self.train), self.budget.epochs, cfg["lr"], seed,
                               folder / "last.pt")

        def predict(ds: SequenceChunks, i: int, item: Dict[str, Any]) -> Tensor:
            scene, _ = self._scene(ds, i)
            return model(scene, item["rotations"][:, -1], item["translation"][:, -1])

        def make_batch(item: Dict[str, Any], b: int) -> Callable[[], Any]:
            it, (scene, _) = _cycled(item, b), self._scene(self.test, 0)
            return lambda: model(scene, it["rotations"][:, -1], it["translation"][:, -1])

        return _Predictor(predict, make_batch, "one call predicting `batch` frames"), \
            dict(info, config=config)

    def _physics_loss(self) -> GarTransLoss:
        return GarTransLoss(PHYSICS_LOSS["weights"], enabled=PHYSICS_LOSS["enabled"],
                            collision_margin=GARTRANS_MODEL["collision_margin"],
                            edge_reduction=GARTRANS_MODEL["edge_reduction"])

    def _hood(self, seed: int) -> Tuple[_Predictor, Dict[str, Any]]:
        cfg = BASELINES[HOOD]
        dt = 1.0 / GARTRANS_MODEL["fps"]
        model = HOODStyle(dt=dt, **cfg["model"])
        loss_fn = self._physics_loss()
        config = {"model": cfg["model"], "coarse": cfg["coarse"], "lr": cfg["lr"],
                  "loss": PHYSICS_LOSS, "epochs": self.budget.epochs, "dt": dt}
        folder = self._folder(HOOD, seed, config)

        def step(idx: int) -> Tensor:
            item = self.train[idx]
            scene, coarse = self._scene(self.train, idx, coarse=True)
            lbs = lbs_coarse(item)
            first = frames_of(item, torch.tensor([0]))
            x_prev = lbs_coarse(history_slot(first, -3))[0]  # frame t0 - 2 (clamped at 0)
            x_curr = lbs_coarse(history_slot(first, -2))[0]  # frame t0 - 1
            preds, inertial = [], []
            for b in range(lbs.shape[0]):  # one step at a time on its own rollout
                nxt = model.step(scene, coarse, x_prev[None], x_curr[None],
                                 item["body_pos"][b:b + 1], lbs[b:b + 1])[0]
                preds.append(nxt)
                inertial.append(2 * x_curr - x_prev)
                x_prev, x_curr = x_curr, nxt.detach()
            inp = LossInputs(pred=torch.stack(preds), faces=item["faces"],
                             body_pos=item["body_pos"], body_faces=item["body_faces"],
                             mass=item["mass"], rest=item["rest"],
                             predicted=torch.stack(inertial), dt=dt)
            return loss_fn(inp)[0]

        info = self._fit_plain(model, step, len(self.train), self.budget.epochs, cfg["lr"], seed,
                               folder / "last.pt")

        def predict(ds: SequenceChunks, i: int, item: Dict[str, Any]) -> Tensor:
            scene, coarse = self._scene(ds, i, coarse=True)
            lbs = lbs_coarse(item)
            return model.rollout(scene, coarse, lbs[0], lbs[1], item["body_pos"],
                                 pinned_targets=lbs)

        def make_batch(item: Dict[str, Any], b: int) -> Callable[[], Any]:
            scene, coarse = self._scene(self.test, 0, coarse=True)
            it = _cycled(item, b)
            lbs = lbs_coarse(it)
            prev = lbs_coarse(history_slot(it, -3))
            curr = lbs_coarse(history_slot(it, -2))
            return lambda: model.step(scene, coarse, prev, curr, it["body_pos"], lbs)

        return _Predictor(predict, make_batch, "one autoregressive step of `batch` independent "
                                               "sequences per call"), dict(info, config=config)

    def _ncs(self, seed: int) -> Tuple[_Predictor, Dict[str, Any]]:
        cfg = BASELINES[NCS]
        h = cfg["model"]["history"]
        H = DATA["history"] + 1
        if H < h + 3:
            raise ValueError(f"`DATA['history']`: NCS with history {h} needs >= {h + 2}")
        dt = 1.0 / GARTRANS_MODEL["fps"]
        loss_fn = self._physics_loss()
        config = {"model": cfg["model"], "lr": cfg["lr"], "loss": PHYSICS_LOSS,
                  "epochs": self.budget.ncs_epochs, "dt": dt,
                  "data": "the poses of the garment's own test sequences (no positions)"}
        folder = self._folder(NCS, seed, config)
        ds = self.test_chunks
        groups: Dict[Tuple[str, str], List[int]] = {}  # (garment, body) -> record indices
        for i, r in enumerate(ds.records):
            groups.setdefault((garment_key(r["garment"]), body_key(r["body"])), []).append(i)

        def poses(item: Dict[str, Any], j: int) -> Tuple[Tensor, Tensor]:
            """(rotations [B, h + 1, S, 3], translation [B, 3]) ending at history slot j."""
            end = H + j + 1
            return item["rotations"][:, end - h - 1:end], item["translation"][:, end - 1]

        models: Dict[Tuple[str, str], NCSStyle] = {}  # (garment, body) -> its model
        total = {"epochs": 0, "train_seconds": 0.0, "resumed_from_epoch": 0}
        for g, (key, recs) in enumerate(sorted(groups.items())):
            scene, _ = self._scene(ds, next(k for k, x in enumerate(ds.index) if x[0] == recs[0]))
            torch.manual_seed(seed * 1000 + g)
            model = NCSStyle(scene.num_vertices, scene.num_joints, **cfg["model"])
            chunks = [k for k, x in enumerate(ds.index) if x[0] in recs]

            def step(k: int, model: NCSStyle = model, scene: GarmentScene = scene,
                     chunks: List[int] = chunks) -> Tensor:
                item = {key_: v for key_, v in ds[chunks[k]].items() if key_ != "gt"}
                p = [model(scene, *poses(item, j)) for j in (-1, -2, -3)]
                inp = LossInputs(pred=p[0], faces=item["faces"], body_pos=item["body_pos"],
                                 body_faces=item["body_faces"], mass=item["mass"],
                                 rest=item["rest"], predicted=2 * p[1] - p[2], dt=dt)
                return loss_fn(inp)[0]

            info = self._fit_plain(model, step, len(chunks), self.budget.ncs_epochs, cfg["lr"],
                                   seed * 1000 + g, folder / f"garment{g}.pt")
            total["epochs"] = info["epochs"]
            total["train_seconds"] += info["train_seconds"]
            total["resumed_from_epoch"] = max(total["resumed_from_epoch"],
                                              info["resumed_from_epoch"])
            models[key] = model

        def model_of(ds: SequenceChunks, i: int) -> NCSStyle:
            r = ds.records[ds.index[i][0]]
            return models[(garment_key(r["garment"]), body_key(r["body"]))]

        def predict(ds: SequenceChunks, i: int, item: Dict[str, Any]) -> Tensor:
            scene, _ = self._scene(ds, i)
            return model_of(ds, i)(scene, *poses(item, -1))

        def make_batch(item: Dict[str, Any], b: int) -> Callable[[], Any]:
            scene, _ = self._scene(self.test, 0)
            r, t = poses(_cycled(item, b), -1)
            model = model_of(self.test, 0)
            return lambda: model(scene, r, t)

        return _Predictor(predict, make_batch, "one call predicting `batch` frames (the first "
                                               "test garment's model)"), \
            dict(total, config=config, models=len(groups))

    def _lbs(self) -> Tuple[_Predictor, Dict[str, Any]]:
        def make_batch(item: Dict[str, Any], b: int) -> Callable[[], Any]:
            it = _cycled(item, b)
            return lambda: lbs_coarse(it)

        return _Predictor(lambda ds, i, item: lbs_coarse(item), make_batch,
                          "one call skinning `batch` frames"), \
            {"epochs": 0, "train_seconds": 0.0, "resumed_from_epoch": 0,
             "config": {"weights": "the simulator's transferred skinning weights"}}


# --------------------------------------------------------------------------- report
def _ordered(records: Sequence[Dict[str, Any]]) -> List[str]:
    seen = [m for m in METHOD_NAMES if any(r["method"] == m for r in records)]
    return seen + sorted({r["method"] for r in records} - set(seen))


def summary(records: Sequence[Dict[str, Any]]) -> Dict[str, Dict[str, Any]]:
    """Per method: mean / std over seeds of the metrics, latency, throughput and train
    time of its ok ``learned`` records."""
    rs = [r for r in records if r["kind"] == KIND]
    out: Dict[str, Dict[str, Any]] = {}
    for method in _ordered(rs):
        mine = [r for r in rs if r["method"] == method]
        ok = [r for r in mine if r["status"] == "ok"]
        entry: Dict[str, Any] = {"records": len(mine), "failed": len(mine) - len(ok)}
        vals = {m: [r["metrics"][m] for r in ok] for m in METRICS}
        vals.update({t: [r["timing"][t] for r in ok] for t in ("latency_ms", "throughput_fps")})
        vals["train_seconds"] = [r["train_seconds"] for r in ok]
        for k, v in vals.items():
            if v:
                entry[k] = dict(zip(("mean", "std"), _mean_std(v)), n=len(v))
        out[method] = entry
    return out


def markdown(records: Sequence[Dict[str, Any]], png: Optional[str] = None) -> List[str]:
    """The "Held-out test split" section of ``report.md`` (empty without records)."""
    rs = [r for r in records if r["kind"] == KIND]
    if not rs:
        return []
    ds = next((r.get("dataset") for r in rs if r.get("dataset")), {}) or {}
    lines = ["## Held-out test split (learned methods; shaped like Tables 1 and 3)", "",
             f"Dataset `{ds.get('name')}` (`{ds.get('root')}`, fingerprint "
             f"{str(ds.get('fingerprint'))[:8]}): {ds.get('sequences', {}).get('train')} train / "
             f"{ds.get('sequences', {}).get('test')} test sequences, "
             f"{ds.get('frames', {}).get('test')} test frames. Every method is trained on "
             "the train split (NCS-style: one model per test garment, on that garment's own "
             "test poses, physics terms only -- never its simulated positions) and scored "
             "on every frame of every test sequence against the simulation (frame-weighted "
             "means). A different case set from the simulator tables above: these rows are "
             "not comparable with them. Mean ± std over training seeds. latency: ms per "
             "frame at batch 1; throughput: frames/s at the best batch; train: wall time of "
             "the training epochs.", ""]
    rows = []
    for method in _ordered(rs):
        mine = [r for r in rs if r["method"] == method]
        ok = [r for r in mine if r["status"] == "ok"]
        label = method + (" (reference, no learning)" if method == LBS else "")
        if len(ok) < len(mine):
            label += f" ({len(mine) - len(ok)}/{len(mine)} failed)"
        if not ok:
            rows.append([label] + ["failed"] * (len(METRICS) + 5))
            continue

        def cell(get: Callable[[Dict[str, Any]], float]) -> str:
            return _fmt([get(r) for r in ok])
        epochs = sorted({int(r.get("epochs", 0)) for r in ok})
        phases = sorted({int(r["phase"]) for r in ok if "phase" in r})
        rows.append([label] + [cell(lambda r, m=m: r["metrics"][m]) for m in METRICS]
                    + [cell(lambda r: r["timing"]["latency_ms"]),
                       cell(lambda r: r["timing"]["throughput_fps"]),
                       cell(lambda r: r["train_seconds"]),
                       "/".join(map(str, epochs)), "/".join(map(str, phases)) or "—",
                       str(len(ok))])
    hdr = ["method"] + [f"{m} ({UNITS[m]})" for m in METRICS] + [
        "latency (ms)", "throughput (fps)", "train (s)", "epochs", "final phase", "seeds"]
    lines += _table(hdr, rows) + [""]
    if png:
        lines += ["Error against run time of these methods: a separate plot from the "
                  "simulator budgets' (other cases).", "", f"![Pareto, learned]({png})", ""]
    return lines


def plot(records: Sequence[Dict[str, Any]], path) -> Optional[Path]:
    """``pareto_learned.png``: log latency (batch 1) against E_dist of the learned
    methods' means; ``None`` without ok records."""
    return plot_summary(summary(records), path, "Held-out test split: error against run time")


__all__ = ["BASELINES", "DATA", "GARTRANS", "GARTRANS_MODEL", "KIND", "LBS", "METHOD_NAMES",
           "PHYSICS_LOSS", "SCHEDULE", "DatasetInfo", "LearnedBudget", "LearnedRunner",
           "TrainClock", "Variant", "frames_of", "history_slot", "markdown", "plot",
           "prepare_dataset", "summary"]
