"""garmentgnn.metrics.split: an error split into a static drape and dynamics, against
hand-computed values, closed forms and per-vertex numpy oracles; the skinning transforms
of GarmentInputs against its skinned garment."""
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from garmentgnn.metrics import split_inputs, static_dynamic_split
from garmentgnn.metrics.split import posed, to_rest_frame
from garmentgnn.data import SequenceChunks

from conftest import skirt_dataset


def affine(lin: np.ndarray, off: np.ndarray) -> torch.Tensor:
    """``[..., 4, 4]`` from linear parts ``[..., 3, 3]`` and offsets ``[..., 3]``."""
    M = np.zeros(lin.shape[:-2] + (4, 4))
    M[..., :3, :3], M[..., :3, 3], M[..., 3, 3] = lin, off, 1.0
    return torch.from_numpy(M)


def random_affine(T: int, V: int, seed: int) -> torch.Tensor:
    """Well-conditioned random affine transforms ``[T, V, 4, 4]``."""
    rng = np.random.default_rng(seed)
    lin = np.eye(3) + 0.3 * rng.standard_normal((T, V, 3, 3))
    return affine(lin, rng.standard_normal((T, V, 3)))


def oracle(pred, gt, M):
    """The split by per-vertex loops with numpy's inverse (cm)."""
    p, x, M = pred.double().numpy(), gt.double().numpy(), M.double().numpy()
    T, V = p.shape[:2]
    Minv = np.array([[np.linalg.inv(M[t, v]) for v in range(V)] for t in range(T)])
    h = lambda a: np.concatenate([a, np.ones(a.shape[:-1] + (1,))], -1)  # noqa: E731
    up = np.einsum("tvij,tvj->tvi", Minv, h(p))[..., :3].mean(0)
    ux = np.einsum("tvij,tvj->tvi", Minv, h(x))[..., :3].mean(0)
    dp = np.einsum("tvij,vj->tvi", M, h(up))[..., :3]
    dx = np.einsum("tvij,vj->tvi", M, h(ux))[..., :3]
    n = lambda a: float(np.linalg.norm(a, axis=-1).mean()) * 100  # noqa: E731
    return {"E_static": n(dp - dx), "E_dynamic": n((p - dp) - (x - dx)), "E_dist": n(p - x)}


def close(a, b, tol=1e-9):
    assert a.keys() == b.keys()
    for k in a:
        assert a[k] == pytest.approx(b[k], abs=tol), (k, a[k], b[k])


# --------------------------------------------------------------------------- synthetic
def test_hand_computed_rigid_example():
    # M_0 = identity; M_1 = 90 degrees about z, then + (1, 0, 0)
    M = torch.tensor([[[[1., 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]],
                      [[[0., -1, 0, 1], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]]],
                     dtype=torch.float64)
    # gt: rest-frame (1, 0, 0) then (1, 2, 0) -> drape (1, 1, 0)
    gt = torch.tensor([[[1., 0, 0]], [[-1., 1, 0]]])
    # pred: rest-frame (0, 0, 0) then (0, 0, 2) -> drape (0, 0, 1)
    pred = torch.tensor([[[0., 0, 0]], [[1., 0, 2]]])
    torch.testing.assert_close(to_rest_frame(M, gt), torch.tensor([[[1., 0, 0]], [[1., 2, 0]]],
                                                                dtype=torch.float64))
    got = static_dynamic_split(pred, gt, M)
    # static: |(0,0,1) - (1,1,0)| = sqrt 3 at both frames (rigid: lengths kept)
    # dynamic: pred's residuals (0,0,-1), (0,0,1); gt's (0,-1,0), R(0,1,0) = (-1,0,0)
    # -> |(0,1,-1)| = |(1,0,1)| = sqrt 2;  dist: |(-1,0,0)| = 1, |(2,-1,2)| = 3
    close(got, {"E_static": 100 * math.sqrt(3), "E_dynamic": 100 * math.sqrt(2),
                "E_dist": 200.0})


def test_rigid_transforms_static_error_is_the_rest_frame_distance():
    rng = np.random.default_rng(3)
    T, V = 5, 7
    R = Rotation.random(T, random_state=4).as_matrix()
    M = affine(np.repeat(R[:, None], V, 1), np.repeat(rng.standard_normal((T, 1, 3)), V, 1))
    pred, gt = (torch.from_numpy(rng.standard_normal((T, V, 3))) for _ in range(2))
    got = static_dynamic_split(pred, gt, M)
    # rest frame: u_t = R_t^T (x_t - c_t); a rotation keeps lengths, so E_static is the
    # distance of the time-mean rest shapes, the same at every frame
    c = M[:, :, :3, 3].numpy()
    up = np.einsum("tji,tvj->tvi", R, pred.numpy() - c).mean(0)
    ux = np.einsum("tji,tvj->tvi", R, gt.numpy() - c).mean(0)
    assert got["E_static"] == pytest.approx(100 * np.linalg.norm(up - ux, axis=-1).mean(),
                                            abs=1e-9)
    close(got, oracle(pred, gt, M))


def test_random_affine_matches_the_numpy_oracle_and_the_triangle_inequality():
    for seed in range(4):
        T, V = 6, 9
        M = random_affine(T, V, seed)
        g = torch.Generator().manual_seed(seed)
        gt = torch.randn(T, V, 3, generator=g, dtype=torch.float64)
        pred = gt + 0.3 * torch.randn(T, V, 3, generator=g, dtype=torch.float64)
        got = static_dynamic_split(pred, gt, M)
        close(got, oracle(pred, gt, M), tol=1e-7)
        assert got["E_static"] > 0 and got["E_dynamic"] > 0
        assert got["E_dist"] <= got["E_static"] + got["E_dynamic"] + 1e-9


def test_prediction_equal_to_ground_truth_scores_zero():
    M = random_affine(4, 5, 0)
    gt = torch.randn(4, 5, 3, generator=torch.Generator().manual_seed(0))
    close(static_dynamic_split(gt.clone(), gt, M),
          {"E_static": 0.0, "E_dynamic": 0.0, "E_dist": 0.0})


def test_static_oracle_has_no_static_error():
    T, V = 6, 8
    M = random_affine(T, V, 1)
    gt = torch.randn(T, V, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    pred = posed(M, to_rest_frame(M, gt).mean(0))  # M_t ū^gt
    got = static_dynamic_split(pred, gt, M)
    assert got["E_static"] == pytest.approx(0.0, abs=1e-9)
    # nothing but dynamics is left, so E_dynamic is the whole distance
    assert got["E_dynamic"] == pytest.approx(got["E_dist"], abs=1e-9) and got["E_dist"] > 1


def test_lbs_dynamic_error_is_the_in_sample_static_oracle_error():
    T, V = 7, 10
    M = random_affine(T, V, 2)
    g = torch.Generator().manual_seed(2)
    rest = torch.randn(V, 3, generator=g, dtype=torch.float64)
    gt = torch.randn(T, V, 3, generator=g, dtype=torch.float64)
    Mn = M.numpy()
    lbs = torch.from_numpy(np.einsum("tvij,vj->tvi", Mn[..., :3, :3], rest.numpy())
                           + Mn[..., :3, 3])
    # the in-sample static oracle, by numpy: each vertex un-skinned, time-averaged, posed
    Minv = np.linalg.inv(Mn)
    ubar = (np.einsum("tvij,tvj->tvi", Minv[..., :3, :3], gt.numpy()) + Minv[..., :3, 3]).mean(0)
    drape = np.einsum("tvij,vj->tvi", Mn[..., :3, :3], ubar) + Mn[..., :3, 3]
    got = static_dynamic_split(lbs, gt, M)
    assert got["E_dynamic"] == pytest.approx(
        100 * np.linalg.norm(drape - gt.numpy(), axis=-1).mean(), abs=1e-9)
    assert got["E_static"] == pytest.approx(
        100 * np.linalg.norm(lbs.numpy() - drape, axis=-1).mean(), abs=1e-9)


def test_constant_offsets_are_static():
    T, V = 5, 6
    g = torch.Generator().manual_seed(5)
    gt = torch.randn(T, V, 3, generator=g, dtype=torch.float64)
    # a fixed rest-frame offset d_v under any transforms: E_static = mean |A_t d_v|
    M = random_affine(T, V, 5)
    d = torch.randn(V, 3, generator=g, dtype=torch.float64)
    pred = posed(M, to_rest_frame(M, gt) + d)
    got = static_dynamic_split(pred, gt, M)
    Ad = torch.einsum("tvij,vj->tvi", M[..., :3, :3], d)
    assert got["E_static"] == pytest.approx(100 * float(Ad.norm(dim=-1).mean()), abs=1e-9)
    assert got["E_dynamic"] == pytest.approx(0.0, abs=1e-9)
    assert got["E_dist"] == pytest.approx(got["E_static"], abs=1e-9)
    # a fixed world offset c, one rotation for all frames, moving translations:
    # E_static = E_dist = |c| (cm), E_dynamic = 0
    R = Rotation.random(random_state=6).as_matrix()
    M = affine(np.broadcast_to(R, (T, V, 3, 3)), np.random.default_rng(6).normal(size=(T, V, 3)))
    c = torch.tensor([0.03, -0.04, 0.0], dtype=torch.float64)
    close(static_dynamic_split(gt + c, gt, M), {"E_static": 5.0, "E_dynamic": 0.0,
                                                "E_dist": 5.0})


def test_bad_input_raises():
    M = random_affine(3, 4, 0)
    x = torch.zeros(3, 4, 3)
    with pytest.raises(ValueError, match="`pred`"):
        static_dynamic_split(torch.zeros(3, 4), x, M)
    with pytest.raises(TypeError, match="`gt`"):
        static_dynamic_split(x, x.numpy(), M)
    with pytest.raises(ValueError, match="`gt`"):
        static_dynamic_split(x, torch.zeros(3, 5, 3), M)
    with pytest.raises(ValueError, match="`transforms`"):
        static_dynamic_split(x, x, M[:2])
    with pytest.raises(ValueError, match="T >= 1"):
        static_dynamic_split(x[:0], x[:0], M[:0])
    for name in ("pred", "gt"):
        bad = x.clone()
        bad[1, 2, 0] = float("nan")
        args = {"pred": x, "gt": x, "transforms": M, name: bad}
        with pytest.raises(ValueError, match=f"`{name}`: contains NaN"):
            static_dynamic_split(**args)
    bad = M.clone()
    bad[0, 0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match="`transforms`: contains NaN"):
        static_dynamic_split(x, x, bad)
    bad = M.clone()
    bad[0, 0, 3, 0] = 0.5  # not affine: a homogeneous solve would silently rescale
    with pytest.raises(ValueError, match="affine"):
        static_dynamic_split(x, x, bad)
    bad = M.clone()
    bad[1, 1, :3, :3] = 0.0
    with pytest.raises(ValueError, match="singular"):
        static_dynamic_split(x, x, bad)


# --------------------------------------------------------------------------- a generated dataset
@pytest.fixture(scope="module")
def chunk(tmp_path_factory):
    """One whole sequence (skirt on a capsule body, walk, 8 frames; LBS + a wobble as
    the 'simulation') as a GarmentInputs, read as benchmarks/experiments/error_split.py reads it."""
    out = skirt_dataset(tmp_path_factory.mktemp("split"), ["walk"], 8, name="s")
    ds = SequenceChunks(out, split=None, chunk=10 ** 9, history=1, nystrom_dim=4,
                        num_landmarks=8)
    return ds[0]


def test_skinning_transforms_pose_the_rest_garment_as_skinned(chunk):
    M = chunk.skinning_transforms()
    T, V = chunk.gt.shape[:2]
    assert M.shape == (T, V, 4, 4) and M.dtype == torch.float64
    torch.testing.assert_close(posed(M, chunk.rest_pos).float(), chunk.skinned(),
                               atol=1e-5, rtol=0)
    # a float32 copy agrees too; the bottom row is [0, 0, 0, 1]
    torch.testing.assert_close(chunk.skinning_transforms(torch.float32), M.float(),
                               atol=1e-5, rtol=0)
    torch.testing.assert_close(M[..., 3, :], torch.tensor([0., 0, 0, 1], dtype=M.dtype)
                               .expand(T, V, 4))


def test_split_inputs_on_a_generated_sequence(chunk):
    lbs = chunk.skinned()
    got = split_inputs(lbs, chunk)
    close(got, oracle(lbs, chunk.gt, chunk.skinning_transforms()), tol=1e-6)
    # the 'simulation' is LBS + 3 mm * sin(.) on each axis: E_dist <= 0.3 sqrt(3) cm;
    # the wobble has a part that stays put in the skinned frame and a part that does not
    assert 0 < got["E_dist"] <= 0.3 * math.sqrt(3) + 1e-6
    assert got["E_static"] > 0.01 and got["E_dynamic"] > 0.01
    close(split_inputs(chunk.gt, chunk), {"E_static": 0.0, "E_dynamic": 0.0, "E_dist": 0.0})
    with pytest.raises(ValueError, match="ground truth"):
        split_inputs(lbs, chunk.without_ground_truth())
