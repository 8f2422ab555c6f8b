"""GarTrans at other sizes (``width``, ``depth``: factors of its default widths and
layer counts), and :func:`garmentgnn.models.blocks.sized`, the rule behind them.
Oracles: the widths worked out by hand, and the default model's own weights."""
import pytest
import torch

from garmentgnn.models import GarTrans
from garmentgnn.models.blocks import sized


def test_sized_by_hand():
    dyn = [32, 64, 64, 64, 32, 3]
    assert sized(dyn, keep_last=True) == dyn and sized([64, 64, 128]) == [64, 64, 128]
    assert sized(dyn, 0.5, 0.5, keep_last=True) == [16, 32, 3]  # hidden 32, 64 (of 5: 2)
    assert sized(dyn, 2, 2, keep_last=True) == [64, 64, 128, 128, 128, 128, 128, 128,
                                                 64, 64, 3]
    assert sized([64, 64, 128], 0.5, 0.5) == [32, 64]  # the last (not an output) halved too
    assert sized([8], 3, 2) == [24]  # no hidden layer: none added


def test_default_size_is_the_model_as_before():
    torch.manual_seed(0)
    a = GarTrans(24, 100).state_dict()
    torch.manual_seed(0)
    b = GarTrans(24, 100, width=1.0, depth=1.0).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("width,depth", [(0.5, 0.5), (2, 2), (2, 1)])
def test_width_and_depth_scale_the_stacks(width, depth):
    m, base = GarTrans(24, 100, width=width, depth=depth), GarTrans(24, 100)
    assert len(m.dynamic.layers) - 1 == max(1, round(5 * depth))  # hidden + the output
    assert len(m.rest_attn.layers) == max(1, round(2 * depth)) + 1
    assert m.gru.hidden_size == round(128 * width)
    assert m.gru.num_layers == max(1, round(2 * depth))
    assert m.rest_attn.out_channels == round(128 * width)
    assert m.dynamic.out_channels == 3 and m.body_default.shape == (round(128 * width), 24)
    n, n0 = (sum(p.numel() for p in x.parameters()) for x in (m, base))
    assert (n > n0) == (width > 1)


@pytest.mark.parametrize("bad", [0, -1, float("nan"), True, "2"])
def test_bad_sizes_name_the_argument(bad):
    for name in ("width", "depth"):
        with pytest.raises(ValueError, match=f"`{name}`"):
            GarTrans(24, 100, **{name: bad})
