"""The original MDS IK chain (specs section e.1), written out independently of ``mds_ach.kinematics.model``: the
reference the URDF, the numpy kinematics, the IK and the console's ``get fk`` are checked against."""

from __future__ import annotations

import math

import numpy as np

L1, L2, L3, L4 = 0.24551, 0.282575, 0.3127375, 0.0635  # specs section e.1 (inches: 9.666, 11.125, 12.3125, 2.5)


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def original_chain(q: np.ndarray, m: float) -> np.ndarray:
    """The original getFkArm: per joint [R(theta) | p] with p applied before the rotation (specs table e.1);
    ``m`` = 1 for the left arm, -1 for the right one. The tool pose (4x4) in the torso frame."""
    steps = [("y", (0, m * L1, 0)), ("x", (0, 0, 0)), ("z", (0, 0, 0)), ("y", (0, 0, -L2)), ("z", (0, 0, -L3)),
             ("x", (0, 0, 0))]
    T = np.eye(4)
    for (axis, p), angle in zip(steps, q, strict=True):
        A = np.eye(4)
        A[:3, :3] = _rot(axis, angle)
        A[:3, 3] = p
        T = T @ A
    E = np.eye(4)
    E[2, 3] = -L4
    return T @ E


def chain_fk(q: list[float], arm: str) -> tuple[np.ndarray, np.ndarray]:
    """The tool point's position and Z-Y-X Euler angles (what the console's ``get fk`` prints) for ``arm``."""
    T = original_chain(np.asarray(q, dtype=float), 1.0 if arm == "left" else -1.0)
    R = T[:3, :3]
    euler = np.array([math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
                      math.atan2(R[1, 0], R[0, 0])])
    return T[:3, 3].copy(), euler
