"""docs/own_garment.md's chain on small files the test writes: an OBJ garment and BVH
takes -> `generate --spec` (the torch simulator) -> `train fit` (two steps) ->
`predict` on the held-out take -> glTF, PC2 and OBJs of that garment."""
import numpy as np
import pytest
import trimesh

from garmentgnn.cli import main as cli_main
from garmentgnn.data import read_manifest
from test_own_garment import files, write_spec  # noqa: F401 (a fixture)


@pytest.mark.slow  # a real simulation, a fit and a prediction (~45 s)
def test_obj_and_bvh_to_a_trained_gartrans_to_gltf(files, tmp_path, capsys):  # noqa: F811
    data, runs, out = tmp_path / "data", tmp_path / "runs", tmp_path / "out" / "twirl"
    spec = write_spec(files, frames=4)
    assert cli_main(["generate", "--spec", str(spec), "--out", str(data), "--workers", "0",
                     "--no-progress", "--no-estimate"]) == 0
    assert read_manifest(data)["counts"] == {"ok": 2}
    assert cli_main(["train", "fit", "--config", "gartrans", "--data.root", str(data),
                     "--data.val_split", "null", "--data.chunk", "4", "--trainer.max_steps",
                     "2", "--trainer.default_root_dir", str(runs),
                     "--trainer.enable_progress_bar", "false"]) == 0
    (ckpt,) = runs.rglob("last.ckpt")
    capsys.readouterr()
    assert cli_main(["predict", "--ckpt", str(ckpt), "--garment", str(files / "skirt.obj"),
                     "--motion", str(files / "twirl.bvh"), "--scale", "0.01", "--frames", "4",
                     "--out", str(out)]) == 0
    assert "gartrans (frame-parallel): 4 frames" in capsys.readouterr().out
    scene = trimesh.load(out.with_suffix(".glb"))
    assert sorted(len(g.vertices) for g in scene.geometry.values()) == [192, 1229]
    objs = sorted(out.parent.glob("twirl_obj/*.obj"))
    assert len(objs) == 4
    assert all(np.isfinite(trimesh.load(p, process=False).vertices).all() for p in objs)
