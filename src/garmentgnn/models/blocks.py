"""The building blocks of :class:`~garmentgnn.models.GarTrans`: MLPs with the §4.1
geometric initialisation, stacks of registry attention layers, and batched copies of a
garment graph (the frames of one garment as one PyG-style batch); and the running input
normaliser of the HOOD-style baseline; :class:`Configurable`, what lets a trained model be
rebuilt from its checkpoint."""
from __future__ import annotations

import inspect
import math
import warnings
import weakref
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch_geometric.data import Data
from torch_geometric.nn import Linear as PyGLinear
from torch_geometric.transforms import Pad
from torch.nn.parameter import UninitializedParameter
from torch.utils._python_dispatch import _get_current_dispatch_mode

from garmentgnn.nn import TensorCache, make_layer

__all__ = ["AttentionStack", "Configurable", "RunningNormalizer", "batch_edges", "bucket",
           "cached_batch_edges", "check_arguments", "compiled_forward", "freeze_edge_output",
           "geometric_init_",
           "mlp", "pad_graph"]


class Configurable:
    """A model that remembers the arguments it was built with, defaults included:
    :attr:`init_args`, and :meth:`spec` (``{"class_path", "init_args"}``, the form of a
    YAML ``model:`` entry and of LightningCLI's ``class_path``), which a LightningModule
    handed the model saves in its checkpoint so the model can be rebuilt from it."""

    #: the arguments of ``__init__`` the instance was built with (defaults filled in)
    init_args: Dict[str, Any]

    def __new__(cls, *args: Any, **kwargs: Any):
        obj = super().__new__(cls)
        try:
            bound = inspect.signature(cls.__init__).bind(None, *args, **kwargs)
        except TypeError:  # a copy (copy/pickle call __new__ bare): its __dict__ follows
            return obj
        bound.apply_defaults()
        # straight into __dict__: nn.Module's __setattr__ is not ready before __init__
        obj.__dict__["init_args"] = {k: v for k, v in list(bound.arguments.items())[1:]}
        return obj

    def spec(self) -> Dict[str, Any]:
        """``{"class_path": "<module>.<class>", "init_args": {...}}`` of this model."""
        cls = type(self)
        return {"class_path": f"{cls.__module__}.{cls.__qualname__}",
                "init_args": dict(self.init_args)}


#: ``torch.compile`` of each module's forward (kept outside the module: its state dict,
#: copies and pickles stay those of the eager module)
_COMPILED: "weakref.WeakKeyDictionary[nn.Module, Dict[Any, Any]]" = \
    weakref.WeakKeyDictionary()
#: set when compiling failed once: every module runs eager from then on
_COMPILE_FAILED: Dict[str, str] = {}


def compiled_forward(module: nn.Module, *args: Any, mode: Optional[str] = None,
                     dynamic: bool = True, method: str = "forward") -> Any:
    """``module(*args)`` through ``torch.compile(type(module).forward, mode=mode,
    dynamic=dynamic)`` (inductor; built once per module and options, kept while the
    module lives, and not keeping it alive; dynamic shapes by
    default, so that other garments and batch sizes reuse it) while autograd records,
    eager otherwise (evaluation runs the eager module), and eager under a
    ``TorchDispatchMode`` (FLOP and operator counters see the eager operators, and the
    compiled code is not specialised to the mode).  Where compiling fails (no C++
    compiler, an unsupported operator) it warns once and every later call runs eager.
    ``method`` names another method of ``module`` to run so (``module.<method>(*args)``,
    compiled on its own)."""
    eager = module if method == "forward" else getattr(module, method)
    if not torch.is_grad_enabled() or _COMPILE_FAILED or _get_current_dispatch_mode():
        return eager(*args)
    fns = _COMPILED.setdefault(module, {})
    fn = fns.get((method, mode, dynamic))
    if fn is None:  # of the class's function: a bound method would keep the module alive
        fn = fns[(method, mode, dynamic)] = torch.compile(getattr(type(module), method),
                                                          mode=mode, dynamic=dynamic)
    try:
        return fn(module, *args)
    except Exception as err:  # noqa: BLE001 -- any compiler failure: run eager
        _COMPILE_FAILED["error"] = f"{type(err).__name__}: {err}"
        warnings.warn(f"torch.compile of {type(module).__name__} unavailable "
                      f"({_COMPILE_FAILED['error']}); running eager", RuntimeWarning,
                      stacklevel=2)
        return eager(*args)


def bucket(n: int, base: int = 256, growth: float = 2 ** 0.25) -> int:
    """The smallest size ``> n`` of the series ``base * growth^k`` (``k >= 0``, each
    rounded up to a multiple of 64): padded to it, the shapes of any batch fall on a few
    sizes (4 a doubling at the default growth, at most 19% padding) and a compiled graph
    (a CUDA graph) of each serves every batch of its bucket.  Always at least one more
    than ``n``: a padded graph has a padding node for its padding edges to point at."""
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ValueError(f"`n`: expected a size >= 0, got {n!r}")
    k = 0
    while True:
        size = -(-int(math.ceil(base * growth ** k)) // 64) * 64
        if size > n:
            return size
        k += 1


def pad_graph(x: Tensor, edge_index: Tensor, edge_attr: Tensor
              ) -> Tuple[Tensor, Tensor, Tensor]:
    """``x [N, F]``, ``edge_index [2, E]`` and ``edge_attr [E, D]`` padded to
    :func:`bucket` sizes of nodes and edges with PyG's
    :class:`~torch_geometric.transforms.Pad`: zero rows for the padding nodes and edges,
    every padding edge a loop on the first padding node (``N``).  No real node receives a
    padding edge, so the first ``N`` rows of a message-passing stack's output are those of
    the unpadded graph, and so are their gradients (``out[:N]``)."""
    data = Data(x=x, edge_index=edge_index, edge_attr=edge_attr)
    out = Pad(max_num_nodes=bucket(x.size(0)), max_num_edges=bucket(edge_index.size(1)))(data)
    return out.x, out.edge_index, out.edge_attr


def mlp(sizes: Sequence[int], act: nn.Module, last_act: bool = True) -> nn.Sequential:
    layers: List[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if last_act or i < len(sizes) - 2:
            layers.append(act)
    return nn.Sequential(*layers)


def geometric_init_(module: nn.Module) -> None:
    """Geometric initialisation of linear layers (Atzmon & Lipman, SAL, the paper's
    [56]): weights ~ N(0, sqrt(2 / fan_out)), zero bias."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, (2.0 / m.out_features) ** 0.5)
            nn.init.zeros_(m.bias)


class RunningNormalizer(nn.Module):
    """MeshGraphNets-style input normaliser (Pfaff et al., ICLR 2021): ``(x - mean) / std``
    per feature, from running statistics of every row seen in training mode over the
    first ``max_updates`` calls; frozen after that and in eval mode.  The statistics are
    buffers, so they travel in the checkpoint.  Before any update it is the identity.

    Not ``nn.BatchNorm1d(affine=False, momentum=None)``: that normalises a training
    batch by its own statistics, so an autoregressive rollout (one frame per batch) would
    see other inputs in training than in evaluation.

    Args:
        size: features per row (the last dimension).
        max_updates: training calls that update the statistics.
        eps: the smallest standard deviation (a constant feature stays finite).
    """

    def __init__(self, size: int, max_updates: int = 100_000, eps: float = 1e-8) -> None:
        super().__init__()
        if not isinstance(size, int) or size < 1:
            raise ValueError(f"`size`: expected a positive int, got {size!r}")
        if not isinstance(max_updates, int) or max_updates < 0:
            raise ValueError(f"`max_updates`: expected an int >= 0, got {max_updates!r}")
        if not eps > 0:
            raise ValueError(f"`eps`: must be positive, got {eps!r}")
        self.size, self.max_updates, self.eps = size, max_updates, float(eps)
        self.register_buffer("updates", torch.zeros((), dtype=torch.long))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("total", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("total_sq", torch.zeros(size, dtype=torch.float64))

    def mean_std(self) -> Tuple[Tensor, Tensor]:
        """The current ``(mean, std)``, each ``[size]`` (float64)."""
        n = self.count.clamp_min(1.0)
        mean = self.total / n
        var = (self.total_sq / n - mean ** 2).clamp_min(0.0)
        return mean, var.sqrt().clamp_min(self.eps)

    def forward(self, x: Tensor) -> Tensor:
        if x.shape[-1] != self.size:
            raise ValueError(f"`x`: expected {self.size} features in the last dimension, got "
                             f"{tuple(x.shape)}")
        if self.training and int(self.updates) < self.max_updates:
            rows = x.detach().reshape(-1, self.size).to(torch.float64)
            self.count += rows.shape[0]
            self.total += rows.sum(0)
            self.total_sq += (rows ** 2).sum(0)
            self.updates += 1
        if float(self.count) == 0:
            return x
        mean, std = self.mean_std()
        return (x - mean.to(x.dtype)) / std.to(x.dtype)

    def extra_repr(self) -> str:
        return f"{self.size}, max_updates={self.max_updates}, updates={int(self.updates)}"


def batch_edges(edge_index: Tensor, copies: int, num_nodes: int) -> Tensor:
    """``copies`` disjoint copies of one graph (frames of a garment), like a PyG
    ``Batch``; a target-sorted ``edge_index`` stays target-sorted (fast layer path)."""
    offsets = torch.arange(copies, device=edge_index.device) * num_nodes
    return (edge_index.unsqueeze(1) + offsets.view(1, -1, 1)).reshape(2, -1)


#: batched copies of garment graphs, per ``edge_index`` tensor, copy and node count
_BATCHED = TensorCache(maxsize=16)


def cached_batch_edges(edge_index: Tensor, copies: int, num_nodes: int) -> Tensor:
    """:func:`batch_edges`, cached per ``edge_index`` tensor (its identity and version),
    copy count and node count; one copy is ``edge_index`` itself.

    The batched tensor is built outside inference mode, so it carries a version counter
    and the layers' CSR plans (:mod:`garmentgnn.nn._graph`) are cached for it too: a
    sequence predicted in chunks sorts and indexes its batched graph once, not once per
    layer and chunk.  An ``edge_index`` made in inference mode has no version counter
    and is not cached (a fresh batch every call)."""
    if copies == 1:
        return edge_index
    out = _BATCHED.lookup(edge_index, copies, num_nodes)
    if out is None:
        with torch.inference_mode(False):
            out = batch_edges(edge_index, copies, num_nodes)
        _BATCHED.store(edge_index, out, copies, num_nodes)
    return out


def freeze_edge_output(layer: nn.Module) -> None:
    """Mark the parameters that only ``layer``'s output edge features read
    ``requires_grad=False`` (its ``edge_output_parameters``, :mod:`garmentgnn.nn`'s layer
    contract), for the last layer of a stack that returns node features only: they never
    get a gradient, and DDP insists that every trainable parameter does (without
    ``find_unused_parameters``).  A layer outside the contract is left as it is."""
    for p in getattr(layer, "edge_output_parameters", tuple)():
        p.requires_grad_(False)


class AttentionStack(nn.Module):
    """Registry layers in series; hidden layers concatenate heads, the last averages."""

    def __init__(self, layer: str, in_channels: int, widths: Sequence[int], heads: int,
                 edge_dim: int, act: str, last_act: bool) -> None:
        super().__init__()
        self.layers = nn.ModuleList()
        c = in_channels
        for i, w in enumerate(widths):
            last = i == len(widths) - 1
            per_head = w if last else max(1, w // heads)
            self.layers.append(make_layer(layer, c, per_head, edge_dim=edge_dim, heads=heads,
                                          concat=not last, validate=False))
            c = w if last else per_head * heads
        self.out_channels = c
        self.act = {"elu": F.elu, "tanh": torch.tanh}[act]
        #: the same, in place (used when no gradient is recorded: saves an allocation
        #: and a pass over the node features per layer)
        self.act_ = {"elu": F.elu_, "tanh": torch.tanh_}[act]
        self.last_act = last_act
        freeze_edge_output(self.layers[-1])

    def reset_parameters(self) -> None:
        """§4.1: Kaiming initialisation (uniform, ``a = sqrt(5)``: bound
        ``1 / sqrt(fan_in)``) of every linear map of every layer -- PyG's ``Linear`` (the
        registry layers') and ``torch.nn.Linear`` alike -- after the layer's own reset
        (which sets the biases and any other parameter)."""
        for layer in self.layers:
            layer.reset_parameters()
            for m in layer.modules():
                if isinstance(m, (nn.Linear, PyGLinear)) and not isinstance(
                        m.weight, UninitializedParameter):
                    nn.init.kaiming_uniform_(m.weight, a=5 ** 0.5)

    def forward(self, x: Tensor, edge_index: Tensor, edge_attr: Tensor) -> Tensor:
        e = edge_attr
        for i, layer in enumerate(self.layers):
            x, e = layer(x, edge_index, e, return_edge_attr=True)
            if i < len(self.layers) - 1 or self.last_act:
                x = self.act_(x) if not torch.is_grad_enabled() else self.act(x)
        return x


#: ``compile_stack``'s choices (:class:`~garmentgnn.models.GarTrans`): eager (``None``) or
#: a ``torch.compile`` mode
COMPILE_MODES = (None, "default", "reduce-overhead", "max-autotune")


def scaled(width: float, *widths: int) -> List[int]:
    """``widths`` times ``width``, rounded, at least 1."""
    return [max(1, round(c * width)) for c in widths]


def sized(widths: Sequence[int], width: float = 1.0, depth: float = 1.0,
          keep_last: bool = False) -> List[int]:
    """A stack's layer ``widths`` resized: its hidden layers (all but the last) ``depth``
    times as many (rounded, at least one; the new ones spread over the old in order) and
    every width times ``width`` (rounded, at least 1), the last kept as it is with
    ``keep_last`` (an output's width).  ``sized(widths)`` is ``widths``."""
    hidden, last = list(widths[:-1]), widths[-1]
    n = max(1, round(len(hidden) * depth)) if hidden else 0
    hidden = [hidden[i * len(hidden) // n] for i in range(n)]
    return scaled(width, *hidden) + ([last] if keep_last else scaled(width, last))


def check_arguments(lbs_start: bool, skin_prior: bool, gate_init: float,
                    accel_unit: Optional[float], strain_limit: int,
                    collision_projection: Optional[float],
                    compile_stack: Optional[str] = None, width: float = 1.0,
                    depth: float = 1.0) -> None:
    """A ``ValueError`` naming the first bad argument of
    :class:`~garmentgnn.models.GarTrans` (its docstring says what each means)."""
    if lbs_start and not skin_prior:
        raise ValueError("`lbs_start`: starting from LBS needs `skin_prior=True` "
                         "(or set `lbs_start=False`)")
    if not gate_init >= 0:
        raise ValueError(f"`gate_init`: expected a value >= 0, got {gate_init}")
    if accel_unit is not None and not accel_unit > 0:
        raise ValueError(f"`accel_unit`: expected metres per output unit > 0 or None, "
                         f"got {accel_unit}")
    if not isinstance(strain_limit, int) or isinstance(strain_limit, bool) or strain_limit < 0:
        raise ValueError(f"`strain_limit`: expected a number of sweeps >= 0, got "
                         f"{strain_limit!r}")
    if collision_projection is not None and not collision_projection >= 0:
        raise ValueError(f"`collision_projection`: expected a margin >= 0 in metres or "
                         f"None, got {collision_projection}")
    if compile_stack not in COMPILE_MODES:
        raise ValueError(f"`compile_stack`: expected one of {COMPILE_MODES}, got "
                         f"{compile_stack!r}")
    for name, v in (("width", width), ("depth", depth)):
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < 100):
            raise ValueError(f"`{name}`: expected a factor of the default size > 0 "
                             f"(e.g. 0.5 or 2), got {v!r}")
