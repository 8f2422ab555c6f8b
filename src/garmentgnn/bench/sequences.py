"""Benchmark inputs: one garment on one body following one motion, built once and shared
by every method (simulator budgets, LBS, learned models)."""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Dict, Optional

from torch import Tensor

from garmentgnn.data.presets import build_inputs
from garmentgnn.garments.skinning import transfer_skinning_weights
from garmentgnn.models.inputs import GarmentInputs, build_garment
from garmentgnn.physics import ClothRest, Material


def case_item(name: str, kind: str, resolution: int, motion: str, num_frames: int,
              params: Optional[Dict[str, Any]] = None, body_shape: str = "regular",
              speed: float = 1.0, amplitude: float = 1.0, material: str = "silk"
              ) -> Dict[str, Any]:
    """A benchmark case in the item format of :mod:`garmentgnn.data.presets` (capsule
    body), plus its ``name``; the seed is filled in per run."""
    if num_frames < 2:
        raise ValueError(f"`num_frames`: at least 2 (frame 0 is the shared initial state), "
                         f"got {num_frames}")
    return {"name": name,
            "garment": {"kind": kind, "params": dict(params or {}), "resolution": resolution},
            "body": {"model": "capsule", "shape": body_shape},
            "motion": {"name": motion, "num_frames": num_frames, "speed": speed,
                       "amplitude": amplitude},
            "material": material, "settings": {}}


def build_scene(garment, body) -> GarmentInputs:
    """The skinned garment (:func:`~garmentgnn.models.inputs.build_garment`) with the
    skinning weights the reference simulator uses (:func:`transfer_skinning_weights` on
    float32 inputs, as in ``simulate``)."""
    W = transfer_skinning_weights(garment.vertices.float(), garment.faces,
                                  body.vertices.float(), body.weights.float())
    return build_garment(garment.vertices.to(body.vertices.dtype), garment.faces, W,
                         body.joints, body.skeleton.parents, garment.pinned)


@dataclass
class BenchSequence:
    """Everything a method needs to predict one sequence, and the evaluator to score it.

    Attributes:
        name: case name; ``seed``: the motion's seed.
        garment, body, motion, material: as given to :func:`garmentgnn.sim.simulate`.
        body_frames: ``[T, Vb, 3]`` posed body vertices.
        scene: the models' view of garment + skeleton (LBS weights of the simulator).
        rest: :class:`ClothRest` of the garment (float64), ``mass`` ``[V]`` (kg).
        item: the case description (JSON-able).
    """

    name: str
    seed: int
    garment: Any
    body: Any
    motion: Any
    material: Material
    body_frames: Tensor
    scene: GarmentInputs
    rest: ClothRest
    mass: Tensor
    item: Dict[str, Any]

    @property
    def num_frames(self) -> int:
        return int(self.motion.num_frames)


def make_sequence(item: Dict[str, Any], seed: int, material: Optional[Material] = None,
                  garment=None, motion=None) -> BenchSequence:
    """Build a :class:`BenchSequence` from a :func:`case_item` with :func:`build_inputs`;
    ``material``/``garment``/``motion`` override what the item describes (the stability
    suite's stiff material, degenerate mesh and extreme pose)."""
    if not isinstance(seed, int) or seed < 0:
        raise ValueError(f"`seed`: expected a non-negative int, got {seed!r}")
    it = copy.deepcopy(item)
    it["seed"] = seed
    g, body, m, mat = build_inputs(it)
    g = garment if garment is not None else g
    m = motion if motion is not None else m
    mat = material if material is not None else mat
    body_frames = body.pose(m.rotations, m.translation)[0]
    rest = ClothRest.from_mesh(g.vertices.double(), g.faces, g.face_uv.double())
    mass = rest.vertex_masses(mat.density, g.num_vertices)
    return BenchSequence(name=item["name"], seed=seed, garment=g, body=body, motion=m,
                         material=mat, body_frames=body_frames, scene=build_scene(g, body),
                         rest=rest, mass=mass, item=it)
