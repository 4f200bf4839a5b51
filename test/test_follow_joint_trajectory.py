"""Issue 19 items 2 and 3: FollowJointTrajectory servers for MoveIt, and a reliable /joint_states with velocities;
issue 27 item 4: joint_trajectory_controller's interface (goal callback checks, EXECUTING, its parameters, its
controller_state, joint_trajectory and query_state endpoints).

The pure parts (goal validation with result codes, tolerances, the velocity estimate) are tested directly; the node
tests run the whole simulated system (``mds-ach start nocan``: daemon, mux, filter, collision gate, IK, bridge), so a
goal goes through the mux, the filter and the gate like every command, and talk to the bridge over DDS from this
process with default-QoS endpoints, as MoveIt and robot_state_publisher do.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from support import REPO
from support.spin import Spinner
from support.system import running_system, state

import mds_ach as mds
from mds_ach.robot import joints
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_MUX_STATE
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED
from mds_ach_bridge import follow, jtc
from mds_ach_bridge.limits import load_limits
from mds_ach_bridge.velocity import FiniteDifference

LIMITS = {"LSP": (-1.9, 1.0), "LEP": (-2.4, 0.0), "RSP": (-1.9, 1.0), "NKY": (-1.0, 1.0)}
Result = follow.Result


def _goal(names: list[str], points: list[tuple[float, list[float]]], stamp: float = 0.0,
          velocities: list[list[float]] | None = None):
    from control_msgs.action import FollowJointTrajectory
    from trajectory_msgs.msg import JointTrajectoryPoint

    goal = FollowJointTrajectory.Goal()
    goal.trajectory.joint_names = names
    goal.trajectory.header.stamp.sec, goal.trajectory.header.stamp.nanosec = int(stamp), int(stamp % 1 * 1e9)
    for i, (t, pos) in enumerate(points):
        p = JointTrajectoryPoint(positions=pos, velocities=[] if velocities is None else velocities[i])
        p.time_from_start.sec, p.time_from_start.nanosec = int(t), int(round(t % 1 * 1e9))
        goal.trajectory.points.append(p)
    return goal


# --------------------------------------------------------------------------------------------- the pure parts


def test_controllers_are_the_moveit_names_and_cover_the_model_joints() -> None:
    assert follow.CONTROLLERS["head_controller"] == ("WST", "NKY", "NKP1", "NKP2", "NKR")
    assert sorted(j for js in follow.CONTROLLERS.values() for j in js) == sorted(joints.MODEL_JOINTS)
    doc = yaml.safe_load((REPO / "config" / "moveit_controllers.yaml").read_text())
    manager = doc["moveit_simple_controller_manager"]
    assert manager["controller_names"] == list(follow.CONTROLLERS)
    for name, names in follow.CONTROLLERS.items():
        c = manager[name]
        assert (c["type"], c["action_ns"], c["joints"]) == ("FollowJointTrajectory", follow.ACTION, list(names))
    assert doc["moveit_controller_manager"] == "moveit_simple_controller_manager/MoveItSimpleControllerManager"


@pytest.mark.parametrize(
    ("controller", "names", "points", "code", "reason"),
    [
        ("left_arm_controller", ["LSP", "XYZ"], [(1.0, [0.0, -0.5])], Result.INVALID_JOINTS, "'XYZ' not joints of"),
        ("left_arm_controller", ["LSP", "RSP"], [(1.0, [0.0, 0.0])], Result.INVALID_JOINTS, "'RSP' not joints of"),
        ("left_arm_controller", ["LSP", "LSP"], [(1.0, [0.0, 0.0])], Result.INVALID_JOINTS, "appears twice"),
        ("left_arm_controller", [], [(1.0, [])], Result.INVALID_JOINTS, "joint_names is empty"),
        ("left_arm_controller", ["LSP", "LEP"], [(1.0, [0.0, -0.5]), (0.5, [0.1, -0.6])], Result.INVALID_GOAL,
         "point 1: time_from_start 0.5 s is not after the previous point"),
        ("left_arm_controller", ["LSP", "LEP"], [(1.0, [0.0, 0.5])], Result.INVALID_GOAL,
         "LEP: position 0.5 rad is outside the limits"),
        ("left_arm_controller", ["LSP", "LEP"], [], Result.INVALID_GOAL, "no points"),
        ("head_controller", ["NKY"], [(1.0, [math.nan])], Result.INVALID_GOAL, "not finite"),
    ],
)
def test_bad_goals_get_a_result_code_and_the_reason(controller: str, names: list[str], points: list,
                                                    code: int, reason: str) -> None:
    with pytest.raises(follow.GoalError, match=reason) as info:
        follow.validate(controller, _goal(names, points), 100.0, LIMITS, allow_partial=True)
    assert info.value.code == code


def test_a_goal_that_ended_before_it_arrived_is_an_old_header_timestamp() -> None:
    with pytest.raises(follow.GoalError, match="ended 2.000 s ago") as info:
        follow.validate("left_arm_controller", _goal(["LSP"], [(1.0, [0.1])], stamp=97.0), 100.0, LIMITS,
                        allow_partial=True)
    assert info.value.code == Result.OLD_HEADER_TIMESTAMP
    traj = follow.validate("left_arm_controller", _goal(["LSP"], [(1.0, [0.1])], stamp=99.5), 100.0, LIMITS,
                           allow_partial=True)
    assert traj.start == 99.5 and traj.names == ("LSP",)


def test_tolerances_follow_joint_trajectory_controller_rules() -> None:
    """> 0 used, 0 = the server's default, -1 = not checked; goal_time_tolerance 0 = the default."""
    from control_msgs.msg import JointTolerance

    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5])])
    goal.goal_tolerance = [JointTolerance(name="LSP", position=0.1), JointTolerance(name="LEP", position=-1.0,
                                                                                      velocity=0.5)]
    goal.path_tolerance = [JointTolerance(name="LEP", position=0.3)]
    tol = follow.tolerances(["LSP", "LEP"], goal, {}, dict.fromkeys(("LSP", "LEP"), follow.Tolerance(0.02, 0.2)), 2.0)
    assert tol.goal == {"LSP": follow.Tolerance(0.1, 0.2), "LEP": follow.Tolerance(math.inf, 0.5)}
    assert tol.path == {"LSP": follow.Tolerance(), "LEP": follow.Tolerance(0.3, math.inf)}
    assert tol.goal_time == 2.0
    assert follow.path_violation(tol, {"LSP": 1.0, "LEP": 0.0}, {"LSP": 0.0, "LEP": -0.29}) is None
    assert "LEP: position error +0.3100 rad exceeds the path tolerance 0.3" in str(
        follow.path_violation(tol, {"LSP": 1.0, "LEP": 0.0}, {"LSP": 0.0, "LEP": -0.31}))
    goal.path_tolerance = [JointTolerance(name="LEP", position=0.3, velocity=0.2)]
    vtol = follow.tolerances(["LSP", "LEP"], goal, {}, {}, 2.0)
    assert follow.path_violation(vtol, {"LEP": 0.0}, {"LEP": 0.0}, {"LEP": 0.5}, {"LEP": 0.35}) is None
    assert "LEP: velocity error +0.2500 rad/s exceeds the path tolerance 0.2 rad/s" in str(
        follow.path_violation(vtol, {"LEP": 0.0}, {"LEP": 0.0}, {"LEP": 0.5}, {"LEP": 0.25}))
    final = {"LSP": 0.5, "LEP": -1.0}
    assert follow.goal_missing(tol, final, {"LSP": 0.45, "LEP": 0.0}, {"LSP": 0.0, "LEP": 0.4}) is None
    assert "LSP: position error" in str(follow.goal_missing(tol, final, {"LSP": 0.3, "LEP": 0.0}, {"LSP": 0, "LEP": 0}))
    assert "LEP: velocity" in str(follow.goal_missing(tol, final, {"LSP": 0.5, "LEP": 0.0}, {"LSP": 0, "LEP": 0.6}))
    goal.goal_time_tolerance.sec = 5
    assert follow.tolerances(["LSP"], goal, {}, {}, 2.0).goal_time == 5.0


@pytest.mark.parametrize("field", ["path_tolerance", "goal_tolerance"])
@pytest.mark.parametrize("what", ["position", "velocity", "acceleration"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, -0.5, -2.0, -1e-9])
def test_a_tolerance_that_means_nothing_is_an_invalid_goal(field: str, what: str, value: float) -> None:
    """Issue #25 item 9: NaN (every comparison false: SUCCESSFUL however far away), +-Inf and negative values other
    than control_msgs' -1 ("no limit") were taken; they are refused with the entry and the value."""
    from control_msgs.msg import JointTolerance

    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5])])
    setattr(goal, field, [JointTolerance(name="LSP", position=0.1), JointTolerance(name="LEP", **{what: value})])
    with pytest.raises(follow.GoalError, match=rf"^{field}\[1\] \(LEP\): {what} {value:g} is not a tolerance: "
                                               r"give > 0 rad.*, 0 for the default or -1 for none$") as info:
        follow.tolerances(["LSP", "LEP"], goal, {}, {"LSP": follow.Tolerance(0.02)}, 2.0)
    assert info.value.code == Result.INVALID_GOAL


def test_the_documented_special_tolerances_stay_valid() -> None:
    """0 = the default, -1 = none (float32-rounded too, as joint_trajectory_controller compares it), > 0 used; a
    negative goal_time_tolerance is refused, 0 is the default."""
    from control_msgs.msg import JointTolerance

    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5])])
    goal.goal_tolerance = [JointTolerance(name="LSP", position=0.0, velocity=-1.0, acceleration=-1.0),
                           JointTolerance(name="LEP", position=-0.99999997, velocity=0.3, acceleration=0.0)]
    tol = follow.tolerances(["LSP", "LEP"], goal, {}, dict.fromkeys(("LSP", "LEP"), follow.Tolerance(0.02, 0.2)), 2.0)
    assert tol.goal == {"LSP": follow.Tolerance(0.02, math.inf), "LEP": follow.Tolerance(math.inf, 0.3)}
    goal.goal_time_tolerance.sec, goal.goal_time_tolerance.nanosec = -1, 500_000_000
    with pytest.raises(follow.GoalError, match=r"^goal_time_tolerance -0\.5 s is negative") as info:
        follow.tolerances(["LSP", "LEP"], goal, {}, {}, 2.0)
    assert info.value.code == Result.INVALID_GOAL


ARM = list(joints.LEFT_ARM)
ARM_LIMITS = {n: (-2.4, 1.0) for n in joints.MODEL_JOINTS}


def test_a_goal_for_part_of_a_controller_is_refused_unless_allow_partial_joints_goal() -> None:
    """Issue #27 item 4: joint_trajectory_controller refuses a goal that leaves joints of the controller out unless
    allow_partial_joints_goal (default false); a disabled joint (not in the limits) need not be given."""
    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5])])
    with pytest.raises(follow.GoalError, match=r"^LSR LSY LWY LWR of left_arm_controller left out: give every joint "
                                               r"of the controller \(allow_partial_joints_goal is false\)$") as info:
        follow.validate("left_arm_controller", goal, 100.0, ARM_LIMITS)
    assert info.value.code == Result.INVALID_JOINTS
    assert follow.validate("left_arm_controller", goal, 100.0, ARM_LIMITS, allow_partial=True).names == ("LSP", "LEP")
    full = _goal(ARM, [(1.0, [0.0, 0.0, 0.0, -0.5, 0.0, 0.0])])
    assert follow.validate("left_arm_controller", full, 100.0, ARM_LIMITS).names == tuple(ARM)
    without_lwr = {n: r for n, r in ARM_LIMITS.items() if n != "LWR"}  # LWR disabled in the joint table
    assert follow.validate("left_arm_controller", _goal(ARM[:5], [(1.0, [0.0, 0.0, 0.0, -0.5, 0.0])]), 100.0,
                           without_lwr).names == tuple(ARM[:5])


def test_a_last_point_that_moves_is_refused_unless_allow_nonzero_velocity_at_trajectory_end() -> None:
    """Issue #27 item 4: as joint_trajectory_controller on Jazzy, a trajectory ends at rest unless allowed."""
    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5]), (2.0, [0.1, -0.6])],
                 velocities=[[0.1, -0.1], [0.0, -0.05]])
    with pytest.raises(follow.GoalError, match=r"^the last point's velocity is not zero \(LEP -0.05 rad/s\): a "
                                               r"trajectory ends at rest \(allow_nonzero_velocity_at_trajectory_end "
                                               r"is false\)$") as info:
        follow.validate("left_arm_controller", goal, 100.0, LIMITS, allow_partial=True)
    assert info.value.code == Result.INVALID_GOAL
    traj = follow.validate("left_arm_controller", goal, 100.0, LIMITS, allow_partial=True, allow_nonzero_end=True)
    assert traj.velocities is not None and traj.velocities[-1] == (0.0, -0.05)


def test_a_goal_timed_faster_than_the_published_velocity_is_refused() -> None:
    """Issue #27 item 4: a goal faster than the joints follow was stretched downstream and reported SUCCESSFUL 1.37 s
    late; it is refused with the joint, the speed it needs and the limit (point velocities and mean speeds)."""
    speeds = {"LSP": 1.5, "LEP": 1.5}
    fast = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5]), (1.5, [0.9, -0.5])])
    with pytest.raises(follow.GoalError, match=r"^LSP: 1\.800 rad/s needed between points 0 and 1 \(0\.900 rad in "
                                               r"0\.500 s\), over the 1\.5 rad/s the joint can follow") as info:
        follow.validate("left_arm_controller", fast, 100.0, LIMITS, allow_partial=True, speeds=speeds)
    assert info.value.code == Result.INVALID_GOAL
    at_limit = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5]), (1.6, [0.9, -0.5])])  # 1.5 rad/s exactly
    follow.validate("left_arm_controller", at_limit, 100.0, LIMITS, allow_partial=True, speeds=speeds)
    declared = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5]), (3.0, [0.5, -0.5]), (4.0, [0.6, -0.5])],
                     velocities=[[0.0, 0.0], [1.7, 0.0], [0.0, 0.0]])
    with pytest.raises(follow.GoalError, match=r"^LSP: point 1's velocity \+1\.700 rad/s is over the 1\.5 rad/s"):
        follow.validate("left_arm_controller", declared, 100.0, {"LSP": (-5.0, 5.0), "LEP": (-2.4, 0.0)},
                        allow_partial=True, speeds=speeds)


def test_jtc_parameters_are_the_per_joint_defaults_and_success_needs_the_joints_stopped() -> None:
    """constraints.<joint>.trajectory / .goal are the per-joint defaults of a goal's 0 tolerances,
    constraints.stopped_velocity_tolerance the goal velocity tolerance, constraints.goal_time 0 = no limit."""
    values = jtc.defaults()
    assert (values[jtc.PARTIAL], values[jtc.NONZERO_END], values[jtc.STOPPED]) == (False, False, 0.01)
    values |= {jtc.path_param("LEP"): 0.3, jtc.goal_param("LSP"): 0.05, jtc.GOAL_TIME: 0.0}
    settings = jtc.Settings.from_values(values)
    goal = _goal(["LSP", "LEP"], [(1.0, [0.0, -0.5])])
    tol = follow.tolerances(["LSP", "LEP"], goal, settings.path, settings.goal, settings.goal_time)
    assert tol.path == {"LSP": follow.Tolerance(), "LEP": follow.Tolerance(0.3)}
    assert tol.goal == {"LSP": follow.Tolerance(0.05, 0.01), "LEP": follow.Tolerance(0.02, 0.01)}
    assert tol.goal_time == math.inf
    final = {"LSP": 0.0, "LEP": -0.5}
    at_target = {"LSP": 0.0, "LEP": -0.5}
    assert "LEP: velocity +0.0300 rad/s" in str(follow.goal_missing(tol, final, at_target, {"LSP": 0.0, "LEP": 0.03}))
    assert follow.goal_missing(tol, final, at_target, {"LSP": 0.0, "LEP": 0.009}) is None
    # A last point that moves (allowed by the parameter): the measured velocity is compared with it.
    assert follow.goal_missing(tol, final, at_target, {"LSP": 0.0, "LEP": 0.2}, {"LSP": 0.0, "LEP": 0.2}) is None


def test_query_state_samples_the_running_trajectory_as_jtc_answers() -> None:
    from mds_ach_bridge import trajectory

    traj = trajectory.build(["LSP"], [(0.0, [0.0], []), (2.0, [1.0], [])], 10.0, {"LSP": (-2.0, 2.0)})
    measured, rate = {"LSP": 0.3, "LEP": -0.5}, {"LSP": 0.0, "LEP": 0.0}
    idle = jtc.query(["LSP", "LEP"], {}, 11.0, measured, rate)
    assert (idle.success, idle.position) == (True, [0.3, -0.5])
    mid = jtc.query(["LSP", "LEP"], {"LSP": traj}, 11.0, measured, rate)
    assert mid.success and mid.position == pytest.approx([0.5, -0.5]) and mid.velocity == pytest.approx([0.5, 0.0])
    late = jtc.query(["LSP", "LEP"], {"LSP": traj}, 12.5, measured, rate)
    assert not late.success and "0.500 s after the running trajectory's end" in late.message
    early = jtc.query(["LSP", "LEP"], {"LSP": traj}, 9.0, measured, rate)
    assert not early.success and "before the running trajectory's start" in early.message


def test_velocity_is_the_finite_difference_over_the_frames_own_stamps() -> None:
    fd = FiniteDifference()
    assert fd.update(10.0, [0.0, 1.0]) == [0.0, 0.0]  # first frame: no estimate
    assert fd.update(10.01, [0.01, 0.98]) == pytest.approx([1.0, -2.0])
    assert fd.update(10.04, [0.04, 0.98]) == pytest.approx([1.0, 0.0])  # two frames missed: the stamps tell
    assert fd.update(10.04, [0.05, 0.98]) == [0.0, 0.0]  # same stamp (restarted daemon): no spike
    assert fd.update(12.0, [0.10, 0.98]) == [0.0, 0.0]  # a stall: no average over the gap


# --------------------------------------------------------------------------------------------- the running system


class Probe(Spinner):
    """A client node in this process: a default-QoS /joint_states subscriber and FollowJointTrajectory clients."""

    def __init__(self) -> None:
        from control_msgs.action import FollowJointTrajectory
        from rclpy.action import ActionClient
        from sensor_msgs.msg import JointState

        self.open_node("fjt_probe")
        self.runtime = Path()  # the system's runtime directory (logs), set by the fixture
        self.states: list = []
        self.node.create_subscription(JointState, "/joint_states", self.states.append, 10)  # default QoS: reliable
        self.clients = {c: ActionClient(self.node, FollowJointTrajectory, f"/{c}/{follow.ACTION}")
                        for c in follow.CONTROLLERS}
        for name, client in self.clients.items():
            self.spin_until(client.server_is_ready, 60.0, f"the {name} action server")
        self.spin_until(lambda: self.states, 30.0, "/joint_states with a default-QoS subscriber")

    def request(self, controller: str, goal, feedback: list | None = None):
        """Send a goal; returns its handle once the server answered (accepted or not)."""
        sent = self.clients[controller].send_goal_async(
            goal, feedback_callback=None if feedback is None else lambda fb: feedback.append(fb.feedback))
        self.spin_until(sent.done, 20.0, "the goal response")
        handle = sent.result()
        assert handle is not None
        return handle

    def send(self, controller: str, goal, feedback: list | None = None):
        """Send a goal that must be accepted; returns its handle."""
        handle = self.request(controller, goal, feedback)
        assert handle.accepted, f"goal rejected; log:\n{self.bridge_log()}"
        return handle

    def bridge_log(self) -> str:
        path = self.runtime / "bridge.log"
        return path.read_text() if path.is_file() else ""

    def result(self, handle, timeout: float = 30.0):
        got = handle.get_result_async()
        self.spin_until(got.done, timeout, "the goal's result")
        return got.result()

    def position(self, name: str) -> float:
        msg = self.states[-1]
        return float(msg.position[list(msg.name).index(name)])

    def close(self) -> None:
        for client in self.clients.values():
            client.destroy()
        self.close_node()


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Probe]:
    runtime = tmp_path_factory.mktemp("fjt")
    with running_system(runtime):
        p = Probe()
        p.runtime = runtime
        try:
            yield p
        finally:
            p.close()


def _arm_goal(moves: dict[str, list[float]], times: list[float], controller: str = "left_arm_controller"):
    """A goal for every joint of ``controller`` (allow_partial_joints_goal is false): the joints of ``moves`` go
    through their positions at ``times``, the others stay at the daemon's reference."""
    names = list(follow.CONTROLLERS[controller])
    st = state()
    rows = [[moves[n][i] if n in moves else st.joint[mds.BY_SHORT[n].address].ref for n in names]
            for i in range(len(times))]
    return _goal(names, list(zip(times, rows, strict=True)))


def _state_rate(seconds: float) -> float:
    from mds_ach.tools.launcher import state_rate

    measured = state_rate(seconds)
    assert measured is not None
    return measured[0]


@pytest.mark.ros
@pytest.mark.slow
def test_a_default_qos_subscriber_gets_joint_states_at_the_state_rate_with_velocities(probe: Probe) -> None:
    window = 3.0
    rate: list[float] = []
    counter = threading.Thread(target=lambda: rate.append(_state_rate(window)))
    probe.states.clear()
    counter.start()
    probe.spin_until(lambda: not counter.is_alive(), window + 10, "the state rate")
    counter.join()
    got = len(probe.states) / window
    assert rate[0] > 5 and got >= 0.8 * rate[0], f"{got:.1f} /joint_states per s, {rate[0]:.1f} state frames per s"
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in probe.states]
    assert len(set(stamps)) == len(stamps), "a state frame was published twice"
    last = probe.states[-1]
    assert len(last.velocity) == len(last.name) == len(joints.MODEL_JOINTS) and not last.effort


@pytest.mark.ros
@pytest.mark.slow
def test_a_goal_slowed_by_collaborative_mode_says_so_in_its_result(probe: Probe) -> None:
    """Issue #31: in collaborative mode the daemon slows a fast goal (hands and elbows within 250 mm/s); the goal
    still succeeds, and its result says it was slowed and which joints, instead of saying nothing. (Runs first of
    the goals: from the start pose, the move is clear of the body.)"""
    from action_msgs.msg import GoalStatus
    from control_msgs.action import FollowJointTrajectory

    from mds_ach.tools.safetycmd import send

    start = {n: probe.position(n) for n in ("LSP", "LEP")}
    assert send(mds.MDS_CMD_MODE, 1.0, 10.0)[0]
    try:
        lo, hi = load_limits()["LEP"]
        end = [start["LSP"] - 0.7, max(lo + 0.1, min(hi - 0.1, start["LEP"] - 0.7))]
        goal = _arm_goal({"LSP": [end[0]], "LEP": [end[1]]}, [1.0])  # 0.7 rad/s on both: the hand above 250 mm/s
        goal.goal_time_tolerance.sec = 20
        res = probe.result(probe.send("left_arm_controller", goal), 40.0)
        assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.error_string
        assert res.result.error_code == FollowJointTrajectory.Result.SUCCESSFUL
        text = res.result.error_string
        assert "slowed by the daemon's collaborative mode" in text and "LSP" in text, text
    finally:
        assert send(mds.MDS_CMD_MODE, 0.0, 10.0)[0]
        back = _arm_goal({"LSP": [start["LSP"]], "LEP": [start["LEP"]]}, [2.0])  # the next tests start there
        back.goal_time_tolerance.sec = 10
        assert probe.result(probe.send("left_arm_controller", back), 30.0).status == GoalStatus.STATUS_SUCCEEDED


@pytest.mark.ros
@pytest.mark.slow
def test_a_two_point_goal_for_lsp_lep_succeeds_within_the_goal_tolerance(probe: Probe) -> None:
    from control_msgs.action import FollowJointTrajectory
    from control_msgs.msg import JointTolerance

    start = {n: probe.position(n) for n in ("LSP", "LEP")}
    lo, hi = load_limits()["LEP"]
    mid = [start["LSP"] - 0.2, max(lo + 0.1, min(hi - 0.1, start["LEP"] - 0.3))]
    end = [start["LSP"] - 0.4, max(lo + 0.1, min(hi - 0.1, start["LEP"] - 0.6))]
    goal = _arm_goal({"LSP": [mid[0], end[0]], "LEP": [mid[1], end[1]]}, [1.0, 2.0])
    goal.goal_tolerance = [JointTolerance(name=n, position=0.01) for n in ("LSP", "LEP")]
    feedback: list = []
    handle = probe.send("left_arm_controller", goal, feedback)
    sent = time.monotonic()
    res = probe.result(handle)
    took = time.monotonic() - sent
    from action_msgs.msg import GoalStatus

    assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.error_string
    assert res.result.error_code == FollowJointTrajectory.Result.SUCCESSFUL
    assert "within the goal tolerance" in res.result.error_string
    # Success only once stopped (constraints.stopped_velocity_tolerance, 0.01 rad/s): the speed it was declared at.
    speed = float(res.result.error_string.split("largest speed ")[1].split(" rad/s")[0])
    assert speed <= 0.01, res.result.error_string
    probe.spin_until(lambda: len(probe.states) > 2, 5.0, "/joint_states")
    for name, want in zip(("LSP", "LEP"), end, strict=True):
        assert abs(state().joint[mds.BY_SHORT[name].address].pos - want) <= 0.01, name
    # Feedback at the state rate: one per state frame while the goal ran (2 s and the settling time).
    assert feedback and list(feedback[-1].joint_names) == list(joints.LEFT_ARM)
    stamps = [f.header.stamp.sec + f.header.stamp.nanosec * 1e-9 for f in feedback]
    assert len(set(stamps)) == len(stamps) and stamps == sorted(stamps)
    measured = _state_rate(1.0)
    assert len(feedback) >= 0.8 * measured * 2.0, f"{len(feedback)} feedback messages in {took:.2f} s at " \
                                                   f"{measured:.1f} frames/s"
    fb = feedback[len(feedback) // 2]
    assert [d - a for d, a in zip(fb.desired.positions, fb.actual.positions, strict=True)] == pytest.approx(
        list(fb.error.positions))


ARM6 = ["LSP", "LSR", "LSY", "LEP", "LWY", "LWR"]
REST = [0.0, 0.0, 0.0, -0.5, 0.0, 0.0]  # inside every left-arm joint's limits (LEP's exclude 0)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize(
    ("names", "points", "velocities", "code", "reason"),
    [
        (["LSP", "XYZ"], [(1.0, [0.0, -0.5])], None, "INVALID_JOINTS", "'XYZ' not joints of left_arm_controller"),
        (["LSP", "LEP"], [(1.0, [0.0, -0.5])], None, "INVALID_JOINTS",
         "LSR LSY LWY LWR of left_arm_controller left out"),
        (ARM6, [(1.0, REST), (0.5, REST)], None, "INVALID_GOAL", "is not after the previous point"),
        (ARM6, [(1.0, [0.0, 0.0, 0.0, 2.5, 0.0, 0.0])], None, "INVALID_GOAL",
         "LEP: position 2.5 rad is outside the limits"),
        (ARM6, [(1.0, REST)], [[0.0, 0.0, 0.0, -0.1, 0.0, 0.0]], "INVALID_GOAL",
         "the last point's velocity is not zero (LEP -0.1 rad/s)"),
        (ARM6, [(1.0, REST), (1.2, [0.8, 0.0, 0.0, -0.5, 0.0, 0.0])], None, "INVALID_GOAL",
         "LSP: 4.000 rad/s needed between points 0 and 1 (0.800 rad in 0.200 s), over the 1.02857 rad/s"),
    ],
)
def test_a_bad_goal_is_rejected_in_the_goal_callback_with_the_reason_logged(
        probe: Probe, names: list[str], points: list, velocities: list | None, code: str, reason: str) -> None:
    """Issue #27 item 4: as joint_trajectory_controller, a goal the bridge cannot run is rejected in the goal
    callback (before: accepted, then aborted); the reason is in the bridge's log and on mds/command_status."""
    before = state().joint[mds.LSP].ref
    handle = probe.request("left_arm_controller", _goal(names, points, velocities=velocities))
    assert not handle.accepted
    probe.spin_until(lambda: f"goal rejected: {code}: " in probe.bridge_log() and reason in probe.bridge_log(), 10.0,
                     "the reason in the bridge's log")
    assert state().joint[mds.LSP].ref == before


@pytest.mark.ros
@pytest.mark.slow
def test_a_partial_goal_runs_when_allow_partial_joints_goal_is_set(probe: Probe) -> None:
    """The parameter can be changed while running, as in joint_trajectory_controller."""
    from action_msgs.msg import GoalStatus
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    client = probe.node.create_client(SetParameters, "/mds_bridge/set_parameters")
    probe.spin_until(client.service_is_ready, 20.0, "the bridge's set_parameters")

    def allow(value: bool) -> None:
        req = SetParameters.Request(parameters=[Parameter(name=jtc.PARTIAL, value=ParameterValue(
            type=ParameterType.PARAMETER_BOOL, bool_value=value))])
        fut = client.call_async(req)
        probe.spin_until(fut.done, 10.0, "set_parameters")
        assert fut.result().results[0].successful

    nky = probe.position("NKY")
    target = nky + 0.2 if nky + 0.2 < load_limits()["NKY"][1] else nky - 0.2
    assert not probe.request("head_controller", _goal(["NKY"], [(1.0, [target])])).accepted
    allow(True)
    try:
        res = probe.result(probe.send("head_controller", _goal(["NKY"], [(1.0, [target])])))
    finally:
        allow(False)
    assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.error_string
    client.destroy()


@pytest.mark.ros
@pytest.mark.slow
def test_a_goal_with_a_nan_tolerance_is_refused_and_moves_nothing(probe: Probe) -> None:
    """The campaign's case: a NaN goal tolerance made a goal SUCCESSFUL while the arm was 0.47 rad away. Now the
    goal is rejected in the goal callback with the reason in the bridge's log, and nothing moves."""
    from control_msgs.msg import JointTolerance

    lsp = probe.position("LSP")
    target = lsp + 0.5 if lsp + 0.5 < load_limits()["LSP"][1] else lsp - 0.5
    before = state().joint[mds.LSP].ref
    goal = _arm_goal({"LSP": [target]}, [3.0])
    goal.goal_tolerance = [JointTolerance(name="LSP", position=math.nan)]
    assert not probe.request("left_arm_controller", goal).accepted
    probe.spin_until(lambda: "goal rejected: INVALID_GOAL: goal_tolerance[0] (LSP): position nan is not a tolerance: "
                             "give > 0 rad, 0 for the default or -1 for none" in probe.bridge_log(), 10.0,
                     "the reason in the log")
    time.sleep(0.5)  # what a wrongly accepted goal would have started by now
    assert state().joint[mds.LSP].ref == before


def _mux_held(address: int) -> int:
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as ch:
        st = ch.latest()
    assert st is not None
    return int(st.held[address])


@pytest.mark.ros
@pytest.mark.slow
def test_cancel_holds_the_arm_and_a_new_goal_preempts(probe: Probe) -> None:
    from action_msgs.msg import GoalStatus

    lsp = probe.position("LSP")
    far = [(4.0, [lsp + 0.6])] if lsp + 0.6 < load_limits()["LSP"][1] else [(4.0, [lsp - 0.6])]
    handle = probe.send("left_arm_controller", _arm_goal({"LSP": far[0][1]}, [4.0]))
    probe.spin_until(lambda: abs(probe.position("LSP") - lsp) > 0.05, 15.0, "LSP moving")
    cancel = handle.cancel_goal_async()
    probe.spin_until(cancel.done, 10.0, "the cancel response")
    res = probe.result(handle, 10.0)
    assert res.status == GoalStatus.STATUS_CANCELED and "cancelled by its action client" in res.result.error_string
    probe.spin_until(lambda: _mux_held(mds.LSP) == MUX_CANCELLED, 10.0, "LSP held (cancelled) by the mux")
    time.sleep(0.5)  # the filter and the daemon settle on the held reference
    held = state().joint[mds.LSP].ref
    time.sleep(1.0)
    assert state().joint[mds.LSP].ref == pytest.approx(held, abs=1e-9), "LSP went on after the cancel"
    assert abs(held - far[0][1][0]) > 0.1, "the cancel came too late to show the hold"

    # Preemption: a second goal on the same controller ends the first one, and then runs to success.
    lsp = probe.position("LSP")
    first = probe.send("left_arm_controller", _arm_goal({"LSP": [lsp + (0.5 if lsp < 0 else -0.5)]}, [4.0]))
    probe.spin_until(lambda: abs(probe.position("LSP") - lsp) > 0.03, 15.0, "LSP moving")
    second = probe.send("left_arm_controller", _arm_goal({"LSP": [lsp]}, [1.0]))
    res = probe.result(first, 10.0)
    assert res.status == GoalStatus.STATUS_ABORTED and "preempted by left_arm_controller goal" in \
        res.result.error_string, res.result
    res = probe.result(second)
    assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.error_string


@pytest.mark.ros
@pytest.mark.slow
def test_the_three_action_servers_are_on_the_graph(probe: Probe) -> None:
    from rclpy.action import get_action_names_and_types

    found = dict(get_action_names_and_types(probe.node))
    for c in follow.CONTROLLERS:
        assert found.get(f"/{c}/{follow.ACTION}") == ["control_msgs/action/FollowJointTrajectory"], found


@pytest.mark.ros
@pytest.mark.slow
def test_the_status_is_executing_while_the_goal_runs(probe: Probe) -> None:
    """Issue #27 item 4: the goal's status is EXECUTING from its start (before: ACCEPTED until the end, EXECUTING
    only as it ended), as the action status topic and the client's handle show."""
    from action_msgs.msg import GoalStatus, GoalStatusArray

    statuses: list = []
    sub = probe.node.create_subscription(GoalStatusArray, f"/left_arm_controller/{follow.ACTION}/_action/status",
                                         statuses.append, 10)
    lsp = probe.position("LSP")
    target = lsp + 0.3 if lsp + 0.3 < load_limits()["LSP"][1] else lsp - 0.3
    handle = probe.send("left_arm_controller", _arm_goal({"LSP": [target]}, [2.0]))
    uuid = bytes(handle.goal_id.uuid)

    def status() -> int | None:
        for arr in reversed(statuses):
            for s in arr.status_list:
                if bytes(s.goal_info.goal_id.uuid) == uuid:
                    return int(s.status)
        return None

    probe.spin_until(lambda: status() == GoalStatus.STATUS_EXECUTING, 5.0, "status EXECUTING")
    assert abs(probe.position("LSP") - target) > 0.1, "EXECUTING only came at the end"
    res = probe.result(handle)
    assert res.status == GoalStatus.STATUS_SUCCEEDED, res.result.error_string
    probe.node.destroy_subscription(sub)


@pytest.mark.ros
@pytest.mark.slow
def test_controller_state_query_state_and_the_controllers_joint_trajectory_topic(probe: Probe) -> None:
    """Issue #27 item 4: joint_trajectory_controller's ~/controller_state (one per state frame), ~/query_state and
    ~/joint_trajectory, for each controller."""
    from control_msgs.msg import JointTrajectoryControllerState
    from control_msgs.srv import QueryTrajectoryState
    from trajectory_msgs.msg import JointTrajectory

    states: list = []
    sub = probe.node.create_subscription(JointTrajectoryControllerState, "/left_arm_controller/controller_state",
                                         states.append, 10)
    pub = probe.node.create_publisher(JointTrajectory, "/left_arm_controller/joint_trajectory", 10)
    query = probe.node.create_client(QueryTrajectoryState, "/left_arm_controller/query_state")
    probe.spin_until(query.service_is_ready, 20.0, "/left_arm_controller/query_state")
    probe.spin_until(lambda: len(states) >= 3 and pub.get_subscription_count() > 0, 20.0, "controller_state")
    idle = states[-1]
    assert list(idle.joint_names) == list(joints.LEFT_ARM) and idle.speed_scaling_factor == 1.0
    assert list(idle.error.positions) == pytest.approx(
        [r - f for r, f in zip(idle.reference.positions, idle.feedback.positions, strict=True)])

    def ask(t: float):
        req = QueryTrajectoryState.Request()
        req.time.sec, req.time.nanosec = int(t), int(t % 1 * 1e9)
        fut = query.call_async(req)
        probe.spin_until(fut.done, 10.0, "query_state")
        return fut.result()

    now = probe.node.get_clock().now().nanoseconds * 1e-9
    at_rest = ask(now)
    assert at_rest.success and list(at_rest.name) == list(joints.LEFT_ARM)
    assert at_rest.position[0] == pytest.approx(probe.position("LSP"), abs=0.01)

    # A trajectory on the controller's topic: every joint of the controller, stamped so its times are known.
    lsp = probe.position("LSP")
    target = lsp + 0.3 if lsp + 0.3 < load_limits()["LSP"][1] else lsp - 0.3
    msg = _arm_goal({"LSP": [lsp, target]}, [0.5, 2.5]).trajectory
    start = probe.node.get_clock().now().nanoseconds * 1e-9 + 0.3
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(start), int(start % 1 * 1e9)
    states.clear()
    pub.publish(msg)
    probe.spin_until(lambda: abs(probe.position("LSP") - lsp) > 0.05, 15.0, "LSP moving on the controller's topic")
    mid = ask(start + 1.5)
    assert mid.success, mid.message
    assert mid.position[0] == pytest.approx((lsp + target) / 2, abs=1e-6)
    assert mid.velocity[0] == pytest.approx((target - lsp) / 2.0, rel=0.01)
    assert not ask(start + 10.0).success
    moving = [m for m in states if abs(m.reference.velocities[0]) > 0.05]
    assert moving, "no controller_state with the trajectory's velocity"
    probe.spin_until(lambda: abs(probe.position("LSP") - target) < 0.02, 20.0, "LSP at the target")
    rate = _state_rate(1.0)
    window = [m for m in states if m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 >= start + 0.5]
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in window]
    assert len(set(stamps)) == len(stamps)
    assert len(window) >= 0.8 * rate * (stamps[-1] - stamps[0]), f"{len(window)} states, {rate:.1f} frames/s"

    # The controller's topic takes only its joints.
    bad = JointTrajectory(joint_names=["RSP"])
    bad.points = msg.points[:1]
    pub.publish(bad)
    probe.spin_until(lambda: "left_arm_controller/joint_trajectory" in probe.bridge_log()
                     and "'RSP' not joints of left_arm_controller" in probe.bridge_log(), 10.0, "the rejection")
    for entity in (sub, pub):
        probe.node.destroy_subscription(entity) if entity is sub else probe.node.destroy_publisher(entity)
    probe.node.destroy_client(query)
