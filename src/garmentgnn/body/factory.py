"""Bodies from their dataset descriptions: ``{"model": "capsule" | "anny", "shape": ...}``.

The one place that turns a body entry of a dataset spec (or of a sequence file's meta)
into a :class:`~garmentgnn.body.Body`; generation, the data sets, training and the bench
all build their bodies here.  Models and bodies are cached per process: a body is built
once per (model, shape).
"""
from __future__ import annotations

from typing import Any, Dict, Hashable, Tuple

from garmentgnn.body.anny_body import AnnyBodyModel
from garmentgnn.body.body import Body, BodyModel
from garmentgnn.body.capsule import CapsuleBodyModel

#: the body models a spec can name
BODY_MODELS = {"capsule": CapsuleBodyModel, "anny": AnnyBodyModel}

_MODELS: Dict[str, BodyModel] = {}
_BODIES: Dict[Tuple[str, Hashable], Body] = {}


def body_model(name: str) -> BodyModel:
    """A (per-process cached) body model: ``capsule`` or ``anny``."""
    if name not in _MODELS:
        if name not in BODY_MODELS:
            raise ValueError(f"body model: unknown {name!r}; use one of {sorted(BODY_MODELS)}")
        _MODELS[name] = BODY_MODELS[name]()
    return _MODELS[name]


def build_body(spec: Dict[str, Any]) -> Body:
    """The (per-process cached) rest body of a spec entry ``{"model", "shape"}``;
    ``shape`` is a preset name (``"thin"``, ``"regular"``, ...) or the model's shape
    parameters as a list of floats."""
    if not isinstance(spec, dict) or "model" not in spec or "shape" not in spec:
        raise ValueError(f"`spec`: a dict with 'model' and 'shape', got {spec!r}")
    shape = spec["shape"]
    key = (spec["model"], shape if isinstance(shape, str) else tuple(float(x) for x in shape))
    if key not in _BODIES:
        _BODIES[key] = body_model(spec["model"])(shape)
    return _BODIES[key]


__all__ = ["BODY_MODELS", "body_model", "build_body"]
