"""glTF export read back by an independent reader (VTK's vtkGLTFReader: node
transforms, morph targets and the animation applied by VTK), frame by frame, in our
vertex order; the PC2 / OBJ round trips are in test_data.py."""

import numpy as np
import pytest
import torch

from garmentgnn.body.factory import build_body
from garmentgnn.cli import main
from garmentgnn.data import store
from garmentgnn.data.export import export_sequence
from garmentgnn.data.gltf import GltfMesh, write_gltf

from conftest import skirt_dataset


vtk = pytest.importorskip("vtk", reason='VTK is not installed: pip install "garmentgnn[viz]"')
pytest.importorskip("pygltflib", reason='pygltflib is not installed: pip install "garmentgnn[viz]"')
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def make_dataset(out):
    """Two 8-frame sequences of a skirt on a capsule body; the `run` motion is held out."""
    return skirt_dataset(out, ["walk", "run"], 8, held_out={"test": ["run"]}, name="v")


_DATA = {}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """Generated once per test run (tmp_path_factory's folders live that long) and shared
    with test_viz.py."""
    if "root" not in _DATA:
        _DATA["root"] = make_dataset(tmp_path_factory.mktemp("vizdata"))
    return _DATA["root"]


def vtk_read(path, times):
    """For each time: the leaf meshes' (points [V, 3], triangles [F, 3]) in file order,
    with the points converted back from glTF's Y up to our Z up: (x, y, z) = (x, -z', y')."""
    r = vtk.vtkGLTFReader()
    r.SetFileName(str(path))
    r.UpdateInformation()
    assert r.GetNumberOfAnimations() == 1
    r.EnableAnimation(0)
    frames = []
    for t in times:
        r.UpdateTimeStep(t)
        leaves = []

        def walk(block):
            if isinstance(block, vtk.vtkMultiBlockDataSet):
                for i in range(block.GetNumberOfBlocks()):
                    walk(block.GetBlock(i))
            elif block is not None:
                p = vtk_to_numpy(block.GetPoints().GetData()).astype(np.float64)
                c = vtk_to_numpy(block.GetPolys().GetConnectivityArray()).reshape(-1, 3)
                leaves.append((np.stack([p[:, 0], -p[:, 2], p[:, 1]], 1), c))
        walk(r.GetOutput())
        frames.append(leaves)
    return frames


def test_gltf_export_round_trip_with_body(dataset, tmp_path):
    seq_path = sorted((dataset / "sequences").glob("*.npz"))[0]
    seq = store.load_sequence(seq_path)
    out = tmp_path / "seq.glb"
    assert main(["export", "--seq", str(seq_path), "--format", "gltf", "--out", str(out)]) == 0
    assert out.read_bytes()[:4] == b"glTF"
    body = build_body(seq["meta"]["body"])
    dt = body.vertices.dtype
    with torch.no_grad():
        bpos, _ = body.pose(torch.from_numpy(seq["motion_rotations"]).to(dt),
                            torch.from_numpy(seq["motion_translation"]).to(dt))
    P = seq["positions"]
    T = P.shape[0]
    fps = seq["meta"]["settings"]["fps"]
    frames = vtk_read(out, [k / fps for k in range(T)])
    for k, leaves in enumerate(frames):
        assert len(leaves) == 2
        (g, gf), (b, bf) = leaves
        np.testing.assert_allclose(g, P[k], atol=2e-6)  # our vertex order, frame k
        np.testing.assert_allclose(b, bpos[k].numpy(), atol=2e-6)
        np.testing.assert_array_equal(gf, seq["garment_faces"])
        np.testing.assert_array_equal(bf, body.faces.numpy())
    assert np.abs(P[1] - P[0]).max() > 1e-4  # the frames differ, so the check above can fail
    # garment only
    assert main(["export", "--seq", str(seq_path), "--format", "gltf", "--no-body",
                 "--out", str(tmp_path / "g.glb")]) == 0
    (leaves,) = vtk_read(tmp_path / "g.glb", [3 / fps])
    assert len(leaves) == 1
    np.testing.assert_allclose(leaves[0][0], P[3], atol=2e-6)


def test_write_gltf_offsets_and_input_checks(tmp_path):
    rng = np.random.default_rng(0)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    a = rng.normal(size=(5, 4, 3))
    b = rng.normal(size=(5, 4, 3))
    write_gltf(tmp_path / "x.glb", [GltfMesh("a", a, faces),
                                   GltfMesh("b", b, faces, offset=(1.5, 0.0, -0.5))], fps=10)
    frames = vtk_read(tmp_path / "x.glb", [k / 10 for k in range(5)])
    for k, ((pa, _), (pb, _)) in enumerate(frames):
        np.testing.assert_allclose(pa, a[k], atol=1e-5)
        np.testing.assert_allclose(pb, b[k] + [1.5, 0.0, -0.5], atol=1e-5)
    with pytest.raises(ValueError, match="same frames"):
        write_gltf(tmp_path / "y.glb", [GltfMesh("a", a, faces), GltfMesh("b", b[:3], faces)])
    with pytest.raises(ValueError, match="NaN"):
        GltfMesh("n", np.full((2, 4, 3), np.nan), faces)
    with pytest.raises(ValueError, match="indices"):
        GltfMesh("f", a, faces + 3)
    with pytest.raises(ValueError, match="fps"):
        write_gltf(tmp_path / "z.glb", [GltfMesh("a", a, faces)], fps=0)
    with pytest.raises(ValueError, match="gltf"):
        export_sequence(tmp_path / "none.npz", "fbx", tmp_path / "q")


def test_single_frame_gltf_has_no_animation(tmp_path):
    pygltflib = pytest.importorskip("pygltflib")
    faces = np.array([[0, 1, 2]])
    p = write_gltf(tmp_path / "one.glb", [GltfMesh("t", np.eye(3), faces)])
    doc = pygltflib.GLTF2().load(str(p))
    assert not doc.animations and doc.meshes[0].primitives[0].targets in (None, [])


