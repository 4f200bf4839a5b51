"""Mux test inputs written once: a reference array with a few joints set, and an ``mds-hold`` request."""

from __future__ import annotations

import math

import numpy as np

import mds_ach as mds
from mds_ach.robot.msgs import MDS_JOINT_COUNT
from mds_ach.robot.msgs.hold import MDS_HOLD


def frame(base: np.ndarray | None = None, **joints: float) -> np.ndarray:
    """``base`` (zeros when None) with the joints named by short name set, e.g. ``frame(pose, LSP=-0.3)``."""
    out = np.zeros(MDS_JOINT_COUNT) if base is None else base.copy()
    for name, value in joints.items():
        out[getattr(mds, name)] = value
    return out


def hold_request(action: int, seq: int, joints: tuple[int, ...] = (),
                 targets: dict[int, float] | None = None) -> MDS_HOLD:
    """An ``mds-hold`` frame from source 'test': NaN targets but those given; no joints listed = every joint."""
    h = MDS_HOLD(seq=seq, action=action, source=b"test", reason=b"unit test")
    for a in range(MDS_JOINT_COUNT):
        h.target[a] = math.nan
    for a in joints:
        h.joints[a] = 1
    for a, v in (targets or {}).items():
        h.target[a] = v
    return h
