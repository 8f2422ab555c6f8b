"""The settings ``benchmarks/learning.py`` compares: GarTrans variants (model and module
settings over the packaged recipe ``garmentgnn/recipes/gartrans.yaml``, Trainer
arguments, data-module settings, the bench's schedule) and the baselines (``baseline``:
the method, ``module``: settings over its packaged recipe,
``garmentgnn/recipes/baselines/<name>.yaml``)."""
from __future__ import annotations

import inspect
from typing import Any, Dict

from garmentgnn.bench.methods import DA, HOOD
from garmentgnn.bench.presets import preset
from garmentgnn.physics.materials import MATERIALS
from garmentgnn.training import BaselineModule, GarTransModule

#: HOOD-style's configuration before it started from its own states with normalised inputs
_HOOD_FORMER: Dict[str, Any] = {"start_state": "lbs", "model": {"normalize": False}}
_S = MATERIALS["silk"]
#: loss weights that make the physics terms the silk preset's energies (SI units)
_SILK: Dict[str, float] = {"stretch": _S.stretch, "shear": _S.shear, "bending": _S.bending,
                           "gravity": 1.0, "inertia": 1.0}
#: GarTrans settings compared by ``curves``: model and module settings over the packaged
#: recipe, Trainer arguments and data-module settings.  Every variant but ``config``
#: starts from the former recipe's world-frame dynamic stack on raw inputs
#: (:data:`_FORMER_INPUTS`, merged in below), as they were measured, unless it names the
#: switches itself
VARIANTS: Dict[str, Dict[str, Any]] = {
    "config": {},
    "former config (world frame, raw inputs)": {},
    "former config (gates at 0, acceleration)": {"model": {"gate_init": 0.0,
                                                           "accel_unit": None}},
    "gate 0.1": {"model": {"gate_init": 0.1}},
    "gate 1": {"model": {"gate_init": 1.0}},
    "gate 0.1, cm": {"model": {"gate_init": 0.1, "accel_unit": 0.01}},
    "gate 1, cm": {"model": {"gate_init": 1.0, "accel_unit": 0.01}},
    "gate 1, cm, adam 1e-3": {"model": {"gate_init": 1.0, "accel_unit": 0.01,
                                        "optimizer": "adam", "lr": 1e-3}},
    "gate 1, cm, 4 chunks/step": {"model": {"gate_init": 1.0, "accel_unit": 0.01},
                                  "trainer": {"accumulate_grad_batches": 4}},
    "gate 0.1, cm, adam 1e-3": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                          "optimizer": "adam", "lr": 1e-3}},
    "gate 0.1, cm, 4 chunks/step": {"model": {"gate_init": 0.1, "accel_unit": 0.01},
                                    "trainer": {"accumulate_grad_batches": 4}},
    "gate 0.1, cm, vert only": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                          "loss_weights": {"edge": 0.0, "norm": 0.0,
                                                           "curv": 0.0}}},
    "gate 0.1, cm, no limit/projection": {"model": {"gate_init": 0.1, "accel_unit": 0.01,
                                                    "strain_limit": 0,
                                                    "collision_projection": None}},
    "lr 3e-4": {"model": {"lr": 3e-4}},
    "lr 1e-2": {"model": {"lr": 1e-2}},
    "input normalisers": {"model": {"input_norm": True}},
    # the dynamic stack in each vertex's skinned local frame (inputs and output)
    "local frame": {"model": {"local_frame": True}},
    "local frame, input normalisers": {"model": {"local_frame": True, "input_norm": True}},
    # the paper's blend shape B^t (a learned offset of the template, skinned with it)
    "blend shape": {"model": {"blend_shape": True}},
    "blend shape, local frame": {"model": {"blend_shape": True, "local_frame": True}},
    "blend shape, pose history 10": {"model": {"blend_shape": True}, "data": {"history": 10}},
    # ``schedule``: the bench's ProgressiveSchedule (the curvature term from phase 1, phases
    # 2 and 3 at plateaus of ``window`` epochs) instead of phase 1 alone
    "schedule": {"schedule": {"window": 1}},
    "schedule, no phase-3 freeze": {"schedule": {"window": 1, "freeze_rest": False}},
    "schedule, phase 1 only (curvature term)": {"schedule": {"window": 1, "max_phase": 1}},
    # ``data``: the data module's settings (the pose history is the GRU's input)
    "pose history 2": {"data": {"history": 2}},
    "pose history 10": {"data": {"history": 10}},
    "pose history 30": {"data": {"history": 30}},
    # the baselines on the same curves (``baseline``: the method, ``module``: settings over
    # its packaged recipe)
    "DA-style": {"baseline": DA},
    "HOOD-style": {"baseline": HOOD},
    "HOOD-style, lr 1e-4": {"baseline": HOOD, "module": {"lr": 1e-4}},
    "HOOD-style, LBS start": {"baseline": HOOD, "module": {"start_state": "lbs"}},
    "HOOD-style, raw inputs": {"baseline": HOOD, "module": {"model": {"normalize": False}}},
    "HOOD-style, accelerations x10": {"baseline": HOOD, "module": {
        "model": {"accel_scale": 10.0}}},
    # its objective in SI units: the stiffnesses of the silk preset as the loss weights
    # (the configuration's are the GarTrans paper's loss weights, ~1/5000 of silk's
    # stretch), gravity and inertia at 1
    "HOOD-style, silk energies": {"baseline": HOOD, "module": {"loss": {"weights": _SILK}}},
    "HOOD-style, silk energies, collision x10": {"baseline": HOOD, "module": {
        "loss": {"weights": dict(_SILK, collision=15.0)}}},
    # the own-state chain never reset to LBS (the configuration resets where the kept
    # state drifted over 0.25 m from LBS on average): training sees the states a
    # diverging test rollout reaches
    "HOOD-style, no drift reset": {"baseline": HOOD, "module": {"max_start_drift": 100.0}},
    "HOOD-style, silk energies, no drift reset": {"baseline": HOOD, "module": {
        "loss": {"weights": _SILK}, "max_start_drift": 100.0}},
    # before its configuration started from its own states with normalised inputs
    "HOOD-style, former recipe": {"baseline": HOOD, "module": _HOOD_FORMER},
    "HOOD-style, former recipe, lr 1e-4": {"baseline": HOOD, "module": dict(
        _HOOD_FORMER, lr=1e-4)},
    "HOOD-style, former recipe, accelerations x10": {"baseline": HOOD, "module": dict(
        _HOOD_FORMER, model={"normalize": False, "accel_scale": 10.0})},
}
#: the recipe's dynamic-stack switches before ``local_frame`` and ``input_norm`` became
#: its defaults (docs/model.md)
_FORMER_INPUTS: Dict[str, Any] = {"local_frame": False, "input_norm": False}
for _name, _v in VARIANTS.items():
    if _name != "config" and "baseline" not in _v:
        _v["model"] = dict(_FORMER_INPUTS, **_v.get("model", {}))

#: the bench's ``learn`` budget (``garmentgnn bench --preset learn``), read from its preset
_BUDGET = preset("learn").learned


def _lr(module: type) -> float:
    """``module``'s learning rate (its recipes' default) at the ``learn`` budget's factor."""
    return inspect.signature(module.__init__).parameters["lr"].default * _BUDGET.lr_factor


#: the bench's ``learn`` settings: 16 chunks a step, 4x the learning rate, epochs of 25
#: steps (400 chunks), the learning rate annealed to 0 over the run (``anneal``: a cosine
#: over ``--steps``, as the bench anneals over its time budget; at a constant 0.012 the
#: frame-parallel model's training error rose from 0.85x to 1.04x LBS between steps 300
#: and 500)
_LEARN: Dict[str, Any] = {
    "model": {"lr": _lr(GarTransModule)}, "data": {"batch_size": _BUDGET.batch_size},
    "trainer": {"limit_train_batches": -(-_BUDGET.epoch_chunks // _BUDGET.batch_size)},
    "anneal": True}
#: which model can hold the garment's state (docs/experiments.md), today's recipe at the
#: ``learn`` settings: frame-parallel.  The motion code in the dynamic stack, the
#: autoregressive offsets and the recurrent vertex latent, measured beside it, left the
#: model (their runs name the commit they ran at)
STATE: Dict[str, Dict[str, Any]] = {
    "state: frame-parallel (the paper)": {},
}
for _v in STATE.values():
    for _k, _base in _LEARN.items():
        _v[_k] = dict(_base, **_v.get(_k, {})) if isinstance(_base, dict) else _base
VARIANTS.update(STATE)

#: HOOD-style at the ``learn`` settings: its configuration, and HOOD's published recipe
#: where it fits (docs/experiments.md, "HOOD-style at its fair best"): 3 mm noise on the
#: current and previous positions, rollouts from the LBS garment growing 1 -> 5 frames
#: with detached steps, gradients clipped at 1, 100 warm-up steps; at the bench's
#: learning rate (the configuration's x 4, ``lr_factor``) and at HOOD's (5e-5 x 4)
_HOOD_LR = 5e-5
_HOOD_RECIPE: Dict[str, Any] = {"start_state": "lbs", "rollout": 5, "rollout_ramp": 100,
                                "rollout_noise": 0.003, "warmup": 100}
HOOD_LEARN: Dict[str, Dict[str, Any]] = {
    "HOOD-style, learn settings": {"baseline": HOOD, "module": {"lr": _lr(BaselineModule)}},
    "HOOD-style, HOOD's recipe": {"baseline": HOOD,
                                  "module": dict(_HOOD_RECIPE, lr=_lr(BaselineModule)),
                                  "trainer": {"gradient_clip_val": 1.0}},
    "HOOD-style, HOOD's recipe and learning rate": {
        "baseline": HOOD, "module": dict(_HOOD_RECIPE, lr=_HOOD_LR * _BUDGET.lr_factor),
        "trainer": {"gradient_clip_val": 1.0}},
}
for _v in HOOD_LEARN.values():  # _LEARN's batches and epochs (its lr and anneal are GarTrans's)
    _v["data"] = dict(_LEARN["data"])
    _v["trainer"] = dict(_LEARN["trainer"], **_v.get("trainer", {}))
VARIANTS.update(HOOD_LEARN)
