"""IK node: request handling (IkService), the Ach loop with real channels, and the `ik` executable."""

from __future__ import annotations

import ctypes
import json
import math
import re
import signal
import subprocess
import threading

import numpy as np
import pytest
from support import VENV_BIN, wait_for
from support.channels import newest

import mds_ach as mds
from mds_ach import ik
from mds_ach.kinematics import model as kinematics
from mds_ach.nodes.ik import IkNodeConfig, IkRunner, IkService, arm_limits
from mds_ach.nodes.ik_client import IkClient, make_request
from mds_ach.nodes.pipeline import make_ref, ref_arrays
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs.ik_status import (
    IK_BAD_REQUEST,
    IK_NOT_READY,
    IK_SOLVED,
    IK_UNREACHABLE,
    MDS_IK_STATUS,
    get_message,
    status_to_dict,
)

N = mds.MDS_JOINT_COUNT
LEFT_ADDR = [BY_SHORT[s].address for s in LEFT_ARM]
RIGHT_ADDR = [BY_SHORT[s].address for s in RIGHT_ARM]


def current_pose() -> np.ndarray:
    """A plausible current reference: elbows bent, arms slightly out, everything else 0."""
    ref = np.zeros(N)
    ref[LEFT_ADDR] = [-0.2, 0.3, 0.0, -1.0, 0.0, 0.0]
    ref[RIGHT_ADDR] = [-0.2, -0.3, 0.0, -1.0, 0.0, 0.0]
    ref[mds.NKY] = 0.1
    return ref


def put_state(ref: np.ndarray) -> None:
    from mds_ach.robot.channels import StructChannel

    st = mds.MDS_STATE()
    for a in range(N):
        st.joint[a].ref = ref[a]
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(st)


def test_status_struct_layout() -> None:
    assert ctypes.sizeof(MDS_IK_STATUS) == 214
    offsets = {name: getattr(MDS_IK_STATUS, name).offset for name, _ in MDS_IK_STATUS._fields_}
    assert offsets == {"seq": 0, "status": 4, "arm": 6, "dof": 8, "iterations": 10, "error": 14, "solve_time": 22,
                       "target": 30, "q": 78, "stamp": 126, "message": 134}


# --------------------------------------------------------------------------------------------- IkService


@pytest.fixture(scope="module")
def service() -> IkService:
    return IkService(IkNodeConfig(), arm_limits("default"))


def test_service_solves_and_changes_only_the_six_arm_joints(service: IkService) -> None:
    target = [0.3, 0.2, 0.0]
    out = service.handle(make_request("left", 3, target), current_pose())
    st = out.status
    assert st.status == IK_SOLVED and st.arm == mds.LEFT and st.dof == 3
    assert set(out.refs) == set(LEFT_ADDR)
    q = np.array([out.refs[a] for a in LEFT_ADDR])
    assert np.allclose(q, list(st.q))
    assert np.linalg.norm(kinematics.fk_matrix(q, "left")[:3, 3] - target) <= 0.01
    assert 0 <= st.error <= 0.01 and st.iterations >= 1 and st.solve_time > 0
    doc = status_to_dict(st)
    assert doc["status_name"] == "solved" and doc["arm"] == "left" and doc["target"][:3] == target
    json.dumps(doc)


def test_service_respects_the_joint_table_limits(service: IkService) -> None:
    lower, upper = arm_limits("default")[mds.RIGHT]
    solver = service.solvers[mds.RIGHT]
    assert np.all(solver.lower >= lower) and np.all(solver.upper <= upper)
    out = service.handle(make_request("right", 5, [0.35, -0.25, -0.1, 0.0, 0.3]), current_pose())
    q = np.array(list(out.status.q))
    assert np.all(q >= solver.lower) and np.all(q <= solver.upper)


@pytest.mark.parametrize(
    "move, dof, values, message",
    [
        (2, 3, [0.3, 0.2, 0.0], "move must be 0 \\(right\\) or 1 \\(left\\), got 2"),
        (1, 0, [0.3, 0.2, 0.0], "DOF\\) must be 1..6, got 0"),
        (1, 7, [0.3, 0.2, 0.0], "DOF\\) must be 1..6, got 7"),
        (1, 3, [0.3, math.nan, 0.0], "NaN/Inf"),
        (0, 2, [math.inf, 0.2, 0.0], "NaN/Inf"),
    ],
)
def test_service_refuses_bad_requests(service: IkService, move: int, dof: int, values: list[float],
                                      message: str) -> None:
    req = mds.MDS_IK()
    arm = req.arm[move] if move in (0, 1) else req.arm[1]
    arm.t_x, arm.t_y, arm.t_z = values
    arm.ik_method = dof
    req.move = move
    out = service.handle(req, current_pose())
    assert out.refs is None and out.status.status == IK_BAD_REQUEST
    assert re.search(message, get_message(out.status)), get_message(out.status)


def test_service_nan_beyond_the_used_dof_is_fine(service: IkService) -> None:
    req = make_request("left", 3, [0.3, 0.2, 0.0])
    req.arm[mds.LEFT].r_x = math.nan  # not part of a 3-DOF task
    assert service.handle(req, current_pose()).status.status == IK_SOLVED


def test_service_unreachable_moves_nothing(service: IkService) -> None:
    fast = IkService(IkNodeConfig(max_iterations=60), arm_limits("default"))
    out = fast.handle(make_request("left", 3, [1.5, 0.2, 0.0]), current_pose())
    assert out.refs is None and out.status.status == IK_UNREACHABLE
    assert "unreachable" in get_message(out.status) and "nothing moved" in get_message(out.status)
    assert out.status.error > 0.01


def test_service_without_a_current_reference_is_not_ready(service: IkService) -> None:
    out = service.handle(make_request("left", 3, [0.3, 0.2, 0.0]), None)
    assert out.refs is None and out.status.status == IK_NOT_READY


def test_service_seeds_from_the_current_reference(service: IkService) -> None:
    """Asking for where the hand already is changes nothing (the seed is the current pose)."""
    cur = current_pose()
    here = kinematics.fk_matrix(cur[LEFT_ADDR], "left")
    req = make_request("left", 6, ik.getPosCurrentFromOrder(here, ik.DOF_ORDERS[6]).tolist())
    out = service.handle(req, cur)
    assert out.status.status == IK_SOLVED and out.status.iterations == 0
    assert np.allclose([out.refs[a] for a in LEFT_ADDR], cur[LEFT_ADDR], atol=1e-12)


def test_collision_hook_keeps_solutions_clear_of_the_body() -> None:
    from mds_ach.kinematics.collision import load_model
    from mds_ach.nodes.ik import collision_safety

    svc = IkService(IkNodeConfig(), arm_limits("default"), collision_safety(lambda level, msg: None))
    model = load_model()
    cur = current_pose()
    # A point in front of the chest, reachable with the hand; candidates must not touch the body.
    out = svc.handle(make_request("left", 3, [0.3, 0.05, -0.2]), cur)
    assert out.status.status == IK_SOLVED
    ref = cur.copy()
    for a, v in out.refs.items():
        ref[a] = v
    assert "left" not in model.check(model.q_from_ref(ref)).arms


def test_config_never_writes_mds_ref() -> None:
    with pytest.raises(ValueError, match="never writes mds-ref"):
        IkNodeConfig(output=mds.MDS_CHAN_REF_NAME)


# --------------------------------------------------------------------------------------------- runner + channels


def _frames(ch) -> list:
    out = []
    while (f := ch.latest()) is not None:
        out.append(f)
    return out


@pytest.mark.parametrize("output", [mds.MDS_CHAN_REF_IK_NAME, mds.MDS_CHAN_REF_FILTER_NAME])
def test_runner_with_real_channels(clean_shm: None, output: str) -> None:
    from mds_ach.robot.channels import StructChannel

    cur = current_pose()
    put_state(cur)
    other = cur.copy()
    other[mds.LSP] = -0.5  # another client's pending command for a left-arm joint on the shared channel
    other[mds.NKY] = 0.3
    if output == mds.MDS_CHAN_REF_FILTER_NAME:
        with StructChannel(output, mds.MDS_REF) as ch:
            ch.put(make_ref(other, np.zeros(N, dtype=np.int16)))
    runner = IkRunner(IkService(IkNodeConfig(output=output, max_iterations=200), arm_limits("default")),
                      log=lambda level, msg: None)
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    out = StructChannel(output, mds.MDS_REF)
    ref_ch = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
    _frames(out)
    try:
        assert runner.ready.wait(10)
        with IkClient() as client:
            reply = client.request("right", 3, [0.3, -0.2, 0.0], timeout=10)
            assert reply.success and reply.status == IK_SOLVED and reply.arm == "right"
            frames = wait_for(lambda: _frames(out), 5, what="the solution on the output channel")
            ref, _ = ref_arrays(frames[-1])
            base = other if output == mds.MDS_CHAN_REF_FILTER_NAME else cur
            changed = set(np.flatnonzero(ref != base))
            assert changed <= set(RIGHT_ADDR) and changed  # only the right arm's six joints
            assert np.allclose(ref[RIGHT_ADDR], reply.q)
            assert np.linalg.norm(kinematics.fk_matrix(ref[RIGHT_ADDR], "right")[:3, 3] - [0.3, -0.2, 0.0]) <= 0.01
            # Unreachable and bad requests: an answer, and nothing written.
            reply = client.request("left", 3, [1.4, 0.2, 0.0], timeout=10)
            assert reply.status == IK_UNREACHABLE and not reply.success
            bad = make_request("left", 3, [0.3, 0.2, 0.0])
            bad.arm[mds.LEFT].ik_method = 9
            client.requests.put(bad)
            st = wait_for(lambda: client.answers.latest(), 5, what="answer to the bad request")
            assert st.status == IK_BAD_REQUEST and "1..6" in get_message(st)
            assert _frames(out) == []
        assert ref_ch.latest() is None  # never straight to the daemon's channel
        assert runner.handled == 3
    finally:
        runner.stop()
        t.join(5)
        out.close()
        ref_ch.close()
    assert not t.is_alive()


def test_old_requests_are_not_commands(clean_shm: None) -> None:
    """Requests already in mds-ik when the node starts are flushed, like the original did."""
    from mds_ach.robot.channels import StructChannel

    put_state(current_pose())
    with StructChannel(mds.MDS_CHAN_IK_NAME, mds.MDS_IK) as ch:
        ch.put(make_request("left", 3, [0.3, 0.2, 0.0]))
    runner = IkRunner(IkService(IkNodeConfig(), arm_limits("default")), log=lambda level, msg: None)
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    try:
        assert runner.ready.wait(10)
        with StructChannel(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS) as answers:
            assert answers.wait(timeout=0.5) is None
        assert runner.handled == 0
    finally:
        runner.stop()
        t.join(5)


def test_the_launchers_probe_is_answered_without_a_warning(clean_shm: None) -> None:
    """Issue 28: every start logged a WARN "bad request: move must be 0 (right) or 1 (left), got -1" in ik.log: the
    launcher's own readiness probe. It is answered (refused, nothing moves) and logged as a probe; a real bad
    request still warns."""
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs.ik_status import IK_PROBE_MOVE, PROBE_ANSWER

    put_state(current_pose())
    logged: list[tuple[str, str]] = []
    runner = IkRunner(IkService(IkNodeConfig(), arm_limits("default")),
                      log=lambda level, msg: logged.append((level, msg)))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    try:
        assert runner.ready.wait(10)
        with StructChannel(mds.MDS_CHAN_IK_NAME, mds.MDS_IK, create=False) as requests, \
                StructChannel(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS, create=False) as answers:
            answers.flush()
            requests.put(mds.MDS_IK(move=IK_PROBE_MOVE))
            st = wait_for(lambda: answers.latest(), 5, what="the answer to the probe")
            assert st.status == IK_BAD_REQUEST and get_message(st) == PROBE_ANSWER and st.arm == -1
            requests.put(mds.MDS_IK(move=2))
            st = wait_for(lambda: answers.latest(), 5, what="the answer to the bad request")
            assert "move must be 0 (right) or 1 (left), got 2" in get_message(st)
    finally:
        runner.stop()
        t.join(5)
    answered = [(level, msg) for level, msg in logged if "#" in msg]
    assert [level for level, _ in answered] == ["info", "warn"], answered
    assert not any("got -1" in msg for _, msg in logged), logged


# --------------------------------------------------------------------------------------------- executable


def test_ik_help() -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-ik"), "--help"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "usage: ik" in proc.stdout and "mds-ref-ik" in proc.stdout


def test_ik_refuses_mds_ref_as_output() -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-ik"), "--output", "mds-ref"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "never writes mds-ref" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ik_node_answers_on_channels_and_ros_topic(clean_shm: None, sig: int) -> None:
    """Answers on mds-ik-state and on /mds/ik_status (mds_ach_interfaces/msg/IkStatus), which carries what the
    channel carries, answer for answer."""
    import rclpy
    from mds_ach_interfaces.msg import IkStatus

    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs.ik_status import IK_STATUS_TOPIC, status_to_dict

    put_state(current_pose())
    proc = subprocess.Popen([str(VENV_BIN / "mds-ach-ik")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node("ik_test")
    got: list[dict] = []
    from rclpy.qos import DurabilityPolicy, QoSProfile

    typed: list[IkStatus] = []
    latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(IkStatus, IK_STATUS_TOPIC, typed.append, latched)
    out = StructChannel(mds.MDS_CHAN_REF_IK_NAME, mds.MDS_REF)
    try:
        def matched() -> bool:
            rclpy.spin_once(node, timeout_sec=0.05)
            return node.count_publishers(IK_STATUS_TOPIC) > 0

        wait_for(matched, 60, what="the ik node's status publisher")
        # A 5-DOF pose the left hand can take (arm forward, elbow bent) with the body clear.
        pose = kinematics.fk_matrix([-0.6, 0.3, 0.2, -1.2, 0.3, 0.2], "left")
        with IkClient() as client:
            # A refused request first (logged as a warning), then a solved one (info): both must be answered.
            bad = make_request("left", 3, [0.3, 0.2, 0.0])
            bad.move = 5
            client.requests.put(bad)
            refused = wait_for(lambda: client.answers.latest(), 20, what="the answer to the bad request")
            assert refused.status == IK_BAD_REQUEST
            got.append(status_to_dict(refused))
            reply = client.request("left", 5, ik.getPosCurrentFromOrder(pose, ik.DOF_ORDERS[5]), timeout=30)
        assert reply.success, reply.message
        answer = newest(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS)
        assert answer is not None and answer.seq == reply.seq
        got.append(status_to_dict(answer))
        frame = wait_for(lambda: out.latest(), 5, what="the solution on mds-ref-ik")
        assert np.allclose(ref_arrays(frame)[0][LEFT_ADDR], reply.q)

        def topic() -> bool:
            rclpy.spin_once(node, timeout_sec=0.05)
            return len(got) >= 2 and len(typed) >= 2

        wait_for(topic, 20, what=f"both answers on {IK_STATUS_TOPIC}")
        assert [m.status for m in typed] == [IkStatus.BAD_REQUEST, IkStatus.SOLVED]
        assert typed[-1].arm == "left" and typed[-1].dof == 5 and typed[-1].seq == reply.seq
        assert list(typed[-1].q) == pytest.approx(list(reply.q))
        assert [d["status_name"] for d in got] == ["bad request", "solved"]
        for m, d in zip(typed, got, strict=True):
            assert (m.seq, m.status, m.status_name, m.arm, m.dof, m.iterations, m.stamp, m.message) == (
                d["seq"], d["status"], d["status_name"], d["arm"], d["dof"], d["iterations"], d["stamp"],
                d["message"])
            for key in ("error", "solve_time"):  # JSON null <-> NaN
                value = getattr(m, key)
                assert math.isnan(value) if d[key] is None else value == d[key], key
            assert [None if math.isnan(v) else v for v in m.target] == d["target"]
            assert [None if math.isnan(v) else v for v in m.q] == d["q"]
    finally:
        proc.send_signal(sig)
        text, _ = proc.communicate(timeout=20)
        out.close()
        node.destroy_node()
        rclpy.try_shutdown()
    assert proc.returncode == 0, text
    assert "Traceback" not in text, text


# --------------------------------------------------------------------------------------------- approach to contact


@pytest.fixture(scope="module")
def safety():
    from mds_ach.nodes.ik import collision_safety

    return collision_safety(lambda level, msg: None)


def _at(arm: str, point: list[float], base: np.ndarray) -> np.ndarray:
    idx = LEFT_ADDR if arm == "left" else RIGHT_ADDR
    res = ik.solve(point, "p-x p-y p-z", arm, base[idx])
    assert res.success
    out = base.copy()
    out[idx] = res.q
    return out


def test_a_colliding_goal_is_sent_in_approach_mode_and_refused_in_refuse_mode(safety) -> None:
    """Paper §4.2: the right hand sent to where the left hand is. approach (default): solved and sent, the gate
    stops it at contact; refuse: today's 'unreachable ... colliding; nothing moved'."""
    cur = _at("left", [0.40, 0.0, -0.10], current_pose())
    req = make_request("right", 3, [0.40, 0.0, -0.10])
    assert IkNodeConfig().on_collision == "approach"
    approach = IkService(IkNodeConfig(), arm_limits("default"), safety).handle(req, cur)
    assert approach.status.status == IK_SOLVED and approach.collides and approach.refs is not None
    assert "stops at contact" in get_message(approach.status)
    refuse = IkService(IkNodeConfig(on_collision="refuse"), arm_limits("default"), safety).handle(req, cur)
    assert refuse.status.status == IK_UNREACHABLE and refuse.refs is None and "colliding" in get_message(refuse.status)
    with pytest.raises(ValueError, match="on_collision"):
        IkNodeConfig(on_collision="ignore")


def test_the_other_arms_commanded_target_counts(safety) -> None:
    """The left arm is still at its current pose but commanded to the point: a right-hand goal there collides with
    where the left hand is heading (mds-ref-mux), not only with where it is."""
    cur = current_pose()
    commanded = _at("left", [0.40, 0.0, -0.10], cur)
    req = make_request("right", 3, [0.40, 0.0, -0.10])
    refuse = IkService(IkNodeConfig(on_collision="refuse"), arm_limits("default"), safety)
    assert refuse.handle(req, cur).status.status == IK_SOLVED  # against the current pose alone: clear
    assert refuse.handle(req, cur, commanded).status.status == IK_UNREACHABLE
    approach = IkService(IkNodeConfig(), arm_limits("default"), safety).handle(req, cur, commanded)
    assert approach.status.status == IK_SOLVED and approach.collides


def test_a_stop_at_contact_gets_a_second_answer(clean_shm: None) -> None:
    """After a solution was written, the gate's HOLD_CANCEL (source collision) for that arm gives the request a
    second status frame with the same seq: IK_STOPPED_AT_CONTACT, 'stopped at contact: right hand / left hand'.
    Another writer's cancel, or one for the other arm, is not a stop at contact of this request."""
    from mds_ach.nodes.gate import UNIT_ADDRESSES
    from mds_ach.robot import lifecycle
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs.hold import MDS_HOLD
    from mds_ach.robot.msgs.ik_status import IK_STOPPED_AT_CONTACT

    cur = current_pose()
    put_state(cur)
    runner = IkRunner(IkService(IkNodeConfig(max_iterations=200), arm_limits("default")),
                      log=lambda level, msg: None)
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    holds = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
    try:
        assert runner.ready.wait(10)
        with IkClient() as client:
            reply = client.request("right", 3, [0.3, -0.2, 0.0], timeout=10)
            assert reply.status == IK_SOLVED and client.stopped(reply) is None

            def cancel(arm: str, reason: str, source: str = "collision") -> MDS_HOLD:
                targets = {int(a): float(cur[a]) for a in UNIT_ADDRESSES[arm]}
                return lifecycle.make(lifecycle.HOLD_CANCEL, targets=targets, source=source, reason=reason)

            other = cancel("left", "stopped at contact: left hand / table")
            console = cancel("right", "goto timed out", source="console")
            for frame in (other, console):  # read in order before the gate's: a wrong match would answer first
                holds.put(frame)
            holds.put(cancel("right", "stopped at contact: right hand / left hand"))
            msg = wait_for(lambda: client.stopped(reply), 5, what="the follow-up answer")
            assert msg == "stopped at contact: right hand / left hand"
        assert runner.watches == {}
    finally:
        runner.stop()
        t.join(5)
        holds.close()
    assert not t.is_alive()
    assert IK_STOPPED_AT_CONTACT == 5 and status_to_dict(MDS_IK_STATUS(status=5))["status_name"] == \
        "stopped at contact"


def test_a_solution_the_daemon_will_slow_says_so(clean_shm: None) -> None:
    """Issue #31: while the daemon is in collaborative mode a solved status notes that the arm is slowed (the daemon
    keeps the hands and elbows within its Cartesian bound), so the client does not read the slower arm as a fault."""
    from mds_ach.nodes.ik import SLOWED_NOTE
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs import daemon_status as ds

    put_state(current_pose())
    runner = IkRunner(IkService(IkNodeConfig(max_iterations=200), arm_limits("default")), log=lambda level, msg: None)
    t = threading.Thread(target=runner.run, daemon=True)
    status = StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    t.start()
    try:
        assert runner.ready.wait(10)
        with IkClient() as client:
            reply = client.request("right", 3, [0.3, -0.2, 0.0], timeout=10)
            assert reply.success and SLOWED_NOTE not in reply.message
            status.put(ds.MDS_DAEMON_STATUS(version=ds.DAEMON_STATUS_VERSION, collaborative=1,
                                            collaborative_speed=0.25))
            reply = client.request("right", 3, [0.3, -0.25, 0.0], timeout=10)
            assert reply.success and reply.message.endswith(SLOWED_NOTE), reply.message
    finally:
        runner.stop()
        t.join(5)
        status.close()
