import os

import torch_geometric.typing


def test_scatter_backend_matches_request():
    """`make test` runs the suite twice: once with torch-scatter, once hiding it."""
    hidden = os.environ.get("GARMENTGNN_NO_SCATTER") == "1"
    if hidden:
        assert not torch_geometric.typing.WITH_TORCH_SCATTER
    elif os.environ.get("GARMENTGNN_EXPECT_SCATTER") == "1":
        assert torch_geometric.typing.WITH_TORCH_SCATTER, "torch-scatter should be installed"
