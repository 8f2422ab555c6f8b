"""The MGN-style learned simulator and its training recipe: body edges against a k-d
tree, invariance to the body's rigid motion (analytic), a batch against its garments
alone, the integration and pinning, a gradient in every branch for every layer, the
noise-corrected target, the overfit of one batch, windows of the data module, and the
checks a run makes at set-up."""
import math

import lightning as L
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from garmentgnn.cli import main as cli_main
from garmentgnn.data import SequenceChunks
from garmentgnn.geometry import push_outside
from garmentgnn.geometry.measures import edge_lengths, project_edge_lengths
from garmentgnn.geometry.mesh import unique_edges
from garmentgnn.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from garmentgnn.models import EncodeProcessDecode, MGNStyle
from garmentgnn.models.sequence import STRAIN_CHEBYSHEV
from garmentgnn.models.baselines import DAStyle
from garmentgnn.nn import LAYERS
from garmentgnn.physics import MATERIALS, material_features
from garmentgnn.training import BaselineModule, GarmentDataModule, RolloutModule
from garmentgnn.training.recipes import recipes_of_model
from garmentgnn.training.integrity import CheckpointError

from conftest import skirt_dataset

NY = 8


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return skirt_dataset(tmp_path_factory.mktemp("mgn"), ["walk", "run", "jump"], 8,
                         held_out={"val": ["run"]}, name="mgn")


def windows(root, chunk=3):
    return SequenceChunks(root, "train", chunk=chunk, stride=1, drop_last=True, history=1,
                          nystrom_dim=NY, num_landmarks=16)


def trained_stats(model, batch):
    """``model`` with its normalisation statistics taken from ``batch``, in eval mode."""
    module = RolloutModule(model, stats_steps=1, rollout=1)
    module.train()
    with torch.no_grad():
        module.window_loss(batch)
    return model.eval()


def test_windows_start_at_every_frame(root):
    ds = windows(root, chunk=3)
    per_seq = {}
    for i, t0, n in ds.index:
        per_seq.setdefault(i, []).append((t0, n))
    assert all(v == [(t, 3) for t in range(6)] for v in per_seq.values())  # 8 frames: 0..5
    item = ds[4]
    full = SequenceChunks(root, "train", chunk=8, history=1, nystrom_dim=NY, num_landmarks=16)
    torch.testing.assert_close(item.gt, full[0].gt[4:7])
    with pytest.raises(ValueError, match="`stride`"):
        SequenceChunks(root, "train", chunk=3, stride=0)
    dm = GarmentDataModule(root, chunk=3, stride=1, drop_last=True, eval_chunk=100,
                           history=1, nystrom_dim=NY, num_landmarks=16)
    dm.setup("fit")
    assert len(dm.train_set) == 2 * 6
    assert [n for _, _, n in dm.val_set.index] == [8]  # whole sequences, never dropped
    with pytest.raises(ValueError, match="--data.eval_chunk"):
        GarmentDataModule(root, eval_chunk=0)


def test_items_carry_their_fabric(root):
    item = windows(root)[0]
    torch.testing.assert_close(item.material, material_features(MATERIALS["silk"]))
    np.testing.assert_allclose(item.material.numpy(),
                               np.log([23600.0, 8000.0, 3.96e-5, 0.20022]), rtol=1e-6)
    batch = windows(root)[[0, 7]]
    assert batch.material.shape == (2, 4)
    with pytest.raises(ValueError, match="`fabric`"):
        material_features({"stretch": 1.0, "shear": -1.0, "bending": 1.0, "density": 1.0})


def test_body_edges_are_the_nearest_body_vertices_within_the_radius(root):
    model = MGNStyle(hidden=8, layers=1, heads=1, body_radius=0.08, body_k=3)
    batch = windows(root)[[1, 9]]
    motion = model.scene_motion(batch)
    x = batch.gt[1]
    src, dst = model.body_edges(motion, x, 2)
    body = motion.body[2]  # [N, Vb, 3]
    Vb = body.shape[1]
    want = set()
    for n in range(2):
        verts = (motion.vertex_chunk == n).nonzero().flatten()
        d, j = cKDTree(body[n].numpy()).query(x[verts].numpy(), k=3)
        for v, dd, jj in zip(verts.tolist(), d, j):
            want |= {(v, n * Vb + int(b)) for b, e in zip(jj, dd) if e < 0.08}
    assert set(zip(src.tolist(), dst.tolist())) == want
    assert len(want) > 0


def _rigid(batch, Q, shift):
    """``batch`` with the world rotated by ``Q`` and shifted by ``shift``: the root's
    rotation and translation changed so that every posed point p becomes Q p + shift."""
    out = batch.clone()
    rot = batch.rotations.clone()  # [B, H, S, 3]
    R0 = axis_angle_to_matrix(rot[..., 0, :].double())
    rot[..., 0, :] = matrix_to_axis_angle(Q.double() @ R0).float()
    j0 = batch.rest_joints[0]
    # posed root position j0 + t  ->  Q (j0 + t) + shift
    out.translation = ((j0 + batch.translation) @ Q.T + shift - j0)
    out.rotations = rot
    out.body_pos = batch.body_pos @ Q.T + shift
    out.gt = batch.gt @ Q.T + shift
    return out


def test_the_acceleration_turns_and_moves_with_the_body(root):
    torch.manual_seed(0)
    batch = windows(root)[3]
    model = trained_stats(MGNStyle(hidden=16, layers=2, heads=2, body_radius=0.1), batch)
    Q = axis_angle_to_matrix(torch.tensor([0.3, -1.1, 0.7]))
    moved = _rigid(batch, Q, torch.tensor([0.4, -0.2, 1.5]))
    with torch.no_grad():
        m0, m1 = model.scene_motion(batch), model.scene_motion(moved)
        torch.testing.assert_close(m1.lbs, m0.lbs @ Q.T + torch.tensor([0.4, -0.2, 1.5]),
                                   atol=1e-5, rtol=0)
        out0 = model(batch, m0, 2, batch.gt[0], batch.gt[1])
        out1 = model(moved, m1, 2, moved.gt[0], moved.gt[1])
        torch.testing.assert_close(out1, out0, atol=2e-4, rtol=1e-4)  # local-frame output
        a0, a1 = model.acceleration(out0, m0, 2), model.acceleration(out1, m1, 2)
        torch.testing.assert_close(a1, a0 @ Q.T, atol=1e-6, rtol=1e-4)


def test_a_batch_is_its_garments_alone(root):
    ds = windows(root)
    batch = ds[[2, 8]]
    model = trained_stats(MGNStyle(hidden=16, layers=2, heads=2), batch)
    with torch.no_grad():
        mb = model.scene_motion(batch)
        both = model.step(batch, mb, 2, batch.gt[0], batch.gt[1])
        alone = []
        for i in (2, 8):
            item = ds[i]
            m = model.scene_motion(item)
            alone.append(model.step(item, m, 2, item.gt[0], item.gt[1]))
    torch.testing.assert_close(both, torch.cat(alone), atol=1e-5, rtol=1e-5)


def test_a_step_integrates_the_acceleration_and_pins_to_lbs(root):
    batch = windows(root)[5]
    pinned = torch.zeros(batch.num_vertices, dtype=torch.bool)
    pinned[:20] = True
    batch.pinned = pinned
    model = trained_stats(MGNStyle(hidden=16, layers=2, heads=2), batch)
    with torch.no_grad():
        m = model.scene_motion(batch)
        xp, xc = batch.gt[0], batch.gt[1]
        a = model.acceleration(model(batch, m, 2, xp, xc), m, 2)
        nxt = model.step(batch, m, 2, xp, xc)
        free = 2 * xc - xp + a  # the update equation; the step projects it (tested below)
        free[:20] = m.lbs[2, :20]
        projected = model.project(batch, m, 2, free)
    torch.testing.assert_close(nxt, projected)
    torch.testing.assert_close(nxt[:20], m.lbs[2, :20])
    model.strain_limit, model.inextensible, model.collision_projection = 0, 0, None  # none
    with torch.no_grad():
        nxt = model.step(batch, m, 2, xp, xc)
    torch.testing.assert_close(nxt[20:], (2 * xc - xp + a)[20:])
    torch.testing.assert_close(nxt[:20], m.lbs[2, :20])
    full = SequenceChunks(root, "train", chunk=8, history=1, nystrom_dim=NY,
                          num_landmarks=16)[1]
    with torch.no_grad():
        roll = model.rollout(full, full.gt[0], full.gt[1])
    assert roll.shape == full.gt.shape and torch.equal(roll[:2], full.gt[:2])
    assert torch.isfinite(roll).all()


def test_bf16_autocast_keeps_inputs_and_integration_in_float32(root):
    """Under ``torch.autocast(bfloat16)`` (``--trainer.precision bf16-mixed``) the
    kinematics and the inputs the encoders read are float32's bit for bit (bfloat16
    positions are ~4 mm off at 1 m, the size of the features), and the step, the loss and
    its gradient stay within the bfloat16 networks' round-off.  Oracle: the same model
    and batch in float32."""
    batch = windows(root)[5]
    model = trained_stats(MGNStyle(hidden=16, layers=2, heads=2), batch)
    seen = {}
    hooks = [getattr(model, n).register_forward_pre_hook(
        lambda mod, args, n=n: seen.setdefault(n, []).append(args[0]))
        for n in ("node_norm", "edge_norm", "body_norm")]
    module = RolloutModule(model, stats_steps=0, rollout=1)

    def run():
        with torch.no_grad():
            m = model.scene_motion(batch)
            nxt = model.step(batch, m, 2, batch.gt[0], batch.gt[1])
        torch.manual_seed(0)  # the same input noise
        loss, _ = module.window_loss(batch)
        grad = torch.autograd.grad(loss, model.network.decoder[-1].weight)[0]
        return m, nxt, loss, grad

    m32, ref, loss32, grad32 = run()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        m16, got, loss16, grad16 = run()
    for h in hooks:
        h.remove()
    for name, runs in seen.items():  # the step's call and the loss's, in each precision
        assert len(runs) == 4 and all(r.dtype == torch.float32 for r in runs), name
        assert torch.equal(runs[0], runs[2]) and torch.equal(runs[1], runs[3]), name
    assert torch.equal(m16.lbs, m32.lbs) and torch.equal(m16.frame, m32.frame)
    accel = ref - (2 * batch.gt[1] - batch.gt[0])
    assert got.dtype == torch.float32
    assert (got - ref).abs().max() <= 0.05 * accel.abs().max()
    assert loss16.dtype == torch.float32
    assert abs(loss16.item() - loss32.item()) <= 0.02 * loss32.item()
    assert (grad16.float() - grad32).norm() <= 0.05 * grad32.norm()


@pytest.mark.parametrize("layer,body_blocks", [(name, False) for name in sorted(LAYERS)]
                         + [("sat", True)])
def test_every_parameter_learns_with_every_layer(root, layer, body_blocks):
    torch.manual_seed(0)
    batch = windows(root)[[0, 6]]
    model = MGNStyle(hidden=16, layers=2, heads=2, layer=layer, body_radius=0.2,
                     body_blocks=body_blocks)
    module = RolloutModule(model, stats_steps=0, noise=1e-3, rollout=1)
    loss, _ = module.window_loss(batch)
    loss.backward()
    dead = [n for n, p in model.named_parameters()
            if p.requires_grad and (p.grad is None or not p.grad.abs().sum() > 0)]
    frozen = [n for n, p in model.named_parameters() if not p.requires_grad]
    assert all(n.startswith("network.convs.1.") for n in frozen)  # the last edge output
    if layer in ("gat", "gt"):  # layers that do not read the edges: the edge encoder is idle
        dead = [n for n in dead if not n.startswith("network.edge_enc")]
    assert not dead
    assert any(n.startswith("network.contact_updates.") for n, _ in model.named_parameters()) \
        == body_blocks


@pytest.mark.parametrize("layer", sorted(LAYERS))
def test_the_frozen_edge_output_is_what_gets_no_gradient(layer):
    """The parameters a layer declares as its edge output's (frozen in the network's last
    block, with no backward pass at construction) are exactly those that autograd leaves
    without a gradient when every parameter is trainable."""
    torch.manual_seed(0)
    net = EncodeProcessDecode(5, 4, 3, hidden=8, layers=2, heads=2, layer=layer)
    frozen = {n for n, p in net.named_parameters() if not p.requires_grad}
    for p in net.parameters():
        p.requires_grad_(True)
    ei = torch.tensor([[0, 1, 2, 1, 3], [1, 2, 0, 0, 2]])
    net(torch.randn(4, 5), ei, torch.randn(5, 4)).square().sum().backward()
    no_grad = {n for n, p in net.named_parameters() if p.grad is None
               and not (layer in ("gat", "gt") and n.startswith("edge_enc"))}  # edges unread
    assert frozen == no_grad
    if layer in ("sat", "gt_edge"):
        assert frozen


def test_the_target_keeps_its_share_of_the_noise(root):
    batch = windows(root)[[1, 7]]
    model = MGNStyle(hidden=8, layers=1, heads=1, norm_updates=1)
    trained_stats(model, batch)  # then frozen: the oracle below sees the same statistics
    for gamma in (0.0, 0.1):
        module = RolloutModule(model, stats_steps=0, noise=0.01, noise_gamma=gamma,
                                 rollout=1)
        module.train()
        torch.manual_seed(3)
        loss, _ = module.window_loss(batch)
        # the oracle: the same noise drawn again, the target written out
        m = model.scene_motion(batch)
        torch.manual_seed(3)
        free = ~batch.pinned_mask()
        n = 0.01 * torch.randn_like(batch.gt[1]) * free.unsqueeze(1)
        xc = batch.gt[1] + n
        want_pos = batch.gt[2] + (1 - gamma) * n
        with torch.no_grad():
            out = model(batch, m, 2, batch.gt[0], xc)
            a = model.acceleration(out, m, 2)
            # the target as positions: 2 x + a_target - x_prev
            R = m.frame[1]
            mean, std = model.target_norm.mean_std()
            a_want = want_pos - 2 * xc + batch.gt[0]
            tgt = ((a_want.unsqueeze(-2) @ R).squeeze(-2) - mean.float()) / std.float()
            expected = ((out - tgt) ** 2).sum(1)[free].mean()
        assert float(loss) == pytest.approx(float(expected), rel=1e-4)
        assert a.shape == n.shape


def test_one_batch_is_learnt(root):
    torch.manual_seed(0)
    batch = windows(root)[[0, 4, 8]]
    model = MGNStyle(hidden=32, layers=2, heads=2)
    module = RolloutModule(model, stats_steps=1, noise=0.0, rollout=1)
    module.train()
    with torch.no_grad():
        module.window_loss(batch)
    opt = torch.optim.Adam(module.parameters(), 3e-3)
    first = None
    for _ in range(120):
        loss, extra = module.window_loss(batch)
        first = first if first is not None else float(extra["one_step_m"])
        opt.zero_grad()
        loss.backward()
        opt.step()
    _, extra = module.window_loss(batch)
    assert float(extra["one_step_m"]) < first / 5


def test_the_learning_rate_decays_exponentially(root):
    module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1), lr=1e-3, decay=0.1,
                             decay_steps=100, lr_min=2e-5)
    cfg = module.configure_optimizers()
    opt, sched = cfg["optimizer"], cfg["lr_scheduler"]["scheduler"]
    rates = []
    for _ in range(251):
        rates.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert rates[0] == pytest.approx(1e-3)
    assert rates[50] == pytest.approx(1e-3 * 0.1 ** 0.5)
    assert rates[100] == pytest.approx(1e-4)
    assert rates[250] == pytest.approx(2e-5)  # the floor


def test_the_learning_rate_decays_over_the_runs_steps_unless_told(root):
    """``decay_steps`` unset: the rate falls by ``decay`` over the trainer's max_steps;
    without max_steps it stays (a TimeBudget anneals it), with a warning otherwise."""
    import lightning as L  # noqa: PLC0415
    from garmentgnn.training import TimeBudget  # noqa: PLC0415
    for max_steps, callbacks, want in ((400, [], 1e-4), (-1, [TimeBudget(60.0)], 1e-3)):
        module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1), lr=1e-3, decay=0.1)
        module.trainer = L.Trainer(max_steps=max_steps, callbacks=callbacks, logger=False,
                                   enable_checkpointing=False, enable_progress_bar=False)
        cfg = module.configure_optimizers()
        opt, sched = cfg["optimizer"], cfg["lr_scheduler"]["scheduler"]
        for _ in range(400):
            opt.step()
            sched.step()
        assert opt.param_groups[0]["lr"] == pytest.approx(want)
    module.trainer = L.Trainer(max_steps=-1, logger=False, enable_checkpointing=False)
    with pytest.warns(UserWarning, match="no --trainer.max_steps"):
        module.configure_optimizers()


def test_bad_arguments_and_inputs(root):
    for kw, name in (({"hidden": 10, "heads": 4}, "`heads`"), ({"layer": "nope"}, "`layer`"),
                     ({"body_radius": 0.0}, "`body_radius`"), ({"fps": -1.0}, "`fps`")):
        with pytest.raises(ValueError, match=name):
            MGNStyle(**kw)
    for bad in (-1, True, 2.0):
        with pytest.raises(ValueError, match="`inextensible`"):
            MGNStyle(inextensible=bad)
    model = MGNStyle(hidden=8, layers=1, heads=1)
    for kw, name in (({"rollout": 0}, "`rollout`"), ({"noise": -1.0}, "`noise`"),
                     ({"start": "x"}, "`start`"), ({"noise_gamma": 2.0}, "`noise_gamma`"),
                     ({"stats_steps": 10 ** 6}, "`stats_steps`")):
        with pytest.raises(ValueError, match=name):
            RolloutModule(model, **kw)
    with pytest.raises(TypeError, match="`model`"):
        RolloutModule(torch.nn.Linear(2, 2))
    item = windows(root)[0]
    short = item.select(torch.tensor([0, 1]))
    module = RolloutModule(model)
    with pytest.raises(ValueError, match="at least 3 frames"):
        module.rollout(short)
    bare = item.clone()
    del bare.material
    with pytest.raises(ValueError, match="`scene.material`"):
        model.scene_motion(bare)
    with pytest.raises(ValueError, match=r"2 \+ the longest rollout = 3 frames, got 4"):
        RolloutModule(model, rollout=1).window_loss(windows(root, chunk=4)[0])


def _trainer(tmp_path, steps):
    return L.Trainer(max_steps=steps, accelerator="cpu", logger=False,
                     enable_progress_bar=False, enable_model_summary=False,
                     default_root_dir=str(tmp_path), limit_val_batches=1,
                     val_check_interval=steps, check_val_every_n_epoch=None)


def test_set_up_refuses_other_windows_and_frame_rates(root, tmp_path):
    dm = GarmentDataModule(root, chunk=4, stride=1, drop_last=True, eval_chunk=100,
                           history=1, nystrom_dim=NY, num_landmarks=16)
    module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1), stats_steps=0, rollout=1)
    with pytest.raises(ValueError, match="--data.chunk 3"):
        _trainer(tmp_path, 2).fit(module, dm)
    dm = GarmentDataModule(root, chunk=3, stride=1, drop_last=True, eval_chunk=100,
                           history=1, nystrom_dim=NY, num_landmarks=16)
    module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1, fps=60.0), stats_steps=0,
                             rollout=1)
    with pytest.raises(ValueError, match="at 30 fps.*60 fps"):
        _trainer(tmp_path, 2).fit(module, dm)


def test_fit_checkpoint_and_rollout_scores(root, tmp_path):
    L.seed_everything(0)
    dm = GarmentDataModule(root, chunk=3, stride=1, drop_last=True, eval_chunk=100,
                           history=1, nystrom_dim=NY, num_landmarks=16, batch_size=4)
    module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1), stats_steps=1, rollout=1)
    trainer = _trainer(tmp_path, 2)  # optimizer steps: the statistics batch is not one
    trainer.fit(module, dm)
    path = tmp_path / "m.ckpt"
    trainer.save_checkpoint(path)
    back = RolloutModule.load_from_checkpoint(str(path)).eval()
    assert int(back.model.target_norm.updates) == 3  # the statistics travel with it
    assert torch.equal(back.model.node_norm.total, module.model.node_norm.total)
    val = dm.val_set[0]
    with torch.no_grad():
        a, b = module.eval().rollout(val), back.rollout(val)
    torch.testing.assert_close(a, b)
    assert math.isfinite(float(trainer.callback_metrics["val/E_dist"]))
    other = BaselineModule(DAStyle(num_joints=val.num_joints))
    with pytest.raises(CheckpointError, match="MGNStyle"):
        other.on_load_checkpoint(torch.load(path, weights_only=False))


def test_pushforward_trains_from_its_own_state(root):
    batch = windows(root, chunk=4)[[0, 5]]
    model = MGNStyle(hidden=8, layers=1, heads=1, norm_updates=1)
    module = RolloutModule(model, stats_steps=0, noise=0.0, rollout=2, rollout_start=0)
    module.train()
    with torch.no_grad():
        module.window_loss(batch)  # the statistics, then frozen
        loss, _ = module.window_loss(batch)
        m = model.scene_motion(batch)
        x2 = model.step(batch, m, 2, batch.gt[0], batch.gt[1])  # its own frame 2
        out = model(batch, m, 3, batch.gt[1], x2)
        want = model.normalized_target(batch.gt[3] - 2 * x2 + batch.gt[1], m, 3)
        free = ~batch.pinned_mask()
        assert float(loss) == pytest.approx(float(((out - want) ** 2).sum(1)[free].mean()),
                                            rel=1e-5)
        # before `rollout_start`: one step on the window's last three frames
        one = RolloutModule(model, stats_steps=0, noise=0.0, rollout=2, rollout_start=10)
        last3 = batch.select(torch.arange(1, 4))
        m3 = model.scene_motion(last3)
        out = model(last3, m3, 2, last3.gt[0], last3.gt[1])
        want = model.normalized_target(last3.gt[2] - 2 * last3.gt[1] + last3.gt[0], m3, 2)
        assert float(one.window_loss(batch)[0]) == pytest.approx(
            float(((out - want) ** 2).sum(1)[free].mean()), rel=1e-5)


def test_the_packaged_configs_name_the_model_they_train():
    assert recipes_of_model("garmentgnn.models.MGNStyle") == ["mgn"]
    assert recipes_of_model("x.GarTrans") == ["gartrans"]
    assert recipes_of_model("DAStyle") == ["baselines/da"]
    assert recipes_of_model("Nothing") == []


def _cli_args(root, tmp_path):
    return ["--data.root", str(root), "--data.nystrom_dim", str(NY), "--data.num_landmarks",
            "16", "--data.batch_size", "2", "--trainer.max_steps", "2",
            "--trainer.limit_val_batches", "1", "--trainer.enable_progress_bar", "false",
            "--trainer.default_root_dir", str(tmp_path),
            "--trainer.logger.init_args.save_dir", str(tmp_path)]


def _one_error_line(capsys, argv):
    capsys.readouterr()
    rc = cli_main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:"), err
    return err[0]


def test_the_command_line_refuses_what_the_model_cannot_run(root, tmp_path, capsys):
    """One ``error:`` line each: a motion at another frame rate than the model learned
    at, a checkpoint of another method, sequences shorter than a rollout needs."""
    args = ["train", "fit", "--config", "mgn"] + _cli_args(root, tmp_path / "a")
    line = _one_error_line(capsys, args + ["--model.model.init_args.fps", "60"])
    assert "--data.root" in line and "30 fps" in line and "60 fps" in line
    assert not (tmp_path / "a" / "logs").exists() or not list((tmp_path / "a").rglob("*.ckpt"))
    # a DA-style checkpoint given to the MGN-style configuration
    dm = GarmentDataModule(root, chunk=4, history=3, nystrom_dim=NY, num_landmarks=16)
    da = BaselineModule(DAStyle(num_joints=dm.dims["num_joints"]))
    trainer = L.Trainer(max_steps=1, accelerator="cpu", logger=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, default_root_dir=str(tmp_path / "da"))
    trainer.fit(da, dm)
    trainer.save_checkpoint(tmp_path / "da.ckpt")
    line = _one_error_line(capsys, ["train", "test", "--config", "mgn", "--ckpt_path",
                                    str(tmp_path / "da.ckpt")] + _cli_args(root, tmp_path / "b"))
    assert "a checkpoint of DAStyle, not of MGNStyle; give --config baselines/da" in line
    # two-frame sequences: nothing to roll out from
    short = skirt_dataset(tmp_path / "short", ["walk"], 2, held_out={"val": []}, name="s")
    line = _one_error_line(capsys, ["train", "fit", "--config", "mgn", "--data.drop_last",
                                    "false"] + _cli_args(short, tmp_path / "c")
                           + ["--data.batch_size", "1", "--data.val_split", "null"])
    assert "2 + the longest rollout = 5 frames, got 2" in line and "--data.chunk 5" in line


def test_the_anchor_bounds_the_offset_and_the_target_inverts_it(root):
    """``integrate`` against its analytic form (the free update, its offset from LBS
    decayed and clipped; pinned vertices on LBS), and ``target_acceleration`` as its
    inverse."""
    torch.manual_seed(0)
    batch = windows(root)[[0, 6]]
    x0, x1 = batch.gt[0], batch.gt[1]
    for decay, clip in ((0.0, None), (0.2, None), (0.2, 0.01)):
        model = MGNStyle(hidden=8, layers=1, heads=1, anchor_decay=decay, anchor_clip=clip)
        m = model.scene_motion(batch)
        a = 1e-2 * torch.randn_like(x1)
        x = model.integrate(m, 2, x0, x1, a)
        lbs, free = m.lbs[2], ~m.pinned
        want = lbs + (1 - decay) * (2 * x1 - x0 + a - lbs)
        if clip is not None:
            off = want - lbs
            want = lbs + off * (clip / off.norm(dim=1, keepdim=True)).clamp(max=1.0)
            assert float((x - lbs).norm(dim=1).max()) <= clip * (1 + 1e-5)
        torch.testing.assert_close(x[free], want[free])
        torch.testing.assert_close(x[~free], lbs[~free])
        assert bool(free.any()) and bool((~free).any())
        if clip is None:
            back = model.target_acceleration(m, 2, x0, x1, x)
            torch.testing.assert_close(back[free], a[free], rtol=0, atol=1e-6)


def test_the_rollout_schedule_and_its_modes():
    model = MGNStyle(hidden=8, layers=1, heads=1)
    m = RolloutModule(model, rollout_schedule=[[0, 1], [10, 2], [20, 5]])
    assert m.window == 7
    assert [m.rollout_at(s) for s in (0, 9, 10, 19, 20, 10 ** 6)] == [1, 1, 2, 2, 5, 5]
    assert m.frames_to_train(25) == (4, 1)  # pushforward: four free frames, one trained
    assert RolloutModule(model, rollout=3, rollout_start=7).schedule == [(0, 1), (7, 3)]
    r = RolloutModule(model, rollout_schedule=[[0, 4]], rollout_mode="random")
    torch.manual_seed(0)
    drawn = [r.frames_to_train(0) for _ in range(60)]
    assert {f for f, _ in drawn} == {0, 1, 2, 3} and all(n == 1 for _, n in drawn)
    torch.manual_seed(0)
    assert [r.frames_to_train(0) for _ in range(60)] == drawn  # the run's seed
    per = RolloutModule(model, rollout_schedule=[[0, 4]], rollout_mode="per_frame")
    assert per.frames_to_train(0) == (0, 4)


class _Steps(L.Callback):
    """Counts training batches and records each optimizer step's gradient norm."""

    def __init__(self):
        self.batches, self.norms = 0, []

    def on_train_batch_end(self, *args):
        self.batches += 1

    def on_before_optimizer_step(self, trainer, module, optimizer):
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        self.norms.append(float(torch.linalg.vector_norm(torch.stack(
            [torch.linalg.vector_norm(g) for g in grads]))))


@pytest.mark.parametrize("mode,frames,steps", [("per_frame", 3, 6), ("pushforward", 3, 2),
                                               ("random", 3, 2)])
def test_each_rollout_mode_steps_the_optimizer_as_documented(root, mode, frames, steps):
    """One statistics batch, then two batches: ``per_frame`` takes an optimizer step after
    each of the rollout's frames, the others one a batch; every step's gradient is
    clipped to ``clip``."""
    torch.manual_seed(0)
    model = MGNStyle(hidden=8, layers=1, heads=1, norm_updates=1)
    module = RolloutModule(model, stats_steps=1, noise=1e-3, clip=1e-3, rollout_mode=mode,
                             rollout_schedule=[[0, frames]])
    dm = GarmentDataModule(root, chunk=2 + frames, stride=1, drop_last=True, history=1,
                           batch_size=2, nystrom_dim=NY, num_landmarks=16)
    count = _Steps()
    trainer = L.Trainer(max_steps=steps, limit_val_batches=0, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, callbacks=[count])
    trainer.fit(module, dm)
    assert trainer.global_step == steps and count.batches == 3
    assert len(count.norms) == steps
    # the norm seen before the step is the clipped one
    assert max(count.norms) <= 1e-3 * (1 + 1e-4)


@pytest.mark.parametrize("inextensible,training,within", [
    (0, False, 0), (8, True, 0), (8, False, 0), (8, True, 5), (0, True, 5), (0, False, 5)])
def test_the_projection_uses_the_strain_limit_and_the_collision_projection(
        root, inextensible, training, within):
    """A step's projection is the toolkit's strain limit (Provot's on stretched edges; in
    eval mode with ``inextensible`` sweeps, or in either mode with ``within`` sweeps of
    ``inextensible_projection``, every edge toward rest with Chebyshev's acceleration),
    then its collision projection against the garment's own body, pinned vertices back
    on LBS (against those functions called directly: a batch of two garments projects
    each against its own body)."""
    torch.manual_seed(0)
    batch = windows(root)[[0, 6]]
    both = bool(within) or (bool(inextensible) and not training)
    sweeps = within or (inextensible if both else 3)
    model = MGNStyle(hidden=8, layers=1, heads=1, strain_limit=3, inextensible=inextensible,
                     collision_projection=0.004).train(training)
    m = model.scene_motion(batch)
    x = batch.gt[2] + 0.01 * torch.randn_like(batch.gt[2])
    with model.inextensible_projection(within):
        got = model.project(batch, m, 2, x)
    assert model.strain_sweeps() == ((inextensible, True) if inextensible and not training
                                     else (3, False))  # restored on leaving
    plain = MGNStyle(hidden=8, layers=1, heads=1, strain_limit=0, inextensible=0,
                     collision_projection=None)
    assert plain.project(batch, plain.scene_motion(batch), 2, x) is x  # off: unchanged
    edges = unique_edges(batch.faces, batch.num_vertices).edges
    want = project_edge_lengths(x, edges, edge_lengths(batch.rest_pos, edges), sweeps,
                                stretch_only=not both,
                                chebyshev=STRAIN_CHEBYSHEV if both else None)
    for n in range(2):  # each garment against its own body
        rows = m.vertex_chunk == n
        body = batch.body_pos[2].view(2, -1, 3)[n]
        faces = items_body_faces(batch, n)
        want[rows] = push_outside(want[rows], body, faces, 0.004)
    want = torch.where(m.pinned.unsqueeze(1), m.lbs[2], want)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    assert not torch.equal(got, x)


@pytest.mark.parametrize("sweeps", [0, 6])
def test_a_training_rollout_projects_as_train_inextensible_says(root, sweeps):
    """``train_inextensible``: the pushforward frames and the trained frame's state are
    projected with the strain limit (0) or with that many inextensible sweeps, against
    the same window rolled by hand with the model in training mode or in eval mode with
    ``inextensible`` as many sweeps (its statistics frozen, so the two modes differ only
    in the projection)."""
    torch.manual_seed(0)
    batch = windows(root, chunk=5)[[0, 6]]
    model = MGNStyle(hidden=8, layers=1, heads=1, norm_updates=1, strain_limit=2,
                     inextensible=6)
    trained_stats(model, windows(root)[[0, 6]])

    def loss_with(n):
        module = RolloutModule(model, stats_steps=1, noise=0.0, rollout=3, rollout_start=0,
                               train_inextensible=n).train()
        return module.window_loss(batch, free_frames=2, trained=1)

    with torch.no_grad():
        loss, extra = loss_with(sweeps)
        m = model.scene_motion(batch)
        model.train(not sweeps)
        x0, x1 = batch.gt[0], batch.gt[1]
        x2 = model.step(batch, m, 2, x0, x1)
        x3 = model.step(batch, m, 3, x1, x2)
        want, _, err = model.loss(batch, m, 4, x2, x3, batch.gt[4], ~m.pinned)
        model.train()
        other, _ = loss_with(6 - sweeps)
    assert float(loss) == pytest.approx(float(want), rel=1e-5)
    assert float(extra["one_step_m"]) == pytest.approx(float(err), rel=1e-5)
    assert float(other) != pytest.approx(float(loss), rel=1e-3)
    assert model.strain_sweeps() == (2, False)  # left as it was
    with pytest.raises(ValueError, match="`train_inextensible`"):
        RolloutModule(model, stats_steps=1, train_inextensible=-1)


def test_training_windows_start_from_the_lbs_garment_as_lbs_start_says(root):
    """``lbs_start``: the share of training windows rolled out from the LBS garment of
    their first two frames, drawn per window; against the same two windows rolled by hand
    from each combination of starts."""
    batch = windows(root, chunk=5)[[0, 6]]
    model = trained_stats(MGNStyle(hidden=8, layers=1, heads=1, norm_updates=1),
                          windows(root)[[0, 6]]).eval()
    m = model.scene_motion(batch)
    per_window = m.vertex_chunk.unsqueeze(1)

    def by_hand(from_lbs):  # from_lbs[k]: window k starts from the LBS garment
        pick = torch.tensor(from_lbs)[per_window]
        x0 = torch.where(pick, m.lbs[0], batch.gt[0])
        x1 = torch.where(pick, m.lbs[1], batch.gt[1])
        x2 = model.step(batch, m, 2, x0, x1)
        x3 = model.step(batch, m, 3, x1, x2)
        return float(model.loss(batch, m, 4, x2, x3, batch.gt[4], ~m.pinned)[0])

    def loss_with(share, seed=0):
        torch.manual_seed(seed)
        module = RolloutModule(model, stats_steps=1, noise=0.0, rollout=3, rollout_start=0,
                               lbs_start=share)
        return float(module.window_loss(batch, free_frames=2, trained=1)[0])

    with torch.no_grad():
        combos = {c: by_hand(c) for c in [(False, False), (True, False), (False, True),
                                          (True, True)]}
        assert loss_with(0.0) == pytest.approx(combos[False, False], rel=1e-5)
        assert loss_with(1.0) == pytest.approx(combos[True, True], rel=1e-5)
        assert combos[True, True] != pytest.approx(combos[False, False], rel=1e-3)
        seen = set()
        for seed in range(24):
            got = loss_with(0.5, seed)
            match = [c for c, v in combos.items() if got == pytest.approx(v, rel=1e-5)]
            assert len(match) == 1
            seen.add(match[0])
    assert (True, False) in seen and (False, True) in seen  # drawn per window
    for bad in (-0.1, 1.5, True, "half"):
        with pytest.raises(ValueError, match="`lbs_start`"):
            RolloutModule(model, stats_steps=1, lbs_start=bad)


def items_body_faces(batch, n):
    """Garment ``n``'s body faces in its own body's vertex numbering."""
    faces = batch.body_faces
    Vb = batch.body_pos.shape[1] // batch.num_chunks
    per = faces.shape[0] // batch.num_chunks
    return faces[n * per:(n + 1) * per] - n * Vb


def test_the_preroll_start_settles_on_the_first_pose_then_follows_the_motion(root):
    """``start="preroll"``: the LBS garment of frame 0 held still, ``preroll_frames``
    steps with the body held at frame 0, then the motion; against the model's steps
    called by hand (no ground truth read)."""
    torch.manual_seed(0)
    item = SequenceChunks(root, "val", chunk=8, history=1, nystrom_dim=NY,
                          num_landmarks=16)[0]
    model = trained_stats(MGNStyle(hidden=8, layers=1, heads=1), windows(root)[[0, 6]])
    module = RolloutModule(model, preroll_frames=3).eval()
    bare = item.clone()
    del bare.gt
    with torch.no_grad():
        got = module.rollout(bare, start="preroll")
        assert got.shape == item.gt.shape
        held = item.select(torch.zeros(4, dtype=torch.long))
        m0 = model.scene_motion(held)
        l0 = m0.lbs[0]
        a = model.step(held, m0, 2, l0, l0)
        b = model.step(held, m0, 3, l0, a)
        torch.testing.assert_close(got[0], b)
        zero = RolloutModule(model, preroll_frames=0).eval()
        m = model.scene_motion(item)
        torch.testing.assert_close(zero.rollout(bare, start="preroll"),
                                   model.rollout(item, m.lbs[0], m.lbs[0], m))


def test_a_rollout_starts_from_the_frames_it_is_given(root):
    """``start`` as the garment ``[2, V, 3]`` of frames 0 and 1 (another method's
    prediction): the rollout of the named start whose frames they are; a garment of
    another size, or not finite, is refused naming ``start``."""
    torch.manual_seed(0)
    item = SequenceChunks(root, "val", chunk=6, history=1, nystrom_dim=NY,
                          num_landmarks=16)[0]
    model = trained_stats(MGNStyle(hidden=8, layers=1, heads=1), windows(root)[[0, 6]])
    module = RolloutModule(model).eval()
    bare = item.clone()
    del bare.gt
    with torch.no_grad():
        lbs = model.scene_motion(item).lbs
        torch.testing.assert_close(module.rollout(bare, start=item.gt[:2].clone()),
                                   module.rollout(item, start="gt"), rtol=0, atol=0)
        torch.testing.assert_close(module.rollout(bare, start=lbs[:3].double()),
                                   module.rollout(bare, start="lbs"), rtol=0, atol=0)
        assert not torch.equal(module.rollout(bare, start=lbs[:2]),
                               module.rollout(item, start="gt"))
        with pytest.raises(ValueError, match=r"`start`: .* must be \[2, \d+, 3\]"):
            module.rollout(bare, start=lbs[:2, :-1])
        bad = lbs[:2].clone()
        bad[1, 0, 0] = float("nan")
        with pytest.raises(ValueError, match="`start`: .* not finite"):
            module.rollout(bare, start=bad)
