"""Optional SMPL bodies through ``smplx``, for users who own the SMPL model files.

The SMPL files are licensed and never downloaded here: pass the path of your
own ``SMPL_*.pkl`` (``pip install smplx``; official files that store chumpy
arrays also need ``chumpy`` to unpickle).  The body is converted to the
project's frame (SMPL is Y-up facing +Z; garmentgnn is Z-up facing -Y: a +90
degree turn about X) and skinned by the project's LBS (Eq. 1).  SMPL's
pose-dependent corrective blend shapes (``posedirs``) are *not* applied by
:meth:`Body.pose` -- the paper's Eq. (1) is plain LBS -- so posed bodies differ
from ``smplx``'s output by those correctives (zero in the test model).
"""
from __future__ import annotations

import pickle
from pathlib import Path
from typing import Optional, Union

import torch
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import Skeleton

SMPL_JOINTS = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
]
SMPL_ROLES = {
    "pelvis": "pelvis", "spine": "spine1", "chest": "spine3", "neck": "neck", "head": "head",
    "l_hip": "left_hip", "l_knee": "left_knee", "l_ankle": "left_ankle",
    "r_hip": "right_hip", "r_knee": "right_knee", "r_ankle": "right_ankle",
    "l_shoulder": "left_shoulder", "l_elbow": "left_elbow", "l_wrist": "left_wrist",
    "r_shoulder": "right_shoulder", "r_elbow": "right_elbow", "r_wrist": "right_wrist",
}
#: SMPL frame (Y up, facing +Z) -> garmentgnn frame (Z up, facing -Y)
Y_UP_TO_Z_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def landmark_ids(num_verts: int) -> dict:
    """smplx's extra-landmark vertex ids, kept in range for files with fewer vertices
    (the landmarks are not used by the adapter)."""
    from smplx.vertex_ids import vertex_ids  # noqa: PLC0415 (optional: the smpl extra)

    return {k: (v if v < num_verts else 0) for k, v in vertex_ids["smplh"].items()}


class SMPLBodyModel:
    """SMPL shapes (``beta``, up to the file's shape space) as :class:`Body` objects.

    Args:
        model_path: path to a SMPL ``.pkl`` file (or a folder holding
            ``SMPL_{GENDER}.pkl``).
        gender: ``neutral``, ``male`` or ``female`` (used with a folder).
        num_betas: shape coefficients used.
    """

    def __init__(self, model_path: Union[str, Path], gender: str = "neutral",
                 num_betas: int = 10, dtype: torch.dtype = torch.float32) -> None:
        try:
            import smplx  # noqa: PLC0415 (optional: the smpl extra)
        except ImportError as exc:
            raise ImportError("SMPLBodyModel needs `smplx` (pip install smplx) and your own "
                              "SMPL model files") from exc
        path = Path(model_path)
        if not path.exists():
            raise ValueError(f"`model_path`: {path} does not exist; SMPL files are licensed "
                             "and must be downloaded by you from the SMPL website")
        from smplx.utils import Struct  # noqa: PLC0415 (optional: the smpl extra)

        file = path if path.is_file() else path / f"SMPL_{gender.upper()}.pkl"
        with open(file, "rb") as f:  # as smplx itself loads it (the file is the user's own)
            data = pickle.load(f, encoding="latin1")
        self.model = smplx.SMPL(model_path=str(file), data_struct=Struct(**data),
                                num_betas=num_betas,
                                vertex_ids=landmark_ids(len(data["v_template"])))
        self.num_betas, self.dtype = num_betas, dtype
        parents = self.model.parents.clone()
        parents[0] = -1
        names = SMPL_JOINTS if len(parents) == len(SMPL_JOINTS) else [
            f"joint{i}" for i in range(len(parents))]
        roles = SMPL_ROLES if names is SMPL_JOINTS else {}
        self.skeleton = Skeleton(list(names), parents, roles)

    def __call__(self, shape: Optional[Tensor] = None) -> Body:
        """Rest-pose body for ``beta`` (``[num_betas]``, zeros by default)."""
        beta = torch.zeros(self.num_betas) if shape is None else torch.as_tensor(shape).flatten()
        if beta.numel() != self.num_betas or not torch.isfinite(beta).all():
            raise ValueError(f"`shape`: expected {self.num_betas} finite betas, got "
                             f"{beta.numel()} values")
        m = self.model
        beta = beta.to(m.shapedirs.dtype)
        with torch.no_grad():
            v = m.v_template + torch.einsum("vcb,b->vc", m.shapedirs[..., : self.num_betas], beta)
            joints = m.J_regressor @ v
        C = Y_UP_TO_Z_UP.to(v.dtype)
        return Body(vertices=(v @ C.T).to(self.dtype),
                    faces=torch.as_tensor(m.faces.astype("int64")),
                    skeleton=self.skeleton, joints=(joints @ C.T).to(self.dtype),
                    weights=m.lbs_weights.to(self.dtype), shape=beta.to(self.dtype))
