"""Bodies: forward kinematics and LBS against analytic poses, the capsule body, and
the anny adapter against anny's own forward pass."""
import math
import pickle
import time

import numpy as np
import pytest
import torch
import trimesh

from garmentgnn.body import Body, Skeleton, forward_kinematics, linear_blend_skinning
from garmentgnn.body.anny_body import AnnyBodyModel, PHENOTYPES
from garmentgnn.body.capsule import CapsuleBodyModel
from garmentgnn.body.smpl_body import SMPLBodyModel, Y_UP_TO_Z_UP, landmark_ids
from garmentgnn.geometry.rotations import axis_angle_to_matrix


def chain():
    """Three joints on the z axis: root at 0, child at z=1, grandchild at z=2."""
    sk = Skeleton(["a", "b", "c"], torch.tensor([-1, 0, 1]))
    return sk, torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 2.0]])


def test_fk_analytic_chain():
    sk, J = chain()
    rot = torch.zeros(1, 3, 3)
    rot[0, 1] = torch.tensor([math.pi / 2, 0.0, 0.0])  # bend at b by 90 deg about x
    A, joints = forward_kinematics(rot, J, sk.parents, torch.tensor([[1.0, 0.0, 0.0]]))
    # rotating (0,0,1) by +90 deg about x gives (0,-1,0)
    expected = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 1.0], [1.0, -1.0, 1.0]])
    torch.testing.assert_close(joints[0], expected, atol=1e-6, rtol=0)
    # A maps rest joints to posed joints
    Jh = torch.cat([J, torch.ones(3, 1)], 1)
    posed = torch.einsum("sij,sj->si", A[0], Jh)[:, :3]
    torch.testing.assert_close(posed, expected, atol=1e-6, rtol=0)


def test_lbs_rigid_and_blended():
    sk, J = chain()
    verts = torch.tensor([[0.1, 0.0, 1.5], [0.0, 0.2, 0.5]])
    rot = torch.zeros(2, 3, 3)
    rot[1, 1, 2] = 0.7
    A, _ = forward_kinematics(rot, J, sk.parents)
    one_hot = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    out = linear_blend_skinning(verts, one_hot, A)
    torch.testing.assert_close(out[0], verts)  # identity pose
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, 0.7]))
    torch.testing.assert_close(out[1, 0], R @ (verts[0] - J[1]) + J[1])
    torch.testing.assert_close(out[1, 1], verts[1])  # bound to the unrotated root
    half = torch.tensor([[0.5, 0.5, 0.0], [0.5, 0.5, 0.0]])
    blended = linear_blend_skinning(verts, half, A)[1, 0]
    torch.testing.assert_close(blended, 0.5 * verts[0] + 0.5 * (R @ (verts[0] - J[1]) + J[1]))


def test_skeleton_validation():
    with pytest.raises(ValueError, match="parents"):
        Skeleton(["a", "b"], torch.tensor([-1, 1]))
    with pytest.raises(ValueError, match="roles"):
        Skeleton(["a"], torch.tensor([-1]), {"elbow_of_doom": "a"})
    with pytest.raises(ValueError, match="nope"):
        Skeleton(["a"], torch.tensor([-1])).index("nope")


@pytest.mark.parametrize("preset", ["thin", "regular", "fat"])
def test_capsule_body(preset):
    model = CapsuleBodyModel()
    body = model(preset)
    torch.testing.assert_close(body.weights.sum(1), torch.ones(body.vertices.shape[0]))
    mesh = trimesh.Trimesh(body.vertices.numpy(), body.faces.numpy(), process=False)
    assert mesh.is_winding_consistent
    assert all(p.is_watertight for p in mesh.split(only_watertight=False))
    assert body.vertices[:, 2].min() > -0.05 and 1.6 < body.vertices[:, 2].max() < 1.95
    # posing keeps bone lengths (FK oracle) and never produces NaN
    T, S = 4, body.skeleton.num_joints
    rot = 0.5 * torch.randn(T, S, 3, generator=torch.Generator().manual_seed(0))
    verts, joints = body.pose(rot, torch.zeros(T, 3))
    assert torch.isfinite(verts).all()
    par = body.skeleton.parents[1:]
    rest_len = (body.joints[1:] - body.joints[par]).norm(dim=-1)
    torch.testing.assert_close((joints[:, 1:] - joints[:, par]).norm(dim=-1),
                               rest_len.expand(T, -1), atol=1e-5, rtol=0)


def test_capsule_girth_orders_volume():
    model = CapsuleBodyModel()
    vols = []
    for name in ["thin", "regular", "fat"]:
        caps = model.capsules(name)
        vols.append(sum(math.pi * r**2 * float((b - a).norm()) + 4 / 3 * math.pi * r**3
                        for _, a, b, r in caps))
    assert vols[0] < vols[1] < vols[2]


def test_body_rejects_bad_input():
    body = CapsuleBodyModel()("regular")
    with pytest.raises(ValueError, match="vertices"):
        Body(body.vertices * float("nan"), body.faces, body.skeleton, body.joints, body.weights)
    with pytest.raises(ValueError, match="faces"):
        Body(body.vertices, body.faces + body.vertices.shape[0], body.skeleton, body.joints,
             body.weights)
    with pytest.raises(ValueError, match="rotations"):
        body.pose(torch.zeros(2, 3, 3, 3))
    with pytest.raises(ValueError, match="shape"):
        CapsuleBodyModel()("huge")


# --- anny: a real human ------------------------------------------------------

@pytest.fixture(scope="module")
def anny_model():
    pytest.importorskip("anny")
    return AnnyBodyModel(dtype=torch.float64, ground=False)


@pytest.mark.slow
def test_anny_lbs_matches_anny_forward(anny_model):
    """Our LBS (Eq. 1) on the adapter's body equals anny's own local-ref forward pass."""
    import anny  # noqa: PLC0415 (optional: the human extra)

    body = anny_model("fat")
    m = anny.Anny(rig="cmu_mb", topology="notoes_collapse10pc", skinning_method="lbs")
    S = body.skeleton.num_joints
    g = torch.Generator().manual_seed(0)
    aa = 0.4 * torch.randn(3, S, 3, generator=g, dtype=torch.float64)
    tr = 0.1 * torch.randn(3, 3, generator=g, dtype=torch.float64)
    P = torch.eye(4, dtype=torch.float64).repeat(3, S, 1, 1)
    P[:, :, :3, :3] = axis_angle_to_matrix(aa)
    P[:, 0, :3, 3] = tr
    ref = m(pose_parameters=P, phenotype_kwargs=dict(zip(PHENOTYPES, body.shape.tolist())))
    # anny's root transform is global: the root joint goes to `tr`
    verts, _ = body.pose(aa, tr - body.joints[0])
    torch.testing.assert_close(verts, ref["vertices"], atol=1e-9, rtol=0)


@pytest.mark.slow
def test_anny_shapes_and_cache(anny_model):
    vols = []
    for name in ["thin", "regular", "fat"]:
        body = anny_model(name)
        mesh = trimesh.Trimesh(body.vertices.numpy(), body.faces.numpy(), process=False)
        assert mesh.is_watertight
        vols.append(mesh.volume)
    assert vols[0] < vols[1] < vols[2]
    assert set(body.skeleton.roles) >= {"pelvis", "l_knee", "r_elbow", "head"}
    fresh = AnnyBodyModel(dtype=torch.float64, ground=True)
    t0 = time.perf_counter()
    again = fresh("fat")
    assert fresh.last_load_source == "cache" and time.perf_counter() - t0 < 1.0
    assert abs(float(again.vertices[:, 2].min())) < 1e-12  # grounded
    np.testing.assert_allclose(again.vertices.numpy() - again.vertices.numpy()[:1],
                               body.vertices.numpy() - body.vertices.numpy()[:1], atol=1e-12)


def test_anny_rejects_bad_shape():
    with pytest.raises(ValueError, match="shape"):
        AnnyBodyModel.phenotype({"weight": 2.0})
    with pytest.raises(ValueError, match="shape"):
        AnnyBodyModel.phenotype({"wingspan": 0.5})
    with pytest.raises(ValueError, match="shape"):
        AnnyBodyModel.phenotype("giant")


# --- SMPL through smplx, with a tiny SMPL-format file the test writes itself ---------

def tiny_smpl_file(path, num_verts=60, seed=0):
    rng = np.random.default_rng(seed)
    J = 24
    parents = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
    kintree = np.stack([np.array(parents, dtype=np.int64) % (2**32), np.arange(J)])
    reg = np.abs(rng.normal(size=(J, num_verts)))
    w = np.abs(rng.normal(size=(num_verts, J)))
    data = dict(v_template=rng.normal(size=(num_verts, 3)),
                shapedirs=0.05 * rng.normal(size=(num_verts, 3, 10)),
                posedirs=np.zeros((num_verts, 3, 207)),
                J_regressor=reg / reg.sum(1, keepdims=True),
                weights=w / w.sum(1, keepdims=True),
                kintree_table=kintree, f=rng.integers(0, num_verts, size=(80, 3)))
    with open(path, "wb") as f:
        pickle.dump(data, f)
    return data


def test_smpl_adapter_matches_smplx(tmp_path):
    smplx = pytest.importorskip("smplx")
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    tiny_smpl_file(path)
    model = SMPLBodyModel(path, dtype=torch.float64)
    beta = torch.linspace(-1, 1, 10)
    body = model(beta)
    assert body.skeleton.index("l_knee") == 4
    ref_model = smplx.SMPL(model_path=str(path), num_betas=10,
                           vertex_ids=landmark_ids(60)).double()
    g = torch.Generator().manual_seed(0)
    aa = 0.3 * torch.randn(2, 24, 3, generator=g, dtype=torch.float64)
    transl = 0.1 * torch.randn(2, 3, generator=g, dtype=torch.float64)
    ref = ref_model(betas=beta.double().expand(2, -1), global_orient=aa[:, 0],
                    body_pose=aa[:, 1:].reshape(2, -1), transl=transl)
    C = Y_UP_TO_Z_UP.double()
    # rotations and translation expressed in the Z-up frame: R' = C R C^T
    R = axis_angle_to_matrix(aa)
    verts, _ = body.pose(C @ R @ C.T, transl @ C.T)
    # smplx stores its buffers in float32: agreement to float32 round-off
    torch.testing.assert_close(verts, ref.vertices @ C.T, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="shape"):
        model(torch.zeros(3))
    with pytest.raises(ValueError, match="model_path"):
        SMPLBodyModel(tmp_path / "missing.pkl")
