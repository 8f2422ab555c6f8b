"""Lightning training of GarTrans on a tiny generated dataset (no simulator: the
"simulation" is the garment skinned by LBS plus a small smooth offset)."""
import inspect
import math

import lightning as L
import pytest
import torch

from garmentgnn.geometry import signed_distance
from garmentgnn.losses.gartrans_loss import NonFiniteLossError
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (PHASE_TERMS, REST_BRANCH, GarmentDataModule, EpochShuffleSampler,
                                 GarTransModule, ProgressiveSchedule)
from garmentgnn.training.evaluate import evaluate_split
from garmentgnn.models import GarTrans

from conftest import skirt_dataset


NY = 8



@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("chunks"), ["walk", "run"], 8,
                         held_out={"val": ["run"]})


def make(root, **kw):
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=NY, num_landmarks=16, seed=0)
    L.seed_everything(0, workers=True)
    model_args = inspect.signature(GarTrans.__init__).parameters
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans),
                                     **{k: v for k, v in kw.items() if k in model_args}),
                            **{k: v for k, v in kw.items() if k not in model_args})
    return dm, module


#: the paper's schedule (no extra terms, one window and threshold) with one-epoch windows
#: and a threshold every epoch passes: a phase change at the end of every second epoch
FAST = {"window": 1, "threshold": 10.0, "window2": None, "threshold2": None,
        "extra_terms": [], "extra_from": 3}


def schedule_of(tr):
    """The module's own schedule in trainer ``tr`` (``GarTransModule.configure_callbacks``)."""
    sched = ProgressiveSchedule.of(tr)
    assert sched is not None
    return sched


def trainer(max_epochs, callbacks=(), **kw):
    return L.Trainer(max_epochs=max_epochs, accelerator="cpu", devices=1, logger=False,
                     enable_checkpointing=False, enable_progress_bar=False,
                     enable_model_summary=False, callbacks=list(callbacks),
                     deterministic=True, **kw)


def test_chunks_shapes_and_static_cache(root):
    ds = SequenceChunks(root, "train", chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)
    assert len(ds) == 2  # 8 frames / 4
    a, b = ds[0], ds[1]
    B, V, S = 4, a["rest_pos"].shape[0], a["rest_joints"].shape[0]
    assert a["rotations"].shape == (B, 3, S, 3) and a["translation"].shape == (B, 3, 3)
    assert a["gt"].shape == (B, V, 3) and a["body_pos"].shape[0] == B
    assert a["nystrom"].shape == (V, NY) and a["mass"].shape == (V,) and a["mass"].min() > 0
    assert a["body_joint_dists"].shape == (a["body_pos"].shape[1], S)
    # frame 0's history repeats frame 0; frame 5's is frames 3, 4, 5
    torch.testing.assert_close(a["rotations"][0, 0], a["rotations"][0, 2])
    torch.testing.assert_close(b["rotations"][1, :2], torch.stack([a["rotations"][3, 2],
                                                                   b["rotations"][0, 2]]))
    assert ds.num_static_builds == 1 and ds.num_file_loads == 1  # cached per sequence
    assert b["nystrom"] is a["nystrom"]


def test_the_static_cache_holds_every_sequence_of_the_split_by_default(root):
    """Shuffled windows over all sequences build each sequence's static inputs once with
    the default cache (the split's size); a cache of one rebuilds them on every switch."""
    ds = SequenceChunks(root, None, chunk=2, stride=1, history=2, nystrom_dim=NY,
                        num_landmarks=16)
    seqs = len(ds.records)
    assert seqs >= 2 and ds.static_cache == seqs
    order = torch.randperm(len(ds), generator=torch.Generator().manual_seed(0)).tolist()
    for i in order + order:
        ds[i]
    assert ds.num_static_builds == seqs
    one = SequenceChunks(root, None, chunk=2, stride=1, history=2, nystrom_dim=NY,
                         num_landmarks=16, static_cache=1)
    switches = sum(ds.index[a][0] != ds.index[b][0] for a, b in zip(order, order[1:])) + 1
    for i in order:
        one[i]
    assert one.num_static_builds == switches > seqs
    assert len(SequenceChunks(root, "val", chunk=4, history=2, nystrom_dim=NY)) == 2


def test_training_reduces_loss(root):
    dm, module = make(root)
    batch = dm.train_set[0]
    module.eval()
    with torch.no_grad():
        before = float(module.compute_loss(batch, module(batch))[0])
    module.train()
    tr = trainer(2, limit_val_batches=1)
    tr.fit(module, dm)
    module.eval()
    with torch.no_grad():
        after = float(module.compute_loss(batch, module(batch))[0])
    assert math.isfinite(after) and after < before
    m = tr.callback_metrics
    for k in ("train/vert", "train/edge", "train/norm", "val/E_dist", "val/collision"):
        assert k in m and math.isfinite(float(m[k])), k
    assert isinstance(tr.optimizers[0], torch.optim.Adamax)
    assert tr.optimizers[0].defaults["lr"] == pytest.approx(3e-3)
    assert isinstance(tr.lr_scheduler_configs[0].scheduler,
                      torch.optim.lr_scheduler.CosineAnnealingLR)


def test_schedule_passes_all_three_phases(root):
    dm, module = make(root, schedule=FAST)
    seen = {}

    class Record(L.Callback):
        def on_train_epoch_end(self, trainer, pl_module):  # runs before the schedule's
            seen[trainer.current_epoch] = (schedule_of(trainer).phase,
                                           set(pl_module.loss_fn.enabled),
                                           pl_module.loss_fn.supervised_scale,
                                           set(trainer.callback_metrics))

    tr = trainer(5, callbacks=[Record()], limit_train_batches=1, limit_val_batches=0)
    tr.fit(module, dm)
    sched = schedule_of(tr)
    phases = [seen[e][0] for e in range(5)]
    assert phases == [1, 1, 2, 2, 3]
    assert sched.transitions == {2: 1, 3: 3}
    assert seen[0][1] == {"vert", "edge", "norm"} and seen[0][2] == 1.0
    assert seen[2][1] == {"vert", "edge", "norm", "collision", "gravity"}
    assert seen[2][2] == pytest.approx(0.05)
    assert seen[4][1] == set(PHASE_TERMS[3]) and "train/stretch" in seen[4][3]
    assert "train/shear" in seen[4][3] and "train/collision" in seen[2][3]
    for name in REST_BRANCH:
        assert all(not p.requires_grad for p in getattr(module.model, name).parameters())
    fresh = GarTrans(**dm.model_sizes(GarTrans)).dynamic  # (its dead last edge output is frozen)
    assert ([p.requires_grad for p in module.model.dynamic.parameters()]
            == [p.requires_grad for p in fresh.parameters()])
    assert sum(p.requires_grad for p in fresh.parameters()) > 0
    assert sched.state_dict()["phase"] == 3


def test_schedule_extra_terms_join_from_their_phase(root):
    dm, module = make(root, loss_weights={"bending": 0.1},
                      schedule=dict(FAST, extra_terms=["bending"], extra_from=2))
    seen = {}

    class Record(L.Callback):
        def on_train_epoch_end(self, trainer, pl_module):
            seen[trainer.current_epoch] = (set(pl_module.loss_fn.enabled),
                                           set(trainer.callback_metrics))

    trainer(3, callbacks=[Record()], limit_train_batches=1, limit_val_batches=0).fit(module, dm)
    assert "bending" not in seen[0][0] and "train/bending" not in seen[0][1]
    assert seen[2][0] == set(PHASE_TERMS[2]) | {"bending"} and "train/bending" in seen[2][1]
    with pytest.raises(ValueError, match="extra_terms"):
        ProgressiveSchedule(extra_terms=["bend"])
    with pytest.raises(ValueError, match="extra_from"):
        ProgressiveSchedule(extra_terms=["bending"], extra_from=4)


def test_collision_projection_runs_in_training_and_keeps_the_garment_out(root):
    """With ``collision_projection`` the module's prediction (what the losses see) is
    the projected one: no vertex of a training batch closer than eps to the body."""
    dm, module = make(root, collision_projection=0.003)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    with torch.no_grad():
        module.model.gates.fill_(0.5)
        out = module(batch)["final"]
    s = signed_distance(out, batch["body_pos"], batch["body_faces"]).distance
    assert s.min() > 0.003 - 1e-4
    trainer(1, limit_train_batches=1, limit_val_batches=0).fit(module, dm)


@pytest.mark.parametrize("freeze", [True, False])
def test_frozen_rest_branch_does_not_change(root, freeze):
    """Phase 3 freezes the rest-pose branch (the paper); ``freeze_rest=False`` trains it."""
    dm, module = make(root, schedule={"start_phase": 3, "freeze_rest": freeze})
    with torch.no_grad():  # open the lbs_start gates so every branch gets gradient at once
        module.model.gates.fill_(0.5)
    before = [p.detach().clone() for p in module.rest_branch_parameters()]
    dyn = [p.detach().clone() for p in module.model.dynamic.parameters()]
    trainer(1, limit_train_batches=1, limit_val_batches=0).fit(module, dm)
    same = [torch.equal(a, p) for a, p in zip(before, module.rest_branch_parameters())]
    assert all(same) if freeze else not any(same)
    assert any(not torch.equal(a, p) for a, p in zip(dyn, module.model.dynamic.parameters()))


@pytest.mark.slow
def test_checkpoint_resume_is_exact(root, tmp_path):
    kw = {"limit_val_batches": 0}
    # uninterrupted: 4 epochs x 2 chunks, phase changes at the end of epochs 1 and 3
    dm, full = make(root, t_max=4, schedule=FAST)
    t_full = trainer(4, **kw)
    t_full.fit(full, dm)
    s_full = schedule_of(t_full)
    # interrupted after 1 epoch (phase 1, one epoch of history), resumed to 4; the chunk
    # order of epoch 1 differs from epoch 0's, so replaying epoch 0's order would show
    sampler = EpochShuffleSampler(len(dm.train_set), dm.hparams.seed)
    epoch0 = list(sampler)
    sampler.set_epoch(1)
    assert list(sampler) != epoch0
    dm, part = make(root, t_max=4, schedule=FAST)
    t1 = trainer(1, **kw)
    t1.fit(part, dm)
    s1 = schedule_of(t1)
    assert s1.phase == 1 and len(s1.history) == 1
    ckpt = tmp_path / "mid.ckpt"
    t1.save_checkpoint(ckpt)
    dm, resumed = make(root, t_max=4, schedule=FAST)  # fresh weights, overwritten by the ckpt
    t2 = trainer(4, **kw)
    t2.fit(resumed, dm, ckpt_path=str(ckpt))
    s2 = schedule_of(t2)
    assert s2.phase == s_full.phase == 3 and s2.transitions == s_full.transitions
    for (n, a), b in zip(full.named_parameters(), resumed.parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=n)
        assert a.requires_grad == b.requires_grad, n


def test_nan_prediction_stops_training_naming_the_term(root):
    dm, module = make(root)
    inner = module.model.forward

    def poisoned(*a, **k):
        out = dict(inner(*a, **k))
        out["final"] = out["final"].clone()
        out["final"][0, 0, 0] = float("nan")
        return out

    module.model.forward = poisoned
    with pytest.raises(NonFiniteLossError, match="'vert'"):
        trainer(1, limit_val_batches=0).fit(module, dm)


def test_evaluate_split_lbs_matches_the_known_wobble_and_modes_are_finite(root):
    """The toy "simulation" is LBS + 0.003 sin(0.7 t + 8 x), so the LBS mode's E_dist must
    equal the mean wobble amplitude exactly (same skinning weights)."""
    dm, module = make(root)
    res = evaluate_split(module, root, "val", history=2, num_landmarks=16)
    ds = SequenceChunks(root, "val", chunk=100, history=2, nystrom_dim=NY, num_landmarks=16)
    x = ds[0]["rest_pos"][:, 0].double()
    T = ds[0]["gt"].shape[0]
    t = torch.arange(T, dtype=torch.float64).view(T, 1)
    wobble = 0.003 * torch.sin(0.7 * t + 8.0 * x).abs() * 3 ** 0.5  # |(w, w, w)|
    assert res["lbs"]["frames"] == T
    assert res["lbs"]["E_dist"] == pytest.approx(100 * float(wobble.mean()), rel=1e-3)
    for mode in ("gartrans", "gartrans_ar", "lbs"):
        assert set(res[mode]) >= {"E_dist", "E_vnorm", "E_fnorm", "E_len", "E_curv",
                                  "collision", "ms_per_frame"}
        assert all(math.isfinite(v) for v in res[mode].values())
    with pytest.raises(ValueError, match="mode"):
        evaluate_split(module, root, "val", modes=["nope"])
