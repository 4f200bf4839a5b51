"""The bridge node: ``mds-state`` -> JointState, ROS commands -> the bridge's reference channel.

Threads: a dedicated state thread blocks on the state channel (newest frame wins) and, for every new
frame, writes the bridge's reference if there is something new (the newest accepted command, or the
running trajectory sampled at this cycle) and publishes ``joint_states`` and ``mds/joint_references``.
The executor thread only runs subscription callbacks, which validate a command completely and hand it
over under a lock (a position command is written at once), the diagnostics timer and the mds/hold, mds/resume
services; it and the DDS reception threads run SCHED_FIFO (``bridge.main``: ``rosnode.run_node``'s
``rt_priority``). A frame is never published twice; when the daemon stalls the topics fall silent and /diagnostics
reports it.

Lifecycle (issue 17): before each write the state thread reads what the mux did since the last cycle
(``muxwatch``). A frame of the bridge the mux refused (another controller owns a joint, a joint not permitted)
is logged once per command with the owner and reported on /diagnostics and ``mds/command_status``; a trajectory
that is refused, stopped by a HOLD or CANCEL from anyone, aborted (stall) or preempted stops being a target:
the bridge stops streaming it and CANCELs its joints the other controllers do not own, so they hold where they
are. RESUME never restarts it.

Several trajectories run at once on disjoint joints (a goal per MoveIt controller, ``follow``/``actions``); a new
command stops those sharing a joint with it. The state thread also runs the FollowJointTrajectory goals: feedback
and tolerance checks on every frame, and the goal's end (succeeded, aborted with the reason, canceled). Goals are
checked in the goal callback, and each controller has joint_trajectory_controller's ``controller_state``,
``joint_trajectory`` and ``query_state`` (``jtc``; mds_ach_bridge/README.md).
``joint_states`` carries velocities (``velocity.FiniteDifference``) and an empty effort (docs/operator.md).
"""

from __future__ import annotations

import array
import functools
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from control_msgs.msg import JointTrajectoryControllerState
from control_msgs.srv import QueryTrajectoryState
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from mds_ach_interfaces.msg import CommandStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory

import mds_ach as mds
from mds_ach import ach, paths
from mds_ach.ach.glibc import tune_thread
from mds_ach.ach.watch import Latest
from mds_ach.kinematics.limits import current_limits, urdf_with_limits
from mds_ach.kinematics.model import load_model
from mds_ach.nodes.mux import controller_for
from mds_ach.nodes.pipeline import KNOWN_ADDRESSES, labels
from mds_ach.nodes.rosnode import Param, declare, ros_log
from mds_ach.nodes.status_msgs import command_status_msg
from mds_ach.robot import config as joint_config
from mds_ach.robot import contracts, joints, lifecycle, motion
from mds_ach.robot.channels import ChannelGuard, StructChannel
from mds_ach.robot.feedforward import (
    Braking,
    CycleClock,
    limiter_lead,
    retraction_in_time,
    stopping_point,
    took_newest,
)
from mds_ach.robot.msgs import MDS_IK, MDS_REF, MDS_STATE
from mds_ach.robot.msgs.daemon_status import JOINT_SLOWED, MDS_DAEMON_STATUS
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_FREE, MUX_HELD
from mds_ach_bridge import actions, follow, jtc, topics, trajectory
from mds_ach_bridge.commands import CommandError, positions_by_name, positions_from_array
from mds_ach_bridge.ik_request import make_request
from mds_ach_bridge.limits import load_limits
from mds_ach_bridge.muxwatch import MuxNews, MuxWatch
from mds_ach_bridge.stamps import state_stamp_ns
from mds_ach_bridge.tf import TfPublisher
from mds_ach_bridge.velocity import FiniteDifference

NODE_NAME = "mds_bridge"
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
WRITE_RECORDS = 64
"""Recent writes remembered to tell which command a refused frame carried (the mux answers within a cycle)."""
HOLD_RECHECK = 0.005
"""s after a put of a trajectory frame: by then the mux has handled it and said whether it released a hold
(``BridgeNode._recheck_holds``)."""
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
    mux_refused: int = 0
    mux_refused_at_last_diag: int = 0
    last_mux_refusal: str = ""
    stopped: int = 0
    stopped_at_last_diag: int = 0
    last_stop: str = ""
    extra: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class _Write:
    """One frame the bridge wrote: when (just before the put) and which commands it carried, by serial."""

    time: float
    trajectories: tuple[int, ...]  # the trajectories sampled in it
    commands: tuple[int, ...]  # the position commands applied in it


@dataclass
class _Running:
    """A trajectory the bridge streams (from the topic or an action goal); several run at once on disjoint joints."""

    serial: int
    traj: trajectory.Trajectory
    goal: actions.Goal | None = None  # the FollowJointTrajectory goal it carries out
    written: float | None = None  # monotonic time of its first write
    finished: bool = False  # sampled to its end; kept while its goal waits for the goal tolerance
    slowed: set[str] = field(default_factory=set)  # its joints the daemon's collaborative mode slowed (#31)
    due: float | None = None  # the time its newest written targets were sampled for (node clock)
    desired: dict[str, tuple[float, float]] = field(default_factory=dict)  # (position, velocity) there, per joint
    previous: tuple[float, dict[str, tuple[float, float]]] | None = None  # (due, desired) of the sample before
    floors: dict[str, _Floor] = field(default_factory=dict)  # a replaced motion's braking, per joint (``_Floor``)
    ramps: dict[str, float] = field(default_factory=dict)  # joints going back from a floor: their last target


@dataclass(frozen=True)
class _Floor:
    """A joint whose previous motion was replaced while moving: its target already sent or in flight is the
    stopping point ``value`` (moving in direction ``sign``), which the MCB may already be braking onto. A new target
    short of it would make the joint pass it and come back, so the joint's targets stay at ``value`` until the new
    trajectory's own targets pass it (``forward``: the new trajectory goes on beyond it) or, when the new trajectory
    goes back, until the joint has come to rest there (``rest``, node clock); then its targets go from ``value`` to
    the new trajectory's at the published velocity (a jump would make the daemon's limiter, 7.2 rad/s^2, carry the
    targets past the new ones and back)."""

    value: float
    sign: float
    rest: float
    forward: bool


@dataclass
class _Stop:
    """Joints of a stopped trajectory whose frame was retracted to the daemon's reference (``BridgeNode._retract``),
    waiting for their CANCEL until the daemon has taken it (``BridgeNode._check_stops``)."""

    names: tuple[str, ...]
    reason: str
    hold: dict[str, float]  # where the frame holds each joint: the daemon's reference at the stop
    newest: dict[str, float]  # the newest value written before: the last target if the daemon took it first
    brakes: dict[str, Braking]  # the joints' braking from the newest targets (``BridgeNode._braking``), for that case
    frame: int  # the state frames counted when written: the next one tells what the daemon took
    deadline: float  # monotonic: CANCEL then whatever the daemon took (no state frame: a stall)


@dataclass(frozen=True)
class _Retracted:
    """A joint a new trajectory takes over from a moving one, its frame retracted to the daemon's reference
    (``BridgeNode._retract``): the new trajectory's first cycle tells which of the two the daemon took
    (``BridgeNode._replace``)."""

    hold: float  # the daemon's reference at the replacement
    newest: float  # the replaced trajectory's newest value
    braking: Braking  # the replaced motion's braking from its newest target (if the daemon took that one)
    frame: int  # the state frames counted at the replacement


@dataclass(frozen=True)
class _Event:
    """Something to log and publish on mds/command_status once the lock is released."""

    level: str  # "info" or "warn"
    text: str
    doc: dict[str, Any]


SECONDS = (0.001, 3600.0)
PARAMETERS = (
    Param("state_channel", contracts.base_name(mds.MDS_CHAN_STATE_NAME), "Ach channel of mds_state_t frames"),
    Param("ref_channel", contracts.base_name(mds.MDS_CHAN_REF_ROS_NAME),
          "Ach channel the bridge writes its mds_ref_t to: its mux input (default), or mds-ref-filter when no mux "
          "runs"),
    Param("ik_channel", contracts.base_name(mds.MDS_CHAN_IK_NAME), "Ach channel for mds_ik_t requests"),
    Param("allow_ungated", False,
          f"allow ref_channel = {contracts.base_name(mds.MDS_CHAN_DAEMON_INPUT_NAME)} (the daemon's input), which "
          "bypasses mux, filter and collision gate (simulation tests only)"),
    Param("state_qos", "reliable", "QoS of joint_states and mds/joint_references: reliable (default, what "
                                   "robot_state_publisher, RViz and MoveIt subscribe with) or sensor_data "
                                   "(best effort)"),
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
    Param("publish_tf", True, "publish /tf (moving joints, per joint_states message) and /tf_static (fixed joints) "
                              "from the URDF, as robot_state_publisher does: false when one runs"),
    Param("rt_priority", 0, "SCHED_FIFO priority (1-99) of the state thread, which wakes on every state frame and "
                            "publishes it; 0 = normal scheduling. Needs CAP_SYS_NICE or an rtprio limit; refused: "
                            "logged, normal priority", range=(0, 99)),
    Param("diagnostics_period", 1.0, "seconds between /diagnostics messages", range=SECONDS),
    *jtc.PARAMETERS,  # joint_trajectory_controller's, for every controller (mds_ach_bridge/README.md)
)


class BridgeNode(Node):
    """See the module docstring; parameters are declared with descriptions (``ros2 param describe``)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        p = self.get_parameter
        # channel parameters name the original channels; $MDS_ACH_CHANNEL_PREFIX makes them this system's
        self._state_name: str = contracts.channel_name(p("state_channel").value)
        self._ref_name: str = contracts.channel_name(p("ref_channel").value)
        self._ik_name: str = contracts.channel_name(p("ik_channel").value)
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
        self._jtc_values: dict[str, Any] = {name: p(name).value for name in jtc.NAMES}
        self._max_age: float = p("max_state_age").value
        self._command_mode: int = p("command_mode").value
        self._trajectory_mode: int = p("trajectory_mode").value
        self._ik_dof = {"left": p("ik_dof_left").value, "right": p("ik_dof_right").value}
        self._ik_frames = {"", p("ik_frame").value}
        urdf = p("urdf").value or str(paths.urdf_path())
        self._effective = current_limits(p("robot").value or None)
        self._limits = load_limits(joints.MODEL_JOINTS, effective=self._effective)
        # The published velocity of each joint: a goal timed faster is rejected (it would be stretched, late).
        self._speeds = {n: m[0] for n in self._limits for m in (self._effective.motion(n),) if m is not None}
        # The MOVETO acceleration the daemon commands: trajectories are sent as their stopping points at it.
        self._moveto_accel = math.radians(joint_config.load(self._effective.robot).accel_deg_s2)
        self._cycle = CycleClock()  # state thread only: the daemon's period, from the state frames' stamps
        # The daemon's limiter at its margin: its targets trail a moving reference by their braking distance at this.
        table = joint_config.load(self._effective.robot)
        self._limiter_accel = motion.LIMIT_MARGIN * table.motion_bounds().max_acceleration
        self._limiter_speed = motion.LIMIT_MARGIN * table.motion_bounds().max_velocity
        self._intended: dict[str, float] = {}  # the newest intended daemon target per trajectory joint (the lock)
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._names = list(joints.MODEL_JOINTS)
        self._addresses = [joints.BY_SHORT[n].address for n in self._names]
        self._lock = threading.Lock()
        # One writer of the reference channel at a time (the state thread, a position command written at once by
        # its callback), held from building a frame to its put, so frames reach the mux in the order they were built.
        self._write_lock = threading.Lock()
        self._counters = _Counters()
        self._pending: dict[str, float] = {}  # accepted position commands not yet written
        self._running: dict[int, _Running] = {}  # by serial, in start order
        self._goal_ends: list[actions.Goal] = []  # goals that ended under the lock, told to the client after it
        self._frame: MDS_REF | None = None  # the bridge's reference, created on the first write
        self._unsent = False  # under _write_lock: the newest frame could not be written (a damaged channel)
        self._late_rejections: list[tuple[str, str]] = []  # found on the state thread under the lock, logged after it
        # Lifecycle: commands get a serial; the state thread remembers which ones each write carried.
        self._controller = controller_for(self._ref_name)  # the bridge's name in the mux (config/mux.yaml)
        self._serial = 0
        self._what: dict[int, str] = {}  # serial -> "trajectory #3 (LSP, LEP)" for the messages
        self._pending_cmds: list[int] = []  # serials of the commands in _pending
        self._carried: tuple[tuple[int, ...], tuple[int, ...]] = ((), ())  # what _next_reference's frame carries
        self._writes: deque[_Write] = deque(maxlen=WRITE_RECORDS)  # appended under _write_lock, read under _lock
        self._reported: deque[int] = deque(maxlen=WRITE_RECORDS)  # serials whose refusal was logged already
        self._cancels: list[tuple[tuple[str, ...], str]] = []  # (joints, reason) to CANCEL, sent outside the lock
        self._stops: list[_Stop] = []  # retracted stops waiting for their CANCEL (``_check_stops``)
        self._stops_done = threading.Condition(self._lock)  # notified when ``_stops`` empties
        self._retracted: dict[str, _Retracted] = {}  # joints a new trajectory takes from a retracted one
        # Frame values of stopped joints to write next (a retraction or its undoing, ``_check_stops``); put into the
        # frame under the write lock (a put reads the frame outside the lock), by ``_take_holds``.
        self._holds: dict[str, float] = {}
        self._recheck_at: float | None = None  # monotonic: when to read the mux's news after a put (``_recheck_holds``)
        self._resync: set[str] = set()  # joints of a stopped trajectory: the frame's value is not where they hold
        # The commanded motion of joints whose trajectory stopped or was replaced while moving: they brake at the
        # MOVETO acceleration from their desired state at the last written target onto its stopping point. A new
        # trajectory for them starts from this state (position and velocity), as joint_trajectory_controller does.
        self._braking: dict[str, Braking] = {}
        self._events: list[_Event] = []
        # Goal requests checked in the goal callback, by id(request): (request, trajectory, tolerances), taken by the
        # accepted callback that follows (rclpy hands both the same request object).
        self._checked: dict[int, tuple[Any, trajectory.Trajectory, follow.Tolerances]] = {}
        self._measured: tuple[dict[str, float], dict[str, float]] | None = None  # newest frame's positions, velocities
        self._state: MDS_STATE | None = None  # the newest state frame (the lock): a first write's base without a mux
        self._due: float | None = None  # what the targets written after the newest frame are sampled for (the lock)
        self._started = time.monotonic()
        self._last_frame_mono: float | None = None
        self._stalled = False

        self._state_chan = StructChannel(self._state_name, MDS_STATE)
        self._ref_chan = StructChannel(self._ref_name, MDS_REF)
        self._ik_chan = StructChannel(self._ik_name, MDS_IK)
        self._mux = MuxWatch(self._controller)
        self._daemon = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)  # collaborative mode: slowed

        state_qos = STATE_QOS[qos_name]
        self._js_pub = self.create_publisher(JointState, topics.JOINT_STATES, state_qos)
        self._ref_pub = self.create_publisher(JointState, topics.JOINT_REFERENCES, state_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, 10)
        self._status_pub = self.create_publisher(CommandStatus, topics.COMMAND_STATUS, COMMAND_QOS)
        model = load_model(urdf)
        self._js_msg = JointState(name=self._names)
        # The URDF root, as joint_state_broadcaster's default frame_id (its own parameter default "base_link").
        self._js_msg.header.frame_id = model.root
        self._velocity = FiniteDifference()  # state thread only
        self._ref_msg = JointState(name=self._names)
        self._ref_msg.header.frame_id = model.root
        if p("publish_robot_description").value:
            self._desc_pub = self.create_publisher(String, topics.ROBOT_DESCRIPTION, LATCHED_QOS)
            # The URDF with the effective limits, so MoveIt, RViz sliders and planners use what the robot accepts.
            self._desc_pub.publish(String(data=urdf_with_limits(Path(urdf).read_text(), self._effective)))
        self._tf = TfPublisher(self, model, self._names) if p("publish_tf").value else None
        self.create_subscription(JointState, topics.JOINT_COMMAND, self._on_joint_command, COMMAND_QOS)
        self.create_subscription(JointTrajectory, topics.JOINT_TRAJECTORY, self._on_trajectory, COMMAND_QOS)
        self.create_subscription(Float64MultiArray, topics.JOINT_POSITIONS, self._on_positions, COMMAND_QOS)
        self.create_subscription(PoseStamped, topics.IK_LEFT, lambda m: self._on_ik("left", m), COMMAND_QOS)
        self.create_subscription(PoseStamped, topics.IK_RIGHT, lambda m: self._on_ik("right", m), COMMAND_QOS)
        self.create_timer(p("diagnostics_period").value, self._publish_diagnostics)
        self.create_service(Trigger, topics.HOLD_SERVICE, self._on_hold)
        self.create_service(Trigger, topics.RESUME_SERVICE, self._on_resume)
        self._action_servers = actions.create_servers(self, self._on_goal_request, self._on_goal, self._on_goal_cancel)
        # joint_trajectory_controller's other endpoints, for each controller.
        self._state_pubs = {c: self.create_publisher(JointTrajectoryControllerState, f"{c}/{topics.CONTROLLER_STATE}",
                                                     10) for c in follow.CONTROLLERS}
        for c in follow.CONTROLLERS:
            self.create_subscription(JointTrajectory, f"{c}/{topics.CONTROLLER_TRAJECTORY}",
                                     functools.partial(self._on_trajectory, controller=c), COMMAND_QOS)
            self.create_service(QueryTrajectoryState, f"{c}/{topics.QUERY_STATE}",
                                functools.partial(self._on_query_state, c))

        self._stop = threading.Event()
        # A damaged channel (a writer killed mid-put, a scribbled header) must not stop the bridge or its state
        # thread: it reads as "nothing new" (the stall check then holds the trajectories), writes fail with a
        # report, and StructChannel re-opens a file `mds-ach repair` re-created (docs/reliability.md §2).
        self._guard = ChannelGuard(ros_log(self), self._stop)
        self._thread = threading.Thread(target=self._state_loop, name="mds-bridge-state", daemon=True)
        self._thread.start()
        self.get_logger().info(
            f"bridging {self._state_name} -> {self.resolve_topic_name(topics.JOINT_STATES)}, "
            f"commands -> {self._ref_name} (mux controller '{self._controller}'), IK -> {self._ik_name}"
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
                elif prm.name in jtc.NAMES:
                    self._jtc_values[prm.name] = prm.value
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------------------------ state -> ROS

    def _state_loop(self) -> None:
        """Block on the state channel; for each new frame write the reference, then publish the frame once."""
        for problem in tune_thread(self._rt_priority):
            self.get_logger().warning(f"state thread: {problem}")
        try:
            while not self._stop.is_set():
                # The wait returns on every put; its timeout only paces the stall check.
                timeout = max(0.01, min(0.25, self._stale_timeout / 4))
                if self._recheck_at is not None:
                    timeout = max(0.0, min(timeout, self._recheck_at - time.monotonic()))
                state = self._guard.call(self._state_chan.name, self._state_chan.wait, timeout=timeout)
                if state is None:
                    self._recheck_holds()
                    self._check_stall()
                    self._flush_cancels()
                    continue
                self._on_state(state)
                self._flush_cancels()
        except Exception as exc:  # a dead state thread must be loud, not a silently frozen bridge
            self.get_logger().fatal(f"state thread stopped: {exc!r}")
            self._counters.extra["state thread"] = f"stopped: {exc!r}"
            raise

    def _on_state(self, state: MDS_STATE) -> None:
        mono = time.clock_gettime(time.CLOCK_MONOTONIC)
        now_ns = self.get_clock().now().nanoseconds
        js = [state.joint[a] for a in self._addresses]
        positions = [j.pos for j in js]
        velocities = self._velocity.update(state.time, positions)
        self._cycle.update(state.time)
        # When the frame was measured, on the node's clock (trajectories are timed on it), and when the target
        # written now is due (``feedforward.CycleClock.lookahead``).
        stamp_ns, comparable = state_stamp_ns(now_ns, mono, state.time, self._max_age)
        measured_s = stamp_ns * 1e-9
        due_s = measured_s + self._cycle.lookahead()
        # What the mux did since the last cycle: before anything else is written.
        news = self._guard.call(self._mux.states.name, self._mux.poll, default=MuxNews())
        # The reference first: it is one put, and a pending command should not wait for two publishes.
        with self._write_lock:
            with self._lock:
                was_stalled = self._stalled
                self._stalled = False
                self._last_frame_mono = mono
                self._counters.frames += 1
                self._take_mux_news(news)
                self._check_stops(state)
                before = None if self._frame is None else MDS_REF.from_buffer_copy(self._frame)
                ref = self._next_reference(state, due_s)
                carried = self._carried
                measured = (dict(zip(self._names, positions, strict=True)),
                            dict(zip(self._names, velocities, strict=True)))
                self._measured = measured
                self._state = state
                self._due = due_s
                feedback = self._follow_goals(measured_s, *measured)
                # The newest frame did not get through, or a stop's retraction is to be written: write it (again).
                if self._take_holds() or (ref is None and self._unsent):
                    ref = self._frame
                running = self._running_by_joint()
                late, self._late_rejections = self._late_rejections, []
            if ref is not None and carried[0]:
                self._held_meanwhile(before, carried[0])
            if ref is not None:
                self._writes.append(_Write(time.monotonic(), *carried))
                self._unsent = not self._guard.put(self._ref_chan, ref)  # reported; the next cycle writes it again
                if not self._unsent:
                    with self._lock:
                        self._counters.references_written += 1
                    if carried[0]:
                        self._recheck_at = time.monotonic() + HOLD_RECHECK
        for topic, reason in late:
            self._reject(topic, reason)
        self._emit()

        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        self._js_msg.header.stamp = stamp
        self._js_msg.position = array.array("d", positions)
        self._js_msg.velocity = array.array("d", velocities)
        self._js_pub.publish(self._js_msg)
        for goal, *values in feedback:
            goal.feedback(stamp, *values)
        self._publish_controller_states(stamp, measured_s, running, measured, js)
        if self._ref_pub.get_subscription_count() > 0:  # nobody listening: skip the serialisation
            self._ref_msg.header.stamp = stamp
            self._ref_msg.position = array.array("d", [j.ref for j in js])
            self._ref_pub.publish(self._ref_msg)
        if self._tf is not None:  # last: its 17 transforms (~0.4 ms) delay no feedback
            self._tf.publish(positions, stamp)
        if not comparable:
            with self._lock:
                self._counters.clock_fallbacks += 1
        if was_stalled:
            self.get_logger().info(f"{self._state_name} is live again")
            self._publish_diagnostics()

    def _recheck_holds(self) -> None:
        """``HOLD_RECHECK`` after a put of a trajectory frame: a hold the mux handled between the last read of its
        news and that put was released by the frame; the mux says so at once (its held mask changed). The
        trajectory then stops now, retracted to the daemon's reference while the daemon has not sent the frame
        (``_take_mux_news``), not at the next cycle, after the daemon sent it."""
        if self._recheck_at is None or time.monotonic() < self._recheck_at:
            return
        self._recheck_at = None
        news = self._guard.call(self._mux.states.name, self._mux.poll, default=MuxNews())
        if not news.holds and not news.refusals:
            return
        with self._lock:
            self._take_mux_news(news)
        self._emit()

    def _held_meanwhile(self, before: MDS_REF | None, sampled: tuple[int, ...]) -> None:
        """Just before the put of a frame sampling the trajectories ``sampled``: a hold or cancel that reached the
        mux since this cycle's news (another client's, sent right after the daemon's state frame) would be released
        by the frame (a changed value is a new command) and the joint would run on to the new target. Read the mux's
        news once more: a trajectory a hold stopped meanwhile (``_take_mux_news``) keeps its joints' previous values
        in the frame (``before``), so the frame commands nothing new for them (caller holds the write lock)."""
        news = self._guard.call(self._mux.states.name, self._mux.poll, default=MuxNews())
        if not news.holds and not news.refusals:
            return
        with self._lock:
            names = {s: self._running[s].traj.names for s in sampled if s in self._running}
            self._take_mux_news(news)
            if before is None or self._frame is None:
                return
            for serial, stopped in names.items():
                if serial in self._running:
                    continue
                for n in stopped:
                    a = joints.BY_SHORT[n].address
                    self._frame.joint[a].ref = before.joint[a].ref
                    self._frame.joint[a].mode = before.joint[a].mode

    def _check_stall(self) -> None:
        now = time.monotonic()
        with self._lock:
            since = self._last_frame_mono if self._last_frame_mono is not None else self._started
            if self._stalled or now - since <= self._stale_timeout:
                return
            self._stalled = True
            # A trajectory must not jump ahead when the state comes back: drop it and hold.
            dropped = bool(self._stop_all("aborted: the state stream stalled"))
            self._end_stops(everything=True)
        what = "no state frame yet" if self._last_frame_mono is None else f"no new state frame for {now - since:.2f} s"
        self.get_logger().warning(
            f"{self._state_name}: {what}; is the daemon running?" + (" Trajectory aborted." if dropped else "")
        )
        self._emit()
        self._publish_diagnostics()

    # ------------------------------------------------------------------------------------ ROS -> reference

    def _next_reference(self, state: MDS_STATE, due_s: float) -> MDS_REF | None:
        """The frame to write this cycle, or None when nothing changed (caller holds the lock).

        A running trajectory is sampled at ``due_s`` (the time the daemon's MOVETO of this frame aims at) and
        written as its stopping point at the MOVETO acceleration (``mds_ach.robot.feedforward``), clamped to the
        limits: the MCB then passes the trajectory's position with its velocity instead of lagging it.

        Sets ``_carried``: the serials of the trajectory and commands in the frame, to name them if it is refused.
        """
        self._carried = ((), ())
        active = [r for r in self._running.values() if not r.finished]
        if not active and not self._pending:
            return None  # nothing new: the mux holds the last frame (an unchanged frame would not count anyway)
        if self._frame is None:
            self._frame = self._base_frame(state)
        sampled = self._sample(active, state, due_s)
        self._carried = (tuple(sampled), self._apply_pending())
        return self._frame

    def _sample(self, active: list[_Running], state: MDS_STATE, due_s: float) -> list[int]:
        """Write the targets of the trajectories ``active`` for ``due_s`` into the frame (anchored first where they
        need it): their serials (caller holds the lock, the frame exists)."""
        assert self._frame is not None
        sampled: list[int] = []
        for r in active:
            if r.written is None:
                self._replace(r, due_s, state)
            if not r.traj.anchored:
                # Joints of a stopped trajectory hold where the daemon's reference is, not at the frame's last sample;
                # a joint still braking from a replaced motion starts from its commanded state (position, velocity).
                current = {
                    n: state.joint[a].ref_r if n in self._resync else self._frame.joint[a].ref
                    for n in r.traj.names for a in (joints.BY_SHORT[n].address,)
                }  # fmt: skip
                speed = dict.fromkeys(r.traj.names, 0.0)
                for n in r.traj.names:
                    b = self._braking.get(n)
                    if b is not None and b.moving(r.traj.start):  # at rest: where the daemon's reference is
                        current[n], speed[n] = b.at(r.traj.start)
                try:
                    r.traj = r.traj.anchor(current, self._limits, speed)
                except CommandError as exc:
                    del self._running[r.serial]
                    if r.goal is None:
                        self._late_rejections.append((topics.JOINT_TRAJECTORY, str(exc)))
                    else:
                        self._end_goal(r.goal, actions.ABORT, follow.Result.INVALID_GOAL, str(exc))
                    continue
            values, speeds, done = r.traj.sample_state(due_s)
            if r.due is not None:
                r.previous = (r.due, r.desired)
            r.due, r.desired = due_s, {n: (values[n], speeds[n]) for n in values}
            targets = self._floored(r, self._feedforward(values, speeds), due_s)
            self._apply(targets if done else self._lead(targets), self._trajectory_mode)  # the end: exactly there
            for n in r.traj.names:
                self._braking.pop(n, None)
            sampled.append(r.serial)
            if r.written is None:
                r.written = time.monotonic()
            if done:
                r.finished = True
                if r.goal is None:
                    del self._running[r.serial]
                what = self._what.get(r.serial, "trajectory")
                self._events.append(_Event("info", f"{what} finished", {"event": "finished", "command": what}))
        return sampled

    def _apply_pending(self) -> tuple[int, ...]:
        """Put the accepted position commands into the frame; their serials (caller holds the lock)."""
        commands: tuple[int, ...] = ()
        if self._pending:
            for n in self._pending:
                self._braking.pop(n, None)
            self._apply(self._pending, self._command_mode)
            self._pending = {}
            commands, self._pending_cmds = tuple(self._pending_cmds), []
        return commands

    def _write_commands(self) -> None:
        """Write the accepted position commands now, not at the next state frame: a command is an event (#26 item
        5), the first one too (the bridge's first frame is built here then, as the state thread would build it)."""
        with self._write_lock:
            with self._lock:
                if not self._pending or self._state is None:
                    return
                if self._frame is None:
                    self._frame = self._base_frame(self._state)
                commands = self._apply_pending()
                self._take_holds()
                self._writes.append(_Write(time.monotonic(), (), commands))
            self._unsent = not self._guard.put(self._ref_chan, self._frame)  # the next state cycle writes it again
            if not self._unsent:
                with self._lock:
                    self._counters.references_written += 1

    def _write_started(self) -> None:
        """Write a trajectory accepted between two state frames now, for the daemon's next cycle, instead of at the
        next frame (#26 items 2 and 5): its first target is then sent one cycle earlier. Written now, it is sent at
        the daemon's next cycle, the one the newest frame's targets were written for, so it is sampled for that
        frame's due time (``_due``); one that misses that cycle is never sent: the next frame's write replaces it
        before the cycle after. A trajectory that takes over joints from a moving one is written on the next frame
        (which of the retracted and the newest targets the daemon sent is known there, ``_replace``). Other
        trajectories and commands keep their values in the frame."""
        with self._write_lock:
            with self._lock:
                due = self._due
                if self._state is None or due is None or self._stalled:
                    return
                fresh = [r for r in self._running.values() if r.written is None and not r.finished
                         and not any(n in self._retracted or ((b := self._braking.get(n)) is not None and b.moving(due))
                                     for n in r.traj.names)]
                if not fresh:
                    return
                if self._frame is None:
                    self._frame = self._base_frame(self._state)
                held = self._take_holds()  # a retraction of the same callback goes with it
                sampled = self._sample(fresh, self._state, due)
                if not sampled and not held:  # refused when anchored (reported by the state thread)
                    return
                self._writes.append(_Write(time.monotonic(), tuple(sampled), ()))
            self._unsent = not self._guard.put(self._ref_chan, self._frame)  # the next state cycle writes it again
            if not self._unsent:
                with self._lock:
                    self._counters.references_written += 1

    def _replace(self, r: _Running, due_s: float, state: MDS_STATE) -> None:
        """A new trajectory's joints that were braking from a replaced motion keep their braking target until the
        new one's targets pass it (``_Floor``): the joint stops within the braking distance from its commanded
        velocity and never goes back to meet a trajectory that goes on the same way (caller holds the lock).

        The braking target is the last one the daemon sent: the daemon's reference the replacement retracted the
        frame to (``_stop_running``), if this cycle's state shows the daemon took it, else the replaced trajectory's
        newest target (the daemon sent it before the retraction arrived)."""
        final = dict(zip(r.traj.names, r.traj.positions[-1], strict=True))
        for n in r.traj.names:
            retracted = self._retracted.pop(n, None)
            hold = None
            if retracted is not None and self._counters.frames <= retracted.frame + 1:
                taken = state.joint[joints.BY_SHORT[n].address].ref_r
                if abs(taken - retracted.newest) < abs(taken - retracted.hold):
                    self._braking[n] = retracted.braking
                else:
                    hold = retracted.hold  # the reference itself: the daemon's target does not go back from it
            b = self._braking.get(n)
            if b is None or not b.moving(due_s):  # (at rest it may have been moved since by another controller)
                continue
            value = stopping_point(b.q0, b.v0, b.accel) if hold is None else hold
            sign = math.copysign(1.0, b.v0)
            r.floors[n] = _Floor(value, sign, b.t0 + abs(b.v0) / b.accel, sign * (final[n] - value) > 0.0)

    def _floored(self, r: _Running, targets: dict[str, float], due_s: float) -> dict[str, float]:
        """``targets`` with the joints of ``r.floors`` kept at their braking target while it applies, and those going
        back from it moving towards the new targets at the published velocity (``_Floor``)."""
        for n, f in list(r.floors.items()):
            short = f.sign * (targets[n] - f.value) < 0.0
            if short and (f.forward or due_s < f.rest):
                targets[n] = f.value
                continue
            del r.floors[n]
            if short:
                r.ramps[n] = f.value
        for n, last in list(r.ramps.items()):
            motion = self._effective.motion(n)
            step = (motion[0] if motion is not None else 0.5) * self._cycle.period
            if abs(targets[n] - last) <= step:
                del r.ramps[n]
                continue
            targets[n] = r.ramps[n] = last + math.copysign(step, targets[n] - last)
        return targets

    def _lead(self, targets: dict[str, float]) -> dict[str, float]:
        """The references that make the daemon's limiter send ``targets`` (``feedforward.limiter_lead``: ahead by
        the braking distance of the target sequence's step speed at the limiter's acceleration), within the limits."""
        period = self._cycle.period
        out = {}
        for n, t in targets.items():
            # A step the limiter cannot take in one cycle anyway (a linear trajectory's corner) gets no more lead than
            # its speed bound allows.
            step = min(max((t - self._intended.get(n, t)) / period, -self._limiter_speed), self._limiter_speed)
            self._intended[n] = t
            lower, upper = self._limits[n]
            out[n] = min(max(t + limiter_lead(step, self._limiter_accel), lower), upper)
        return out

    def _feedforward(self, values: dict[str, float], speeds: dict[str, float]) -> dict[str, float]:
        """The MOVETO targets for a desired state: its stopping points, within the limits."""
        out = {}
        for n, q in values.items():
            lower, upper = self._limits[n]
            out[n] = min(max(stopping_point(q, speeds[n], self._moveto_accel), lower), upper)
        return out

    def _base_frame(self, state: MDS_STATE) -> MDS_REF:
        """What the first frame holds for the joints no command touches (caller holds the lock).

        The mux compares a controller's frame with its previous one (or, for its very first frame, with the
        mux output), and marks every difference as a command. So the base is, in this order: the newest
        frame already in the bridge's channel (its frame from before a restart, or the seed the mux writes
        to mds-ref-filter); the mux output; and only without a mux the daemon's reference (state ref_r).
        Taken at the first write, not at start-up, so it is never an old pose.
        """
        frame = self._guard.call(self._ref_chan.name, self._ref_chan.latest)
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
            self._resync.discard(name)
            self._holds.pop(name, None)

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
        self._publish_status({"event": "rejected", "command": topic, "message": reason})

    def _accept_positions(self, topic: str, make: Callable[[], dict[str, float]]) -> None:
        try:
            values = make()
        except CommandError as exc:
            self._reject(topic, str(exc))
            return
        with self._lock:
            reason = self._refuse_reason()
            if reason is None:
                serial = self._new_command(f"{topic} command #{{}} ({', '.join(values)})")
                self._pending.update(values)
                self._pending_cmds.append(serial)
                self._preempt(tuple(values), self._what[serial])
                self._counters.accepted += 1
        if reason is not None:
            self._reject(topic, reason)
        else:
            self._write_commands()
        self._emit()

    def _on_joint_command(self, msg: JointState) -> None:
        self._accept_positions(topics.JOINT_COMMAND, lambda: positions_by_name(msg.name, msg.position, self._limits))

    def _on_positions(self, msg: Float64MultiArray) -> None:
        self._accept_positions(topics.JOINT_POSITIONS, lambda: positions_from_array(msg.data, self._limits))

    def _on_trajectory(self, msg: JointTrajectory, controller: str | None = None) -> None:
        """``mds/joint_trajectory`` (any joints), or ``<controller>/joint_trajectory``: that controller's joints,
        checked as its goals are (joint_trajectory_controller's topic)."""
        now = self.get_clock().now().nanoseconds * 1e-9
        topic = topics.JOINT_TRAJECTORY if controller is None else f"{controller}/{topics.CONTROLLER_TRAJECTORY}"
        try:
            if controller is None:
                traj = trajectory.from_message(msg, now, self._limits)
            else:
                with self._lock:
                    settings = jtc.Settings.from_values(self._jtc_values)
                traj = follow.validate_trajectory(controller, msg, now, self._limits, settings.allow_partial,
                                                  settings.allow_nonzero_end, self._speeds)
        except CommandError as exc:
            self._reject(topic, str(exc))
            return
        with self._lock:
            reason = self._refuse_reason()
            if reason is None:
                serial = self._new_command(f"{'' if controller is None else controller + ' '}trajectory #{{}} "
                                           f"({', '.join(traj.names)})")
                replaced = self._preempt(traj.names, self._what[serial], trajectory=True)
                self._start(serial, traj)
        if reason is not None:
            self._reject(topic, reason)
            return
        self._write_started()
        self._flush_cancels()
        self._emit()
        self._announce_accepted(serial, replaced,
                                f"{len(traj.names)} joints, {len(traj.times)} points, {traj.times[-1]:.3f} s")

    def _announce_accepted(self, serial: int, replaced: Sequence[str], detail: str) -> None:
        """Log and publish on the status topic that a trajectory (topic or goal) was accepted, and what it replaced."""
        replaces = f" (replaces {' and '.join(replaced)})" if replaced else ""
        text = f"{self._what[serial]} accepted{replaces}: {detail}"
        self.get_logger().info(text)
        self._publish_status({"event": "accepted", "command": self._what[serial], "message": text})

    def _start(self, serial: int, traj: trajectory.Trajectory, goal: actions.Goal | None = None) -> None:
        """Run ``traj`` from the next state cycle, anchored at the current reference there (caller holds the lock)."""
        for n in traj.names:
            self._pending.pop(n, None)
        self._running[serial] = _Running(serial, traj, goal)  # anchored at the current reference on the next cycle
        self._counters.accepted += 1

    # ------------------------------------------------------------------------------------ FollowJointTrajectory

    def _on_goal_request(self, controller: str, request: Any) -> bool:
        """The goal callback of ``<controller>/follow_joint_trajectory``: check the goal completely (the topic's
        checks, the controller's joints, its tolerances, a live state stream), as joint_trajectory_controller does
        before accepting. False rejects it; the reason goes to the log and mds/command_status (a rejected goal has no
        result to carry it)."""
        action = f"{controller}/{follow.ACTION}"
        now = self.get_clock().now().nanoseconds * 1e-9
        with self._lock:
            settings = jtc.Settings.from_values(self._jtc_values)
            refused = self._refuse_reason()
        try:
            if refused is not None:
                raise follow.GoalError(follow.Result.INVALID_GOAL, refused)
            traj = follow.validate(controller, request, now, self._limits, settings.allow_partial,
                                   settings.allow_nonzero_end, self._speeds)
            tol = follow.tolerances(traj.names, request, settings.path, settings.goal, settings.goal_time)
        except follow.GoalError as exc:
            self._reject(action, f"goal rejected: {follow.CODE_NAMES[exc.code]}: {exc}")
            return False
        with self._lock:
            self._checked[id(request)] = (request, traj, tol)
            while len(self._checked) > 16:  # accepted goals take theirs at once; rclpy failing to make a handle won't
                del self._checked[next(iter(self._checked))]
        return True

    def _on_goal(self, controller: str, handle: Any, server: Any) -> None:
        """An accepted goal (checked by ``_on_goal_request``): mark it EXECUTING and run it like a trajectory from
        the topic; it preempts the controller's running goal and anything else on its joints."""
        goal = actions.Goal(handle, controller, server)
        goal.executing()
        action = f"{controller}/{follow.ACTION}"
        with self._lock:
            checked = self._checked.pop(id(handle.request), None)
            reason = self._refuse_reason()  # it may have stalled since the goal callback
            if checked is None or checked[0] is not handle.request:
                reason = "internal: an accepted goal that was not checked"
            if reason is None:
                assert checked is not None
                _, traj, goal.tolerances = checked
                serial = self._new_command(f"{controller} goal #{{}} ({', '.join(traj.names)})")
                mine = tuple(r.serial for r in self._running.values()
                             if r.goal is not None and r.goal.controller == controller)
                replaced = self._preempt(traj.names, self._what[serial], also=mine, trajectory=True)
                self._start(serial, traj, goal)
            else:
                goal.end(actions.ABORT, follow.Result.INVALID_GOAL, reason)
        if reason is not None:
            self._reject(action, reason)
            goal.publish_end()
            return
        self._write_started()
        self._flush_cancels()
        self._emit()
        self._announce_accepted(serial, replaced, f"{len(traj.times)} points, {traj.times[-1]:.3f} s")

    def _on_goal_cancel(self, handle: Any) -> bool:
        """A cancel request: stop the goal's trajectory; its joints hold at the current reference (a lifecycle
        CANCEL through the mux, as joint_trajectory_controller holds). False when the goal has ended already."""
        with self._lock:
            r = next((r for r in self._running.values() if r.goal is not None and r.goal.handle is handle), None)
            if r is None or r.goal is None or r.goal.outcome is not None:
                return False
            self._stop_running(r, "cancelled by its action client", how=actions.CANCELED,
                               code=follow.Result.SUCCESSFUL)
        self._flush_cancels()
        self._emit()
        return True

    def _follow_goals(self, now_s: float, positions: dict[str, float],
                      velocities: dict[str, float]) -> list[tuple[Any, ...]]:
        """Check the running goals against this frame's measured positions: path tolerance while moving, goal
        tolerance after the end (within goal_time_tolerance). Returns the feedback to publish (caller holds the
        lock; the state thread)."""
        feedback: list[tuple[Any, ...]] = []
        slowed = self._slowed_joints()
        for r in list(self._running.values()):
            g = r.goal
            if g is None or g.outcome is not None or g.tolerances is None or not r.traj.anchored:
                continue
            r.slowed |= slowed & set(r.traj.names)
            desired, _ = r.traj.sample(now_s)
            desired_velocity = jtc.velocity(r.traj, now_s)
            actual = {n: positions[n] for n in r.traj.names}
            what = self._what.get(r.serial, "goal")
            if not r.finished:
                why = follow.path_violation(g.tolerances, desired, actual, desired_velocity, velocities)
                if why is not None:
                    self._stop_running(r, f"path tolerance violated: {why}{_slowed_text(r.slowed)}",
                                       code=follow.Result.PATH_TOLERANCE_VIOLATED)
                    continue
            else:
                final = dict(zip(r.traj.names, r.traj.positions[-1], strict=True))
                final_velocity = dict(zip(r.traj.names, r.traj.velocities[-1], strict=True)) if r.traj.velocities \
                    else None
                missing = follow.goal_missing(g.tolerances, final, actual, velocities, final_velocity)
                if missing is None:
                    del self._running[r.serial]
                    worst = max(abs(final[n] - actual[n]) for n in final)
                    fastest = max(abs(velocities[n]) for n in final)
                    self._end_goal(g, actions.SUCCEED, follow.Result.SUCCESSFUL,
                                   f"{what}: every joint within the goal tolerance (largest error {worst:.4f} rad, "
                                   f"largest speed {fastest:.4f} rad/s){_slowed_text(r.slowed)}")
                    continue
                if now_s > r.traj.end + g.tolerances.goal_time:
                    del self._running[r.serial]
                    self._end_goal(g, actions.ABORT, follow.Result.GOAL_TOLERANCE_VIOLATED,
                                   f"{what}: {missing} {g.tolerances.goal_time:g} s after the trajectory's end "
                                   f"(goal_time_tolerance){_slowed_text(r.slowed)}")
                    continue
            feedback.append((g, r.traj.names, [desired[n] for n in r.traj.names], [actual[n] for n in r.traj.names],
                             [velocities[n] for n in r.traj.names], [desired_velocity[n] for n in r.traj.names]))
        return feedback

    def _slowed_joints(self) -> set[str]:
        """The joints whose latest step the daemon's collaborative mode slowed (``JOINT_SLOWED``)."""
        try:
            st = self._daemon.read_new()
        except Exception:  # a damaged status channel: the daemon's own diagnostics report it
            return set()
        if st is None or not st.collaborative:
            return set()
        return {n for n, a in zip(self._names, self._addresses, strict=True) if st.joint_flags[a] & JOINT_SLOWED}

    def _running_by_joint(self) -> dict[str, trajectory.Trajectory]:
        """The trajectory each joint follows now (anchored, not finished), by joint (caller holds the lock)."""
        return {n: r.traj for r in self._running.values() if r.traj.anchored and not r.finished for n in r.traj.names}

    def _publish_controller_states(self, stamp: Time, now_s: float, running: dict[str, trajectory.Trajectory],
                                   measured: tuple[dict[str, float], dict[str, float]], js: Sequence[Any]) -> None:
        """``<controller>/controller_state`` for this frame (state thread), skipped while nobody listens; ``js`` the
        frame's joints in ``_names`` order (their ``ref`` is the output)."""
        listened = [(c, pub) for c, pub in self._state_pubs.items() if pub.get_subscription_count() > 0]
        if not listened:
            return
        output = {n: j.ref for n, j in zip(self._names, js, strict=True)}
        for controller, pub in listened:
            names = [n for n in follow.CONTROLLERS[controller] if n in self._limits]
            desired = jtc.reference(running, names, now_s, output)
            pub.publish(jtc.controller_state(names, stamp, desired, *measured, output))

    def _on_query_state(self, controller: str, request: Any, response: Any) -> Any:
        """``<controller>/query_state``: the controller's trajectory sampled at the requested time (JTC's service)."""
        with self._lock:
            running, measured, refused = self._running_by_joint(), self._measured, self._refuse_reason()
        names = [n for n in follow.CONTROLLERS[controller] if n in self._limits]
        response.name = names
        if measured is None:
            response.success, response.message = False, refused or "no state frame yet"
            return response
        answer = jtc.query(names, running, trajectory.seconds(request.time), *measured)
        response.success, response.message = answer.success, answer.message
        response.position, response.velocity = answer.position, answer.velocity
        return response

    def _end_goal(self, goal: actions.Goal, how: str, code: int, text: str) -> None:
        """Decide a goal's outcome; the client is told once the lock is released (caller holds the lock)."""
        if goal.end(how, code, text):
            self._goal_ends.append(goal)
            level = "info" if how != actions.ABORT else "warn"
            self._events.append(_Event(level, f"{goal.controller} goal {how} ({follow.CODE_NAMES[code]}): {text}",
                                       {"event": f"goal {how}", "command": f"{goal.controller}/{follow.ACTION}",
                                        "code": follow.CODE_NAMES[code], "message": text}))

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
        if not self._guard.put(self._ik_chan, req):
            self._reject(topic, f"{self._ik_name} cannot be written (damaged: `mds-ach repair {self._ik_name}`)")
            return
        with self._lock:
            self._counters.accepted += 1
            self._counters.ik_forwarded += 1

    # ------------------------------------------------------------------------------------ lifecycle

    def _new_command(self, template: str) -> int:
        """A serial for an accepted command, described by ``template`` with ``{}`` for it (caller holds the lock)."""
        self._serial += 1
        self._what[self._serial] = template.format(self._serial)
        while len(self._what) > 4 * WRITE_RECORDS:
            del self._what[next(iter(self._what))]
        return self._serial

    def _stop_running(self, r: _Running, reason: str, keep: tuple[str, ...] = (), cancel: bool = True,
                      how: str = actions.ABORT, code: int = follow.Result.INVALID_GOAL, retract: bool = True,
                      replaced: bool = False) -> str:
        """Stop streaming ``r`` for good and queue a CANCEL for its joints not in ``keep`` (a new command takes
        those); ``cancel`` False when nothing of it was applied. ``retract``: the bridge's frame may take back its
        newest targets first (``_retract``; not when the mux already stopped the joints: a new value would be a new
        command); ``replaced``: a new trajectory takes the joints of ``keep``, which are retracted too (``_replace``).
        Its goal, if any, ends ``how`` with ``code``. Returns its description (caller holds the lock)."""
        what = self._what.get(r.serial, "trajectory")
        self._running.pop(r.serial, None)
        for n in r.traj.names:
            self._intended.pop(n, None)
        names = tuple(n for n in r.traj.names if n not in keep)
        moved = cancel and not r.finished and r.written is not None and bool(names)
        held = self._retract(names) if moved and retract else {}
        kept = tuple(n for n in r.traj.names if n in keep)
        brakes: dict[str, Braking] = {}  # from the newest targets
        taken = self._retract(kept) if replaced and not r.finished and r.written is not None and kept else {}
        if not r.finished and r.due is not None:  # its joints brake from the last target sent (feedforward)
            for n, (q, v) in r.desired.items():
                brakes[n] = self._braking[n] = Braking(q, v, r.due, self._moveto_accel)
                if (n in held or n in taken) and r.previous is not None:
                    self._braking[n] = Braking(*r.previous[1][n], r.previous[0], self._moveto_accel)
                if n in taken:
                    self._retracted[n] = _Retracted(taken[n], self._frame_value(n), brakes[n],
                                                    self._counters.frames)
            self._holds.update(taken)
        if not r.finished:
            self._resync.update(names)
            if held:  # the CANCEL once the daemon took the retraction
                newest = {n: self._frame_value(n) for n in held}
                self._holds.update(held)
                self._stops.append(_Stop(names, f"{what} stopped: {reason}", held, newest, brakes,
                                         self._counters.frames, time.monotonic() + 3 * self._cycle.period + 0.1))
            elif moved:  # it moved them: end their targets where they are
                self._cancels.append((names, f"{what} stopped: {reason}"))
            self._counters.stopped += 1
            self._counters.last_stop = f"{what}: {reason}"
            level = "info" if reason.startswith("preempted") or how == actions.CANCELED else "warn"
            self._events.append(_Event(level, f"{what} stopped ({reason}); it will not continue: send it again",
                                       {"event": "stopped", "command": what, "message": reason}))
        if r.goal is not None:
            self._end_goal(r.goal, how, code, f"{what} stopped: {reason}")
        return what

    def _preempt(self, names: tuple[str, ...], by: str, also: tuple[int, ...] = (), trajectory: bool = False,
                 ) -> list[str]:
        """Stop the trajectories that share a joint with a new command ``by`` on ``names`` (and those of ``also``,
        the preempted goal of the same controller; ``trajectory``: the new command is one, ``_replace``); returns
        their descriptions (caller holds the lock)."""
        taken = set(names)
        self._release_stops(taken)
        hit = [r for r in self._running.values() if r.serial in also or taken & set(r.traj.names)]
        return [self._stop_running(r, f"preempted by {by}", keep=names, replaced=trajectory) for r in hit]

    def _stop_all(self, reason: str) -> list[str]:
        """Stop every trajectory and goal (caller holds the lock)."""
        return [self._stop_running(r, reason) for r in list(self._running.values())]

    def _take_mux_news(self, news: MuxNews) -> None:
        """Refusals of the bridge's frames and new holds: report them, stop the trajectories they hit (caller holds
        the lock; the state thread)."""
        for rf in news.refusals:
            self._counters.mux_refused += rf.count
            self._counters.last_mux_refusal = rf.message
            write = next((w for w in reversed(self._writes) if w.time <= rf.frame_time + 1e-6), None)
            serials = [] if write is None else [s for s in (*write.trajectories, *write.commands) if s]
            new = [s for s in serials if s not in self._reported]
            self._reported.extend(new)
            if new or not serials:  # once per command
                what = " and ".join(self._what.get(s, f"command #{s}") for s in new) or "a frame"
                text = f"the mux refused {what} of the bridge as a whole: {rf.message}; nothing of that frame applied"
                self._events.append(_Event("warn", text, {"event": "refused", "command": what, "message": rf.message,
                                                          "owner": rf.owner, "frames": rf.count}))
            if write is None:
                continue
            for serial in write.trajectories:
                r = self._running.get(serial)
                if r is None:
                    continue
                # Refused at its first frame: nothing of it was applied, nothing to cancel. The frame's arrival time
                # maps it to a write only roughly (a late mux reader stamps its frame after the bridge wrote more):
                # a frame the mux applied made the bridge own its joints, and a refusal changes no owner, so when
                # the bridge owns none of them in the refusal's state, no frame of it moved anything either.
                first = not any(serial in w.trajectories and w.time < write.time for w in self._writes)
                applied = bool(rf.owned & {joints.BY_SHORT[n].address for n in r.traj.names})
                self._stop_running(r, f"refused by the mux: {rf.message}", cancel=applied and not first,
                                   retract=False)
        held, cancelled = self._mux.held()
        stopped = set(held) | set(cancelled)
        for r in list(self._running.values()):
            if r.written is None or r.finished:
                continue
            mine = {joints.BY_SHORT[n].address for n in r.traj.names}
            for h in news.holds:
                hit = h.addresses & mine
                if h.time >= r.written - 1e-6 and hit:
                    # Retracted like the bridge's own stops only when a frame of it released the hold (the mux
                    # handled the hold first): the joints are free, a retraction releases nothing. Still held, the
                    # filter stops them by the same rule (a new value would release the hold).
                    self._stop_running(r, f"{labels(sorted(hit))} {'held' if h.action == 'hold' else h.action + 'led'} "
                                          f"by '{h.source}'", retract=not hit & stopped)
                    break

    def _retract(self, names: tuple[str, ...]) -> dict[str, float]:
        """Where a stop holds ``names`` (caller holds the lock): the daemon's reference now (``mds-state`` ref_r),
        for those whose newest frame value is still waiting for the daemon's next cycle; empty when there is no
        time left before that cycle (``feedforward.retraction_in_time``, the rule every stopping stage shares): the
        daemon takes the newest frame, its last target then.

        Each frame aims at the daemon's next send and the one after (``feedforward.CycleClock.lookahead``): held
        there, a stop travels up to two periods of the motion more than braking needs. The daemon's reference is
        where its last target sent came from: held there the joint brakes from the commanded state onto that target
        (plus the limiter's lead), which the MCB is already running to, so the stop moves it no further than it was
        already going and never reverses it (no target is taken back once sent)."""
        state, frame, seen = self._state, self._frame, self._last_frame_mono
        if state is None or frame is None or seen is None or self._stalled:
            return {}
        if not retraction_in_time(seen, self._cycle.period, time.monotonic()):
            return {}
        addresses = {n: joints.BY_SHORT[n].address for n in names}
        theirs = self._mux.others_own(addresses.values())
        out = {}
        for n, a in addresses.items():
            reference = state.joint[a].ref_r
            if a not in theirs and math.isfinite(reference) and reference != frame.joint[a].ref:
                out[n] = reference
        return out

    def _frame_value(self, name: str) -> float:
        assert self._frame is not None
        return float(self._frame.joint[joints.BY_SHORT[name].address].ref)

    def _take_holds(self) -> bool:
        """Put ``_holds`` into the frame, modes unchanged (not ``_apply``: the joints stay to be re-synced); True if
        there were any (caller holds the write lock and the lock)."""
        if not self._holds or self._frame is None:
            return False
        for n, value in self._holds.items():
            self._frame.joint[joints.BY_SHORT[n].address].ref = value
        self._holds = {}
        return True

    def _check_stops(self, state: MDS_STATE) -> None:
        """The retracted stops, on a state frame after their write (caller holds the lock): each joint whose
        reference the daemon took is CANCELled there; one whose newest value the daemon took first (the retraction
        arrived after its cycle) gets that value back, its last target, and is CANCELled once the daemon has it."""
        for s in list(self._stops):
            if self._counters.frames <= s.frame:
                continue
            late = False
            for n, value in s.hold.items():
                taken = state.joint[joints.BY_SHORT[n].address].ref_r
                newest = s.newest[n]
                if took_newest(taken, newest, value):
                    s.hold[n] = self._holds[n] = newest
                    if n in self._braking and n in s.brakes:
                        self._braking[n] = s.brakes[n]
                    late = True
            if late and time.monotonic() < s.deadline:
                s.frame = self._counters.frames
                continue
            self._stops.remove(s)
            self._cancels.append((s.names, s.reason))
        self._end_stops()

    def _end_stops(self, everything: bool = False) -> None:
        """CANCEL the retracted stops past their deadline (``everything``: all of them, the state stream stalled)
        and tell ``_on_hold`` when none is left (caller holds the lock)."""
        now = time.monotonic()
        for s in [s for s in self._stops if everything or now >= s.deadline]:
            self._stops.remove(s)
            self._cancels.append((s.names, s.reason))
        if not self._stops:
            self._stops_done.notify_all()

    def _release_stops(self, names: set[str]) -> None:
        """A new command takes ``names``: no pending CANCEL may end it (caller holds the lock)."""
        for n in names:
            self._holds.pop(n, None)
            self._retracted.pop(n, None)
        for s in list(self._stops):
            s.names = tuple(n for n in s.names if n not in names)
            for n in names:
                s.hold.pop(n, None)
                s.newest.pop(n, None)
            if not s.names:
                self._stops.remove(s)
        if not self._stops:
            self._stops_done.notify_all()

    def _write_retraction(self) -> None:
        """Write the frame now when it holds a retraction (or its undoing) the state thread has not written."""
        with self._write_lock:
            with self._lock:
                if not self._take_holds():
                    return
                self._writes.append(_Write(time.monotonic(), (), ()))
            self._unsent = not self._guard.put(self._ref_chan, self._frame)  # the next state cycle writes it again
            if not self._unsent:
                with self._lock:
                    self._counters.references_written += 1

    def _flush_cancels(self) -> None:
        """Write a retraction, then send the queued CANCELs: the joints of a stopped trajectory hold where they are.
        Joints another controller owns are left to it (a CANCEL would end its target)."""
        self._write_retraction()
        with self._lock:
            self._end_stops()
            todo, self._cancels = self._cancels, []
        for names, reason in todo:
            addresses = [joints.BY_SHORT[n].address for n in names]
            theirs = self._mux.others_own(addresses)
            mine = [a for a in addresses if a not in theirs]
            if not mine:
                continue
            try:
                lifecycle.send(lifecycle.HOLD_CANCEL, mine, source=self._controller, reason=reason)
            except Exception as exc:  # a broken hold channel must not stop the state thread
                self.get_logger().error(f"could not cancel {labels(mine)} on {mds.MDS_CHAN_HOLD_NAME}: {exc!r}")
                continue
            self.get_logger().info(f"cancelled {labels(mine)}: they hold where they are ({reason})")

    def _emit(self) -> None:
        """Log and publish the events noted under the lock."""
        with self._lock:
            events, self._events = self._events, []
            ends, self._goal_ends = self._goal_ends, []
        for goal in ends:
            goal.publish_end()
        for e in events:
            # One call site per severity: rclpy refuses a call site whose severity changes.
            if e.level == "warn":
                self.get_logger().warning(e.text)
            else:
                self.get_logger().info(e.text)
            self._publish_status(e.doc | {"message": e.doc.get("message", e.text)})

    def _publish_status(self, doc: dict[str, Any]) -> None:
        """One event on mds/command_status (``mds_ach_interfaces/msg/CommandStatus``): what happened to a command,
        and why."""
        try:
            self._status_pub.publish(command_status_msg(doc, self.get_clock().now().to_msg()))
        except Exception:  # noqa: BLE001 - the context is shutting down; the log has the event already
            pass

    def _on_hold(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """mds/hold: stop the bridge's trajectory first (its next frame would release a held joint), then HOLD
        every joint through the mux; success only when the mux acknowledged it."""
        with self._lock:
            stopped = " and ".join(self._stop_all(f"hold requested on {topics.HOLD_SERVICE}"))
            wait = 3 * self._cycle.period + 0.2
        self._emit()
        self._flush_cancels()
        # The CANCELs before the HOLD (the retracted frame would be a new command after it): the daemon takes the
        # retraction within a cycle (``_check_stops``).
        with self._lock:
            self._stops_done.wait_for(lambda: not self._stops, timeout=wait)
        self._flush_cancels()
        ack = self._mux_request(lifecycle.HOLD_HOLD, f"ROS {topics.HOLD_SERVICE}")
        response.success = ack.ok
        if ack.ok and ack.state is not None:
            held = [a for a in range(mds.MDS_JOINT_COUNT) if ack.state.held[a] == MUX_HELD]
            cancelled = [a for a in range(mds.MDS_JOINT_COUNT) if ack.state.held[a] == MUX_CANCELLED]
            every = set(KNOWN_ADDRESSES) <= set(held) | set(cancelled)
            response.message = f"held by the mux: {'every joint' if every else labels(held) or 'no joint'}" + (
                f"; cancelled (only a new command moves them): {labels(cancelled)}" if cancelled else "")
        else:
            response.message = ack.message
        if stopped:
            response.message += f"; {stopped} stopped and will not continue (resume does not restart it)"
        self._log_answer(topics.HOLD_SERVICE, ack.ok, response.message)
        self._publish_status({"event": "hold" if ack.ok else "hold failed", "command": topics.HOLD_SERVICE,
                              "message": response.message})
        return response

    def _mux_request(self, action: int, reason: str) -> lifecycle.Ack:
        """``lifecycle.request`` from a service callback: a damaged ``mds-hold`` or ``mds-mux-state`` is a failed
        answer, never an exception (it would stop the executor, and the node with it)."""
        try:
            return lifecycle.request(action, source=self._controller, reason=reason)
        except ach.AchException as exc:
            fix = f"mds-ach repair {exc.channel}" if exc.channel else "mds-ach repair"
            return lifecycle.Ack(0, False, f"{exc}; run `{fix}`")

    def _log_answer(self, service: str, ok: bool, message: str) -> None:
        if ok:
            self.get_logger().info(f"{service}: {message}")
        else:
            self.get_logger().warning(f"{service}: {message}")

    def _on_resume(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """mds/resume: release held joints through the mux. A trajectory the bridge stopped is not restarted, and
        cancelled joints stay where they are until a new command."""
        ack = self._mux_request(lifecycle.HOLD_RESUME, f"ROS {topics.RESUME_SERVICE}")
        response.success = ack.ok
        if ack.ok and ack.state is not None:
            still = [a for a in range(mds.MDS_JOINT_COUNT) if ack.state.held[a] != MUX_FREE]
            response.message = "resumed: held joints go on to their controllers' targets" + (
                f"; {labels(still)} stay where they are (cancelled: a new command moves them)" if still else "")
            response.message += "; a stopped trajectory is not restarted (send it again)"
        else:
            response.message = ack.message
        self._log_answer(topics.RESUME_SERVICE, ack.ok, response.message)
        self._publish_status({"event": "resume" if ack.ok else "resume failed", "command": topics.RESUME_SERVICE,
                              "message": response.message})
        return response

    # ------------------------------------------------------------------------------------ diagnostics

    def _publish_diagnostics(self) -> None:
        now = time.monotonic()
        with self._lock:
            c = self._counters
            frames_new = c.frames - c.frames_at_last_diag
            rejected_new = c.rejected - c.rejected_at_last_diag
            c.frames_at_last_diag, c.rejected_at_last_diag = c.frames, c.rejected
            moving = [self._what.get(r.serial, "") for r in self._running.values() if not r.finished]
            traj_active = bool(moving)
            refused_new, stopped_new = c.mux_refused - c.mux_refused_at_last_diag, c.stopped - c.stopped_at_last_diag
            c.mux_refused_at_last_diag, c.stopped_at_last_diag = c.mux_refused, c.stopped
            held, cancelled = self._mux.held()
            lifecycle_values = {
                "mux controller": self._controller,
                "mux refusals": str(c.mux_refused),
                "last mux refusal": c.last_mux_refusal,
                "trajectory": "; ".join(moving) if traj_active else "none",
                "goals": "; ".join(self._what.get(r.serial, "") for r in self._running.values() if r.goal) or "none",
                "trajectories stopped": str(c.stopped),
                "last trajectory stop": c.last_stop,
                "held joints": labels(held),
                "cancelled joints": labels(cancelled),
            }
            last_refusal, last_stop = c.last_mux_refusal, c.last_stop
            last = self._last_frame_mono
            stalled = self._stalled
            values: dict[str, str] = {
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
        problems = []
        if rejected_new:
            problems.append(f"{rejected_new} rejected")
        if refused_new:
            problems.append(f"{refused_new} refused by the mux ({last_refusal})")
        if stopped_new:
            problems.append(f"trajectory stopped ({last_stop})")
        cmd_level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        commands = DiagnosticStatus(
            level=cmd_level, name=f"{self.get_name()}: commands", hardware_id="mds",
            message="; ".join(problems) + " since the last report" if problems else "ok",
            values=[KeyValue(key=k, value=v) for k, v in lifecycle_values.items()],
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
        self._mux.close()
        self._daemon.close()


def _slowed_text(slowed: set[str]) -> str:
    """What a goal's result says when collaborative mode slowed it (issue #31): slowed, not failed in silence."""
    if not slowed:
        return ""
    return (f"; slowed by the daemon's collaborative mode (hands and elbows within its Cartesian bound): "
            f"{' '.join(sorted(slowed))}")
