"""The cached nearest-body-face search (``NearestFaceCache``) against the exact brute force.

Oracle: :func:`garmentgnn.geometry.signed_distance` with ``candidates=None`` (every body
face evaluated; itself checked against trimesh in test_geometry_distance.py) on a real
scene: a t-shirt skinned to a capsule body walking, with a smooth wobble, over
consecutive frames.  Faces are compared up to exact ties (a point nearest to an edge or
a corner shared by several faces: the faces differ, the distance, closest point and
normal do not).  A search that skips the bound (the candidates trusted blindly) is
shown to go wrong on the same motions, so the comparisons can fail.
"""
import pytest
import torch

from garmentgnn import geometry as G
from garmentgnn.body import CapsuleBodyModel
from garmentgnn.garments import make_garment
from garmentgnn.geometry import face_cache as fc_mod
from garmentgnn.motion import make_motion
from garmentgnn.sim.stand_in import wobbling_frames

D = torch.float64


@pytest.fixture(scope="module")
def walk():
    """``(garment [T, V, 3], body [T, Vb, 3], body faces)``: 12 frames of a walk at 30 fps,
    the t-shirt skinned to the body plus a 3 mm wobble (float64)."""
    body = CapsuleBodyModel(resolution=6)("regular")
    g = make_garment("tshirt", body, resolution=250)
    m = make_motion("walk", body.skeleton, num_frames=12, fps=30.0, seed=0,
                    rest_joints=body.joints)
    P, X = wobbling_frames(g, body, m, D)
    return P, X, body.faces


def assert_exact(out: G.SignedDistance, P, X, F):
    """``out`` is the brute force's result: same distance, closest point and normal; the
    same face except where another face is exactly as near."""
    ref = G.signed_distance(P, X, F, candidates=None)
    torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.closest, ref.closest, rtol=0, atol=1e-9)
    torch.testing.assert_close(out.normal, ref.normal, rtol=0, atol=1e-9)
    differ = out.face != ref.face
    assert int(differ.sum()) <= 0.01 * differ.numel()  # ties only: rare
    return ref


def test_cached_search_equals_brute_force_over_a_walk(walk):
    P, X, F = walk
    B = 8
    cache = G.NearestFaceCache()
    out = G.signed_distance(P[:B], X[:B], F, cache=cache)
    ref = assert_exact(out, P[:B], X[:B], F)
    assert cache.stats.rebuilt == B * P.size(1) and cache.stats.refreshed == 0
    # the candidates' bound: every other face is at least that far
    assert bool((cache._bound > ref.distance.abs()).all())
    # the garment moves a little (the next training step, the loss after the projection)
    g = torch.Generator().manual_seed(0)
    Q = P[:B] + 1e-3 * torch.randn(P[:B].shape, generator=g, dtype=D)
    searched = cache.stats.searched
    assert_exact(G.signed_distance(Q, X[:B], F, cache=cache), Q, X[:B], F)
    assert cache.stats.searched - searched < 0.05 * B * P.size(1)  # served from the cache
    # the collision projection, then the loss on the projected garment: one cache
    pushed = G.push_outside(Q, X[:B], F, 0.002, cache=cache)
    torch.testing.assert_close(pushed, G.push_outside(Q, X[:B], F, 0.002, candidates=None),
                               rtol=0, atol=1e-12)
    assert_exact(G.signed_distance(pushed, X[:B], F, cache=cache), pushed, X[:B], F)
    assert cache.stats.calls == 4


def test_large_motion_refreshes_and_stays_exact(walk):
    """The next chunk of the walk (the body moved 4-16 cm a frame), a few points thrown
    10 cm, a chunk seeded from its first frame: the bound refuses the candidates, the
    points are searched again, the result stays the brute force's."""
    P, X, F = walk
    V = P.size(1)
    cache = G.NearestFaceCache()
    G.signed_distance(P[:4], X[:4], F, cache=cache)
    before = cache.stats.searched
    assert_exact(G.signed_distance(P[4:8], X[4:8], F, cache=cache), P[4:8], X[4:8], F)
    assert cache.stats.searched - before > 0.5 * 4 * V  # refreshed or rebuilt
    # same body, a tenth of the points moved 10 cm: only (about) those are searched again
    Q = P[4:8].clone()
    moved = torch.zeros(4, V, dtype=torch.bool)
    moved[:, ::10] = True
    Q[moved] += torch.tensor([0.08, -0.05, 0.04], dtype=D)
    refreshed = cache.stats.refreshed
    assert_exact(G.signed_distance(Q, X[4:8], F, cache=cache), Q, X[4:8], F)
    n = cache.stats.refreshed - refreshed
    assert 0.5 * int(moved.sum()) <= n <= 2 * int(moved.sum())
    # built on one frame, serving the chunk from it
    seeded = G.NearestFaceCache()
    G.signed_distance(P[:1], X[:1], F, cache=seeded)
    assert_exact(G.signed_distance(P[:6], X[:6], F, cache=seeded), P[:6], X[:6], F)
    assert seeded.stats.searched > V  # the later frames moved beyond the bound
    # frame by frame along the walk
    seq = G.NearestFaceCache(k=16)
    for i in range(P.size(0)):
        assert_exact(G.signed_distance(P[i], X[i], F, cache=seq), P[i], X[i], F)


def test_the_bound_is_what_keeps_it_exact(walk, monkeypatch):
    """Trusting the candidates without the bound gives wrong faces on the same motions
    (so the comparisons above can fail); a cache whose bound was inflated by 1 m is
    wrong too, and one left stale by motion but with its true bound is refreshed."""
    P, X, F = walk
    real = fc_mod._certify

    def blind(*args):
        fid, slack, t, beta = real(*args)
        return fid, torch.full_like(slack, float("inf")), t, beta

    ref = G.signed_distance(P[8:12], X[8:12], F, candidates=None)
    cache = G.NearestFaceCache(k=4)
    G.signed_distance(P[:4], X[:4], F, cache=cache)
    monkeypatch.setattr(fc_mod, "_certify", blind)
    stale = G.signed_distance(P[8:12], X[8:12], F, cache=cache)
    assert int(((stale.distance - ref.distance).abs() > 1e-6).sum()) >= 5
    monkeypatch.setattr(fc_mod, "_certify", real)
    inflated = G.NearestFaceCache(k=4)
    G.signed_distance(P[:4], X[:4], F, cache=inflated)
    inflated._bound += 1.0
    wrong = G.signed_distance(P[8:12], X[8:12], F, cache=inflated)
    assert int(((wrong.distance - ref.distance).abs() > 1e-6).sum()) >= 5
    honest = G.NearestFaceCache(k=4)
    G.signed_distance(P[:4], X[:4], F, cache=honest)
    assert_exact(G.signed_distance(P[8:12], X[8:12], F, cache=honest), P[8:12], X[8:12], F)
    assert honest.stats.searched > 4 * P.size(1)


def test_gradients_match_the_uncached_search(walk):
    P, X, F = walk
    p0, x0 = P[2:4].clone(), X[2:4].clone()
    cache = G.NearestFaceCache()
    G.signed_distance(p0, x0, F, cache=cache)  # warm: the gradient pass uses the cache
    grads = []
    for kw in ({"candidates": None}, {"cache": cache}):
        p, x = p0.clone().requires_grad_(True), x0.clone().requires_grad_(True)
        sd = G.signed_distance(p, x, F, **kw)
        push = G.push_outside(p, x, F, 0.004, **kw)
        loss = (sd.distance.sin().sum() + (sd.closest ** 2).sum() + (push ** 3).sum())
        grads.append(torch.autograd.grad(loss, (p, x)))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)
    assert cache.stats.rebuilt == 2 * P.size(1)  # built once, then served


def test_cache_rebuilds_on_new_shapes_and_faces(walk):
    P, X, F = walk
    V = P.size(1)
    cache = G.NearestFaceCache(k=12, search=12)
    cache.nearest(P[:2], X[:2], F)
    assert cache.stats.rebuilt == 2 * V
    fid = cache.nearest(P[0], X[0], F)  # one frame: [V]
    assert fid.shape == (V,) and cache.stats.rebuilt == 3 * V
    cache.nearest(P[0, :100], X[0], F)  # other vertices
    assert cache.stats.rebuilt == 3 * V + 100
    flipped = F[:, [0, 2, 1]].clone()  # equal shape, other faces
    out = cache.nearest(P[0, :100], X[0], flipped)
    assert cache.stats.rebuilt == 3 * V + 200
    assert torch.equal(out, G.signed_distance(P[0, :100], X[0], flipped).face)
    cache.nearest(P[0, :100], X[0], flipped.clone())  # equal content: kept
    assert cache.stats.rebuilt == 3 * V + 200
    cache.reset()
    cache.nearest(P[0, :100], X[0], flipped)
    assert cache.stats.rebuilt == 3 * V + 300
    # float32 works as well (the rounding allowance scales with the dtype)
    c32 = G.NearestFaceCache()
    out = G.signed_distance(P[:2].float(), X[:2].float(), F, cache=c32)
    ref = G.signed_distance(P[:2].float(), X[:2].float(), F, candidates=None)
    torch.testing.assert_close(out.distance, ref.distance, rtol=0, atol=1e-6)


def test_small_bodies_and_bad_arguments():
    """Fewer faces than ``k``: every face is a candidate (no bound needed)."""
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.2, -0.5]], dtype=D)
    tri = torch.tensor([[-1.0, -1, 0], [1, -1, 0], [0, 1, 0], [0, 0, 0.5]], dtype=D)
    faces = torch.tensor([[0, 1, 2], [0, 1, 3]])
    cache = G.NearestFaceCache(k=4)
    for shift in (0.0, 0.5, 3.0):
        out = G.signed_distance(pts + shift, tri, faces, cache=cache)
        ref = G.signed_distance(pts + shift, tri, faces, candidates=None)
        assert torch.equal(out.face, ref.face)
    assert cache.stats.searched == 2
    with pytest.raises(ValueError, match="`k`"):
        G.NearestFaceCache(k=0)
    with pytest.raises(ValueError, match="`search`"):
        G.NearestFaceCache(k=8, search=4)
    with pytest.raises(ValueError, match="`rebuild_fraction`"):
        G.NearestFaceCache(rebuild_fraction=1.5)


@pytest.mark.slow
def test_compiled_cache_matches_eager(walk):
    P, X, F = walk
    eager, comp = G.NearestFaceCache(), G.NearestFaceCache(compiled=True)
    for c in (eager, comp):
        c.nearest(P[:4], X[:4], F)
    g = torch.Generator().manual_seed(1)
    Q = P[:4] + 2e-3 * torch.randn(P[:4].shape, generator=g, dtype=D)
    out = G.signed_distance(Q, X[:4], F, cache=comp)
    torch.testing.assert_close(out.distance, G.signed_distance(Q, X[:4], F, cache=eager).distance,
                               rtol=0, atol=1e-12)
    assert_exact(out, Q, X[:4], F)
