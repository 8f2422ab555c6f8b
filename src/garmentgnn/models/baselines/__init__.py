"""Baselines of the paper's comparison (§4.3, Tables 2-3), written from their papers'
descriptions (no code copied), small enough to train on a CPU.

* :class:`LBSBaseline` -- no learning: the rest garment skinned to the frame (Eq. 1).
* :class:`DAStyle` -- "DA" / DeePSD-style static, supervised graph network on
  multi-source per-vertex attributes, predicting an offset on top of LBS.
* :class:`HOODStyle` -- HOOD-style hierarchical message passing predicting per-vertex
  accelerations from the two previous garment states and the body; autoregressive.
* :class:`NCSStyle` -- NCS-style garment-specific MLP from the pose history to
  per-vertex offsets, skinned.

Every model reads the one model-input type, :class:`~garmentgnn.models.inputs.GarmentInputs`
(rest mesh, skinning weights, skeleton, pinned mask, poses); this package never builds
garments or runs the simulator.  Training losses are not re-implemented here: the
physics-trained baselines (HOOD, NCS) are meant to be trained with
:class:`garmentgnn.losses.GarTransLoss` with only its physics terms enabled (collision,
gravity, stretch, shear, bending, and inertia for the dynamic ones); DA with its
supervised terms.
"""
from garmentgnn.models.baselines.common import LBSBaseline, skin
from garmentgnn.models.baselines.da import DAStyle
from garmentgnn.models.baselines.hood import CoarseLevel, HOODStyle, MLPMessagePassing
from garmentgnn.models.baselines.ncs import NCSStyle

__all__ = ["CoarseLevel", "DAStyle", "HOODStyle", "LBSBaseline", "MLPMessagePassing",
           "NCSStyle", "skin"]
