"""One seed seeds the run: ``--seed_everything`` (the recipe's ``seed_everything``) sets
the training chunks' order as well as the initialisation and the noise, unless
``data.seed`` names an order of its own; a resumed fit keeps the order it started with and
goes on from the batch it stopped at."""
import os

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import ModelCheckpoint

from conftest import skirt_dataset
from garmentgnn.training import GarmentDataModule, load_recipe


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    # 5 sequences of 8 frames: 10 training chunks of 4 frames, 10! orders
    return skirt_dataset(tmp_path_factory.mktemp("seeded"),
                         ["walk", "run", "jump", "twirl", "kick"], 8)


def run(root, run_seed, **data):
    """What ``garmentgnn train fit --config gartrans --seed_everything SEED`` starts
    from: the first epoch's training chunks in order, the first weights, and the first
    noise drawn after the set-up."""
    r = load_recipe("gartrans", args=["--seed_everything", str(run_seed)],
                    data=dict(root=str(root), val_split=None, chunk=4, history=2,
                              nystrom_dim=4, num_landmarks=16, **data))
    order = list(r.datamodule.train_dataloader().sampler)
    weights = torch.cat([p.detach().flatten() for p in r.module.parameters()])
    return order, weights, torch.randn(4)


def test_the_runs_seed_orders_the_data(root):
    order0, w0, noise0 = run(root, 0)
    order1, w1, noise1 = run(root, 1)
    again0, again_w0, again_noise0 = run(root, 0)
    assert sorted(order0) == sorted(order1) == list(range(10))
    # another seed: another order (the first batch too), other weights, other noise
    assert order0[0] != order1[0] and order0 != order1
    assert not torch.equal(w0, w1) and not torch.equal(noise0, noise1)
    # the same seed: the same run
    assert again0 == order0 and torch.equal(again_w0, w0) and torch.equal(again_noise0, noise0)


def test_an_explicit_data_seed_keeps_its_order(root):
    order0, _, _ = run(root, 0, seed=5)
    order1, w1, _ = run(root, 1, seed=5)
    plain1, plain_w1, _ = run(root, 1)
    assert order0 == order1  # the order data.seed names, whatever the run's seed
    assert order1 != plain1 and torch.equal(w1, plain_w1)  # the rest follows the run's


def test_a_resumed_fit_keeps_its_order(root, monkeypatch):
    monkeypatch.setenv("PL_GLOBAL_SEED", "3")
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=4, num_landmarks=16,
                           val_split=None)
    assert dm.order_seed() == 3
    monkeypatch.setenv("PL_GLOBAL_SEED", "7")  # resumed under another run seed
    resumed = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=4, num_landmarks=16,
                                val_split=None)
    resumed.load_state_dict({"next_epoch": 2, "order_seed": 3})
    assert resumed.order_seed() == 3 and resumed.start_epoch == 2
    monkeypatch.delenv("PL_GLOBAL_SEED")
    assert GarmentDataModule(root, chunk=4, history=2, nystrom_dim=4, num_landmarks=16,
                             val_split=None).order_seed() == 0
    assert "PL_GLOBAL_SEED" not in os.environ


def test_a_checkpoints_data_settings_rebuild_its_data_module(root):
    dm = GarmentDataModule(root, chunk=5, history=2, nystrom_dim=4, num_landmarks=16,
                           val_split=None, seed=4)
    saved = dict(dm.hparams, self=None, an_older_setting=1)  # as a checkpoint keeps them
    settings = GarmentDataModule.settings(saved)
    assert "an_older_setting" not in settings and "self" not in settings
    assert dict(GarmentDataModule(**settings).hparams) == dict(dm.hparams)
    assert GarmentDataModule.settings(None) == {}


@pytest.mark.parametrize("seed", [1.5, "1", True])
def test_a_data_seed_that_is_no_integer_is_refused(root, seed):
    with pytest.raises(ValueError, match="--data.seed"):
        GarmentDataModule(root, chunk=4, seed=seed)



class _Seen(L.Callback):
    """The training batches a fit runs, in order: (epoch, batch index, the batch's
    ground truth summed), the last naming its chunks."""

    def __init__(self):
        self.seen = []

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        self.seen.append((trainer.current_epoch, batch_idx, round(float(batch["gt"].sum()), 4)))


class _Fit(L.LightningModule):
    """One weight fitted to the batches' mean ground truth: a fit whose cost is the data's."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(()))

    def training_step(self, batch, batch_idx):
        return (self.w - batch["gt"].mean()) ** 2

    def validation_step(self, batch, batch_idx):
        self.log("val", (self.w - batch["gt"].mean()) ** 2)

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


@pytest.fixture(scope="module")
def with_val(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("seeded_val"),
                         ["walk", "run", "jump", "twirl", "kick", "sit_stand"], 8,
                         held_out={"val": ["sit_stand"]})


def _fit(root, callbacks, batch_size, ckpt_path=None, **trainer_kw):
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=4, num_landmarks=16,
                           seed=0, batch_size=batch_size)
    L.seed_everything(0)
    tr = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                   enable_model_summary=False, callbacks=callbacks, num_sanity_val_steps=0,
                   limit_val_batches=1, **trainer_kw)
    tr.fit(_Fit(), dm, ckpt_path=ckpt_path)
    return dm


@pytest.mark.parametrize("batch_size, stop", [
    (1, {"max_steps": 3}),  # the checkpoint of a batch in the middle of the first epoch
    (1, {"max_steps": 13}),  # ... of the second epoch
    (1, {"max_steps": 10}),  # ... of an epoch's last batch (its end not yet reached)
    (1, {"max_epochs": 1}),  # the end of an epoch
    (1, {"max_steps": 6, "val_check_interval": 3}),  # the end of a validation in an epoch
    (2, {"max_steps": 7}),  # two chunks a batch, in the second epoch
])
def test_a_fit_stopped_anywhere_resumes_with_the_batches_it_had_not_run(with_val, tmp_path,
                                                                       batch_size, stop):
    """Stopped at a checkpoint and resumed, a fit runs the batches of an uninterrupted
    fit in its order: none twice, none left out.  Lightning alone would replay the
    stopped epoch from its first batch, and a checkpoint of an epoch's last batch would
    replay that epoch's order as the next epoch's."""
    n = 10 // batch_size  # batches an epoch: 10 training chunks
    val = {"val_check_interval": stop.get("val_check_interval")}
    full = _Seen()
    _fit(with_val, [full], batch_size, max_epochs=3, enable_checkpointing=False, **val)
    assert len(full.seen) == 3 * n
    assert [s[2] for s in full.seen[:n]] != [s[2] for s in full.seen[n:2 * n]]
    part, rest = _Seen(), _Seen()
    every = {} if "max_epochs" in stop else {"every_n_train_steps": 1}
    _fit(with_val, [part, ModelCheckpoint(dirpath=tmp_path, save_last=True, **every)],
         batch_size, **stop)
    assert 0 < len(part.seen) < 3 * n
    dm = _fit(with_val, [rest], batch_size, ckpt_path=str(tmp_path / "last.ckpt"),
              max_epochs=3, enable_checkpointing=False, **val)
    assert part.seen + rest.seen == full.seen
    assert dm.state_dict()["epoch_batches"] == 0  # a finished fit: no epoch in progress
