"""The bridge node: ``mds-state`` -> JointState, ROS commands -> the bridge's reference channel.

Threads: a dedicated state thread blocks on the state channel (newest frame wins) and, for every new
frame, writes the bridge's reference if there is something new (the newest accepted command, or the
running trajectory sampled at this cycle) and publishes ``joint_states`` and ``mds/joint_references``.
The executor thread only runs subscription callbacks, which validate a command completely and hand it
over under a lock, and the diagnostics timer. A frame is never published twice; when the daemon stalls
the topics fall silent and /diagnostics reports it.
"""

from __future__ import annotations

import array
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory

import mds_ach as mds
from mds_ach import ach, paths
from mds_ach.ach.glibc import tune_thread
from mds_ach.kinematics.limits import current_limits, urdf_with_limits
from mds_ach.nodes.rosnode import Param, declare
from mds_ach.robot import joints
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_IK, MDS_REF, MDS_STATE
from mds_ach_bridge import topics, trajectory
from mds_ach_bridge.commands import CommandError, positions_by_name, positions_from_array
from mds_ach_bridge.ik_request import make_request
from mds_ach_bridge.limits import load_limits
from mds_ach_bridge.stamps import state_stamp_ns

NODE_NAME = "mds_bridge"
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
STATE_QOS = {
    "sensor_data": qos_profile_sensor_data,  # best effort, keep last 5
    "reliable": QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE),
}


@dataclass
class _Counters:
    frames: int = 0
    frames_at_last_diag: int = 0
    clock_fallbacks: int = 0
    accepted: int = 0
    rejected: int = 0
    rejected_at_last_diag: int = 0
    last_rejection: str = ""
    references_written: int = 0
    ik_forwarded: int = 0
    extra: dict[str, str] = field(default_factory=dict)


SECONDS = (0.001, 3600.0)
PARAMETERS = (
    Param("state_channel", mds.MDS_CHAN_STATE_NAME, "Ach channel of mds_state_t frames"),
    Param("ref_channel", mds.MDS_CHAN_REF_ROS_NAME,
          "Ach channel the bridge writes its mds_ref_t to: its mux input (default), or mds-ref-filter when no mux "
          "runs"),
    Param("ik_channel", mds.MDS_CHAN_IK_NAME, "Ach channel for mds_ik_t requests"),
    Param("allow_ungated", False,
          f"allow ref_channel = {mds.MDS_CHAN_DAEMON_INPUT_NAME} (the daemon's input), which bypasses mux, filter and "
          "collision gate (simulation tests only)"),
    Param("state_qos", "sensor_data", "QoS of joint_states and mds/joint_references: sensor_data (best effort) or "
                                      "reliable (for subscribers that insist on RELIABLE)"),
    Param("stale_timeout", 0.5, "seconds without a new state frame before /diagnostics reports the daemon as stalled",
          range=SECONDS, read_only=False),
    Param("max_state_age", 1.0, "largest plausible age (s) of a state frame at receipt; older or future frames are "
                                "stamped with the receipt time (the daemon's monotonic clock is not comparable, e.g. "
                                "over the network)", range=SECONDS, read_only=False),
    Param("command_mode", int(mds.MDS_REF_MODE_REF_FILTER),
          "mds ref mode for position commands (0 filter, 1 pass-through, 2 compliant, 3 encoder filter)",
          range=(0, 3), read_only=False),
    Param("trajectory_mode", int(mds.MDS_REF_MODE_REF),
          "mds ref mode for trajectory samples (default pass-through: the trajectory is already smooth)",
          range=(0, 3), read_only=False),
    Param("ik_dof_left", 3, "task DOF for mds/ik/left: a prefix of p-x p-y p-z t-x t-y t-z (3 = position, 6 = full "
                            "pose)", range=(1, 6), read_only=False),
    Param("ik_dof_right", 3, "task DOF for mds/ik/right, as ik_dof_left", range=(1, 6), read_only=False),
    Param("ik_frame", "torso", "frame_id accepted for IK targets besides '' (the robot frame between the shoulders)",
          read_only=False),
    Param("urdf", "", "URDF file for robot_description; empty: the package's urdf/mds.urdf"),
    Param("robot", "", "robot variant of the joint table for the limits; empty: $MDS_ACH_ROBOT, else default"),
    Param("publish_robot_description", True, "publish the URDF on robot_description (transient local)"),
    Param("rt_priority", 0, "SCHED_FIFO priority (1-99) of the state thread, which wakes on every state frame and "
                            "publishes it; 0 = normal scheduling. Needs CAP_SYS_NICE or an rtprio limit; refused: "
                            "logged, normal priority", range=(0, 99)),
    Param("diagnostics_period", 1.0, "seconds between /diagnostics messages", range=SECONDS),
)


class BridgeNode(Node):
    """See the module docstring; parameters are declared with descriptions (``ros2 param describe``)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        p = self.get_parameter
        self._state_name: str = p("state_channel").value
        self._ref_name: str = p("ref_channel").value
        self._ik_name: str = p("ik_channel").value
        if self._ref_name == mds.MDS_CHAN_DAEMON_INPUT_NAME and not p("allow_ungated").value:
            raise ValueError(
                f"ref_channel '{self._ref_name}' goes straight to the daemon, past the mux, filter and collision gate; "
                "set allow_ungated:=true only for tests on the simulated robot"
            )
        qos_name: str = p("state_qos").value
        if qos_name not in STATE_QOS:
            raise ValueError(f"state_qos must be one of {', '.join(STATE_QOS)}, not {qos_name!r}")
        self._rt_priority: int = p("rt_priority").value
        self._stale_timeout: float = p("stale_timeout").value
        self._max_age: float = p("max_state_age").value
        self._command_mode: int = p("command_mode").value
        self._trajectory_mode: int = p("trajectory_mode").value
        self._ik_dof = {"left": p("ik_dof_left").value, "right": p("ik_dof_right").value}
        self._ik_frames = {"", p("ik_frame").value}
        urdf = p("urdf").value or str(paths.urdf_path())
        self._effective = current_limits(p("robot").value or None)
        self._limits = load_limits(joints.MODEL_JOINTS, effective=self._effective)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._names = list(joints.MODEL_JOINTS)
        self._addresses = [joints.BY_SHORT[n].address for n in self._names]
        self._lock = threading.Lock()
        self._counters = _Counters()
        self._pending: dict[str, float] = {}  # accepted position commands not yet written
        self._trajectory: trajectory.Trajectory | None = None
        self._frame: MDS_REF | None = None  # the bridge's reference, created on the first write
        self._late_rejections: list[tuple[str, str]] = []  # found on the state thread under the lock, logged after it
        self._started = time.monotonic()
        self._last_frame_mono: float | None = None
        self._stalled = False

        self._state_chan = StructChannel(self._state_name, MDS_STATE)
        self._ref_chan = StructChannel(self._ref_name, MDS_REF)
        self._ik_chan = StructChannel(self._ik_name, MDS_IK)

        state_qos = STATE_QOS[qos_name]
        self._js_pub = self.create_publisher(JointState, topics.JOINT_STATES, state_qos)
        self._ref_pub = self.create_publisher(JointState, topics.JOINT_REFERENCES, state_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._js_msg = JointState(name=self._names)
        self._ref_msg = JointState(name=self._names)
        if p("publish_robot_description").value:
            self._desc_pub = self.create_publisher(String, topics.ROBOT_DESCRIPTION, LATCHED_QOS)
            # The URDF with the effective limits, so MoveIt, RViz sliders and planners use what the robot accepts.
            self._desc_pub.publish(String(data=urdf_with_limits(Path(urdf).read_text(), self._effective)))
        self.create_subscription(JointState, topics.JOINT_COMMAND, self._on_joint_command, COMMAND_QOS)
        self.create_subscription(JointTrajectory, topics.JOINT_TRAJECTORY, self._on_trajectory, COMMAND_QOS)
        self.create_subscription(Float64MultiArray, topics.JOINT_POSITIONS, self._on_positions, COMMAND_QOS)
        self.create_subscription(PoseStamped, topics.IK_LEFT, lambda m: self._on_ik("left", m), COMMAND_QOS)
        self.create_subscription(PoseStamped, topics.IK_RIGHT, lambda m: self._on_ik("right", m), COMMAND_QOS)
        self.create_timer(p("diagnostics_period").value, self._publish_diagnostics)

        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._state_loop, name="mds-bridge-state", daemon=True)
        self._thread.start()
        self.get_logger().info(
            f"bridging {self._state_name} -> {self.resolve_topic_name(topics.JOINT_STATES)}, "
            f"commands -> {self._ref_name}, IK -> {self._ik_name}"
        )

    # ------------------------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> None:
        for param in PARAMETERS:
            declare(self, param)

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """Runtime-changeable settings: apply them under the lock so the state thread sees them whole."""
        with self._lock:
            for prm in params:
                if prm.name == "ik_dof_left":
                    self._ik_dof["left"] = prm.value
                elif prm.name == "ik_dof_right":
                    self._ik_dof["right"] = prm.value
                elif prm.name == "ik_frame":
                    self._ik_frames = {"", prm.value}
                elif prm.name == "command_mode":
                    self._command_mode = prm.value
                elif prm.name == "trajectory_mode":
                    self._trajectory_mode = prm.value
                elif prm.name == "stale_timeout":
                    self._stale_timeout = prm.value
                elif prm.name == "max_state_age":
                    self._max_age = prm.value
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------------------------ state -> ROS

    def _state_loop(self) -> None:
        """Block on the state channel; for each new frame write the reference, then publish the frame once."""
        for problem in tune_thread(self._rt_priority):
            self.get_logger().warning(f"state thread: {problem}")
        try:
            while not self._stop.is_set():
                # The wait returns on every put; its timeout only paces the stall check.
                state = self._state_chan.wait(timeout=max(0.01, min(0.25, self._stale_timeout / 4)))
                if state is None:
                    self._check_stall()
                    continue
                self._on_state(state)
        except Exception as exc:  # a dead state thread must be loud, not a silently frozen bridge
            self.get_logger().fatal(f"state thread stopped: {exc!r}")
            self._counters.extra["state thread"] = f"stopped: {exc!r}"
            raise

    def _on_state(self, state: MDS_STATE) -> None:
        mono = time.clock_gettime(time.CLOCK_MONOTONIC)
        now_ns = self.get_clock().now().nanoseconds
        js = [state.joint[a] for a in self._addresses]
        # The reference first: it is one put, and a pending command should not wait for two publishes.
        with self._lock:
            was_stalled = self._stalled
            self._stalled = False
            self._last_frame_mono = mono
            self._counters.frames += 1
            ref = self._next_reference(state, now_ns * 1e-9)
            late, self._late_rejections = self._late_rejections, []
        if ref is not None:
            self._ref_chan.put(ref)
            with self._lock:
                self._counters.references_written += 1
        for topic, reason in late:
            self._reject(topic, reason)

        stamp_ns, comparable = state_stamp_ns(now_ns, mono, state.time, self._max_age)
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        self._js_msg.header.stamp = stamp
        self._js_msg.position = array.array("d", [j.pos for j in js])
        self._js_pub.publish(self._js_msg)
        if self._ref_pub.get_subscription_count() > 0:  # nobody listening: skip the serialisation
            self._ref_msg.header.stamp = stamp
            self._ref_msg.position = array.array("d", [j.ref for j in js])
            self._ref_pub.publish(self._ref_msg)
        if not comparable:
            with self._lock:
                self._counters.clock_fallbacks += 1
        if was_stalled:
            self.get_logger().info(f"{self._state_name} is live again")
            self._publish_diagnostics()

    def _check_stall(self) -> None:
        now = time.monotonic()
        with self._lock:
            since = self._last_frame_mono if self._last_frame_mono is not None else self._started
            if self._stalled or now - since <= self._stale_timeout:
                return
            self._stalled = True
            # A trajectory must not jump ahead when the state comes back: drop it and hold.
            dropped = self._trajectory is not None
            self._trajectory = None
        what = "no state frame yet" if self._last_frame_mono is None else f"no new state frame for {now - since:.2f} s"
        self.get_logger().warning(
            f"{self._state_name}: {what}; is the daemon running?" + (" Trajectory aborted." if dropped else "")
        )
        self._publish_diagnostics()

    # ------------------------------------------------------------------------------------ ROS -> reference

    def _next_reference(self, state: MDS_STATE, now_s: float) -> MDS_REF | None:
        """The frame to write this cycle, or None when nothing changed (caller holds the lock)."""
        if self._trajectory is None and not self._pending:
            return None  # nothing new: the mux holds the last frame (an unchanged frame would not count anyway)
        if self._frame is None:
            self._frame = self._base_frame(state)
        if self._trajectory is not None and not self._trajectory.anchored:
            current = {n: self._frame.joint[joints.BY_SHORT[n].address].ref for n in self._trajectory.names}
            try:
                self._trajectory = self._trajectory.anchor(current, self._limits)
            except CommandError as exc:
                self._late_rejections.append((topics.JOINT_TRAJECTORY, str(exc)))
                self._trajectory = None
        if self._trajectory is not None:
            values, done = self._trajectory.sample(now_s)
            self._apply(values, self._trajectory_mode)
            if done:
                self._trajectory = None
        if self._pending:
            self._apply(self._pending, self._command_mode)
            self._pending = {}
        return self._frame

    def _base_frame(self, state: MDS_STATE) -> MDS_REF:
        """What the first frame holds for the joints no command touches (caller holds the lock).

        The mux compares a controller's frame with its previous one (or, for its very first frame, with the
        mux output), and marks every difference as a command. So the base is, in this order: the newest
        frame already in the bridge's channel (its frame from before a restart, or the seed the mux writes
        to mds-ref-filter); the mux output; and only without a mux the daemon's reference (state ref_r).
        Taken at the first write, not at start-up, so it is never an old pose.
        """
        frame = self._ref_chan.latest()
        if frame is not None:
            return frame
        try:
            with StructChannel(mds.MDS_CHAN_REF_MUX_NAME, MDS_REF, create=False) as mux_out:
                frame = mux_out.latest()
        except (ach.AchException, ValueError):
            frame = None
        if frame is not None and self._ref_name != mds.MDS_CHAN_DAEMON_INPUT_NAME:
            return frame
        frame = MDS_REF()
        for a in range(mds.MDS_JOINT_COUNT):
            frame.joint[a].ref = state.joint[a].ref_r
            frame.joint[a].mode = self._command_mode
        return frame

    def _apply(self, values: dict[str, float], mode: int) -> None:
        assert self._frame is not None
        for name, value in values.items():
            j = self._frame.joint[joints.BY_SHORT[name].address]
            j.ref = value
            j.mode = mode

    def _refuse_reason(self) -> str | None:
        """Commands need a live state stream: the bridge writes in step with it (caller holds the lock)."""
        if self._last_frame_mono is None:
            return f"no {self._state_name} frame received yet (is the daemon running?)"
        if self._stalled:
            return f"{self._state_name} has stalled"
        return None

    def _reject(self, topic: str, reason: str) -> None:
        with self._lock:
            self._counters.rejected += 1
            self._counters.last_rejection = f"{topic}: {reason}"
        self.get_logger().warning(f"rejected message on {self.resolve_topic_name(topic)}: {reason}")

    def _accept_positions(self, topic: str, make: Callable[[], dict[str, float]]) -> None:
        try:
            values = make()
        except CommandError as exc:
            self._reject(topic, str(exc))
            return
        with self._lock:
            reason = self._refuse_reason()
            if reason is None:
                self._pending.update(values)
                if self._trajectory is not None:
                    self.get_logger().info("position command preempts the running trajectory")
                    self._trajectory = None
                self._counters.accepted += 1
        if reason is not None:
            self._reject(topic, reason)

    def _on_joint_command(self, msg: JointState) -> None:
        self._accept_positions(topics.JOINT_COMMAND, lambda: positions_by_name(msg.name, msg.position, self._limits))

    def _on_positions(self, msg: Float64MultiArray) -> None:
        self._accept_positions(topics.JOINT_POSITIONS, lambda: positions_from_array(msg.data, self._limits))

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        now = self.get_clock().now().nanoseconds * 1e-9
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        start = stamp if stamp > 0.0 else now
        points = [
            (p.time_from_start.sec + p.time_from_start.nanosec * 1e-9, p.positions, p.velocities) for p in msg.points
        ]
        try:
            traj = trajectory.build(msg.joint_names, points, start, self._limits)
            if traj.end < now:
                raise CommandError(f"the trajectory ended {now - traj.end:.3f} s ago (header.stamp in the past)")
        except CommandError as exc:
            self._reject(topics.JOINT_TRAJECTORY, str(exc))
            return
        with self._lock:
            reason = self._refuse_reason()
            if reason is None:
                replaced = self._trajectory is not None
                for n in traj.names:
                    self._pending.pop(n, None)
                self._trajectory = traj  # anchored at the current reference on the next state cycle
                self._counters.accepted += 1
        if reason is not None:
            self._reject(topics.JOINT_TRAJECTORY, reason)
            return
        self.get_logger().info(
            f"trajectory accepted{' (replaces the running one)' if replaced else ''}: {len(traj.names)} joints, "
            f"{len(traj.times)} points, {traj.times[-1]:.3f} s"
        )

    def _on_ik(self, arm: str, msg: PoseStamped) -> None:
        topic = topics.IK_LEFT if arm == "left" else topics.IK_RIGHT
        with self._lock:
            frames, dof = set(self._ik_frames), self._ik_dof[arm]
        if msg.header.frame_id not in frames:
            accepted = " or ".join(map(repr, sorted(frames)))
            self._reject(topic, f"frame_id {msg.header.frame_id!r} is not the robot frame ({accepted})")
            return
        pos, ori = msg.pose.position, msg.pose.orientation
        try:
            req = make_request(arm, (pos.x, pos.y, pos.z), (ori.x, ori.y, ori.z, ori.w), dof)
        except CommandError as exc:
            self._reject(topic, str(exc))
            return
        self._ik_chan.put(req)
        with self._lock:
            self._counters.accepted += 1
            self._counters.ik_forwarded += 1

    # ------------------------------------------------------------------------------------ diagnostics

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        with self._lock:
            c = self._counters
            frames_new = c.frames - c.frames_at_last_diag
            rejected_new = c.rejected - c.rejected_at_last_diag
            c.frames_at_last_diag, c.rejected_at_last_diag = c.frames, c.rejected
            last = self._last_frame_mono
            stalled = self._stalled
            traj_active = self._trajectory is not None
            values = {
                "state channel": self._state_name,
                "reference channel": self._ref_name,
                "frames published": str(c.frames),
                "frames since last report": str(frames_new),
                "last frame age [s]": "never" if last is None else f"{now - last:.3f}",
                "stamps from receipt time (clock not comparable)": str(c.clock_fallbacks),
                "commands accepted": str(c.accepted),
                "commands rejected": str(c.rejected),
                "last rejection": c.last_rejection,
                "references written": str(c.references_written),
                "IK requests forwarded": str(c.ik_forwarded),
                "trajectory active": str(traj_active),
                **c.extra,
            }
        if stalled and last is not None:
            level, message = DiagnosticStatus.ERROR, f"state stream stalled: no frame for {now - last:.2f} s"
        elif last is None:
            level, message = DiagnosticStatus.WARN, f"waiting for the first {self._state_name} frame"
        elif "state thread" in values:
            level, message = DiagnosticStatus.ERROR, "state thread stopped"
        else:
            level, message = DiagnosticStatus.OK, "state stream live"
        stream = DiagnosticStatus(
            level=level, name=f"{self.get_name()}: state stream", message=message, hardware_id="mds",
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )  # fmt: skip
        cmd_level = DiagnosticStatus.WARN if rejected_new else DiagnosticStatus.OK
        commands = DiagnosticStatus(
            level=cmd_level, name=f"{self.get_name()}: commands", hardware_id="mds",
            message=f"{rejected_new} rejected since the last report" if rejected_new else "ok",
        )  # fmt: skip
        arr = DiagnosticArray(status=[stream, commands])
        arr.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(arr)

    # ------------------------------------------------------------------------------------ shutdown

    def shutdown(self) -> None:
        """What ``run_node`` calls at exit: ``close()``."""
        self.close()

    def close(self) -> None:
        """Stop the state thread and release the channels (idempotent)."""
        self._stop.set()
        self._state_chan.cancel()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for chan in (self._state_chan, self._ref_chan, self._ik_chan):
            chan.close()

