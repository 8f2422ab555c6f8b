"""The learned methods inside ``garmentgnn bench``: every method trained and evaluated on
the same generated dataset and data split, through one training path.

One bench run (:func:`garmentgnn.bench.runner.run`) with a preset that has a
:class:`~garmentgnn.bench.methods.LearnedBudget`:

1. uses a generated dataset (:func:`prepare_dataset`: ``garmentgnn.data.generate``'s
   preset of the bench preset, generated -- resumably -- under ``OUT/data``, or an
   existing folder given by ``--data``);
2. trains each method of the budget for each training seed for the budget's epochs or
   wall-clock minutes (:class:`TimeBudget`): each built from its recipe by
   :func:`~garmentgnn.training.load_recipe` (:mod:`~garmentgnn.bench.methods`; any recipe
   is a method too) and trained, predicted and timed as its module's method protocol
   says (:class:`~garmentgnn.training.GarmentModule`: the same calls for GarTrans, its
   Table 1 variants, the DA-, HOOD-, NCS- and MGN-style methods and a new one), on its
   :class:`GarmentDataModule`, by one Lightning ``Trainer`` set-up (the recipe's trainer
   with the bench's limits, :meth:`LearnedRunner.fit`) that resumes from
   ``OUT/models/<method>--s<seed>/``; a per-garment method (NCS-style) trains one model
   per (garment, body) of the scored test sequences on their poses (never their
   simulated positions);
3. scores it on the ``test`` split (all of it, or the budget's stratified subset:
   :mod:`garmentgnn.bench.scoring`), times it (:func:`~garmentgnn.bench.timing.batch_sweep`,
   :func:`~garmentgnn.bench.timing.peak_memory`) and returns one record of kind
   ``"learned"`` per (method, seed); the bench writes it atomically.

``LBS only`` is the rest garment skinned with the stored skinning weights
(:meth:`GarmentInputs.skinned`): the reference row of the table.
"""
from __future__ import annotations

import io
import json
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from torch import Tensor

from garmentgnn._files import atomic_write_bytes, atomic_write_json
from garmentgnn.bench import stability as stab
from garmentgnn.bench import scoring
from garmentgnn.bench.curves import LearningCurve, TrainClock, quiet_lightning
from garmentgnn.bench.dataset import DatasetInfo, ensemble_sequences, prepare_dataset
from garmentgnn.bench.methods import (DATA, LBS, LONG, LearnedBudget, is_method,
                                        module_class, per_garment, recipe_of)
from garmentgnn.bench.model_inputs import BenchChunks, Predictor, lbs_predictor
from garmentgnn.bench.page import MEDIA
from garmentgnn.bench.records import failure
from garmentgnn.bench.tables import slug
from garmentgnn.bench.timing import batch_sweep, peak_memory
from garmentgnn.data import SequenceChunks, store
from garmentgnn.data.keys import body_key, garment_key
from garmentgnn.geometry import push_outside
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.training import Recipe, TimeBudget, load_recipe

KIND = "learned"
#: the record kind of :meth:`LearnedRunner.stability_record`
STABILITY_KIND = "learned_stability"
#: the reference simulator, with the dataset's settings, in the learned stability suite
SIMULATOR = "simulator (dataset settings)"
#: frames per call of a frame-parallel method in the stability suite (memory: GarTrans on
#: all 1000 frames of ``long_1000`` at once needs over 24 GB); HOOD-style rolls out the
#: whole sequence in one call
STABILITY_CHUNK = 50
#: stability cases the simulator leaves out there (``long_1000``: about 50 min)
SIMULATOR_SKIPS: Tuple[str, ...] = ("long_1000",)


# --------------------------------------------------------------------------- runner
class LearnedRunner:
    """Trains and scores the learned methods on one dataset (see the module doc).

    Args:
        data: from :func:`prepare_dataset`.
        budget: epochs, schedule window, methods.
        out: the bench folder (checkpoints under ``out/models``).
        batches, warmup, repeats: the preset's timing settings.
    """

    #: more callbacks of every fit (a sweep's reports to Ray Tune)
    fit_callbacks: Tuple[L.Callback, ...] = ()

    def __init__(self, data: DatasetInfo, budget: LearnedBudget, out, batches: Sequence[int],
                 warmup: int, repeats: int) -> None:
        if not isinstance(data, DatasetInfo):
            raise ValueError(f"`data`: expected a DatasetInfo, got {type(data).__name__}")
        if not isinstance(budget, LearnedBudget):
            raise ValueError(f"`budget`: expected a LearnedBudget, got {type(budget).__name__}")
        self.data, self.budget, self.out = data, budget, Path(out)
        self.batches, self.warmup, self.repeats = tuple(batches), warmup, repeats
        self.train_chunks = chunks = len(SequenceChunks(  # an epoch of the whole split
            data.root, "train", DATA["chunk"], DATA["history"], DATA["nystrom_dim"],
            DATA["num_landmarks"]))
        if budget.batch_size > chunks:
            raise ValueError(f"--batch-size: {budget.batch_size} is more than the {chunks} "
                             f"training chunks of {data.root}; give at most {chunks}")
        self.test = self._whole("test", budget.test_sequences)  # the same for every method
        self.ensemble, self.ensemble_test = ensemble_sequences(data.root)
        self.val: Optional[SequenceChunks] = None
        self.train_fit: Optional[SequenceChunks] = None  # the curves' training sequences
        if budget.curve_every is not None:
            if not data.sequences.get("val"):
                raise ValueError(f"`data` (--data): {data.root} has no `val` split for the "
                                 "preset's learning curves; give a dataset with one")
            self.val = self._whole("val", budget.val_sequences)
            if budget.train_sequences is not None:
                self.train_fit = self._whole("train", budget.train_sequences)
        self._trained: Dict[Tuple[str, int], Tuple[Predictor, Dict[str, Any]]] = {}
        self._warm_up_compiled_search()

    def _whole(self, split: str, n: Optional[int]) -> SequenceChunks:
        """``split``'s whole sequences, or ``n`` of them: drawn evenly from the held-out
        groups (:func:`~garmentgnn.bench.scoring.stratified`), or evenly spaced in id
        order for ``train``, which holds nothing out."""
        kw = dict(chunk=10 ** 9, history=DATA["history"], nystrom_dim=DATA["nystrom_dim"],
                  num_landmarks=DATA["num_landmarks"])
        seqs = SequenceChunks(self.data.root, split, **kw)
        if n is None:
            return seqs
        if split == "train":  # no held-out groups: evenly spaced in id order
            ids = sorted(r["id"] for r in seqs.records)
            ids = [ids[i * len(ids) // n] for i in range(min(n, len(ids)))]
        else:
            ids = scoring.stratified(seqs.records, n)
        return SequenceChunks(self.data.root, split, ids=ids, **kw)

    def _warm_up_compiled_search(self) -> None:
        """Compile the nearest-face search (``compile_search`` of the modules) once,
        for one frame and for several, before any training: its one-off cost (10-20 s)
        would otherwise come out of the budget of whichever run happens to be first."""
        item = self.test[0]
        for b in (1, 2):
            push_outside(item.gt[:b], item.body_pos[:b], item.body_faces, 1e-3,
                         compiled=True)

    # -- records ----------------------------------------------------------------------
    def record(self, method: str, seed: int) -> Dict[str, Any]:
        """Train (or resume) ``method`` with ``seed``, evaluate and time it; exceptions
        (e.g. :class:`NonFiniteLossError`) give a failed record with their message."""
        if method != LBS:
            module_class(method)  # a ValueError naming the choices where it is no method
        rec: Dict[str, Any] = {"kind": KIND, "method": method, "case": self.data.case,
                               "seed": seed, "dataset": self.data.to_json()}
        t0 = time.perf_counter()
        try:
            pred, info = self.trained(method, seed)
            rec.update(info)
            rec.update(self.evaluate(pred))
            if self.budget.equal_steps is not None and pred.module is not None:
                rec["equal_steps"] = self.at_snapshot(pred)
            if pred.module_family not in (None, "gartrans") and seed == 0:
                self.save_prediction(method, pred)  # the page shows GarTrans's checkpoints
            rec["timing"] = self.timing(pred)
            rec.update(status="ok", message="ok")
        except Exception as err:
            rec.update(failure(err, limit=6))
        rec["seconds"] = time.perf_counter() - t0
        return rec

    def save_prediction(self, method: str, pred: "Predictor") -> Path:
        """``OUT/media/predictions/<method>.npy``: ``method``'s ``[T, V, 3]`` prediction
        of the first test sequence, a panel of the report's animation
        (:mod:`garmentgnn.bench.page`)."""
        item = self.test[0]
        with torch.no_grad():
            P = pred.predict(self.test, 0, item).float().numpy()
        buf = io.BytesIO()
        np.save(buf, P)
        return atomic_write_bytes(self.out / MEDIA / "predictions" / f"{slug(method)}.npy",
                                        buf.getvalue())

    def trained(self, method: str, seed: int) -> Tuple[Predictor, Dict[str, Any]]:
        """``method`` trained with ``seed`` (trained, or resumed from its checkpoint, on
        the first call; kept until another method is asked for: it holds its data caches)."""
        key = (method, seed)
        if key not in self._trained:
            self._trained.clear()
            self._trained[key] = lbs_predictor() if method == LBS else \
                self._method(method, seed)
        return self._trained[key]

    def stability_record(self, method: str, seed: int, case: str) -> Dict[str, Any]:
        """Stability ``case`` (:mod:`garmentgnn.bench.stability`) built on the first test
        sequence of the dataset (its body, garment, motion and motion seed), predicted by
        ``method`` trained with ``seed`` -- or by :data:`SIMULATOR` with the dataset's
        simulator settings -- and scored like the simulator's cases.  The model sees the
        case as the data module would present it (:class:`BenchChunks`); no learned
        method takes the material as input, so ``stiff_x1000`` changes only how its
        output is scored."""
        if method != SIMULATOR and not is_method(method):
            raise ValueError(f"`method`: unknown {method!r}; give a method, a recipe or "
                             f"{SIMULATOR!r}")
        base = self.test.records[0]
        item = {k: v for k, v in base.items() if k in ("garment", "body", "motion", "material",
                                                        "settings")}
        if method == SIMULATOR:
            predict = stab.simulator_predictor(**item["settings"])
        else:
            def predict(seq) -> Tensor:
                pred, _ = self.trained(method, seed)
                ds = BenchChunks(seq, chunk=None if pred.autoregressive else STABILITY_CHUNK,
                                 history=DATA["history"], nystrom_dim=DATA["nystrom_dim"],
                                 num_landmarks=DATA["num_landmarks"])
                with torch.no_grad():
                    return torch.cat([pred.predict(ds, i, ds[i]) for i in range(len(ds))])
        rec = stab.run_case(case, dict(item, name=case), int(base["seed"]), predict, method)
        rec.update(kind=STABILITY_KIND, seed=seed, motion_seed=int(base["seed"]),
                   sequence=base["id"])
        return rec

    def evaluate(self, pred: Predictor) -> Dict[str, Any]:
        """``metrics`` (frame-weighted means over the valid ground-truth frames of every test
        sequence), ``groups`` (per held-out group), ``per_sequence``, ``test_frames`` and,
        with an ensemble ground truth, ``ensemble`` (:mod:`garmentgnn.bench.scoring`)."""
        per_seq = scoring.score(lambda i, item: pred.predict(self.test, i, item), self.test)
        agg = scoring.aggregate(per_seq)
        out = {"metrics": agg.pop("all"), "groups": agg, "per_sequence": per_seq,
               "test_frames": sum(s["frames"] for s in per_seq)}
        if self.ensemble is not None:
            ens = self.ensemble_test
            out["ensemble"] = scoring.score_ensemble(
                lambda i, item: pred.predict(ens, i, item), ens, self.ensemble)
        return out

    def at_snapshot(self, pred: Predictor) -> Dict[str, Any]:
        """:meth:`evaluate` of ``pred``'s weights after the budget's ``equal_steps``
        (``reached: False`` when its training stopped before)."""
        step = self.budget.equal_steps
        if pred.snapshot is None or not pred.snapshot.exists():
            return {"step": step, "reached": False}
        state = torch.load(pred.snapshot, map_location="cpu", weights_only=False)
        final = {k: v.clone() for k, v in pred.module.state_dict().items()}
        pred.module.load_state_dict(state["state_dict"])
        try:
            res = self.evaluate(pred)
        finally:
            pred.module.load_state_dict(final)
        return {"step": int(state["step"]), "reached": True, "metrics": res["metrics"],
                "per_sequence": res["per_sequence"]}

    def val_error(self, predict: Callable[[L.LightningModule, GarmentInputs], Tensor],
                  seqs: Optional[SequenceChunks] = None) -> Callable[[L.LightningModule], float]:
        """The validation E_dist (cm) of a module: ``predict(module, item)`` scored on
        every ``val`` sequence of the curves (or of ``seqs``;
        :mod:`garmentgnn.bench.scoring`), on the module's device."""
        seqs = self.val if seqs is None else seqs

        def run(module: L.LightningModule) -> float:
            per = scoring.score(lambda i, item: predict(module, item.to(module.device)).cpu(),
                                seqs)
            return scoring.aggregate(per)["all"]["E_dist"]
        return run

    def timing(self, pred: Predictor) -> Dict[str, Any]:
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

    # -- one training path -------------------------------------------------------------
    def _folder(self, method: str, seed: int, config: Dict[str, Any]) -> Path:
        """``OUT/models/<method>--s<seed>/``; ``run.json`` there names the dataset and
        configuration, and a folder of another run is refused (``ValueError``)."""
        folder = self.out / "models" / f"{slug(method)}--s{seed}"
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
            atomic_write_json(path, desc)
        return folder

    def load(self, method: str, seed: int, args: Sequence[str] = (),
             set: Optional[Dict[str, Any]] = None) -> Tuple[Recipe, Dict[str, Any]]:
        """``method``'s recipe (:func:`~garmentgnn.bench.methods.recipe_of`) on this
        dataset (:func:`~garmentgnn.training.load_recipe`), seeded with ``seed``, no
        validation split, the budget's ``lr_factor``, ``args`` and ``set`` on top; and the
        run's description for ``run.json`` (:meth:`_folder`): recipe, module and data
        settings, limits."""
        recipe, lr, b = recipe_of(method), self.budget.lr_factor, self.budget
        r = load_recipe(recipe, args=["--seed_everything", str(seed), *args],
                        data={"root": self.data.root, "val_split": None, "seed": seed,
                              "num_workers": 0},
                        set=dict({"model.init_args.lr": lambda v: v * lr} if lr != 1 else {},
                                 **(set or {})))
        data = {k: v for k, v in r.config["data"].items()
                if k not in ("root", "num_workers", "cache_size", "cache_bytes",
                             "predict_split")}
        minutes = b.long_minutes if method == LONG else b.minutes
        config = {"recipe": recipe, "model": r.config["model"], "data": data,
                  "epochs": b.epochs, "minutes": minutes, "epoch_chunks": b.epoch_chunks,
                  **({"lr_factor": b.lr_factor} if b.lr_factor != 1 else {})}
        return r, json.loads(json.dumps(config, default=str))

    def fit(self, recipe: Recipe, folder: Path, epochs: int,
            callbacks: Sequence[L.Callback] = (), minutes: Optional[float] = None,
            predict: Optional[Callable[[L.LightningModule, GarmentInputs], Tensor]] = None
            ) -> Dict[str, Any]:
        """Fit ``recipe``'s module on its data module for ``epochs`` (at most, with a
        ``minutes`` budget: :class:`TimeBudget`) with one Lightning ``Trainer`` set-up
        (the recipe's trainer with the bench's limits, callbacks and checkpoint, on the
        accelerator Lightning picks), resuming from ``folder/last.ckpt``; with
        ``predict(module, item)`` and the budget's ``curve_every``, its learning curve
        (:class:`LearningCurve`) and ``equal_steps`` snapshot (``folder/equal_steps.pt``).
        Returns the epochs and steps done, the training wall time (validation excluded),
        the epoch it resumed from, the device and the curve; the module ends on the CPU."""
        module, dm = recipe.module, recipe.datamodule
        clock = TrainClock()
        budget = [TimeBudget(60.0 * minutes)] if minutes is not None else []
        curve = None
        if predict is not None and self.val is not None:
            snap = self.budget.equal_steps
            every = max(1, self.budget.curve_every // dm.hparams.batch_size)
            fit = None if self.train_fit is None else self.val_error(predict, self.train_fit)
            curve = LearningCurve(every, self.val_error(predict), snap,
                                  None if snap is None else folder / "equal_steps.pt",
                                  budget[0] if budget else None, fit, self.train_chunks)
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
        with quiet_lightning():
            trainer = recipe.trainer(
                max_epochs=epochs, max_steps=-1, accelerator="auto", devices=1, logger=False,
                enable_checkpointing=True, enable_progress_bar=False,
                enable_model_summary=False, limit_val_batches=0, num_sanity_val_steps=0,
                val_check_interval=1.0, check_val_every_n_epoch=1,
                callbacks=[*callbacks, *self.fit_callbacks, *budget, *([curve] if curve else []),
                           clock, ckpt],
                limit_train_batches=self._epoch_batches(dm), default_root_dir=folder)
            trainer.fit(module, dm, ckpt_path=str(last) if last.exists() else None)
        device = str(trainer.strategy.root_device)
        module.cpu().eval()
        info = {"epochs": clock.epochs, "train_seconds": clock.seconds,
                "resumed_from_epoch": clock.restored_epochs, "checkpoint": str(last),
                "device": device, "steps": int(trainer.global_step)}
        if budget:
            info.update(budget_seconds=budget[0].seconds)
        if curve is not None:
            def skinned(m: L.LightningModule, item: GarmentInputs) -> Tensor:  # LBS
                return item.skinned()
            lbs = {"lbs_E_dist": self.val_error(skinned)(module)}
            if self.train_fit is not None:
                lbs["train_lbs_E_dist"] = self.val_error(skinned, self.train_fit)(module)
            info.update(curve=dict(curve.to_json(), **lbs),
                        train_seconds=clock.seconds - curve.eval_seconds)
        return info

    def _epoch_batches(self, dm) -> Optional[int]:
        """Lightning's ``limit_train_batches``: the budget's ``epoch_chunks`` in ``dm``'s
        batches."""
        n = self.budget.epoch_chunks
        return None if n is None else -(-n // dm.hparams.batch_size)

    # -- one method, as its module's protocol says ---------------------------------------
    def _method(self, method: str, seed: int) -> Tuple[Predictor, Dict[str, Any]]:
        """``method`` trained on the budget's batches, with the recipe settings its module
        asks of the budget (``bench_overrides``: GarTrans's schedule windows, the MGN-style
        rollout a training sequence holds); a per-garment method is trained per test
        garment (:meth:`_per_garment`).  It predicts from what a user has
        (``predict_sequence``) and is timed by its ``timed_call``."""
        if per_garment(method):
            return self._per_garment(method, seed)
        shortest = min(int(r["num_frames"]) for r in store.read_manifest(self.data.root)[
            "items"] if r["split"] == "train" and r["status"] == "ok")
        overrides = module_class(method).bench_overrides(schedule_window=self.budget.window,
                                                         shortest_sequence=shortest)
        recipe, config = self.load(method, seed, ["--data.batch_size",
                                                  str(self.budget.batch_size)], overrides)
        module = recipe.module
        folder = self._folder(method, seed, config)
        minutes = config["minutes"]
        info = self.fit(recipe, folder, self.budget.epochs, minutes=minutes,
                        predict=lambda m, item: m.predict_sequence(item))
        info.update(module.fit_info(), config=config)
        return Predictor(lambda ds, i, item: module.predict_sequence(item), module.timed_call,
                         module.timing_note, module, folder / "equal_steps.pt",
                         module.autoregressive, module.family), info

    def _per_garment(self, method: str, seed: int) -> Tuple[Predictor, Dict[str, Any]]:
        """One model per (garment, body) of the scored test sequences, trained on their
        poses (never their simulated positions), the budget shared evenly."""
        groups: Dict[Tuple[str, str], List[str]] = {}  # (garment, body) -> sequence ids
        for r in self.test.records:
            groups.setdefault((garment_key(r["garment"]), body_key(r["body"])), []).append(r["id"])
        each = None if self.budget.minutes is None else self.budget.minutes / len(groups)
        folder, config = None, {}
        modules: Dict[Tuple[str, str], L.LightningModule] = {}
        total: Dict[str, Any] = {"epochs": 0, "train_seconds": 0.0, "resumed_from_epoch": 0}
        for g, (key, ids) in enumerate(sorted(groups.items())):
            recipe, config = self.load(method, seed * 1000 + g,
                                       set={"data.train_split": "test", "data.train_ids": ids})
            config = dict(config, epochs=self.budget.ncs_epochs, data="the poses of the "
                          "garment's own test sequences (no positions)")
            folder = folder or self._folder(method, seed, config)
            info = self.fit(recipe, folder / f"garment{g}", self.budget.ncs_epochs,
                            minutes=each)
            total["epochs"], total["device"] = info["epochs"], info["device"]
            total["train_seconds"] += info["train_seconds"]
            for k in ("budget_seconds", "steps"):
                if k in info:
                    total[k] = total.get(k, 0) + info[k]
            total["resumed_from_epoch"] = max(total["resumed_from_epoch"],
                                              info["resumed_from_epoch"])
            modules[key] = recipe.module

        def module_of(ds: SequenceChunks, i: int) -> L.LightningModule:
            r = ds.records[ds.index[i][0]]
            return modules[(garment_key(r["garment"]), body_key(r["body"]))]

        first = module_of(self.test, 0)
        return Predictor(lambda ds, i, item: module_of(ds, i).predict_sequence(item),
                         first.timed_call, f"{first.timing_note} (the first test garment's "
                         f"model)", autoregressive=first.autoregressive,
                         module_family=first.family), dict(total, config=config,
                                                            models=len(groups))


__all__ = ["KIND", "SIMULATOR", "STABILITY_KIND", "DatasetInfo", "LearnedRunner",
           "prepare_dataset"]
