"""The reference pipeline's hand-offs and its cost at rest, on the whole system (``mds-ach start nocan``).

* **Hand-off latency**: a client streams a slow ramp on one joint at 50 Hz on a legacy input (``mds-ref-filter``,
  ``mds-ref``); each stage's output channel (``mds-ref-mux``, ``mds-ref-smooth``, ``mds-ref-gated``) is read by a
  thread blocked on it. The latency of a put at a stage is the time until that stage's first output frame after
  it (an event-driven stage answers the put itself; a polling one at its next tick). The daemon's own period is
  not in it: ``mds-ref-gated`` is the daemon's input.
* **Idle CPU**: CPU time (utime + stime, /proc/<pid>/stat, every thread and child) of every node over a window
  with nothing commanded, as a fraction of one core. CPU time, not wall: on a busy machine our processes' CPU
  time is still ours.

``python -m bench.bench_events [--quick]`` inside ``tools/netns-run`` (it starts and stops its own system in a
private runtime directory); ``test/test_events.py`` uses the same functions.
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.glibc import tune_thread
from mds_ach.nodes.pipeline import make_ref, ref_arrays
from mds_ach.robot.channels import StructChannel

try:
    from bench.common import Row, percentile
except ImportError:  # imported by the tests from test/ with the repo root on sys.path
    from common import Row, percentile  # type: ignore[no-redef]

GROUP = "pipeline"
STAGES = (mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME)
NODES = ("daemon", "mux", "filter", "collision", "ik", "bridge")
TICKS = os.sysconf("SC_CLK_TCK")
JOINT = "LWY"  # left wrist yaw: turning it near the rest pose collides with nothing


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (a node started through a wrapper counts with its children)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def cpu_seconds(pid: int) -> float:
    """utime + stime of ``pid`` and its descendants, in s (a process gone meanwhile counts 0)."""
    total = 0
    for p in _tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / TICKS


def node_pids(runtime: Path) -> dict[str, int]:
    """The running nodes' pids from the launcher's pid files in ``runtime``."""
    from mds_ach.tools.launcher import read_pid

    return {n: pid for n in NODES if (pid := read_pid(n, runtime)) is not None}


def idle_cpu(pids: dict[str, int], seconds: float) -> dict[str, float]:
    """Each node's CPU time over ``seconds`` of wall time as a fraction of one core (``total``: their sum)."""
    start = {n: cpu_seconds(p) for n, p in pids.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - t0
    out = {n: (cpu_seconds(p) - start[n]) / wall for n, p in pids.items()}
    out["total"] = sum(out.values())
    return out


HARNESS_PRIORITY = 10
"""SCHED_FIFO priority of the harness's own threads (the putter and the recorders), below the daemon loop's 50.
Instrumentation, not the product: at normal priority on a busy machine the recorders' own wake-ups (three threads
sharing one interpreter lock, any of them preempted while holding it) were most of a 70-140 ms p99; the nodes
measured stay at normal priority. Refused (no privilege): measured anyway, and the result says so."""

ROS = "ROS /mds/joint_command"
"""The ROS input of ``handoff_latency``: a ``sensor_msgs/JointState`` position command to the bridge."""


def _realtime() -> bool:
    """Put the calling harness thread at ``HARNESS_PRIORITY``; False if refused."""
    return not tune_thread(HARNESS_PRIORITY)


class _Recorder(threading.Thread):
    """Blocks on one reference channel and records the arrival time (CLOCK_MONOTONIC) of every new frame and its
    reference for ``JOINT``."""

    def __init__(self, name: str) -> None:
        super().__init__(name=f"rec-{name}", daemon=True)
        self.chan = ach.Channel(name, create=False)
        self.chan.flush()
        self.times: list[float] = []
        self.values: list[float] = []
        self.stop = threading.Event()
        self.realtime = False

    def run(self) -> None:
        self.realtime = _realtime()
        buf = mds.MDS_REF()
        address = mds.BY_SHORT[JOINT].address
        while not self.stop.is_set():
            try:
                status, _ = self.chan.get(buf, wait=True, last=True, timeout=0.2)
            except ach.AchException:
                return
            if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                self.times.append(time.monotonic())
                self.values.append(buf.joint[address].ref)

    def close(self) -> None:
        self.stop.set()
        self.join(2.0)
        self.chan.close()


class Latency(NamedTuple):
    """Per stage output channel, the latency in s of each put; ``realtime``: the harness ran SCHED_FIFO."""

    stages: dict[str, list[float]]
    realtime: bool


def _ros_sender() -> tuple[Callable[[np.ndarray], None], Callable[[], None]]:
    """A publisher of position commands for ``JOINT`` on the bridge's ``/mds/joint_command`` (connected before it
    returns) and its close."""
    import rclpy
    from sensor_msgs.msg import JointState

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_events", context=context)
    pub = node.create_publisher(JointState, "/mds/joint_command", 10)
    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise RuntimeError("the bridge did not subscribe to /mds/joint_command within 30 s")
        time.sleep(0.05)
    address = mds.BY_SHORT[JOINT].address

    def send(ref: np.ndarray) -> None:
        pub.publish(JointState(name=[JOINT], position=[float(ref[address])]))

    def close() -> None:
        node.destroy_node()
        context.try_shutdown()

    return send, close


def handoff_latency(source: str, count: int = 150, rate: float = 50.0, step: float = 0.001) -> Latency:
    """Stream ``count`` commands at ``rate`` on ``source`` (a channel name, or ``ROS``: the bridge's topic, with the
    bridge's channel ``mds-ref-ros`` as a first stage), a ramp of ``step`` rad per command on ``JOINT`` from the
    current reference; per stage output, the latency in s of each command (until that stage's first frame after
    it)."""
    address = mds.BY_SHORT[JOINT].address
    gated = ach.Channel(mds.MDS_CHAN_DAEMON_INPUT_NAME, create=False)
    frame = mds.MDS_REF()
    status, _ = gated.get(frame, last=True, copy=True)
    gated.close()
    assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME), "no reference on mds-ref-gated"
    ref, mode = ref_arrays(frame)
    stages = STAGES
    if source == ROS:
        send, close = _ros_sender()
        stages = (mds.MDS_CHAN_REF_ROS_NAME, *STAGES)  # the bridge's own hand-off first
    else:
        inp = ach.Channel(source, create=False)
        send, close = (lambda r: inp.put(bytes(make_ref(r, mode)))), inp.close
    recorders = {name: _Recorder(name) for name in stages}
    for r in recorders.values():
        r.start()
    put_times: list[float] = []
    realtime = [False]

    def stream() -> None:
        realtime[0] = _realtime()
        period = 1.0 / rate
        next_t = time.monotonic()
        for k in range(count):
            ref[address] += step if (k // 50) % 2 == 0 else -step  # back and forth: stays near the rest pose
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            put_times.append(time.monotonic())
            send(ref)

    try:
        time.sleep(0.3)  # the recorders are blocked on their channels
        putter = threading.Thread(target=stream, name="putter")
        putter.start()
        putter.join()
        time.sleep(0.5)
    finally:
        for r in recorders.values():
            r.close()
        close()
    result: dict[str, list[float]] = {}
    for name, r in recorders.items():
        arrivals = np.array(r.times)
        lat = []
        for t in put_times:
            later = arrivals[arrivals >= t]
            if later.size:
                lat.append(float(later[0] - t))
        result[name] = lat
    return Latency(result, realtime[0] and all(r.realtime for r in recorders.values()))


GOAL_STEP = 0.02
"""rad: each FollowJointTrajectory goal of ``goal_first_target`` moves ``JOINT`` this far (back and forth)."""
GOAL_DURATION = 0.3
"""s: the goal's duration (its last point's time_from_start)."""
GOAL_WARMUP = 2
"""Goals sent first and not counted: a new action client's first goals waited 180-370 ms once in a few runs on the
loaded machine (DDS matching of the action's topics and the bridge's first goal, one-time costs of a connection),
the steady state is what a MoveIt or teleoperation client sees goal after goal."""


class GoalLatency(NamedTuple):
    """Per goal, the latency in s from sending it to its first target on each stage (``mds-ref-ros``: the bridge's
    write; ``mds-ref-gated``: the daemon's input); ``period``: the daemon's (median ``mds-state`` interval): the bridge
    writes an accepted goal's first target at once, for the daemon's next cycle, then once per state frame."""

    stages: dict[str, list[float]]
    period: float
    realtime: bool


def _newest(name: str) -> float:
    """``JOINT``'s reference in the newest frame of reference channel ``name`` (NaN: none yet)."""
    with StructChannel(name, mds.MDS_REF, create=False) as chan:
        frame = chan.latest()
    return math.nan if frame is None else float(frame.joint[mds.BY_SHORT[JOINT].address].ref)


def daemon_period(frames: int = 11) -> float:
    """s: the median interval of ``frames`` consecutive ``mds-state`` frames."""
    chan = ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    buf = mds.MDS_STATE()
    times: list[float] = []
    try:
        chan.flush()
        while len(times) < frames:
            status, _ = chan.get(buf, wait=True, last=True, timeout=2.0)
            if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                raise RuntimeError(f"no mds-state frame within 2 s ({ach.result_string(status)})")
            times.append(time.monotonic())
    finally:
        chan.close()
    return float(np.median(np.diff(times)))


def goal_first_target(count: int = 20) -> GoalLatency:
    """Send ``count`` FollowJointTrajectory goals (after ``GOAL_WARMUP`` not counted), one at a time at a random
    point of the daemon's cycle, each moving ``JOINT`` by ``GOAL_STEP`` over ``GOAL_DURATION`` from the measured
    pose (the other joints of its controller staying), as MoveIt sends them; per stage, the latency of each goal
    until the stage's first frame with a new ``JOINT`` reference."""
    import rclpy
    from control_msgs.action import FollowJointTrajectory
    from rclpy.action import ActionClient
    from rclpy.executors import SingleThreadedExecutor
    from trajectory_msgs.msg import JointTrajectoryPoint

    from mds_ach_bridge import follow

    controller = next(c for c, names in follow.CONTROLLERS.items() if JOINT in names)
    names = list(follow.CONTROLLERS[controller])
    period = daemon_period()
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("bench_events_goals", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    client = ActionClient(node, FollowJointTrajectory, f"/{controller}/{follow.ACTION}")
    stages = (mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME)
    recorders = {name: _Recorder(name) for name in stages}
    sent: list[tuple[float, dict[str, float]]] = []  # (send time, JOINT's reference on each stage before it)
    problems: list[str] = []
    realtime = [False]
    phase = np.random.default_rng(26)

    def wait(future: Any, what: str) -> Any:
        executor.spin_until_future_complete(future, timeout_sec=30.0)
        if not future.done():
            raise RuntimeError(f"no {what} within 30 s")
        return future.result()

    def goals() -> None:
        realtime[0] = _realtime()
        try:
            deadline = time.monotonic() + 30.0
            while not client.server_is_ready():
                if time.monotonic() > deadline:
                    raise RuntimeError(f"no {controller} action server within 30 s")
                executor.spin_once(timeout_sec=0.05)
            for k in range(-GOAL_WARMUP, count):
                with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as chan:
                    state = chan.wait(timeout=2.0)
                if state is None:
                    raise RuntimeError("no mds-state frame within 2 s")
                time.sleep(phase.uniform(0.0, period))  # sent at any point of the daemon's cycle (at rest: same pose)
                start = [state.joint[mds.BY_SHORT[n].address].pos for n in names]
                end = [q + (GOAL_STEP if k % 2 == 0 and n == JOINT else -GOAL_STEP if n == JOINT else 0.0)
                       for n, q in zip(names, start, strict=True)]
                goal = FollowJointTrajectory.Goal()
                goal.trajectory.joint_names = names
                for t, pos in ((0.0, start), (GOAL_DURATION, end)):
                    point = JointTrajectoryPoint(positions=pos)
                    point.time_from_start.sec, point.time_from_start.nanosec = int(t), int(round(t % 1 * 1e9))
                    goal.trajectory.points.append(point)
                if k >= 0:
                    sent.append((time.monotonic(), {name: _newest(name) for name in stages}))
                handle = wait(client.send_goal_async(goal), "goal response")
                if not handle.accepted:
                    raise RuntimeError(f"goal {k} rejected")
                wait(handle.get_result_async(), "goal result")
                time.sleep(0.2)  # at rest again: the next goal's first target is the first change
        except RuntimeError as exc:
            problems.append(str(exc))

    try:
        for r in recorders.values():
            r.start()
        time.sleep(0.3)  # the recorders are blocked on their channels
        runner = threading.Thread(target=goals, name="goals")
        runner.start()
        runner.join()
    finally:
        for r in recorders.values():
            r.close()
        node.destroy_node()
        context.try_shutdown()
    if problems:
        raise RuntimeError(problems[0])
    result: dict[str, list[float]] = {}
    for name, r in recorders.items():
        times, values = np.array(r.times), np.array(r.values)
        lat = []
        for t, before in sent:
            later = (times >= t) & (np.abs(values - before[name]) > 1e-9)
            if later.any():
                lat.append(float(times[later][0] - t))
        result[name] = lat
    return GoalLatency(result, period, realtime[0] and all(r.realtime for r in recorders.values()))


@contextmanager
def whole_system() -> Iterator[Path]:
    """``mds-ach start nocan`` in a private runtime directory (inside tools/netns-run); stopped afterwards."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
    from support.system import running_system

    with tempfile.TemporaryDirectory(prefix="mds-bench-events-") as tmp, running_system(Path(tmp)):
        yield Path(tmp)


ORIGINAL_FILTER_RATE = 40.0
"""Hz: the original mds-filter's loop, which read ``mds-ref-filter`` once per tick (the anchor of the legacy path)."""
JTC_RATE = 100.0
"""Hz: ros2_control's controller_manager default ``update_rate``: joint_trajectory_controller reads a command at
its next update (the anchor of the ROS path)."""


def _anchor(rate: float, q: float) -> float:
    """ms: the q-th percentile of the wait for the next tick of a loop at ``rate`` polling its input (uniform; an
    infinite rate: no stage in between, 0)."""
    return q / 100.0 * 1e3 / rate


def run(quick: bool = False) -> list[Row]:
    rows: list[Row] = []
    with whole_system() as runtime:
        time.sleep(3.0)  # start-up work (imports, first frames) is not rest
        pids = node_pids(runtime)
        cpu = idle_cpu(pids, 10.0 if quick else 60.0)
        each = ", ".join(f"{n} {cpu[n] * 100:.1f}" for n in pids)
        rows.append(Row(GROUP, f"idle CPU, whole system, {10 if quick else 60} s ({each} %)", cpu["total"] * 100,
                        "% core", target="<= 5 % of one core", passed=cpu["total"] <= 0.05))
        # the legacy inputs first: a ROS command makes the bridge's controller own the joint until it goes stale
        # anchors: the original read mds-ref-filter in mds-filter's 40 Hz loop; mds-ref was its daemon's own input
        inputs = ((mds.MDS_CHAN_REF_FILTER_NAME, "original mds-filter 40 Hz poll", ORIGINAL_FILTER_RATE),
                  (mds.MDS_CHAN_REF_NAME, "original: mds-ref is the daemon's input", math.inf),
                  (ROS, "joint_trajectory_controller 100 Hz", JTC_RATE))
        for source, anchor, rate in inputs:
            lat = handoff_latency(source, count=60 if quick else 300)
            gated = [v * 1e3 for v in lat.stages[mds.MDS_CHAN_DAEMON_INPUT_NAME]]
            harness = "" if lat.realtime else ", harness not real-time"
            for q in (50, 99):
                value = percentile(gated, q)
                rows.append(Row(GROUP, f"{source} -> mds-ref-gated p{q} (50 Hz stream{harness})", value, "ms",
                                baseline_name=f"anchor: {anchor} (computed)", baseline_value=_anchor(rate, q),
                                target="p99 <= 5 ms" if q == 99 else "",
                                passed=value <= 5.0 if q == 99 else None))
        # a goal's first target is written when the goal is accepted, for the daemon's next cycle (it waited for the
        # bridge's next state frame: up to one period); the item's bound stays "5 ms beyond the daemon's period"
        goals = goal_first_target(count=8 if quick else 40)
        first = [v * 1e3 for v in goals.stages[mds.MDS_CHAN_DAEMON_INPUT_NAME]]
        bound = goals.period * 1e3 + 5.0
        harness = "" if goals.realtime else ", harness not real-time"
        for q in (50, 99):
            value = percentile(first, q)
            rows.append(Row(GROUP, f"FollowJointTrajectory goal -> first target on mds-ref-gated p{q} "
                                   f"(daemon period {goals.period * 1e3:.0f} ms{harness})", value, "ms",
                            baseline_name="anchor: joint_trajectory_controller 100 Hz (computed)",
                            baseline_value=_anchor(JTC_RATE, q),
                            target=f"p99 <= period + 5 ms ({bound:.0f} ms)" if q == 99 else "",
                            passed=value <= bound if q == 99 else None))
    return rows


def main(argv: list[str]) -> int:
    rows = run(quick="--quick" in argv)
    for r in rows:
        print(f"{r.name}: {r.value:.2f} {r.unit} {'' if r.passed is None else ('ok' if r.passed else 'NO')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
