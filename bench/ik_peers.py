"""The IK benchmark's peers and its referee, none of which shares code with ``mds_ach.kinematics``.

* ``TracIkPeer``: TRAC-IK (``pytracik``, the C++ KDL + SQP solver behind ROS MoveIt's favourite plugin) on the
  same URDF chain, full 6-DOF poses only (it has no masked tasks).
* ``PinocchioDls``: the solver a competent Pinocchio user writes: C++ FK and frame Jacobian per iteration,
  damped least squares with a step cap, joint limits clamped, restarts from random joint vectors. Masked
  tasks use the same Z-Y-X angle rows as the task definition needs (position rows, then roll/pitch/yaw
  rates); the full pose uses the rotation-vector error (``pin.log3``).
* ``Referee``: an independent forward kinematics (yourdfpy's own URDF parser and scene graph) that decides
  whether an answer is a success: within the URDF limits, position within 1 mm, orientation within 0.01 rad.

Imported only by bench/bench_ik.py; ``pin`` and ``pytracik`` come from bench/requirements.txt (``make bench``).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

POSITION_TOLERANCE = 1e-3  # m
ANGLE_TOLERANCE = 0.01  # rad
ARM_JOINTS = {"left": ("LSP", "LSR", "LSY", "LEP", "LWY", "LWR"), "right": ("RSP", "RSR", "RSY", "REP", "RWY", "RWR")}


def _wrap(a: float) -> float:
    return math.remainder(a, 2.0 * math.pi)


def _euler(R: np.ndarray) -> tuple[float, float, float]:
    """Z-Y-X (roll, pitch, yaw) of a rotation matrix: the task's angle convention (the original getRot)."""
    return (math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
            math.atan2(R[1, 0], R[0, 0]))


def task_values(R: np.ndarray, p: np.ndarray, dof: int) -> np.ndarray:
    """The first ``dof`` of x, y, z, roll, pitch, yaw."""
    return np.concatenate([p, _euler(R)])[:dof]


class Referee:
    """Success as a user means it, from yourdfpy's FK: the task's position within 1 mm and its angles within
    0.01 rad (the full pose: the rotation angle between target and answer), every joint within its limits."""

    def __init__(self, urdf: Path) -> None:
        import yourdfpy
        self.robot = yourdfpy.URDF.load(str(urdf), load_meshes=False, build_collision_scene_graph=False)
        self.limits = {j.name: (j.limit.lower, j.limit.upper) for j in self.robot.robot.joints if j.limit is not None}

    def pose(self, arm: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = dict(zip(ARM_JOINTS[arm], (float(v) for v in q), strict=True))
        self.robot.update_cfg(cfg)
        T = self.robot.get_transform(f"{arm}_tool", "torso")
        return T[:3, :3], T[:3, 3]

    def target(self, arm: str, q: np.ndarray, dof: int) -> tuple[np.ndarray, np.ndarray]:
        """(task values, full target rotation) for the tool pose at ``q``."""
        R, p = self.pose(arm, q)
        return task_values(R, p, dof), R

    def success(self, arm: str, q: np.ndarray | None, dof: int, values: np.ndarray, R_target: np.ndarray) -> bool:
        if q is None or not np.all(np.isfinite(q)):
            return False
        for name, v in zip(ARM_JOINTS[arm], q, strict=True):
            lo, hi = self.limits[name]
            if not lo - 1e-9 <= v <= hi + 1e-9:
                return False
        R, p = self.pose(arm, q)
        n_pos = min(dof, 3)
        if np.linalg.norm(p[:n_pos] - values[:n_pos]) > POSITION_TOLERANCE:
            return False
        if dof == 6:
            c = (np.trace(R_target.T @ R) - 1.0) / 2.0
            return math.acos(max(-1.0, min(1.0, c))) <= ANGLE_TOLERANCE
        got = _euler(R)
        diff = [_wrap(values[3 + k] - got[k]) for k in range(dof - 3)]
        return math.sqrt(sum(d * d for d in diff)) <= ANGLE_TOLERANCE


class TracIkPeer:
    """TRAC-IK on torso -> <arm>_tool, Speed mode. ``epsilon`` 5e-4 (its bound on each twist component, m and
    rad): the loosest that keeps its answers within 1 mm / 0.01 rad (1e-3 lets 10 % of them miss 1 mm), looser
    than its 1e-5 default, so faster for it, never slower."""

    def __init__(self, urdf: Path, arm: str, timeout: float = 0.02, epsilon: float = 5e-4) -> None:
        import pytracik
        self._ik = pytracik.TRAC_IK("torso", f"{arm}_tool", urdf.read_text(), timeout, epsilon,
                                    pytracik.SolveType.Speed)
        self._solve = pytracik.ik

    def solve(self, R: np.ndarray, p: np.ndarray, q0: np.ndarray) -> np.ndarray | None:
        qw, qx, qy, qz = _quaternion(R)
        r = self._solve(self._ik, np.asarray(q0, dtype=float), float(p[0]), float(p[1]), float(p[2]), qx, qy, qz, qw)
        return np.asarray(r[1:], dtype=float) if r[0] >= 0 else None  # r[0] < 0: no solution


def _quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        return 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    i = int(np.argmax([R[0, 0], R[1, 1], R[2, 2]]))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
    v = [0.0, 0.0, 0.0]
    v[i] = 0.25 * s
    v[j] = (R[j, i] + R[i, j]) / s
    v[k] = (R[k, i] + R[i, k]) / s
    return (R[k, j] - R[j, k]) / s, v[0], v[1], v[2]


class PinocchioDls:
    """Damped least squares on Pinocchio's FK/Jacobian with restarts (the peer for masked tasks and 6-DOF).

    Per iteration: ``computeFrameJacobian`` (C++ FK + Jacobian, world-aligned), the task rows, one 6x6 solve.
    Steps are capped at 0.5 rad per joint and clamped to the limits; a search that has not converged after
    ``restart_after`` iterations restarts from a random joint vector until ``timeout`` seconds passed.
    """

    def __init__(self, urdf: Path, arm: str, damping: float = 1e-4, restart_after: int = 40,
                 timeout: float = 0.02, seed: int = 0) -> None:
        import pinocchio as pin
        self.pin = pin
        full = pin.buildModelFromUrdf(str(urdf))
        keep = set(ARM_JOINTS[arm])
        lock = [full.getJointId(n) for n in full.names[1:] if n not in keep]
        self.model = pin.buildReducedModel(full, lock, pin.neutral(full))
        self.data = self.model.createData()
        self.fid = self.model.getFrameId(f"{arm}_tool")
        torso = self.model.getFrameId("torso")
        pin.framesForwardKinematics(self.model, self.data, pin.neutral(self.model))
        self.torso_R = self.data.oMf[torso].rotation.copy()  # constant: the waist is locked
        self.torso_p = self.data.oMf[torso].translation.copy()
        order = [self.model.getJointId(n) for n in ARM_JOINTS[arm]]
        self.index = np.array([self.model.joints[j].idx_q for j in order])  # ours -> pinocchio's q order
        self.lower = self.model.lowerPositionLimit[self.index]
        self.upper = self.model.upperPositionLimit[self.index]
        self.damping, self.restart_after, self.timeout = damping, restart_after, timeout
        self.rng = np.random.default_rng(seed)
        self._q = pin.neutral(self.model)

    def _fk_jac(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tool R, p in the torso frame and the 6x6 Jacobian (rows v, w) in torso axes, columns in our order."""
        pin = self.pin
        self._q[self.index] = q
        J = pin.computeFrameJacobian(self.model, self.data, self._q, self.fid, pin.LOCAL_WORLD_ALIGNED)
        pin.updateFramePlacement(self.model, self.data, self.fid)
        M = self.data.oMf[self.fid]
        Rt = self.torso_R.T
        R = Rt @ M.rotation
        p = Rt @ (M.translation - self.torso_p)
        J = J[:, self.index]
        return R, p, np.vstack([Rt @ J[:3], Rt @ J[3:]])

    def _rows(self, R: np.ndarray, p: np.ndarray, J: np.ndarray, dof: int, values: np.ndarray,
              R_target: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        n_pos = min(dof, 3)
        e_pos = values[:n_pos] - p[:n_pos]
        ok = float(np.linalg.norm(e_pos)) <= POSITION_TOLERANCE
        if dof == 6:
            w = self.pin.log3(R_target @ R.T)
            ok = ok and float(np.linalg.norm(w)) <= ANGLE_TOLERANCE
            return np.concatenate([e_pos, w]), J, ok
        if dof <= 3:
            return e_pos, J[:n_pos], ok
        roll, pitch, _ = _euler(R)
        c2 = max(R[2, 1] ** 2 + R[2, 2] ** 2, 1e-12)  # cos^2(pitch)
        g = [np.array([R[0, 0] / c2, R[1, 0] / c2, 0.0])]  # d roll / d omega
        e_ang = [_wrap(values[3] - roll)]
        if dof == 5:
            c = math.sqrt(c2)
            g.append(np.array([-R[1, 0] / c, R[0, 0] / c, 0.0]))  # d pitch / d omega
            e_ang.append(_wrap(values[4] - pitch))
        ok = ok and math.sqrt(sum(d * d for d in e_ang)) <= ANGLE_TOLERANCE
        return np.concatenate([e_pos, e_ang]), np.vstack([J[:n_pos], np.array(g) @ J[3:]]), ok

    def solve(self, dof: int, values: np.ndarray, R_target: np.ndarray, q0: np.ndarray) -> np.ndarray | None:
        t_end = time.perf_counter() + self.timeout
        q = np.clip(np.asarray(q0, dtype=float), self.lower, self.upper)
        it = 0
        while True:
            R, p, J = self._fk_jac(q)
            e, Je, ok = self._rows(R, p, J, dof, values, R_target)
            if ok:
                return q
            it += 1
            if it > self.restart_after:
                if time.perf_counter() > t_end:
                    return None
                q = self.rng.uniform(self.lower, self.upper)
                it = 0
                continue
            A = Je @ Je.T
            A[np.diag_indices_from(A)] += self.damping
            dq = Je.T @ np.linalg.solve(A, e)
            big = float(np.abs(dq).max())
            if big > 0.5:
                dq *= 0.5 / big
            q = np.clip(q + dq, self.lower, self.upper)
