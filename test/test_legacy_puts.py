"""Issue 26 item 4: every put on a legacy input (``mds-ref-filter``, ``mds-ref``) is a command, as on the original.

* a put commands the joints it changed *and* the joints another controller moved away from its value (a re-put of
  the same frame sends the robot back, once the mux's priorities and staleness allow);
* a frame built from zeros is executed: values outside the effective limits are clamped to them, with a verdict
  naming the clamped joints, never refused silently (NaN/Inf still refuse the frame);
* a hold holds and a cancelled command stays cancelled while a client keeps re-putting the same frame at 50 Hz; a
  new value (or RESUME for a held joint) releases them;
* ``ros`` and ``ik`` keep "changed values only" and whole-frame refusal (config/mux.yaml ``legacy``).

The core rules on ``MuxCore`` with the shipped config/mux.yaml and limits; the issue's scenario through the mux's
real channels (``MuxRunner``, threads and Ach), asserted on ``mds-ref-mux``.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from support import wait_for
from support.mux_frames import frame as _frame
from support.mux_frames import hold_request as _hold

import mds_ach as mds
from mds_ach.kinematics.limits import compute
from mds_ach.nodes.mux import MuxCore, MuxRunner, load_config, state_to_dict
from mds_ach.nodes.pipeline import make_ref, ref_arrays
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE
from mds_ach.robot.msgs.hold import HOLD_CANCEL, HOLD_HOLD, HOLD_RESUME
from mds_ach.robot.msgs.mux_state import (
    MUX_CANCELLED,
    MUX_FREE,
    MUX_HELD,
    VERDICT_APPLIED,
    VERDICT_CLAMPED,
    VERDICT_INVALID,
    VERDICT_OWNED,
)

ZERO_MODE = np.zeros(MDS_JOINT_COUNT, dtype=np.int16)
CONTROLLERS = load_config()["controllers"]
INDEX = {c.name: i for i, c in enumerate(CONTROLLERS)}
ROS, IK, DEFAULT, DIRECT = INDEX["ros"], INDEX["ik"], INDEX["default"], INDEX["direct"]
LIMITS = compute()
LOWER, UPPER = LIMITS.arrays()


def _start() -> np.ndarray:
    """A pose inside every range: 0 clamped into the limits."""
    return np.clip(np.zeros(MDS_JOINT_COUNT), LOWER, UPPER)


def _core(start: np.ndarray | None = None) -> MuxCore:
    start = _start() if start is None else start
    core = MuxCore(CONTROLLERS, start, ZERO_MODE, LIMITS)
    for i in range(len(CONTROLLERS)):
        core.absorb(i, start, ZERO_MODE)
    return core






def test_the_shipped_config_makes_the_original_channels_legacy_inputs() -> None:
    assert {c.name for c in CONTROLLERS if c.legacy} == {"default", "direct"}
    assert {c.channel for c in CONTROLLERS if c.legacy} == {mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_NAME}


@pytest.mark.parametrize("other", ["ik", "ros"])
def test_a_reput_of_the_same_frame_sends_back_a_joint_another_controller_moved(other: str) -> None:
    """The issue's scenario: LSP -0.123 from the client, another controller moves LSP, the same frame again."""
    core = _core()
    frame = _frame(_start(), LSP=-0.123)
    assert core.update(DEFAULT, frame, ZERO_MODE, now=1.0) == (True, None)
    moved = _frame(_start(), LSP=0.3)
    assert core.update(INDEX[other], moved, ZERO_MODE, now=1.1)[0] and core.ref[mds.LSP] == 0.3
    # while the other controller is fresh and outranks 'default', the re-put is refused (named), not lost silently
    changed, problem = core.update(DEFAULT, frame, ZERO_MODE, now=1.2)
    assert not changed and problem is not None and f"owned by '{other}'" in problem
    assert core.verdict[DEFAULT] == VERDICT_OWNED and core.ref[mds.LSP] == 0.3
    # once it is stale, the same frame put again is a command: the robot goes back, as the original did
    later = 1.1 + CONTROLLERS[INDEX[other]].timeout + 0.1
    changed, problem = core.update(DEFAULT, frame, ZERO_MODE, now=later)
    assert changed and problem is None and core.ref[mds.LSP] == -0.123 and core.owner[mds.LSP] == DEFAULT
    assert core.verdict[DEFAULT] == VERDICT_APPLIED
    # re-putting it once more changes nothing (nothing differs): no output, no refusal
    assert core.update(DEFAULT, frame, ZERO_MODE, now=later + 0.1) == (False, None)


def test_a_direct_reput_outranks_the_streaming_controllers_at_once() -> None:
    core = _core()
    frame = _frame(_start(), LSP=-0.123)
    core.update(DIRECT, frame, ZERO_MODE, now=1.0)
    core.update(IK, _frame(_start(), LSP=0.3), ZERO_MODE, now=3.0)  # 'direct' went stale after 1 s
    assert core.ref[mds.LSP] == 0.3
    changed, problem = core.update(DIRECT, frame, ZERO_MODE, now=3.1)  # priority 40 > ik's 20
    assert changed and problem is None and core.ref[mds.LSP] == -0.123


def test_ik_and_ros_keep_changed_values_only() -> None:
    core = _core()
    core.update(IK, _frame(_start(), LSP=0.3), ZERO_MODE, now=1.0)
    core.update(DEFAULT, _frame(_start(), LSP=-0.2), ZERO_MODE, now=5.0)
    assert core.ref[mds.LSP] == -0.2
    assert core.update(IK, _frame(_start(), LSP=0.3), ZERO_MODE, now=5.1) == (False, None)
    assert core.ref[mds.LSP] == -0.2


def test_a_zero_built_frame_moves_every_joint_with_the_out_of_range_ones_clamped() -> None:
    """The original's client: memset(0), set one joint, put. The elbows' ranges exclude 0: clamped, not refused."""
    start = _frame(_start(), LSP=0.4, NKY=0.2)
    core = _core(start)
    frame = _frame(np.zeros(MDS_JOINT_COUNT), LSP=-0.123)
    outside = sorted(a for a in range(MDS_JOINT_COUNT) if core._known[a] and not LOWER[a] <= 0.0 <= UPPER[a])
    assert mds.LEP in outside and mds.REP in outside, "the shipped limits: the elbows' ranges exclude 0"
    changed, problem = core.update(DEFAULT, frame, ZERO_MODE, now=1.0)
    assert changed and problem is None
    expected = np.clip(frame, LOWER, UPPER)
    known = core._known
    assert np.array_equal(core.ref[known], expected[known]) and core.ref[mds.LSP] == -0.123 and core.ref[mds.NKY] == 0
    assert core.verdict[DEFAULT] == VERDICT_CLAMPED and core.blocked_joint[DEFAULT] == outside[0]
    assert core.refused[DEFAULT] == 0 and core.clamp_message is not None and "REP" in core.clamp_message
    st = core.state(now=1.1)
    assert st.clamped_joints(DEFAULT) == outside
    doc = state_to_dict(st)["controllers"][DEFAULT]
    assert doc["verdict"] == "clamped" and "REP" in " ".join(doc["clamped"])
    # the same frame again: nothing differs from the clamped output, nothing to log
    assert core.update(DEFAULT, frame, ZERO_MODE, now=1.2) == (False, None) and core.clamp_message is None


def test_a_non_finite_value_still_refuses_the_legacy_frame_whole() -> None:
    core = _core()
    changed, problem = core.update(DEFAULT, _frame(_start(), LSP=-0.1, REP=math.nan), ZERO_MODE, now=1.0)
    assert not changed and problem is not None and "non-finite" in problem
    assert core.verdict[DEFAULT] == VERDICT_INVALID and core.ref[mds.LSP] == _start()[mds.LSP]


def test_out_of_limit_values_from_ros_are_still_refused_whole() -> None:
    core = _core()
    changed, problem = core.update(ROS, _frame(_start(), LSP=-0.1, LEP=0.0), ZERO_MODE, now=1.0)
    assert not changed and problem is not None and "as a whole" in problem and core.verdict[ROS] == VERDICT_INVALID


def test_a_hold_holds_while_a_client_keeps_reputting_at_50_hz() -> None:
    core = _core()
    frame = _frame(_start(), LSP=-0.123)
    core.update(DEFAULT, frame, ZERO_MODE, now=1.0)
    core.update(IK, _frame(_start(), LSP=0.3), ZERO_MODE, now=1.1)
    core.hold(_hold(HOLD_HOLD, 1, (mds.LSP,)), None)
    for k in range(150):  # 3 s at 50 Hz, well past ik's timeout
        now = 1.2 + k * 0.02
        changed, _ = core.update(DEFAULT, frame, ZERO_MODE, now=now)
        core.release_stale(now)
        assert not changed and core.held[mds.LSP] == MUX_HELD and core.ref[mds.LSP] == 0.3
    # RESUME ends the hold: the next re-put commands again
    core.hold(_hold(HOLD_RESUME, 2, (mds.LSP,)), None)
    changed, _ = core.update(DEFAULT, frame, ZERO_MODE, now=5.0)
    assert changed and core.ref[mds.LSP] == -0.123 and core.held[mds.LSP] == MUX_FREE


def test_a_hold_holds_a_streaming_clients_own_joint_until_a_new_value() -> None:
    core = _core()
    frame = _frame(_start(), LSP=-0.123)
    core.update(DEFAULT, frame, ZERO_MODE, now=1.0)
    core.hold(_hold(HOLD_HOLD, 1, (mds.LSP,)), None)
    for k in range(100):
        core.update(DEFAULT, frame, ZERO_MODE, now=1.1 + k * 0.02)
        assert core.held[mds.LSP] == MUX_HELD
    changed, _ = core.update(DEFAULT, _frame(frame, LSP=-0.2), ZERO_MODE, now=4.0)  # a new command releases it
    assert changed and core.held[mds.LSP] == MUX_FREE and core.ref[mds.LSP] == -0.2


@pytest.mark.parametrize("gate_target", [False, True])
def test_a_cancelled_command_is_not_revived_by_the_same_reput(gate_target: bool) -> None:
    """A cancel without target (console, timeouts) and one with the gate's target (where the reference stopped)."""
    core = _core()
    frame = _frame(_start(), LSP=-0.5)
    core.update(DEFAULT, frame, ZERO_MODE, now=1.0)
    current = np.full(MDS_JOINT_COUNT, math.nan)
    current[mds.LSP] = -0.2  # the reference stopped on its way
    core.hold(_hold(HOLD_CANCEL, 1, (mds.LSP,), {mds.LSP: -0.2} if gate_target else None), current)
    assert core.ref[mds.LSP] == -0.2
    for k in range(100):
        changed, problem = core.update(DEFAULT, frame, ZERO_MODE, now=1.1 + k * 0.02)
        assert not changed and problem is None and core.ref[mds.LSP] == -0.2
    assert core.held[mds.LSP] == (MUX_FREE if gate_target else MUX_CANCELLED)
    core.hold(_hold(HOLD_RESUME, 2, (mds.LSP,)), None)
    assert core.update(DEFAULT, frame, ZERO_MODE, now=4.0) == (False, None) and core.ref[mds.LSP] == -0.2
    changed, _ = core.update(DEFAULT, _frame(frame, LSP=-0.4), ZERO_MODE, now=4.1)  # a new command
    assert changed and core.ref[mds.LSP] == -0.4 and core.held[mds.LSP] == MUX_FREE


def test_a_reput_does_not_drive_a_reseeded_joint_back() -> None:
    """After HOME the joint restarts where it is; a client re-putting its pre-HOME frame does not move it."""
    core = _core()
    frame = _frame(_start(), LSP=-0.5)
    core.update(DEFAULT, frame, ZERO_MODE, now=1.0)
    core.reseed(np.array([mds.LSP]), np.array([0.0]))
    assert core.update(DEFAULT, frame, ZERO_MODE, now=2.0) == (False, None) and core.ref[mds.LSP] == 0.0


# --------------------------------------------------------------------------------------------- through the channels


def _put(name: str, ref: np.ndarray) -> None:
    with StructChannel(name, mds.MDS_REF) as ch:
        ch.put(make_ref(ref, ZERO_MODE))


def test_the_issue_scenario_through_the_mux_channels(clean_shm: None) -> None:
    """Client put LSP -0.123 on mds-ref-filter, IK moves LSP, the same frame put again: mds-ref-mux goes back.
    Also: a re-put with identical bytes is a new Ach frame, which the mux's reader wakes for."""
    start = _start()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, start)
    logs: list[str] = []
    r = MuxRunner(CONTROLLERS, state_rate=50.0, log=lambda level, msg: logs.append(f"{level}: {msg}"))
    t = threading.Thread(target=r.run, daemon=True)
    t.start()
    out = StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
    state_ch = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
    try:
        assert r.ready.wait(10), logs
        core = r.core
        assert core is not None

        newest: list[np.ndarray] = []

        def output_lsp(value: float) -> bool:
            """The newest frame on mds-ref-mux has LSP at ``value``."""
            while (frame := out.latest()) is not None:
                newest.append(ref_arrays(frame)[0])
            return bool(newest) and newest[-1][mds.LSP] == value

        client = _frame(start, LSP=-0.123)
        _put(mds.MDS_CHAN_REF_FILTER_NAME, client)
        wait_for(lambda: output_lsp(-0.123), 5, what="LSP -0.123 on mds-ref-mux")
        ik_frame = _frame(start, LSP=0.3)
        _put(mds.MDS_CHAN_REF_IK_NAME, ik_frame)
        wait_for(lambda: output_lsp(0.3), 5, what="IK's LSP on mds-ref-mux")
        ik_at = time.monotonic()
        timeout = CONTROLLERS[IK].timeout
        assert timeout is not None
        wait_for(lambda: time.monotonic() - ik_at > timeout + 0.2, timeout + 5, what="IK stale")
        refused = int(core.refused[DEFAULT])
        _put(mds.MDS_CHAN_REF_FILTER_NAME, client)  # the same bytes again
        wait_for(lambda: output_lsp(-0.123), 5, what="the re-put sends LSP back on mds-ref-mux")
        assert core.refused[DEFAULT] == refused

        # a zero-built frame: executed with the elbows clamped, the verdict names them
        zero = _frame(np.zeros(MDS_JOINT_COUNT), LSP=-0.123, NKY=0.1)
        _put(mds.MDS_CHAN_REF_FILTER_NAME, zero)
        wait_for(lambda: core.ref[mds.NKY] == 0.1, 5, what="the zero-built frame applied")

        def clamped() -> bool:
            st = state_ch.latest()
            return st is not None and st.verdict[DEFAULT] == VERDICT_CLAMPED and mds.REP in st.clamped_joints(DEFAULT)

        wait_for(clamped, 5, what="verdict 'clamped' naming REP on mds-mux-state")
        assert core.ref[mds.REP] == UPPER[mds.REP] or core.ref[mds.REP] == LOWER[mds.REP]
        wait_for(lambda: any("clamped a frame from 'default'" in m and "REP" in m for m in logs), 5,
                 what="the clamping log line")
        for _ in range(20):  # re-put: no more lines, nothing changes
            _put(mds.MDS_CHAN_REF_FILTER_NAME, zero)
        wait_for(lambda: r._queue.empty(), 5, what="the re-puts handled")
        assert sum("clamped a frame" in m for m in logs) == 1
    finally:
        r.stop()
        t.join(5)
        out.close()
        state_ch.close()
    assert not t.is_alive()


def test_a_hold_holds_through_the_channels_while_a_client_reputs_at_50_hz(clean_shm: None) -> None:
    """LSP put by the client, moved by IK, held on mds-hold; the client re-puts its frame at 50 Hz past IK's
    timeout: mds-ref-mux keeps LSP where the hold found it. After RESUME, the next re-put sends it back."""
    from mds_ach.robot import lifecycle

    start = _start()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, start)
    logs: list[str] = []
    r = MuxRunner(CONTROLLERS, state_rate=50.0, log=lambda level, msg: logs.append(f"{level}: {msg}"))
    t = threading.Thread(target=r.run, daemon=True)
    t.start()
    try:
        assert r.ready.wait(10), logs
        core = r.core
        assert core is not None
        client = _frame(start, LSP=-0.123)
        _put(mds.MDS_CHAN_REF_FILTER_NAME, client)
        wait_for(lambda: core.ref[mds.LSP] == -0.123, 5, what="the client's LSP")
        _put(mds.MDS_CHAN_REF_IK_NAME, _frame(start, LSP=0.3))
        wait_for(lambda: core.ref[mds.LSP] == 0.3, 5, what="IK's LSP")
        ack = lifecycle.request(HOLD_HOLD, [mds.LSP], source="test", timeout=5)
        assert ack.ok, ack.message
        timeout = CONTROLLERS[IK].timeout
        assert timeout is not None
        with StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF) as out, \
                StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF) as legacy:
            end = time.monotonic() + timeout + 0.5
            puts = 0
            next_at = time.monotonic()
            while time.monotonic() < end:
                legacy.put(make_ref(client, ZERO_MODE))
                puts += 1
                while (frame := out.latest()) is not None:
                    assert ref_arrays(frame)[0][mds.LSP] == 0.3, "a re-put moved a held joint"
                next_at += 0.02
                time.sleep(max(0.0, next_at - time.monotonic()))
            wait_for(lambda: r._queue.empty(), 5, what="the re-puts handled")
            assert puts >= 100 and core.ref[mds.LSP] == 0.3 and core.held[mds.LSP] == MUX_HELD
            assert core.stale(IK, time.monotonic()), "IK went stale meanwhile: only the hold kept LSP"
            ack = lifecycle.request(HOLD_RESUME, [mds.LSP], source="test", timeout=5)
            assert ack.ok, ack.message
            legacy.put(make_ref(client, ZERO_MODE))
            wait_for(lambda: core.ref[mds.LSP] == -0.123, 5, what="after RESUME, the re-put sends LSP back")
    finally:
        r.stop()
        t.join(5)
    assert not t.is_alive()
