"""BVH (Biovision hierarchy) import and export.

A BVH file stores a joint tree of rest ``OFFSET`` s (the rest frames of all
joints are aligned with the world axes) and, per frame, each joint's Euler
channels in its local frame: channels listed ``Zrotation Xrotation Yrotation``
mean ``R = R_Z R_X R_Y`` (intrinsic ``"ZXY"``), in degrees.  Because the rest
frames are world-aligned, these matrices are exactly the local rotations
"relative to the parent in world-aligned rest axes" of
:func:`garmentgnn.body.forward_kinematics`.

Conventions of this module:

* Up axis.  BVH files are usually Y-up with the figure facing +Z; ours is Z-up
  facing -Y (metres).  ``up="Y"`` (the default) converts with the rotation
  ``C = R_X(+90 deg)``: ``(x, y, z)_file -> (x, -z, y)``, so +Y (up) becomes +Z,
  +Z (the figure's front) becomes -Y and +X (the figure's left) stays +X.
  Rotations are conjugated, ``R -> C R C^T``.  ``up="Z"`` reads/writes the axes
  as they are.
* Units.  ``scale`` is metres per file unit (``0.01`` for centimetre files;
  ``0.0254`` for inches) both when loading and saving.
* Root translation.  The root's position channels hold its absolute position
  (the convention of Blender's importer); ``Motion.translation`` is that minus
  the root's rest ``OFFSET``, so ``forward_kinematics(rot, rest_joints, parents,
  translation)`` reproduces the file's joint positions.  Position channels of
  non-root joints (bone stretching) cannot be represented and are ignored with a
  warning.
* ``End Site`` entries are not joints; their offsets are recorded in
  :attr:`BVHHierarchy.end_sites` (keyed by the joint that holds them) and
  written back by :func:`save_bvh`.
"""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from garmentgnn.body.skeleton import Skeleton
from garmentgnn.geometry.rotations import (axis_angle_to_matrix, matrix_to_axis_angle,
                                           matrix_to_euler, unwrap_axis_angle)
from garmentgnn.motion.retarget import guess_roles
from garmentgnn.motion.sequence import Motion

_CHANNELS = {f"{a}{kind}": (kind, a) for a in "XYZ" for kind in ("position", "rotation")}
_CHANNELS_LOWER = {k.lower(): k for k in _CHANNELS}
# (x, y, z)_Yup -> (x, -z, y)_Zup: a rotation of +90 deg about X
_Y_TO_Z = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)


@dataclass
class BVHHierarchy:
    """The joint tree of a BVH file (in metres and in our axes after conversion).

    Attributes:
        joint_names: ``S`` joint names in file (depth-first) order.
        parents: ``[S]`` parent indices, root ``-1``.
        offsets: ``[S, 3]`` rest offsets from the parent (the root's: its rest position).
        channels: per joint, its channel names in file order (e.g.
            ``["Xposition", ..., "Zrotation", "Xrotation", "Yrotation"]``).
        end_sites: joint name -> ``[3]`` offset of the ``End Site`` it holds.
    """

    joint_names: List[str]
    parents: Tensor
    offsets: Tensor
    channels: List[List[str]]
    end_sites: Dict[str, Tensor] = field(default_factory=dict)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def rotation_orders(self) -> List[str]:
        """Per joint, its rotation channels' axes in order (``"ZXY"``; ``""`` if none)."""
        return ["".join(c[0] for c in ch if c.endswith("rotation")) for ch in self.channels]

    @property
    def rest_joints(self) -> Tensor:
        """``[S, 3]`` rest joint positions (offsets accumulated down the tree)."""
        pos = self.offsets.clone()
        for k in range(1, self.num_joints):
            pos[k] = pos[int(self.parents[k])] + self.offsets[k]
        return pos

    def to_skeleton(self, roles: Optional[Dict[str, str]] = None) -> Skeleton:
        """A :class:`Skeleton`; ``roles`` default to those guessed from common
        joint-naming schemes (CMU, Mixamo, SMPL), see
        :func:`garmentgnn.motion.retarget.guess_roles`."""
        return Skeleton(list(self.joint_names), self.parents.clone(),
                        guess_roles(self.joint_names) if roles is None else dict(roles))


def _err(lineno: int, msg: str) -> ValueError:
    return ValueError(f"BVH line {lineno}: {msg}")


def _floats(lineno: int, tokens: List[str], what: str) -> List[float]:
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        raise _err(lineno, f"{what}: non-numeric value in {' '.join(tokens)!r}") from None
    if not all(math.isfinite(v) for v in vals):
        raise _err(lineno, f"{what}: NaN/inf value in {' '.join(tokens)!r}")
    return vals


def _statements(lines: List[str]):
    """Split hierarchy lines into ``(lineno, keyword, args)``; braces are statements."""
    for i, line in enumerate(lines):
        toks = line.replace("{", " { ").replace("}", " } ").split()
        j = 0
        while j < len(toks):
            if toks[j] in "{}":
                yield i + 1, toks[j], []
                j += 1
                continue
            k = j + 1
            while k < len(toks) and toks[k] not in ("{", "}"):
                k += 1
            yield i + 1, toks[j], toks[j + 1:k]
            j = k


def _decode(data: bytes, where: str) -> str:
    """``data`` as UTF-8 text; a byte that is not is a ``ValueError`` naming ``where``,
    the byte's offset and its line: read through a replacement character, a joint name
    would match no joint of the body and leave that joint silently at rest."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise ValueError(f"{where}: byte 0x{data[exc.start]:02X} at offset {exc.start} (BVH "
                         f"line {line}) is not UTF-8 text; a joint name read through it "
                         f"would match no joint; save the file as UTF-8 (or give the "
                         f"joint an ASCII name)") from None


def _read_source(source) -> str:
    if isinstance(source, os.PathLike) or (isinstance(source, str) and "\n" not in source
                                           and "HIERARCHY" not in source):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise ValueError(f"`source`: no such BVH file {path!r} (pass a path or the BVH text)")
        with open(path, "rb") as f:
            return _decode(f.read(), path)
    if isinstance(source, bytes):
        return _decode(source, "`source`")
    if not isinstance(source, str):
        raise ValueError(f"`source`: expected a path or the BVH text, got {type(source).__name__}")
    return source


def _check_up(up: str) -> str:
    if not isinstance(up, str) or up.upper() not in ("Y", "Z"):
        raise ValueError(f"`up`: expected 'Y' (convert a Y-up file to our Z-up) or 'Z' "
                         f"(no conversion), got {up!r}")
    return up.upper()


def _check_scale(scale) -> float:
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) \
            or not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"`scale`: expected metres per file unit > 0 (0.01 for centimetres), "
                         f"got {scale!r}")
    return float(scale)


def parse_bvh(text: str) -> Tuple[List[str], List[int], np.ndarray, List[List[str]],
                                   Dict[str, np.ndarray], np.ndarray, float]:
    """Low-level parse in file units and axes: names, parents, offsets ``[S, 3]``,
    channels, end sites, frame data ``[T, C]`` and the frame time."""
    lines = text.splitlines()
    motion_line = next((i for i, s in enumerate(lines) if s.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise ValueError("BVH: no MOTION section found; is this a BVH file?")
    names: List[str] = []
    parents: List[int] = []
    offsets: List[Optional[List[float]]] = []
    channels: List[List[str]] = []
    end_sites: Dict[str, np.ndarray] = {}
    stack: List[Tuple[str, int]] = []  # ("joint", index) or ("end", parent index)
    pending: Optional[Tuple[str, int, int]] = None  # kind, index, line awaiting "{"
    started = done = False
    end_offset: Optional[List[float]] = None
    for lineno, kw, args in _statements(lines[:motion_line]):
        key = kw.upper()
        if not started:
            if key != "HIERARCHY":
                raise _err(lineno, f"expected 'HIERARCHY', got {kw!r}")
            started = True
            continue
        if done:
            raise _err(lineno, f"unexpected {kw!r} after the root joint was closed "
                               "(only one ROOT is supported)")
        if pending is not None and kw != "{":
            raise _err(lineno, f"expected '{{' after line {pending[2]}, got {kw!r}")
        if key in ("ROOT", "JOINT"):
            if not args:
                raise _err(lineno, f"{kw} without a name")
            if key == "ROOT" and (names or stack):
                raise _err(lineno, "a second ROOT; only one skeleton per file is supported")
            if key == "JOINT" and not stack:
                raise _err(lineno, "JOINT outside the ROOT's braces")
            if stack and stack[-1][0] == "end":
                raise _err(lineno, "a joint inside an End Site")
            name = " ".join(args)
            if "\ufffd" in name:
                raise _err(lineno, f"joint name {name!r} holds a character that stands for "
                                   f"a byte that was not UTF-8 text (U+FFFD); it would match "
                                   f"no joint; save the file as UTF-8 (or give the joint an "
                                   f"ASCII name)")
            if name in names:
                raise _err(lineno, f"duplicate joint name {name!r}")
            names.append(name)
            parents.append(stack[-1][1] if stack else -1)
            offsets.append(None)
            channels.append([])
            pending = ("joint", len(names) - 1, lineno)
        elif key == "END":
            if not stack or stack[-1][0] != "joint":
                raise _err(lineno, "End Site outside a joint")
            pending = ("end", stack[-1][1], lineno)
            end_offset = None
        elif kw == "{":
            if pending is None:
                raise _err(lineno, "unexpected '{'")
            stack.append((pending[0], pending[1]))
            pending = None
        elif kw == "}":
            if not stack:
                raise _err(lineno, "unbalanced '}'")
            kind, idx = stack.pop()
            if kind == "joint" and offsets[idx] is None:
                raise _err(lineno, f"joint {names[idx]!r} has no OFFSET")
            if kind == "end":
                if end_offset is None:
                    raise _err(lineno, f"End Site of {names[idx]!r} has no OFFSET")
                end_sites[names[idx]] = np.array(end_offset)
            if not stack:
                done = True
        elif key == "OFFSET":
            if not stack:
                raise _err(lineno, "OFFSET outside a joint")
            if len(args) != 3:
                raise _err(lineno, f"OFFSET needs 3 numbers, got {len(args)}")
            vals = _floats(lineno, args, "OFFSET")
            if stack[-1][0] == "end":
                end_offset = vals
            else:
                offsets[stack[-1][1]] = vals
        elif key == "CHANNELS":
            if not stack or stack[-1][0] != "joint":
                raise _err(lineno, "CHANNELS outside a joint")
            try:
                n = int(args[0])
            except (IndexError, ValueError):
                raise _err(lineno, "CHANNELS needs a count, e.g. 'CHANNELS 3 Zrotation "
                                   "Xrotation Yrotation'") from None
            if n != len(args) - 1:
                raise _err(lineno, f"CHANNELS says {n} channels but lists {len(args) - 1}")
            chans = []
            for c in args[1:]:
                if c.lower() not in _CHANNELS_LOWER:
                    raise _err(lineno, f"unknown channel {c!r}; expected one of "
                                       f"{sorted(_CHANNELS)}")
                chans.append(_CHANNELS_LOWER[c.lower()])
            if len(set(chans)) != len(chans):
                raise _err(lineno, f"repeated channel in {args[1:]}")
            channels[stack[-1][1]] = chans
        else:
            raise _err(lineno, f"unknown keyword {kw!r}")
    if not started:
        raise ValueError("BVH: missing 'HIERARCHY'")
    if not names:
        raise ValueError("BVH: no ROOT joint in the HIERARCHY section")
    if not done or pending is not None:
        raise _err(motion_line + 1, "MOTION before the hierarchy's braces were closed")

    # MOTION section
    rest = [(i + 1, s.strip()) for i, s in enumerate(lines[motion_line + 1:], motion_line + 1)]
    rest = [(n, s) for n, s in rest if s]
    if len(rest) < 2:
        raise _err(motion_line + 1, "MOTION needs 'Frames:' and 'Frame Time:' lines")
    (n1, l1), (n2, l2) = rest[0], rest[1]
    if not l1.lower().startswith("frames:"):
        raise _err(n1, f"expected 'Frames: <count>', got {l1!r}")
    try:
        num_frames = int(l1.split(":", 1)[1])
    except ValueError:
        raise _err(n1, f"bad frame count in {l1!r}") from None
    if num_frames < 0:
        raise _err(n1, f"negative frame count {num_frames}")
    if not l2.lower().replace(" ", "").startswith("frametime:"):
        raise _err(n2, f"expected 'Frame Time: <seconds>', got {l2!r}")
    frame_time = _floats(n2, [l2.split(":", 1)[1].strip()], "Frame Time")[0]
    if frame_time <= 0:
        raise _err(n2, f"Frame Time must be positive, got {frame_time}")
    data_lines = rest[2:]
    if len(data_lines) != num_frames:
        raise _err(n1, f"'Frames: {num_frames}' but the file has {len(data_lines)} frame lines")
    C = sum(len(c) for c in channels)
    data = np.zeros((num_frames, C))
    for f, (n, line) in enumerate(data_lines):
        toks = line.split()
        if len(toks) != C:
            raise _err(n, f"frame {f} has {len(toks)} values, the hierarchy has {C} channels")
        data[f] = _floats(n, toks, f"frame {f}")
    return (names, parents, np.array(offsets, dtype=np.float64).reshape(-1, 3), channels,
            end_sites, data, frame_time)


def _fps(frame_time: float) -> float:
    fps = 1.0 / frame_time
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) < 1e-3 * fps else fps


def load_bvh(source: Union[str, os.PathLike], *, scale: float = 1.0, up: str = "Y",
             dtype: torch.dtype = torch.float32) -> Tuple[BVHHierarchy, Motion]:
    """Read a BVH file (path, or the text itself).

    Args:
        source: a path, or the BVH text.
        scale: metres per file unit (``0.01`` for centimetre files).
        up: ``"Y"`` converts a Y-up file (facing +Z) to our Z-up (facing -Y);
            ``"Z"`` keeps the axes.
        dtype: of the returned tensors.

    Returns:
        ``(hierarchy, motion)``; ``motion.fps = 1 / Frame Time`` (rounded to an
        integer when within 0.1%), ``motion.rotations`` are local axis-angle
        rotations in our axes.  Pose with ``hierarchy.rest_joints``, e.g.
        ``forward_kinematics(motion.rotations, hierarchy.rest_joints,
        hierarchy.parents, motion.translation)``.

    Raises:
        ValueError: corrupt files, naming the offending line.
    """
    scale, up = _check_scale(scale), _check_up(up)
    names, parents, offsets, channels, end_sites, data, frame_time = parse_bvh(
        _read_source(source))
    T, S = data.shape[0], len(names)
    offsets_t = torch.from_numpy(offsets)
    R = torch.eye(3, dtype=torch.float64).expand(T, S, 3, 3).clone()
    root_pos = offsets_t[0].expand(T, 3).clone()
    col = 0
    ignored = []
    for j, chans in enumerate(channels):
        for c in chans:
            kind, axis = _CHANNELS[c]
            v = torch.from_numpy(data[:, col])
            col += 1
            if kind == "rotation":
                aa = torch.zeros(T, 3, dtype=torch.float64)
                aa[:, "XYZ".index(axis)] = torch.deg2rad(v)
                R[:, j] = R[:, j] @ axis_angle_to_matrix(aa)
            elif j == 0:
                root_pos[:, "XYZ".index(axis)] = v
            else:
                ignored.append(names[j])
    if ignored:
        warnings.warn(f"BVH: position channels of non-root joints {sorted(set(ignored))} "
                      "are ignored (bone stretching is not supported)", stacklevel=2)
    translation = (root_pos - offsets_t[0]) * scale
    offsets_t = offsets_t * scale
    ends = {k: torch.from_numpy(v) * scale for k, v in end_sites.items()}
    if up == "Y":
        C = _Y_TO_Z
        offsets_t = offsets_t @ C.T
        translation = translation @ C.T
        ends = {k: C @ v for k, v in ends.items()}
        R = C @ R @ C.T
    aa = torch.from_numpy(unwrap_axis_angle(matrix_to_axis_angle(R).numpy())) if T else \
        torch.zeros(0, S, 3, dtype=torch.float64)
    hierarchy = BVHHierarchy(names, torch.tensor(parents, dtype=torch.long),
                             offsets_t.to(dtype), channels,
                             {k: v.to(dtype) for k, v in ends.items()})
    motion = Motion(aa.to(dtype), translation.to(dtype), list(names), _fps(frame_time))
    return hierarchy, motion


def _fmt(v: float, precision: int) -> str:
    s = f"{v:.{precision}f}"
    return "0" if float(s) == 0.0 else s.rstrip("0").rstrip(".") if "." in s else s


def save_bvh(path: Optional[Union[str, os.PathLike]], motion: Motion, skeleton: Skeleton,
             rest_joints: Tensor, *, order: str = "ZXY", up: str = "Y", scale: float = 1.0,
             end_sites: Optional[Dict[str, Tensor]] = None, precision: int = 6) -> str:
    """Write ``motion`` on ``skeleton`` (rest joint positions ``rest_joints [S, 3]``,
    metres, Z-up) as BVH; returns the text (and writes it to ``path`` unless ``None``).

    Every joint gets rotation channels in ``order`` (``"ZXY"`` writes
    ``Zrotation Xrotation Yrotation``, the CMU layout); the root also gets
    ``Xposition Yposition Zposition`` (absolute: rest position + translation).
    Joints are written depth-first (the only order BVH knows), so a skeleton
    whose joint order is not depth-first (the capsule body's) reads back in
    another order; ``retarget(motion, skeleton)`` restores it by name.
    ``up="Y"`` writes the usual Y-up file (inverse of :func:`load_bvh`'s
    conversion); ``scale`` is metres per file unit.  Leaf joints get an
    ``End Site`` from ``end_sites`` (metres, our axes; e.g. a loaded
    hierarchy's) or, by default, half their incoming bone.
    """
    if not isinstance(motion, Motion):
        raise ValueError(f"`motion`: expected a Motion, got {type(motion).__name__}")
    if not isinstance(skeleton, Skeleton):
        raise ValueError(f"`skeleton`: expected a Skeleton, got {type(skeleton).__name__}")
    if list(motion.joint_names) != list(skeleton.joint_names):
        raise ValueError("`motion`: its joint names differ from `skeleton`'s; retarget the "
                         "motion first (garmentgnn.motion.retarget)")
    S = skeleton.num_joints
    J = torch.as_tensor(rest_joints).detach().to(torch.float64)
    if J.shape != (S, 3) or not torch.isfinite(J).all():
        raise ValueError(f"`rest_joints`: expected finite [{S}, 3], got {tuple(J.shape)}")
    order = order.upper() if isinstance(order, str) else order
    if not isinstance(order, str) or sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"`order`: expected a permutation of 'XYZ' such as 'ZXY', got {order!r}")
    up, scale = _check_up(up), _check_scale(scale)
    if isinstance(precision, bool) or not isinstance(precision, int) or not 1 <= precision <= 12:
        raise ValueError(f"`precision`: expected decimals in 1..12, got {precision!r}")
    Ci = _Y_TO_Z.T if up == "Y" else torch.eye(3, dtype=torch.float64)  # ours -> file
    par = skeleton.parents.tolist()
    off = J.clone()
    off[1:] = J[1:] - J[par[1:]]
    off_file = off @ Ci.T / scale
    R = axis_angle_to_matrix(motion.rotations.detach().to(torch.float64))
    R_file = Ci @ R @ Ci.T
    euler = np.rad2deg(np.unwrap(matrix_to_euler(R_file, order).numpy(), axis=0)) \
        if motion.num_frames else np.zeros((0, S, 3))
    root = (J[0] + motion.translation.detach().to(torch.float64)) @ Ci.T / scale
    children: List[List[int]] = [[] for _ in range(S)]
    for k in range(1, S):
        children[par[k]].append(k)
    ends = {} if end_sites is None else dict(end_sites)
    unknown = set(ends) - set(skeleton.joint_names)
    if unknown:
        raise ValueError(f"`end_sites`: unknown joint name(s) {sorted(unknown)}")
    rot_ch = " ".join(f"{a}rotation" for a in order)
    out = ["HIERARCHY"]

    def vec(v) -> str:
        return " ".join(_fmt(float(x), precision) for x in v)

    dfs: List[int] = []  # file order of the joints (and of their channels)

    def write(k: int, depth: int) -> None:
        dfs.append(k)
        ind = "  " * depth
        if k == 0:
            out.append(f"ROOT {skeleton.joint_names[k]}")
        else:
            out.append(f"{ind}JOINT {skeleton.joint_names[k]}")
        out.append(f"{ind}{{")
        out.append(f"{ind}  OFFSET {vec(off_file[k])}")
        if k == 0:
            out.append(f"{ind}  CHANNELS 6 Xposition Yposition Zposition {rot_ch}")
        else:
            out.append(f"{ind}  CHANNELS 3 {rot_ch}")
        for c in children[k]:
            write(c, depth + 1)
        name = skeleton.joint_names[k]
        if name in ends or not children[k]:
            if name in ends:
                e = torch.as_tensor(ends[name], dtype=torch.float64).reshape(3)
            elif k == 0:
                e = torch.tensor([0.0, 0.0, 0.1], dtype=torch.float64)
            else:
                e = 0.5 * off[k]
            out.append(f"{ind}  End Site")
            out.append(f"{ind}  {{")
            out.append(f"{ind}    OFFSET {vec(Ci @ e / scale)}")
            out.append(f"{ind}  }}")
        out.append(f"{ind}}}")

    write(0, 0)
    out.append("MOTION")
    out.append(f"Frames: {motion.num_frames}")
    out.append(f"Frame Time: {1.0 / motion.fps:.10f}")
    for t in range(motion.num_frames):
        vals = [vec(root[t])] + [vec(euler[t, k]) for k in dfs]
        out.append(" ".join(vals))
    text = "\n".join(out) + "\n"
    if path is not None:
        with open(os.fspath(path), "w", encoding="utf-8") as f:
            f.write(text)
    return text


__all__ = ["BVHHierarchy", "load_bvh", "parse_bvh", "save_bvh"]
