"""Inverse kinematics for the MDS arms: damped least squares on the analytic Jacobian, batched restarts.

Two APIs over one solver:

* the legacy functions of the original ``mds_ik.py`` (``getFkArm``, ``getIK``, ``getPosCurrentFromOrder``,
  ``getRot``, ``getJacobian``), so the original examples port unchanged;
* ``IKSolver`` / ``solve`` returning an ``IKResult`` (success, error, iterations, time, ...).

Tasks are 1-6 components in any order from ``p-x p-y p-z t-x t-y t-z`` (``p_x`` spellings accepted):
tool position in the torso frame and the tool orientation as the original's Z-Y-X angles
(roll = t-x, pitch = t-y, yaw = t-z; ``getRot``). The DOFs a task leaves free are used in the null
space to stay close to the seed. Joint limits come from the URDF and are never left.

Success (``Tolerance``) is what users mean by "solved": the task's position components within 1 mm (their
Euclidean norm) and its angles within 0.01 rad, each checked separately (a full pose: the rotation angle
between target and answer; otherwise the norm of the wrapped Z-Y-X angle differences). The original's test,
the norm of all target-minus-current components with m and rad mixed (1 cm by default), is kept as
``Tolerance.mixed``: the legacy ``getIK(..., err=[dtheta, step, tol])`` still means exactly that, and
``IKResult.error`` always reports that mixed norm. The steps are steered differently where the Z-Y-X
angles are singular (pitch = +-pi/2, which is the arm raised forward): a roll+pitch+yaw target is
approached as a rotation, a roll+pitch target as the direction of the world z axis seen from the tool;
single angles (and roll/yaw or pitch/yaw pairs) use the analytic rates of the angles themselves. At
gimbal lock the angles are not unique, so a pose within 1e-6 of the target counts as reached. Angle
targets are canonicalised (``IKResult.target``): roll=0, pitch=2 describes the same tilt as roll=pi,
pitch=pi-2.

The searches run in C (``_iksearch.c``: the same steps and success test, one call per solve) when that
extension was built, else in Python (plain floats for the seed's search, numpy-batched restarts).

No torch here: ``import mds_ach.ik`` stays light.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from mds_ach.kinematics.analytic import ArmGeometry, within
from mds_ach.kinematics.model import ArmKinematics, arm_kinematics, arm_name, euler_zyx

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

_iksearch: Any
try:  # the optional C searches (setup.py builds them when a compiler is there); else the Python ones run
    from mds_ach.kinematics import _iksearch  # type: ignore[attr-defined, no-redef]
except ImportError:  # pragma: no cover - depends on the build
    _iksearch = None

NATIVE_AVAILABLE = _iksearch is not None

TASK_COMPONENTS: tuple[str, ...] = ("p-x", "p-y", "p-z", "t-x", "t-y", "t-z")
# Legacy ik_method / console "dof": the first n of x, y, z, roll, pitch, yaw.
DOF_ORDERS: dict[int, tuple[str, ...]] = {n: TASK_COMPONENTS[:n] for n in range(1, 7)}
DEFAULT_ERR: tuple[float, float, float] = (0.01, 0.01, 0.01)  # legacy getIK err: steps, mixed m+rad tolerance
DEFAULT_TOLERANCE = 1e-3  # m, position components (their Euclidean norm)
DEFAULT_ANGLE_TOLERANCE = 0.01  # rad, orientation components
DEFAULT_ITERATIONS = 1000
_SQRT3 = math.sqrt(3.0)
_TWO_PI = 2.0 * math.pi
# The fast search hands over to the batched ones when its error fell less than 10 % over 5 iterations.
_CREEP_WINDOW, _CREEP_RATIO = 5, 0.9
EXACT = 1e-6  # a pose this close to the target counts as reached whatever its Euler angles (gimbal lock)
# Trust-region update after an accepted / rejected step: (step-limit scale, LM damping) factors.
_ACCEPT = np.array([16.0, 0.5])
_REJECT = np.array([0.5, 4.0])
_MODES = {"position": 0, "euler": 1, "tilt": 2, "full": 3}  # Task.mode as the C searches number it
# C searches: steps one search from a random start may take before the next start (most converge in 10-30).
_NATIVE_PER_START = 60

SafetyCheck = Callable[[np.ndarray, str], bool]


_parsed_orders: dict[object, tuple[int, ...]] = {}  # orders seen (a robot asks for few): parsing costs more than IK


def parse_order(order: Sequence[str] | str) -> tuple[int, ...]:
    """Component indices 0..5 for an order such as ``['p-x', 'p-z', 't-y']`` (also ``'p_x'``, case-insensitive)."""
    key = order if isinstance(order, str) else tuple(order)
    try:
        return _parsed_orders[key]
    except (KeyError, TypeError):  # TypeError: an unhashable item, which the parse below refuses
        pass
    idx = _parse_order(key)
    if len(_parsed_orders) < 256:
        _parsed_orders[key] = idx
    return idx


def _parse_order(order: Sequence[str] | str) -> tuple[int, ...]:
    if isinstance(order, str):
        order = order.replace(",", " ").split()
    idx: list[int] = []
    for item in order:
        key = str(item).strip().lower().replace("_", "-")
        if key not in TASK_COMPONENTS:
            raise ValueError(f"unknown task component {item!r}; use {', '.join(TASK_COMPONENTS)}")
        i = TASK_COMPONENTS.index(key)
        if i in idx:
            raise ValueError(f"task component {item!r} given twice")
        idx.append(i)
    if not idx:
        raise ValueError("empty task order: give 1 to 6 of " + ", ".join(TASK_COMPONENTS))
    return tuple(idx)


def order_for_dof(dof: int) -> tuple[str, ...]:
    """The legacy component order for ``ik_method`` = dof (1..6)."""
    if isinstance(dof, bool) or not isinstance(dof, int | np.integer) or int(dof) not in DOF_ORDERS:
        raise ValueError(f"bad IK dof {dof!r}: must be an integer 1..6 (x, y, z, roll, pitch, yaw in that order)")
    return DOF_ORDERS[int(dof)]


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angles into (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)


_ROWS_A, _COLS_A = [2, 0, 1], [1, 2, 0]


def _rotvec(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation vectors (K, 3) and angles (K,) of rotation matrices (K, 3, 3)."""
    v = 0.5 * (M[:, _ROWS_A, _COLS_A] - M[:, _COLS_A, _ROWS_A])  # vee(M - M^T) / 2 = sin(theta) * axis
    s = np.sqrt((v * v).sum(1))
    c = 0.5 * (M.trace(axis1=1, axis2=2) - 1.0)
    theta = np.arctan2(s, c)
    rv = v * (theta / np.maximum(s, 1e-300))[:, None]  # theta / s -> 1 as theta -> 0 (s = 0 gives v = 0)
    near_pi = (s < 1e-6) & (c < 0)
    if near_pi.any():  # half-turn: the axis is the dominant column of (M + I)
        for k in np.flatnonzero(near_pi):
            B = M[k] + np.eye(3)
            col = B[:, int(np.argmax(np.einsum("ij,ij->j", B, B)))]
            rv[k] = col / np.linalg.norm(col) * theta[k]
    return rv, theta


@dataclass(frozen=True)
class Tolerance:
    """When a pose counts as reached: position within ``position`` (m) and angles within ``angle`` (rad),
    checked separately; or, when ``mixed`` is set, the original's single test instead (the norm of all
    target-minus-current components, m and rad mixed, e.g. the legacy ``getIK`` err[2])."""

    position: float = DEFAULT_TOLERANCE
    angle: float = DEFAULT_ANGLE_TOLERANCE
    mixed: float | None = None

    def __post_init__(self) -> None:
        values = (self.position, self.angle) + (() if self.mixed is None else (self.mixed,))
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"tolerances must be finite and > 0, got {self}")

    @property
    def bound(self) -> float:
        """The angle (or mixed error) beyond which the Euler differences cannot pass: no need to work them out."""
        return _SQRT3 * (self.angle if self.mixed is None else self.mixed)


class Task:
    """A parsed target: which components, canonical target values, and the residual / Jacobian rows."""

    def __init__(self, target: Sequence[float] | np.ndarray, order: Sequence[str] | str,
                 tolerance: Tolerance | float | None = None) -> None:
        """``tolerance``: the success test (a float: the original's mixed one); default 1 mm / 0.01 rad."""
        if tolerance is None:
            tolerance = Tolerance()
        elif not isinstance(tolerance, Tolerance):
            tolerance = Tolerance(mixed=float(tolerance))
        self.tolerance = tolerance
        self._legacy: Task | None = None  # the same target under the original's test, for ``error``
        self._always_exact = False  # work out the Euler differences even where they cannot pass
        self.idx = parse_order(order)
        values = np.array(target, dtype=float).reshape(-1)
        if values.size != len(self.idx):
            raise ValueError(f"target has {values.size} values but the order has {len(self.idx)} components")
        given_list = values.tolist()
        if not all(math.isfinite(v) for v in given_list):
            raise ValueError(f"target contains NaN or Inf: {given_list}")
        self.requested = values
        given = dict(zip(self.idx, given_list, strict=True))
        self.pos_idx = [i for i in self.idx if i < 3]
        angles = {i for i in self.idx if i >= 3}
        canonical = dict(given)
        # Plain floats first (residual_scalar and the C searches use them; the numpy copies are made on demand).
        self._R_target_list: list[float] = []
        self._up_list: list[float] = []
        self.euler_idx: list[int] = []
        if angles == {3, 4, 5}:
            self.mode = "full"
            self._R_target_list = _rotation_zyx_list(given[3], given[4], given[5])
            canonical.update(zip((3, 4, 5), _euler_zyx_list(self._R_target_list), strict=True))
        elif {3, 4} <= angles:
            self.mode = "tilt"
            r, p = given[3], given[4]
            # World z expressed in the tool frame: the third row of Rz Ry(p) Rx(r), independent of yaw.
            b = self._up_list = [-math.sin(p), math.cos(p) * math.sin(r), math.cos(p) * math.cos(r)]
            canonical[3] = math.atan2(b[1], b[2])
            canonical[4] = math.atan2(-b[0], math.hypot(b[1], b[2]))
            self.euler_idx = [5] if 5 in angles else []
        else:
            self.mode = "euler" if angles else "position"
            self.euler_idx = sorted(angles)
        for i in self.euler_idx:
            w = math.remainder(given[i], _TWO_PI)
            canonical[i] = math.pi if w <= -math.pi else w  # (-pi, pi] like wrap_angle
        self.target = np.array([canonical[i] for i in self.idx])
        self._pos_list = [given[i] for i in self.pos_idx]
        self._euler_list = [canonical[i] for i in self.euler_idx]
        # Canonical roll, pitch (and yaw) compared component-wise for the reported error in full/tilt mode.
        self._rotation_list = [canonical[i] for i in {"full": (3, 4, 5), "tilt": (3, 4)}.get(self.mode, ())]
        n_pos = len(self.pos_idx)
        self._pos_sel: slice | list[int] = slice(0, n_pos) if self.pos_idx == list(range(n_pos)) else self.pos_idx
        self._euler_sel = [i - 3 for i in self.euler_idx]

    @property
    def dof(self) -> int:
        return len(self.idx)

    @cached_property
    def pos_target(self) -> np.ndarray:
        """Target values of the position components, in ``pos_idx`` order."""
        return np.array(self._pos_list)

    @cached_property
    def euler_target(self) -> np.ndarray:
        """Canonical targets of the angles compared one by one, in ``euler_idx`` order."""
        return np.array(self._euler_list)

    @cached_property
    def R_target(self) -> np.ndarray | None:
        """The target rotation of a full pose (else None)."""
        return np.array(self._R_target_list).reshape(3, 3) if self._R_target_list else None

    @cached_property
    def up_in_tool(self) -> np.ndarray | None:
        """A roll+pitch target: the world z axis seen from the tool (else None)."""
        return np.array(self._up_list) if self._up_list else None

    @cached_property
    def _rotation_target(self) -> np.ndarray:
        return np.array(self._rotation_list)

    def native_spec(self) -> tuple[Any, ...]:
        """The task as the C searches take it (``_iksearch.c``: parse_task): the same numbers ``residual_scalar``
        uses, so both compute the same rows and score."""
        tol = self.tolerance
        return (_MODES[self.mode], self.pos_idx, self._pos_list, self.euler_idx, self._euler_list,
                self._R_target_list, self._up_list, self._rotation_list, tol.position, tol.angle,
                0.0 if tol.mixed is None else tol.mixed, self._always_exact)

    def residual(self, R: np.ndarray, p: np.ndarray, J: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Batched error rows e (K, r), their Jacobian (K, r, n), the solver's error and the score (K,).

        The solver's error is sqrt(sum of squared position errors and orientation angles), m and rad mixed; it
        measures a roll+pitch(+yaw) target by the rotation angle (smooth everywhere). The score is the success
        test scaled so that <= 1 passes (see ``Tolerance``); its angles are wrapped differences of the Z-Y-X
        angles except for a full pose under the separate test (the rotation angle). At gimbal lock those
        angles are not unique, so a pose within 1e-6 of the target counts with the solver's error.
        """
        rows: list[np.ndarray] = []
        jac: list[np.ndarray] = []
        if self.pos_idx:
            sel = self._pos_sel
            e = self.pos_target - p[:, sel]
            rows.append(e)
            jac.append(J[:, sel, :])
            sq_pos = (e * e).sum(1)
        else:
            sq_pos = np.zeros(p.shape[0])
        if self.mode == "position":
            err = np.sqrt(sq_pos)
            return rows[0], jac[0], err, err / (self.tolerance.mixed or self.tolerance.position)
        Jw = J[:, 3:, :]
        sq_rot = 0.0  # the solver's orientation error, squared
        if self.mode == "full":
            rv, theta = _rotvec(self.R_target @ R.transpose(0, 2, 1))
            rows.append(rv)
            jac.append(Jw)
            sq_rot = theta * theta
        elif self.mode == "tilt":
            u = R @ self.up_in_tool  # (K, 3): where the target's "up" currently points in the world
            s = np.hypot(u[:, 0], u[:, 1])
            theta = np.arctan2(s, u[:, 2])
            scale = theta / np.maximum(s, 1e-12)
            # Rotation vector (u x e_z) * theta / |u x e_z|; upside down (s = 0) any horizontal axis will do.
            rv = np.stack([u[:, 1] * scale, -u[:, 0] * scale, np.zeros_like(s)], axis=-1)
            flipped = (s <= 1e-12) & (u[:, 2] < 0)
            if flipped.any():
                rv[flipped] = (np.pi, 0.0, 0.0)
            rows.append(rv)
            # Spinning about u itself does not change the error: project it out (rank 2 block).
            jac.append(Jw - u[:, :, None] * (u[:, None, :] @ Jw))
            sq_rot = theta * theta
        ang = euler_zyx(R) if self.euler_idx or self.mode != "euler" else None
        sq_ang = np.zeros_like(sq_pos)
        if self.euler_idx:
            assert ang is not None  # computed above whenever euler_idx is set
            e = wrap_angle(self.euler_target - ang[:, self._euler_sel])
            rows.append(e)
            jac.append(_euler_rate_rows(R, self.euler_idx) @ Jw)
            sq_ang = (e * e).sum(1)
        tol = self.tolerance
        err = np.sqrt(sq_pos + sq_ang + sq_rot)
        if tol.mixed is None and self.mode in ("euler", "full"):
            score = np.maximum(np.sqrt(sq_pos) / tol.position, np.sqrt(sq_ang + sq_rot) / tol.angle)
        else:
            mixed = tol.mixed is not None
            angle = err if mixed else np.sqrt(sq_ang + sq_rot)  # what the Euler differences replace, if near
            if self.mode != "euler" and (self._always_exact or np.any(angle <= tol.bound)):
                # Else the Euler differences' norm >= angle / sqrt(3) > tolerance (each bounds its share of
                # the rotation angle), so ``angle`` stands in for it where it cannot pass anyway.
                assert ang is not None  # computed above whenever mode != "euler"
                d = wrap_angle(self._rotation_target - ang[:, : len(self._rotation_target)])
                exact = np.sqrt((sq_pos if mixed else 0.0) + sq_ang + (d * d).sum(1))
                angle = np.where(err <= EXACT, np.minimum(angle, exact), exact)
            score = angle / tol.mixed if tol.mixed is not None else np.maximum(np.sqrt(sq_pos) / tol.position,
                                                                                angle / tol.angle)
        return np.concatenate(rows, axis=1), np.concatenate(jac, axis=1), err, score

    def score(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The success measure (K,) of tool poses: <= 1 passes the tolerance."""
        return self.residual(R, p, np.zeros(p.shape[:1] + (6, 1)))[3]

    def error(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The original's error (K,) of tool poses: the norm of all component differences, m and rad mixed."""
        if self._legacy is None:
            self._legacy = Task(self.requested, [TASK_COMPONENTS[i] for i in self.idx], 1.0)
            self._legacy._always_exact = True
        return self._legacy.score(R, p)

    def residual_scalar(self, R: list[float], p: list[float], cols: list[list[float]]
                        ) -> tuple[list[float], list[list[float]], float, float]:
        """``residual`` for one pose in plain floats (R row-major, Jacobian as columns); rows are lists."""
        e: list[float] = []
        rows: list[list[float]] = []
        sq_pos = 0.0
        for i, t in zip(self.pos_idx, self._pos_list, strict=True):
            d = t - p[i]
            e.append(d)
            rows.append([c[i] for c in cols])
            sq_pos += d * d
        tol = self.tolerance
        if self.mode == "position":
            err = math.sqrt(sq_pos)
            return e, rows, err, err / (tol.mixed or tol.position)
        sq_rot = 0.0
        if self.mode == "full":
            T = self._R_target_list  # M = R_target @ R^T
            M = [T[i] * R[j] + T[i + 1] * R[j + 1] + T[i + 2] * R[j + 2] for i in (0, 3, 6) for j in (0, 3, 6)]
            vx, vy, vz = 0.5 * (M[7] - M[5]), 0.5 * (M[2] - M[6]), 0.5 * (M[3] - M[1])
            sin_t = math.sqrt(vx * vx + vy * vy + vz * vz)
            cos_t = 0.5 * (M[0] + M[4] + M[8] - 1.0)
            theta = math.atan2(sin_t, cos_t)
            if sin_t < 1e-6 and cos_t < 0:  # half-turn: let the batched helper find the axis
                rv = _rotvec(np.array(M).reshape(1, 3, 3))[0][0].tolist()
            else:
                f = theta / sin_t if sin_t > 1e-300 else 1.0
                rv = [vx * f, vy * f, vz * f]
            e += rv
            rows += [[c[3] for c in cols], [c[4] for c in cols], [c[5] for c in cols]]
            sq_rot = theta * theta
        elif self.mode == "tilt":
            b0, b1, b2 = self._up_list
            u0, u1, u2 = (R[0] * b0 + R[1] * b1 + R[2] * b2, R[3] * b0 + R[4] * b1 + R[5] * b2,
                          R[6] * b0 + R[7] * b1 + R[8] * b2)
            sin_t = math.hypot(u0, u1)
            theta = math.atan2(sin_t, u2)
            if sin_t > 1e-12:
                e += [u1 * theta / sin_t, -u0 * theta / sin_t, 0.0]
            else:
                e += [math.pi, 0.0, 0.0] if u2 < 0 else [0.0, 0.0, 0.0]
            along = [u0 * c[3] + u1 * c[4] + u2 * c[5] for c in cols]
            rows += [[c[3 + k] - u * a for c, a in zip(cols, along, strict=True)] for k, u in enumerate((u0, u1, u2))]
            sq_rot = theta * theta
        angles = (math.atan2(R[7], R[8]), math.atan2(-R[6], math.hypot(R[7], R[8])), math.atan2(R[3], R[0]))
        sq_ang = 0.0
        for i, t in zip(self.euler_idx, self._euler_list, strict=True):
            d = math.remainder(t - angles[i - 3], _TWO_PI)
            e.append(d)
            sq_ang += d * d
            if i == 3:  # roll rate = (R00 wx + R10 wy) / cos^2(pitch)
                c2 = max(R[7] * R[7] + R[8] * R[8], 1e-12)
                g = (R[0] / c2, R[3] / c2, 0.0)
            elif i == 4:  # pitch rate = (-R10 wx + R00 wy) / cos(pitch)
                c1 = math.sqrt(max(R[7] * R[7] + R[8] * R[8], 1e-12))
                g = (-R[3] / c1, R[0] / c1, 0.0)
            else:  # yaw rate
                dd = max(R[0] * R[0] + R[3] * R[3], 1e-12)
                g = (-R[0] * R[6] / dd, -R[3] * R[6] / dd, 1.0)
            rows.append([g[0] * c[3] + g[1] * c[4] + g[2] * c[5] for c in cols])
        err = math.sqrt(sq_pos + sq_ang + sq_rot)
        if tol.mixed is None and self.mode in ("euler", "full"):
            return e, rows, err, max(math.sqrt(sq_pos) / tol.position, math.sqrt(sq_ang + sq_rot) / tol.angle)
        mixed = tol.mixed is not None
        angle = err if mixed else math.sqrt(sq_ang + sq_rot)
        if self.mode != "euler" and (self._always_exact or angle <= tol.bound):  # else it cannot pass: see ``residual``
            d2 = sum(math.remainder(t - a, _TWO_PI) ** 2 for t, a in zip(self._rotation_list, angles, strict=False))
            exact = math.sqrt((sq_pos if mixed else 0.0) + sq_ang + d2)
            angle = min(angle, exact) if err <= EXACT else exact
        if tol.mixed is not None:
            return e, rows, err, angle / tol.mixed
        return e, rows, err, max(math.sqrt(sq_pos) / tol.position, angle / tol.angle)


def _rotation_zyx_list(roll: float, pitch: float, yaw: float) -> list[float]:
    """``rotation_zyx`` of one angle triple in plain floats, row-major (numpy costs more than it saves here)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr]


def _euler_zyx_list(R: list[float]) -> list[float]:
    """``euler_zyx`` of one row-major rotation in plain floats."""
    return [math.atan2(R[7], R[8]), math.atan2(-R[6], math.hypot(R[7], R[8])), math.atan2(R[3], R[0])]


def _euler_rate_rows(R: np.ndarray, which: list[int]) -> np.ndarray:
    """Rows g (K, len(which), 3) with d(angle)/dt = g . omega for the Z-Y-X angles (omega in the world frame)."""
    out = np.empty((R.shape[0], len(which), 3))
    c2 = np.maximum(R[:, 2, 1] ** 2 + R[:, 2, 2] ** 2, 1e-12)  # cos^2(pitch)
    for k, i in enumerate(which):
        if i == 3:  # roll = atan2(R21, R22)
            out[:, k, 0] = R[:, 0, 0] / c2
            out[:, k, 1] = R[:, 1, 0] / c2
            out[:, k, 2] = 0.0
        elif i == 4:  # pitch = asin(-R20)
            c = np.sqrt(c2)
            out[:, k, 0] = -R[:, 1, 0] / c
            out[:, k, 1] = R[:, 0, 0] / c
            out[:, k, 2] = 0.0
        else:  # yaw = atan2(R10, R00)
            d = np.maximum(R[:, 0, 0] ** 2 + R[:, 1, 0] ** 2, 1e-12)
            out[:, k, 0] = -R[:, 0, 0] * R[:, 2, 0] / d
            out[:, k, 1] = -R[:, 1, 0] * R[:, 2, 0] / d
            out[:, k, 2] = 1.0
    return out


@dataclass
class IKResult:
    """What the solver found. ``q`` is always within the joint limits; on failure it is the best attempt.

    ``error`` is the original's measure whatever the tolerance: the norm of all target-minus-achieved
    components, m and rad mixed (so 0.005 can be a 5 mm miss that a 1 mm tolerance rejects). ``iterations``:
    steps of the batched searches, or with the C searches, single-search steps (at most ``max_iterations *
    seeds``); 0 when the closed form or the seed itself answered."""

    q: np.ndarray
    success: bool
    error: float
    iterations: int
    time: float
    arm: str
    order: tuple[str, ...]
    target: np.ndarray  # canonical target values in ``order``
    achieved: np.ndarray  # the same components at ``q``
    restarts: int = 0
    rejected_unsafe: int = 0
    message: str = ""
    seed: np.ndarray = field(default_factory=lambda: np.zeros(6))


@dataclass
class IKOptions:
    """Solver settings. ``joint_step``/``task_step`` are the initial per-iteration step limits (rad, m|rad).

    With ``adaptive`` (default) the limits are a trust region: a step that lowers the error multiplies them
    by 16 (up to the ``max_*`` caps) and lowers the damping, one that does not is undone, halves them and
    raises the damping (Levenberg-Marquardt). The original's small steps are kept near trouble, but a far
    target does not take hundreds of iterations. With ``adaptive=False`` the limits hold for every step.

    The first ``fast_iterations`` run one search from the caller's seed in plain floats (quick); if it does
    not converge, ``seeds`` searches run side by side; ``stall_iterations`` without progress restart one from a
    random joint vector; once a search other than the caller's seed converges, the seed's own search gets
    ``grace_iterations`` more to finish (its answer is nearer the current pose). ``path_samples`` points on
    the joint-space line from the seed to a candidate are collision-checked along with it. A solution then
    gets up to ``polish_iterations`` more steps toward 1/1000 of the tolerance (kept only if better and safe).

    A full pose (all six components) is first solved in closed form (``analytic``, when the arm has the MDS
    shape and ``closed_form``): the exact solution within the limits nearest the seed that passes ``is_safe``;
    the searches run only when there is none.

    With the C searches (``NATIVE_AVAILABLE``; ``adaptive`` only) the seed's search runs up to
    ``fast_iterations`` steps, then on until it stalls, then searches from random starts run one after another
    (each up to 60 steps or ``stall_iterations`` without progress) until one converges, within a budget of
    ``max_iterations * seeds`` steps (the batched searches' work) and ``timeout``.

    Success: position within ``tolerance`` (m) and angles within ``angle_tolerance`` (rad), each checked
    separately; ``mixed_tolerance``, when set, replaces both with the original's single m+rad test.
    """

    tolerance: float = DEFAULT_TOLERANCE
    angle_tolerance: float = DEFAULT_ANGLE_TOLERANCE
    mixed_tolerance: float | None = None
    max_iterations: int = DEFAULT_ITERATIONS
    joint_step: float = 0.01
    task_step: float = 0.01
    adaptive: bool = True
    max_joint_step: float = 0.6
    max_task_step: float = 0.5
    damping: float = 1e-3
    seeds: int = 8
    null_gain: float = 0.1
    stall_iterations: int = 12
    grace_iterations: int = 1
    path_samples: int = 4
    fast_iterations: int = 20
    polish_iterations: int = 2
    timeout: float | None = None
    closed_form: bool = True


class _Searches:
    """The K parallel damped-least-squares searches of one solve (seed 0 starts at the caller's seed).

    Written for few numpy calls per step: with 6 joints and a handful of seeds the cost is per call.
    """

    def __init__(self, kin: ArmKinematics, task: Task, q: np.ndarray, opt: IKOptions) -> None:
        self.kin, self.task, self.opt = kin, task, opt
        K = q.shape[0]
        self.q = q
        # Per search: trust-region scale (step limits = scale * the initial ones, capped) and LM damping.
        self.ls = np.empty((K, 2))
        self.ls[:, 0], self.ls[:, 1] = 1.0, opt.damping
        max_scale = max(opt.max_joint_step / opt.joint_step, opt.max_task_step / opt.task_step, 1.0)
        self.ls_min = np.array([1e-4, opt.damping])
        self.ls_max = np.array([max_scale, 1.0])
        self.since_progress = np.zeros(K, dtype=int)
        self.best_q, self.best_err = q[0].copy(), math.inf
        self.evaluate()
        self.eye = np.eye(self.e.shape[1])

    def evaluate(self) -> None:
        R, p, J = self.kin.fk_jacobian(self.q)
        self.e, self.Jt, self.err, self.reported = self.task.residual(R, p, J)

    def note_best(self, slots: np.ndarray | None = None) -> None:
        """Remember the best pose seen (before ``slots`` are restarted, and at the end)."""
        err = self.err if slots is None else self.err[slots]
        k = int(np.argmin(err))
        if err[k] < self.best_err:
            self.best_err = float(err[k])
            self.best_q = (self.q if slots is None else self.q[slots])[k].copy()

    def restart(self, slots: np.ndarray, q: np.ndarray) -> None:
        self.note_best(slots)
        self.q[slots] = q
        self.ls[slots] = (1.0, self.opt.damping)
        self.since_progress[slots] = 0
        self.evaluate()

    def step(self, rest: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
        """One trust-region step for every search: propose, evaluate, keep it only if the error went down."""
        opt, q, e, Jt = self.opt, self.q, self.e, self.Jt
        scale, lam = self.ls[:, 0], self.ls[:, 1]
        task_limit = np.minimum(scale * opt.task_step, opt.max_task_step)
        e_step = e * np.minimum(1.0, task_limit / (np.sqrt((e * e).sum(1)) + 1e-300))[:, None]
        # Active set: a joint at a limit whose error gradient J^T e points outward is held for this step.
        g = (e[:, None, :] @ Jt)[:, 0, :]
        free = ~np.where(g < 0, q <= lower, q >= upper)
        Jf = Jt * free[:, None, :]
        JfT = Jf.transpose(0, 2, 1)
        A = Jf @ JfT + (lam * lam)[:, None, None] * self.eye
        if self.task.dof < q.shape[1] and opt.null_gain > 0:
            # Plus a pull toward ``rest`` projected into the (damped) null space of the free columns.
            z = (-opt.null_gain * (q - rest)) * free
            y = JfT @ np.linalg.solve(A, np.concatenate([e_step[..., None], Jf @ z[..., None]], axis=-1))
            dq = y[..., 0] + z - y[..., 1]
        else:
            dq = (JfT @ np.linalg.solve(A, e_step[..., None]))[..., 0]
        joint_limit = np.minimum(scale * opt.joint_step, opt.max_joint_step)
        dq *= np.minimum(1.0, joint_limit / (np.abs(dq).max(1) + 1e-300))[:, None]
        q_new = np.minimum(np.maximum(q + dq, lower), upper)
        R, p, J = self.kin.fk_jacobian(q_new)
        e_new, Jt_new, err_new, reported_new = self.task.residual(R, p, J)
        self.since_progress = np.where(err_new < self.err * (1.0 - 1e-4), 0, self.since_progress + 1)
        better = err_new < self.err
        if not opt.adaptive:
            self.note_best()  # the error may go up again: remember the best
        elif not better.all():
            self.ls = np.minimum(np.maximum(self.ls * np.where(better[:, None], _ACCEPT, _REJECT), self.ls_min),
                                 self.ls_max)
            self.q = np.where(better[:, None], q_new, q)
            self.e = np.where(better[:, None], e_new, e)
            self.Jt = np.where(better[:, None, None], Jt_new, Jt)
            self.err = np.where(better, err_new, self.err)
            self.reported = np.where(better, reported_new, self.reported)
            return
        else:
            self.ls = np.minimum(np.maximum(self.ls * _ACCEPT, self.ls_min), self.ls_max)
        self.q, self.e, self.Jt, self.err, self.reported = q_new, e_new, Jt_new, err_new, reported_new


class IKSolver:
    """Batched damped-least-squares IK for one arm (see the module doc for the task conventions).

    ``options.seeds`` searches run side by side (numpy-vectorised, so extra seeds cost little): the first
    starts at the caller's seed, the others at random joint vectors. A search that stalls above the
    tolerance (a local minimum, usually at joint limits) restarts from a fresh random vector. The result
    is the first converged candidate that passes ``is_safe``, preferring the one nearest the seed.
    """

    def __init__(self, arm: str | int, options: IKOptions | None = None, *, rng_seed: int | None = 0,
                 is_safe: SafetyCheck | None = None,
                 limits: tuple[ArrayLike, ArrayLike] | None = None) -> None:
        """``limits`` (lower, upper) narrow the URDF limits, e.g. to the active robot's joint table."""
        self.arm = arm_name(arm)
        self._kin: ArmKinematics = arm_kinematics(self.arm)
        self.options = options or IKOptions()
        self.rng = np.random.default_rng(rng_seed)
        self.is_safe = is_safe
        self.geometry = ArmGeometry.of(self.kin)
        self.lower = self.kin.lower.copy()
        self.upper = self.kin.upper.copy()
        if limits is not None:
            lo, hi = (np.asarray(v, dtype=float).reshape(-1) for v in limits)
            if lo.size != self.kin.dof or hi.size != self.kin.dof or np.isnan(lo).any() or np.isnan(hi).any():
                raise ValueError(f"limits must be two vectors of {self.kin.dof} numbers")
            self.lower = np.maximum(self.lower, lo)
            self.upper = np.minimum(self.upper, hi)
            if np.any(self.lower > self.upper):
                bad = [n for n, a, b in zip(self.kin.joint_names, self.lower, self.upper, strict=True) if a > b]
                raise ValueError(f"empty joint range for {', '.join(bad)} after applying the limits")
        # The C searches (None: the Python ones), with the chain from the URDF model and these limits.
        self._native: Any = self._native_arm()
        self._rng_state = int(np.random.SeedSequence(rng_seed).generate_state(1, np.uint64)[0])

    @property
    def kin(self) -> ArmKinematics:
        """The arm's chain. Setting another one (a modified URDF) rebuilds what was derived from it: the
        closed-form geometry and the C searches (None when that chain has no plain-float form)."""
        return self._kin

    @kin.setter
    def kin(self, kin: ArmKinematics) -> None:
        self._kin = kin
        self.geometry = ArmGeometry.of(kin)
        self._native = self._native_arm()

    def _native_arm(self) -> Any:
        chain = self.kin.scalar_chain
        if _iksearch is None or chain is None or self.kin.dof > _iksearch.MAX_JOINTS:
            return None
        g = self.geometry
        return _iksearch.arm([c[0] for c in chain], [c[1] for c in chain], [v for c in chain for v in c[2:]],
                             list(self.kin._tail_floats), self._lower_list, self._upper_list,
                             None if g is None else (*g.shoulder, g.upper, g.fore, g.tool))

    @property
    def _lower_list(self) -> list[float]:
        return self.lower.tolist()

    @property
    def _upper_list(self) -> list[float]:
        return self.upper.tolist()

    def random_configurations(self, n: int) -> np.ndarray:
        return self.rng.uniform(self.lower, self.upper, size=(n, self.kin.dof))

    def solve(self, target: Sequence[float] | np.ndarray, order: Sequence[str] | str,
              q0: Sequence[float] | np.ndarray | None = None, options: IKOptions | None = None) -> IKResult:
        """Solve for ``target`` (values in ``order``) starting from ``q0`` (default: the zero pose, clamped)."""
        t_start = time.perf_counter()
        opt = options or self.options
        if not (opt.joint_step > 0 and opt.task_step > 0 and opt.max_iterations >= 1 and opt.seeds >= 1):
            raise ValueError("step limits must be > 0, max_iterations and seeds >= 1")
        task = Task(target, order, Tolerance(opt.tolerance, opt.angle_tolerance, opt.mixed_tolerance))
        n = self.kin.dof
        seed = np.zeros(n) if q0 is None else np.asarray(q0, dtype=float).reshape(-1)
        if seed.size != n or not np.isfinite(seed).all():
            raise ValueError(f"seed must be {n} finite joint values, got {seed.tolist()}")
        seed = np.minimum(np.maximum(seed, self.lower), self.upper)
        # If the arm already is in a (predicted) collision, any path out starts in one: check only the goal.
        samples = opt.path_samples if self.is_safe is not None and self.is_safe(seed.copy(), self.arm) else 0
        iterations = restarts = unsafe = 0
        if opt.closed_form and self.geometry is not None and task.dof == 6:
            if self._native is not None:  # the same candidates in the same order, computed in C
                for q_list, err, pose in _iksearch.closed_form(self._native, task.native_spec(), seed.tolist()):
                    q_found = np.array(q_list)
                    if self._safe(q_found, seed, samples):
                        return self._result(task, seed, q_found, True, 0, t_start, 0, 0, "", (err, pose))
                    unsafe += 1
            else:
                q_exact, unsafe = self._closed_form(task, seed, samples)
                if q_exact is not None:
                    return self._result(task, seed, q_exact, True, 0, t_start, 0, 0, "")
        if self._native is not None and opt.adaptive:
            return self._solve_native(task, seed, opt, samples, t_start, unsafe)
        start = np.concatenate([seed[None], self.random_configurations(opt.seeds - 1)])
        fast: tuple[np.ndarray, float] | None = None
        if opt.adaptive and opt.fast_iterations > 0 and self.kin.scalar_chain is not None:
            # Fast path: the caller's seed alone, in plain floats. Most requests end here.
            q1, reported, err1, iterations, converged = self._fast_search(task, seed, opt)
            if converged and self._safe(q1, seed, samples):
                q1, reported, used = self._polish(task, seed, q1, reported, opt)
                return self._result(task, seed, q1, True, iterations + used, t_start, 0, 0, "")
            unsafe += int(converged)
            # The batched searches take over: slot 0 from where the fast one stalled (or afresh if it collided).
            start[0] = self.random_configurations(1)[0] if converged else q1
            fast = (q1, err1)
        st = _Searches(self.kin, task, start, opt)
        if fast is not None:
            st.best_q, st.best_err = fast

        candidates: list[tuple[float, np.ndarray, float]] = []  # (max joint distance to seed, q, error)
        first_found = 0
        message = ""
        while True:
            converged_now = st.reported <= 1.0
            if converged_now.any():
                done = np.flatnonzero(converged_now)
                for k in done:
                    if self._safe(st.q[k], seed, samples):
                        if not candidates:
                            first_found = iterations
                        candidates.append((float(np.max(np.abs(st.q[k] - seed))), st.q[k].copy(),
                                           float(st.reported[k])))
                    else:
                        unsafe += 1
                # Stop when the seed's own search converged (the pose nearest the current one) or after a grace.
                if candidates and (done[0] == 0 or iterations - first_found >= opt.grace_iterations):
                    break
                st.restart(done, self.random_configurations(len(done)))  # converged slots keep looking
                restarts += len(done)
            elif candidates and iterations - first_found >= opt.grace_iterations:
                break
            if iterations >= opt.max_iterations:
                message = f"no IK solution within {opt.max_iterations} iterations"
                break
            if opt.timeout is not None and time.perf_counter() - t_start > opt.timeout:
                message = f"IK gave up after {opt.timeout:.3g} s"
                break
            iterations += 1
            st.step(seed, self.lower, self.upper)
            if iterations % 5 == 0:  # a stall is counted in tens of iterations: no need to look every time
                stuck = np.flatnonzero((st.since_progress > opt.stall_iterations) & (st.reported > 1.0))
                if len(stuck):
                    st.restart(stuck, self.random_configurations(len(stuck)))
                    restarts += len(stuck)

        if candidates:
            _, q, err = min(candidates, key=lambda c: c[0])
            q, err, used = self._polish(task, seed, q, err, opt)
            return self._result(task, seed, q, True, iterations + used, t_start, restarts, unsafe, "")
        st.note_best()
        return self._result(task, seed, st.best_q, False, iterations, t_start, restarts, unsafe, message)

    def _solve_native(self, task: Task, seed: np.ndarray, opt: IKOptions, samples: int, t_start: float,
                      unsafe: int) -> IKResult:
        """The searches in C (``_iksearch.solve``): the seed's search, then one random start after another until
        one converges, in one call. The step budget is ``max_iterations * seeds`` single-search steps, the work
        the batched searches may do. A candidate the collision hook rejects sends the searches on from random
        starts with what is left of the budget."""
        spec, steps = task.native_spec(), self._native_steps(opt)
        budget = opt.max_iterations * opt.seeds
        polish = opt.polish_iterations if self.is_safe is None else 0
        seed_list = seed.tolist()
        spent = restarts = 0
        from_seed = True
        while True:
            left = 0.0
            if opt.timeout is not None:
                left = opt.timeout - (time.perf_counter() - t_start)
                if left <= 0:
                    left = 1e-9
            q_list, score, _, used, started, converged, self._rng_state, err, pose = _iksearch.solve(
                self._native, spec, steps, seed_list, from_seed, opt.fast_iterations, _NATIVE_PER_START,
                budget - spent, left, polish, self._rng_state)
            spent += used
            restarts += started
            q = np.array(q_list)
            if converged:
                if self._safe(q, seed, samples):
                    report: tuple[float, list[float]] | None = (err, pose)
                    if self.is_safe is not None:
                        q, _, used = self._polish(task, seed, q, score, opt)
                        spent += used
                        report = None if used else report
                    return self._result(task, seed, q, True, spent, t_start, restarts, unsafe, "", report)
                unsafe += 1
            timed_out = opt.timeout is not None and time.perf_counter() - t_start >= opt.timeout
            if not converged or spent >= budget or timed_out:
                message = (f"IK gave up after {opt.timeout:.3g} s" if opt.timeout is not None and spent < budget
                           else f"no IK solution within {opt.max_iterations} iterations ({spent} search steps)")
                return self._result(task, seed, q, False, spent, t_start, restarts, unsafe, message, (err, pose))
            from_seed = False

    @staticmethod
    def _native_steps(opt: IKOptions) -> tuple[float, float, float, float, float, float, int]:
        return (opt.joint_step, opt.task_step, opt.max_joint_step, opt.max_task_step, opt.damping, opt.null_gain,
                opt.stall_iterations)

    def _result(self, task: Task, seed: np.ndarray, q: np.ndarray, success: bool, iterations: int, t_start: float,
                restarts: int, unsafe: int, message: str, report: tuple[float, list[float]] | None = None
                ) -> IKResult:
        """``report``: the original's error at ``q`` and its six pose components, when the C searches gave them."""
        if report is not None:
            err = report[0]
            achieved = np.array([report[1][i] for i in task.idx])
        elif self.kin.scalar_chain is not None:  # plain floats: numpy's per-call cost would dominate a quick solve
            if task._legacy is None:
                task._legacy = Task(task.requested, [TASK_COMPONENTS[i] for i in task.idx], 1.0)
                task._legacy._always_exact = True
            Rs, ps, cols = self.kin.fk_jacobian_scalar(q.tolist())
            err = task._legacy.residual_scalar(Rs, ps, cols)[3]
            full = ps + _euler_zyx_list(Rs)
            achieved = np.array([full[i] for i in task.idx])
        else:
            R, p = self.kin.fk(q[None])
            err = float(task.error(R, p)[0])
            achieved = _components(R[0], p[0], task.idx)
        if not success:
            message += f" (best error {err:.4g})"
            if unsafe:
                message += f"; {unsafe} solution(s) rejected by the collision check"
        return IKResult(q=q, success=success, error=err, iterations=iterations,
                        time=time.perf_counter() - t_start, arm=self.arm,
                        order=tuple(TASK_COMPONENTS[i] for i in task.idx), target=task.target,
                        achieved=achieved, restarts=restarts, rejected_unsafe=unsafe,
                        message=message or "solved", seed=seed)

    def _closed_form(self, task: Task, seed: np.ndarray, samples: int) -> tuple[np.ndarray | None, int]:
        """The exact solution within the limits nearest ``seed`` (max joint distance) that passes the collision
        hook, checked by FK against the task; (None, solutions rejected as unsafe) when there is none."""
        assert self.geometry is not None and task.R_target is not None
        p = [0.0, 0.0, 0.0]
        for i, v in zip(task.pos_idx, task.pos_target.tolist(), strict=True):
            p[i] = v
        lower, upper = self._lower_list, self._upper_list
        found = [q for q in (within(s, lower, upper) for s in self.geometry.solve(task._R_target_list, p))
                 if q is not None]
        seed_list = seed.tolist()
        found.sort(key=lambda q: max(abs(a - b) for a, b in zip(q, seed_list, strict=True)))
        found.insert(0, seed_list)  # already there (to round-off): move nothing, not even by the closed form's 1e-8
        unsafe = 0
        for q in found:
            if task.residual_scalar(*self.kin.fk_jacobian_scalar(q))[3] > 1e-3:
                continue  # clamped at a limit beyond the tolerance (or a round-off case): not this one
            qa = np.array(q)
            if self._safe(qa, seed, samples):
                return qa, unsafe
            unsafe += 1
        return None, unsafe

    def _fast_search(self, task: Task, seed: np.ndarray, opt: IKOptions, start: np.ndarray | None = None,
                     budget: int | None = None, tolerance: float | None = None, scale: float = 1.0
                     ) -> tuple[np.ndarray, float, float, int, bool]:
        """One search with the same steps as ``_Searches`` (trust region, LM damping, active set, null-space
        pull toward ``seed``), FK and errors in plain floats: numpy's per-call cost would dominate for one arm.

        Starts at ``start`` (default ``seed``) with step limits ``scale`` times the initial ones; stops when the
        score is within ``tolerance`` (default 1: the options' tolerance), after ``budget`` iterations (default
        ``opt.fast_iterations``) or when stalled or creeping (the batched searches do better from there).
        Returns (q, score, solver error, iterations, converged).
        """
        kin = self.kin
        lower, upper = self._lower_list, self._upper_list
        n = kin.dof
        rest = seed
        tol = 1.0 if tolerance is None else tolerance
        q = (seed if start is None else start).tolist()
        e, rows, err, reported = task.residual_scalar(*kin.fk_jacobian_scalar(q))
        lam = opt.damping
        max_scale = max(opt.max_joint_step / opt.joint_step, opt.max_task_step / opt.task_step, 1.0)
        null = task.dof < n and opt.null_gain > 0
        stall = min(opt.stall_iterations, 10)
        history = [err]
        since = iterations = 0
        budget = min(opt.fast_iterations if budget is None else budget, opt.max_iterations)
        while reported > tol and iterations < budget and since <= stall:
            if len(history) > _CREEP_WINDOW and history[-1] > _CREEP_RATIO * history[-1 - _CREEP_WINDOW]:
                break  # creeping: most likely a local minimum at the joint limits; the batched searches take over
            iterations += 1
            Jt = np.array(rows)
            ev = np.array(e)
            g = ev @ Jt
            free = np.array([not (q[j] <= lower[j] if g[j] < 0 else q[j] >= upper[j]) for j in range(n)])
            Jf = Jt * free
            A = Jf @ Jf.T
            A.flat[:: A.shape[0] + 1] += lam * lam
            norm_e = math.sqrt(sum(x * x for x in e))
            cut = min(1.0, min(scale * opt.task_step, opt.max_task_step) / (norm_e + 1e-300))
            if null:
                z = (-opt.null_gain * (np.array(q) - rest)) * free
                y = Jf.T @ np.linalg.solve(A, np.stack([ev * cut, Jf @ z], axis=1))
                dq = y[:, 0] + z - y[:, 1]
            else:
                dq = Jf.T @ np.linalg.solve(A, ev * cut)
            dq = dq.tolist()
            big = max(abs(x) for x in dq)
            joint_limit = min(scale * opt.joint_step, opt.max_joint_step)
            f = joint_limit / big if big > joint_limit else 1.0
            q_new = [min(max(a + f * d, lo), hi) for a, d, lo, hi in zip(q, dq, lower, upper, strict=True)]
            e_new, rows_new, err_new, reported_new = task.residual_scalar(*kin.fk_jacobian_scalar(q_new))
            since = 0 if err_new < err * (1.0 - 1e-4) else since + 1
            history.append(min(err_new, err))
            if err_new < err:
                q, e, rows, err, reported = q_new, e_new, rows_new, err_new, reported_new
                scale = min(scale * _ACCEPT[0], max_scale)
                lam = max(lam * _ACCEPT[1], opt.damping)
            else:
                scale = max(scale * _REJECT[0], 1e-4)
                lam = min(lam * _REJECT[1], 1.0)
        return np.array(q), reported, err, iterations, reported <= tol

    def _polish(self, task: Task, seed: np.ndarray, q: np.ndarray, reported: float, opt: IKOptions
                ) -> tuple[np.ndarray, float, int]:
        """A few more steps from a solution already within the tolerance, toward 1000x tighter: the original
        stopped at 1 cm, the robot deserves better when it costs a fraction of a millisecond."""
        if opt.polish_iterations <= 0 or self.kin.scalar_chain is None or reported <= 1e-3:
            return q, reported, 0
        full = max(opt.max_joint_step / opt.joint_step, opt.max_task_step / opt.task_step, 1.0)  # already close
        if self._native is not None:
            q_list, reported2, _, used, _ = _iksearch.search(
                self._native, task.native_spec(), self._native_steps(opt), q.tolist(), seed.tolist(),
                opt.polish_iterations, 1e-3, full, min(opt.stall_iterations, 10), True)
            q2 = np.array(q_list)
        else:
            q2, reported2, _, used, _ = self._fast_search(task, seed, opt, start=q, budget=opt.polish_iterations,
                                                          tolerance=1e-3, scale=full)
        if reported2 < reported and (self.is_safe is None or self.is_safe(q2.copy(), self.arm)):
            return q2, reported2, used
        return q, reported, used

    def _safe(self, q: np.ndarray, seed: np.ndarray, samples: int) -> bool:
        """The collision hook on the candidate and on ``samples`` points of the joint-space path to it.

        The filter moves every joint by the same fraction each tick, so the commanded motion follows this
        straight line in joint space.
        """
        if self.is_safe is None:
            return True
        if not self.is_safe(q.copy(), self.arm):
            return False
        for s in range(1, samples + 1):
            if not self.is_safe(seed + (q - seed) * (s / (samples + 1)), self.arm):
                return False
        return True


def _components(R: np.ndarray, p: np.ndarray, idx: Sequence[int]) -> np.ndarray:
    full = np.concatenate([p, euler_zyx(R)])
    return full[list(idx)]


_solvers: dict[str, IKSolver] = {}


def solver(arm: str | int) -> IKSolver:
    """A shared default ``IKSolver`` per arm (no collision hook)."""
    name = arm_name(arm)
    if name not in _solvers:
        _solvers[name] = IKSolver(name)
    return _solvers[name]


def solve(target: Sequence[float] | np.ndarray, order: Sequence[str] | str, arm: str | int,
          q0: Sequence[float] | np.ndarray | None = None, *, options: IKOptions | None = None,
          is_safe: SafetyCheck | None = None) -> IKResult:
    """One-shot IK (see ``IKSolver.solve``); ``is_safe(q, arm) -> bool`` rejects colliding candidates."""
    if is_safe is None:
        return solver(arm).solve(target, order, q0, options)
    return IKSolver(arm, options, is_safe=is_safe).solve(target, order, q0, options)


# --------------------------------------------------------------------------------------------- legacy API


def getFkArm(a: Sequence[float] | np.ndarray, arm: str | int) -> np.ndarray:
    """4x4 tool pose of ``arm`` ('left'/'right') for a = [SP, SR, SY, EP, WY, WR] (rad), torso frame.

    The original returned -1 for an unknown arm; this raises ``ValueError`` instead.
    """
    q = np.asarray(a, dtype=float).reshape(-1)
    if q.size != 6:
        raise ValueError(f"getFkArm needs 6 joint values [SP, SR, SY, EP, WY, WR], got {q.size}")
    return arm_kinematics(arm).fk_matrix(q)


def getRot(A: np.ndarray, axis: str) -> float:
    """Z-Y-X angle of a pose: axis 'x' (roll), 'y' (pitch) or 'z' (yaw); 't_x'/'t-x' spellings accepted."""
    key = str(axis).strip().lower().replace("_", "-")
    names = {"x": 0, "y": 1, "z": 2, "t-x": 0, "t-y": 1, "t-z": 2, "roll": 0, "pitch": 1, "yaw": 2}
    if key not in names:
        raise ValueError(f"unknown rotation axis {axis!r}: use 'x', 'y' or 'z'")
    return float(euler_zyx(np.asarray(A, dtype=float)[:3, :3])[names[key]])


def getPosCurrentFromOrder(A: np.ndarray, order: Sequence[str] | str) -> np.ndarray:
    """The components of pose ``A`` named by ``order`` (e.g. ['p_x', 'p_y', 't_z'])."""
    A = np.asarray(A, dtype=float)
    return _components(A[:3, :3], A[:3, 3], parse_order(order))


def getJacobian(q: Sequence[float] | np.ndarray, order: Sequence[str] | str, dtheta: float | None = None,
                arm: str | int = "left") -> np.ndarray:
    """len(order) x 6 Jacobian of the ordered components (Z-Y-X angle rates). Analytic; ``dtheta`` is ignored."""
    del dtheta
    idx = parse_order(order)
    R, p, J = arm_kinematics(arm).fk_jacobian(np.asarray(q, dtype=float).reshape(1, 6))
    out = np.empty((len(idx), 6))
    for r, i in enumerate(idx):
        out[r] = J[0, i] if i < 3 else (_euler_rate_rows(R, [i]) @ J[:, 3:, :])[0, 0]
    return out


def getIK(q0: Sequence[float] | np.ndarray, target: Sequence[float] | np.ndarray, order: Sequence[str] | str,
          arm: str | int, err: Sequence[float] | None = None, itr: int | None = None) -> tuple[np.ndarray, int]:
    """Legacy IK: ``(q, 0)`` on success, ``(q_last, -1)`` on failure.

    ``err = [dθ, step, tol]``: initial joint step limit, initial task step limit and the original's tolerance,
    the norm of all target-minus-achieved components with m and rad mixed (as in the original). Without
    ``err`` the steps are the original's 0.01 and success is the default ``Tolerance``: position within 1 mm,
    angles within 0.01 rad, each checked separately (the original's default, 0.01 mixed, accepted 1 cm).
    ``itr`` caps the iterations (default 1000; the original's itr=None failed at once).
    """
    iterations = DEFAULT_ITERATIONS if itr is None else int(itr)
    if err is None:
        opt = IKOptions(joint_step=DEFAULT_ERR[0], task_step=DEFAULT_ERR[1], max_iterations=iterations)
    else:
        e = tuple(float(x) for x in err)
        if len(e) != 3 or not all(math.isfinite(x) and x > 0 for x in e):
            raise ValueError(f"err must be three positive numbers [dtheta, step, tolerance], got {err!r}")
        opt = IKOptions(mixed_tolerance=e[2], joint_step=e[0], task_step=e[1], max_iterations=iterations)
    result = solver(arm).solve(target, order, q0, opt)
    return result.q, (0 if result.success else -1)


def getDist2End(eff_current: Sequence[float] | np.ndarray, eff_end: Sequence[float] | np.ndarray) -> float:  # noqa: N802
    """Euclidean distance of the first three components (the original's position error)."""
    d = np.asarray(eff_end, dtype=float).reshape(-1)[:3] - np.asarray(eff_current, dtype=float).reshape(-1)[:3]
    return float(np.linalg.norm(d))


def getDist2End2(eff_current: Sequence[float] | np.ndarray, eff_end: Sequence[float] | np.ndarray) -> float:  # noqa: N802
    """Euclidean norm of all components, m and rad mixed (the original's error for any task)."""
    d = np.asarray(eff_end, dtype=float).reshape(-1) - np.asarray(eff_current, dtype=float).reshape(-1)
    return float(np.linalg.norm(d))


def getIK3dof(q0: Sequence[float] | np.ndarray, eff_end: Sequence[float] | np.ndarray,  # noqa: N802
              arm: str | int) -> np.ndarray:
    """Legacy: joints putting the tool point at [x, y, z] (the original looped without an iteration cap; this
    is ``getIK`` with the default 1000 and returns its last pose either way, as the original returned q)."""
    return getIK(q0, eff_end, ("p_x", "p_y", "p_z"), arm)[0]


def getIK6dof(q0: Sequence[float] | np.ndarray, eff_end: Sequence[float] | np.ndarray,  # noqa: N802
              arm: str | int) -> np.ndarray:
    """Legacy: joints for the full pose [x, y, z, rx, ry, rz] (see ``getIK3dof``)."""
    return getIK(q0, eff_end, ("p_x", "p_y", "p_z", "t_x", "t_y", "t_z"), arm)[0]

