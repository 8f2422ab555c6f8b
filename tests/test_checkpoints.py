"""One loader for every method's checkpoint: :func:`garmentgnn.training.load_checkpoint`
picks the module class from what the file stores (its ``_class_path``, else its model's
class) and rebuilds it with the same weights."""
from __future__ import annotations

import lightning as L
import pytest
import torch

from garmentgnn.models import GarTrans, MGNStyle
from garmentgnn.models.baselines import DAStyle, HOODStyle, NCSStyle
from garmentgnn.training import (BaselineModule, GarmentModule, GarTransModule,
                                 RolloutModule, load_checkpoint)
from garmentgnn.training.checkpoints import module_class
from garmentgnn.training.integrity import CheckpointError, stamp_checkpoint

JOINTS, BODY_VERTICES, VERTICES = 5, 12, 9


class RenamedModule(GarTransModule):
    """A module of its own that trains GarTrans: only its stored class path tells it apart."""


def _save(module: GarmentModule, path, class_path: str = "") -> None:
    """``module`` written as Lightning writes a checkpoint (``class_path``: as
    ``garmentgnn train`` adds it)."""
    hp = dict(module.hparams)
    if class_path:
        hp["_class_path"] = class_path
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": hp,
            "pytorch-lightning_version": L.__version__}
    stamp_checkpoint(ckpt)
    torch.save(ckpt, path)


def _methods():
    return {
        "gartrans": (GarTransModule, lambda: GarTransModule(
            GarTrans(JOINTS, BODY_VERTICES, nystrom_dim=4, heads=1))),
        "da": (BaselineModule, lambda: BaselineModule(DAStyle(JOINTS, hidden=8))),
        "hood": (BaselineModule, lambda: BaselineModule(HOODStyle(hidden=8))),
        "ncs": (BaselineModule, lambda: BaselineModule(NCSStyle(VERTICES, JOINTS, hidden=8))),
        "mgn": (RolloutModule, lambda: RolloutModule(MGNStyle(hidden=8, layers=1, heads=1))),
    }


@pytest.mark.parametrize("stored", [False, True], ids=["model-class", "class-path"])
@pytest.mark.parametrize("kind", list(_methods()))
def test_each_method_loads_as_its_module_with_its_weights(kind, stored, tmp_path):
    cls, build = _methods()[kind]
    L.seed_everything(0)
    module = build()
    path = tmp_path / f"{kind}.ckpt"
    _save(module, path, f"{cls.__module__}.{cls.__name__}" if stored else "")
    loaded = load_checkpoint(path)
    assert type(loaded) is cls and not loaded.training
    assert type(loaded.model) is type(module.model)
    if cls is BaselineModule:
        assert loaded.method == kind
    want = module.state_dict()
    got = loaded.state_dict()
    assert want.keys() == got.keys()
    for k, v in want.items():
        torch.testing.assert_close(got[k], v, msg=k)


def test_the_stored_class_path_decides_over_the_model(tmp_path):
    """A module of one's own around GarTrans loads as itself, not as GarTransModule."""
    L.seed_everything(0)
    module = RenamedModule(GarTrans(JOINTS, BODY_VERTICES, nystrom_dim=4, heads=1))
    path = tmp_path / "own.ckpt"
    _save(module, path, f"{RenamedModule.__module__}.RenamedModule")
    assert type(load_checkpoint(path)) is RenamedModule
    _save(module, path)  # without it: the module that trains the model
    assert type(load_checkpoint(path)) is GarTransModule


def test_a_stored_class_path_that_is_no_module_is_refused():
    with pytest.raises(CheckpointError, match="not a garmentgnn module"):
        module_class({"_class_path": "torch.nn.Linear"})
    with pytest.raises(CheckpointError, match="cannot be imported"):
        module_class({"_class_path": "garmentgnn.training.NoSuchModule"})


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_checkpoint(tmp_path / "none.ckpt")


def test_a_checkpoint_of_a_renamed_module_loads_under_its_new_name(tmp_path):
    """A checkpoint written while the MGN-style module had its former name (its
    ``_class_path`` as ``garmentgnn train`` wrote it then) loads as today's module."""
    L.seed_everything(0)
    module = RolloutModule(MGNStyle(hidden=8, layers=1, heads=1))
    path = tmp_path / "former.ckpt"
    _save(module, path, "garmentgnn.training.SimulatorModule")
    loaded = load_checkpoint(path)
    assert type(loaded) is RolloutModule
    for k, v in module.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[k], v, msg=k)
    _save(module, path, "garmentgnn.training.NoSuchModule")
    with pytest.raises(CheckpointError, match="NoSuchModule"):
        load_checkpoint(path)
