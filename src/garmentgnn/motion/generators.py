"""Procedural motions for the kinds of sequences the paper trains and tests on.

Every generator has the signature ``(skeleton, num_frames=120, fps=30.0,
speed=1.0, amplitude=1.0, seed=None, rest_joints=None) -> Motion`` and drives
joints through the skeleton's semantic ``roles`` (joints without a role stay at
rest).  Angles are written per role as Euler angles about the world-aligned rest
axes with the sign conventions of :mod:`garmentgnn.motion.limits` (left side;
right-side angles are mirrored), then clamped to the joint limits, so every
motion is anatomically valid at any ``amplitude``.

* ``amplitude`` scales every joint angle (relative to the rest pose);
* ``speed`` scales cadence and thereby velocity (``speed=2`` doubles both);
  the flight of :func:`jump` obeys ``g = 9.81 m/s^2`` whatever the speed;
* ``seed=None`` gives the canonical motion; an integer adds a reproducible
  variation of style (per-joint amplitude jitter, phase offset);
* ``rest_joints`` ``[S, 3]`` (optional) supplies the body's bone lengths for the
  root translation (stride length, pelvis drop while crouching/sitting); the
  default assumes a 1.75 m body (thigh 0.42 m, shank 0.40 m).

Root translation: walk and run move forward (-Y); jump follows a ballistic arc;
sit/stand, jump's crouch and kick's support leg move the pelvis so that the
planted feet stay in place.
"""
from __future__ import annotations

import inspect
import math
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from garmentgnn.body.skeleton import Skeleton
from garmentgnn.geometry.rotations import (axis_angle_to_matrix, euler_to_matrix,
                                           matrix_to_axis_angle, unwrap_axis_angle)
from garmentgnn.motion.limits import JOINT_LIMITS
from garmentgnn.motion.sequence import Motion

GRAVITY = 9.81
#: Gait periods (seconds per full cycle = two steps) at ``speed=1``; chosen to be
#: whole numbers of frames at 30 fps (33 and 21 frames).
WALK_PERIOD = 1.1
RUN_PERIOD = 0.7
ARM_SWING_PERIOD = 1.5
KICK_PERIOD = 1.6
SIT_STAND_PERIOD = 4.0
TWIRL_REVS_PER_SECOND = 0.5

_PELVIS_ORDER = "ZXY"  # yaw, then pitch, then roll
_THIGH, _SHANK = 0.42, 0.40  # default bone lengths (1.75 m body)


# ----------------------------------------------------------------------------- helpers


def _check(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints):
    if not isinstance(skeleton, Skeleton):
        raise ValueError(f"`skeleton`: expected a garmentgnn.body.Skeleton, got "
                         f"{type(skeleton).__name__}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) \
            or num_frames < 1:
        raise ValueError(f"`num_frames`: expected a positive integer, got {num_frames!r}")
    for name, v, lo in (("fps", fps, 0.0), ("speed", speed, 0.0)):
        if not isinstance(v, (int, float)) or not math.isfinite(v) or not v > lo:
            raise ValueError(f"`{name}`: expected a positive finite number, got {v!r}")
    if not isinstance(amplitude, (int, float)) or not math.isfinite(amplitude) or amplitude < 0:
        raise ValueError(f"`amplitude`: expected a finite number >= 0, got {amplitude!r}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
        raise ValueError(f"`seed`: expected None or an integer, got {seed!r}")
    if rest_joints is not None:
        rj = torch.as_tensor(rest_joints)
        if rj.shape != (skeleton.num_joints, 3) or not torch.isfinite(rj).all():
            raise ValueError(f"`rest_joints`: expected finite [{skeleton.num_joints}, 3], got "
                             f"{tuple(rj.shape)}")


def _smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _keys(u, times: Sequence[float], values: Sequence[float]):
    """Ease-in/ease-out interpolation through keyframes (``times`` increasing)."""
    out = np.full_like(u, float(values[0]))
    for t0, t1, v0, v1 in zip(times[:-1], times[1:], values[:-1], values[1:]):
        m = (u >= t0) & (u <= t1)
        out[m] = v0 + (v1 - v0) * _smoothstep((u[m] - t0) / (t1 - t0))
    out[u > times[-1]] = values[-1]
    return out


def _bump(phase, center: float, power: float):
    """Smooth periodic bump in [0, 1] peaking at ``phase = center``."""
    return ((1.0 + np.cos(phase - center)) / 2.0) ** power


class _Pose:
    """Per-role Euler angles (degrees, about X, Y, Z) over ``T`` frames."""

    def __init__(self, skeleton: Skeleton, T: int, amplitude: float,
                 rng: Optional[np.random.Generator]) -> None:
        self.skeleton, self.T, self.amplitude = skeleton, T, amplitude
        self.angles: Dict[str, np.ndarray] = {}
        self.rng = rng
        self._jitter: Dict[str, float] = {}

    def jitter(self, role: str) -> float:
        if self.rng is None:
            return 1.0
        side = role[2:] if role[:2] in ("l_", "r_") else role
        if side not in self._jitter:
            self._jitter[side] = float(self.rng.uniform(0.85, 1.15))
        return self._jitter[side]

    def add(self, role: str, x=0.0, y=0.0, z=0.0, scaled: bool = True) -> None:
        """Add angles in the left-side convention; ``r_*`` roles are mirrored (Y, Z negated)."""
        s = (self.amplitude * self.jitter(role)) if scaled else 1.0
        sign = -1.0 if role.startswith("r_") else 1.0
        a = self.angles.setdefault(role, np.zeros((self.T, 3)))
        a[:, 0] += s * np.broadcast_to(x, (self.T,))
        a[:, 1] += s * sign * np.broadcast_to(y, (self.T,))
        a[:, 2] += s * sign * np.broadcast_to(z, (self.T,))


def _finish(skeleton: Skeleton, pose: _Pose, translation: np.ndarray, fps: float,
            dtype: torch.dtype = torch.float32) -> Motion:
    T, S = pose.T, skeleton.num_joints
    aa = np.zeros((T, S, 3))
    for role, ang in pose.angles.items():
        if role not in skeleton.roles:
            continue
        k = skeleton.joint_names.index(skeleton.roles[role])
        if role == "pelvis":  # the root's global orientation: unlimited
            order, clamped = _PELVIS_ORDER, ang
        else:
            lim = JOINT_LIMITS[role]
            order, clamped = lim.order, np.clip(ang, lim.lower, lim.upper)
        euler = clamped[:, ["XYZ".index(a) for a in order]]
        R = euler_to_matrix(torch.from_numpy(np.deg2rad(euler)), order)
        aa[:, k] = matrix_to_axis_angle(R).numpy()
    aa = unwrap_axis_angle(aa)
    return Motion(torch.tensor(aa, dtype=dtype), torch.tensor(translation, dtype=dtype),
                  list(skeleton.joint_names), float(fps))


def _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints):
    _check(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    rng = None if seed is None else np.random.default_rng(int(seed))
    t = np.arange(num_frames, dtype=np.float64) / float(fps)
    phase0 = 0.0 if rng is None else float(rng.uniform(0.0, 2 * np.pi))
    return t, rng, phase0, _Pose(skeleton, num_frames, float(amplitude), rng)


def _leg_vectors(skeleton: Skeleton, rest_joints) -> Tuple[np.ndarray, np.ndarray]:
    """Rest thigh (hip->knee) and shank (knee->ankle) vectors of the left leg."""
    if rest_joints is not None and all(r in skeleton.roles for r in ("l_hip", "l_knee", "l_ankle")):
        J = torch.as_tensor(rest_joints, dtype=torch.float64).numpy()
        h, k, a = (skeleton.index(r) for r in ("l_hip", "l_knee", "l_ankle"))
        return J[k] - J[h], J[a] - J[k]
    return np.array([0.0, 0.0, -_THIGH]), np.array([0.0, 0.0, -_SHANK])


def _rot_x(deg, v: np.ndarray) -> np.ndarray:
    """Rotate the vector ``v`` about +X by ``deg`` (array [T]) -> [T, 3]."""
    a = np.deg2rad(deg)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.full_like(a, v[0]), c * v[1] - s * v[2], s * v[1] + c * v[2]], -1)


def _planted_leg(hip_flex, shank_tilt, thigh: np.ndarray, shank: np.ndarray):
    """A sagittal leg pose with the foot flat and fixed on the ground.

    ``hip_flex`` (thigh forward) and ``shank_tilt`` (shank leaning forward, knee
    ahead of the ankle), degrees, are clipped to the joint limits.  Returns the
    hip, knee, ankle X angles and the pelvis offset ``[T, 3]`` that keeps the
    ankle where it is at rest.
    """
    hip_flex = np.clip(hip_flex, -30.0, 120.0)
    shank_tilt = np.clip(shank_tilt, 0.0, 30.0)
    hip_x, knee_x, ankle_x = -hip_flex, hip_flex + shank_tilt, -shank_tilt
    ankle_rel = _rot_x(hip_x, thigh) + _rot_x(shank_tilt, shank)  # shank global X = hip + knee
    offset = (thigh + shank)[None, :] - ankle_rel
    return hip_x, knee_x, ankle_x, offset


# ----------------------------------------------------------------------------- gaits


def _gait(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints, *, run: bool) -> Motion:
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    period = (RUN_PERIOD if run else WALK_PERIOD) / speed
    phi = 2 * np.pi * t / period + phase0
    A = pose.amplitude
    if run:
        hip_amp, hip_mean, knee_base, knee_swing, elbow = 35.0, 10.0, 20.0, 90.0, 85.0
        arm_amp, lean = 30.0, 8.0
    else:
        hip_amp, hip_mean, knee_base, knee_swing, elbow = 22.0, 3.0, 5.0, 55.0, 15.0
        arm_amp, lean = 18.0, 2.0
    for side, ph in (("l", phi), ("r", phi + np.pi)):
        # leg forward when sin(ph) > 0; swing (hip flexing) when cos(ph) > 0
        pose.add(f"{side}_hip", x=-(hip_mean + hip_amp * np.sin(ph)),
                 y=-3.0 * np.cos(ph), z=4.0 * np.sin(ph))
        knee = knee_base + knee_swing * _bump(ph, -0.3, 3.0) + 10.0 * _bump(ph, 2.4, 4.0)
        pose.add(f"{side}_knee", x=knee)
        pose.add(f"{side}_ankle", x=12.0 * _bump(ph, -1.3, 4.0) - 10.0 * _bump(ph, 0.5, 2.0))
        # the arm swings with the opposite leg
        arm = ph + np.pi
        pose.add(f"{side}_shoulder", x=-arm_amp * np.sin(arm), y=12.0)
        pose.add(f"{side}_elbow", x=-(elbow + 10.0 * (1.0 + np.sin(arm)) / 2.0))
    pose.add("pelvis", z=-5.0 * np.sin(phi), y=2.0 * np.cos(phi), x=2.0 * np.cos(2 * phi))
    pose.add("spine", x=lean / 2, z=3.0 * np.sin(phi))
    pose.add("chest", x=lean / 2, z=5.0 * np.sin(phi))
    pose.add("neck", z=-1.5 * np.sin(phi))
    pose.add("head", z=-1.5 * np.sin(phi))

    thigh, shank = _leg_vectors(skeleton, rest_joints)
    leg = float(np.linalg.norm(thigh + shank))
    a = np.deg2rad(min(hip_amp * A * pose.jitter("l_hip"), 90.0))
    stride = 4.0 * leg * math.sin(a) * (1.5 if run else 1.0)  # two steps
    velocity = stride / period
    tr = np.zeros((num_frames, 3))
    tr[:, 1] = -velocity * t
    tr[:, 0] = -0.02 * min(A, 2.0) * np.cos(phi)  # sway over the stance leg
    if run:  # lowest at mid-stance, highest in flight
        tr[:, 2] = -0.04 * min(A, 2.0) * (1.0 + np.cos(2 * phi)) / 2.0
    else:  # lowest in double support (legs spread)
        tr[:, 2] = -0.5 * leg * (1.0 - np.cos(a * np.sin(phi)))
    return _finish(skeleton, pose, tr, fps)


def walk(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
         amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Walking forward (-Y): a gait cycle of :data:`WALK_PERIOD` / ``speed`` seconds
    (1.1 s, ~109 steps/min), legs in antiphase, arms swinging with the opposite leg.
    Root velocity = stride / period (about 1.1 m/s for a 1.75 m body)."""
    return _gait(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints, run=False)


def run(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
        amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Running forward (-Y): cycle of :data:`RUN_PERIOD` / ``speed`` seconds (0.7 s,
    ~171 steps/min), higher knees, bent elbows, forward lean, vertical bounce."""
    return _gait(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints, run=True)


# ----------------------------------------------------------------------------- others


def twirl(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
          amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Spinning on the spot about +Z (counter-clockwise seen from above) at
    :data:`TWIRL_REVS_PER_SECOND` x ``speed`` revolutions per second, easing in
    over the first 0.5 s / ``speed``; arms held out, small steps in place.
    ``amplitude`` scales the limbs, not the spin."""
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    omega = 360.0 * TWIRL_REVS_PER_SECOND * speed  # deg/s
    ramp = 0.5 / speed
    u = np.clip(t / ramp, 0.0, 1.0)
    yaw = np.where(t < ramp, omega * ramp * (u ** 3 - u ** 4 / 2.0),
                   omega * (ramp / 2.0 + (t - ramp)))
    pose.add("pelvis", z=yaw, scaled=False)
    step = 2 * np.pi * 2.0 * TWIRL_REVS_PER_SECOND * speed * t + phase0
    flutter = np.sin(2 * step)
    for side, ph in (("l", step), ("r", step + np.pi)):
        lift = 12.0 * ((1.0 + np.sin(ph)) / 2.0) ** 2
        pose.add(f"{side}_hip", x=-lift)
        pose.add(f"{side}_knee", x=2.0 * lift)
        pose.add(f"{side}_ankle", x=-0.5 * lift)
        pose.add(f"{side}_shoulder", y=-55.0 - 5.0 * flutter, x=-10.0)
        pose.add(f"{side}_elbow", x=-20.0)
        pose.add(f"{side}_wrist", y=-10.0)
    pose.add("spine", x=3.0)
    pose.add("head", z=-10.0 * np.sin(step / 2.0))
    tr = np.zeros((num_frames, 3))
    return _finish(skeleton, pose, tr, fps)


def kick(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
         amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Forward kicks, alternating right and left, one every :data:`KICK_PERIOD` /
    ``speed`` seconds: wind-up (hip back, knee bent), snap (hip flexes to ~75 deg,
    knee extends), recovery.  The support leg bends slightly with its foot planted."""
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    period = KICK_PERIOD / speed
    cycle = np.floor(t / period).astype(int)
    u = t / period - cycle
    times = [0.0, 0.3, 0.5, 0.7, 1.0]
    hip = _keys(u, times, [0.0, -15.0, 75.0, 30.0, 0.0])
    knee = _keys(u, times, [0.0, 70.0, 5.0, 40.0, 0.0])
    ankle = _keys(u, times, [0.0, 10.0, 30.0, 10.0, 0.0])
    effort = np.sin(np.pi * u) ** 2  # 0 at the start/end of every kick
    thigh, shank = _leg_vectors(skeleton, rest_joints)
    A = pose.amplitude
    sup_hip_x, sup_knee_x, sup_ankle_x, offset = _planted_leg(
        A * 8.0 * effort, A * 8.0 * effort, thigh, shank)
    right_kicks = (cycle % 2) == 0
    for side in ("l", "r"):
        kicking = right_kicks if side == "r" else ~right_kicks
        k = kicking.astype(float)
        s = 1.0 - k
        pose.add(f"{side}_hip", x=-hip * k)
        pose.add(f"{side}_knee", x=knee * k)
        pose.add(f"{side}_ankle", x=ankle * k)
        pose.add(f"{side}_hip", x=sup_hip_x * s, scaled=False)
        pose.add(f"{side}_knee", x=sup_knee_x * s, scaled=False)
        pose.add(f"{side}_ankle", x=sup_ankle_x * s, scaled=False)
        # arms: the one opposite the kicking leg swings forward, the other back and out
        pose.add(f"{side}_shoulder", x=effort * np.where(kicking, 20.0, -40.0), y=-20.0 * effort)
        pose.add(f"{side}_elbow", x=-30.0 * effort)
    pose.add("spine", x=-10.0 * effort)
    pose.add("chest", x=-5.0 * effort)
    pose.add("head", x=8.0 * effort)
    return _finish(skeleton, pose, offset, fps)


def arm_swing(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
              amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Standing, swinging both arms forward and back in antiphase (a cycle every
    :data:`ARM_SWING_PERIOD` / ``speed`` seconds) with a chest twist and a small
    knee bounce, feet planted."""
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    phi = 2 * np.pi * t * speed / ARM_SWING_PERIOD + phase0
    for side, ph in (("l", phi), ("r", phi + np.pi)):
        pose.add(f"{side}_shoulder", x=-50.0 * np.sin(ph), y=-10.0 * (1.0 - np.cos(2 * ph)) / 2.0)
        pose.add(f"{side}_elbow", x=-(15.0 + 25.0 * (1.0 + np.sin(ph)) / 2.0))
        pose.add(f"{side}_wrist", y=10.0 * np.sin(ph))
    pose.add("chest", z=-8.0 * np.sin(phi))
    pose.add("spine", z=-4.0 * np.sin(phi))
    pose.add("head", z=6.0 * np.sin(phi))
    bounce = pose.amplitude * 6.0 * (1.0 - np.cos(2 * phi)) / 2.0
    thigh, shank = _leg_vectors(skeleton, rest_joints)
    hip_x, knee_x, ankle_x, offset = _planted_leg(bounce, bounce, thigh, shank)
    for side in ("l", "r"):
        pose.add(f"{side}_hip", x=hip_x, scaled=False)
        pose.add(f"{side}_knee", x=knee_x, scaled=False)
        pose.add(f"{side}_ankle", x=ankle_x, scaled=False)
    return _finish(skeleton, pose, offset, fps)


def jump(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
         amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None,
         height: float = 0.3) -> Motion:
    """Vertical jumps on the spot, repeated: pause, crouch (feet planted), push-off
    (0.3 s), a ballistic flight of apex ``height`` metres under ``g = 9.81``
    (pelvis height exactly ``v0 t - g t^2 / 2`` with ``v0 = sqrt(2 g height)``),
    landing absorbed by the legs (0.3 s), rise.  The feet stay flat (no toe-off),
    so the pelvis height is continuous but its velocity jumps at take-off and
    touch-down.  ``speed`` shortens the pause, crouch and rise (not push, flight or
    landing); ``amplitude`` scales the crouch depth and the arm swing."""
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    if isinstance(height, bool) or not isinstance(height, (int, float)) \
            or not math.isfinite(height) or height <= 0:
        raise ValueError(f"`height`: expected a positive number of metres, got {height!r}")
    thigh, shank = _leg_vectors(skeleton, rest_joints)
    A = pose.amplitude
    v0 = math.sqrt(2.0 * GRAVITY * height)
    t_flight = 2.0 * v0 / GRAVITY
    #          pause        crouch       push  flight    land  rise
    segments = [0.3 / speed, 0.5 / speed, 0.3, t_flight, 0.3, 0.5 / speed]
    bounds = np.cumsum([0.0] + segments)
    tc = np.mod(t, bounds[-1])
    c = np.zeros_like(t)  # crouch depth in [0, 1] while on the ground
    flying = np.zeros(t.shape, dtype=bool)
    for i in range(len(segments)):
        m = (tc >= bounds[i]) & (tc < bounds[i + 1])
        s = (tc[m] - bounds[i]) / segments[i]
        if i == 1:
            c[m] = _smoothstep(s)
        elif i == 2:
            c[m] = 1.0 - s ** 2  # accelerating extension
        elif i == 3:
            flying[m] = s > 0
        elif i == 4:
            c[m] = 1.0 - (1.0 - s) ** 2  # decelerating flexion
        elif i == 5:
            c[m] = 1.0 - _smoothstep(s)
    hip_x, knee_x, ankle_x, offset = _planted_leg(55.0 * A * c, 30.0 * A * c, thigh, shank)
    tf = tc - bounds[3]
    arms = _keys(tc, list(bounds[[0, 1, 2, 3]]) + [bounds[3] + t_flight / 2] + list(bounds[4:]),
                 [0.0, 0.0, -40.0, 60.0, 80.0, 40.0, 0.0, 0.0])  # shoulder flexion
    point = np.where(flying, 20.0 * np.sin(np.pi * np.clip(tf / t_flight, 0.0, 1.0)), 0.0)
    for side in ("l", "r"):
        pose.add(f"{side}_hip", x=hip_x, scaled=False)
        pose.add(f"{side}_knee", x=knee_x, scaled=False)
        pose.add(f"{side}_ankle", x=ankle_x + A * point, scaled=False)
        pose.add(f"{side}_shoulder", x=-arms, y=-10.0 * np.clip(arms, 0.0, None) / 80.0)
        pose.add(f"{side}_elbow", x=-15.0)
    pose.add("spine", x=25.0 * c)
    pose.add("chest", x=10.0 * c)
    pose.add("head", x=-10.0 * c)
    tr = offset.copy()
    tr[flying] = 0.0
    tr[flying, 2] = v0 * tf[flying] - 0.5 * GRAVITY * tf[flying] ** 2
    return _finish(skeleton, pose, tr, fps)


def sit_stand(skeleton: Skeleton, num_frames: int = 120, fps: float = 30.0, speed: float = 1.0,
              amplitude: float = 1.0, seed: Optional[int] = None, rest_joints=None) -> Motion:
    """Sitting down onto a (virtual) chair and standing up again, one cycle every
    :data:`SIT_STAND_PERIOD` / ``speed`` seconds: hips flex to 90 deg, the pelvis
    moves down and back (about 0.43 m down for a 1.75 m body) with the feet
    planted, the trunk leans forward and the arms reach forward during the
    transitions."""
    t, rng, phase0, pose = _setup(skeleton, num_frames, fps, speed, amplitude, seed, rest_joints)
    period = SIT_STAND_PERIOD / speed
    u = np.mod(t / period + phase0 / (2 * np.pi), 1.0)
    c = _keys(u, [0.0, 0.1, 0.45, 0.6, 0.9, 1.0], [0.0, 0.0, 1.0, 1.0, 0.0, 0.0])
    A = pose.amplitude
    thigh, shank = _leg_vectors(skeleton, rest_joints)
    hip_x, knee_x, ankle_x, offset = _planted_leg(90.0 * A * c, 10.0 * A * c, thigh, shank)
    transit = np.sin(np.pi * c)
    for side in ("l", "r"):
        pose.add(f"{side}_hip", x=hip_x, scaled=False)
        pose.add(f"{side}_knee", x=knee_x, scaled=False)
        pose.add(f"{side}_ankle", x=ankle_x, scaled=False)
        pose.add(f"{side}_shoulder", x=-35.0 * transit, y=5.0 * c)
        pose.add(f"{side}_elbow", x=-(10.0 + 30.0 * c))
    pose.add("spine", x=25.0 * transit + 5.0 * c)
    pose.add("chest", x=10.0 * transit)
    pose.add("head", x=-10.0 * transit)
    return _finish(skeleton, pose, offset, fps)


#: Motion kind -> generator.
MOTIONS: Dict[str, Callable[..., Motion]] = {
    "walk": walk, "run": run, "twirl": twirl, "kick": kick, "arm_swing": arm_swing,
    "jump": jump, "sit_stand": sit_stand,
}


def make_motion(name: str, skeleton: Skeleton, **kwargs) -> Motion:
    """``MOTIONS[name](skeleton, **kwargs)`` with a ``ValueError`` for unknown names.

    ``"a+b"`` (e.g. ``"walk+arm_swing"``) is the even :func:`blend` of two generators
    called with the same arguments: a mix of the two motions."""
    if isinstance(name, str) and "+" in name:
        parts = name.split("+")
        if len(parts) != 2 or parts[0] == parts[1]:
            raise ValueError(f"`name`: a mix names two different motions, 'a+b'; got {name!r}")
        a, b = (make_motion(p, skeleton, **kwargs) for p in parts)
        return blend(a, b, 0.5)
    if name not in MOTIONS:
        raise ValueError(f"`name`: unknown motion {name!r}; choose one of {sorted(MOTIONS)} "
                         f"or a mix 'a+b' of two")
    fn = MOTIONS[name]
    accepted = set(inspect.signature(fn).parameters) - {"skeleton"}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise ValueError(f"`{unknown[0]}`: not an argument of {name!r}; it accepts "
                         f"{sorted(accepted)}")
    return fn(skeleton, **kwargs)


# ----------------------------------------------------------------------------- combining


def slerp_rotations(a: Tensor, b: Tensor, w) -> Tensor:
    """Geodesic interpolation of axis-angle rotations ``[..., 3]``: ``w=0`` gives ``a``,
    ``w=1`` gives ``b`` (``w`` a float or a tensor broadcasting against ``[..., 1]``)."""
    Ra, Rb = axis_angle_to_matrix(a), axis_angle_to_matrix(b)
    delta = matrix_to_axis_angle(Ra.transpose(-1, -2) @ Rb)
    w = torch.as_tensor(w, dtype=a.dtype)
    return matrix_to_axis_angle(Ra @ axis_angle_to_matrix(delta * w))


def _same_joints(motions: Sequence[Motion], what: str) -> None:
    for m in motions:
        if not isinstance(m, Motion):
            raise ValueError(f"`{what}`: expected Motion objects, got {type(m).__name__}")
        if m.joint_names != motions[0].joint_names:
            raise ValueError(f"`{what}`: motions have different joints; retarget them first")


def blend(a: Motion, b: Motion, weight: float = 0.5) -> Motion:
    """Frame-by-frame mix of two motions of equal length and joints (rotations by
    slerp, translation linearly); ``weight`` is the share of ``b``."""
    _same_joints([a, b], "a/b")
    if a.num_frames != b.num_frames:
        raise ValueError(f"`a`/`b`: lengths differ ({a.num_frames} vs {b.num_frames}); "
                         "trim or resample first")
    if not 0.0 <= float(weight) <= 1.0:
        raise ValueError(f"`weight`: expected a number in [0, 1], got {weight!r}")
    rot = slerp_rotations(a.rotations, b.rotations.to(a.rotations.dtype), float(weight))
    tr = torch.lerp(a.translation, b.translation.to(a.translation.dtype), float(weight))
    return Motion(rot, tr, list(a.joint_names), a.fps)


def concat(motions: Sequence[Motion], blend_frames: int = 0) -> Motion:
    """Play motions one after the other.  Each motion's horizontal root translation
    continues from where the previous one ended; with ``blend_frames > 0`` the last
    frames of one and the first of the next are cross-faded (total length shrinks
    by ``blend_frames`` per junction)."""
    if not isinstance(motions, (list, tuple)) or not motions:
        raise ValueError("`motions`: expected a non-empty list of Motion objects")
    _same_joints(motions, "motions")
    if any(abs(m.fps - motions[0].fps) > 1e-9 for m in motions):
        raise ValueError("`motions`: frame rates differ; resample them first (Motion.resample)")
    if isinstance(blend_frames, bool) or not isinstance(blend_frames, int) or blend_frames < 0:
        raise ValueError(f"`blend_frames`: expected an integer >= 0, got {blend_frames!r}")
    if blend_frames and any(m.num_frames < blend_frames for m in motions):
        raise ValueError(f"`blend_frames`: {blend_frames} is longer than one of the motions")
    rot, tr = motions[0].rotations, motions[0].translation
    dtype = rot.dtype
    for m in motions[1:]:
        r2, t2 = m.rotations.to(dtype), m.translation.to(dtype).clone()
        n = blend_frames
        # continue horizontally from the frame the blend starts at
        anchor = tr[-n] if n else tr[-1]
        t2[:, :2] += anchor[:2] - t2[0, :2]
        if n:
            w = ((torch.arange(n, dtype=dtype) + 1) / (n + 1)).view(n, 1, 1)
            mid_r = slerp_rotations(rot[-n:], r2[:n], w)
            mid_t = tr[-n:] + (t2[:n] - tr[-n:]) * w[:, :, 0]
            rot = torch.cat([rot[:-n], mid_r, r2[n:]])
            tr = torch.cat([tr[:-n], mid_t, t2[n:]])
        else:
            rot, tr = torch.cat([rot, r2]), torch.cat([tr, t2])
    return Motion(rot, tr, list(motions[0].joint_names), motions[0].fps)


__all__ = ["GRAVITY", "MOTIONS", "arm_swing", "blend", "concat", "jump", "kick",
           "make_motion", "run", "sit_stand", "slerp_rotations", "twirl", "walk"]
