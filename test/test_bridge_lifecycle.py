"""Issue 17 in the ROS bridge: /mds/hold and /mds/resume, refusals told to the sender, trajectories that stop for good.

The node tests run the simulated daemon and the bridge as child processes and the real mux (``MuxRunner``) in
this process, with a controller above the bridge ('teleop', priority 40, left arm) so the mux has a reason to
refuse the bridge's frames; they talk to the bridge over DDS (inside tools/netns-run) and watch the channels.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mds_ach_interfaces.msg import CommandStatus
from support.bridgeproc import BridgeProcs, module_harness

import mds_ach as mds
from mds_ach.nodes.mux import Controller, MuxCore, MuxRunner
from mds_ach.nodes.pipeline import make_ref, select_joints
from mds_ach.robot import lifecycle
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE
from mds_ach.robot.msgs.hold import HOLD_HOLD, MDS_HOLD
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_FREE, MUX_HELD
from mds_ach_bridge.muxwatch import MuxNews, MuxTracker

TELEOP_CHANNEL = "mds-ref-teleop"
CONTROLLERS = [
    Controller("teleop", TELEOP_CHANNEL, 40, select_joints("left_arm"), None),
    Controller("ros", mds.MDS_CHAN_REF_ROS_NAME, 30, select_joints(["left_arm", "right_arm", "torso"]), 1.0),
    Controller("default", mds.MDS_CHAN_REF_FILTER_NAME, 10, select_joints("all"), None, seed=True),
]
ZERO_MODE = np.zeros(MDS_JOINT_COUNT, dtype=np.int16)


# --------------------------------------------------------------------------------------------- the tracker


def _state(core: MuxCore, now: float, seq: int) -> MDS_MUX_STATE:
    return MDS_MUX_STATE.from_buffer_copy(bytes(core.state(now, seq)))


def test_tracker_reports_each_refusal_with_the_owner_and_the_frame_time() -> None:
    core = MuxCore(CONTROLLERS, np.zeros(MDS_JOINT_COUNT), ZERO_MODE)
    for i in range(3):
        core.absorb(i, np.zeros(MDS_JOINT_COUNT), ZERO_MODE)
    old = np.zeros(MDS_JOINT_COUNT)
    old[mds.RSP] = 0.1
    core.update(1, old, ZERO_MODE, now=1.0)
    previous = np.eye(MDS_JOINT_COUNT)[mds.NKY]
    core.update(1, previous, ZERO_MODE, now=1.5)  # refused: NKY is not permitted to 'ros' here
    tracker = MuxTracker("ros", _state(core, 2.0, 1))  # what happened before the bridge started is no news
    teleop = np.zeros(MDS_JOINT_COUNT)
    teleop[mds.LSP] = 0.2
    core.update(0, teleop, ZERO_MODE, now=3.0)
    frame = previous.copy()
    frame[[mds.LSP, mds.LEP]] = [0.3, -0.5]
    core.update(1, frame, ZERO_MODE, now=3.25)
    news = MuxNews()
    tracker.feed(_state(core, 3.5, 2), news)
    assert len(news.refusals) == 1 and not news.holds
    r = news.refusals[0]
    assert r.count == 1 and r.owner == "teleop" and r.frame_time == pytest.approx(3.25)
    assert "LSP owned by 'teleop' (priority 40)" in r.message
    news = MuxNews()
    tracker.feed(_state(core, 3.6, 3), news)  # the same state again: nothing new
    assert not news.refusals
    assert tracker.others_own([mds.LSP, mds.LEP, mds.RSP]) == {mds.LSP}


def test_tracker_reports_joints_that_become_held_not_those_already_held() -> None:
    core = MuxCore(CONTROLLERS, np.zeros(MDS_JOINT_COUNT), ZERO_MODE)
    hold = MDS_HOLD(seq=1, action=HOLD_HOLD, source=b"console")
    hold.joints[mds.NKY] = 1
    core.hold(hold)
    tracker = MuxTracker("ros", _state(core, 1.0, 1))
    hold = MDS_HOLD(seq=2, action=HOLD_HOLD, source=b"console")
    for a in (mds.NKY, mds.RSP):
        hold.joints[a] = 1
    core.hold(hold)
    news = MuxNews()
    tracker.feed(_state(core, 2.0, 2), news)
    assert [(h.addresses, h.source, h.action, h.time) for h in news.holds] == [
        (frozenset({mds.RSP}), "console", "hold", 2.0)]
    assert tracker.held() == (sorted([mds.RSP, mds.NKY]), [])


# --------------------------------------------------------------------------------------------- the node

RATE = 50.0  # over the default robot's CAN budget (22 Hz), hence --over-budget
BRIDGE_PARAMS = ["-p", "diagnostics_period:=0.2", "-p", "stale_timeout:=1.0"]


class System(BridgeProcs):
    """daemon --nocan and the bridge as child processes, the mux in this process, a probe node for DDS."""

    def __init__(self, tmp: Path) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Trigger
        from trajectory_msgs.msg import JointTrajectory

        from mds_ach.robot.channels import StructChannel

        self.start_daemon(tmp, "-r", str(RATE), "--over-budget")
        self.mux_log: list[str] = []
        self.mux = MuxRunner(CONTROLLERS, state_rate=10.0, log=lambda level, msg: self.mux_log.append(msg))
        self.mux_thread = threading.Thread(target=self.mux.run, daemon=True)
        self.mux_thread.start()
        assert self.mux.ready.wait(30), "the mux did not start (no mds-state from the daemon?)"
        self.teleop = StructChannel(TELEOP_CHANNEL, mds.MDS_REF)
        # teleop's newest frame (ref, mode): the mux compares its next one with it
        self.teleop_frame: tuple[np.ndarray, np.ndarray] | None = None
        self.start_bridge(*BRIDGE_PARAMS)
        self.open_node("bridge_lifecycle_probe")
        self.diags: list = []
        self.status: list[dict] = []
        n = self.node
        n.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        n.create_subscription(CommandStatus, "/mds/command_status", self._on_status, 10)
        self.command = n.create_publisher(JointState, "/mds/joint_command", 10)
        self.trajectory = n.create_publisher(JointTrajectory, "/mds/joint_trajectory", 10)
        self.hold = n.create_client(Trigger, "/mds/hold")
        self.resume = n.create_client(Trigger, "/mds/resume")
        for pub in (self.command, self.trajectory):
            self.spin_until(lambda p=pub: p.get_subscription_count() > 0, 30.0, f"a subscriber on {pub.topic_name}")
        self.spin_until(lambda: self.hold.service_is_ready() and self.resume.service_is_ready(), 30.0,
                        "/mds/hold and /mds/resume")
        self.spin_until(lambda: self.diags, 30.0, "the bridge's diagnostics")

    def _on_status(self, m: CommandStatus) -> None:
        """mds/command_status is typed (mds_ach_interfaces/msg/CommandStatus, issue #27 item 6), stamped."""
        assert m.header.stamp.sec > 0, m
        self.status.append({"event": m.event, "command": m.command, "message": m.message, "owner": m.owner,
                            "frames": m.frames, "code": m.code})

    def put_teleop(self, frame: np.ndarray, mode: np.ndarray | None = None) -> None:
        mode = self.core.mode.copy() if mode is None else mode
        self.teleop_frame = (frame.copy(), mode)
        self.teleop.put(make_ref(frame, mode))

    @property
    def core(self) -> MuxCore:
        assert self.mux.core is not None
        return self.mux.core


    def call(self, client, timeout: float = 20.0):
        from std_srvs.srv import Trigger

        future = client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout, f"the answer of {client.srv_name}")
        return future.result()

    def commands_diag(self):
        for arr in reversed(self.diags):
            for st in arr.status:
                if "commands" in st.name:
                    return st
        return None

    def close(self) -> int:
        self.close_node()
        rc = self.stop_bridge()
        self.mux.stop()
        self.mux_thread.join(5)
        self.teleop.close()
        self.stop_daemon()
        return rc


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:
    yield from module_harness(lambda: System(tmp_path_factory.mktemp("bridge_lifecycle")))


def _trajectory(names: list[str], start: list[float], end: list[float], seconds: float):
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    msg = JointTrajectory(joint_names=names)
    steps = 10
    for k in range(1, steps + 1):
        t = seconds * k / steps
        msg.points.append(JointTrajectoryPoint(
            positions=[a + (b - a) * k / steps for a, b in zip(start, end, strict=True)],
            time_from_start=Duration(sec=int(t), nanosec=int((t % 1) * 1e9))))
    return msg


@pytest.mark.ros
@pytest.mark.slow
def test_hold_and_resume_services_answer_once_the_mux_acknowledged(system: System) -> None:
    reply = system.call(system.hold)
    assert reply.success, reply.message
    assert reply.message.startswith("held by the mux: every joint"), reply.message
    assert all(system.core.held[a] == MUX_HELD for a in select_joints("model"))
    assert system.core.hold_source == "ros"
    reply = system.call(system.resume)
    assert reply.success and reply.message.startswith("resumed"), reply.message
    assert "not restarted" in reply.message
    assert (system.core.held == MUX_FREE).all()


@pytest.mark.ros
@pytest.mark.slow
def test_trajectory_stopped_by_a_hold_never_continues(system: System) -> None:
    """A HOLD from another client while the bridge streams: the bridge stops the trajectory (its frames would
    release the held joints one by one), cancels its joints, says so; RESUME does not restart it."""
    names = ["RSP", "REP"]
    start = [float(system.core.ref[mds.RSP]), float(system.core.ref[mds.REP])]
    end = [start[0] - 0.6, start[1] - 0.6]
    seconds = 4.0
    system.status.clear()
    system.trajectory.publish(_trajectory(names, start, end, seconds))
    sent = time.monotonic()
    system.spin_until(lambda: system.core.ref[mds.RSP] < start[0] - 0.1, 15.0, "RSP moving along the trajectory")
    ack = lifecycle.request(lifecycle.HOLD_HOLD, source="console", reason="operator hold")
    assert ack.ok, ack.message
    system.spin_until(lambda: any(e["event"] == "stopped" for e in system.status), 10.0, "the stop on command_status")
    stop = next(e for e in system.status if e["event"] == "stopped")
    assert "held by 'console'" in stop["message"] and "trajectory #" in stop["command"]
    system.spin_until(lambda: system.core.held[mds.RSP] == MUX_CANCELLED and system.core.held[mds.REP] == MUX_CANCELLED,
                      10.0, "RSP and REP cancelled by the bridge")
    stopped_at = system.core.ref[[mds.RSP, mds.REP]].copy()
    # Past the trajectory's end and after a RESUME: nothing of it moves again.
    reply = system.call(system.resume)
    assert reply.success and "RSP" in reply.message and "not restarted" in reply.message, reply.message
    system.spin_until(lambda: time.monotonic() > sent + seconds + 1.0, seconds + 5.0, "the trajectory's end")
    assert np.array_equal(system.core.ref[[mds.RSP, mds.REP]], stopped_at), "the stopped trajectory went on"
    assert system.core.held[mds.RSP] == MUX_CANCELLED and system.core.held[mds.REP] == MUX_CANCELLED
    assert system.core.ref[mds.RSP] > end[0] + 0.05 and system.core.ref[mds.REP] > end[1] + 0.05
    log = system.bridge_log()
    assert "stopped (REP, RSP held by 'console'); it will not continue" in log  # joints in address order
    assert "cancelled RSP, REP: they hold where they are" in log
    system.spin_until(lambda: (d := system.commands_diag()) is not None
                      and {kv.key: kv.value for kv in d.values}.get("trajectory") == "none"
                      and "held by 'console'" in {kv.key: kv.value for kv in d.values}["last trajectory stop"],
                      10.0, "the stop on /diagnostics")


@pytest.mark.ros
@pytest.mark.slow
def test_refused_frames_are_reported_once_with_the_owner(system: System) -> None:
    """'teleop' (priority 40) owns LSP: the bridge's joint command and trajectory for the left arm are refused
    whole; the bridge logs each once with the owner, reports it on /diagnostics and mds/command_status, and the
    refused trajectory stops (it is not applied later)."""
    from diagnostic_msgs.msg import DiagnosticStatus
    from sensor_msgs.msg import JointState

    frame = system.core.ref.copy()
    frame[mds.LSP] += 0.05
    system.put_teleop(frame)
    system.spin_until(lambda: system.core.owner[mds.LSP] == 0, 10.0, "teleop owning LSP")
    before = system.core.ref.copy()
    system.status.clear()
    system.command.publish(JointState(name=["LSP", "LEP"], position=[before[mds.LSP] - 0.1, before[mds.LEP] - 0.1]))
    system.spin_until(lambda: any(e["event"] == "refused" for e in system.status), 10.0, "the refusal")
    refusal = next(e for e in system.status if e["event"] == "refused")
    assert refusal["owner"] == "teleop" and "LSP owned by 'teleop' (priority 40)" in refusal["message"]
    assert refusal["frames"] >= 1 and refusal["code"] == "" and refusal["event"] == CommandStatus.REFUSED
    assert "mds/joint_command command #" in refusal["command"]
    system.spin_until(lambda: (d := system.commands_diag()) is not None and d.level == DiagnosticStatus.WARN
                      and "refused by the mux" in d.message and "teleop" in d.message, 10.0, "the WARN diagnostic")

    system.status.clear()
    lsp, lep = float(before[mds.LSP]), float(before[mds.LEP])
    system.trajectory.publish(_trajectory(["LSP", "LEP"], [lsp, lep], [lsp - 0.5, lep - 0.5], 2.0))
    system.spin_until(lambda: any(e["event"] == "stopped" for e in system.status), 10.0, "the trajectory stopped")
    system.spin_for(2.5)
    assert system.core.ref[mds.LSP] == before[mds.LSP] and system.core.ref[mds.LEP] == before[mds.LEP]
    assert system.core.held[mds.LEP] == MUX_FREE  # refused at its first frame: nothing to cancel
    refusals = [e for e in system.status if e["event"] == "refused"]
    assert len(refusals) == 1 and "trajectory #" in refusals[0]["command"], system.status
    log = system.bridge_log()
    assert log.count("owned by 'teleop' (priority 40); nothing of that frame applied") == 2, log
    assert "WARN" in log.splitlines()[[i for i, line in enumerate(log.splitlines()) if "owned by 'teleop'" in line][0]]

    system.status.clear()
    system.command.publish(JointState(name=["NKY"], position=[0.1]))  # not permitted to 'ros' here
    system.spin_until(lambda: any(e["event"] == "refused" for e in system.status), 10.0, "the NKY refusal")
    assert "NKY is not permitted" in system.status[-1]["message"]
    assert not math.isclose(system.core.ref[mds.NKY], 0.1)


@pytest.mark.ros
@pytest.mark.slow
def test_a_refusal_stamped_late_cancels_nothing_the_trajectory_never_moved(system: System) -> None:
    """A loaded host wakes the mux's reader late: it stamps the trajectory's first frame after the bridge wrote
    more of them, so the refusal maps to a later write. Every frame was refused (the bridge owns none of its
    joints in the mux's state): nothing was applied, so nothing is cancelled (CI failure of
    test_refused_frames_are_reported_once_with_the_owner at load 8-12). The reader here is the in-process mux's
    thread, kept from the GIL for 0.4 s as a scheduler would keep it from a CPU."""
    if system.core.owner[mds.LSP] != 0:
        frame = system.core.ref.copy()
        frame[mds.LSP] += 0.05
        system.put_teleop(frame)
        system.spin_until(lambda: system.core.owner[mds.LSP] == 0, 10.0, "teleop owning LSP")
    system.spin_until(lambda: system.core.owner[mds.LEP] == -1 and system.core.held[mds.LEP] == MUX_FREE, 10.0,
                      "LEP free, owned by nobody")
    before = system.core.ref.copy()
    refused = system.bridge_log().count("owned by 'teleop' (priority 40); nothing of that frame applied")
    system.status.clear()
    lsp, lep = float(before[mds.LSP]), float(before[mds.LEP])
    system.trajectory.publish(_trajectory(["LSP", "LEP"], [lsp, lep], [lsp - 0.5, lep - 0.5], 2.0))
    switch = sys.getswitchinterval()
    sys.setswitchinterval(5.0)  # this busy thread keeps the GIL: the mux's reader wakes but cannot stamp its frame
    try:
        end = time.monotonic() + 0.4
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(switch)
    system.spin_until(lambda: any(e["event"] == "stopped" for e in system.status), 10.0, "the trajectory stopped")
    system.spin_for(2.5)  # a CANCEL would be sent with the stop: give it time to reach the mux
    assert system.bridge_log().count("owned by 'teleop' (priority 40); nothing of that frame applied") == refused + 1
    assert system.core.ref[mds.LSP] == before[mds.LSP] and system.core.ref[mds.LEP] == before[mds.LEP]
    assert system.core.held[mds.LEP] == MUX_FREE, system.bridge_log()  # no frame of it was applied: nothing to cancel
    assert "cancelled" not in system.bridge_log().split("trajectory #")[-1]


@pytest.mark.ros
@pytest.mark.slow
def test_a_trajectory_refused_after_it_moved_cancels_the_joints_it_still_owns(system: System) -> None:
    """The other side of the rule above: frames of the trajectory were applied (the bridge owns its joints), then
    'teleop' takes LEP and the next frame is refused: the trajectory stops and the joint it still owns (LWY) is
    cancelled where it is; LEP, teleop's now, is left to teleop."""
    if system.teleop_frame is None:
        system.put_teleop(system.core.ref.copy())  # the frame teleop's next one is compared with (changes nothing)
    lep, lwy = float(system.core.ref[mds.LEP]), float(system.core.ref[mds.LWY])
    system.status.clear()
    system.trajectory.publish(_trajectory(["LEP", "LWY"], [lep, lwy], [lep - 0.4, lwy - 0.4], 3.0))
    system.spin_until(lambda: system.core.ref[mds.LWY] < lwy - 0.05 and system.core.owner[mds.LWY] == 1, 15.0,
                      "LWY moving along the trajectory, owned by 'ros'")
    frame, mode = system.teleop_frame  # teleop modifies LEP only: it takes LEP, not the joints the bridge moved
    frame = frame.copy()
    frame[mds.LEP] = system.core.ref[mds.LEP] + 0.01
    system.put_teleop(frame, mode)
    system.spin_until(lambda: any(e["event"] == "stopped" for e in system.status), 10.0, "the trajectory stopped")
    assert "refused by the mux" in next(e for e in system.status if e["event"] == "stopped")["message"]
    system.spin_until(lambda: system.core.held[mds.LWY] == MUX_CANCELLED, 10.0, "LWY cancelled by the bridge")
    assert system.core.owner[mds.LEP] == 0 and system.core.held[mds.LEP] == MUX_FREE


@pytest.mark.ros
@pytest.mark.slow
def test_hold_service_fails_when_the_mux_does_not_answer(system: System) -> None:
    system.mux.stop()
    system.mux_thread.join(5)
    reply = system.call(system.hold)
    assert not reply.success and "not acknowledged" in reply.message and "mux" in reply.message
