"""Learning diagnostics: does every branch of a model learn from the first step on?

:func:`branch_gradients` runs one training loss of a LightningModule (GarTrans or a
baseline) on one batch, back-propagates it, and reports per *branch* -- each direct child
module of ``module.model`` and each parameter held by ``module.model`` itself (e.g.
GarTrans's ``gates``) -- how many trainable parameters it has, how many of them received a
non-zero gradient, and the gradient's norm.  A branch whose trainable parameters all get an
exactly zero gradient cannot move under any first-order optimizer until something else
moves first (a zero-initialised multiplicative gate in front of it, a dead activation).
``benchmarks/learning.py`` prints this table for every method; the tests require every
active branch to get a gradient.
"""
from __future__ import annotations

from typing import Any, Dict, List

import lightning as L
import torch
from torch import nn

__all__ = ["branch_gradients", "dead_branches", "training_loss"]


def training_loss(module: L.LightningModule, batch: Any) -> torch.Tensor:
    """The total loss of one training step of ``module`` on ``batch`` (its
    ``training_loss``, the method protocol of
    :class:`~garmentgnn.training.GarmentModule`)."""
    return module.training_loss(batch)


def _branches(model: nn.Module) -> Dict[str, List[nn.Parameter]]:
    out: Dict[str, List[nn.Parameter]] = {}
    for name, p in model.named_parameters(recurse=False):
        out[name] = [p]
    for name, child in model.named_children():
        params = list(child.parameters())
        if params:
            out[name] = params
    return out


def branch_gradients(module: L.LightningModule, batch: Any) -> Dict[str, Dict[str, Any]]:
    """Per branch of ``module.model``: ``trainable`` (parameter tensors that require a
    gradient), ``with_grad`` (those whose gradient has a non-zero entry), ``norm`` (the
    gradient's L2 norm over the branch) after one backward pass of the training loss on
    ``batch``.  Gradients are cleared before and after; the weights are not changed."""
    if not isinstance(getattr(module, "model", None), nn.Module):
        raise TypeError(f"`module`: expected a LightningModule with a `model` attribute, got "
                        f"{type(module).__name__}")
    module.zero_grad(set_to_none=True)
    module.train()
    loss = training_loss(module, batch)
    if not torch.isfinite(loss):
        raise FloatingPointError(f"the training loss is {float(loss)} at step 0")
    loss.backward()
    report: Dict[str, Dict[str, Any]] = {}
    for name, params in _branches(module.model).items():
        live = [p for p in params if p.requires_grad]
        grads = [p.grad for p in live if p.grad is not None]
        norm = float(torch.sqrt(sum((g.double() ** 2).sum() for g in grads))) if grads else 0.0
        report[name] = {"trainable": len(live),
                        "with_grad": sum(int(bool((g != 0).any())) for g in grads),
                        "norm": norm}
    module.zero_grad(set_to_none=True)
    return report


def dead_branches(report: Dict[str, Dict[str, Any]]) -> List[str]:
    """The branches of a :func:`branch_gradients` report that have trainable parameters
    but received no gradient at all."""
    return [k for k, r in report.items() if r["trainable"] and r["with_grad"] == 0]
