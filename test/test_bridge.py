"""The ROS 2 bridge: command validation, trajectory sampling, IK requests, and the running node.

The node tests start a simulated daemon and the ``bridge`` executable as separate processes and talk to
them from this process over DDS (inside tools/netns-run, like the whole suite) and over the Ach channels.
"""

from __future__ import annotations

import ctypes
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import VENV_BIN
from support.bridgeproc import BridgeProcs, module_harness

import mds_ach as mds
from mds_ach import ach, paths
from mds_ach.kinematics import model as kinematics
from mds_ach.nodes.pipeline import HANDOFF_RT_PRIORITY
from mds_ach.nodes.rosnode import DDS_RECEPTION_THREAD
from mds_ach.robot import config, joints, motion
from mds_ach.robot.feedforward import limiter_lead, stopping_point
from mds_ach.robot.msgs import MDS_IK, MDS_STATE
from mds_ach_bridge import trajectory
from mds_ach_bridge.commands import CommandError, positions_by_name, positions_from_array
from mds_ach_bridge.ik_request import make_request, quaternion_to_rpy
from mds_ach_bridge.limits import load_limits
from mds_ach_bridge.stamps import state_stamp_ns

LIMITS = {"LEP": (-2.4, 0.0), "LSP": (-1.9, 1.0), "WST": (-0.4, 0.4)}

# --------------------------------------------------------------------------------------------- commands


def test_positions_by_name_accepts_a_valid_command() -> None:
    assert positions_by_name(["LEP", "WST"], [-1.0, 0.25], LIMITS) == {"LEP": -1.0, "WST": 0.25}


@pytest.mark.parametrize(
    ("names", "positions", "reason"),
    [
        (["LEP", "XYZ"], [-1.0, 0.0], "'XYZ' is not an MDS joint name"),
        (["LEP", "RF1"], [-1.0, 0.0], "'RF1' is disabled in the joint table"),  # a real node the bridge does not drive
        (["LEP", "LSP"], [-1.0], "2 joint names but 1 positions"),
        (["LEP", "LEP"], [-1.0, -1.0], "appears twice"),
        (["LEP"], [math.nan], "not finite"),
        (["LEP"], [math.inf], "not finite"),
        (["LEP", "LSP"], [-1.0, 1.5], "LSP: position 1.5 rad is outside the limits"),
        ([], [], "no joint names"),
    ],
)
def test_positions_by_name_rejects(names: list[str], positions: list[float], reason: str) -> None:
    with pytest.raises(CommandError, match=reason):
        positions_by_name(names, positions, LIMITS)


def test_positions_from_array_uses_the_documented_order() -> None:
    limits = load_limits()
    values = [(lo + hi) / 2 for lo, hi in (limits[n] for n in joints.MODEL_JOINTS)]
    got = positions_from_array(values, limits)
    assert list(got) == list(joints.MODEL_JOINTS) and list(got.values()) == values
    with pytest.raises(CommandError, match=f"expected {len(joints.MODEL_JOINTS)} values"):
        positions_from_array(values[:-1], limits)


def test_limits_are_the_effective_limits() -> None:
    """Issue #17: the joint table intersected with the URDF (mds_ach.kinematics.limits), not the table alone."""
    from mds_ach.kinematics.limits import compute
    from mds_ach.kinematics.model import load_model
    from mds_ach.robot import config

    table = config.load()
    urdf = load_model()
    effective = compute(table)
    limits = load_limits()
    assert set(limits) == {n for n in joints.MODEL_JOINTS if table[n].enabled}
    for name, (lower, upper) in limits.items():
        assert (lower, upper) == effective.range(name)
        assert (lower, upper) == (max(table[name].lower, urdf.joints[name].lower),
                                  min(table[name].upper, urdf.joints[name].upper))
    for name, value in (("LSR", -0.15), ("RSR", 0.15), ("LEP", -2.45), ("REP", -2.45), ("LWR", -1.0),
                        ("RWR", 1.0)):  # the table allows these, the URDF does not
        assert table[name].within_limits(value)
        with pytest.raises(CommandError, match=f"{name}: position .* is outside the limits"):
            positions_by_name([name], [value], limits)


# --------------------------------------------------------------------------------------------- trajectories


def _lin(names, points, current=None, start=100.0):
    traj = trajectory.build(names, [(t, p, []) for t, p in points], start, LIMITS)
    return traj.anchor(current or {}, LIMITS)


def test_linear_trajectory_is_anchored_at_the_current_reference_and_interpolated() -> None:
    traj = _lin(["LEP", "WST"], [(1.0, [-1.0, 0.2]), (3.0, [-2.0, -0.2])], current={"LEP": 0.0, "WST": 0.0})
    assert traj.times == (0.0, 1.0, 3.0)
    assert traj.sample(99.0) == ({"LEP": 0.0, "WST": 0.0}, False)  # before the start: hold the start
    values, done = traj.sample(100.5)
    assert not done and values == pytest.approx({"LEP": -0.5, "WST": 0.1})
    values, done = traj.sample(102.0)
    assert not done and values == pytest.approx({"LEP": -1.5, "WST": 0.0})
    assert traj.sample(103.0) == ({"LEP": -2.0, "WST": -0.2}, True)
    assert traj.sample(200.0) == ({"LEP": -2.0, "WST": -0.2}, True)


def test_cubic_trajectory_meets_positions_and_velocities_at_the_points() -> None:
    pts = [(0.0, [-1.0], [0.0]), (1.0, [-1.5], [-0.6]), (2.0, [-2.0], [0.0])]
    traj = trajectory.build(["LEP"], pts, 0.0, LIMITS)
    assert traj.anchored
    for t, (p,), (v,) in pts:
        assert traj.sample(t)[0]["LEP"] == pytest.approx(p)
        if 0.0 < t < 2.0:
            h = 1e-6
            slope = (traj.sample(t + h)[0]["LEP"] - traj.sample(t - h)[0]["LEP"]) / (2 * h)
            assert slope == pytest.approx(v, abs=1e-4)


@pytest.mark.parametrize(
    ("points", "reason"),
    [
        ([], "no points"),
        ([(1.0, [-1.0], []), (1.0, [-1.5], [])], "is not after the previous point"),
        ([(1.0, [-1.0], []), (0.5, [-1.5], [])], "is not after the previous point"),
        ([(-1.0, [-1.0], [])], "must be finite and >= 0"),
        ([(1.0, [-1.0, 0.0], [])], "2 positions for 1 joints"),
        ([(1.0, [-1.0], []), (2.0, [0.5], [])], "point 1: LEP: position 0.5 rad is outside"),
        ([(1.0, [math.nan], [])], "point 0: LEP: position nan is not finite"),
        ([(1.0, [-1.0], [0.0]), (2.0, [-1.5], [])], "on every point or on none"),
        # Waypoints inside the limits, but the velocities make the cubic overshoot 0.0:
        ([(0.0, [-0.05], [5.0]), (1.0, [-0.05], [5.0])], "a cubic segment reaches"),
    ],
)
def test_trajectory_rejects(points: list, reason: str) -> None:
    with pytest.raises(CommandError, match=reason):
        trajectory.build(["LEP"], points, 0.0, LIMITS)


def test_anchoring_checks_the_segment_from_the_current_reference() -> None:
    traj = trajectory.build(["LEP"], [(1.0, [-0.02], [-3.0]), (2.0, [-0.1], [0.0])], 0.0, LIMITS)
    assert not traj.anchored
    with pytest.raises(ValueError, match="anchor"):
        traj.sample(0.5)
    with pytest.raises(CommandError, match="no current reference for LEP"):
        traj.anchor({}, LIMITS)
    # From -1.0 with v=0 up to -0.02, arriving while moving down at 3 rad/s: the cubic overshoots 0.0 first.
    with pytest.raises(CommandError, match="a cubic segment reaches"):
        traj.anchor({"LEP": -1.0}, LIMITS)
    ok = trajectory.build(["LEP"], [(1.0, [-0.5], [0.0])], 0.0, LIMITS).anchor({"LEP": -1.0}, LIMITS)
    assert ok.times == (0.0, 1.0) and ok.sample(0.5)[0]["LEP"] == pytest.approx(-0.75)


# --------------------------------------------------------------------------------------------- IK, stamps


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.3, -0.4, 1.2), (-2.0, 1.1, -3.0), (1.57, 0.0, -1.57)])
def test_quaternion_to_rpy_matches_the_kinematics_convention(rpy: tuple[float, float, float]) -> None:
    """Same Z-Y-X angles the IK node extracts from a rotation matrix (mds_ach.kinematics.model.euler_zyx)."""
    R = kinematics.rpy_matrix(*rpy)
    # quaternion from the matrix (w-major branch is fine away from 180 deg rotations)
    w = math.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x, y, z = (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)
    assert quaternion_to_rpy(x, y, z, w) == pytest.approx(tuple(kinematics.euler_zyx(R)), abs=1e-9)


def test_ik_request_fills_the_chosen_arm() -> None:
    half = math.sqrt(0.5)
    req = make_request("right", (0.3, -0.2, 0.1), (0.0, 0.0, half, half), 6)
    arm = req.arm[mds.RIGHT]
    assert req.move == mds.RIGHT and arm.ik_method == 6
    assert (arm.t_x, arm.t_y, arm.t_z) == (0.3, -0.2, 0.1)
    assert (arm.r_x, arm.r_y, arm.r_z) == pytest.approx((0.0, 0.0, math.pi / 2))
    assert bytes(req.arm[mds.LEFT]) == bytes(len(bytes(req.arm[mds.LEFT])))  # the other arm untouched


@pytest.mark.parametrize(
    ("arm", "pos", "quat", "dof", "reason"),
    [
        ("middle", (0, 0, 0), (0, 0, 0, 1), 3, "unknown arm"),
        ("left", (0, 0, 0), (0, 0, 0, 1), 0, "must be 1..6"),
        ("left", (0, 0, 0), (0, 0, 0, 1), 7, "must be 1..6"),
        ("left", (math.nan, 0, 0), (0, 0, 0, 1), 3, "NaN or Inf"),
        ("left", (0, 0, 0), (0, 0, 0, 0), 3, "norm 0"),
    ],
)
def test_ik_request_rejects(arm: str, pos: tuple, quat: tuple, dof: int, reason: str) -> None:
    with pytest.raises(CommandError, match=reason):
        make_request(arm, pos, quat, dof)


def test_state_stamp_subtracts_the_frame_age() -> None:
    assert state_stamp_ns(10_000_000_000, 50.0, 49.99, 1.0) == (9_990_000_000, True)
    assert state_stamp_ns(10_000_000_000, 50.0, 50.5, 1.0) == (10_000_000_000, False)  # from the future
    assert state_stamp_ns(10_000_000_000, 50.0, 7.0, 1.0) == (10_000_000_000, False)  # other machine's clock


def test_help_does_not_start_ros() -> None:
    out = subprocess.run([str(VENV_BIN / "mds-ach-bridge"), "--help"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    for text in ("joint_states", "mds/joint_trajectory", "ik_dof_left", " ".join(joints.MODEL_JOINTS)):
        assert text in out.stdout
    code = textwrap.dedent(
        """
        import sys
        from mds_ach_bridge import bridge
        try:
            bridge.main(['--help'])
        except SystemExit:
            pass
        assert 'rclpy' not in sys.modules, 'bridge --help imported rclpy'
        """
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr


@pytest.mark.ros
@pytest.mark.parametrize(("param", "reason"), [
    ("rt_priority:=200", "out of range"),
    ("command_mode:=7", "out of range"),
    ("ref_channel:=mds-ref-gated", "past the mux, filter and collision gate"),
])
def test_bad_parameters_are_refused_with_a_message(clean_shm: None, param: str, reason: str) -> None:
    """A bad parameter stops the bridge before it touches a channel: exit 2 and one line, no traceback."""
    res = subprocess.run([str(VENV_BIN / "mds-ach-bridge"), "--ros-args", "-p", param], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2, res.stderr
    assert reason in res.stderr and "Traceback" not in res.stderr, res.stderr
    assert not any(ach.exists(n) for n in (mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME,
                                           mds.MDS_CHAN_STATE_NAME))


# --------------------------------------------------------------------------------------------- the node

RATE = 50.0  # daemon loop rate for these tests: over the default robot's CAN budget (22 Hz), hence --over-budget
NODE_PARAMS = [
    "-p", "ref_channel:=mds-ref-gated", "-p", "allow_ungated:=true",  # no mux/filter/gate here: straight to the daemon
    "-p", "command_mode:=1",  # pass-through, so a command shows in pos within a second, not after the filter
    "-p", "stale_timeout:=0.5", "-p", "diagnostics_period:=0.2", "-p", "ik_dof_left:=5",
    "-p", "rt_priority:=7",  # the state thread runs SCHED_FIFO 7 where allowed
]  # fmt: skip


class Harness(BridgeProcs):
    """``daemon --nocan`` and the bridge as child processes, plus a probe node in this process."""

    def __init__(self, tmp: Path) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray, String
        from trajectory_msgs.msg import JointTrajectory

        self.start_daemon(tmp, "-r", str(RATE), "--over-budget")
        self.start_bridge(*NODE_PARAMS)
        self.open_node("bridge_test_probe")
        self.states: list = []
        self.refs: list = []
        self.diags: list = []
        self.descriptions: list = []
        n = self.node
        n.create_subscription(JointState, "/joint_states", self.states.append, qos_profile_sensor_data)
        n.create_subscription(JointState, "/mds/joint_references", self.refs.append, qos_profile_sensor_data)
        n.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        latched = QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        n.create_subscription(String, "/robot_description", self.descriptions.append, latched)
        self.command = n.create_publisher(JointState, "/mds/joint_command", 10)
        self.positions = n.create_publisher(Float64MultiArray, "/mds/joint_positions", 10)
        self.trajectory = n.create_publisher(JointTrajectory, "/mds/joint_trajectory", 10)
        from geometry_msgs.msg import PoseStamped

        self.ik_left = n.create_publisher(PoseStamped, "/mds/ik/left", 10)
        for pub in (self.command, self.positions, self.trajectory, self.ik_left):
            self.spin_until(lambda p=pub: p.get_subscription_count() > 0, 20.0, f"a subscriber on {pub.topic_name}")
        self.spin_until(lambda: len(self.states) > 0, 30.0, "first /joint_states")
        self.start = dict(zip(self.states[-1].name, self.states[-1].position, strict=True))


    def last_diag(self, name_part: str):
        for arr in reversed(self.diags):
            for st in arr.status:
                if name_part in st.name:
                    return st
        return None

    def diag_values(self, name_part: str) -> dict[str, str]:
        st = self.last_diag(name_part)
        return {} if st is None else {kv.key: kv.value for kv in st.values}



@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Harness]:
    yield from module_harness(lambda: Harness(tmp_path_factory.mktemp("bridge")))


def _state_channel():
    from mds_ach.robot.channels import StructChannel

    return StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE, create=False)


def _read_every_state_frame(frames: list[MDS_STATE], stop: threading.Event, ready: threading.Event) -> None:
    """Read mds-state in order (not newest-only), so every frame the daemon publishes is seen once."""
    from mds_ach import ach

    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as chan:
        chan.flush()
        ready.set()
        buf = MDS_STATE()
        while not stop.is_set():
            status, size = chan.get(buf, wait=True, timeout=0.1)
            if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(MDS_STATE):
                frames.append(MDS_STATE.from_buffer_copy(buf))


@pytest.mark.ros
@pytest.mark.slow
def test_joint_states_carry_every_state_frame_once(harness: Harness) -> None:
    """Each daemon frame becomes exactly one JointState with its values; the stamp is the frame's time."""
    frames: list[MDS_STATE] = []
    stop, ready = threading.Event(), threading.Event()
    reader = threading.Thread(target=_read_every_state_frame, args=(frames, stop, ready))
    reader.start()
    try:
        assert ready.wait(10.0)
        harness.states.clear()
        harness.spin_for(2.0)
    finally:
        stop.set()
        reader.join()
    msgs = list(harness.states)
    assert len(frames) > 10 and msgs, f"{len(frames)} state frames, {len(msgs)} /joint_states messages"
    # stamp = ROS time - age, i.e. state.time shifted by (CLOCK_REALTIME - CLOCK_MONOTONIC): undo the shift.
    offset = sorted(time.time() - time.monotonic() for _ in range(5))[2]
    times = [f.time for f in frames]
    spacing = sorted(b - a for a, b in zip(times, times[1:], strict=False))[len(times) // 2]
    matched: list[int] = []
    for m in msgs:
        assert list(m.name) == list(joints.MODEL_JOINTS)
        t = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 - offset
        k = min(range(len(times)), key=lambda i: abs(times[i] - t))
        if abs(times[k] - t) > spacing / 2:
            continue  # a frame from before the reader started or after it stopped
        expected = [frames[k].joint[joints.BY_SHORT[n].address].pos for n in joints.MODEL_JOINTS]
        assert list(m.position) == expected, f"message for frame {k} carries other values"
        matched.append(k)
    assert matched == sorted(set(matched)), "a state frame was published twice or out of order"
    span = matched[-1] - matched[0] + 1
    assert len(matched) >= 0.9 * span, f"{len(matched)} messages for {span} state frames: frames were dropped"
    assert harness.refs and list(harness.refs[-1].name) == list(joints.MODEL_JOINTS)


@pytest.mark.ros
@pytest.mark.slow
def test_state_thread_gets_the_requested_realtime_priority(harness: Harness) -> None:
    """rt_priority:=7 puts exactly one thread (the state thread) under SCHED_FIFO 7, or says why not; the hand-off
    threads of a ROS command (the executor, the main thread, and the DDS reception threads) run at
    ``HANDOFF_RT_PRIORITY`` whatever rt_priority says (``bridge.main``), and nothing else is real-time."""
    tasks = [int(t) for t in os.listdir(f"/proc/{harness.bridge.pid}/task")]
    fifo = []
    handoff = []
    for tid in tasks:
        try:
            if os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO:  # tune_thread sets both
                priority = os.sched_getparam(tid).sched_priority
                if priority == HANDOFF_RT_PRIORITY:
                    handoff.append(Path(f"/proc/{harness.bridge.pid}/task/{tid}/comm").read_text().strip())
                else:
                    fifo.append(priority)
        except (ProcessLookupError, FileNotFoundError):
            pass
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        allowed = True
    except PermissionError:
        allowed = False
    if allowed:
        assert fifo == [7], f"SCHED_FIFO priorities of the bridge's threads: {fifo}"
        main = Path(f"/proc/{harness.bridge.pid}/comm").read_text().strip()
        dds = [t for t in handoff if t != main]
        assert main in handoff and dds and all(DDS_RECEPTION_THREAD.fullmatch(t) for t in dds), handoff
    else:
        assert fifo == [] and handoff == [] and "SCHED_FIFO 7 refused" in harness.bridge_log()


def assert_description_limits(text: str, limits) -> None:
    """Every actuated joint of the URDF text carries exactly the effective limits."""
    import xml.etree.ElementTree as ET

    seen = set()
    for joint in ET.fromstring(text).findall("joint"):
        limit = joint.find("limit")
        if joint.get("type") == "fixed" or limit is None:
            continue
        name = joint.get("name")
        assert (float(limit.get("lower")), float(limit.get("upper"))) == limits.range(name), name
        seen.add(name)
    assert seen == set(joints.MODEL_JOINTS)


def test_urdf_with_limits_carries_the_effective_limits() -> None:
    from mds_ach.kinematics.limits import compute, urdf_with_limits

    limits = compute()
    raw = paths.urdf_path().read_text()
    text = urdf_with_limits(raw, limits)
    assert_description_limits(text, limits)
    assert 'name="LSR"' in text and text.count("<limit") == raw.count("<limit")  # nothing else rewritten
    assert limits.range("LSR")[0] == 0.0 and limits.range("LWR") == (-0.4712, 0.4712)


@pytest.mark.ros
@pytest.mark.slow
def test_robot_description_is_latched(harness: Harness) -> None:
    harness.spin_until(lambda: harness.descriptions, 10.0, "/robot_description")
    from mds_ach.kinematics.limits import current_limits, urdf_with_limits

    published = current_limits()
    assert published.published  # the harness runs a daemon: mds-limits is there
    text = harness.descriptions[-1].data
    assert text == urdf_with_limits(paths.urdf_path().read_text(), published)
    assert_description_limits(text, published)


@pytest.mark.ros
@pytest.mark.slow
def test_joint_command_moves_the_joint_and_rejects_bad_messages(harness: Harness) -> None:
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    limits = load_limits()
    lep_lo, lep_hi = limits["LEP"]
    lsp_lo, lsp_hi = limits["LSP"]
    target_lep, target_lsp = lep_lo + 0.3 * (lep_hi - lep_lo), lsp_lo + 0.6 * (lsp_hi - lsp_lo)
    i_lep, i_lsp = joints.MODEL_JOINTS.index("LEP"), joints.MODEL_JOINTS.index("LSP")
    bad = [
        (JointState(name=["LEP", "LSP"], position=[target_lep, lsp_hi + 0.1]), "outside the limits"),
        (JointState(name=["LEP", "NOPE"], position=[target_lep, 0.0]), "'NOPE' is not an MDS joint name"),
        (JointState(name=["LEP", "LSP"], position=[target_lep]), "2 joint names but 1 positions"),
        (JointState(name=["LEP"], position=[math.nan]), "LEP: position nan is not finite"),
    ]
    rejected_before = harness.bridge_log().count("rejected message")
    for msg, _ in bad:
        harness.command.publish(msg)
    harness.positions.publish(Float64MultiArray(data=[0.0] * 3))
    harness.spin_until(
        lambda: harness.bridge_log().count("rejected message") >= rejected_before + len(bad) + 1, 10.0, "rejections"
    )
    log = harness.bridge_log()
    for _, reason in bad:
        assert reason in log
    assert "expected 17 values" in log
    # nothing partial: LEP (valid in the first message) must not have moved
    harness.states.clear()
    harness.spin_for(0.3)
    assert harness.states[-1].position[i_lep] == pytest.approx(harness.start["LEP"], abs=1e-6)

    harness.command.publish(JointState(name=["LEP", "LSP"], position=[target_lep, target_lsp]))
    with _state_channel() as chan:  # the daemon took exactly the commanded references ...
        harness.spin_until(lambda: (st := chan.latest()) is not None and st.joint[mds.LEP].ref_r == target_lep,
                           10.0, "LEP reference at the daemon")  # fmt: skip
        st = chan.wait(timeout=5.0)
        assert st is not None and st.joint[mds.LSP].ref_r == target_lsp
    # ... and the simulated joints get there
    harness.spin_until(
        lambda: abs(harness.states[-1].position[i_lep] - target_lep) < 1e-3
        and abs(harness.states[-1].position[i_lsp] - target_lsp) < 1e-3,
        15.0,
        "LEP and LSP at their targets",
    )
    last = dict(zip(harness.states[-1].name, harness.states[-1].position, strict=True))
    for n in joints.MODEL_JOINTS:
        if n not in ("LEP", "LSP"):
            assert last[n] == pytest.approx(harness.start[n], abs=1e-3), n

    def counted() -> bool:
        values = harness.diag_values("state stream")
        return int(values.get("commands rejected", 0)) >= len(bad) + 1 and int(values["commands accepted"]) >= 1

    harness.spin_until(counted, 10.0, "the commands counted on /diagnostics")


@pytest.mark.ros
@pytest.mark.slow
def test_trajectory_from_another_process_moves_the_simulated_joint(harness: Harness) -> None:
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    limits = load_limits()
    lo, hi = limits["WST"]
    a, b = lo + 0.25 * (hi - lo), lo + 0.75 * (hi - lo)
    addr = joints.BY_SHORT["WST"].address
    with _state_channel() as chan:
        now = chan.wait(timeout=5.0)
        assert now is not None
        start_value = now.joint[addr].ref_r
        msg = JointTrajectory(joint_names=["WST"])
        msg.points = [
            JointTrajectoryPoint(positions=[a], time_from_start=Duration(sec=0, nanosec=500_000_000)),
            JointTrajectoryPoint(positions=[b], time_from_start=Duration(sec=1, nanosec=500_000_000)),
        ]
        sent = time.monotonic()
        harness.trajectory.publish(msg)
        samples: list[tuple[float, float, float]] = []  # (state time, WST ref_r, WST pos) from the daemon
        while time.monotonic() - sent < 12.0:
            harness.executor.spin_once(timeout_sec=0.0)
            st = chan.wait(timeout=0.5)
            if st is not None:
                samples.append((st.time - sent, st.joint[addr].ref_r, st.joint[addr].pos))
                if st.time - sent > 1.5 and abs(st.joint[addr].pos - b) < 1e-3:
                    break
    refs = [r for _, r, _ in samples]
    assert refs[-1] == b, "the trajectory did not end at its last point"
    assert abs(samples[-1][2] - b) < 1e-3, f"the simulated WST stopped at {samples[-1][2]}, not at {b}"
    # The daemon received intermediate references on both segments, not a jump:
    seg1 = [r for r in refs if min(start_value, a) + 1e-6 < r < max(start_value, a) - 1e-6]
    seg2 = [r for r in refs if a + 1e-6 < r < b - 1e-6]
    assert len(seg1) >= 3 and len(seg2) >= 5, (seg1, seg2)
    # Every reference is a target of the commanded path: the stopping point at the MOVETO acceleration of traj(t + d)
    # (issue #26: the bridge samples the trajectory for the daemon's next send, a cycle ahead, as the feed-forward
    # target the MCB passes the path with) for d from -0.5 s (DDS delivery, one state cycle until the daemon reads it,
    # a loaded CI machine) to +0.25 s (the look-ahead, two cycles). A jump or a wrong shape falls outside.
    traj = trajectory.build(["WST"], [(0.5, [a], []), (1.5, [b], [])], 0.0, limits).anchor({"WST": start_value}, limits)
    accel = math.radians(config.load().accel_deg_s2)

    bounds = config.load().motion_bounds()
    period = 1.0 / RATE  # the daemon's

    def target(x: float) -> float:
        q, v, _ = traj.sample_state(x)
        return min(max(stopping_point(q["WST"], v["WST"], accel), lo), hi)

    def reference(x: float) -> float:
        """The target ahead by what the daemon's limiter trails it (``feedforward.limiter_lead``) over a period."""
        speed = motion.LIMIT_MARGIN * bounds.max_velocity
        step = min(max((target(x) - target(x - period)) / period, -speed), speed)
        lead = limiter_lead(step, motion.LIMIT_MARGIN * bounds.max_acceleration)
        return min(max(target(x) + lead, lo), hi)

    for t, r, _ in samples:
        # Linear segments: the path's extremes sit at the waypoints (each side), so sample those too.
        lags = [t + 0.25 - i * 0.01 for i in range(76)]
        lags += [w + e + d for w in (0.5, 1.5) for e in (-1e-6, 1e-6) for d in (0.0, period)
                 if t - 0.5 <= w + d <= t + 0.25]
        path = [f(x) for x in lags for f in (target, reference)]
        assert min(path) - 1e-9 <= r <= max(path) + 1e-9, f"WST reference {r} at t={t:.3f} s is off the trajectory"


@pytest.mark.ros
@pytest.mark.slow
def test_ik_target_is_forwarded_and_bad_frames_rejected(harness: Harness) -> None:
    from geometry_msgs.msg import PoseStamped

    from mds_ach.robot.channels import StructChannel

    with StructChannel(mds.MDS_CHAN_IK_NAME, MDS_IK) as chan:
        chan.flush()
        wrong = PoseStamped()
        wrong.header.frame_id = "map"
        wrong.pose.orientation.w = 1.0
        harness.ik_left.publish(wrong)
        good = PoseStamped()
        good.header.frame_id = "torso"
        good.pose.position.x, good.pose.position.y, good.pose.position.z = 0.3, 0.2, -0.1
        good.pose.orientation.w = 1.0
        harness.ik_left.publish(good)
        got = None
        deadline = time.monotonic() + 10.0
        while got is None and time.monotonic() < deadline:
            harness.executor.spin_once(timeout_sec=0.02)
            got = chan.latest()
    assert got is not None, harness.bridge_log()
    arm = got.arm[mds.LEFT]
    assert got.move == mds.LEFT and arm.ik_method == 5  # ik_dof_left:=5 in the harness
    assert (arm.t_x, arm.t_y, arm.t_z, arm.r_x, arm.r_y, arm.r_z) == (0.3, 0.2, -0.1, 0.0, 0.0, 0.0)
    harness.spin_until(lambda: "frame_id 'map' is not the robot frame" in harness.bridge_log(), 5.0, "IK rejection")


@pytest.mark.ros
@pytest.mark.slow
def test_stalled_daemon_gives_silence_and_an_error_diagnostic(harness: Harness) -> None:
    from diagnostic_msgs.msg import DiagnosticStatus

    OK, ERROR = DiagnosticStatus.OK, DiagnosticStatus.ERROR
    os.kill(harness.daemon.pid, signal.SIGSTOP)
    try:
        harness.spin_until(
            lambda: (d := harness.last_diag("state stream")) is not None and d.level == ERROR, 10.0, "stall ERROR"
        )
        assert "stalled" in harness.last_diag("state stream").message
        harness.states.clear()
        harness.spin_for(0.5)
        assert harness.states == [], "old data republished while the daemon is stalled"
    finally:
        os.kill(harness.daemon.pid, signal.SIGCONT)
    harness.spin_until(lambda: harness.states, 10.0, "/joint_states after the daemon resumed")
    harness.spin_until(
        lambda: (d := harness.last_diag("state stream")) is not None and d.level == OK, 10.0, "stream OK again"
    )


@pytest.mark.ros
@pytest.mark.slow
def test_first_frame_keeps_the_channel_content_for_joints_not_commanded(harness: Harness) -> None:
    """A second bridge, namespaced and remapped, on the legacy mds-ref-filter that already holds a frame: only
    the commanded joint may differ from that frame (the mux would take any other difference as a command)."""
    from sensor_msgs.msg import JointState

    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs import MDS_REF

    limits = load_limits()
    lo, hi = limits["LSP"]
    target = lo + 0.4 * (hi - lo)
    previous = MDS_REF()
    for a in range(mds.MDS_JOINT_COUNT):
        previous.joint[a].ref = 0.001 * a
        previous.joint[a].mode = mds.MDS_REF_MODE_COMPLIANT
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, MDS_REF) as chan:
        chan.put(previous)
        chan.flush()
        second = subprocess.Popen(
            [str(VENV_BIN / "mds-ach-bridge"), "--ros-args", "-r", "__ns:=/b2", "-r", "__node:=bridge2",
             "-p", "ref_channel:=mds-ref-filter", "-p", "publish_robot_description:=false"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            pub = harness.node.create_publisher(JointState, "/b2/mds/joint_command", 10)
            harness.spin_until(lambda: pub.get_subscription_count() > 0, 20.0, "the second bridge")
            got = None
            deadline = time.monotonic() + 10.0
            while got is None and time.monotonic() < deadline:
                pub.publish(JointState(name=["LSP"], position=[target]))  # until its state stream is live
                harness.spin_for(0.1)
                got = chan.latest()
        finally:
            second.send_signal(signal.SIGINT)
            assert second.wait(timeout=15) == 0
            harness.node.destroy_publisher(pub)
    assert got is not None, "the second bridge wrote nothing to mds-ref-filter"
    lsp = joints.BY_SHORT["LSP"].address
    assert got.joint[lsp].ref == target and got.joint[lsp].mode == mds.MDS_REF_MODE_REF_FILTER
    for a in range(mds.MDS_JOINT_COUNT):
        if a != lsp:
            assert (got.joint[a].ref, got.joint[a].mode) == (0.001 * a, mds.MDS_REF_MODE_COMPLIANT), a
