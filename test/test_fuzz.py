"""Fuzzing (hypothesis): malformed input everywhere -> no crash, nothing unsafe on the bus, every rejection counted.

* every input channel of the daemon (``mds-ref-gated``, ``mds-cmd``, ``mds-collide``): random bytes of any size, and
  well-sized frames full of NaN, Inf, huge values and bad modes, fed to the real daemon loop on the simulated bus;
* the mux, filter and collision-gate inputs (``mds-ref-filter``/``-ik``/``-ros``, ``mds-ref-mux``,
  ``mds-ref-smooth``): the same frames through each node's decision code, then through the daemon;
* random CAN frames from the bus into the daemon's receive path (any ID, length, flags, error classes);
* random console lines into the console's parser and executor;
* random ROS command messages (JointState, Float64MultiArray, JointTrajectory, PoseStamped) into the bridge's
  validation functions.

"Nothing unsafe": every MOVETO the simulated bus received is inside its joint's limits in counts and addressed to
an enabled joint (``support.rig.unsafe_commands``), and every MOVETO of the daemon rig obeys the motion bounds
(``motion_audit``: random mode switches, setup commands and position replies included). Examples are few and
fixed and there is no deadline, so CI stays fast and repeatable; set ``MDS_FUZZ_EXAMPLES=2000`` for a deep run
with fresh random examples.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import struct
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import remove_mds_channels
from support.motion_audit import audit
from support.rig import TABLE, DaemonRig, unsafe_commands

import mds_ach as mds
from mds_ach import ach
from mds_ach.bus import mcb
from mds_ach.nodes.pipeline import KNOWN_ADDRESSES, ref_arrays
from mds_ach.robot.msgs import MDS_CMD, MDS_COLLIDE, MDS_JOINT_COUNT, MDS_REF
from mds_ach.robot.msgs import daemon_status as ds

# CI runs a fixed, modest set of examples; MDS_FUZZ_EXAMPLES=2000 fuzzes deeper with fresh random examples.
FUZZ_EXAMPLES = int(os.environ.get("MDS_FUZZ_EXAMPLES", "30"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize="MDS_FUZZ_EXAMPLES" not in os.environ,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])
ENABLED = [j.address for j in TABLE.enabled]

# --------------------------------------------------------------------------------------------- strategies

nasty_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 5e-324, -0.0, 3.4e38, 1e19]),
    st.floats(-4.0, 4.0),
)
modes = st.one_of(st.sampled_from([0, 1, 2, 3]), st.integers(-32768, 32767))


@st.composite
def ref_frames(draw: st.DrawFn) -> bytes:
    """An MDS_REF (1000 B) with some joints set to nasty values and modes, the others at the home pose."""
    ref = MDS_REF()
    for j in TABLE:
        ref.joint[j.address].ref = j.home
        ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
    changed = draw(st.dictionaries(st.sampled_from(range(MDS_JOINT_COUNT)), st.tuples(nasty_floats, modes),
                                   max_size=12))
    for a, (value, mode) in changed.items():
        ref.joint[a].ref, ref.joint[a].mode = value, mode
    return bytes(ref)


def sized_garbage(size: int) -> st.SearchStrategy[bytes]:
    """Random bytes of exactly ``size`` (random doubles are mostly huge or NaN)."""
    return st.binary(min_size=size, max_size=size)


any_size = st.binary(min_size=1, max_size=mds.CHANNEL_FRAME_COUNT * mds.CHANNEL_FRAME_SIZE)
ref_payloads = st.one_of(ref_frames(), sized_garbage(ctypes.sizeof(MDS_REF)), any_size)


@st.composite
def cmd_frames(draw: st.DrawFn) -> bytes:
    cmd = MDS_CMD(seq=draw(st.integers(1, 2**32 - 1)), cmd=draw(st.integers(0, 0xFFFF)),
                  address=draw(st.one_of(st.sampled_from([0, *ENABLED]), st.integers(0, 0xFFFF))),
                  value=draw(nasty_floats))
    return bytes(cmd)


daemon_events = st.lists(st.one_of(
    st.tuples(st.just(mds.MDS_CHAN_DAEMON_INPUT_NAME), ref_payloads),
    st.tuples(st.just(mds.MDS_CHAN_BOARD_CMD_NAME), st.one_of(cmd_frames(), st.binary(min_size=1, max_size=64))),
    st.tuples(st.just(mds.MDS_CHAN_COLLIDE_NAME), st.one_of(sized_garbage(ctypes.sizeof(MDS_COLLIDE)), any_size)),
), min_size=1, max_size=8)


@pytest.fixture
def fresh() -> Iterator[None]:
    """Hypothesis runs many examples in one test call: each example builds and removes its own channels."""
    remove_mds_channels()
    yield
    remove_mds_channels()


def assert_state_safe(rig: DaemonRig) -> None:
    assert unsafe_commands(rig.net.commands) == []
    bounded = audit(rig.log.frames, TABLE, rig.loop.bounds, rig.loop.stale_after)
    assert bounded.violations == [], bounded.violations  # any mode switch, command or reply: within the bounds
    for a in ENABLED:
        j = TABLE.get(a)
        ref = rig.loop.state.joint[a].ref
        assert math.isfinite(ref) and j.lower - 1e-9 <= ref <= j.upper + 1e-9, f"{j.short} commanded {ref}"


# --------------------------------------------------------------------------------------------- daemon inputs


@FUZZ
@given(events=daemon_events)
def test_daemon_survives_anything_on_its_input_channels(fresh: None, caplog: pytest.LogCaptureFixture,
                                                         events: list[tuple[str, bytes]]) -> None:
    caplog.clear()
    rig = DaemonRig.moving()
    try:
        rig.run(0.3)  # moving
        for channel, data in events:
            with ach.Channel(channel, create=False) as ch:
                ch.put(data)
            bad_before = (rig.loop.ch.ref.bad_frames, rig.loop.ch.collide.bad_frames)
            with caplog.at_level(logging.WARNING, logger="mds_ach.nodes.daemon"):
                rig.run(0.1, move=False)  # one cycle takes the frame
            st_ = rig.status()
            if channel == mds.MDS_CHAN_DAEMON_INPUT_NAME:
                if len(data) != ctypes.sizeof(MDS_REF):
                    assert rig.loop.ch.ref.bad_frames == bad_before[0] + 1  # refused and counted
                else:
                    ref, mode = ref_arrays(MDS_REF.from_buffer_copy(data))
                    for a in ENABLED:
                        if not math.isfinite(ref[a]) or not 0 <= mode[a] <= 3:
                            assert st_.joint_flags[a] & ds.JOINT_REFUSED, f"{TABLE.get(a).short} not refused"
                        elif not TABLE.get(a).within_limits(ref[a]):
                            assert st_.joint_flags[a] & ds.JOINT_CLAMPED, f"{TABLE.get(a).short} not clamped"
            elif channel == mds.MDS_CHAN_BOARD_CMD_NAME:
                if len(data) == ctypes.sizeof(MDS_CMD):
                    cmd = MDS_CMD.from_buffer_copy(data)
                    assert st_.cmd_seq == cmd.seq  # every command gets an answer
                    known = cmd.cmd in (mds.MDS_CMD_ENABLE, mds.MDS_CMD_DISABLE, mds.MDS_CMD_HOME, mds.MDS_CMD_RESET,
                                        mds.MDS_CMD_ZERO_ENCODER, mds.MDS_CMD_RESET_BUS)
                    if not known or (cmd.cmd != mds.MDS_CMD_RESET_BUS and cmd.address and cmd.address not in ENABLED):
                        assert st_.cmd_result == ds.CMD_REFUSED
                else:
                    assert f"ignored a {len(data)}-byte frame" in caplog.text  # reported
            elif len(data) != ctypes.sizeof(MDS_COLLIDE):
                assert rig.loop.ch.collide.bad_frames == bad_before[1] + 1
            assert_state_safe(rig)
        rig.run(0.5)  # and it still moves the arms, safely
        assert_state_safe(rig)
    finally:
        rig.close()


# --------------------------------------------------------------------------------------------- pipeline inputs


@pytest.fixture(scope="module")
def gate_parts() -> tuple:
    from mds_ach.nodes.collision import build_gate_parts

    return build_gate_parts()


mux_events = st.lists(st.tuples(st.integers(0, 2), ref_payloads), min_size=1, max_size=8)


@FUZZ
@given(events=mux_events)
def test_pipeline_nodes_never_pass_on_what_they_must_refuse(fresh: None, gate_parts: tuple,
                                                            events: list[tuple[int, bytes]]) -> None:
    """mux inputs -> MuxCore -> FilterCore -> Gate -> mds-ref-gated -> daemon, each with its real decision code. Frames
    of the wrong size are dropped (StructChannel counts them); NaN/Inf frames are refused by the mux and counted; the
    filter ignores non-finite targets with a warning; the gate passes only finite, in-limit, collision-free
    references with valid modes."""
    from mds_ach.nodes.filter import FilterCore, load_config
    from mds_ach.nodes.gate import Gate
    from mds_ach.nodes.mux import MuxCore
    from mds_ach.nodes.mux import load_config as mux_config
    from mds_ach.nodes.pipeline import make_ref

    model, gate_cfg, lower, upper = gate_parts
    rig = DaemonRig.moving()
    try:
        start = np.array([rig.loop.state.joint[a].ref for a in range(MDS_JOINT_COUNT)])
        mode0 = np.ones(MDS_JOINT_COUNT, dtype=np.int16)
        mux = MuxCore(mux_config()["controllers"], start, mode0)
        filt = FilterCore(load_config(), start, mode0)
        now = 1000.0
        gate = Gate(model, gate_cfg, start, mode0, now, lower, upper)
        assert not gate.current.collides
        for index, data in events:
            now += 0.05
            if len(data) != ctypes.sizeof(MDS_REF):
                continue  # StructChannel never hands such a frame out (tested in test_ach_api); nothing to apply
            ref, mode = ref_arrays(MDS_REF.from_buffer_copy(data))
            refused_before = int(mux.refused[index])
            mux.update(index, ref, mode, now)
            if not np.isfinite(ref[list(KNOWN_ADDRESSES)]).all():
                assert mux.refused[index] == refused_before + 1
            assert np.isfinite(mux.ref[list(KNOWN_ADDRESSES)]).all()
            problem = filt.set_target(mux.ref, mux.mode)
            assert problem is None or "non-finite" in problem
            for _ in range(4):  # the filter at 40 Hz, the gate on each of its frames
                now += 0.025
                decision = gate.process(filt.step(), filt.out_mode(), now)
                out = decision.ref[list(KNOWN_ADDRESSES)]
                out_mode = decision.mode[list(KNOWN_ADDRESSES)]
                assert np.isfinite(out).all() and ((out_mode >= 0) & (out_mode <= 3)).all()
                assert (decision.ref >= lower - 1e-9).all() and (decision.ref <= upper + 1e-9).all()
                assert not model.check(model.q_from_ref(decision.ref)).collides
                rig.ref_out.put(make_ref(decision.ref, decision.mode))
            rig.run(0.1, move=False)
            assert_state_safe(rig)
    finally:
        rig.close()


# --------------------------------------------------------------------------------------------- CAN frames


def _frame(kind: str, data: st.DrawFn) -> tuple[str, int, bytes, bool]:
    """(kind, arbitration id, data, extended) for one random frame 'from the bus'."""
    draw = data
    if kind == "junk":
        return kind, draw(st.integers(0, 0x7FF)), draw(st.binary(max_size=8)), False
    if kind == "extended":
        return kind, draw(st.integers(0, 0x1FFFFFFF)), draw(st.binary(max_size=8)), True
    if kind == "short":
        return kind, mcb.HOST_SID, draw(st.binary(max_size=7)), False
    address = draw(st.one_of(st.sampled_from(ENABLED), st.integers(0, 0xFFFF)))
    if kind == "position":
        value = draw(nasty_floats)
        word = struct.unpack("<I", struct.pack("<f", value if abs(value) < 3e38 or not math.isfinite(value)
                                               else math.copysign(3e38, value)))[0]
        return kind, mcb.HOST_SID, mcb.pack(mcb.Response.STATE, mcb.StateArg.ACTUAL_POSITION, word, address), False
    code = draw(st.one_of(st.sampled_from([int(r) for r in mcb.Response]), st.integers(0, 0xFF)))
    return kind, mcb.HOST_SID, mcb.pack(code, draw(st.integers(0, 0xFF)), draw(st.integers(0, 2**32 - 1)),
                                        address), False


@st.composite
def can_frames(draw: st.DrawFn) -> list[tuple[str, int, bytes, bool]]:
    kinds = draw(st.lists(st.sampled_from(["junk", "extended", "short", "position", "reply", "error"]),
                          min_size=1, max_size=20))
    return [("error", draw(st.integers(1, 0x1FF)), bytes([0, draw(st.integers(0, 0xFF))]), False)
            if k == "error" else _frame(k, draw) for k in kinds]


@FUZZ
@given(frames=can_frames(), compliant=st.booleans())
def test_random_can_frames_into_the_daemon(fresh: None, frames: list[tuple[str, int, bytes, bool]],
                                           compliant: bool) -> None:
    """Whatever arrives from the bus: no crash, every frame counted, nothing unsafe sent, never a non-finite
    position taken as a measurement. In compliant mode the garbage positions even become references: the limits
    still hold."""
    from mds_ach.bus.constants import CAN_ERR_CRTL

    rig = DaemonRig.moving()
    mode = mds.MDS_REF_MODE_COMPLIANT if compliant else mds.MDS_REF_MODE_REF
    try:
        rig.run(0.3, mode=mode)
        before = rig.status()
        for kind, arb, data, extended in frames:
            if kind == "error":
                rig.net.inject_error_frame(arb, status=data[1] if arb & CAN_ERR_CRTL else 0)
            else:
                rig.net.inject_frame(arb, data, is_extended_id=extended)
        rig.run(0.2, mode=mode)
        after = rig.status()
        received = (after.rx_frames - before.rx_frames) + (after.error_frames - before.error_frames)
        assert received >= len(frames)
        malformed = sum(1 for k, _, d, e in frames if k in ("extended", "short") or (k == "junk" and len(d) != 8))
        assert after.malformed_frames - before.malformed_frames >= malformed
        assert after.error_frames - before.error_frames == sum(1 for k, *_ in frames if k == "error")
        for s in rig.states[-2:]:
            for a in ENABLED:
                assert not math.isinf(s.joint[a].pos)
        assert_state_safe(rig)
    finally:
        rig.close()


@FUZZ
@given(arb=st.integers(-5, 0x800), data=st.binary(max_size=12))
def test_mcb_decode_takes_any_bytes(arb: int, data: bytes) -> None:
    try:
        frame = mcb.decode(arb, data)
    except ValueError:
        assert len(data) != mcb.DLC or not 0 <= arb <= 0x7FF
        return
    assert str(frame) and frame.to_raw().data == bytes(data) or frame.is_response is False


# --------------------------------------------------------------------------------------------- console


words = st.sampled_from(["goto", "get", "fk", "ik", "left", "right", "wait", "zeroall", "help", "exit", "filter",
                         "LSP", "lep", "LeftShoulderExt", "NKY", "XYZ", "0x5f", "3", "7", "-1", "nan", "inf", "-inf",
                         "1e309", "0.1", "-0.5", "abc", "#", ""])
console_lines = st.one_of(st.text(max_size=60), st.lists(st.one_of(words, st.text(max_size=8)), max_size=9).map(
    " ".join), st.lists(words, max_size=9).map(" ".join))


@pytest.fixture
def console_rig(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple]:
    """A daemon publishing mds-state (simulated bus), the legacy input channel, and a console with short waits."""
    from mds_ach.tools import console

    remove_mds_channels()
    for name, value in (("GOTO_TIMEOUT", 0.05), ("IK_TIMEOUT", 0.05), ("IK_MOTION_TIMEOUT", 0.05),
                        ("STATE_WAIT", 0.05), ("RELEASE_TIMEOUT", 0.05)):
        monkeypatch.setattr(console, name, value)
    rig = DaemonRig.moving()
    ach.create(mds.MDS_CHAN_REF_FILTER_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    out: list[str] = []
    con = console.Console(out=out.append, err=out.append, progress=lambda: None)
    try:
        yield rig, con, out
    finally:
        con.close()
        rig.close()
        remove_mds_channels()


@FUZZ
@given(line=console_lines)
def test_random_console_lines(console_rig: tuple, line: str) -> None:
    from mds_ach.tools import console

    rig, con, out = console_rig
    try:
        cmd = console.parse(line)
    except console.CommandError as exc:
        assert str(exc)
        cmd = None
    out.clear()
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as ch:
        ch.flush()
        ok = con.run_line(line)
        assert isinstance(ok, bool)
        if not ok:
            assert out, "a failed command printed nothing"
        frame = MDS_REF()
        status, size = ch.get(frame, last=True)
    if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):  # something was sent: only in-limit, finite targets
        assert ok and isinstance(cmd, console.Goto) and size == ctypes.sizeof(MDS_REF)
        value = frame.joint[cmd.joint.address].ref
        assert value == cmd.value and TABLE.get(cmd.joint.address).within_limits(value)
    rig.run(0.1, move=False)
    assert_state_safe(rig)


# --------------------------------------------------------------------------------------------- ROS commands


@pytest.fixture(scope="module")
def limits() -> dict[str, tuple[float, float]]:
    from mds_ach_bridge.limits import load_limits

    return load_limits()


names = st.one_of(st.sampled_from(list(mds.joints.MODEL_JOINTS)), st.sampled_from(["", "lsp", "XYZ", "LEB", "NK Y"]),
                  st.text(max_size=6))


def assert_in_limits(values: dict[str, float], limits: dict[str, tuple[float, float]]) -> None:
    for n, v in values.items():
        lo, hi = limits[n]
        assert math.isfinite(v) and lo <= v <= hi, f"{n} = {v} accepted"


@FUZZ
@given(joint_names=st.lists(names, max_size=20), positions=st.lists(nasty_floats, max_size=20),
       array=st.lists(nasty_floats, max_size=20))
def test_random_joint_commands_into_the_bridge(limits: dict, joint_names: list[str], positions: list[float],
                                               array: list[float]) -> None:
    """sensor_msgs/JointState and std_msgs/Float64MultiArray, built as real messages, through the functions the
    bridge's callbacks call: all or nothing, every accepted value finite and within its limits."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from mds_ach_bridge.commands import CommandError, positions_by_name, positions_from_array

    msg = JointState(name=joint_names, position=positions)
    try:
        values = positions_by_name(msg.name, msg.position, limits)
    except CommandError as exc:
        assert str(exc)
    else:
        assert set(values) == set(joint_names) and len(joint_names) == len(positions)
        assert_in_limits(values, limits)
    arr = Float64MultiArray(data=array)
    try:
        values = positions_from_array(arr.data, limits)
    except CommandError as exc:
        assert str(exc)
    else:
        assert_in_limits(values, limits)


points = st.lists(st.tuples(nasty_floats, st.lists(nasty_floats, max_size=4), st.lists(nasty_floats, max_size=4)),
                  max_size=5)


@FUZZ
@given(joint_names=st.lists(names, max_size=4), pts=points, probe=st.lists(st.floats(-1, 30), max_size=10))
def test_random_trajectories_into_the_bridge(limits: dict, joint_names: list[str],
                                             pts: list[tuple[float, list[float], list[float]]],
                                             probe: list[float]) -> None:
    """trajectory_msgs/JointTrajectory through the bridge's trajectory validation: an accepted trajectory never
    samples outside the limits, whenever it is sampled (after anchoring at an in-limit current reference)."""
    from builtin_interfaces.msg import Duration
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    from mds_ach_bridge import trajectory
    from mds_ach_bridge.commands import CommandError

    msg = JointTrajectory(joint_names=joint_names)
    for t, pos, vel in pts:
        if not (math.isfinite(t) and 0 <= t < 2**31):
            t = 0.5
        msg.points.append(JointTrajectoryPoint(positions=pos, velocities=vel,
                                               time_from_start=Duration(sec=int(t), nanosec=int((t % 1) * 1e9))))
    points_ = [(p.time_from_start.sec + p.time_from_start.nanosec * 1e-9, p.positions, p.velocities)
               for p in msg.points]
    try:
        traj = trajectory.build(msg.joint_names, points_, 100.0, limits)
        traj = traj.anchor({n: sum(limits[n]) / 2 for n in traj.names}, limits)
    except CommandError as exc:
        assert str(exc)
        return
    for t in [0.0, *probe, traj.times[-1], traj.times[-1] + 1]:
        values, _ = traj.sample(100.0 + t)
        assert_in_limits(values, limits)


@FUZZ
@given(arm=st.sampled_from(["left", "right", "up", ""]), pos=st.tuples(nasty_floats, nasty_floats, nasty_floats),
       quat=st.tuples(nasty_floats, nasty_floats, nasty_floats, nasty_floats), dof=st.integers(-2, 9))
def test_random_ik_poses_into_the_bridge(arm: str, pos: tuple, quat: tuple, dof: int) -> None:
    """geometry_msgs/PoseStamped -> MDS_IK request: refused with a reason, or finite with a valid arm and DOF."""
    from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion

    from mds_ach_bridge.commands import CommandError
    from mds_ach_bridge.ik_request import make_request

    msg = PoseStamped(pose=Pose(position=Point(x=pos[0], y=pos[1], z=pos[2]),
                                orientation=Quaternion(x=quat[0], y=quat[1], z=quat[2], w=quat[3])))
    p, o = msg.pose.position, msg.pose.orientation
    try:
        req = make_request(arm, (p.x, p.y, p.z), (o.x, o.y, o.z, o.w), dof)
    except CommandError as exc:
        assert str(exc)
        return
    assert req.move in (mds.LEFT, mds.RIGHT) and 1 <= req.arm[req.move].ik_method <= 6
    a = req.arm[req.move]
    assert all(math.isfinite(v) for v in (a.t_x, a.t_y, a.t_z, a.r_x, a.r_y, a.r_z))
