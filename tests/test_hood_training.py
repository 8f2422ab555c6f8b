"""HOOD-style training aids: the running input normaliser and the own start state."""
import runpy
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from garmentgnn.harness.methods import BASELINES, HOOD
from garmentgnn.models.baselines import CoarseLevel, HOODStyle
from garmentgnn.models.blocks import RunningNormalizer
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (BaselineModule, GarmentDataModule)
from garmentgnn.training.module import loss_inputs
from garmentgnn.models.baselines import DAStyle
from garmentgnn.training.configs import instantiate, merge

from conftest import skirt_dataset



def test_running_normalizer_is_the_statistics_of_the_training_rows():
    g = torch.Generator().manual_seed(0)
    norm = RunningNormalizer(3, max_updates=2)
    x = torch.randn(4, 5, 3, generator=g)
    assert torch.equal(norm.eval()(x), x)  # before any statistics: the identity
    batches = [torch.randn(4, 5, 3, generator=g) * torch.tensor([1.0, 10.0, 0.1]) + 7.0
               for _ in range(3)]
    norm.train()
    for b in batches:
        norm(b)
    seen = np.concatenate([b.reshape(-1, 3).numpy() for b in batches[:2]]).astype(np.float64)
    mean, std = norm.mean_std()
    np.testing.assert_allclose(mean.numpy(), seen.mean(0), rtol=1e-12)
    np.testing.assert_allclose(std.numpy(), seen.std(0), rtol=1e-9)  # the third call: frozen
    assert int(norm.updates) == 2 and float(norm.count) == 40
    norm.eval()
    probe = torch.randn(2, 3, generator=g, dtype=torch.float64)
    np.testing.assert_allclose(norm(probe).numpy(), (probe.numpy() - seen.mean(0)) / seen.std(0),
                               rtol=1e-9)
    assert int(norm.updates) == 2
    fresh = RunningNormalizer(3)
    fresh.load_state_dict(norm.state_dict())  # the statistics travel in the checkpoint
    torch.testing.assert_close(fresh.eval()(probe), norm(probe))
    const = RunningNormalizer(2)
    out = const(torch.ones(5, 2))  # a constant feature: zero, not NaN
    assert torch.equal(out, torch.zeros(5, 2))
    for kw in ({"size": 0}, {"size": 2, "max_updates": -1}, {"size": 2, "eps": 0.0}):
        with pytest.raises(ValueError, match=f"`{list(kw)[-1]}`"):
            RunningNormalizer(**kw)
    with pytest.raises(ValueError, match="`x`"):
        norm(torch.zeros(2, 4))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("data"), ["walk", "run"], 8, name="hood")


def _module(dims, **kw) -> BaselineModule:
    model = kw.pop("model", {"hidden": 16, "fine_blocks": 1, "coarse_blocks": 1})
    spec = merge(BASELINES[HOOD], {"init_args": dict(kw, loss={"compile_search": False})})
    spec["init_args"]["model"]["init_args"] = model
    return instantiate(spec, dims)


def test_hood_normalised_inputs(data):
    chunks = SequenceChunks(data, "train", chunk=4)
    item = chunks[0]
    module = _module(GarmentDataModule(data, chunk=4).dims, model={"hidden": 16, "normalize": True})
    model = module.model
    coarse = CoarseLevel.build(item.rest_pos, item.faces)
    x = item.skinned()
    model.train()
    a = model(item, coarse, x[0:2], x[1:3], item.body_pos[2:4])
    assert torch.isfinite(a).all()
    assert int(model.node_norm.updates) == 1 and int(model.edge_norm.updates) == 1
    assert float(model.node_norm.count) == 2 * item.num_vertices
    model.eval()
    model(item, coarse, x[0:2], x[1:3], item.body_pos[2:4])
    assert int(model.node_norm.updates) == 1  # frozen in evaluation
    assert "node_norm.total" in model.state_dict()
    assert "node_norm.total" not in HOODStyle(hidden=16).state_dict()  # off by default


def test_hood_acceleration_unit(data):
    item = SequenceChunks(data, "train", chunk=4)[0]
    coarse = CoarseLevel.build(item.rest_pos, item.faces)
    x = item.skinned()
    torch.manual_seed(0)
    unit = HOODStyle(hidden=16)
    scaled = HOODStyle(hidden=16, accel_scale=10.0)
    scaled.load_state_dict(unit.state_dict())  # no new weights: an output unit
    args = (item, coarse, x[0:2], x[1:3], item.body_pos[2:4])
    torch.testing.assert_close(scaled(*args), 10.0 * unit(*args))
    with pytest.raises(ValueError, match="`accel_scale`"):
        HOODStyle(accel_scale=0.0)



def test_hood_with_a_zero_decoder_throws_the_garment_at_its_first_velocity(data):
    """Where the decoder outputs 0 the rollout is ballistic, ``x0 + t v``, with the pinned
    waist driven by LBS."""
    item = SequenceChunks(data, "train", chunk=8)[0]
    coarse = CoarseLevel.build(item.rest_pos, item.faces)
    lbs = item.skinned().double()
    torch.manual_seed(0)
    plain = HOODStyle(hidden=16).double()
    torch.nn.init.zeros_(plain.decoder[-1].weight)
    torch.nn.init.zeros_(plain.decoder[-1].bias)
    body = item.body_pos.double()
    with torch.no_grad():
        t = torch.arange(8, dtype=torch.float64).view(8, 1, 1)  # the oracle: x0 + t v,
        thrown = lbs[0] + t * (lbs[1] - lbs[0])  # the pinned waist driven by LBS
        thrown = torch.where(item.pinned_mask().view(1, -1, 1), lbs, thrown)
        assert item.pinned_mask().any() and not item.pinned_mask().all()
        torch.testing.assert_close(plain.rollout(item, coarse, lbs[0], lbs[1], body, lbs),
                                   thrown, rtol=0, atol=1e-12)


def test_hood_training_rollout_keeps_the_states_of_its_steps(data):
    """The training rollout of a chunk starts from the LBS garment of the two frames
    before it: the states it keeps are those of ``HOODStyle.step`` by hand."""
    chunks = SequenceChunks(data, "train", chunk=4)
    second = chunks[1]
    assert int(second.frames[0]) == 4
    torch.manual_seed(0)
    module = _module(GarmentDataModule(data, chunk=4, val_split=None).dims, start_state="own",
                     model={"hidden": 16, "fine_blocks": 1, "coarse_blocks": 1})
    module.compute_loss(second)
    whole = SequenceChunks(data, "train", chunk=8)[0]  # frames 0-7 of the same sequence
    assert whole.seq_id == second.seq_id
    path = whole.skinned()
    coarse = module.coarse_level(second)
    x_prev, x_curr = path[2], path[3]
    with torch.no_grad():
        for t in range(4, 8):
            nxt = module.model.step(second, coarse, x_prev[None], x_curr[None],
                                    second.body_pos[t - 4:t - 3], path[t:t + 1])[0]
            x_prev, x_curr = x_curr, nxt
    kept = module._states[second.seq_id]
    torch.testing.assert_close(kept[6], x_prev)
    torch.testing.assert_close(kept[7], x_curr)


def test_own_start_state_chains_the_rollouts(data, tmp_path):
    dm = GarmentDataModule(data, chunk=4, val_split=None)
    chunks = SequenceChunks(data, "train", chunk=4)
    first, second = chunks[0], chunks[1]
    assert first.seq_id == second.seq_id and int(second.frames[0]) == 4
    torch.manual_seed(0)
    module = _module(dm.dims, start_state="own")
    lbs = first.skinned()
    prev, curr = module._start(second)  # nothing kept yet: the LBS garment of frames 2, 3
    torch.testing.assert_close(prev, lbs[2])
    torch.testing.assert_close(curr, lbs[3])

    module.compute_loss(first)
    # the oracle: the same rollout by HOODStyle.step, from the LBS garment of frame 0
    coarse = module.coarse_level(first)
    x_prev = x_curr = lbs[0]
    with torch.no_grad():
        for b in range(4):
            nxt = module.model.step(first, coarse, x_prev[None], x_curr[None],
                                    first.body_pos[b:b + 1], lbs[b:b + 1])[0]
            x_prev, x_curr = x_curr, nxt
    kept = module._states[first.seq_id]
    assert sorted(kept) == [2, 3]
    torch.testing.assert_close(kept[2], x_prev)
    torch.testing.assert_close(kept[3], x_curr)
    prev, curr = module._start(second)  # the next chunk starts where this one ended
    assert torch.equal(prev, kept[2]) and torch.equal(curr, kept[3])
    assert not torch.equal(curr, lbs[3])

    strict = _module(dm.dims, start_state="own", max_start_drift=1e-12)
    strict._states = module._states  # farther from LBS than allowed: the LBS garment
    torch.testing.assert_close(strict._start(second)[1], lbs[3])
    plain = _module(dm.dims, start_state="lbs")
    plain.compute_loss(first)
    assert plain._states == {}  # "lbs" keeps nothing

    ckpt = {}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, tmp_path / "c.pt")
    back = _module(dm.dims, start_state="own")
    back.on_load_checkpoint(torch.load(tmp_path / "c.pt", weights_only=True))
    assert torch.equal(back._start(second)[1], kept[3])


def test_own_start_state_through_the_trainer(data):
    dm = GarmentDataModule(data, chunk=4, val_split=None)
    L.seed_everything(0, verbose=False)
    module = _module(dm.dims, start_state="own")
    L.Trainer(max_epochs=2, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False,
              limit_val_batches=0).fit(module, dm)
    assert len(module._states) == 2  # every training sequence
    assert all(sorted(k) == [2, 3, 6, 7] for k in module._states.values())
    assert all(torch.isfinite(s).all() for k in module._states.values() for s in k.values())


def test_start_state_arguments(data):
    dims = GarmentDataModule(data, chunk=4).dims
    with pytest.raises(ValueError, match="`start_state`"):
        _module(dims, start_state="simulated")
    with pytest.raises(ValueError, match="`start_state`"):
        BaselineModule(DAStyle(dims["num_joints"]), start_state="own")
    with pytest.raises(ValueError, match="`max_start_drift`"):
        _module(dims, max_start_drift=0.0)


def test_own_objective_is_the_mean_of_the_per_frame_training_losses(data):
    """``benchmarks/learning.py``'s ``own_objective``: frame ``t``'s physics loss with the
    inertial prediction ``2 p_{t-1} - p_{t-2}``, averaged over frames 2.."""
    bench = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                               "learning.py"), run_name="own_objective_check")
    item = SequenceChunks(data, "train", chunk=10 ** 9)[0]
    module = _module(GarmentDataModule(data, chunk=4).dims)
    g = torch.Generator().manual_seed(0)
    traj = item.skinned() + 0.01 * torch.randn(item.skinned().shape, generator=g)
    got = bench["own_objective"](module, item, traj)
    per_frame = []
    for t in range(2, item.num_frames):
        frame = item.select(torch.tensor([t]))
        total, _ = module.loss_fn(loss_inputs(frame, traj[t:t + 1], module.dt,
                                              predicted=(2 * traj[t - 1] - traj[t - 2])[None],
                                              ground_truth=False))
        per_frame.append(float(total))
    assert got["total"] == pytest.approx(np.mean(per_frame), rel=1e-5)
    assert {"inertia", "stretch", "collision"} <= set(got)
