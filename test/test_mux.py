"""Joint mux: the merge rule (modified + permitted + priority + staleness), its channels and its node."""

from __future__ import annotations

import ctypes
import json
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
from support import VENV_BIN, wait_for

import mds_ach as mds
from mds_ach.nodes.mux import (
    MDS_MUX_STATE,
    Controller,
    MuxCore,
    MuxRunner,
    load_config,
    parse_controllers,
    state_to_dict,
)
from mds_ach.nodes.pipeline import make_ref, ref_arrays, select_joints
from mds_ach.robot.msgs.mux_state import VERDICT_APPLIED, VERDICT_NOT_PERMITTED

ARMS = select_joints(["left_arm", "right_arm"])
ALL = select_joints("all")


def _controllers(ik_timeout: float | None = 1.0) -> list[Controller]:
    return [
        Controller("ros", "mds-ref-ros", 30, ALL, 0.5),
        Controller("ik", "mds-ref-ik", 20, ARMS, ik_timeout),
        Controller("default", "mds-ref-filter", 10, ALL, None, seed=True),
    ]


def _start_ref() -> tuple[np.ndarray, np.ndarray]:
    ref = np.zeros(mds.MDS_JOINT_COUNT)
    ref[mds.LSR], ref[mds.RSR], ref[mds.LEP], ref[mds.REP] = 1.2, -1.18, -1.25, -1.25
    return ref, np.zeros(mds.MDS_JOINT_COUNT, dtype=np.int16)


def _frame(base: np.ndarray, **joints: float) -> np.ndarray:
    out = base.copy()
    for name, value in joints.items():
        out[getattr(mds, name)] = value
    return out


ZERO_MODE = np.zeros(mds.MDS_JOINT_COUNT, dtype=np.int16)


# --------------------------------------------------------------------------------------------- config


def test_default_config_wires_the_documented_controllers() -> None:
    cfg = load_config()
    by_name = {c.name: c for c in cfg["controllers"]}
    assert by_name["default"].channel == mds.MDS_CHAN_REF_FILTER_NAME
    assert by_name["ik"].channel == mds.MDS_CHAN_REF_IK_NAME
    assert by_name["ros"].channel == mds.MDS_CHAN_REF_ROS_NAME
    assert by_name["ros"].priority > by_name["ik"].priority > by_name["default"].priority
    assert by_name["default"].seed and by_name["default"].timeout is None
    assert set(by_name["ik"].joints) == set(ARMS)
    assert mds.NKY not in by_name["ik"].joints


def test_joint_selection_patterns_groups_and_errors() -> None:
    left = select_joints("L*")
    assert mds.LSP in left and mds.LF0 in left and mds.RSP not in left
    assert select_joints(["neck", "WST"]) == tuple(sorted([mds.NKY, mds.NKP1, mds.NKP2, mds.NKR, mds.WST]))
    assert select_joints([0x5F, "RightElbowFlex"]) == tuple(sorted([mds.LSP, mds.REP]))
    with pytest.raises(ValueError, match="matches no joint"):
        select_joints("Q*")
    with pytest.raises(ValueError, match="unknown joint"):
        select_joints(["LSP", "ELBOW"])


@pytest.mark.parametrize(
    "entries, message",
    [
        ([{"name": "a", "channel": "x", "priority": 1}, {"name": "b", "channel": "y", "priority": 1}], "priorities"),
        ([{"name": "a", "channel": "x", "priority": 1}, {"name": "a", "channel": "y", "priority": 2}], "names"),
        ([{"name": "a", "channel": "x", "priority": 1, "timeout": 0}], "timeout"),
        ([{"name": "a", "channel": "mds-ref-gated", "priority": 1}], "pipeline output"),
        ([{"name": "a", "channel": "x", "priority": 1, "joints": "nope"}], "unknown joint"),
        ([{"name": "a", "channel": "x"}], "priority"),
        ([{"name": "a", "channel": "x", "priority": 1, "colour": "red"}], "unknown keys"),
        ([], "no controllers"),
    ],
)
def test_bad_controller_config_is_refused(entries: list, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_controllers(entries)


def test_state_struct_layout() -> None:
    assert ctypes.sizeof(MDS_MUX_STATE) == 920
    assert MDS_MUX_STATE.owner.offset == 0
    assert MDS_MUX_STATE.time.offset == 494 and MDS_MUX_STATE.held.offset == 506
    assert MDS_MUX_STATE.hold_reason.offset == 700  # appended (issue 25): the fields before keep their offsets


# --------------------------------------------------------------------------------------------- merge rule


def test_only_modified_joints_change() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    old = _frame(ref, LSP=0.7, NKY=0.3)  # an old frame of the legacy channel, different from the output
    core.absorb(2, old, ZERO_MODE)
    changed, problem = core.update(2, _frame(old, LEP=-1.0), ZERO_MODE, now=1.0)
    assert changed and problem is None
    assert core.ref[mds.LEP] == -1.0
    # LSP and NKY were different from the output but not modified by this frame: untouched
    assert core.ref[mds.LSP] == ref[mds.LSP] and core.ref[mds.NKY] == ref[mds.NKY]
    assert core.owner[mds.LEP] == 2 and core.owner[mds.LSP] == -1


def test_first_frame_is_compared_with_the_output() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    changed, _ = core.update(1, _frame(ref, LSP=-0.5), ZERO_MODE, now=1.0)
    assert changed and core.ref[mds.LSP] == -0.5
    assert np.array_equal(np.delete(core.ref, mds.LSP), np.delete(ref, mds.LSP))


def test_permission_is_required_and_a_frame_with_a_forbidden_joint_is_refused_whole() -> None:
    """Atomic goals (issue 17): a frame that also modifies a joint its controller may not move is refused as a
    whole (nothing of it applied), with the joint named; a frame within the permission is applied."""
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    changed, problem = core.update(1, _frame(ref, NKY=0.4, LSP=-0.2), ZERO_MODE, now=1.0)  # ik may not move NKY
    assert not changed and problem is not None and "NKY" in problem and "may not move" in problem
    assert core.ref[mds.NKY] == ref[mds.NKY] and core.ref[mds.LSP] == ref[mds.LSP]
    assert core.owner[mds.NKY] == -1 and core.owner[mds.LSP] == -1
    assert core.verdict[1] == VERDICT_NOT_PERMITTED and core.refused[1] == 1
    changed, problem = core.update(1, _frame(ref, NKY=0.4, LSP=-0.3), ZERO_MODE, now=1.1)  # only LSP modified now
    assert changed and problem is None and core.ref[mds.LSP] == -0.3 and core.verdict[1] == VERDICT_APPLIED


def test_priority_then_fallback_after_staleness_without_jump() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(ik_timeout=1.0), ref, mode)
    core.absorb(2, ref, ZERO_MODE)
    core.update(1, _frame(ref, LSP=-0.8), ZERO_MODE, now=10.0)  # ik takes LSP
    default_frame = _frame(ref, LSP=0.3)
    changed, _ = core.update(2, default_frame, ZERO_MODE, now=10.5)  # lower priority while ik is fresh
    assert not changed and core.ref[mds.LSP] == -0.8 and core.owner[mds.LSP] == 1
    # ik re-sends the same frame: that is holding, not commanding, so it does not stay fresh
    core.update(1, _frame(ref, LSP=-0.8), ZERO_MODE, now=10.9)
    assert core.release_stale(now=11.2)
    assert core.owner[mds.LSP] == -1 and core.ref[mds.LSP] == -0.8  # released, value held: no jump
    # the default controller's old value (0.3) is not replayed; its next change wins
    changed, _ = core.update(2, default_frame, ZERO_MODE, now=11.3)
    assert not changed and core.ref[mds.LSP] == -0.8
    changed, _ = core.update(2, _frame(ref, LSP=0.25), ZERO_MODE, now=11.4)
    assert changed and core.ref[mds.LSP] == 0.25 and core.owner[mds.LSP] == 2


def test_higher_priority_takes_over_a_joint() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    core.update(2, _frame(ref, LSP=0.1), ZERO_MODE, now=1.0)
    assert core.owner[mds.LSP] == 2
    changed, _ = core.update(0, _frame(ref, LSP=-0.3), ZERO_MODE, now=1.1)
    assert changed and core.owner[mds.LSP] == 0 and core.ref[mds.LSP] == -0.3
    changed, _ = core.update(2, _frame(ref, LSP=0.2), ZERO_MODE, now=1.2)
    assert not changed and core.ref[mds.LSP] == -0.3


def test_mode_change_counts_as_a_modification() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    core.absorb(2, ref, ZERO_MODE)
    new_mode = ZERO_MODE.copy()
    new_mode[mds.WST] = mds.MDS_REF_MODE_REF
    changed, _ = core.update(2, ref, new_mode, now=1.0)
    assert changed and core.mode[mds.WST] == mds.MDS_REF_MODE_REF and core.owner[mds.WST] == 2


def test_non_finite_frame_is_refused_whole() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    bad = _frame(ref, LSP=0.5, LEP=float("nan"))
    changed, problem = core.update(2, bad, ZERO_MODE, now=1.0)
    assert not changed and "LEP" in problem and "non-finite" in problem
    assert np.array_equal(core.ref, ref) and core.refused[2] == 1
    # the refused frame is not the controller's previous frame: the next good frame is compared with the output
    changed, _ = core.update(2, _frame(ref, LSP=0.5), ZERO_MODE, now=1.1)
    assert changed and core.ref[mds.LSP] == 0.5


def test_state_reports_owners_ages_and_names() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    core.update(1, _frame(ref, LSP=-0.4), ZERO_MODE, now=5.0)
    st = core.state(now=5.25, seq=7)
    assert st.owner[mds.LSP] == 1 and st.owner[mds.RSP] == -1
    assert st.count == 3 and st.seq == 7
    assert st.age[1] == pytest.approx(0.25) and st.age[0] == -1.0
    assert not st.stale[1] and st.stale[0]
    doc = state_to_dict(MDS_MUX_STATE.from_buffer_copy(bytes(st)))
    assert doc["owners"] == {"LSP": "ik"}
    assert [c["name"] for c in doc["controllers"]] == ["ros", "ik", "default"]
    assert json.loads(json.dumps(doc)) == doc


# --------------------------------------------------------------------------------------------- channels


def _put(name: str, ref: np.ndarray, mode: np.ndarray = ZERO_MODE) -> None:
    from mds_ach.robot.channels import StructChannel

    with StructChannel(name, mds.MDS_REF) as ch:
        ch.put(make_ref(ref, mode))


@pytest.fixture
def runner(clean_shm: None):
    """A MuxRunner on the real channel names (private /dev/shm), started from a known mds-ref."""
    from mds_ach.robot.channels import StructChannel

    ref, mode = _start_ref()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, ref)
    _put(mds.MDS_CHAN_REF_IK_NAME, _frame(ref, LSP=1.0))  # an old IK frame: must not be applied
    out = StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
    logs: list[str] = []
    r = MuxRunner(_controllers(ik_timeout=30.0), state_rate=50.0, log=lambda level, msg: logs.append(f"{level}: {msg}"))
    t = threading.Thread(target=r.run, daemon=True)
    t.start()
    assert r.ready.wait(10), logs
    yield r, out, ref, logs
    r.stop()
    t.join(5)
    out.close()
    assert not t.is_alive()


def _newest(ch, timeout: float = 5.0):
    frames = []

    def got():
        while (f := ch.latest()) is not None:
            frames.append(f)
        return frames

    wait_for(got, timeout, what="a frame")
    return ref_arrays(frames[-1])[0]


def test_runner_starts_from_current_reference_and_seeds_legacy_channel(runner) -> None:
    from mds_ach.robot.channels import StructChannel

    r, out, ref, _ = runner
    assert np.array_equal(_newest(out), ref)  # first output = current reference, not the old IK frame
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF) as legacy:
        assert np.array_equal(ref_arrays(legacy.latest())[0], ref)


def test_runner_merges_inputs_event_driven(runner) -> None:
    from mds_ach.robot.channels import StructChannel

    r, out, ref, logs = runner
    _newest(out)
    _put(mds.MDS_CHAN_REF_IK_NAME, _frame(ref, LSP=-0.6))  # compared with the absorbed old frame: LSP changed
    got = _newest(out)
    assert got[mds.LSP] == -0.6
    # legacy client: neck free, but LSP owned by ik: atomic goals refuse the whole frame, naming the owner
    _put(mds.MDS_CHAN_REF_FILTER_NAME, _frame(ref, NKY=0.2, LSP=0.4))
    wait_for(lambda: any("owned by 'ik'" in m and "LSP" in m for m in logs), 5, what="refusal naming the owner")
    assert r.core.ref[mds.NKY] == ref[mds.NKY] and out.latest() is None
    _put(mds.MDS_CHAN_REF_FILTER_NAME, _frame(ref, NKY=0.25, LSP=0.4))  # vs its previous frame: only NKY
    wait_for(lambda: r.core.ref[mds.NKY] == 0.25, 5, what="neck change")
    got = _newest(out)
    assert got[mds.NKY] == 0.25 and got[mds.LSP] == -0.6
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as state_ch:
        def owners():
            st = state_ch.latest()
            return (st is not None and st.owner[mds.LSP] == 1 and st.owner[mds.NKY] == 2
                    and st.verdict[2] == VERDICT_APPLIED)

        wait_for(owners, 5, what="mux state with the owners")


def test_runner_refuses_nan_frames_with_a_message(runner) -> None:
    r, out, ref, logs = runner
    _newest(out)
    _put(mds.MDS_CHAN_REF_ROS_NAME, _frame(ref, RSP=float("inf")))
    wait_for(lambda: any("non-finite" in m and "RSP" in m for m in logs), 5, what="refusal message")
    assert out.latest() is None  # nothing published
    assert np.array_equal(r.core.ref, ref)


def test_a_flood_of_refused_frames_logs_a_bounded_number_of_lines_and_counts_every_one(clean_shm: None) -> None:
    """1 kHz of out-of-limit frames (each with a new value) for 3 s: one line for the first refusal, then
    summaries at most every ``log_every`` s; the summary's total and mds-mux-state ``refused`` agree with the
    mux's count of every frame it refused (issue #25, item 9: 77.5 MB of mux.log in 10 s)."""
    from mds_ach.robot.channels import StructChannel

    ref, mode = _start_ref()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, ref)
    logs: list[str] = []
    r = MuxRunner(_controllers(), state_rate=50.0, log=lambda level, msg: logs.append(f"{level}: {msg}"),
                  log_every=1.0)
    t = threading.Thread(target=r.run, daemon=True)
    t.start()
    try:
        assert r.ready.wait(10), logs
        started = len(logs)
        with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, mds.MDS_REF) as ch:
            t0 = time.monotonic()
            sent = 0
            while time.monotonic() - t0 < 3.0:
                ch.put(make_ref(_frame(ref, LSP=5.0 + 1e-4 * sent), mode))
                sent += 1
                time.sleep(max(0.0, t0 + sent * 1e-3 - time.monotonic()))
        assert sent > 2000
        core = r.core
        assert core is not None
        # the last summary comes from the mux's own tick once the flood stopped
        wait_for(lambda: any(f"{int(core.refused[0])} in all" in m for m in logs[started:]), 10,
                 what="a summary with the total")
        refused = int(core.refused[0])
        lines = [m for m in logs[started:] if "refused a frame from 'ros'" in m]
        assert refused > 500 and r.refusals.total("ros") == refused
        assert 2 <= len(lines) <= 3 + 3 / 1.0 + 2, lines
        assert lines[0].startswith("error: ") and "LSP" in lines[0] and "in all" not in lines[0]  # the first, whole
        with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as state_ch:
            wait_for(lambda: (st := state_ch.latest()) is not None and int(st.refused[0]) == refused, 5,
                     what="mds-mux-state refused = every refused frame")
    finally:
        r.stop()
        t.join(5)
    assert not t.is_alive()


# --------------------------------------------------------------------------------------------- node


def test_mux_help() -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-mux"), "--help"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "usage: mux" in proc.stdout and "priority" in proc.stdout


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_mux_node_publishes_state_and_stops_cleanly(clean_shm: None, sig: int) -> None:
    """/mds/mux_state is typed (mds_ach_interfaces/msg/MuxState) and carries what mds-mux-state carries, report
    for report."""
    import rclpy
    from mds_ach_interfaces.msg import MuxState
    from rclpy.node import Node

    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs import MDS_MUX_STATE

    ref, _ = _start_ref()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, ref)
    proc = subprocess.Popen([str(VENV_BIN / "mds-ach-mux"), "--ros-args", "--log-level", "warn"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = Node("test_mux_listener")
    msgs: list[MuxState] = []
    docs: list[dict] = []
    node.create_subscription(MuxState, "/mds/mux_state", msgs.append, 10)
    frames = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)

    def read_frames() -> None:
        while (frame := frames.next()) is not None:
            docs.append(state_to_dict(frame))

    def owner(m: MuxState, joint: str) -> str:
        return m.owner[list(m.joint_names).index(joint)]

    try:
        deadline = time.monotonic() + 20
        sent = False
        while time.monotonic() < deadline and not (any(owner(m, "LSP") == "ik" for m in msgs)
                                                   and any(d["owners"].get("LSP") == "ik" for d in docs)):
            rclpy.spin_once(node, timeout_sec=0.1)
            read_frames()
            if msgs and not sent:
                _put(mds.MDS_CHAN_REF_IK_NAME, _frame(ref, LSP=-0.3))
                sent = True
        assert any(owner(m, "LSP") == "ik" for m in msgs), (msgs[-1:], proc.poll())
        by_time = {d["time"]: d for d in docs}
        pairs = [(m, by_time[m.time]) for m in msgs if m.time in by_time]
        assert pairs and any(d["owners"] for _, d in pairs)
        for m, d in pairs:
            assert {j: o for j, o in zip(m.joint_names, m.owner, strict=True) if o} == d["owners"]
            held = {j: ("held", "cancelled")[h - 1] for j, h in zip(m.joint_names, m.held, strict=True) if h}
            assert held == d["held"]
            assert [(c.name, c.priority, c.stale, c.verdict, c.refused) for c in m.controllers] == \
                [(c["name"], c["priority"], c["stale"], c["verdict"], c["refused"]) for c in d["controllers"]]
            assert [c.age for c in m.controllers] == [-1.0 if c["age"] is None else c["age"] for c in d["controllers"]]
            assert (m.hold_seq, m.hold_action, m.hold_source, m.hold_status, m.hold_reason) == tuple(
                d["hold"].values())
        assert "LSP" in msgs[-1].joint_names and msgs[-1].header.stamp.sec > 0
    finally:
        frames.close()
        node.destroy_node()
        rclpy.shutdown()
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=15)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out
