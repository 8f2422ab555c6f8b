"""``garmentgnn train`` (LightningCLI + configs/) and DDP on 2 CPU processes (gloo)."""
from pathlib import Path

import lightning as L
import pytest
import torch

from garmentgnn.cli import main as cli_main
from garmentgnn.training import GarmentDataModule, GarTransModule, ProgressiveSchedule
from garmentgnn.training.lightning_cli import main as train_main
from test_training import NY, root  # noqa: F401  (the module-scoped toy dataset fixture)

CONFIGS = Path(__file__).resolve().parents[1] / "src" / "garmentgnn" / "configs"
VARIANTS = sorted(p.name for p in (CONFIGS / "ablations").glob("*.yaml"))


def fast_args(data_root, tmp_path):
    return ["--data.root", str(data_root), "--data.chunk", "4", "--data.history", "2",
            "--data.nystrom_dim", str(NY), "--data.num_landmarks", "16",
            "--trainer.max_epochs", "1", "--trainer.limit_train_batches", "2",
            "--trainer.limit_val_batches", "1", "--trainer.enable_progress_bar", "false",
            "--trainer.default_root_dir", str(tmp_path),
            "--trainer.logger.init_args.save_dir", str(tmp_path)]


def test_variants_cover_table1():
    assert VARIANTS == ["gat.yaml", "structure_aware.yaml", "wo_edge.yaml", "wo_gating.yaml",
                        "wo_unsup.yaml"]


@pytest.mark.parametrize("variant", [None] + VARIANTS)
def test_config_builds_the_variant(root, tmp_path, variant):  # noqa: F811
    args = ["--config", str(CONFIGS / "gartrans.yaml")]
    if variant:
        args += ["--config", str(CONFIGS / "ablations" / variant)]
    cli = train_main(args + fast_args(root, tmp_path), run=False)
    m = cli.model
    assert isinstance(m, GarTransModule) and isinstance(cli.datamodule, GarmentDataModule)
    assert m.hparams.num_joints == cli.datamodule.dims["num_joints"]  # linked from the data
    assert m.hparams.nystrom_dim == NY
    expected = {"wo_edge.yaml": "gt", "wo_gating.yaml": "gt_edge", "gat.yaml": "gat",
                "structure_aware.yaml": "structure_aware"}.get(variant, "sat")
    assert m.hparams.dynamic_layer == expected
    sched = [c for c in cli.trainer.callbacks if isinstance(c, ProgressiveSchedule)]
    assert len(sched) == 1
    assert sched[0].max_phase == (1 if variant == "wo_unsup.yaml" else 3)


def test_cli_fit_writes_checkpoint_and_resumes(root, tmp_path):  # noqa: F811
    args = ["train", "fit", "--config", str(CONFIGS / "gartrans.yaml")] + fast_args(root, tmp_path)
    assert cli_main(args) == 0
    last = list(tmp_path.rglob("last.ckpt"))
    assert len(last) == 1
    ck = torch.load(last[0], weights_only=False)
    assert ck["epoch"] == 0
    # resume for one more epoch from `last`
    args2 = list(args)
    args2[args2.index("--trainer.max_epochs") + 1] = "2"
    assert cli_main(args2 + ["--ckpt_path", str(last[0])]) == 0
    ck2 = torch.load(sorted(tmp_path.rglob("last*.ckpt"), key=lambda p: p.stat().st_mtime)[-1],
                     weights_only=False)
    assert ck2["epoch"] == 1


class _ReplicasEqual(L.Callback):
    def on_train_end(self, trainer, pl_module):
        import torch.distributed as dist
        assert dist.is_initialized() and dist.get_world_size() == 2
        assert dist.get_backend() == "gloo"
        # DDP keeps replicas identical: gather a parameter checksum from both ranks
        s = torch.stack([p.detach().double().sum() for p in pl_module.parameters()]).sum()
        out = [torch.zeros_like(s) for _ in range(2)]
        dist.all_gather(out, s)
        assert torch.equal(out[0], out[1])


@pytest.mark.slow
@pytest.mark.parametrize("phase", [1, 3])
def test_ddp_two_cpu_processes_gloo(root, tmp_path, phase):  # noqa: F811
    """Plain DDP (every trainable parameter gets a gradient) in phase 1; phase 3 freezes
    the rest branch mid-run, which DDP only allows with ``find_unused_parameters``."""
    from lightning.pytorch.strategies import DDPStrategy
    dm = GarmentDataModule(root, chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)
    module = GarTransModule(**dm.dims)
    with torch.no_grad():  # open the lbs_start gates so every branch gets gradient at once
        module.model.gates.fill_(0.5)
    strategy = DDPStrategy(start_method="spawn", find_unused_parameters=phase == 3)
    trainer = L.Trainer(accelerator="cpu", devices=2, strategy=strategy, max_epochs=1,
                        limit_train_batches=2, limit_val_batches=0, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False,
                        callbacks=[_ReplicasEqual(), ProgressiveSchedule(start_phase=phase)],
                        default_root_dir=str(tmp_path))
    before = {n: p.detach().clone() for n, p in module.named_parameters()}
    trainer.fit(module, dm)
    # the spawn strategy copies the trained weights back to the main process
    after = dict(module.named_parameters())
    changed = {n for n in before if not torch.equal(before[n], after[n])}
    assert any(n.startswith("model.dynamic") for n in changed)
    rest = {n for n in before if n.split(".")[1] in ("rest_fc", "rest_attn", "nystrom_fc")}
    assert (rest & changed) == (set() if phase == 3 else rest)
