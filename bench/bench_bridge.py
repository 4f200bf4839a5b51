"""Bridge latency and CPU: state frame -> /joint_states in another process, command -> reference in the channel.

Runs inside tools/netns-run (``make bench``) with a private /dev/shm. A child process plays the daemon and the
mux (puts ``mds-state`` at 100 Hz, each frame numbered and timed with CLOCK_MONOTONIC; blocks on
``mds-ref-ros`` and times each reference), this process plays the ROS user (subscribes to /joint_states,
publishes position commands at random phases) with nothing else running in it, exactly as it receives the
baseline; the ``bridge`` executable runs as its own process in between. Baseline, same run: a plain rclpy
JointState publisher process at the same rate and QoS, received here (one DDS hop, nothing else).

Measured:
* state frame put -> JointState received here (Ach hop + bridge + DDS hop);
* ROS command published -> reference in the channel: the bridge writes a position command when it arrives (an
  event, issue #26 item 5), not at the next state frame; the reader playing the mux waits at the mux hand-off
  threads' SCHED_FIFO priority, as the real one does (``bench_events`` measures the whole path to the daemon's
  input with the real nodes);
* the bridge's CPU (user + system, /proc via psutil) while it bridges 100 Hz state plus the commands.
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

from bench.common import Row, median, percentile
from mds_ach.paths import bin_name

RATE_HZ = 100.0
COMMAND_HZ = 25.0
GROUP = "bridge"
BIN = Path(sys.executable).parent

# A plain rclpy publisher: the same 17-joint JointState at the same rate and QoS, CLOCK_MONOTONIC in position[0].
BASELINE_PUBLISHER = textwrap.dedent(
    """
    import sys, time, rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from mds_ach.robot import joints
    rate, seconds = float(sys.argv[1]), float(sys.argv[2])
    rclpy.init()
    node = rclpy.create_node('bench_baseline_publisher')
    pub = node.create_publisher(JointState, 'bench/joint_states', qos_profile_sensor_data)
    msg = JointState(name=list(joints.MODEL_JOINTS), position=[0.0] * len(joints.MODEL_JOINTS))
    while pub.get_subscription_count() == 0:
        time.sleep(0.01)
    print('ready', flush=True)
    period, t = 1.0 / rate, time.monotonic()
    end = t + seconds
    while t < end:
        msg.position[0] = time.monotonic()
        msg.header.stamp = node.get_clock().now().to_msg()
        pub.publish(msg)
        t += period
        time.sleep(max(0.0, t - time.monotonic()))
    rclpy.shutdown()
    """
)


# The daemon and the mux: state frames out, references in; prints what it did as JSON when told to stop.
FAKE_DAEMON = textwrap.dedent(
    """
    import json, sys, threading, time
    import mds_ach as mds
    from mds_ach import ach
    from mds_ach.ach.glibc import tune_thread
    from mds_ach.nodes.pipeline import HANDOFF_RT_PRIORITY
    from mds_ach.robot import joints
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs import MDS_REF, MDS_STATE
    rate = float(sys.argv[1])
    for name in (mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_CHAN_IK_NAME):
        if ach.exists(name):
            ach.unlink(name)
    state_ch = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    ref_ch = StructChannel(mds.MDS_CHAN_REF_ROS_NAME, MDS_REF)
    nkr, lep = joints.BY_SHORT["NKR"].address, joints.BY_SHORT["LEP"].address
    put_times, arrivals, stop = [], [], threading.Event()

    def writer():
        st = MDS_STATE()
        for j in joints.JOINTS:
            st.joint[j.address].address = j.address
        period, t = 1.0 / rate, time.monotonic()
        while not stop.is_set():
            st.joint[nkr].pos = float(len(put_times))
            now = time.monotonic()
            st.time = now
            put_times.append(now)
            state_ch.put(st)
            t += period
            time.sleep(max(0.0, t - time.monotonic()))

    def watcher():
        tune_thread(HANDOFF_RT_PRIORITY)  # as the mux's hand-off thread (no-op without the right to)
        while not stop.is_set():
            ref = ref_ch.wait(timeout=0.1)
            if ref is not None:
                arrivals.append((time.monotonic(), ref.joint[lep].ref))

    threads = [threading.Thread(target=writer), threading.Thread(target=watcher)]
    for th in threads:
        th.start()
    print("ready", flush=True)
    sys.stdin.readline()
    stop.set()
    for th in threads:
        th.join()
    print(json.dumps({"put_times": put_times, "arrivals": arrivals}), flush=True)
    """
)


def _cpu_seconds(pid: int) -> float:
    import psutil

    t = psutil.Process(pid).cpu_times()
    return t.user + t.system


def _ms(samples: list[float]) -> list[float]:
    return [s * 1e3 for s in samples]


class _Ros:
    """A private context, node and executor for this benchmark's subscriptions and publishers."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("bench_bridge_probe", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, pred, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise RuntimeError(f"bench_bridge: timed out waiting for {what}")
            self.executor.spin_once(timeout_sec=0.01)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def _baseline(ros: _Ros, seconds: float) -> tuple[list[float], float]:
    """One-way latency of a plain rclpy publisher process -> this process, and that publisher's CPU share."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    latencies: list[float] = []
    started = threading.Event()

    def on_msg(msg: JointState) -> None:
        if started.is_set():
            latencies.append(time.monotonic() - msg.position[0])

    sub = ros.node.create_subscription(JointState, "bench/joint_states", on_msg, qos_profile_sensor_data)
    proc = subprocess.Popen(
        [sys.executable, "-c", BASELINE_PUBLISHER, str(RATE_HZ), str(seconds + 2.0)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if line.strip() != "ready":
            raise RuntimeError("bench_bridge: the baseline publisher did not start")
        ros.spin_for(0.5)  # let discovery settle
        started.set()
        cpu0, t0 = _cpu_seconds(proc.pid), time.monotonic()
        ros.spin_for(seconds)
        cpu = (_cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - t0)
    finally:
        proc.wait(timeout=seconds + 30)
        ros.node.destroy_subscription(sub)
    return latencies, cpu


def _bridge(ros: _Ros, seconds: float) -> dict[str, object]:
    """Run the bridge against a 100 Hz state stream plus random-phase commands; collect every latency."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    from mds_ach.robot import joints
    from mds_ach_bridge.limits import load_limits

    nkr = joints.MODEL_JOINTS.index("NKR")
    lo, hi = load_limits()["LEP"]
    values = [lo + (hi - lo) * (0.1 + 0.8 * i / 49) for i in range(50)]  # distinct, cycled
    received: list[tuple[int, float]] = []  # (state frame number, CLOCK_MONOTONIC at receipt)
    measuring = threading.Event()

    def on_state(msg: JointState) -> None:
        now = time.monotonic()
        if measuring.is_set():
            received.append((int(msg.position[nkr]), now))

    daemon = subprocess.Popen([sys.executable, "-c", FAKE_DAEMON, str(RATE_HZ)], text=True,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert daemon.stdout is not None and daemon.stdin is not None
    if daemon.stdout.readline().strip() != "ready":
        daemon.kill()
        raise RuntimeError("bench_bridge: the state writer did not start")
    sub = ros.node.create_subscription(JointState, "joint_states", on_state, qos_profile_sensor_data)
    cmd_pub = ros.node.create_publisher(JointState, "mds/joint_command", 10)
    bridge = subprocess.Popen([str(BIN / bin_name("bridge"))], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    commands: list[tuple[float, float]] = []  # (publish time, LEP value)
    try:
        ros.spin_until(lambda: cmd_pub.get_subscription_count() > 0 and sub.get_publisher_count() > 0, 30.0,
                       "the bridge's topics")  # fmt: skip
        ros.spin_for(1.0)
        measuring.set()
        cpu0, t0 = _cpu_seconds(bridge.pid), time.monotonic()
        end = t0 + seconds
        rng = random.Random(1)
        next_cmd = time.monotonic() + rng.uniform(0.0, 2.0 / COMMAND_HZ)
        i = 0
        while time.monotonic() < end:
            if time.monotonic() >= next_cmd:
                value = values[i % len(values)]
                i += 1
                commands.append((time.monotonic(), value))
                cmd_pub.publish(JointState(name=["LEP"], position=[value]))
                next_cmd += rng.uniform(0.5 / COMMAND_HZ, 1.5 / COMMAND_HZ)
            ros.executor.spin_once(timeout_sec=max(0.0, min(0.005, next_cmd - time.monotonic())))
        cpu = (_cpu_seconds(bridge.pid) - cpu0) / (time.monotonic() - t0)
        ros.spin_for(0.2)
    finally:
        bridge.terminate()
        bridge_rc = bridge.wait(timeout=15)
        out, _ = daemon.communicate("stop\n", timeout=30)
        ros.node.destroy_subscription(sub)
        ros.node.destroy_publisher(cmd_pub)
    if bridge_rc != 0:
        raise RuntimeError(f"bench_bridge: the bridge exited with {bridge_rc} on SIGTERM")
    report = json.loads(out.strip().splitlines()[-1])
    put_times: list[float] = report["put_times"]
    ref_arrivals = [(t, v) for t, v in report["arrivals"] if t >= t0]
    js_latency = [now - put_times[k] for k, now in received if 0 <= k < len(put_times)]

    # Match each reference frame to its command (the newest command with that value).
    cmd_latency = []
    for arrival, value in ref_arrivals:
        sent = [t for t, v in commands if v == value and t <= arrival]
        if sent:
            cmd_latency.append(arrival - sent[-1])
    return {"joint_states": js_latency, "command": cmd_latency, "cpu": cpu,
            "commands": len(commands), "references": len(ref_arrivals)}  # fmt: skip


def run(quick: bool = False) -> list[Row]:
    if os.environ.get("MDS_NETNS_ACTIVE") != "1" or os.environ.get("MDS_NETNS_SHARE_SHM") == "1":
        raise RuntimeError("bench_bridge needs a private namespace and /dev/shm: run it through tools/netns-run")
    seconds = 3.0 if quick else 10.0
    ros = _Ros()
    try:
        base, base_cpu = _baseline(ros, seconds)
        res = _bridge(ros, seconds)
    finally:
        ros.close()
    base_ms = _ms(base)
    js, cmd = _ms(res["joint_states"]), _ms(res["command"])  # type: ignore[arg-type]
    b50, b99 = median(base_ms), percentile(base_ms, 99)
    base_name = f"rclpy JointState pub->sub, {RATE_HZ:.0f} Hz"
    rows = [
        Row(GROUP, f"state frame -> /joint_states median (n={len(js)})", median(js), "ms", base_name + " p50", b50),
        Row(GROUP, "state frame -> /joint_states p99", percentile(js, 99), "ms", base_name + " p99", b99,
            target="p99 <= 2 ms", passed=percentile(js, 99) <= 2.0),
        Row(GROUP, f"ROS command -> reference (on arrival) median (n={len(cmd)})", median(cmd), "ms",
            base_name + " p50", b50),
        Row(GROUP, "ROS command -> reference (on arrival) p99", percentile(cmd, 99), "ms", base_name + " p99", b99,
            target="p99 <= 5 ms", passed=percentile(cmd, 99) <= 5.0),
        Row(GROUP, f"bridge CPU at {RATE_HZ:.0f} Hz + {COMMAND_HZ:.0f} Hz commands", 100.0 * res["cpu"], "% core",
            f"rclpy publisher process, {RATE_HZ:.0f} Hz", 100.0 * base_cpu, target="<= 10 %",
            passed=100.0 * res["cpu"] <= 10.0),
        # Informational: a command is one write (two arriving while one is written coalesce, newest wins).
        Row(GROUP, f"reference frames written for {res['commands']} commands", float(res["references"]), "frames"),
    ]  # fmt: skip
    return rows


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        print(row)
