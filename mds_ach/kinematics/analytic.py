"""Closed-form inverse kinematics of the MDS arm for a full tool pose (position and orientation).

The arm is a spherical shoulder (pitch about y, roll about x, yaw about z, one point), an elbow pitch (y) a
length ``L1`` below it, a wrist yaw (z, along the forearm) ``L2`` further and a wrist roll (x) at the same
point, the tool ``d`` below the wrist. For a tool pose (R, p) that leaves few unknowns:

* the wrist point is W = p + d R e_z (the tool hangs below it along the tool z axis);
* the forearm direction f = R Rx(-q6) e_z = sin q6 R e_y + cos q6 R e_z, and the elbow E = W + L2 f must lie
  ``L1`` from the shoulder S: a sin q6 + b cos q6 = k, up to two wrist rolls q6;
* the elbow axis is perpendicular to the upper arm and to the forearm: up to two wrist yaws q5 (q5, q5 + pi);
* the elbow angle q4 is the angle from the upper arm to the forearm about that axis;
* the shoulder rotation Ry(q1) Rx(q2) Rz(q3) is then known: two Y-X-Z angle sets.

So at most 8 exact solutions, a few tens of microseconds in plain floats, against an iterative search that
needs a dozen Jacobian steps. ``ArmGeometry.of`` returns None for a chain of another shape (the iterative
solver then does it all). A straight elbow is a singularity (the swivel is free), outside the MDS limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mds_ach.kinematics.model import ArmKinematics

_AXES = (1, 0, 2, 1, 2, 0)  # y, x, z, y, z, x: the joint axes this closed form is written for
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class ArmGeometry:
    """Shoulder point S, upper arm L1, forearm L2 and tool offset d of an arm of the MDS shape."""

    shoulder: tuple[float, float, float]
    upper: float
    fore: float
    tool: float

    @classmethod
    def of(cls, kin: ArmKinematics) -> ArmGeometry | None:
        """The geometry of ``kin`` if its chain has the shape above (all axes positive), else None."""
        chain = kin.scalar_chain
        if chain is None or tuple(c[0] for c in chain) != _AXES or any(c[1] != 1.0 for c in chain):
            return None
        offsets = [c[2:] for c in chain]
        tail = kin._tail_floats
        zero = (0.0, 0.0, 0.0)
        if offsets[1] != zero or offsets[2] != zero or offsets[5] != zero:
            return None
        if offsets[3][:2] != (0.0, 0.0) or offsets[4][:2] != (0.0, 0.0) or tail[:2] != (0.0, 0.0):
            return None
        L1, L2, d = -offsets[3][2], -offsets[4][2], -tail[2]
        if L1 <= 0 or L2 <= 0:
            return None
        sx, sy, sz = offsets[0]
        return cls((sx, sy, sz), L1, L2, d)

    def solve(self, R: list[float], p: list[float]) -> list[list[float]]:
        """Every joint vector [SP, SR, SY, EP, WY, WR] (angles in (-pi, pi]) with tool pose R (9 floats,
        row-major) and p; no limits applied. Empty when the pose is out of reach."""
        X = (R[0], R[3], R[6])
        Y = (R[1], R[4], R[7])
        Z = (R[2], R[5], R[8])
        L1, L2, d = self.upper, self.fore, self.tool
        S = self.shoulder
        W = (p[0] + d * Z[0], p[1] + d * Z[1], p[2] + d * Z[2])
        c = (W[0] - S[0], W[1] - S[1], W[2] - S[2])
        a = c[0] * Y[0] + c[1] * Y[1] + c[2] * Y[2]
        b = c[0] * Z[0] + c[1] * Z[1] + c[2] * Z[2]
        k = (L1 * L1 - L2 * L2 - (c[0] * c[0] + c[1] * c[1] + c[2] * c[2])) / (2.0 * L2)
        rho = math.hypot(a, b)
        if rho < 1e-12 or abs(k) > rho * (1.0 + 1e-12):
            return []
        phi = math.atan2(a, b)
        delta = math.acos(max(-1.0, min(1.0, k / rho)))
        out: list[list[float]] = []
        for q6 in ((phi + delta, phi - delta) if delta > 1e-12 else (phi,)):
            c6, s6 = math.cos(q6), math.sin(q6)
            f = (s6 * Y[0] + c6 * Z[0], s6 * Y[1] + c6 * Z[1], s6 * Y[2] + c6 * Z[2])  # forearm axis
            u = tuple((S[i] - W[i] - L2 * f[i]) / L1 for i in range(3))  # upper arm axis (shoulder frame z)
            g2 = (c6 * Y[0] - s6 * Z[0], c6 * Y[1] - s6 * Z[1], c6 * Y[2] - s6 * Z[2])
            gu1 = X[0] * u[0] + X[1] * u[1] + X[2] * u[2]
            gu2 = g2[0] * u[0] + g2[1] * u[1] + g2[2] * u[2]
            if math.hypot(gu1, gu2) < 1e-9:
                continue  # straight elbow: the swivel is free (outside the MDS limits); the search handles it
            q5a = math.atan2(-gu2, gu1)
            for q5 in (q5a, q5a + math.pi):
                c5, s5 = math.cos(q5), math.sin(q5)
                ex = tuple(c5 * X[i] - s5 * g2[i] for i in range(3))  # forearm frame x
                ey = tuple(s5 * X[i] + c5 * g2[i] for i in range(3))  # elbow axis
                q4 = math.atan2(-(u[0] * ex[0] + u[1] * ex[1] + u[2] * ex[2]),
                                u[0] * f[0] + u[1] * f[1] + u[2] * f[2])
                c4, s4 = math.cos(q4), math.sin(q4)
                mx1 = c4 * ex[1] + s4 * f[1]  # shoulder frame: x column's y entry; y column = ey; z column = u
                q1 = math.atan2(u[0], u[2])
                q2 = math.atan2(-u[1], math.hypot(mx1, ey[1]))
                q3 = math.atan2(mx1, ey[1])
                tail = [q4, math.remainder(q5, _TWO_PI), math.remainder(q6, _TWO_PI)]
                out.append([q1, q2, q3, *tail])
                out.append([math.remainder(q1 + math.pi, _TWO_PI), math.remainder(math.pi - q2, _TWO_PI),
                            math.remainder(q3 + math.pi, _TWO_PI), *tail])
        return out


def within(q: list[float], lower: list[float], upper: list[float], slack: float = 1e-9) -> list[float] | None:
    """``q`` moved into [lower, upper] by whole turns where that is possible (clamped within ``slack``), else None."""
    out = []
    for v, lo, hi in zip(q, lower, upper, strict=True):
        if v < lo - slack:
            v += _TWO_PI * math.ceil((lo - slack - v) / _TWO_PI)
        elif v > hi + slack:
            v -= _TWO_PI * math.ceil((v - hi - slack) / _TWO_PI)
        if not lo - slack <= v <= hi + slack:
            return None
        out.append(min(max(v, lo), hi))
    return out
