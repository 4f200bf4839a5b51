"""The daemon's last-line motion bounds: what limit() sends always passes check(), and it still arrives."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mds_ach.robot.motion import MotionBounds, Track, check, limit

BOUNDS = MotionBounds(max_velocity=2.0, max_acceleration=8.0, max_interval=0.15)


def _run(desired: list[float], dts: list[float], q0: float = 0.0) -> list[tuple[float, float]]:
    track, now, sent = Track(q0, 0.0, 0.0), 0.0, []
    for want, dt in zip(desired, dts, strict=True):
        now += dt
        q = limit(track, want, now, BOUNDS)
        assert check(track, q, now, BOUNDS) == [], (track, q, now)
        track.advance(q, now, BOUNDS)
        sent.append((now, q))
    return sent


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.0, 3.0), st.one_of(st.floats(0.001, 0.2), st.floats(0.2, 5.0))),
                min_size=1, max_size=200))
def test_every_limited_target_passes_the_audit_whatever_the_timing(steps: list[tuple[float, float]]) -> None:
    _run([s[0] for s in steps], [s[1] for s in steps])


def test_a_distant_target_is_reached_at_the_velocity_bound_without_overshoot() -> None:
    sent = _run([2.0] * 60, [0.1] * 60)
    qs = [q for _, q in sent]
    assert max(qs) <= 2.0 + 1e-9
    assert abs(qs[-1] - 2.0) < 1e-6
    # 0.9 * 2 rad/s cruise: about 1.1 s of travel plus ramps, at 10 Hz
    arrival = next(i for i, q in enumerate(qs) if abs(q - 2.0) < 1e-3)
    assert 10 <= arrival <= 20, arrival


def test_a_stall_does_not_earn_a_bigger_step() -> None:
    track = Track(0.0, 0.0, 0.0)
    q = limit(track, 1.5, 3.0, BOUNDS)  # 3 s since the last target
    assert abs(q) <= 0.9 * BOUNDS.max_acceleration * BOUNDS.max_interval ** 2 + 1e-12


def test_check_reports_a_jump() -> None:
    track = Track(0.0, 0.0, 0.0)
    kinds = {v.kind for v in check(track, 0.5, 0.1, BOUNDS)}
    assert kinds == {"speed", "acceleration"}
    assert check(Track(0.0, 0.0, 0.0), 0.02, 0.1, BOUNDS) == []
    assert math.isinf(BOUNDS.interval(math.inf)) is False


def _trapezoid(distance: float, v: float, a: float, t: float) -> float:
    """Position at ``t`` of a rest-to-rest move over ``distance`` with speed ``v`` and acceleration ``a``."""
    t_acc = v / a
    t_cruise = distance / v - t_acc
    if t < t_acc:
        return 0.5 * a * t * t
    if t < t_acc + t_cruise:
        return 0.5 * a * t_acc ** 2 + v * (t - t_acc)
    t_end = 2 * t_acc + t_cruise
    return distance - 0.5 * a * max(t_end - t, 0.0) ** 2


def test_a_reference_moving_within_the_bounds_is_trailed_by_its_braking_distance_and_never_passed() -> None:
    """What the filter sends (1.57 rad/s, 4 rad/s^2) is followed within the bounds, nothing ever past it: the target
    trails the reference by at most the distance it needs to stop at it (it could stop where the reference is,
    whenever the reference stops), and arrives with it."""
    track, h = Track(0.0, 0.0, 0.0), 0.1
    previous = 0.0
    a = 0.9 * BOUNDS.max_acceleration
    for k in range(1, 40):
        now = k * h
        desired = _trapezoid(2.0, 1.57, 4.0, now)
        q = limit(track, desired, now, BOUNDS, desired_velocity=(desired - previous) / h)
        assert check(track, q, now, BOUNDS) == []
        v = (q - track.q) / h
        assert q <= desired + 1e-12, (now, q, desired)
        assert desired - q <= v * v / (2 * a) + v * h + 1e-9, (now, q, desired)  # within its stopping distance
        track.advance(q, now, BOUNDS)
        previous = desired
    assert track.q == pytest.approx(2.0, abs=1e-9)


@pytest.mark.parametrize("rate", [10.0, 100.0, 200.0])
def test_a_target_closing_in_on_a_reference_that_stops_never_passes_it(rate: float) -> None:
    """A reference that stops at once (the collision gate stops an arm at a contact more abruptly than the bounds
    allow) is never passed: the target is always able to stop where the reference is. Before, a target following
    it at speed ran on past it by up to v^2/2a (0.084 rad at 10 Hz here), into the contact; at 100 Hz the same
    happened to a target closing in on a reference it trailed (test_collision_node.py, the 100 Hz adversary)."""
    h, frame = 1.0 / rate, 0.025  # the daemon's period; the gate's frames (40 Hz)
    track = Track(0.0, 0.0, 0.0)
    stop_at = 0.6  # where the gate stops the reference (a contact ahead)
    goal = goal_prev = 0.0
    t_prev = 0.0
    for k in range(1, round(1.5 * rate)):
        now = k * h
        t_frame = math.floor(now / frame + 1e-9) * frame  # the newest gate frame the daemon has read
        reference = 1.5 * t_frame  # moving at 1.5 rad/s (the published velocity), stopped at once at the contact
        goal_prev, goal = goal, min(reference, stop_at)
        velocity = (goal - goal_prev) / (now - t_prev)  # as the daemon estimates it: per cycle
        t_prev = now
        q = limit(track, goal, now, BOUNDS, desired_velocity=velocity)
        assert check(track, q, now, BOUNDS) == [], (now, q)
        assert q <= stop_at + 1e-9, f"{q - stop_at:.4f} rad past the reference where it stopped (t {now:.3f} s)"
        track.advance(q, now, BOUNDS)
    assert track.q == pytest.approx(stop_at, abs=1e-6)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.0, 3.0), st.floats(-50.0, 50.0)), min_size=1, max_size=100),
       st.floats(0.01, 0.2))
def test_targets_stay_in_bounds_and_inside_the_walls_whatever_the_target_velocity(
        steps: list[tuple[float, float]], h: float) -> None:
    """Any claimed target velocity, any target in the joint range: the bounds hold and the limiter never leaves
    [lower, upper] (it brakes for the limits as for a target at rest)."""
    lower, upper = -1.0, 1.5
    track, now = Track(0.0, 0.0, 0.0), 0.0
    for want, velocity in steps:
        now += h
        q = limit(track, min(max(want, lower), upper), now, BOUNDS, desired_velocity=velocity, lower=lower,
                  upper=upper)
        assert check(track, q, now, BOUNDS) == [], (track, q, now)
        assert lower - 1e-9 <= q <= upper + 1e-9, (track, q)
        track.advance(q, now, BOUNDS)


def test_an_overestimated_reference_velocity_never_carries_the_target_past_a_reachable_stop() -> None:
    """The daemon estimates the reference's velocity from samples; when the reference stopped (e.g. held by the
    collision gate) and stopping there is within the acceleration bound, the target stops there, not beyond."""
    track = Track(0.0, 0.5, 0.0)  # moving at 0.5 rad/s
    q = limit(track, 0.02, 0.1, BOUNDS, desired_velocity=1.5)  # the stale estimate says 1.5 rad/s
    assert 0.0 <= q <= 0.02 + 1e-12, q
    assert check(track, q, 0.1, BOUNDS) == []
    # where stopping is not within the bound, the bound wins: passed by what braking requires, no more
    fast = Track(0.0, 1.6, 0.0)
    q = limit(fast, 0.0, 0.1, BOUNDS, desired_velocity=1.6)
    assert check(fast, q, 0.1, BOUNDS) == [] and 0.0 < q <= (1.6 - 0.9 * 8.0 * 0.1) * 0.1 + 1e-12, q
