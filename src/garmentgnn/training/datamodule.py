"""The Lightning data module of every trained method: the training chunks of a generated
dataset (:class:`~garmentgnn.data.SequenceChunks`) in a seeded per-epoch order
(:class:`EpochShuffleSampler`), ``batch_size`` chunks of one frame count per step collated
as one PyG ``Batch`` (:meth:`~garmentgnn.models.inputs.GarmentInputs.collate`); validation,
test and predict one chunk per step."""
from __future__ import annotations

import inspect
import os

from pathlib import Path
from typing import Any, Dict, Iterator, List, Optional, Sequence, Union

import lightning as L
import torch
from torch.utils.data import DataLoader
from torch.utils.data.distributed import DistributedSampler

from garmentgnn.models.inputs import CHUNK, HISTORY, NUM_LANDMARKS, NYSTROM_DIM
from garmentgnn.data import store
from garmentgnn.data.chunks import CACHE_BYTES, CACHE_SIZE, SequenceChunks
from garmentgnn.data.keys import body_key, garment_key

#: the data settings a checkpoint's model learned from (the inputs it reads): a resumed
#: or scored checkpoint is compared with them, and a fork cannot change them
MODEL_INPUTS = ("history", "num_landmarks", "nystrom_dim")


class EpochShuffleSampler(DistributedSampler):
    """A permutation seeded by ``(seed, epoch)``: the order of an epoch does not depend
    on what ran before it, so a run resumed from a checkpoint sees the same batches as
    an uninterrupted one (Lightning calls :meth:`set_epoch` every epoch).  A fit resumed
    in the middle of an epoch goes on from the batch it stopped at: :meth:`set_epoch`'s
    ``skip`` leaves out the epoch's first batches once, from the next iteration only;
    :meth:`__len__` stays the whole epoch's, as Lightning counts the batches a resumed
    epoch already ran.

    With ``num_replicas > 1`` (DDP) replica ``rank`` takes every ``num_replicas``-th
    chunk of that one permutation (the tail padded with its first chunks, as
    :class:`~torch.utils.data.DistributedSampler` does), so the replicas' chunks of one
    step are consecutive chunks of the single-process order: ``W`` replicas equal one
    process with ``accumulate_grad_batches=W``.  Being a ``DistributedSampler``, it is
    not wrapped by Lightning's ``DistributedSamplerWrapper``, whose own shuffle (seeded
    by ``PL_GLOBAL_SEED``) would reorder the permutation a second time.
    """

    def __init__(self, n: int, seed: int = 0, shuffle: bool = True, num_replicas: int = 1,
                 rank: int = 0, batch_size: int = 1,
                 lengths: Optional[Sequence[int]] = None) -> None:
        if not 0 <= rank < num_replicas:
            raise ValueError(f"`rank`: expected 0 <= rank < num_replicas={num_replicas}, "
                             f"got {rank}")
        if lengths is not None and len(lengths) != n:
            raise ValueError(f"`lengths`: expected {n} chunk lengths, got {len(lengths)}")
        # the base class only shards positions (its own shuffle stays off)
        super().__init__(range(n), num_replicas=num_replicas, rank=rank, shuffle=False)
        self.n, self.seed, self.order_shuffle = n, seed, shuffle
        self.batch_size = batch_size
        self.lengths = list(lengths) if lengths is not None else [0] * n
        self.skip = 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        """The epoch whose order comes next; its first ``skip`` batches (chunks at
        ``batch_size`` 1) are left out of the next iteration only."""
        if skip < 0:
            raise ValueError(f"`skip`: expected batches >= 0, got {skip}")
        self.epoch, self.skip = int(epoch), int(skip)

    def order(self) -> List[int]:
        """The epoch's order of all ``n`` chunks (before sharding)."""
        if not self.order_shuffle:
            return list(range(self.n))
        g = torch.Generator().manual_seed(self.seed * 100003 + self.epoch)
        return torch.randperm(self.n, generator=g).tolist()

    def _shard(self) -> List[int]:
        order = self.order()
        return [order[i] for i in super().__iter__()]

    def batches(self) -> List[List[int]]:
        """This replica's batches of the epoch: its chunks in order, each added to the
        open batch of its frame count, a batch given out when it holds ``batch_size``
        chunks; the last, partly filled ones at the end."""
        open_: Dict[int, List[int]] = {}
        out: List[List[int]] = []
        for i in self._shard():
            b = open_.setdefault(self.lengths[i], [])
            b.append(i)
            if len(b) == self.batch_size:
                out.append(open_.pop(self.lengths[i]))
        return out + [b for b in open_.values() if b]

    def __iter__(self) -> Iterator[Any]:
        """Chunk indices (``batch_size`` 1), else lists of them (:meth:`batches`)."""
        items = self._shard() if self.batch_size == 1 else self.batches()
        skip, self.skip = self.skip, 0
        return iter(items[skip:])

    def __len__(self) -> int:
        return super().__len__() if self.batch_size == 1 else len(self.batches())

    def __repr__(self) -> str:
        return (f"EpochShuffleSampler(n={self.n}, seed={self.seed}, "
                f"shuffle={self.order_shuffle}, rank={self.rank}/{self.num_replicas}, "
                f"batch_size={self.batch_size})")


def _identity(x):
    return x


class GarmentDataModule(L.LightningDataModule):
    """Train/val/test chunks from the manifest's splits: ``batch_size`` training chunks
    per step (one ``Batch``, see the module doc); validation, test and predict one chunk
    (a sequence's frames in order) per step.

    The arguments are the data module's hyper-parameters (``self.hparams``, stored in
    every checkpoint).  :meth:`setup` builds only what a stage reads: ``fit`` the
    training and validation chunks, ``validate`` the validation chunks, ``test`` the
    ``test_split`` chunks, ``predict`` the ``predict_split`` chunks (default: the test
    split) in order.

    :attr:`dims` (for building a model) are read from the first training chunk.

    ``stride`` spaces the training chunks' first frames (default ``chunk``: disjoint
    chunks; ``chunk=3, stride=1, drop_last=True``: every frame triple, the one-step
    samples of a learned simulator); ``eval_chunk`` is the frames of a validation, test
    and predict chunk (default ``chunk``; the sequence length: whole sequences, which an
    autoregressive method rolls out; ``drop_last`` does not apply to them).

    ``cache_size`` and ``cache_bytes`` bound each split's cache of loaded sequence files
    (files, bytes of their arrays; :class:`~garmentgnn.data.SequenceChunks`), one cache
    per process and per loader worker.

    ``seed`` seeds the training chunks' order; ``None`` (the default) takes the run's
    seed, the one ``--seed_everything`` (or Lightning's ``seed_everything``) set, so one
    seed seeds the initialisation, the noise and the data order alike (0 where nothing
    was seeded).  An explicit ``seed`` keeps one order whatever the run's seed
    (:meth:`order_seed`).

    Resuming: the epoch to continue with, the batches of it that already ran and the
    order's seed are kept in the checkpoint (:meth:`state_dict`) and the training
    sampler starts there, because Lightning (2.6) builds a resumed fit's first data
    iterator *before* it calls the sampler's ``set_epoch``, which would replay epoch 0's
    chunk order, and replays a plain sampler's epoch from its first batch: a fit
    stopped anywhere and resumed sees the batches of an uninterrupted one, in order.
    """

    def __init__(self, root: Union[str, Path], chunk: int = CHUNK, history: int = HISTORY,
                 num_workers: int = 0, nystrom_dim: int = NYSTROM_DIM,
                 num_landmarks: int = NUM_LANDMARKS,
                 train_split: str = "train", val_split: Optional[str] = "val",
                 shuffle: bool = True, seed: Optional[int] = None, drop_last: bool = False,
                 test_split: str = "test", train_ids: Optional[Sequence[str]] = None,
                 cache_size: int = CACHE_SIZE, predict_split: Optional[str] = None,
                 batch_size: int = 1, stride: Optional[int] = None,
                 eval_chunk: Optional[int] = None, cache_bytes: int = CACHE_BYTES) -> None:
        super().__init__()
        if eval_chunk is not None and (not isinstance(eval_chunk, int)
                                       or isinstance(eval_chunk, bool) or eval_chunk < 1):
            raise ValueError(f"--data.eval_chunk: expected frames >= 1 or null (--data.chunk), "
                             f"got {eval_chunk!r}")
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
            raise ValueError(f"--data.seed: expected an integer, or null for the run's seed "
                             f"(--seed_everything), got {seed!r}")
        if not isinstance(batch_size, int) or isinstance(batch_size, bool) or batch_size < 1:
            raise ValueError(f"--data.batch_size: expected a number of chunks >= 1, got "
                             f"{batch_size!r}")
        if not (Path(root) / store.MANIFEST).is_file():
            store.read_manifest(root)  # raises: which path, and the command that makes it
        # plain types in the hyper-parameters: checkpoints load with weights_only=True
        root = str(root)
        if train_ids is not None:
            train_ids = [str(i) for i in train_ids]
        self.save_hyperparameters()
        self.root = Path(root)
        self.train_set: Optional[SequenceChunks] = None
        self.val_set: Optional[SequenceChunks] = None
        self.test_set: Optional[SequenceChunks] = None
        self.predict_set: Optional[SequenceChunks] = None
        self.start_epoch = 0  # the epoch a resumed fit continues with
        self.start_batch = 0  # and the batches of it that already ran
        self._resumed_seed: Optional[int] = None  # the order's seed of a resumed fit

    @classmethod
    def settings(cls, saved: Optional[Dict[str, Any]]) -> Dict[str, Any]:
        """The arguments of this class among a checkpoint's saved data-module settings
        (``datamodule_hyper_parameters``); entries of another version or another
        class are left out."""
        params = inspect.signature(cls.__init__).parameters
        return {k: v for k, v in (saved or {}).items() if k in params and k != "self"}

    def order_seed(self) -> int:
        """The seed of the training chunks' order: ``seed`` when given; else the one a
        resumed fit's checkpoint kept; else the run's seed (``PL_GLOBAL_SEED``, which
        Lightning's ``seed_everything`` sets), 0 when nothing was seeded."""
        if self.hparams.get("seed") is not None:
            return int(self.hparams.seed)
        if self._resumed_seed is not None:
            return self._resumed_seed
        return int(os.environ.get("PL_GLOBAL_SEED", 0))

    def state_dict(self) -> Dict[str, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return {}
        # epochs whose training part ran to its end (a checkpoint written in
        # on_train_epoch_end or after fit); a resumed fit starts with the next one, after
        # the batches of it that ran (a checkpoint written in the middle of an epoch: on
        # a batch's end, after a validation)
        epochs = trainer.fit_loop.epoch_progress.current
        batches = trainer.fit_loop.epoch_loop.batch_progress.current.processed
        return {"next_epoch": int(epochs.processed),
                "epoch_batches": int(batches) if epochs.started > epochs.processed else 0,
                "order_seed": self.order_seed()}

    def load_state_dict(self, state: Dict[str, int]) -> None:
        self.start_epoch = int(state.get("next_epoch", 0))
        self.start_batch = int(state.get("epoch_batches", 0))
        # a resumed fit goes on in the order it started with (a checkpoint written
        # before the seed was kept: the run's seed, as then)
        if "order_seed" in state:
            self._resumed_seed = int(state["order_seed"])

    def _make(self, name: str, split: Optional[str], ids: Optional[Sequence[str]] = None
              ) -> SequenceChunks:
        """The chunks of ``split``, the value of argument ``name`` (``"val_split"``, ...):
        an error about the split names that argument."""
        hp = self.hparams
        train = name == "train_split"
        whole = not train and hp.get("eval_chunk") is not None
        chunk = hp.eval_chunk if whole else hp.chunk
        try:
            return SequenceChunks(self.root, split, chunk, hp.history, hp.nystrom_dim,
                                  hp.num_landmarks, drop_last=hp.drop_last and not whole,
                                  cache_size=hp.cache_size,
                                  cache_bytes=hp.get("cache_bytes", CACHE_BYTES), ids=ids,
                                  stride=hp.get("stride") if train else None)
        except ValueError as exc:
            msg = str(exc)
            if not msg.startswith("`split`"):
                raise
            fix = {"val_split": " (or val_split=None, --data.val_split null, to train "
                                "without validation)"}.get(name, "")
            raise ValueError(f"`{name}`{msg[len('`split`'):]}{fix}") from None

    def _train(self, batches: bool = False) -> SequenceChunks:
        """The training chunks; ``batches``: checked against ``batch_size`` (what a fit
        draws; a test or predict run reads them only for the model's sizes)."""
        if self.train_set is None:
            self.train_set = self._make("train_split", self.hparams.train_split,
                                        self.hparams.train_ids)
        train = self.train_set
        if batches and self.hparams.batch_size > len(train):
            raise ValueError(f"--data.batch_size: {self.hparams.batch_size} is more than "
                             f"the {len(train)} chunks of the {self.hparams.train_split!r} "
                             f"split; give at most {len(train)}")
        return train

    def setup(self, stage: Optional[str] = None) -> None:
        """Build the chunks ``stage`` reads (``"fit"``, ``"validate"``, ``"test"``,
        ``"predict"``; ``None``: all of them)."""
        hp = self.hparams
        if stage not in (None, "fit", "validate", "test", "predict"):
            raise ValueError(f"`stage`: expected fit, validate, test, predict or None, "
                             f"got {stage!r}")
        if stage in (None, "fit"):
            self._train(batches=True)
        if stage in (None, "fit", "validate") and self.val_set is None \
                and hp.val_split is not None:
            self.val_set = self._make("val_split", hp.val_split)
        if stage in (None, "test") and self.test_set is None:
            self.test_set = self._make("test_split", hp.test_split)
        if stage in (None, "predict") and self.predict_set is None:
            name = "test_split" if hp.predict_split is None else "predict_split"
            self.predict_set = self._make(name, hp[name])

    @property
    def dims(self) -> Dict[str, Optional[int]]:
        """The model sizes of the data: ``num_joints``, ``num_body_vertices``,
        ``nystrom_dim`` and ``num_vertices`` (the garment's vertex count when every
        training sequence shows one garment on one body, else ``None``: what a
        garment-specific model such as NCS-style is built for)."""
        train = self._train()
        if not len(train):
            raise ValueError(f"no {self.hparams.train_split!r} chunks under {self.root}")
        st = train.static(train.index[0][0])
        pairs = {(garment_key(r["garment"]), body_key(r["body"])) for r in train.records}
        return {"num_joints": st["rest_joints"].shape[0],
                "num_body_vertices": st["body_joint_dists"].shape[0],
                "nystrom_dim": self.hparams.nystrom_dim,
                "num_vertices": st.num_vertices if len(pairs) == 1 else None}

    def model_sizes(self, model_class: type) -> Dict[str, Optional[int]]:
        """The :attr:`dims` that ``model_class`` takes, as ``garmentgnn train`` links them:
        ``GarTrans(**dm.model_sizes(GarTrans))``."""
        params = inspect.signature(model_class.__init__).parameters
        return {k: v for k, v in self.dims.items() if k in params}

    def _loader(self, ds: SequenceChunks, shuffle: bool, num_replicas: int = 1,
                rank: int = 0, batch_size: int = 1) -> DataLoader:
        hp = self.hparams
        sampler = EpochShuffleSampler(len(ds), self.order_seed(), shuffle, num_replicas, rank,
                                      batch_size, ds.frame_counts())
        return DataLoader(ds, batch_size=None, sampler=sampler,
                          num_workers=hp.num_workers, collate_fn=_identity,
                          persistent_workers=hp.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        trainer = getattr(self, "trainer", None)
        # DDP: this replica's share (Trainer.distributed_sampler_kwargs is None for a
        # strategy that does not shard the data)
        shard = trainer.distributed_sampler_kwargs if trainer is not None else None
        world, rank = (shard["num_replicas"], shard["rank"]) if shard else (1, 0)
        dl = self._loader(self._train(batches=True), self.hparams.shuffle, world, rank,
                          self.hparams.batch_size)
        if self.start_batch >= len(dl.sampler):  # stopped after the epoch's last batch
            dl.sampler.set_epoch(self.start_epoch + 1)
        else:
            dl.sampler.set_epoch(self.start_epoch, skip=self.start_batch)
        return dl

    def val_dataloader(self) -> Union[DataLoader, List[DataLoader]]:
        self.setup("validate")
        if self.val_set is None:
            return []
        return self._loader(self.val_set, False)

    def test_dataloader(self) -> DataLoader:
        """Chunks of ``test_split`` in order (``garmentgnn train test``)."""
        self.setup("test")
        return self._loader(self.test_set, False)

    def predict_dataloader(self) -> DataLoader:
        """Chunks of ``predict_split`` (default: ``test_split``) in order
        (``garmentgnn train predict``)."""
        self.setup("predict")
        return self._loader(self.predict_set, False)


__all__ = ["MODEL_INPUTS", "EpochShuffleSampler", "GarmentDataModule"]
