"""Robot kinematics from ``urdf/mds.urdf``: numpy FK/Jacobian for the arms, whole-tree link poses.

The URDF is the single source of truth. It is parsed here with the standard library (no yourdfpy, no torch),
so the console, the viewer and the collision gate get forward kinematics without heavy imports. The tests
cross-check it against pytorch-kinematics (test/support/torch_kinematics.py; torch is a test requirement only).

Arm frames follow the original IK (specs section e.1): the arm chain runs from ``torso`` (robot frame,
midway between the shoulders, x forward, y left, z up) to ``left_tool``/``right_tool`` (mid-hand, 0.0635 m
below the wrist); joint order ``[SP, SR, SY, EP, WY, WR]``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from mds_ach.paths import urdf_path

ARMS: tuple[str, str] = ("left", "right")
ARM_ROOT = "torso"
_NEXT, _PREV = [1, 2, 0], [2, 0, 1]  # (a x b)_i = a_next b_prev - a_prev b_next
_REVOLUTE = ("revolute", "continuous")


# --------------------------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class Geometry:
    """One visual or collision primitive: ``kind`` box|cylinder|sphere|mesh, placed by ``origin`` (4x4, link frame).

    ``size`` is (x, y, z) for a box, (radius, length) for a cylinder (axis along local z), (radius,) for a sphere.
    """

    kind: str
    size: tuple[float, ...]
    origin: np.ndarray
    rgba: tuple[float, float, float, float] | None = None
    filename: str = ""


@dataclass(frozen=True)
class Link:
    name: str
    visuals: tuple[Geometry, ...]
    collisions: tuple[Geometry, ...]


@dataclass(frozen=True)
class Joint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4, child joint frame in the parent link frame at q = 0
    axis: np.ndarray  # unit vector in the joint frame
    lower: float
    upper: float
    velocity: float
    effort: float

    @property
    def actuated(self) -> bool:
        return self.type in _REVOLUTE or self.type == "prismatic"


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _floats(text: str | None, n: int, default: float = 0.0) -> tuple[float, ...]:
    if text is None:
        return (default,) * n
    vals = tuple(float(v) for v in text.split())
    if len(vals) != n:
        raise ValueError(f"expected {n} numbers, got {text!r}")
    return vals


def _origin(elem: ET.Element | None) -> np.ndarray:
    T = np.eye(4)
    if elem is not None:
        T[:3, :3] = rpy_matrix(*_floats(elem.get("rpy"), 3))
        T[:3, 3] = _floats(elem.get("xyz"), 3)
    return T


def _geometry(elem: ET.Element, materials: Mapping[str, tuple[float, ...]]) -> Geometry:
    geo = elem.find("geometry")
    if geo is None or len(geo) != 1:
        raise ValueError("a visual/collision needs exactly one geometry element")
    shape = geo[0]
    if shape.tag == "box":
        kind, size, fname = "box", _floats(shape.get("size"), 3), ""
    elif shape.tag == "cylinder":
        kind, size, fname = "cylinder", (float(shape.get("radius", "0")), float(shape.get("length", "0"))), ""
    elif shape.tag == "sphere":
        kind, size, fname = "sphere", (float(shape.get("radius", "0")),), ""
    elif shape.tag == "mesh":
        kind, size, fname = "mesh", _floats(shape.get("scale"), 3, 1.0), shape.get("filename", "")
    else:
        raise ValueError(f"unsupported geometry {shape.tag!r}")
    rgba = None
    mat = elem.find("material")
    if mat is not None:
        color = mat.find("color")
        if color is not None:
            rgba = _floats(color.get("rgba"), 4)
        else:
            rgba = materials.get(mat.get("name", ""))
    return Geometry(kind, size, _origin(elem.find("origin")), rgba, fname)  # type: ignore[arg-type]


class RobotModel:
    """The parsed URDF tree: links with their primitives, joints with origins, axes and limits."""

    def __init__(self, root: ET.Element, source: str = "") -> None:
        self.name = root.get("name", "")
        self.source = source
        materials: dict[str, tuple[float, ...]] = {}
        for mat in root.findall("material"):
            color = mat.find("color")
            if color is not None:
                materials[mat.get("name", "")] = _floats(color.get("rgba"), 4)
        self.links: dict[str, Link] = {}
        for el in root.findall("link"):
            name = el.get("name", "")
            self.links[name] = Link(
                name,
                tuple(_geometry(v, materials) for v in el.findall("visual")),
                tuple(_geometry(c, materials) for c in el.findall("collision")),
            )
        self.joints: dict[str, Joint] = {}
        for el in root.findall("joint"):
            jtype = el.get("type", "")
            limit = el.find("limit")
            lower = float(limit.get("lower", "0")) if limit is not None else 0.0
            upper = float(limit.get("upper", "0")) if limit is not None else 0.0
            if jtype == "continuous":
                lower, upper = -math.inf, math.inf
            axis_el = el.find("axis")
            axis = np.array(_floats(axis_el.get("xyz") if axis_el is not None else "1 0 0", 3))
            norm = float(np.linalg.norm(axis))
            self.joints[el.get("name", "")] = Joint(
                name=el.get("name", ""),
                type=jtype,
                parent=el.find("parent").get("link", ""),  # type: ignore[union-attr]
                child=el.find("child").get("link", ""),  # type: ignore[union-attr]
                origin=_origin(el.find("origin")),
                axis=axis / norm if norm > 0 else axis,
                lower=lower,
                upper=upper,
                velocity=float(limit.get("velocity", "0")) if limit is not None else 0.0,
                effort=float(limit.get("effort", "0")) if limit is not None else 0.0,
            )
        self._parent_joint = {j.child: j for j in self.joints.values()}
        roots = [n for n in self.links if n not in self._parent_joint]
        if len(roots) != 1:
            raise ValueError(f"URDF {source}: expected one root link, found {roots}")
        self.root = roots[0]

    @property
    def actuated_joints(self) -> tuple[str, ...]:
        return tuple(n for n, j in self.joints.items() if j.actuated)

    def limits(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) arrays for the named joints, in that order."""
        return (np.array([self.joints[n].lower for n in names]), np.array([self.joints[n].upper for n in names]))

    def chain(self, root: str, tip: str) -> list[Joint]:
        """Joints on the path from ``root`` down to ``tip`` (tip must be a descendant of root)."""
        path: list[Joint] = []
        link = tip
        while link != root:
            joint = self._parent_joint.get(link)
            if joint is None:
                raise ValueError(f"link {tip!r} is not below {root!r}")
            path.append(joint)
            link = joint.parent
        return path[::-1]

    def link_poses(self, q: Mapping[str, float] | None = None, root: str | None = None) -> dict[str, np.ndarray]:
        """4x4 pose of every link in the ``root`` frame (default the URDF root) for joint values ``q`` (missing = 0).

        Cheap (a few tens of microseconds): meant for viewers and collision checks of one configuration.
        """
        q = q or {}
        poses: dict[str, np.ndarray] = {self.root: np.eye(4)}
        pending = [self.root]
        children: dict[str, list[Joint]] = {}
        for j in self.joints.values():
            children.setdefault(j.parent, []).append(j)
        while pending:
            parent = pending.pop()
            for j in children.get(parent, ()):
                poses[j.child] = poses[parent] @ j.origin @ _joint_motion(j, float(q.get(j.name, 0.0)))
                pending.append(j.child)
        if root is not None and root != self.root:
            inv = np.linalg.inv(poses[root])
            poses = {name: inv @ T for name, T in poses.items()}
        return poses


def joint_transform(joint: Joint, value: float) -> np.ndarray:
    """4x4 pose of the joint's child link in its parent link's frame at ``value`` (a /tf transform)."""
    return joint.origin @ _joint_motion(joint, value)


def _joint_motion(joint: Joint, value: float) -> np.ndarray:
    T = np.eye(4)
    if joint.type in _REVOLUTE:
        T[:3, :3] = axis_angle(joint.axis, value)
    elif joint.type == "prismatic":
        T[:3, 3] = joint.axis * value
    return T


def quaternion_wxyz(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a 3x3 rotation matrix (Shepperd's method).

    Scalar code on purpose: the viewer and the bridge's /tf convert a few dozen poses per update, where a batched
    converter (viser's SO3.from_matrix) costs ~30x more per call.
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = rotation[:3, :3].tolist()
    trace = m00 + m11 + m22
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        return 0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s
    if m00 > m11 and m00 > m22:
        s = 2.0 * math.sqrt(1.0 + m00 - m11 - m22)
        return (m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s
    if m11 > m22:
        s = 2.0 * math.sqrt(1.0 + m11 - m00 - m22)
        return (m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s
    s = 2.0 * math.sqrt(1.0 + m22 - m00 - m11)
    return (m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s


def axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues)."""
    K = _skew(axis)
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def load_model(path: str | Path | None = None) -> RobotModel:
    """Parse a URDF (default: the package's ``urdf/mds.urdf``; that one is cached)."""
    if path is None:
        return _default_model()
    return RobotModel(ET.parse(path).getroot(), str(path))


@lru_cache(maxsize=1)
def _default_model() -> RobotModel:
    path = urdf_path()
    return RobotModel(ET.parse(path).getroot(), str(path))


# --------------------------------------------------------------------------------------------- arms


def arm_name(arm: str | int) -> str:
    """Normalise an arm selector: 'left'/'right' (any case, or 'l'/'r') or the legacy ints LEFT=1, RIGHT=0."""
    if isinstance(arm, int | np.integer) and not isinstance(arm, bool):
        if arm == 1:
            return "left"
        if arm == 0:
            return "right"
    elif isinstance(arm, str):
        a = arm.strip().lower()
        if a in ("left", "l"):
            return "left"
        if a in ("right", "r"):
            return "right"
    raise ValueError(f"unknown arm {arm!r}: use 'left' or 'right' (or LEFT=1 / RIGHT=0)")


class ArmKinematics:
    """Batched FK and geometric Jacobian of one arm (torso -> tool point), from the URDF chain.

    Every method takes joint vectors of shape (..., 6) in the IK order and works on any leading batch
    shape. Poses are in the torso (robot) frame.
    """

    def __init__(self, model: RobotModel, arm: str | int) -> None:
        self.arm = arm_name(arm)
        self.tip = f"{self.arm}_tool"
        chain = model.chain(ARM_ROOT, self.tip)
        moving = [j for j in chain if j.actuated]
        if any(j.type == "prismatic" for j in moving):
            raise ValueError("arm chains must be revolute")
        self.joint_names: tuple[str, ...] = tuple(j.name for j in moving)
        self.lower, self.upper = model.limits(self.joint_names)
        # Fold the fixed transforms into the next joint's origin; whatever follows the last joint is the tail.
        origins: list[np.ndarray] = []
        pending = np.eye(4)
        for j in chain:
            pending = pending @ j.origin
            if j.actuated:
                origins.append(pending)
                pending = np.eye(4)
        # The tool frame is usually parallel to the last link: skip that product then.
        self._tail_R = None if np.allclose(pending[:3, :3], np.eye(3), atol=0) else pending[:3, :3].copy()
        self._tail_p = pending[:3, 3].copy()
        self._tail_floats = tuple(float(v) for v in self._tail_p)
        self._origin_p = np.array([T[:3, 3] for T in origins])  # (n, 3)
        Ro = np.array([T[:3, :3] for T in origins])  # (n, 3, 3)
        K = np.array([_skew(j.axis) for j in moving])
        # R_i(q) = Ro_i @ (I + sin q K + (1 - cos q) K^2): three constant matrices per joint.
        self._A0 = Ro
        self._A1 = Ro @ K
        self._A2 = Ro @ K @ K
        axis_in_parent = np.einsum("nij,nj->ni", Ro, np.array([j.axis for j in moving]))  # (n, 3)
        self._origin_and_axis = np.stack([self._origin_p, axis_in_parent], axis=-1)  # (n, 3, 2)
        # Plain-float chain for fk_jacobian_scalar: possible when every joint frame stays parallel to its
        # parent and turns about +-x, +-y or +-z (true for the MDS arms, as for most URDF arms).
        self.scalar_chain: tuple[tuple[int, float, float, float, float], ...] | None = None
        if all(np.allclose(R, np.eye(3), atol=0) for R in Ro) and self._tail_R is None:
            chain_data = []
            for j, t in zip(moving, self._origin_p, strict=True):
                k = int(np.argmax(np.abs(j.axis)))
                if abs(abs(j.axis[k]) - 1.0) > 1e-15:
                    break
                chain_data.append((k, float(np.sign(j.axis[k])), float(t[0]), float(t[1]), float(t[2])))
            else:
                self.scalar_chain = tuple(chain_data)

    @property
    def dof(self) -> int:
        return len(self.joint_names)

    def _joint_rotations(self, q: np.ndarray) -> np.ndarray:
        s = np.sin(q)[..., None, None]
        c1 = (1.0 - np.cos(q))[..., None, None]
        return self._A0 + s * self._A1 + c1 * self._A2  # (..., n, 3, 3)

    def _frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World axes (..., n, 3) and positions (..., n, 3) of the joints, the last link's rotation and position."""
        Rj = self._joint_rotations(q)
        before = np.empty(Rj.shape)  # rotation of the frame each joint's origin is expressed in
        before[..., 0, :, :] = np.eye(3)
        R = Rj[..., 0, :, :]
        for i in range(1, self.dof):
            before[..., i, :, :] = R
            R = R @ Rj[..., i, :, :]
        # One product gives each joint's world axis and the world step from the previous joint to it.
        both = before @ self._origin_and_axis  # (..., n, 3, 2)
        points = np.cumsum(both[..., 0], axis=-2)
        return both[..., 1], points, R, points[..., -1, :]

    def fk(self, q: np.ndarray | Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """Tool rotation (..., 3, 3) and position (..., 3)."""
        q = np.asarray(q, dtype=float)
        Rj = self._joint_rotations(q)
        R = Rj[..., 0, :, :]
        p = np.broadcast_to(self._origin_p[0], q.shape[:-1] + (3,))
        for i in range(1, self.dof):
            p = p + R @ self._origin_p[i]
            R = R @ Rj[..., i, :, :]
        return (R if self._tail_R is None else R @ self._tail_R), p + R @ self._tail_p

    def fk_jacobian(self, q: np.ndarray | Sequence[float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tool rotation, position and the geometric Jacobian (..., 6, n): rows v (m/rad) then w (rad/rad)."""
        q = np.asarray(q, dtype=float)
        axes, points, R, p_last = self._frames(q)
        p_tool = p_last + R @ self._tail_p
        r = p_tool[..., None, :] - points
        # v_i = axis_i x (p_tool - p_i), written with index permutations: np.cross is slow on small arrays.
        v = axes[..., _NEXT] * r[..., _PREV] - axes[..., _PREV] * r[..., _NEXT]
        J = np.concatenate([v, axes], axis=-1).swapaxes(-1, -2)
        return (R if self._tail_R is None else R @ self._tail_R), p_tool, J

    def fk_jacobian_scalar(self, q: Sequence[float]) -> tuple[list[float], list[float], list[list[float]]]:
        """``fk_jacobian`` for one joint vector in plain Python floats: several times faster than numpy on a
        single 6-joint arm, where numpy's per-call cost dominates. Returns R (9 floats, row-major), p (3) and
        the Jacobian as n columns [vx, vy, vz, wx, wy, wz]. Needs ``scalar_chain`` (not None)."""
        chain = self.scalar_chain
        if chain is None:
            raise ValueError(f"the {self.arm} arm chain has joints off the principal axes: use fk_jacobian")
        r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        px = py = pz = 0.0
        axes = []
        points = []
        for (k, sign, tx, ty, tz), angle in zip(chain, q, strict=True):
            if tx or ty or tz:
                px += r[0] * tx + r[1] * ty + r[2] * tz
                py += r[3] * tx + r[4] * ty + r[5] * tz
                pz += r[6] * tx + r[7] * ty + r[8] * tz
            axes.append((sign * r[k], sign * r[3 + k], sign * r[6 + k]))
            points.append((px, py, pz))
            # R <- R @ Rot(axis k, angle): the other two columns a, b turn into each other.
            c, s = math.cos(angle), sign * math.sin(angle)
            a, b = _NEXT[k], _PREV[k]
            ca, cb = r[a], r[b]
            r[a], r[b] = ca * c + cb * s, cb * c - ca * s
            ca, cb = r[3 + a], r[3 + b]
            r[3 + a], r[3 + b] = ca * c + cb * s, cb * c - ca * s
            ca, cb = r[6 + a], r[6 + b]
            r[6 + a], r[6 + b] = ca * c + cb * s, cb * c - ca * s
        tx, ty, tz = self._tail_floats
        px += r[0] * tx + r[1] * ty + r[2] * tz
        py += r[3] * tx + r[4] * ty + r[5] * tz
        pz += r[6] * tx + r[7] * ty + r[8] * tz
        columns = []
        for (ax, ay, az), (x, y, z) in zip(axes, points, strict=True):
            dx, dy, dz = px - x, py - y, pz - z
            columns.append([ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx, ax, ay, az])
        return r, [px, py, pz], columns

    def fk_matrix(self, q: np.ndarray | Sequence[float]) -> np.ndarray:
        """Homogeneous tool pose(s) (..., 4, 4)."""
        R, p = self.fk(q)
        T = np.zeros(R.shape[:-2] + (4, 4))
        T[..., :3, :3] = R
        T[..., :3, 3] = p
        T[..., 3, 3] = 1.0
        return T

    def joint_points(self, q: np.ndarray | Sequence[float]) -> dict[str, np.ndarray]:
        """Shoulder, elbow, wrist and tool positions (..., 3): the skeleton for viewers and quick checks."""
        q = np.asarray(q, dtype=float)
        _, points, R, _ = self._frames(q)
        return {"shoulder": points[..., 0, :], "elbow": points[..., 3, :], "wrist": points[..., 4, :],
                "tool": points[..., -1, :] + R @ self._tail_p}

    def clamp(self, q: np.ndarray) -> np.ndarray:
        return np.clip(q, self.lower, self.upper)

    def within_limits(self, q: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        return np.all((q >= self.lower - tol) & (q <= self.upper + tol), axis=-1)


@lru_cache(maxsize=4)
def _arm_cached(arm: str) -> ArmKinematics:
    return ArmKinematics(_default_model(), arm)


def arm_kinematics(arm: str | int) -> ArmKinematics:
    """The cached ``ArmKinematics`` of the package URDF for 'left'/'right'."""
    return _arm_cached(arm_name(arm))


def fk_matrix(q: np.ndarray | Sequence[float], arm: str | int) -> np.ndarray:
    """4x4 tool pose of one arm in the torso frame (batched over leading dimensions)."""
    return arm_kinematics(arm).fk_matrix(q)


def euler_zyx(R: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) of rotation matrices (..., 3, 3), the original ``getRot`` Z-Y-X extraction.

    roll = atan2(R21, R22), pitch = atan2(-R20, sqrt(R21^2 + R22^2)), yaw = atan2(R10, R00).
    """
    R = np.asarray(R, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def rotation_zyx(roll: Any, pitch: Any, yaw: Any) -> np.ndarray:
    """Rz(yaw) Ry(pitch) Rx(roll), the inverse of ``euler_zyx`` (batched over array inputs)."""
    r, p, y = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float), np.asarray(yaw, float))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )
