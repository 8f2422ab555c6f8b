"""HOOD-style training aids: the running input normaliser and the own start state."""
import inspect
import runpy
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch

from garmentgnn.models.baselines import CoarseLevel, HOODStyle
from garmentgnn.models.blocks import RunningNormalizer
from garmentgnn.training.baselines import ramped_length
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (BaselineModule, GarmentDataModule)
from garmentgnn.training.module import loss_inputs
from garmentgnn.models.baselines import DAStyle

from conftest import skirt_dataset
from recipe_helpers import module as recipe_module



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


def _module(root, **kw) -> BaselineModule:
    """The HOOD-style recipe's module on ``root`` with module settings ``kw`` and a
    small model (``model``: its settings; the recipe's are replaced)."""
    model = kw.pop("model", {"hidden": 16, "fine_blocks": 1, "coarse_blocks": 1})
    defaults = inspect.signature(HOODStyle.__init__).parameters
    model = dict({k: defaults[k].default for k in ("hidden", "fine_blocks", "coarse_blocks",
                                                   "normalize")}, **model)
    return recipe_module("baselines/hood", root, **{f"model.model.{k}": v
                                                    for k, v in model.items()},
                         **{f"model.{k}": v for k, v in kw.items()})


def test_hood_normalised_inputs(data):
    chunks = SequenceChunks(data, "train", chunk=4)
    item = chunks[0]
    module = _module(data, model={"hidden": 16, "normalize": True})
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
    module = _module(data, start_state="own",
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
    chunks = SequenceChunks(data, "train", chunk=4)
    first, second = chunks[0], chunks[1]
    assert first.seq_id == second.seq_id and int(second.frames[0]) == 4
    torch.manual_seed(0)
    module = _module(data, start_state="own")
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

    strict = _module(data, start_state="own", max_start_drift=1e-12)
    strict._states = module._states  # farther from LBS than allowed: the LBS garment
    torch.testing.assert_close(strict._start(second)[1], lbs[3])
    plain = _module(data, start_state="lbs")
    plain.compute_loss(first)
    assert plain._states == {}  # "lbs" keeps nothing

    ckpt = {}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, tmp_path / "c.pt")
    back = _module(data, start_state="own")
    back.on_load_checkpoint(torch.load(tmp_path / "c.pt", weights_only=True))
    assert torch.equal(back._start(second)[1], kept[3])


def test_own_start_state_through_the_trainer(data):
    dm = GarmentDataModule(data, chunk=4, val_split=None)
    L.seed_everything(0, verbose=False)
    module = _module(data, start_state="own")
    L.Trainer(max_epochs=2, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False,
              limit_val_batches=0).fit(module, dm)
    assert len(module._states) == 2  # every training sequence
    assert all(sorted(k) == [2, 3, 6, 7] for k in module._states.values())
    assert all(torch.isfinite(s).all() for k in module._states.values() for s in k.values())


def test_start_state_arguments(data):
    dims = GarmentDataModule(data, chunk=4).dims
    with pytest.raises(ValueError, match="`start_state`"):
        _module(data, start_state="simulated")
    with pytest.raises(ValueError, match="`start_state`"):
        BaselineModule(DAStyle(dims["num_joints"]), start_state="own")
    with pytest.raises(ValueError, match="`max_start_drift`"):
        _module(data, max_start_drift=0.0)


def test_own_objective_is_the_mean_of_the_per_frame_training_losses(data):
    """``benchmarks/learning.py``'s ``own_objective``: frame ``t``'s physics loss with the
    inertial prediction ``2 p_{t-1} - p_{t-2}``, averaged over frames 2.."""
    bench = runpy.run_path(str(Path(__file__).resolve().parents[1] / "benchmarks" /
                               "learning.py"), run_name="own_objective_check")
    item = SequenceChunks(data, "train", chunk=10 ** 9)[0]
    module = _module(data)
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


def _recorded_rollout(module, item):
    """``module.compute_loss(item)`` with every ``HOODStyle.step``'s input positions and
    output, and the loss's inputs, recorded."""
    calls, seen = [], []
    step = module.model.step

    def record_step(inp, coarse, x_prev, x_curr, *a, **kw):
        out = step(inp, coarse, x_prev, x_curr, *a, **kw)
        calls.append((x_prev[0].detach(), x_curr[0].detach(), out[0].detach()))
        return out

    module.model.step = record_step
    module.loss_fn.register_forward_pre_hook(lambda _, args: seen.append(args[0]))
    module.compute_loss(item)
    return calls, seen[0]


@pytest.mark.parametrize("rollout", [1, 3])
def test_hood_rollouts_restart_from_the_lbs_garment(data, rollout):
    """HOOD's recipe: a rollout restarts every ``rollout`` frames from the LBS garment of
    the two frames before it; between restarts each step continues from the last two
    outputs.  Oracle: the LBS garment of the whole sequence."""
    item = SequenceChunks(data, "train", chunk=4)[1]  # frames 4-7
    assert int(item.frames[0]) == 4
    path = SequenceChunks(data, "train", chunk=10 ** 9)[0].skinned()
    torch.manual_seed(0)
    module = _module(data, rollout=rollout)
    calls, _ = _recorded_rollout(module, item)
    assert len(calls) == 4
    for b, (p, c, _) in enumerate(calls):
        if b % rollout == 0:  # from the LBS garment of frames 4 + b - 2, 4 + b - 1
            torch.testing.assert_close(p, path[2 + b])
            torch.testing.assert_close(c, path[3 + b])
        else:
            assert torch.equal(c, calls[b - 1][2])
            assert torch.equal(p, calls[b - 1][1])
    whole = _module(data)  # None: one rollout per chunk
    calls, _ = _recorded_rollout(whole, item)
    assert all(torch.equal(calls[b][1], calls[b - 1][2]) for b in range(1, 4))


def test_hood_noise_on_the_current_and_previous_positions(data):
    """3 mm of Gaussian noise on both input positions of every step (their std, from
    ``4 x 200 x 3`` samples each, within 5%), the inertial prediction ``2 c - p`` of the
    noisy positions, and the noise-free states carried on."""
    item = SequenceChunks(data, "train", chunk=4)[1]
    path = SequenceChunks(data, "train", chunk=10 ** 9)[0].skinned()
    torch.manual_seed(0)
    module = _module(data, rollout=1, rollout_noise=0.003)
    calls, li = _recorded_rollout(module, item)
    dp = torch.stack([p - path[2 + b] for b, (p, _, _) in enumerate(calls)])
    dc = torch.stack([c - path[3 + b] for b, (_, c, _) in enumerate(calls)])
    for d in (dp, dc):
        assert float(d.mean().abs()) < 3e-4
        assert float(d.std()) == pytest.approx(0.003, rel=0.05)
    assert float((dp - dc).std()) == pytest.approx(0.003 * 2 ** 0.5, rel=0.05)  # independent
    expected = torch.stack([2 * c - p for p, c, _ in calls])
    torch.testing.assert_close(li.predicted, expected)
    torch.testing.assert_close(li.pred.detach(), torch.stack([o for _, _, o in calls]))


def test_rollout_length_ramp():
    assert [ramped_length(5, 100, s) for s in (0, 24, 25, 50, 99, 100, 10 ** 6)] == \
        [1, 1, 2, 3, 4, 5, 5]
    assert ramped_length(5, 0, 0) == 5


def test_hood_warmup_scales_the_learning_rate_of_each_step(data):
    """The rate seen by the optimizer at step ``s`` is ``lr (s + 1) / warmup``; the
    oracle for the first: Adam's first update moves every parameter with a gradient
    well above its ``eps`` by exactly the rate."""
    dm = GarmentDataModule(data, chunk=4, val_split=None)
    L.seed_everything(0, verbose=False)
    module = _module(data, warmup=4, lr=1e-3)
    before = {k: v.detach().clone() for k, v in module.model.named_parameters()}
    rates, grads = [], {}

    class Record(L.Callback):
        def on_before_optimizer_step(self, trainer, pl_module, optimizer):
            rates.append(optimizer.param_groups[0]["lr"])
            if not grads:
                grads.update({k: v.grad.detach().clone()
                              for k, v in pl_module.model.named_parameters()
                              if v.grad is not None})

    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0, callbacks=[Record()])
    trainer.fit(module, dm)
    moved = [(module.model.get_parameter(k).detach() - before[k])[g.abs() > 1e-4]
             for k, g in grads.items()]
    moved = torch.cat([m.abs() for m in moved])
    assert moved.numel() > 100
    torch.testing.assert_close(moved, torch.full_like(moved, 0.25e-3), rtol=1e-3, atol=0)
    assert trainer.optimizers[0].param_groups[0]["lr"] == 1e-3  # put back after the step
    L.Trainer(max_steps=4, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
              callbacks=[Record()]).fit(_module(data, warmup=4, lr=1e-3), dm)
    assert rates == pytest.approx([0.25e-3, 0.25e-3, 0.5e-3, 0.75e-3, 1e-3])


def test_hood_recipe_arguments(data):
    dims = GarmentDataModule(data, chunk=4).dims
    for kw, name in (({"rollout": 0}, "rollout"), ({"rollout_noise": -0.1}, "rollout_noise"),
                     ({"rollout_ramp": -1}, "rollout_ramp"), ({"warmup": -1}, "warmup"),
                     ({"warmup": 2.5}, "warmup")):
        with pytest.raises(ValueError, match=name):  # the module's check, or the parser's
            _module(data, **kw)
    with pytest.raises(ValueError, match="`rollout`"):
        BaselineModule(DAStyle(dims["num_joints"]), rollout=5)
