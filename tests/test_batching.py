"""Batched training steps: chunks of several garments (different vertex counts) collated as
one PyG ``Batch``; the batch's loss and gradients against each chunk on its own, a batch of
one chunk against the plain chunk step by step, the data module's batches and its
``--data.batch_size`` checks."""
import gc
import weakref

import lightning as L
import pytest
import torch

from garmentgnn.data import Spec, generate
from garmentgnn.models import PAPER_FORM, blocks
from garmentgnn.models.inputs import GarmentInputs
from garmentgnn.nn.functional import csr_kernels
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (EpochShuffleSampler, GarmentDataModule)
from garmentgnn.sim.stand_in import skinned_wobble
from recipe_helpers import module as recipe_module


NY = 8


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """Two garments of different vertex counts on one body, three motions of 10 frames
    (chunks of 4: two of 4 frames and one of 2 per sequence)."""
    out = tmp_path_factory.mktemp("mixed")
    g = [{"kind": "skirt", "params": {"length": "mini"}, "resolution": 200},
         {"kind": "tshirt", "params": {}, "resolution": 300}]
    b = [{"model": "capsule", "shape": "regular"}]
    m = [{"name": n, "num_frames": 10, "speed": 1.0, "amplitude": 1.0}
         for n in ("walk", "run", "jump")]
    spec = Spec("mixed", g, b, m, ["silk"], held_out={})
    s = generate(spec, out, workers=0, simulate_fn=skinned_wobble, progress=False)
    assert s.failed == 0 and s.done == 6
    return out


DATA = {"chunk": 4, "history": 2, "nystrom_dim": NY, "num_landmarks": 16, "seed": 0,
        "val_split": None, "train_split": "train"}


def data(root, **kw):
    return GarmentDataModule(root, **dict(DATA, **kw))


@pytest.fixture(scope="module")
def chunks(root):
    return SequenceChunks(root, "train", chunk=4, history=2, nystrom_dim=NY, num_landmarks=16)


def gartrans(root, **kw):
    return recipe_module("gartrans", root, DATA, **{f"model.model.{k}": v for k, v in kw.items()})


def pick(chunks):
    """Three chunks of 4 frames, of at least two garments (vertex counts)."""
    full = [i for i, n in enumerate(chunks.frame_counts()) if n == 4]
    by_size = {}
    for i in full:
        by_size.setdefault(chunks[i].num_vertices, []).append(i)
    assert len(by_size) == 2, by_size
    a, b = by_size.values()
    return [a[0], b[0], a[1]]


def test_batch_of_mixed_garments_collates_as_one_union_graph(chunks):
    idx = pick(chunks)
    items = [chunks[i] for i in idx]
    batch = chunks[idx]
    V = [it.num_vertices for it in items]
    assert len(set(V)) == 2 and batch.num_chunks == 3 and batch.num_frames == 4
    assert batch.num_vertices == sum(V) and batch.gt.shape == (4, sum(V), 3)
    assert batch.rotations.shape == (3,) + tuple(items[0].rotations.shape)
    Vb = items[0].body_pos.shape[1]
    assert batch.body_pos.shape == (4, 3 * Vb, 3)
    # each chunk comes back whole: faces and body faces offset and undone
    for it, back in zip(items, batch.chunks()):
        for k in ("rest_pos", "faces", "edge_index", "gt", "body_pos", "body_faces",
                  "rotations", "face_uv", "skin_weights"):
            if k in it:
                assert torch.equal(it[k], back[k]), k
    # the union's faces index each garment's own vertices
    F0 = items[0].faces.shape[0]
    assert torch.equal(batch.faces[F0:F0 + items[1].faces.shape[0]], items[1].faces + V[0])


def test_collate_refuses_what_one_batch_cannot_hold(chunks):
    n = chunks.frame_counts()
    four, two = n.index(4), n.index(2)
    with pytest.raises(ValueError, match="`items`.*same frame count"):
        GarmentInputs.collate([chunks[four], chunks[two]])
    with pytest.raises(TypeError, match="`items`"):
        GarmentInputs.collate([])


@pytest.mark.parametrize("form", ["project", "paper"])
def test_batch_loss_and_gradients_are_the_mean_of_each_chunk_alone(root, chunks, form):
    """The oracle: each chunk's loss on its own, averaged; the batch's gradient is the
    mean of the chunks' gradients."""
    kw = {} if form == "project" else dict(PAPER_FORM)
    module = gartrans(root, **kw).eval()  # eval: the normalisers stay fixed
    module.loss_fn.set_enabled(["vert", "edge", "norm", "collision", "gravity", "stretch",
                                "shear", "curv"])
    idx = pick(chunks)
    batch = chunks[idx]

    def grads(loss):
        module.zero_grad()
        loss.backward()
        return {n: p.grad.clone() for n, p in module.named_parameters() if p.grad is not None}

    total, terms = module.compute_loss(batch, module(batch))
    g_batch = grads(total)
    singles = [module.compute_loss(chunks[i], module(chunks[i])) for i in idx]
    mean = sum(t for t, _ in singles) / 3
    torch.testing.assert_close(total, mean, rtol=1e-5, atol=1e-6)
    for k in terms:
        torch.testing.assert_close(terms[k], sum(t[k] for _, t in singles) / 3, rtol=1e-5,
                                   atol=1e-6)
    g_single = grads(sum(t for t, _ in [module.compute_loss(chunks[i], module(chunks[i]))
                                        for i in idx]) / 3)
    assert g_batch.keys() == g_single.keys() and len(g_batch) > 10
    for n in g_batch:
        scale = float(g_single[n].abs().max()) + 1e-8
        assert float((g_batch[n] - g_single[n]).abs().max()) <= 1e-4 * scale + 1e-7, n


def test_da_style_batch_is_each_chunk_alone(root, chunks):
    """DA-style predicts a batch in one pass over the union graph: the same positions as
    each chunk alone, and the mean of their losses."""
    module = recipe_module("baselines/da", root, DATA).eval()
    idx = pick(chunks)
    batch = chunks[idx]
    with torch.no_grad():
        pred = module(batch)
        v0 = 0
        for i in idx:
            one = module(chunks[i])
            torch.testing.assert_close(pred[:, v0:v0 + one.shape[1]], one, atol=1e-5, rtol=0)
            v0 += one.shape[1]
        total, _ = module.compute_loss(batch)
        mean = sum(module.compute_loss(chunks[i])[0] for i in idx) / 3
    torch.testing.assert_close(total, mean, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("several", [False, True])
def test_da_style_compiled_training_matches_eager(root, chunks, several):
    """DA-style's ``compile`` (its network through torch.compile while training) gives
    eager's loss and gradients, on a batch of one chunk (one graph) and of three:
    relative 1e-4 on the loss, 1e-4 of each gradient's largest entry."""
    compiled = recipe_module("baselines/da", root, DATA, **{"model.model.compile": True})
    assert compiled.model.compile
    eager = recipe_module("baselines/da", root, DATA, **{"model.model.compile": False})
    eager.load_state_dict(compiled.state_dict())
    idx = pick(chunks) if several else pick(chunks)[:1]
    batch = chunks[idx]
    out = []
    for module in (compiled, eager):
        total, _ = module.compute_loss(batch)
        grads = torch.autograd.grad(total, [p for p in module.parameters() if p.requires_grad])
        out.append((total.detach(), grads))
    assert not blocks._COMPILE_FAILED and compiled.model in blocks._COMPILED
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-4, atol=0)
    for g, ref in zip(out[0][1], out[1][1]):
        torch.testing.assert_close(g, ref, rtol=0, atol=1e-4 * float(ref.abs().max()) + 1e-12)


def test_compiled_forward_lets_the_module_go():
    """``compiled_forward`` keeps its compiled function per module in a weak-keyed table;
    the function must not hold the module (a bound method would), or every model ever
    compiled stays in memory with its compiled code."""
    class Net(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.lin = torch.nn.Linear(4, 4)

        def forward(self, x):
            return self.lin(x).relu()

        def twice(self, x):
            return 2 * self.forward(x)

    for method in ("forward", "twice"):
        net = Net()
        x = torch.randn(3, 4, requires_grad=True)
        y = blocks.compiled_forward(net, x, method=method)
        assert not blocks._COMPILE_FAILED and net in blocks._COMPILED
        torch.testing.assert_close(y, getattr(net, method)(x))
        alive = weakref.ref(net)
        del net, y
        gc.collect()
        assert alive() is None


def test_da_style_compiles_by_default_on_one_cpu_thread_only(root, chunks):
    """``compile=None`` (the recipe's default): eager with two torch threads, compiled
    with one (where it was measured faster), decided at every training call."""
    module = recipe_module("baselines/da", root, DATA)
    assert module.model.compile is None
    batch = chunks[pick(chunks)[:1]]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        module.compute_loss(batch)
        assert module.model not in blocks._COMPILED
        torch.set_num_threads(1)
        module.compute_loss(batch)
        assert module.model in blocks._COMPILED
    finally:
        torch.set_num_threads(threads)


def test_batch_of_one_chunk_trains_as_the_chunk_itself(root, chunks):
    """Same chunk order, one chunk per step: the plain chunk and a ``Batch`` holding it
    give the same loss trajectory (Adamax, 6 steps, training-mode normalisers)."""
    losses = {}
    for mode in ("plain", "batch"):
        module = gartrans(root).train()
        opt = module.configure_optimizers()["optimizer"]
        out = []
        for step in range(6):
            item = chunks[step % len(chunks)]
            if mode == "batch":
                item = GarmentInputs.collate([item])
            loss, _ = module.compute_loss(item, module(item))
            opt.zero_grad()
            loss.backward()
            opt.step()
            out.append(float(loss))
        losses[mode] = out
    assert max(abs(a - b) for a, b in zip(*losses.values())) <= 1e-6 * max(losses["plain"])


def test_sampler_batches_each_chunk_once_with_one_frame_count(chunks):
    lengths = chunks.frame_counts()
    s = EpochShuffleSampler(len(chunks), seed=3, batch_size=4, lengths=lengths)
    for epoch in (0, 1):
        s.set_epoch(epoch)
        batches = list(s)
        assert len(batches) == len(s)
        flat = [i for b in batches for i in b]
        assert sorted(flat) == list(range(len(chunks)))  # each chunk once
        assert all(len({lengths[i] for i in b}) == 1 for b in batches)
        assert all(len(b) <= 4 for b in batches)
        assert sum(len(b) == 4 for b in batches) >= len(chunks) // 4 - 1
        s.set_epoch(epoch)
        assert list(s) == batches  # the order of an epoch depends on the epoch alone
    one = EpochShuffleSampler(len(chunks), seed=3)
    assert all(isinstance(i, int) for i in one)


@pytest.mark.parametrize("bad", [0, -2, True, 1.5])
def test_batch_size_flag_refuses_nonsense(root, bad):
    with pytest.raises(ValueError, match="--data.batch_size"):
        data(root, batch_size=bad)


def test_batch_size_larger_than_the_split_is_refused(root, chunks):
    with pytest.raises(ValueError, match=f"--data.batch_size.*at most {len(chunks)}"):
        data(root, batch_size=len(chunks) + 1).setup("fit")


@pytest.mark.slow
def test_every_method_fits_batched_through_the_trainer(root):
    """GarTrans and the three baselines take the same batched steps through Lightning."""
    modules = [gartrans(root)] + [recipe_module(f"baselines/{method}", root, DATA)
                                  for method in ("da", "hood")]
    for module in modules:
        before = {n: p.detach().clone() for n, p in module.named_parameters()
                  if p.requires_grad}
        tr = L.Trainer(max_steps=3, accelerator="cpu", devices=1, logger=False,
                       enable_checkpointing=False, enable_progress_bar=False,
                       enable_model_summary=False, limit_val_batches=0)
        tr.fit(module, datamodule=data(root, batch_size=4))
        assert tr.global_step == 3
        moved = [n for n, p in module.named_parameters() if n in before
                 and not torch.equal(p.detach(), before[n])]
        assert moved, type(module).__name__


@pytest.mark.parametrize("method", ["gartrans", "baselines/da", "baselines/hood"])
@pytest.mark.parametrize("several", [True, False], ids=["batch", "one-chunk"])
def test_bf16_autocast_keeps_positions_and_loss_in_float32(root, chunks, method, several):
    """Under ``torch.autocast(bfloat16)`` the networks run in bfloat16 while the
    kinematics, skinning, post-steps, HOOD's integration and the loss stay float32: the
    prediction is float32 and within 1 mm of the float32 run's, the loss within 3e-3 of it
    (relative: under bfloat16's own 2^-8 = 3.9e-3 a rounding; the loss moved by 1.2-1.4e-3
    with the weights of seed 0 since the layers' construction stopped drawing random
    numbers). The bug it guards against is orders of magnitude larger: bfloat16 positions
    are ~4 mm off at 1 m, GarTrans's and HOOD-style's steps raised on the mixed dtypes and
    DA-style's loss moved by up to 3x its value."""
    module = recipe_module(method, root, DATA).eval()
    idx = pick(chunks)
    batch = chunks[idx] if several else chunks[idx[0]]

    def run():
        if method == "gartrans":
            out = module.model(batch)
            return out["final"], module.compute_loss(batch, out)[0]
        if method == "baselines/hood":  # one garment at a time
            pred = torch.cat([module(c) for c in batch.chunks()], 1)
        else:
            pred = module(batch)
        return pred, module.compute_loss(batch)[0]

    with torch.no_grad():
        pred, loss = run()
        with torch.autocast("cpu", dtype=torch.bfloat16):
            pred16, loss16 = run()
    assert pred.dtype == pred16.dtype == loss16.dtype == torch.float32
    assert (pred16 - pred).abs().max() < 1e-3
    assert abs(float(loss16) / float(loss) - 1) < 3e-3


def test_bucket_sizes_are_few_and_above_the_size():
    """Every size ``n`` pads to a bucket above it (room for a padding node), a multiple of
    64, at most 19% above ``n`` past the first bucket, and a doubling of ``n`` spans at
    most five buckets."""
    sizes = [blocks.bucket(n) for n in range(0, 40000, 7)]
    assert all(b > n and b % 64 == 0 for n, b in zip(range(0, 40000, 7), sizes))
    assert all(b <= 1.19 * n + 64 for n, b in zip(range(0, 40000, 7), sizes) if n > 256)
    assert len({blocks.bucket(n) for n in range(10000, 20000)}) <= 5
    assert sizes == sorted(sizes)
    with pytest.raises(ValueError, match="`n`"):
        blocks.bucket(-1)


@pytest.mark.parametrize("kernels", [True, False])
@pytest.mark.parametrize("shuffle", [False, True])
def test_padding_the_graph_changes_no_real_output(chunks, kernels, shuffle):
    """The dynamic stack's layers (SAT) on a garment graph padded to bucket sizes
    (:func:`~garmentgnn.models.blocks.pad_graph`): the real vertices' outputs and the
    gradients of a loss on them (parameters and inputs) are the unpadded graph's, on the
    sparse kernels and on the message route, edges in CSR order or shuffled.  Oracle:
    the same stack on the unpadded graph, float64."""
    torch.manual_seed(0)
    stack = blocks.AttentionStack("sat", 5, [16, 16, 3], 4, 4, "elu", last_act=False).double()
    ei = chunks[0].edge_index
    if shuffle:
        ei = ei[:, torch.randperm(ei.size(1))]
    x = torch.randn(chunks[0].num_vertices, 5, dtype=torch.float64, requires_grad=True)
    e = torch.randn(ei.size(1), 4, dtype=torch.float64, requires_grad=True)
    w = torch.randn(x.size(0), 3, dtype=torch.float64)
    params = [p for p in stack.parameters() if p.requires_grad]
    res = []
    with csr_kernels(kernels):
        for padded in (False, True):
            args = blocks.pad_graph(x, ei, e) if padded else (x, ei, e)
            if padded:
                assert args[0].size(0) > x.size(0) and args[1].size(1) >= ei.size(1)
            out = stack(*args)[:x.size(0)]
            res.append((out, torch.autograd.grad((out * w).sum(), params + [x, e])))
    torch.testing.assert_close(res[1][0], res[0][0], rtol=1e-12, atol=1e-12)
    for g, ref in zip(res[1][1], res[0][1]):
        torch.testing.assert_close(g, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.slow
def test_gartrans_compiled_padded_stack_matches_eager(root, chunks):
    """``compile_stack`` (the dynamic stack compiled with static shapes on its graph
    padded to bucket sizes, while training) gives eager's loss and gradients on a batch
    of three chunks of two garments: relative 1e-4 on the loss, 1e-4 of each gradient's
    largest entry plus 1e-6 of the largest of all (float32); an unknown
    ``compile_stack`` is refused."""
    compiled = gartrans(root, compile_stack="default")
    eager = gartrans(root)
    eager.load_state_dict(compiled.state_dict())
    batch = chunks[pick(chunks)]
    out = []
    for module in (compiled, eager):
        total, _ = module.compute_loss(batch, module(batch))
        grads = torch.autograd.grad(total, [p for p in module.parameters() if p.requires_grad],
                                    allow_unused=True)
        out.append((total.detach(), grads))
    assert not blocks._COMPILE_FAILED and compiled.model.dynamic in blocks._COMPILED
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-4, atol=0)
    # float32 round-off of the whole gradient bounds the nearly-zero ones (~1e-12 here)
    floor = 1e-6 * max(float(r.abs().max()) for r in out[1][1] if r is not None)
    for g, ref in zip(out[0][1], out[1][1]):
        if ref is None:
            assert g is None
            continue
        torch.testing.assert_close(g, ref, rtol=0, atol=1e-4 * float(ref.abs().max()) + floor)
    with pytest.raises(ValueError, match="`compile_stack`"):
        gartrans(root, compile_stack="fast")
