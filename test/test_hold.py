"""Issue 17: atomic goals and the command lifecycle (hold / resume / cancel) in the mux and the filter.
Issue 25: a CANCEL stops, it never moves (limits, owners: ``check_cancel``)."""

from __future__ import annotations

import numpy as np
import pytest
from support.mux_frames import frame as _frame
from support.mux_frames import hold_request as _hold

import mds_ach as mds
from mds_ach.kinematics.limits import compute
from mds_ach.nodes.filter import FilterCore, parse_config
from mds_ach.nodes.mux import Controller, MuxCore, state_to_dict
from mds_ach.nodes.pipeline import select_joints
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE
from mds_ach.robot.msgs.hold import CANCEL_TOLERANCE, HOLD_CANCEL, HOLD_HOLD, HOLD_RESUME
from mds_ach.robot.msgs.mux_state import (
    MUX_CANCELLED,
    MUX_FREE,
    MUX_HELD,
    MUX_HOLD_DONE,
    MUX_HOLD_REFUSED,
    VERDICT_APPLIED,
    VERDICT_OWNED,
)

ARMS = select_joints(["left_arm", "right_arm"])
LEFT_ARM = select_joints("left_arm")
ALL = select_joints("all")
ZERO_MODE = np.zeros(MDS_JOINT_COUNT, dtype=np.int16)


def _core(start: np.ndarray | None = None, limits: bool = False) -> MuxCore:
    controllers = [Controller("ros", "mds-ref-ros", 30, ALL, 1.0), Controller("ik", "mds-ref-ik", 20, ARMS, 2.0),
                   Controller("default", "mds-ref-filter", 10, ALL, None, seed=True)]
    start = np.zeros(MDS_JOINT_COUNT) if start is None else start
    core = MuxCore(controllers, start, ZERO_MODE, compute() if limits else None)
    for i in range(3):
        core.absorb(i, start, ZERO_MODE)
    return core






# --------------------------------------------------------------------------------------------- atomic goals


def test_ik_goal_after_a_joint_command_is_refused_whole_with_the_owner() -> None:
    """Symptom 3: a ROS joint command owns LSP; an IK solution for the whole left arm 0.8 s later must not be
    applied to the other 5 joints. The frame is refused as a whole and the answer names the owner."""
    core = _core()
    changed, problem = core.update(0, _frame(LSP=-0.3), ZERO_MODE, now=10.0)  # ros: joint command on LSP
    assert changed and problem is None and core.owner[mds.LSP] == 0
    solution = _frame(LSP=-0.5, LSR=0.1, LSY=0.2, LEP=-0.9, LWY=0.3, LWR=0.1)
    changed, problem = core.update(1, solution, ZERO_MODE, now=10.8)
    assert not changed and problem is not None
    assert "owned by 'ros' (priority 30)" in problem and "LSP" in problem and "nothing applied" in problem
    assert all(core.ref[a] == 0.0 for a in LEFT_ARM if a != mds.LSP) and core.ref[mds.LSP] == -0.3
    assert (core.owner[[a for a in LEFT_ARM if a != mds.LSP]] == -1).all()
    st = core.state(now=10.9)
    assert st.verdict[1] == VERDICT_OWNED and st.blocker[1] == 0 and st.blocked_joint[1] == mds.LSP
    assert st.refused[1] == 1 and st.verdict[0] == VERDICT_APPLIED
    doc = state_to_dict(MDS_MUX_STATE.from_buffer_copy(bytes(st)))
    ik = next(c for c in doc["controllers"] if c["name"] == "ik")
    assert ik["verdict"] == "owned" and ik["blocker"] == "ros" and ik["refused"] == 1
    # the refused frame is never replayed (re-sending it is not a command) ...
    changed, problem = core.update(1, solution, ZERO_MODE, now=11.5)
    assert not changed and problem is None and core.ref[mds.LSR] == 0.0
    # ... and once ros is stale the next solution is applied to all six joints
    changed, problem = core.update(1, solution + 0.01 * np.isin(np.arange(MDS_JOINT_COUNT), LEFT_ARM), ZERO_MODE,
                                   now=11.6)
    assert changed and problem is None and (core.owner[list(LEFT_ARM)] == 1).all()


# --------------------------------------------------------------------------------------------- lifecycle


def test_hold_is_kept_until_a_new_command_and_resume_restores_the_targets() -> None:
    core = _core()
    core.update(2, _frame(LSP=0.5, RSP=0.4), ZERO_MODE, now=1.0)
    changed, text = core.hold(_hold(HOLD_HOLD, 1), None)  # empty mask: every joint
    assert not changed and "hold #1 from 'test'" in text
    assert core.held[mds.LSP] == MUX_HELD and core.held[mds.RSP] == MUX_HELD and core.dirty
    st = core.state(now=1.1)
    assert st.hold_seq == 1 and st.hold_action == HOLD_HOLD and st.held[mds.LSP] == MUX_HELD
    assert core.ref[mds.LSP] == 0.5  # the output keeps the targets (for RESUME); the filter holds the joints
    # an unchanged re-send is not a command: still held
    core.update(2, _frame(LSP=0.5, RSP=0.4), ZERO_MODE, now=1.2)
    assert core.held[mds.LSP] == MUX_HELD
    # a new command for RSP releases RSP only
    changed, _ = core.update(2, _frame(LSP=0.5, RSP=0.2), ZERO_MODE, now=1.3)
    assert changed and core.held[mds.RSP] == MUX_FREE and core.held[mds.LSP] == MUX_HELD
    core.hold(_hold(HOLD_RESUME, 2), None)
    assert (core.held == MUX_FREE).all() and core.ref[mds.LSP] == 0.5 and core.hold_seq == 2


def test_cancel_ends_targets_for_good() -> None:
    """CANCEL: ownership dropped, the output becomes where the reference is (NaN target, or a target there);
    RESUME never revives it, nor does a read-modify-write client re-sending its old frame."""
    core = _core()
    frame = _frame(LSP=0.5, LEP=-0.6)
    core.update(2, frame, ZERO_MODE, now=1.0)
    current = np.zeros(MDS_JOINT_COUNT)
    current[mds.LSP] = 0.12  # where the reference is now (the gate held the arm)
    current[mds.LEP] = -0.3
    changed, _ = core.hold(_hold(HOLD_CANCEL, 3, (mds.LSP, mds.LEP), {mds.LEP: -0.3}), current)
    assert changed and core.ref[mds.LSP] == 0.12 and core.ref[mds.LEP] == -0.3
    assert core.owner[mds.LSP] == -1 and core.owner[mds.LEP] == -1
    assert core.held[mds.LSP] == MUX_CANCELLED and core.held[mds.LEP] == MUX_FREE
    core.hold(_hold(HOLD_RESUME, 4), None)
    assert core.held[mds.LSP] == MUX_CANCELLED and core.ref[mds.LSP] == 0.12
    changed, _ = core.update(2, frame, ZERO_MODE, now=2.0)  # the client re-sends its old frame
    assert not changed and core.ref[mds.LSP] == 0.12 and core.held[mds.LSP] == MUX_CANCELLED
    changed, _ = core.update(2, _frame(frame, NKY=0.1), ZERO_MODE, now=2.1)  # another joint: LSP still ended
    assert changed and core.ref[mds.LSP] == 0.12 and core.held[mds.LSP] == MUX_CANCELLED
    changed, _ = core.update(2, _frame(frame, NKY=0.1, LSP=0.3), ZERO_MODE, now=2.2)  # a new command for it
    assert changed and core.ref[mds.LSP] == 0.3 and core.held[mds.LSP] == MUX_FREE


def test_invalid_hold_request_is_refused_and_acknowledged() -> None:
    core = _core()
    bad = _hold(HOLD_HOLD, 9)
    bad.action = 7
    changed, text = core.hold(bad, None)
    assert not changed and "refused" in text and "unknown hold action" in text
    st = core.state(now=1.0)
    assert st.hold_seq == 9 and st.hold_status == 1 and (np.frombuffer(bytes(st.held), np.uint8) == 0).all()


def _refusal(core: MuxCore) -> str:
    st = MDS_MUX_STATE.from_buffer_copy(bytes(core.state(now=9.0)))
    assert st.hold_status == MUX_HOLD_REFUSED
    reason = st.hold_reason.decode()
    assert state_to_dict(st)["hold"] == {"seq": st.hold_seq, "action": "cancel", "source": "test",
                                         "status": "refused", "reason": reason}
    return reason


def test_a_cancel_target_outside_the_limits_is_refused() -> None:
    """Issue 25 item 2: LEP at -1.20 and a CANCEL to +1.0 (inside one turn, outside LEP's range) ran LEP to the
    edge of its range. Refused with the reason on mds-mux-state; nothing changes."""
    start = _frame(LEP=-1.2)
    core = _core(start, limits=True)
    changed, text = core.hold(_hold(HOLD_CANCEL, 5, (mds.LEP,), {mds.LEP: 1.0}), start)
    assert not changed and "refused cancel #5 from 'test'" in text and "nothing changed" in text
    assert core.ref[mds.LEP] == -1.2 and core.held[mds.LEP] == MUX_FREE
    assert "outside LEP's range" in _refusal(core)
    # inside the limits but away from the reference: a move, refused as well
    changed, text = core.hold(_hold(HOLD_CANCEL, 6, (mds.LEP,), {mds.LEP: -0.5}), start)
    assert not changed and core.ref[mds.LEP] == -1.2 and "never moves" in _refusal(core)
    # where the reference is: taken (the collision gate's cancel), and the reason is cleared
    changed, text = core.hold(_hold(HOLD_CANCEL, 7, (mds.LEP,), {mds.LEP: -1.2}), start)
    assert not changed and core.hold_status == MUX_HOLD_DONE and core.state(now=9.1).hold_reason == b""


def test_a_cancel_never_moves_a_joint_a_higher_priority_controller_owns() -> None:
    """Issue 25 item 2: a CANCEL with an in-range target moved a joint owned by a higher-priority controller. Now a
    CANCEL only stops: a target away from the reference is refused; one within the tolerance holds the joint where
    its reference is, not at the target, so repeated CANCELs cannot walk it either."""
    core = _core(limits=True)
    core.update(0, _frame(LSP=-0.5), ZERO_MODE, now=1.0)  # ros (priority 30) commands LSP
    current = _frame(LSP=-0.5)  # the pipeline has it there
    assert core.owner[mds.LSP] == 0
    changed, text = core.hold(_hold(HOLD_CANCEL, 8, (mds.LSP,), {mds.LSP: 0.3}), current)
    assert not changed and core.ref[mds.LSP] == -0.5 and core.owner[mds.LSP] == 0
    assert "is 0.8000 rad from its reference" in _refusal(core)
    for k in range(20):  # each target just within the tolerance of the output: still not one step
        near = float(core.ref[mds.LSP]) + 0.9 * CANCEL_TOLERANCE
        core.hold(_hold(HOLD_CANCEL, 9 + k, (mds.LSP,), {mds.LSP: near}), current)
        assert core.hold_status == MUX_HOLD_DONE and core.ref[mds.LSP] == -0.5
    # stopping stays every writer's right: a CANCEL without target ends the target where the reference is
    core.update(0, _frame(LSP=-0.1), ZERO_MODE, now=2.0)
    changed, _ = core.hold(_hold(HOLD_CANCEL, 40, (mds.LSP,)), current)
    assert changed and core.ref[mds.LSP] == -0.5 and core.held[mds.LSP] == MUX_CANCELLED


# --------------------------------------------------------------------------------------------- filter


def _filter() -> FilterCore:
    params = parse_config({"rate": 40.0, "default": {"mode": "velocity_limit", "max_velocity": 1.57,
                                                       "max_accel": 4.0}})
    return FilterCore(params, np.zeros(MDS_JOINT_COUNT), ZERO_MODE)


@pytest.mark.parametrize("steps", [3, 20])  # accelerating, and at full speed
def test_filter_brakes_a_held_joint_without_reversal_or_step(steps: int) -> None:
    f = _filter()
    f.set_target(_frame(LSP=2.0), ZERO_MODE)
    for _ in range(steps):
        f.step()
    before, v0 = f.out[mds.LSP], f.vel[mds.LSP]
    assert v0 > 0
    held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    held[mds.LSP] = True
    f.hold(held, reference=f.out.copy())
    positions, speeds = [before], [v0]
    for _ in range(40):
        positions.append(f.step()[mds.LSP])
        speeds.append((positions[-1] - positions[-2]) * 40.0)
        f.set_target(_frame(LSP=2.0), ZERO_MODE)  # the mux keeps sending the old target: ignored while held
    d = np.diff(positions)
    assert speeds[1] < v0  # from the next output on it no longer advances at the old pace toward the target
    assert (d >= -1e-12).all()  # no reversal
    assert (np.abs(np.diff(speeds)) <= 4.0 / 40.0 + 1e-9).all()  # within the filter's acceleration bound
    assert positions[-1] == positions[-5] and positions[-1] < 2.0  # rests short of the old target
    f.hold(np.zeros(MDS_JOINT_COUNT, dtype=bool))  # released (RESUME): goes on to the target
    for _ in range(200):
        f.step()
    assert f.out[mds.LSP] == pytest.approx(2.0)


def test_filter_restarts_a_joint_the_gate_held_back_where_the_robot_is_sent() -> None:
    """The filter reached the goal but the gate kept mds-ref-gated at 0.3: a hold must not rest at the goal (the arm
    would go there when the gate clears); it restarts at the gate's output."""
    f = _filter()
    f.set_target(_frame(LSP=1.0), ZERO_MODE)
    for _ in range(120):
        f.step()
    assert f.out[mds.LSP] == pytest.approx(1.0)
    reference = np.zeros(MDS_JOINT_COUNT)
    reference[mds.LSP] = 0.3
    held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    held[mds.LSP] = True
    f.hold(held, reference)
    for _ in range(10):
        assert f.step()[mds.LSP] == 0.3


def _passing() -> FilterCore:
    """A filter passing its targets unsmoothed (the bridge's trajectory stopping points, config ``controllers``)."""
    return FilterCore(parse_config({"rate": 40.0, "default": {"mode": "pass"}}), np.zeros(MDS_JOINT_COUNT),
                      ZERO_MODE)


def _daemon_took(**values: float) -> np.ndarray:
    taken = np.full(MDS_JOINT_COUNT, np.nan)
    for name, v in values.items():
        taken[getattr(mds, name)] = v
    return taken


def test_a_hold_stops_an_unsmoothed_joint_at_the_daemons_last_reference() -> None:
    """A trajectory's joint passed unsmoothed, its newest stopping point (0.5) still waiting for the daemon's next
    send: held in time (``feedforward.retraction_in_time``), it stops at the reference the daemon took (0.4), not
    at the newest; the daemon's next cycle shows it took the retraction: it stays. Without ``taken`` (too late
    before the next send) it stops at the newest, as before."""
    held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    held[mds.LSP] = True
    for taken, stop in ((_daemon_took(LSP=0.4), 0.4), (None, 0.5)):
        f = _passing()
        f.set_target(_frame(LSP=0.5), ZERO_MODE)
        f.step()
        f.hold(held, reference=f.out.copy(), taken=taken)
        for _ in range(5):
            assert f.step()[mds.LSP] == stop
            f.set_target(_frame(LSP=0.6), ZERO_MODE)  # a newer frame is a released joint's target, not a held one's
        assert f.settle_retractions(_daemon_took(LSP=0.4)) == [] and not f.retracted
        assert f.step()[mds.LSP] == stop
    f = _passing()
    f.set_target(_frame(LSP=0.5, RSP=0.2), ZERO_MODE)
    f.step()
    f.hold(held, taken=_daemon_took(LSP=0.4, RSP=0.1))
    assert f.step()[mds.RSP] == 0.2  # a joint not held is not retracted


def test_a_retraction_the_daemon_missed_goes_back_to_the_newest_target() -> None:
    """The retraction reached the daemon after its cycle: the daemon took the newest (0.5), its last target now; the
    filter goes back to it before the next cycle (``settle_retractions``), else the target already sent would be
    taken back (a reversal)."""
    f = _passing()
    f.set_target(_frame(LSP=0.5), ZERO_MODE)
    f.step()
    held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    held[mds.LSP] = True
    f.hold(held, taken=_daemon_took(LSP=0.4))
    assert f.step()[mds.LSP] == 0.4
    assert f.settle_retractions(_daemon_took(LSP=0.5)) == [mds.LSP]
    for _ in range(3):
        assert f.step()[mds.LSP] == 0.5


def test_a_hold_of_a_smoothed_joint_is_not_retracted() -> None:
    """An acceleration-limited joint brakes at the filter's acceleration as before: its output is already a
    reference the daemon follows without a lead, so nothing is taken back."""
    f = _filter()
    f.set_target(_frame(LSP=2.0), ZERO_MODE)
    for _ in range(5):
        f.step()
    before = f.out[mds.LSP]
    held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    held[mds.LSP] = True
    f.hold(held, taken=_daemon_took(LSP=0.0))
    assert f.step()[mds.LSP] > before and not f.retracted


# --------------------------------------------------------------------------------------------- with channels


def test_ik_says_not_applied_when_the_mux_refuses_its_solution(clean_shm: None) -> None:
    """Symptom 3 end to end: a ROS joint command on LSP, then an IK pose for the left arm 0.8 s later. The mux
    refuses the whole solution and the IK status says IK_NOT_APPLIED with the owner, not "solved"."""
    import threading
    import time

    from support import wait_for

    from mds_ach.nodes.ik import IkNodeConfig, IkRunner, IkService, arm_limits
    from mds_ach.nodes.ik_client import IkClient
    from mds_ach.nodes.mux import MuxRunner, load_config
    from mds_ach.nodes.pipeline import make_ref
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs.ik_status import IK_NOT_APPLIED, IK_SOLVED

    pose = np.zeros(MDS_JOINT_COUNT)
    pose[list(LEFT_ARM)] = [-0.2, 0.3, 0.0, -1.0, 0.0, 0.0]
    pose[list(select_joints("right_arm"))] = [-0.2, -0.3, 0.0, -1.0, 0.0, 0.0]
    st = mds.MDS_STATE()
    for a in range(MDS_JOINT_COUNT):
        st.joint[a].ref = st.joint[a].pos = pose[a]
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(st)
    with StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF) as ch:
        ch.put(make_ref(pose, ZERO_MODE))
    mux = MuxRunner(load_config()["controllers"], state_rate=10.0, log=lambda level, msg: None)
    ikr = IkRunner(IkService(IkNodeConfig(max_iterations=300), arm_limits("default")), log=lambda level, msg: None)
    threads = [threading.Thread(target=r.run, daemon=True) for r in (mux, ikr)]
    for t in threads:
        t.start()
    try:
        assert mux.ready.wait(20) and ikr.ready.wait(20)
        with IkClient() as client:
            reply = client.request("left", 3, [0.3, 0.25, 0.0], timeout=20)  # nobody owns the arm: applied
            assert reply.status == IK_SOLVED, reply.message
            with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_REF) as ros:
                assert mux.core is not None
                frame = mux.core.ref.copy()  # the bridge's first frame starts from the mux output
                frame[mds.LSP] = -0.35
                ros.put(make_ref(frame, ZERO_MODE))  # the bridge's joint command: ros owns LSP only
                wait_for(lambda: mux.core.owner[mds.LSP] == 0, 5, what="ros owning LSP")
                time.sleep(0.3)  # the symptom's timing: the IK pose 0.3-0.8 s after the joint command
                before = mux.core.ref.copy()
                reply = client.request("left", 3, [0.32, 0.22, 0.02], timeout=20)
        assert reply.status == IK_NOT_APPLIED and not reply.success
        assert "owned by 'ros' (priority 30)" in reply.message and "LSP" in reply.message
        assert np.array_equal(mux.core.ref, before)  # none of the six joints changed
    finally:
        mux.stop()
        ikr.stop()
        for t in threads:
            t.join(5)


def test_cancels_on_mds_hold_that_would_move_a_joint_are_refused_with_the_reason(clean_shm: None) -> None:
    """Issue 25 item 2 through the channels: a CANCEL to +1.0 for LEP at -1.20 (outside its range), and an in-range
    CANCEL for LSP, which a higher-priority controller (ros) commands, are refused; the requester gets the reason
    in the acknowledgement and the mux output does not move. A CANCEL without target still stops LSP."""
    import threading

    from support import wait_for

    from mds_ach.nodes.mux import MuxRunner, load_config
    from mds_ach.nodes.pipeline import make_ref
    from mds_ach.robot import lifecycle
    from mds_ach.robot.channels import StructChannel

    pose = _frame(LEP=-1.2, LSP=-0.2)
    with StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF) as ch:
        ch.put(make_ref(pose, ZERO_MODE))
    logs: list[str] = []
    # log_every 60 s: both refusals within one logging window, however slow the machine
    mux = MuxRunner(load_config()["controllers"], state_rate=10.0, log=lambda level, msg: logs.append(msg),
                    log_every=60.0)
    thread = threading.Thread(target=mux.run, daemon=True)
    thread.start()
    try:
        assert mux.ready.wait(20) and mux.core is not None
        core = mux.core
        ack = lifecycle.request(HOLD_CANCEL, targets={mds.LEP: 1.0}, source="adversary", timeout=5)
        assert not ack.ok and "refused by the mux" in ack.message and "outside LEP's range" in ack.message
        assert core.ref[mds.LEP] == -1.2
        with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_REF) as ros:
            ros.put(make_ref(_frame(pose, LSP=-0.35), ZERO_MODE))  # ros (priority 30) commands LSP
            wait_for(lambda: core.owner[mds.LSP] == 0, 5, what="ros owning LSP")
        ack = lifecycle.request(HOLD_CANCEL, targets={mds.LSP: 0.3}, source="adversary", timeout=5)
        assert not ack.ok and "a CANCEL never moves a joint" in ack.message
        assert core.ref[mds.LSP] == -0.35 and core.owner[mds.LSP] == 0
        assert sum("refused cancel" in m for m in logs) == 1, logs  # the second in the window: counted, not logged
        assert mux.hold_refusals == 2
        ack = lifecycle.request(HOLD_CANCEL, [mds.LSP], source="console", timeout=5)
        assert ack.ok and core.ref[mds.LSP] == -0.2 and core.held[mds.LSP] == MUX_CANCELLED  # where the pipeline is
    finally:
        mux.stop()
        thread.join(5)


class _Gate:
    """A stand-in collision gate: copies mds-ref-smooth to mds-ref, optionally capping LSP (an arm it holds)."""

    def __init__(self, start: np.ndarray) -> None:
        import threading

        from mds_ach.nodes.pipeline import make_ref
        from mds_ach.robot.channels import StructChannel

        self.cap: float | None = None
        self.sent: list[np.ndarray] = []
        self.times: list[float] = []
        self.smooth: list[np.ndarray] = []
        self._stop = threading.Event()
        self._in = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
        self._out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
        self._out.put(make_ref(start, ZERO_MODE))
        self._make_ref = make_ref
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import time

        from mds_ach.nodes.pipeline import ref_arrays

        while not self._stop.is_set():
            frame = self._in.wait(0.2)
            if frame is None:
                continue
            ref, mode = ref_arrays(frame)
            self.smooth.append(ref.copy())
            if self.cap is not None:
                ref[mds.LSP] = min(ref[mds.LSP], self.cap)
            self.sent.append(ref.copy())
            self.times.append(time.monotonic())
            self._out.put(self._make_ref(ref, mode))

    def close(self) -> None:
        self._stop.set()
        self.thread.join(5)
        self._in.close()
        self._out.close()


def test_hold_resume_cancel_through_mux_and_filter(clean_shm: None) -> None:
    """Hold stops the reference (no further advance toward the old target beyond braking, no reversal, then rest);
    nothing moves until resume; resume restarts the held target; a timed-out goto cancelled while the gate
    holds the arm never moves it when the gate clears; resume does not revive a cancelled target."""
    import threading
    import time

    from support import wait_for

    from mds_ach.nodes.filter import FilterRunner
    from mds_ach.nodes.filter import load_config as filter_config
    from mds_ach.nodes.mux import MuxRunner, load_config
    from mds_ach.nodes.pipeline import make_ref
    from mds_ach.robot import lifecycle
    from mds_ach.robot.channels import StructChannel

    start = np.zeros(MDS_JOINT_COUNT)
    gate = _Gate(start)
    mux = MuxRunner(load_config()["controllers"], state_rate=10.0, log=lambda level, msg: None)
    filt = FilterRunner(filter_config(), log=lambda level, msg: None)
    threads = [threading.Thread(target=r.run, daemon=True) for r in (mux, filt)]
    for t in threads:
        t.start()
    legacy = StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF)
    try:
        assert mux.ready.wait(20) and filt.ready.wait(20)
        period = 1.0 / filt.params.rate

        def lsp() -> float:
            return float(gate.sent[-1][mds.LSP]) if gate.sent else 0.0

        legacy.put(make_ref(_frame(LSP=1.0), ZERO_MODE))  # goto LSP 1.0 (its upper limit is 1.0185)
        wait_for(lambda: lsp() > 0.4, 10, what="LSP moving")
        n = len(gate.sent)
        ack = lifecycle.request(lifecycle.HOLD_HOLD, source="test", reason="test hold")
        assert ack.ok, ack.message
        t_ack = time.monotonic()
        time.sleep(0.8)  # braking takes <= 0.4 s at 1.57 rad/s and 4 rad/s^2; then it must rest
        seq = [s[mds.LSP] for s in gate.sent[n:]]
        steps = np.diff(seq)
        assert (steps >= -1e-12).all(), "the held reference reversed"
        assert (np.abs(np.diff(steps)) <= 4.0 * period * period + 1e-9).all(), "braking beyond the filter's bound"
        rest = lsp()
        # stopped short of the target and resting (the filter publishes a step of 0, then no more: it sleeps at rest)
        assert rest < 1.0 - 0.05 and seq[-1] == seq[-2] and filt.core is not None and not filt.core.moving()
        # from the first filter output after the acknowledgement on (allowing one period for the filter to read
        # it and one for delivery), the reference decelerates: no step larger than the one before it
        times = gate.times[n + 1:]
        first = next(k for k, t in enumerate(times) if t > t_ack + 2 * period)
        assert (np.diff(steps[first:]) <= 1e-12).all() and steps[first] < 1.57 * period - 1e-6
        time.sleep(0.5)
        assert lsp() == rest, "moved while held"
        assert time.monotonic() - t_ack > 1.0
        ack = lifecycle.request(lifecycle.HOLD_RESUME, source="test")
        assert ack.ok
        wait_for(lambda: abs(lsp() - 1.0) < 1e-9, 10, what="resume: LSP reaches its held target")

        # a goto the gate holds back, timing out: cancelled where the reference is
        gate.cap = 0.6
        legacy.put(make_ref(_frame(LSP=0.2), ZERO_MODE))
        wait_for(lambda: abs(lsp() - 0.2) < 1e-9, 10, what="LSP back at 0.2")
        legacy.put(make_ref(_frame(LSP=0.95), ZERO_MODE))  # goto LSP 0.95 wait: the gate stops it at 0.6
        wait_for(lambda: gate.smooth and abs(gate.smooth[-1][mds.LSP] - 0.95) < 1e-9, 10, what="filter at 0.95")
        assert lsp() == 0.6
        ack = lifecycle.request(lifecycle.HOLD_CANCEL, [mds.LSP], source="console", reason="goto timed out")
        assert ack.ok and ack.state is not None and ack.state.held[mds.LSP] == MUX_CANCELLED
        wait_for(lambda: gate.smooth and abs(gate.smooth[-1][mds.LSP] - 0.6) < 1e-9, 5, what="filter restarted")
        gate.cap = None  # the gate clears
        assert lifecycle.request(lifecycle.HOLD_RESUME, source="test").ok  # resume does not revive it
        legacy.put(make_ref(_frame(LSP=0.95, NKY=0.1), ZERO_MODE))  # read-modify-write client: another joint
        wait_for(lambda: abs(gate.sent[-1][mds.NKY] - 0.1) < 1e-9, 10, what="NKY moved")
        time.sleep(0.5)
        assert max(s[mds.LSP] for s in gate.sent[-20:]) == 0.6, "a cancelled goto moved the arm later"
    finally:
        legacy.close()
        mux.stop()
        filt.stop()
        for t in threads:
            t.join(5)
        gate.close()


def test_cli_hold_fails_when_the_mux_does_not_acknowledge(clean_shm: None) -> None:
    import subprocess

    from support import VENV_BIN

    proc = subprocess.run([str(VENV_BIN / "mds-ach"), "hold", "left", "--timeout", "0.3"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 1 and "not acknowledged" in proc.stderr and "mux" in proc.stderr
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), "resume", "ELBOW"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "ELBOW" in proc.stderr


def test_console_parses_hold_and_resume() -> None:
    from mds_ach.tools.console import Hold, parse

    cmd = parse("hold left NKY")
    assert isinstance(cmd, Hold) and cmd.action == HOLD_HOLD
    assert set(cmd.addresses) == set(LEFT_ARM) | {mds.NKY}
    cmd = parse("resume")
    assert isinstance(cmd, Hold) and cmd.action == HOLD_RESUME and cmd.addresses == ()


def test_held_joints_are_listed_among_the_enabled_ones_only() -> None:
    """Issue 28: `hold` (all) listed all 43 joints, disabled ones included."""
    from mds_ach.robot.joints import JOINTS
    from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_HELD
    from mds_ach.tools.holdcmd import enabled_joints, held_summary

    st = MDS_MUX_STATE()
    for j in JOINTS:
        st.held[j.address] = MUX_HELD
    state = mds.MDS_STATE()
    for address in (mds.LSP, mds.LEP, mds.RSP):
        state.joint[address].enabled = 1
    enabled = enabled_joints(state)
    assert enabled == {mds.LSP, mds.LEP, mds.RSP}
    assert held_summary(st, enabled) == "held every enabled joint (3) (mds-ach resume)"
    st.held[mds.LEP] = MUX_CANCELLED
    line = held_summary(st, enabled)
    assert line == "held RSP LSP (mds-ach resume); cancelled LEP (until a new command)", line  # table order
    assert "NKY" not in line and "WST" not in line, "disabled joints are not listed"
    assert held_summary(st, None).count(" ") > 40, "without a state every joint is named, as before"
