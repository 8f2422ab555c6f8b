"""Corrupt and truncated files of every format garmentgnn reads: garment meshes
(OBJ, PLY, GLB), BVH motion, sequence files (NPZ), checkpoints, the dataset's JSON."""
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from _fuzz import FUZZ, mutations, outcome
from garmentgnn.body.skeleton import Skeleton
from garmentgnn.data import store
from garmentgnn.garments import load_garment, save_garment
from garmentgnn.garments.garment import Garment
from garmentgnn.geometry import grid_mesh
from garmentgnn.motion import load_bvh, save_bvh
from garmentgnn.motion.sequence import Motion
from garmentgnn.training import GarTransModule
from garmentgnn.training.integrity import CheckpointError, load_checkpoint_file
from garmentgnn.models import GarTrans


def sheet_garment():
    pos, faces = grid_mesh(4, 4, (0.3, 0.3), dtype=torch.float32)
    return Garment(pos + torch.tensor([0.0, 0.0, 1.0]), faces, pos[:, :2].clone())


def _bytes_of(tmp, name, write):
    p = Path(tmp) / name
    write(p)
    return p.read_bytes()


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("meshes")
    g = sheet_garment()
    tm = trimesh.Trimesh(g.vertices.numpy(), g.faces.numpy(), process=False)
    return {
        "obj": _bytes_of(tmp, "g.obj", lambda p: save_garment(p, g)),
        "ply": tm.export(file_type="ply"),
        "glb": tm.export(file_type="glb"),
    }


def check_garment(g):
    assert torch.isfinite(g.vertices).all() and g.vertices.shape[1] == 3
    assert g.faces.numel() and int(g.faces.min()) >= 0
    assert int(g.faces.max()) < g.vertices.shape[0]


@pytest.mark.parametrize("fmt", ["obj", "ply", "glb"])
@FUZZ
@given(data=st.data())
def test_corrupt_mesh_files(mesh_files, tmp_path_factory, fmt, data):
    blob = data.draw(mutations(mesh_files[fmt]))
    p = tmp_path_factory.mktemp("m") / f"fuzz.{fmt}"
    p.write_bytes(blob)
    g = outcome(f"garment {fmt.upper()}", load_garment, p, names=(str(p),))
    if g is not None:
        check_garment(g)


@FUZZ
@given(lines=st.lists(st.one_of(
    st.sampled_from(["v 0 0 0", "v 1 0 0", "v 0 1 0", "v nan 0 0", "v 1e400 0 0", "f 1 2 3",
                     "f 1 2 9", "f -1 -2 -3", "f 1/1 2/2 3/3", "vt 0 0", "f 1 1 2", "f 0 1 2",
                     "o x", "# c\xe9", "usemtl a", "f 1 2", "v 1 2", "\ufeffv 0 0 1"]),
    st.text(max_size=12)), max_size=20), sep=st.sampled_from(["\n", "\r\n", "\r"]),
    base=st.booleans())
def test_obj_statements(tmp_path_factory, lines, sep, base):
    p = tmp_path_factory.mktemp("o") / "s.obj"
    if base:  # a valid triangle first, then the drawn statements
        lines = ["v 0 0 0", "v 1 0 0", "v 0 1 0", "f 1 2 3"] + lines
    p.write_bytes(sep.join(lines).encode("utf-8", "surrogatepass"))
    g = outcome("garment OBJ statements", load_garment, p, names=(str(p),))
    if g is not None:
        check_garment(g)


# ------------------------------------------------------------------ BVH
SKEL = Skeleton(["Hips", "Spine", "LeftUpLeg"], torch.tensor([-1, 0, 0]))
REST = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.2], [0.1, 0.0, 0.9]])


@pytest.fixture(scope="module")
def bvh_text():
    rot = 0.3 * torch.randn(4, 3, 3, generator=torch.Generator().manual_seed(0))
    m = Motion(rot, torch.zeros(4, 3), list(SKEL.joint_names), 30.0)
    return save_bvh(None, m, SKEL, REST)


@FUZZ
@given(data=st.data())
def test_corrupt_bvh(bvh_text, data):
    raw = data.draw(mutations(bvh_text.encode()))
    text = raw.decode("utf-8", errors="replace")
    if "\n" not in text and "HIERARCHY" not in text:
        text += "\n"  # keep it text (a one-line string is read as a path)
    res = outcome("BVH", load_bvh, text, names=("BVH",))
    if res is not None:
        hier, motion = res
        assert torch.isfinite(motion.rotations).all()
        assert motion.rotations.shape[1] == len(hier.joint_names) == len(motion.joint_names)


@FUZZ
@given(token=st.sampled_from(["nan", "inf", "-inf", "1e400", "", "abc", "0x10", "1e-400",
                              "-0", "99999999999999999999"]),
       which=st.integers(0, 10_000))
def test_bvh_odd_numbers(bvh_text, token, which):
    toks = bvh_text.split(" ")
    k = which % len(toks)
    toks[k] = token + ("\n" if toks[k].endswith("\n") else "")
    res = outcome("BVH numbers", load_bvh, " ".join(toks), names=("BVH",))
    if res is not None:
        assert torch.isfinite(res[1].rotations).all()
        assert torch.isfinite(res[1].translation).all()


# ------------------------------------------------------------------ NPZ sequence files
def sequence_arrays(T=3, V=9):
    pos, faces = grid_mesh(3, 3, (0.2, 0.2), dtype=torch.float32)
    P = np.repeat(pos.numpy()[None], T, 0)
    return {"garment_vertices": pos.numpy(), "garment_faces": faces.numpy(),
            "garment_uv": pos[:, :2].numpy(), "garment_face_uv": np.zeros((len(faces), 3, 2),
                                                                          np.float32),
            "garment_pinned": np.zeros(V, bool), "body_shape": np.zeros(0),
            "motion_rotations": np.zeros((T, 2, 3), np.float32),
            "motion_translation": np.zeros((T, 3), np.float32), "positions": P,
            "converged": np.ones(T, bool), "newton_iterations": np.zeros(T, np.int32),
            "residual": np.zeros(T, np.float32)}


@pytest.fixture(scope="module")
def npz_file(tmp_path_factory):
    root = tmp_path_factory.mktemp("npz")
    arrays = sequence_arrays()
    path = root / store.SEQUENCES / "a.npz"
    store.write_sequence(path, arrays, {"id": "a", "num_frames": 3})
    return path.read_bytes(), arrays


@FUZZ
@given(data=st.data())
def test_corrupt_sequence_file(npz_file, tmp_path_factory, data):
    good, arrays = npz_file
    blob = data.draw(mutations(good))
    root = tmp_path_factory.mktemp("seq")
    path = root / store.SEQUENCES / "a.npz"
    path.parent.mkdir()
    path.write_bytes(blob)
    msg = store.validate_sequence(path, "a")  # never raises
    assert msg is None or isinstance(msg, str)
    rec = {"id": "a", "file": "sequences/a.npz", "sha256": store.file_sha256(path)}
    if blob != good:  # the manifest's hash is the original's: any change is an error
        with pytest.raises(store.IntegrityError, match="a.npz"):
            store.load_record_sequence(root, dict(rec, sha256=store.file_sha256(path) + "0"))
    seq = outcome("sequence NPZ (no hash)", store.load_record_sequence, root, rec,
                  names=(str(path),))
    if seq is not None:  # loaded without a hash to compare: it must be the original
        for k, v in arrays.items():
            assert np.array_equal(seq[k], v), f"{k} silently changed"


# ------------------------------------------------------------------ checkpoints
@pytest.fixture(scope="module")
def ckpt_bytes():
    m = GarTransModule(GarTrans(num_joints=3, num_body_vertices=10, nystrom_dim=8, heads=2))
    ck = {"state_dict": m.state_dict(), "hyper_parameters": dict(m.hparams), "epoch": 0}
    m.on_save_checkpoint(ck)
    buf = io.BytesIO()
    torch.save(ck, buf)
    return buf.getvalue(), m.state_dict()


@FUZZ
@given(data=st.data())
def test_corrupt_checkpoint(ckpt_bytes, tmp_path_factory, data):
    good, state = ckpt_bytes
    blob = data.draw(mutations(good))
    p = tmp_path_factory.mktemp("ck") / "x.ckpt"
    p.write_bytes(blob)
    ck = outcome("checkpoint", load_checkpoint_file, p, names=(str(p),))
    if ck is not None:  # loaded and verified: the weights are the original ones
        assert ck["state_dict"].keys() == state.keys()
        for k, v in state.items():
            assert torch.equal(ck["state_dict"][k], v), f"{k} silently changed"


def test_checkpoint_errors_are_checkpoint_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint_file(tmp_path / "missing.ckpt")


# ------------------------------------------------------------------ manifest / spec JSON
@FUZZ
@given(doc=st.one_of(st.binary(max_size=64),
                    st.builds(lambda items: json.dumps({"items": items}).encode(),
                              st.lists(st.dictionaries(st.sampled_from(["id", "status"]),
                                                       st.text(max_size=3)), max_size=2)),
                    st.builds(lambda o: json.dumps(o).encode(),
                                                 st.recursive(st.none() | st.integers()
                                                              | st.text(max_size=5),
                                                              lambda c: st.lists(c, max_size=3)
                                                              | st.dictionaries(
                                                                  st.text(max_size=5), c,
                                                                  max_size=3), max_leaves=8))))
def test_corrupt_manifest(tmp_path_factory, doc):
    root = tmp_path_factory.mktemp("man")
    (root / store.MANIFEST).write_bytes(doc)
    man = outcome("manifest.json", store.read_manifest, root, names=(str(root),))
    if man is not None:
        assert isinstance(man["items"], list)
