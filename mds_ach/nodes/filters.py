"""Reference smoothing maths, shared by the daemon's per-joint modes and the filter node.

One implementation so the daemon and the filter node can never disagree about what a mode means.
All functions are pure and work on floats or numpy arrays alike.
"""

from __future__ import annotations

import math

import numpy as np

# Original deployment: mds-filter ran at 40 Hz with a 1.57 rad/s rate limit.
DEFAULT_MAX_VELOCITY = 1.57
DEFAULT_SETTLE_TIME = 4.0
DEFAULT_SETTLE_FRACTION = 0.95


def filter_length(rate_hz: float, settle_time: float = DEFAULT_SETTLE_TIME,
                  fraction: float = DEFAULT_SETTLE_FRACTION) -> float:
    """The L of the first-order filter that covers ``fraction`` of a step within ``settle_time``.

    After n steps the remaining error is (1 - 1/L)^n; solving (1 - 1/L)^n = 1 - fraction for
    n = rate * settle_time gives L. At 10 Hz and 95 % in 4.0 s this is L ~= 13.9.
    """
    if not (rate_hz > 0 and settle_time > 0 and 0 < fraction < 1):
        raise ValueError("rate_hz and settle_time must be > 0 and fraction in (0, 1)")
    steps = rate_hz * settle_time
    return 1.0 / (1.0 - (1.0 - fraction) ** (1.0 / steps))


def ema_step(previous, target, length: float):
    """Mode 0 (REF_FILTER): theta_n = (theta_{n-1} * (L - 1) + theta_des) / L."""
    if length < 1:
        raise ValueError("filter length L must be >= 1")
    return (previous * (length - 1.0) + target) / length


def enc_filter_step(measured, target, length: float):
    """Mode 3 (ENC_FILTER): theta_n = (theta_enc * (L - 1) + theta_des) / L (compliant to the encoder)."""
    return ema_step(measured, target, length)


def velocity_limit_step(previous, target, max_velocity: float, dt: float):
    """Constant-velocity ramp towards ``target`` that snaps when within one step (the deployed mds-filter)."""
    step = max_velocity * dt
    delta = np.clip(np.asarray(target, dtype=float) - previous, -step, step)
    out = previous + delta
    return float(out) if np.ndim(out) == 0 else out


def accel_limit_step(previous, velocity, target, max_velocity: float, max_accel: float, dt: float):
    """Velocity- and acceleration-limited move towards ``target``; returns (position, velocity).

    Decelerates so that it stops at the target: the commanded speed never exceeds the speed from which
    braking by max_accel*dt per step still stops within the remaining distance (the discrete-time form of
    sqrt(2*a*distance), which would arrive with speed left and stop in one step).
    """
    prev = np.asarray(previous, dtype=float)
    vel = np.asarray(velocity, dtype=float)
    err = np.asarray(target, dtype=float) - prev
    a_dt = max_accel * dt
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # huge/zero steps: inf, capped next line
        stop_speed = a_dt * (np.sqrt(0.25 + 2.0 * np.abs(err) / (a_dt * dt)) - 0.5)
    desired = np.sign(err) * np.minimum(max_velocity, stop_speed)
    dv = np.clip(desired - vel, -max_accel * dt, max_accel * dt)
    new_vel = vel + dv
    new_pos = prev + new_vel * dt
    # Do not overshoot: land on the target when the step would cross it.
    crossed = np.sign(np.asarray(target, dtype=float) - new_pos) != np.sign(err)
    new_pos = np.where(crossed | (err == 0), target, new_pos)
    new_vel = np.where(crossed | (err == 0), 0.0, new_vel)
    if np.ndim(new_pos) == 0:
        return float(new_pos), float(new_vel)
    return new_pos, new_vel


def is_finite(value: float) -> bool:
    return math.isfinite(value)
