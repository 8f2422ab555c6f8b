"""Settings and result records of the reference implicit simulator (:mod:`garmentgnn.sim`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Tuple

import torch
from torch import Tensor

from garmentgnn.physics import GRAVITY

DTYPE = torch.float64


@dataclass
class SimSettings:
    """Simulator settings.

    Attributes:
        fps: frame rate of the output; must equal the motion's fps.
        substeps: implicit steps per frame (``h = 1 / (fps * substeps)``).
        max_newton: Newton iterations per substep.
        tol: convergence threshold on the Newton step, ``max_i |dx_i| / h < tol`` (m/s,
            IPC's criterion): the velocity error the remaining correction would make.
            (A force residual such as ``h^2 |dE/dx_i| / m_i`` is no use for cloth: the
            membrane stiffness is ~10^3 times ``m / h^2``, so a 1 um position error
            already reads as millimetres.)
        membrane: ``"baraff_witkin"`` (stretch Eq. 12 + shear Eq. 13) or ``"stvk"``.
        hessian: ``"analytic"`` (closed-form projected Baraff-Witkin blocks and
            Gauss-Newton bending blocks; StVK falls back to autograd) or ``"autograd"``
            (per-element double backward + eigenvalue clamping, ~5x slower per iteration;
            the reference the analytic blocks are tested against).
        collision_stiffness: ``k`` of the cubic penalty ``k max(eps - s, 0)^3`` (J/m^3).
        collision_power: penalty exponent (3, HOOD's smooth penalty).
        friction: apply Coulomb friction with ``Material.friction`` as ``mu`` against the
            body and the colliders.  Off by default: on the walking skirt it cut the
            converged frames from 3 of 6 to 1 of 6 (silk, mu 0.3; docs/simulator.md), so
            the torch engine's datasets are generated without it.
        friction_velocity: ``eps_v`` (m/s) of the smoothed Coulomb friction
            (:mod:`garmentgnn.physics.friction`): tangential sliding slower than this
            counts as sticking (IPC's static-friction threshold; the potential uses
            ``eps_v h`` as displacement threshold).  ``Material.friction`` is ``mu``;
            ``mu = 0`` disables friction.
        preroll_frames: frames simulated (not recorded) before frame 0 while the body and
            the pinned vertices move from the rest pose into the motion's first pose
            (joint rotations and root translation scaled by a smoothstep from 0 to 1);
            without it the garment starts as its rest shape *skinned* to frame 0, which
            for a walking or kicking pose strains silk by up to +-10% and costs the first
            frames a violent, slowly converging relaxation.
        settle_frames: frames simulated with the body frozen at frame 0 before frame 0
            is recorded (after the pre-roll).
        max_refinements: times a failing frame is retried with twice the substeps.
        retry_unconverged: also retry frames whose Newton solves ran out of iterations
            (by default those are accepted -- they are finite and lowered the energy --
            and reported in ``SimResult.converged``).
        contact_radius: vertices farther than ``margin + contact_radius`` from the body at
            the start of a substep skip the (expensive) distance query during Newton;
            the result is checked against the whole garment afterwards.
        max_penetration: a substep that ends with a vertex deeper than this inside the
            body (after the contact planes were refreshed) fails, so the frame is retried
            with twice the substeps (m); at the last refinement the frame is kept and
            flagged unconverged (a pinch between body parts, not tunnelling).  Every
            recorded frame is also measured exactly at its end (all body faces, winding
            number inside test: :func:`garmentgnn.geometry.penetration_depth`); frames
            deeper than this are flagged in ``SimResult.penetrating`` and the message.
        distance_candidates: ``candidates`` of :func:`garmentgnn.geometry.signed_distance`
            (``None`` = exact brute force).
        gravity: gravity vector (Z up).
        flat_rest: rest dihedral angles 0 (sewn from flat panels) instead of the rest mesh's.
        line_search_steps: maximum step halvings.
    """

    fps: float = 30.0
    substeps: int = 4
    max_newton: int = 30
    tol: float = 1e-3
    membrane: str = "baraff_witkin"
    hessian: str = "analytic"
    collision_stiffness: float = 1e6
    collision_power: int = 3
    friction: bool = False
    friction_velocity: float = 1e-3
    preroll_frames: int = 0
    settle_frames: int = 0
    max_refinements: int = 3
    retry_unconverged: bool = False
    contact_radius: float = 0.02
    max_penetration: float = 1e-2
    distance_candidates: Optional[int] = 8
    gravity: Tuple[float, float, float] = GRAVITY
    flat_rest: bool = False
    line_search_steps: int = 30

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid setting (run at construction
        and again by :func:`simulate`, in case a field was changed since)."""
        def number(name: str, lo: float, strict: bool) -> None:
            v = getattr(self, name)
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
                and (v > lo if strict else v >= lo)
            if not ok:
                raise ValueError(f"`settings.{name}`: must be a finite number "
                                 f"{'>' if strict else '>='} {lo}, got {v!r}")

        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"`settings.fps`: must be a positive finite number, got {self.fps!r}")
        for name in ("substeps", "max_newton"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"`settings.{name}`: must be a positive int, got {v!r}")
        if not (self.tol > 0):
            raise ValueError(f"`settings.tol`: must be positive, got {self.tol!r}")
        if self.hessian not in ("analytic", "autograd"):
            raise ValueError(f"`settings.hessian`: 'analytic' or 'autograd', got {self.hessian!r}")
        if self.membrane not in ("baraff_witkin", "stvk"):
            raise ValueError(f"`settings.membrane`: 'baraff_witkin' or 'stvk', got "
                             f"{self.membrane!r}")
        if not (self.collision_stiffness >= 0):
            raise ValueError("`settings.collision_stiffness`: must be non-negative")
        if self.collision_power not in (2, 3):
            raise ValueError("`settings.collision_power`: 2 or 3 (needs a second derivative)")
        for name in ("settle_frames", "preroll_frames", "max_refinements"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise ValueError(f"`settings.{name}`: must be a non-negative int, got {v!r}")
        if not isinstance(self.line_search_steps, int) or self.line_search_steps < 1:
            raise ValueError(f"`settings.line_search_steps`: must be a positive int, got "
                             f"{self.line_search_steps!r}")
        number("tol", 0.0, True)
        number("collision_stiffness", 0.0, False)
        number("contact_radius", 0.0, False)
        number("friction_velocity", 0.0, True)
        if not isinstance(self.friction, bool):
            raise ValueError(f"`settings.friction`: True or False, got {self.friction!r}")
        number("max_penetration", 0.0, True)
        dc = self.distance_candidates
        if dc is not None and (not isinstance(dc, int) or isinstance(dc, bool) or dc < 1):
            raise ValueError(f"`settings.distance_candidates`: a positive int or None (exact), "
                             f"got {dc!r}")
        g = self.gravity
        if not (isinstance(g, (tuple, list)) and len(g) == 3
                and all(isinstance(c, (int, float)) and math.isfinite(c) for c in g)):
            raise ValueError(f"`settings.gravity`: three finite numbers (m/s^2, Z up), "
                             f"got {g!r}")
        for name in ("retry_unconverged", "flat_rest"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"`settings.{name}`: must be True or False, got "
                                 f"{getattr(self, name)!r}")


@dataclass
class SimResult:
    """Output of :func:`simulate` (one entry per motion frame that was simulated)."""

    positions: Tensor  # [T, V, 3] float32
    converged: Tensor  # [T] bool
    newton_iterations: Tensor  # [T] int
    residual: Tensor  # [T] float
    ok: bool
    message: str
    seconds: float
    substeps: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))  # [T]
    #: [T] exact depth (m) of the deepest garment vertex inside the body at the end of
    #: each frame, or inside a rigid collider (:func:`garmentgnn.geometry.penetration_depth`;
    #: zeros without a body and colliders)
    penetration: Tensor = field(default_factory=lambda: torch.zeros(0))
    #: the ``max_penetration`` the frames were checked against
    max_penetration: float = math.inf

    @property
    def penetrating(self) -> Tensor:
        """``[T]`` bool: frames whose exact penetration exceeds ``max_penetration``."""
        return self.penetration > self.max_penetration


@dataclass
class StepResult:
    x: Tensor
    v: Tensor
    converged: bool
    iterations: int
    residual: float
    ok: bool
    message: str = ""


