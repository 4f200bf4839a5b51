"""The daemon's last-line motion bounds: what limit() sends always passes check(), and it still arrives."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from mds_ach.motion import MotionBounds, Track, check, limit

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
