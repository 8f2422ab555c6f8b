"""One seed seeds the run: ``--seed_everything`` (the recipe's ``seed_everything``) sets
the training chunks' order as well as the initialisation and the noise, unless
``data.seed`` names an order of its own; a resumed fit keeps the order it started with."""
import os

import pytest
import torch

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


@pytest.mark.parametrize("seed", [1.5, "1", True])
def test_a_data_seed_that_is_no_integer_is_refused(root, seed):
    with pytest.raises(ValueError, match="--data.seed"):
        GarmentDataModule(root, chunk=4, seed=seed)
