"""Trajectory execution (issue #26): tracking, replacement and cancel, on the running simulated robot.

Runs inside tools/netns-run (``make bench``): ``mds-ach start nocan`` (daemon at its default 10 Hz, mux, filter, gate,
IK, bridge), and a FollowJointTrajectory client in this process (``support.tracking``). Every number is taken on the
*measured* positions (/joint_states) of the left arm (LSP, LEP), against the desired motion of the goal, known
exactly (its header stamp sets its start).

* tracking: MoveIt-style minimum-jerk goals of 1, 2 and 4 s and trapezoids of 1, 2 and 4 s, at the published
  limits (``mds-limits``; a 4 s trapezoid at them is longer than the arm's range: it cruises slower, at the published
  acceleration): the largest |desired - measured| while it runs, the best-fit lag, and when the result
  came after T (MoveIt's allowance: 0.2 T + 0.5 s);
* replacement: a goal cruising at 0.8 rad/s replaced by one from the measured state at rest (what MoveIt sends):
  going back, how far past the replacement point (bound v^2/2a + v period + 0.01 rad); going on, how far back;
* cancel at 0.38 and 0.9 rad/s: travel after the request (bound v^2/2a + v period + 0.02 rad).

Anchors: the original's direct 10 Hz path (the desired position sent as the MOVETO target each cycle) on the same
MCB model (``support.tracking.direct_path``), and joint_trajectory_controller's lag of one control cycle at its usual
100 Hz (10 ms: what ros2_control's controller does by construction; not measured here, there is no ros2_control).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
from pathlib import Path

from support.system import running_system  # test/support/, on sys.path via bench/__init__.py
from support.tracking import (
    TrackingProbe,
    cruise,
    direct_path,
    minimum_jerk,
    minjerk_amplitude,
    move_with_room,
    published,
    state_period,
    stop_report,
    trapezoid,
)

from bench.common import Row

GROUP = "tracking"
ARM = ("LSP", "LEP")
CONTROLLER = "left_arm_controller"
JTC_LAG_MS = 10.0  # one cycle of joint_trajectory_controller at 100 Hz
JTC = "joint_trajectory_controller: 1 cycle at 100 Hz"


def _trapezoid_distance(duration: float, v: float, a: float) -> float:
    """The distance a trapezoid at ``v``, ``a`` covers in ``duration`` s (a triangle when it is too short)."""
    if duration <= 2 * v / a:
        return a * duration * duration / 4
    return v * (duration - v / a)


def _trapezoid_velocity(duration: float, distance: float, v: float, a: float) -> float:
    """The cruise speed (at most ``v``) of a trapezoid at ``a`` that covers ``distance`` in ``duration`` s: a 4 s move
    at the published limits is longer than the arm's range, so it cruises slower."""
    return min(v, 0.5 * a * (duration - math.sqrt(max(0.0, duration * duration - 4.0 * distance / a))))


def _tracking_rows(probe: TrackingProbe) -> list[Row]:
    v, a = published(ARM)
    rows: list[Row] = []
    goals = [("minimum jerk", d) for d in (1.0, 2.0, 4.0)] + [("trapezoid", d) for d in (1.0, 2.0, 4.0)]
    for kind, duration in goals:
        what = f"{kind} {duration:.1f} s at the limits"
        if kind == "trapezoid":
            amplitude = _trapezoid_distance(duration, v, a) * 0.98
            start, delta = move_with_room(probe, ARM, amplitude)
            room = max(abs(d) for d in delta)
            cruise_v = v if room >= amplitude - 1e-9 else _trapezoid_velocity(duration, room, v, a)
            profile = trapezoid(ARM, start, delta, cruise_v, a)
            if cruise_v < v:  # the arm's range is shorter than a move at the limits this long
                what = f"trapezoid {profile.duration:.1f} s at {cruise_v:.2f} rad/s, a at the limit"
        else:
            start, delta = move_with_room(probe, ARM, minjerk_amplitude(duration, v, a) * 0.98)
            profile = minimum_jerk(ARM, start, delta, duration)
        t = probe.run(CONTROLLER, profile)
        base_error, base_lag = direct_path(profile)
        rows += [
            Row(GROUP, f"{what}: max |desired - measured|", t.max_error, "rad", "original direct 10 Hz path (model)",
                base_error, target="<= 0.05 rad", passed=t.max_error <= 0.05),
            Row(GROUP, f"{what}: best-fit lag", 1e3 * t.lag, "ms", JTC, JTC_LAG_MS),
            Row(GROUP, f"{what}: result after T", t.result_after - profile.duration, "s",
                "original direct 10 Hz path: lag (model)", base_lag,
                target=f"<= 0.2 T + 0.5 ({0.2 * profile.duration + 0.5:.1f} s)",
                passed=t.result_after <= t.allowance and t.final_error <= 0.01),
        ]  # fmt: skip
    return rows


def _replacement_rows(probe: TrackingProbe) -> list[Row]:
    from action_msgs.msg import GoalStatus

    rows = []
    _, a = published(ARM)
    for direction in ("back", "on"):
        c = cruise(probe, CONTROLLER, "LSP", 0.8, 1.6)
        period = state_period(probe)
        t_replace = probe.now()
        step = -c.sign * 0.3 if direction == "back" else c.sign * 0.6  # back: within what it travelled
        second = minimum_jerk(("LSP",), (probe.position("LSP"),), (step,), 2.0)
        replaced = probe.send(CONTROLLER, probe.goal_message(CONTROLLER, second, 0.0), tolerance=0.01)
        first = probe.result(c.handle, 10.0).result.error_string
        res = probe.result(replaced, 20.0)
        if res.status != GoalStatus.STATUS_SUCCEEDED or "preempted" not in first:
            print(f"[bench_tracking] replacement going {direction}: the first goal: {first}; the replacing goal: "
                  f"{res.result.error_string}", file=sys.stderr)
        v, past, back = stop_report(probe, c, "LSP", t_replace)
        if direction == "back":
            bound = v * v / (2 * a) + v * period + 0.01
            rows.append(Row(GROUP, f"replaced at {v:.2f} rad/s, going back: past the point", past, "rad",
                            "v^2/2a (braking at the published a)", v * v / (2 * a), target=f"<= {bound:.3f} rad",
                            passed=past <= bound))
        else:
            rows.append(Row(GROUP, f"replaced at {v:.2f} rad/s, going on: reversal", back, "rad",
                            target="<= 0.01 rad", passed=back <= 0.01))
    return rows


def _cancel_rows(probe: TrackingProbe) -> list[Row]:
    rows = []
    _, a = published(ARM)
    for speed in (0.38, 0.9):
        c = cruise(probe, CONTROLLER, "LSP", speed, 1.6)
        period = state_period(probe)
        t_request = probe.now()
        cancel = c.handle.cancel_goal_async()
        probe.spin_until(cancel.done, 10.0, "the cancel response")
        probe.result(c.handle, 10.0)
        probe.spin_for(2.0)
        v, travel, back = stop_report(probe, c, "LSP", t_request)
        bound = v * v / (2 * a) + v * period + 0.02
        rows.append(Row(GROUP, f"cancel at {v:.2f} rad/s: travel after the request", travel, "rad",
                        "v^2/2a (braking at the published a)", v * v / (2 * a), target=f"<= {bound:.3f} rad",
                        passed=travel <= bound and back <= 0.01))
    return rows


def run(quick: bool = False) -> list[Row]:
    if os.environ.get("MDS_NETNS_ACTIVE") != "1" or os.environ.get("MDS_NETNS_SHARE_SHM") == "1":
        raise RuntimeError("bench_tracking needs a private namespace and /dev/shm: run it through tools/netns-run")
    with tempfile.TemporaryDirectory(prefix="mds-bench-tracking-") as tmp, running_system(Path(tmp)):
        probe = TrackingProbe("bench_tracking")
        try:
            rows = _tracking_rows(probe)
            if not quick:
                rows += _replacement_rows(probe) + _cancel_rows(probe)
        finally:
            probe.close()
    return rows


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        print(row)
