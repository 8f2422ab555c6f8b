"""NCS-style baseline: a garment-specific MLP from the pose history to offsets."""
from __future__ import annotations

from typing import Optional

from torch import Tensor, nn

from garmentgnn.geometry.rotations import axis_angle_to_matrix
from garmentgnn.models.baselines.common import skin, small_init_
from garmentgnn.models.blocks import Configurable, mlp
from garmentgnn.models.inputs import GarmentInputs

__all__ = ["NCSStyle"]


class NCSStyle(Configurable, nn.Module):
    """NCS-style garment-specific network (Bertiche, Madadi & Escalera, *Neural Cloth
    Simulation*, SIGGRAPH Asia 2022).

    One model per garment (fixed vertex count and order): an MLP reads the pose of the
    current and the ``history`` previous frames (joint rotation matrices) and outputs
    per-vertex offsets in the garment's rest (canonical) space, which are then skinned
    with the scene's LBS weights, so the garment follows the body and the network only
    learns the pose- and motion-dependent deformation.  Trained unsupervised, with
    physics losses only (``GarTransLoss`` physics terms; inertia over consecutive
    frames for the dynamics).

    Simplified from NCS: no separate static/dynamic encoders nor learned blend-shape
    basis (a direct linear output layer instead), no learned skinning weights, the root
    (global) orientation is left out of the input (the offsets do not depend on
    heading; NCS feeds the root's motion to its dynamic encoder), and the motion
    history is a fixed number of frames instead of a recurrent encoder.

    Args:
        num_vertices: ``V`` of the garment this model is trained for.
        num_joints: ``S``.
        history: previous frames in the input (1 = current + previous).
        hidden: MLP width.
    """

    def __init__(self, num_vertices: int, num_joints: int, history: int = 1,
                 hidden: int = 128) -> None:
        super().__init__()
        if not isinstance(num_vertices, int) or isinstance(num_vertices, bool) \
                or num_vertices < 1:
            raise ValueError(f"`num_vertices`: the model is garment-specific; give the "
                             f"garment's vertex count, got {num_vertices!r} (garmentgnn "
                             f"train links it from the data module when its training "
                             f"sequences show one garment on one body: select them with "
                             f"--data.train_ids)")
        if num_joints < 2:
            raise ValueError(f"`num_joints`: needs a root and at least one joint, got {num_joints}")
        if history < 0:
            raise ValueError(f"`history`: must be non-negative, got {history}")
        if hidden < 1:
            raise ValueError(f"`hidden`: must be positive, got {hidden}")
        self.num_vertices, self.num_joints, self.history = num_vertices, num_joints, history
        self.mlp = mlp([(history + 1) * (num_joints - 1) * 9, hidden, hidden, num_vertices * 3],
                       nn.Tanh(), last_act=False)
        small_init_(self.mlp[-1])

    def offsets(self, rotations: Tensor) -> Tensor:
        """``rotations [B, history + 1, S, 3]`` (last = current frame) -> canonical
        offsets ``[B, V, 3]``."""
        H = self.history + 1
        if rotations.dim() != 4 or rotations.shape[1:] != (H, self.num_joints, 3):
            raise ValueError(f"`rotations`: expected [B, {H}, {self.num_joints}, 3] axis-angle, "
                             f"got {tuple(rotations.shape)}")
        dtype = self.mlp[0].weight.dtype
        R = axis_angle_to_matrix(rotations[:, :, 1:].to(dtype))
        return self.mlp(R.reshape(R.shape[0], -1)).reshape(-1, self.num_vertices, 3)

    def forward(self, scene: GarmentInputs, rotations: Tensor,
                translation: Optional[Tensor] = None) -> Tensor:
        """``rotations [B, history + 1, S, 3]``, ``translation [B, 3]`` (current frame)
        -> positions ``[B, V, 3]``."""
        if scene.num_vertices != self.num_vertices:
            raise ValueError(f"`scene`: has {scene.num_vertices} vertices; this garment-specific "
                             f"model was built for {self.num_vertices}")
        d = self.offsets(rotations)
        return skin(scene, rotations[:, -1], translation, d.to(scene.rest_pos.dtype))[0]
