"""The collaborative-mode Cartesian bound: how fast the hands and elbows move, from the targets actually sent.

Near people (ISO 10218-1 "reduced speed", ISO/TS 15066) the tool's Cartesian speed is what matters, not a joint's.
In collaborative mode the daemon, the last stage before the bus, keeps the speed of each hand (the URDF's
``left_tool``/``right_tool`` point, mid-hand) and each elbow at most ``max_speed`` (``MAX_SPEED``, 250 mm/s, or a lower
configured value), whatever upstream sent. The CAN-log auditor (``mds-ach check-log``) checks recorded traffic
against the very same definition.

Definition, over one *batch* (the targets the daemon sends in one cycle: between two broadcast position queries in a
log), for the upper body's joints ``JOINTS`` (the torso pan WST carries both arms, so all 13 are one group):

* ``q`` the group's last sent targets before the batch (a joint re-seeded since: where it was measured);
* ``v_j`` the step velocity of joint ``j`` in the batch exactly as the joint bounds define it
  (``mds_ach.robot.motion``: ``(q_i - q_{i-1}) / h_i``); 0 for a joint not sent in the batch (its target stays);
* ``H`` the largest ``h_i`` of the batch (at most ``max_interval``);
* the speed of point ``p`` is ``|p(q + v H) - p(q)| / H`` (forward kinematics of the URDF, base frame), and the
  batch's speed is the largest over the four points.

Each joint's velocity is counted over its own interval, as for the joint bounds, so the speed does not depend on
how the frames of one cycle are spread in time (the daemon dates each joint's MOVETO separately).

The daemon enforces it (:meth:`CartesianBound.scale`) by moving every joint of the group the same fraction ``lam``
from the step the joint bounds allow (``v_lim``) towards the hardest braking they allow (``b``, each joint's speed
reduced by ``a_max h`` towards 0): every such step keeps the joint bounds (speed, acceleration, the joint limits,
never past the goal: ``b`` lies between 0 and ``v_lim``), and the smallest ``lam`` whose speed is within
``LIMIT_MARGIN`` of the bound is taken. A switch into collaborative mode from a fast motion therefore brakes at the
joint acceleration bound, never steps: ``ramp_time`` after the switch the group is within the bound (the auditor
allows that ramp).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mds_ach.kinematics.model import ArmKinematics, _default_model
from mds_ach.robot import motion
from mds_ach.robot.joints import LEFT_ARM, RIGHT_ARM, TORSO

MAX_SPEED = motion.COLLABORATIVE_MAX_SPEED  # m/s: ISO 10218-1 reduced speed; configurable lower, never higher
LIMIT_MARGIN = 0.9  # the daemon aims this far inside the bound (as the joint limiter does)
CHECK_TOLERANCE = 1e-6  # m/s: float32 targets and float rounding
JOINTS: tuple[str, ...] = TORSO + LEFT_ARM + RIGHT_ARM  # the group: WST, then each arm in the IK order
POINTS: tuple[str, ...] = ("left hand", "left elbow", "right hand", "right elbow")
GRID = 32  # lam is chosen on a grid of 1/GRID (about 3 % of the step)


def validate_max_speed(value: float) -> float:
    """The configured bound: finite, > 0 and at most ``MAX_SPEED`` (configurable down only)."""
    if not (math.isfinite(value) and 0 < value <= MAX_SPEED):
        raise ValueError(f"collaborative Cartesian speed bound must be in (0, {MAX_SPEED * 1e3:g}] mm/s "
                         f"(configurable down only), got {value * 1e3:g} mm/s")
    return value


def ramp_time(max_velocity: float, max_acceleration: float, max_interval: float) -> float:
    """How long after a switch into collaborative mode the group may still be braking into the bound (s): from the
    velocity bound to rest at the limiter's acceleration, plus one step."""
    return max_velocity / (LIMIT_MARGIN * max_acceleration) + max_interval


class UpperBody:
    """Batched positions of the hands and elbows in the base frame (the torso pan turns both arms)."""

    def __init__(self) -> None:
        model = _default_model()
        self.arms = (ArmKinematics(model, "left"), ArmKinematics(model, "right"))
        torso = model.chain(model.root, "torso")
        waist = [j for j in torso if j.actuated]
        if [j.name for j in waist] != list(TORSO):
            raise ValueError(f"URDF: expected the torso pan {TORSO} between the base and the torso, found "
                             f"{[j.name for j in waist]}")
        self._waist_axis = waist[0].axis
        after = np.eye(4)
        seen = False
        for j in torso:
            if seen:
                after = after @ j.origin
            seen = seen or j.actuated
        self._after = after  # the waist joint's child frame -> torso (a displacement is rotation-invariant)

    def points(self, q: np.ndarray) -> np.ndarray:
        """``q`` (..., 13) in ``JOINTS`` order -> (..., 4, 3) in ``POINTS`` order (the waist joint's frame)."""
        q = np.asarray(q, dtype=float)
        out = []
        for k, arm in enumerate(self.arms):
            pts = arm.joint_points(q[..., 1 + 6 * k: 7 + 6 * k])
            out += [pts["tool"], pts["elbow"]]
        local = np.stack(out, axis=-2)  # (..., 4, 3) torso frame
        local = local @ self._after[:3, :3].T + self._after[:3, 3]
        rot = _rotations(self._waist_axis, q[..., 0])  # (..., 3, 3)
        return local @ np.swapaxes(rot, -1, -2)


def _rotations(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rotations about ``axis`` by ``angles`` (...,) -> (..., 3, 3) (Rodrigues, batched)."""
    x, y, z = (float(c) for c in axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    angles = np.asarray(angles, dtype=float)[..., None, None]
    return np.eye(3) + np.sin(angles) * k + (1.0 - np.cos(angles)) * (k @ k)


@lru_cache(maxsize=1)
def upper_body() -> UpperBody:
    return UpperBody()


def speeds(q: np.ndarray, v: np.ndarray, h: float, body: UpperBody | None = None) -> np.ndarray:
    """Speed (m/s) of each point for steps ``v`` (..., 13, rad/s) from ``q`` (13,) counted over ``h`` (s)."""
    body = body or upper_body()
    v = np.asarray(v, dtype=float)
    q = np.asarray(q, dtype=float)
    if h <= 0:
        return np.zeros(v.shape[:-1] + (len(POINTS),))
    both = body.points(np.concatenate([q[None, :], (q + v * h).reshape(-1, q.shape[-1])]))
    return (np.linalg.norm(both[1:] - both[0], axis=-1) / h).reshape(v.shape[:-1] + (len(POINTS),))


@dataclass(frozen=True)
class Scaled:
    """What :meth:`CartesianBound.scale` chose: the fraction towards braking and the resulting speed (m/s)."""

    lam: float  # 0: the joint bounds' step unchanged; 1: every joint braked as hard as they allow
    speed: float  # the fastest point's speed with that step
    unscaled: float  # ... with the joint bounds' step
    within: bool  # the speed is within the bound (False only while braking into it, lam == 1)


class CartesianBound:
    """The daemon's collaborative-mode bound on one group's batch of steps."""

    def __init__(self, max_speed: float = MAX_SPEED) -> None:
        self.max_speed = validate_max_speed(max_speed)
        self.body = upper_body()

    def scale(self, q: Sequence[float], v_lim: Sequence[float], brake: Sequence[float], h: float) -> Scaled:
        """The smallest ``lam`` on a grid of [0, 1] (steps of 1/``GRID``) with the speed of
        ``v_lim + lam (brake - v_lim)`` within ``LIMIT_MARGIN`` of the bound; ``lam`` 1 when none is (brake as hard
        as the joint bounds allow). A candidate is only taken for its own speed: the speed along the path need not
        be monotonic. One batched FK call (the loop's budget at 100 Hz)."""
        q_a, v_a, b_a = (np.asarray(x, dtype=float) for x in (q, v_lim, brake))
        if not v_a.any():
            return Scaled(0.0, 0.0, 0.0, True)
        first = float(speeds(q_a, v_a, h, self.body).max())
        if first <= LIMIT_MARGIN * self.max_speed:
            return Scaled(0.0, first, first, True)
        lams = np.linspace(0.0, 1.0, GRID + 1)
        s = speeds(q_a, v_a + lams[:, None] * (b_a - v_a), h, self.body).max(axis=-1)
        ok = np.nonzero(s <= LIMIT_MARGIN * self.max_speed)[0]
        i = int(ok[0]) if ok.size else GRID
        return Scaled(float(lams[i]), float(s[i]), first,
                      bool(s[i] <= self.max_speed * (1 + CHECK_TOLERANCE)))


def brake_velocity(v0: float, a_max: float, h: float) -> float:
    """The hardest braking the acceleration bound allows in one step of ``h`` from ``v0`` (towards 0, never past)."""
    return v0 - max(-a_max * h, min(a_max * h, v0))


def batch_speed(q: Mapping[str, float], v: Mapping[str, float], h: float) -> tuple[float, str]:
    """The batch's speed (m/s) and its fastest point, ``q`` and ``v`` by joint short name (missing: 0)."""
    qa = np.array([q.get(n, 0.0) for n in JOINTS])
    va = np.array([v.get(n, 0.0) for n in JOINTS])
    s = speeds(qa, va, h)
    i = int(np.argmax(s))
    return float(s[i]), POINTS[i]
