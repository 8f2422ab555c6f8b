"""Frames the engine did not converge on are left out of the metrics that read the data
(and counted): the learned methods' scoring and the metric functions' ``keep`` mask."""
import math

import pytest
import torch

from garmentgnn.bench import scoring
from garmentgnn.data import generate, preset
from garmentgnn.metrics import evaluate, evaluate_inputs
from garmentgnn.metrics.split import split_inputs
from garmentgnn.data import SequenceChunks
from garmentgnn.training import (GarTransModule, GarmentDataModule)
from garmentgnn.training.evaluate import evaluate_split
from garmentgnn.models import GarTrans
from garmentgnn.sim.stand_in import skinned_wobble


BAD = (2, 5)  # the frames the double flags as non-converged


def flagged_simulate(garment, body, motion, material, settings=None, progress=None):
    """:func:`garmentgnn.sim.stand_in.skinned_wobble`, with frames ``BAD`` flagged
    non-converged and moved 1 m up: scored, they would dominate every error."""
    res = skinned_wobble(garment, body, motion, material, settings, progress)
    for t in BAD:
        res.positions[t, :, 2] += 1.0
        res.converged[t] = False
    return res


@pytest.fixture(scope="module")
def test_split(tmp_path_factory):
    out = tmp_path_factory.mktemp("nonconv")
    s = generate(preset("tiny"), out, workers=0, simulate_fn=flagged_simulate, progress=False)
    assert s.done == 8
    return SequenceChunks(out, "test", chunk=10 ** 9, history=3, num_landmarks=64, nystrom_dim=16)


def test_sequence_chunks_read_the_flags(test_split, tmp_path):
    keep = test_split.converged(0)
    assert keep.dtype == torch.bool and keep.tolist() == [t not in BAD for t in range(8)]
    assert test_split.valid(0).tolist() == keep.tolist()  # no penetration recorded
    chunks = SequenceChunks(test_split.root, "test", chunk=3, history=3, num_landmarks=64,
                            nystrom_dim=16)
    assert [chunks.converged(i).tolist() for i in range(3)] == \
        [[True, True, False], [True, True, False], [True, True]]
    assert [chunks[i].valid.tolist() for i in range(3)] == \
        [[True, True, False], [True, True, False], [True, True]]


def test_scoring_leaves_them_out(test_split):
    per_seq = scoring.score(lambda i, item: item.skinned(), test_split)
    assert len(per_seq) == len(test_split) == 4
    for i, s in enumerate(per_seq):
        item = test_split[i]
        keep = torch.tensor([t not in BAD for t in range(8)])
        assert s["frames"] == 6 and s["excluded_frames"] == 2
        # oracle: the metric functions on the kept frames alone
        want = evaluate(item.skinned()[keep].float(), item.gt[keep], item.faces,
                        item.body_pos[keep], item.body_faces)
        for k, v in want.items():
            got = s["metrics"]["collision_rate" if k == "collision" else k]
            assert got == pytest.approx(v, rel=1e-6, abs=1e-9), k
        # the flagged frames are 1 m off: with them E_dist would be > 25 cm
        assert evaluate_inputs(item.skinned(), item)["E_dist"] > 25.0 > s["metrics"]["E_dist"]
    agg = scoring.aggregate(per_seq)["all"]
    assert math.isfinite(agg["E_dist"])


def test_keep_is_checked(test_split):
    item = test_split[0]
    pred = item.skinned()
    for bad in (torch.ones(7, dtype=torch.bool), torch.ones(8), torch.zeros(8, dtype=torch.bool)):
        with pytest.raises(ValueError, match="keep"):
            evaluate_inputs(pred, item, bad)
        with pytest.raises(ValueError, match="keep"):
            split_inputs(pred, item, bad)
    everything = torch.ones(8, dtype=torch.bool)
    assert evaluate_inputs(pred, item, everything) == evaluate_inputs(pred, item)
    assert split_inputs(pred, item, everything) == split_inputs(pred, item)


def test_evaluate_split_leaves_them_out(test_split):
    dm = GarmentDataModule(test_split.root, chunk=4, history=3, nystrom_dim=16,
                           num_landmarks=64, val_split=None)
    module = GarTransModule(GarTrans(**dm.model_sizes(GarTrans)))
    res = evaluate_split(module, test_split.root, "test", modes=("lbs",), history=3,
                         num_landmarks=64)["lbs"]
    assert res["frames"] == 4 * 6 and res["excluded_frames"] == 4 * 2
    want = scoring.aggregate(scoring.score(lambda i, item: item.skinned(), test_split))["all"]
    assert res["E_dist"] == pytest.approx(want["E_dist"], rel=1e-6) and res["E_dist"] < 25.0


def test_train_test_step_leaves_them_out(test_split):
    """``garmentgnn train test``'s step (:class:`GarmentModule`) scores the chunk's
    converged frames only, for the method and for LBS: the metric functions on those
    frames alone are the oracle, and a chunk of non-converged frames only is not scored."""
    chunks = SequenceChunks(test_split.root, "test", chunk=3, history=3, num_landmarks=64,
                            nystrom_dim=16)
    item = chunks[0]  # frames 0, 1, 2: frame 2 flagged
    assert item.converged.tolist() == [True, True, False]
    module = GarTransModule(GarTrans(num_joints=item.rotations.shape[2],
                                     num_body_vertices=item.body_pos.shape[1], nystrom_dim=16))
    module.log = lambda *a, **k: None  # outside a Trainer
    with torch.no_grad():
        got = module.test_step(item, 0)
        pred = module.predict_garment(item)
    keep = torch.tensor([True, True, False])
    want = evaluate(pred[keep].float(), item.gt[keep], item.faces, item.body_pos[keep],
                    item.body_faces)
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-5, abs=1e-9), k
    assert got["E_dist"] < 25.0  # the flagged frame is 1 m off
    only_bad = SequenceChunks(test_split.root, "test", chunk=1, history=3, num_landmarks=64,
                              nystrom_dim=16)[2]  # frame 2 alone
    assert only_bad.valid.tolist() == [False]
    assert module._score(only_bad.gt, only_bad, "test") == {}
