"""The daemon loop against the simulated MDS bus, through the real Ach channels.

Most tests step ``DaemonLoop.cycle()`` on a simulated clock (shared with the simulated bus), so a second of
robot time costs milliseconds and every assertion is about behaviour, never about timing. One test runs the
loop thread on the real clock and one runs the real ``daemon --nocan`` executable with ROS.
"""

from __future__ import annotations

import ctypes
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import can
import pytest
from conftest import VENV_BIN, wait_for

import mds_ach as mds
from mds_ach import canio, config, daemon, mcb
from mds_ach import daemon_status as ds
from mds_ach.channels import StructChannel
from mds_ach.daemon_loop import CATCHUP_VELOCITY, DaemonChannels, DaemonLoop, sleep_until
from mds_ach.filters import filter_length
from mds_ach.mcb import Command, StateArg
from mds_ach.msgs import MDS_CMD, MDS_COLLIDE, MDS_REF, MDS_STATE
from mds_ach.simbus import CAN_ERR_CRTL, ManualClock, SimNetwork

TABLE = config.load("default")


@dataclass
class Rig:
    """A daemon loop on a simulated clock, its simulated robot, and client handles on the channels."""

    clock: ManualClock
    net: SimNetwork
    io: canio.CanIO
    channels: DaemonChannels
    loop: DaemonLoop
    ref_out: StructChannel
    state_in: StructChannel
    status_in: StructChannel
    collide_out: StructChannel
    cmd_out: StructChannel
    last_state: MDS_STATE | None = None

    def step(self, n: int = 1) -> MDS_STATE:
        for _ in range(n):
            start = self.clock.now
            self.loop.cycle(deadline=start, start=start)
            self.clock.now = max(self.clock.now, start + self.loop.period)
        return self.state()

    def state(self) -> MDS_STATE:
        """The newest mds-state a client sees (the last one again if nothing new was published)."""
        frame = self.state_in.latest()
        if frame is not None:
            self.last_state = frame
        assert self.last_state is not None, "the daemon published no mds-state"
        return self.last_state

    def put_ref(self, mode: int = mds.MDS_REF_MODE_REF, **refs: float) -> None:
        """Like a client: start from what the daemon commands now, change some joints."""
        ref = MDS_REF()
        st = self.loop.state
        for j in TABLE:
            ref.joint[j.address].ref = st.joint[j.address].ref
            ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
        for short, value in refs.items():
            ref.joint[TABLE[short].address].ref = value
            ref.joint[TABLE[short].address].mode = mode
        self.ref_out.put(ref)

    def frames_to(self, address: int) -> list[mcb.McbFrame]:
        return [f for _, f in self.net.commands if f.arbitration_id == address]

    def measured(self, short: str) -> float:
        j = TABLE[short]
        return j.to_joint(self.net.position(j.address))

    def command(self, code: int, address: int = 0, seq: int = 1) -> None:
        self.cmd_out.put(MDS_CMD(seq=seq, cmd=code, address=address))


def make_rig(rate: float = 10.0, pose: dict[str, float] | None = None, bitrate: int | None = 1_000_000,
             **loop_kwargs) -> Rig:
    clock = ManualClock()
    net = SimNetwork.from_table(TABLE, pose=pose, clock=clock, bitrate=bitrate)
    io = canio.make_canio(nocan=True, network=net)
    channels = DaemonChannels.open()
    loop = DaemonLoop(TABLE, io, channels, rate_hz=rate, nocan=True, clock=clock, **loop_kwargs)
    rig = Rig(clock, net, io, channels, loop, StructChannel(mds.MDS_CHAN_REF_NAME, MDS_REF),
              StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE),
              StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS),
              StructChannel(mds.MDS_CHAN_COLLIDE_NAME, MDS_COLLIDE),
              StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD))
    return rig


def close_rig(rig: Rig) -> None:
    rig.loop.stop()
    rig.io.close()
    rig.channels.close()
    for ch in (rig.ref_out, rig.state_in, rig.status_in, rig.collide_out, rig.cmd_out):
        ch.close()


@pytest.fixture
def rig(clean_shm) -> Iterator[Rig]:
    # The start-up catch-up ramp is off here so that the per-cycle semantics are visible;
    # test_restart_ramps_to_the_running_reference covers it.
    r = make_rig(pose={"LEP": -1.0, "RSR": -0.6, "NKY": 0.1}, catchup_velocity=math.inf)
    r.loop.start_up()
    r.state()
    yield r
    close_rig(r)


def status_of(rig: Rig) -> ds.MDS_DAEMON_STATUS:
    frame = rig.status_in.latest()
    assert frame is not None
    return frame


# --- start-up ---------------------------------------------------------------------------------------------


def test_start_up_begins_at_the_measured_pose_without_a_step(rig: Rig) -> None:
    st = rig.loop.state
    for short, q in (("LEP", -1.0), ("RSR", -0.6), ("NKY", 0.1), ("WST", 0.0)):
        a = TABLE[short].address
        assert st.joint[a].pos == pytest.approx(q, abs=1e-6)
        assert st.joint[a].ref == st.joint[a].ref_r == pytest.approx(q, abs=1e-6)
        assert st.joint[a].active == 1
    # Only position queries went out: no motion frame at start, and none while nothing changes.
    rig.step(20)
    assert all(f.command is Command.QUERY_STATE for _, f in rig.net.commands)
    assert rig.measured("LEP") == pytest.approx(-1.0, abs=1e-6)
    # mds-param is published once, in the legacy layout.
    param = StructChannel(mds.MDS_CHAN_PARAM_NAME, mds.MDS_JOINT_PARAM).latest()
    assert param is not None and param.joint[0x4C].direction == -1 and param.joint[0x4C].enabled == 1


def test_start_up_without_a_robot_uses_the_home_pose(clean_shm) -> None:
    r = make_rig(pose={"LEP": -1.0})
    try:
        for a in r.net.addresses:
            r.net.set_offline(a)
        assert r.loop.start_up() == 0
        st = r.state()
        for j in TABLE:
            assert st.joint[j.address].ref == pytest.approx(j.home)
            assert math.isnan(st.joint[j.address].pos) and st.joint[j.address].active == 0
        r.step(5)
        assert not [f for _, f in r.net.commands if f.command is Command.SET]
        assert status_of(r).stale_count == len(TABLE.enabled)
    finally:
        close_rig(r)


# --- references -------------------------------------------------------------------------------------------


def test_reference_reaches_the_joint_and_shows_in_state(rig: Rig) -> None:
    rig.put_ref(LEP=-0.6, RSP=0.2)
    st = rig.step()
    lep, rsp = TABLE["LEP"], TABLE["RSP"]
    assert st.joint[lep.address].ref_r == -0.6 and st.joint[lep.address].ref == -0.6
    assert st.joint[lep.address].ref_c_send == -0.6
    sets = [f for f in rig.frames_to(lep.address) if f.command is Command.SET]
    assert [f.argument for f in sets] == [StateArg.TRAJECTORY_ACCELERATION, StateArg.MOVETO_TARGET,
                                          StateArg.TRAJECTORY_MODE, StateArg.TRAJECTORY_PERIOD]
    assert sets[1].value == pytest.approx(lep.to_counts(-0.6), rel=1e-6)
    assert sets[0].value == pytest.approx(TABLE.accel_counts(lep), rel=1e-6)
    st = rig.step(30)  # 3 s: a 0.4 rad move at 80 deg/s^2 takes ~1.35 s
    assert st.joint[lep.address].pos == pytest.approx(-0.6, abs=1e-5)
    assert st.joint[rsp.address].pos == pytest.approx(0.2, abs=1e-5)
    assert rig.measured("LEP") == pytest.approx(-0.6, abs=1e-5)
    assert st.joint[lep.address].active == 1 and st.joint[lep.address].vel == 0.0
    assert st.time > 0 and abs(st.time - time.monotonic()) < 5  # CLOCK_MONOTONIC seconds


def test_zero_order_hold(rig: Rig) -> None:
    rig.put_ref(LSP=0.3)
    rig.step()
    n_frames = len(rig.frames_to(0x5F))
    st = rig.step(10)  # no new mds-ref frames: the last reference holds, nothing is re-sent
    assert st.joint[0x5F].ref_r == st.joint[0x5F].ref == 0.3
    assert len(rig.frames_to(0x5F)) == n_frames == 4
    rig.put_ref(LSP=0.3)  # a new frame with the same value: still nothing to send
    rig.step(2)
    assert len(rig.frames_to(0x5F)) == 4
    rig.put_ref(LSP=0.31)
    rig.step()
    assert len(rig.frames_to(0x5F)) == 8


def test_limits_clamp_and_report(rig: Rig) -> None:
    lep = TABLE["LEP"]
    rig.put_ref(LEP=0.5)  # beyond the elbow's upper limit (about -0.0153)
    st = rig.step()
    s = st.joint[lep.address]
    assert s.ref_r == 0.5 and s.ref == pytest.approx(lep.upper)
    moveto = [f for f in rig.frames_to(lep.address) if f.argument is StateArg.MOVETO_TARGET][-1]
    assert lep.to_joint(moveto.value) == pytest.approx(lep.upper, abs=1e-6)
    status = status_of(rig)
    assert status.refs_clamped == 1 and status.joint_flags[lep.address] & ds.JOINT_CLAMPED
    rig.step(40)
    assert rig.measured("LEP") <= lep.upper + 1e-6
    assert status_of(rig).refs_clamped == 1  # counted once per received value, not per held cycle


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_reference_is_refused(rig: Rig, bad: float) -> None:
    rig.put_ref(LSY=0.2)
    rig.step()
    rig.put_ref(LSY=bad, LSP=0.1)  # the bad joint is refused, the others in the frame still apply
    st = rig.step()
    assert st.joint[0x4D].ref_r == 0.2 and st.joint[0x4D].ref == 0.2
    assert st.joint[0x5F].ref == 0.1
    status = status_of(rig)
    assert status.refs_refused == 1 and status.joint_flags[0x4D] & ds.JOINT_REFUSED
    assert all(math.isfinite(f.value) for f in rig.frames_to(0x4D) if isinstance(f.value, float))
    rig.put_ref(LSY=0.25)
    st = rig.step()
    assert st.joint[0x4D].ref == 0.25 and not status_of(rig).joint_flags[0x4D] & ds.JOINT_REFUSED


def test_unknown_mode_is_refused(rig: Rig) -> None:
    rig.put_ref(mode=7, LSY=0.2)
    st = rig.step()
    assert st.joint[0x4D].ref != 0.2 and status_of(rig).refs_refused == 1


def test_disabled_joints_get_no_frames(rig: Rig) -> None:
    disabled = [j for j in TABLE if not j.enabled]
    assert len(disabled) == 26
    rig.put_ref(**{j.short: j.upper * 0.5 for j in disabled}, LEP=-0.9)
    rig.step(10)
    for j in disabled:
        assert rig.frames_to(j.address) == [], j.short
        assert rig.net.position(j.address) == 0.0
    assert rig.frames_to(TABLE["LEP"].address)
    # A joint disabled at run time gets its DISABLE frame and then nothing more.
    rig.command(mds.MDS_CMD_DISABLE, TABLE["LSP"].address, seq=5)
    rig.step()
    assert [f.command for f in rig.frames_to(0x5F)] == [Command.DISABLE]
    status = status_of(rig)
    assert (status.cmd_seq, status.cmd_result) == (5, ds.CMD_OK)
    rig.put_ref(LSP=0.4)
    rig.step(5)
    assert [f.command for f in rig.frames_to(0x5F)] == [Command.DISABLE]
    assert rig.state().joint[0x5F].enabled == 0


@pytest.mark.parametrize("rate", [10.0, 50.0])
def test_mode_0_filter_reaches_95_percent_in_4_seconds(clean_shm, rate: float) -> None:
    r = make_rig(rate=rate, bitrate=None)
    try:
        r.loop.start_up()
        r.step()  # the loop's first cycle runs right after start-up (no time passes: nothing may move yet)
        lsr = TABLE["LSR"]
        start = r.loop.state.joint[lsr.address].ref
        target = start + 0.8
        r.put_ref(mode=mds.MDS_REF_MODE_REF_FILTER, LSR=target)
        n = round(rate * 4.0)
        refs = [r.step().joint[lsr.address].ref for _ in range(n)]
        fraction = [(q - start) / (target - start) for q in refs]
        L = filter_length(rate)
        assert r.loop.L == pytest.approx(L)
        assert fraction[0] == pytest.approx(1 / L)  # theta_1 = (theta_0 (L-1) + theta_des) / L
        assert fraction[n - 2] < 0.95 <= fraction[n - 1] + 1e-9
        assert all(b > a for a, b in zip(fraction, fraction[1:], strict=False))
        if rate == 10.0:
            r.step(int(rate * 10))
            assert r.measured("LSR") == pytest.approx(target, abs=1e-3)  # the robot follows the filtered ref
    finally:
        close_rig(r)


def test_mode_2_compliant_follows_the_encoder(rig: Rig) -> None:
    wst = TABLE["WST"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, WST=0.3)
    rig.step(2)
    assert rig.state().joint[wst.address].ref == pytest.approx(0.0, abs=1e-6)  # stays where it is
    rig.net.set_position(wst.address, wst.to_counts(-0.2))  # pushed by hand
    st = rig.step(3)
    assert st.joint[wst.address].ref == pytest.approx(-0.2, abs=1e-6)
    assert rig.measured("WST") == pytest.approx(-0.2, abs=1e-6)  # and holds there


def test_mode_3_encoder_filter(rig: Rig) -> None:
    rsr = TABLE["RSR"]
    pos = rig.state().joint[rsr.address].pos
    target = pos + 0.4
    rig.put_ref(mode=mds.MDS_REF_MODE_ENC_FILTER, RSR=target)
    st = rig.step()
    L = rig.loop.L
    # theta = (theta_enc (L-1) + theta_des) / L, from the encoder reading of this cycle's start
    assert st.joint[rsr.address].ref == pytest.approx((pos * (L - 1) + target) / L, abs=1e-6)
    rig.step(150)
    assert rig.state().joint[rsr.address].pos == pytest.approx(target, abs=2e-3)


# --- freshness and faults -----------------------------------------------------------------------------------


def test_silent_node_is_stale_never_fresh(rig: Rig) -> None:
    lep = TABLE["LEP"]
    rig.step(2)
    rig.net.set_offline(lep.address)
    last = rig.state().joint[lep.address].pos
    cycles_to_stale = math.ceil(rig.loop.stale_after / rig.loop.period)
    states = [rig.step() for _ in range(cycles_to_stale + 1)]
    assert states[-1].joint[lep.address].active == 0
    assert states[-1].joint[lep.address].pos == last  # the old value is kept but not marked fresh
    status = status_of(rig)
    assert status.stale_count == 1 and status.joint_flags[lep.address] & ds.JOINT_STALE
    assert status.joint_age[lep.address] >= rig.loop.stale_after
    assert status.replies_expected == len(TABLE) - 1  # a stale node is not waited for
    # Every cycle either had a reply within the staleness limit or was reported stale: never stale-as-fresh.
    for st in states:
        assert st.joint[lep.address].active == 0 or st.joint[TABLE["LSP"].address].active == 1
    rig.net.set_offline(lep.address, False)
    st = rig.step()
    assert st.joint[lep.address].active == 1 and status_of(rig).stale_count == 0


def test_dropped_and_late_replies(clean_shm) -> None:
    r = make_rig(bitrate=None)
    try:
        r.loop.start_up()
        r.state()
        r.net.drop_replies(0x4C, count=2)
        st = r.step()
        assert st.joint[0x4C].active == 1  # one missed reply is within the staleness limit
        r.step()
        r.net.delay_replies(0x5F, 0.08)  # later than the reply window: taken next cycle
        s1 = r.step()
        assert status_of(r).replies_received == len(TABLE) - 1
        s2 = r.step()
        assert s1.joint[0x5F].active == 1 and s2.joint[0x5F].active == 1
        assert status_of(r).stale_count == 0
    finally:
        close_rig(r)


def test_unknown_nodes_malformed_and_error_frames_are_counted(rig: Rig) -> None:
    rig.net.inject_frame(0x10, bytes(mcb.encode_state_reply(0xB0, StateArg.ACTUAL_POSITION, 0.0).data))
    rig.net.inject_frame(0x10, b"\x05\x04")
    rig.net.inject_frame(0x10, bytes(8), is_extended_id=True)
    nan_counts = mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, 0x7FC00000, 0x4C)
    rig.net.inject_frame(0x10, nan_counts)
    rig.net.inject_frame(0x10, bytes(mcb.encode_warning(0x4C, mcb.ErrorCode.TRACKING_ERROR).data))
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=0x10)
    st = rig.step()
    status = status_of(rig)
    assert status.unknown_node_frames == 1
    assert status.malformed_frames == 3  # short, extended, NaN position
    assert status.node_errors == 1
    assert status.error_frames == 1 and status.bus_state == ds.BUS_STATE_PASSIVE
    assert math.isfinite(st.joint[0x4C].pos)
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=0x40)  # CAN_ERR_CRTL_ACTIVE: back to error-active
    rig.step()
    assert status_of(rig).bus_state == ds.BUS_STATE_ACTIVE


def test_bus_off_and_reset_bus_command(rig: Rig) -> None:
    rig.net.bus_off()
    rig.step()
    status = status_of(rig)
    assert status.bus_state == ds.BUS_STATE_BUS_OFF and status.bus_off_count == 1
    rig.put_ref(LEP=-0.7)
    rig.step(3)
    assert not [f for f in rig.frames_to(0x4C) if f.command is Command.SET]  # nothing gets through
    assert status_of(rig).tx_errors >= 3  # the position queries fail
    rig.command(mds.MDS_CMD_RESET_BUS, seq=9)
    rig.step(2)
    status = status_of(rig)
    assert status.bus_state == ds.BUS_STATE_ACTIVE and status.bus_resets == 1
    assert (status.cmd_seq, status.cmd_result) == (9, ds.CMD_OK)
    # The held target goes out after the reset.
    moveto = [f for f in rig.frames_to(0x4C) if f.argument is StateArg.MOVETO_TARGET]
    assert moveto and TABLE["LEP"].to_joint(moveto[-1].value) == pytest.approx(-0.7, abs=1e-6)
    rig.step(20)
    assert rig.state().joint[0x4C].pos == pytest.approx(-0.7, abs=1e-5)


def test_corrupt_input_channel_holds_the_reference(rig: Rig) -> None:
    """A writer killed inside a put leaves mds-ref marked dirty: the daemon keeps its loop and holds."""
    from mds_ach import ach

    rig.put_ref(LEP=-0.8)
    rig.step()
    with ach.Channel(mds.MDS_CHAN_REF_NAME, create=False) as raw:
        raw._i32[raw._i_dirty] = 1  # what a writer that died between 'dirty' and 'clean' leaves behind
    states = [rig.step() for _ in range(5)]
    assert all(st.joint[0x4C].ref == -0.8 for st in states)
    status = status_of(rig)
    assert status.channel_errors == 5 and status.cycle == rig.loop.cycle_count
    assert "channel-err 5" in ds.summary_line(status)


def test_missing_acks_resend_the_target(clean_shm) -> None:
    r = make_rig(bitrate=None, catchup_velocity=math.inf)
    try:
        r.loop.start_up()
        r.state()
        r.net.drop_replies(0x4C, count=4)  # the 4 ACKs of the next sequence
        r.put_ref(LEP=-0.8)
        r.step(5)
        status = status_of(r)
        assert status.acks_missing == 1
        movetos = [f for f in r.frames_to(0x4C) if f.argument is StateArg.MOVETO_TARGET]
        assert len(movetos) == 2 and movetos[0].raw == movetos[1].raw
    finally:
        close_rig(r)


def test_collision_gate_holds_and_releases(rig: Rig) -> None:
    collide = MDS_COLLIDE()
    collide.isCollide = 1
    collide.joint[mds.COLLIDE_L_HAND].isCollide = 1
    rig.collide_out.put(collide)
    rig.put_ref(LEP=-0.5)
    st = rig.step(3)
    assert st.collide.isCollide == 1 and st.collide.joint[mds.COLLIDE_L_HAND].isCollide == 1
    assert not [f for f in rig.frames_to(0x4C) if f.command is Command.SET]
    assert st.joint[0x4C].ref_c_send == pytest.approx(-1.0, abs=1e-6)  # not sent
    assert status_of(rig).collision_holds == 3
    rig.collide_out.put(MDS_COLLIDE())
    st = rig.step()
    assert st.joint[0x4C].ref_c_send == -0.5
    assert [f for f in rig.frames_to(0x4C) if f.argument is StateArg.MOVETO_TARGET]



def test_restart_ramps_to_the_running_reference(clean_shm) -> None:
    """A daemon (re)started while the pipeline keeps commanding a distant reference approaches it at the
    catch-up speed (daemon_loop.CATCHUP_VELOCITY), never in one step; afterwards references pass through again."""
    r = make_rig(pose={"LEP": -1.0})
    try:
        r.loop.start_up()
        r.state()
        r.put_ref(LEP=-0.2)
        refs = [r.step().joint[0x4C].ref for _ in range(12)]
        steps = [abs(b - a) for a, b in zip([-1.0] + refs, refs, strict=False)]
        assert max(steps) <= CATCHUP_VELOCITY * 0.1 + 1e-9  # at 10 Hz
        assert min(steps[:5]) > 0  # it does move towards the reference
        assert refs[-1] == pytest.approx(-0.2)
        r.put_ref(LEP=-0.5)
        assert r.step().joint[0x4C].ref == pytest.approx(-0.5)  # caught up: pass-through again
    finally:
        close_rig(r)


def test_reference_input_repaired_after_an_outage_is_approached_not_stepped(clean_shm) -> None:
    """mds-ref left corrupt (a writer died mid-put): the daemon holds; upstream moves on meanwhile. After
    `mds-ach repair` the first new reference is approached at the catch-up speed, like after a restart."""
    from mds_ach import ach, repair

    rig = make_rig(pose={"LEP": -1.0})
    try:
        rig.loop.start_up()
        rig.state()
        rig.put_ref(LEP=-1.0)
        rig.step(2)
        rig.put_ref(LEP=-0.95)
        assert rig.step().joint[0x4C].ref == pytest.approx(-0.95)  # normally a reference passes through at once
        with ach.Channel(mds.MDS_CHAN_REF_NAME, fast=False) as raw:
            raw._i32[raw._i_dirty] = 1  # what a writer killed inside its put leaves behind
        assert rig.step(3).joint[0x4C].ref == pytest.approx(-0.95)  # unreadable input: hold
        assert status_of(rig).channel_errors > 0
        assert repair.repair(mds.MDS_CHAN_REF_NAME).ok
        rig.put_ref(LEP=-0.2)  # where upstream got to in the meantime
        refs = [rig.step().joint[0x4C].ref for _ in range(10)]
        steps = [abs(b - a) for a, b in zip([-0.95] + refs, refs, strict=False)]
        assert max(steps) <= CATCHUP_VELOCITY * 0.1 + 1e-9 and refs[-1] == pytest.approx(-0.2)
        rig.put_ref(LEP=-0.5)
        assert rig.step().joint[0x4C].ref == pytest.approx(-0.5)  # caught up: pass-through again
    finally:
        close_rig(rig)


def test_collision_hold_is_per_arm(rig: Rig) -> None:
    """A left-arm collision report holds the left arm only: the right arm keeps moving (the gate's per-arm
    hold must not become a whole-robot stop at the daemon)."""
    collide = MDS_COLLIDE()
    collide.isCollide = 1
    collide.joint[mds.COLLIDE_L_FOREARM].isCollide = 1
    rig.collide_out.put(collide)
    rig.put_ref(LEP=-0.5, REP=-0.5)
    rig.step(3)
    assert not [f for f in rig.frames_to(0x4C) if f.command is Command.SET]  # LEP held
    assert [f for f in rig.frames_to(0x48) if f.argument is StateArg.MOVETO_TARGET]  # REP moves


def test_collision_report_without_parts_holds_everything(rig: Rig) -> None:
    collide = MDS_COLLIDE()
    collide.isCollide = 1  # e.g. an external legacy checker that flags no part
    rig.collide_out.put(collide)
    rig.put_ref(LEP=-0.5, REP=-0.5)
    rig.step(3)
    assert not [f for f in rig.frames_to(0x4C) if f.command is Command.SET]
    assert not [f for f in rig.frames_to(0x48) if f.command is Command.SET]


def test_collision_override_report_holds_nothing(rig: Rig) -> None:
    collide = MDS_COLLIDE()
    collide.isCollide = 2  # the gate's expert override: logged there, not a hold here
    collide.joint[mds.COLLIDE_L_HAND].isCollide = 1
    rig.collide_out.put(collide)
    rig.put_ref(LEP=-0.5)
    rig.step(3)
    assert [f for f in rig.frames_to(0x4C) if f.argument is StateArg.MOVETO_TARGET]

# --- setup commands ---------------------------------------------------------------------------------------


def test_home_command_homes_and_holds(rig: Rig) -> None:
    lep = TABLE["LEP"]
    rig.command(mds.MDS_CMD_HOME, lep.address, seq=3)
    rig.step(40)
    frames = rig.frames_to(lep.address)
    assert frames[0].argument is StateArg.TRAJECTORY_MODE and frames[0].value == mcb.TrajectoryMode.HOME
    assert not [f for f in frames[1:] if f.command is Command.SET]  # holds while homing and afterwards
    assert rig.net.physical[rig.net.index[lep.address]] == 0.0  # at the ROM middle
    st = rig.state()
    assert st.joint[lep.address].pos == pytest.approx(lep.home) and st.joint[lep.address].active == 1
    assert st.joint[lep.address].ref == pytest.approx(lep.home)
    status = status_of(rig)
    assert (status.cmd_seq, status.cmd_result) == (3, ds.CMD_OK)
    rig.put_ref(LEP=-1.1)  # a new reference ends the hold
    rig.step(20)
    assert rig.measured("LEP") == pytest.approx(-1.1, abs=1e-5)


def test_zero_encoder_does_not_move_the_joint(rig: Rig) -> None:
    rsr = TABLE["RSR"]
    physical = rig.net.physical[rig.net.index[rsr.address]]
    rig.command(mds.MDS_CMD_ZERO_ENCODER, rsr.address)
    st = rig.step(5)
    assert rig.net.physical[rig.net.index[rsr.address]] == physical
    assert st.joint[rsr.address].pos == pytest.approx(rsr.home)  # the count restarted at 0
    assert st.joint[rsr.address].ref == pytest.approx(rsr.home)
    assert [f.command for f in rig.frames_to(rsr.address)] == [Command.ZERO_ENCODER]


def test_commands_refused_for_unknown_or_disabled_joints(rig: Rig) -> None:
    rig.command(mds.MDS_CMD_ENABLE, TABLE["LYY"].address, seq=11)
    rig.step()
    status = status_of(rig)
    assert (status.cmd_seq, status.cmd_result) == (11, ds.CMD_REFUSED)
    assert rig.frames_to(TABLE["LYY"].address) == []
    rig.command(99, 0x4C, seq=12)
    rig.command(mds.MDS_CMD_RESET, 0x70, seq=13)  # two commands in one cycle: both are handled, in order
    rig.step()
    status = status_of(rig)
    assert (status.cmd_seq, status.cmd_result) == (13, ds.CMD_REFUSED)
    cmd = rig.loop.submit(mds.MDS_CMD_ENABLE, 0)
    rig.step()
    assert cmd.done.is_set() and cmd.result == ds.CMD_OK and "LSP" in cmd.message
    assert all(rig.frames_to(j.address)[-1].command is Command.ENABLE for j in TABLE.enabled)


def test_parse_command_text() -> None:
    assert daemon.parse_command("home LEP") == (mds.MDS_CMD_HOME, 0x4C)
    assert daemon.parse_command("RESETBUS") == (mds.MDS_CMD_RESET_BUS, 0)
    assert daemon.parse_command("enable all") == (mds.MDS_CMD_ENABLE, 0)
    assert daemon.parse_command("zero LeftShoulderExt") == (mds.MDS_CMD_ZERO_ENCODER, 0x5F)
    for bad in ("", "fly LEP", "home NOPE", "home LEP now"):
        with pytest.raises(ValueError):
            daemon.parse_command(bad)


# --- accounting and the loop thread ------------------------------------------------------------------------


def test_bus_load_is_counted_with_worst_case_stuffing(rig: Rig) -> None:
    rig.step()
    quiet = status_of(rig)
    frames = 1 + len(TABLE)  # one query, one reply per node
    assert quiet.bus_load == pytest.approx(100 * frames * 135 / (1_000_000 * 0.1))
    rig.put_ref(LEP=-0.9, RSP=0.1)
    rig.step()
    busy = status_of(rig)
    assert busy.bus_load == pytest.approx(100 * (frames + 2 * 8) * 135 / (1_000_000 * 0.1))
    assert busy.tx_frames - quiet.tx_frames == 1 + 8


def test_loop_thread_runs_on_the_real_clock_and_stops(clean_shm) -> None:
    net = SimNetwork.from_table(TABLE, bitrate=None)
    io = canio.make_canio(nocan=True, network=net)
    channels = DaemonChannels.open()
    loop = DaemonLoop(TABLE, io, channels, rate_hz=100.0, nocan=True)
    state_in = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    try:
        loop.start_up()
        loop.start()
        wait_for(lambda: loop.cycle_count >= 20, 10.0, what="20 cycles")
        assert loop.running and state_in.latest() is not None
        loop.stop()
        assert not loop.running
        n = loop.cycle_count
        time.sleep(0.05)
        assert loop.cycle_count == n
        snap = loop.snapshot()
        assert snap.cycle == n and snap.rate_hz == 100.0 and snap.measured_rate_hz > 0
    finally:
        loop.stop()
        io.close()
        channels.close()
        state_in.close()


def test_sleep_until_is_absolute() -> None:
    t0 = time.monotonic()
    sleep_until(t0 + 0.02)
    assert time.monotonic() >= t0 + 0.02
    sleep_until(t0)  # a past deadline returns at once
    assert time.monotonic() - t0 < 5


def test_record_and_replay_through_the_daemon(clean_shm, tmp_path: Path) -> None:
    log_file = tmp_path / "run.asc"
    clock = ManualClock()
    net = SimNetwork.from_table(TABLE, pose={"LSP": 0.25}, clock=clock, bitrate=None)
    io = canio.make_canio(nocan=True, network=net, can_log=str(log_file))
    channels = DaemonChannels.open()
    loop = DaemonLoop(TABLE, io, channels, rate_hz=10.0, clock=clock)
    loop.start_up()
    for _ in range(3):
        loop.cycle()
        clock.advance(0.1)
    loop.stop()
    io.close()
    sent = io.counters.tx_frames
    assert sent >= 4
    logged = list(can.LogReader(str(log_file)))
    assert sum(1 for m in logged if m.arbitration_id == mcb.BROADCAST_SID) == sent
    # Replay the recording into a fresh loop: it sees the recorded positions.
    io2 = canio.make_canio(replay=str(log_file), replay_speed=0)
    loop2 = DaemonLoop(TABLE, io2, channels, rate_hz=10.0)
    loop2.start_up(listen=0.2)
    loop2.cycle()
    assert loop2.state.joint[0x5F].pos == pytest.approx(0.25, abs=1e-6)
    io2.close()
    channels.close()


# --- the real executable ------------------------------------------------------------------------------------


def test_help() -> None:
    out = subprocess.run([str(VENV_BIN / "daemon"), "--help"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and "--nocan" in out.stdout and "--can-log" in out.stdout


def test_bad_configuration_is_a_clear_error(clean_shm, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")} | {"HOME": str(tmp_path)}
    out = subprocess.run([str(VENV_BIN / "daemon"), "--no-ros"], capture_output=True, text=True, timeout=30,
                         env=env, cwd=tmp_path)
    assert out.returncode == 2 and "no CAN interface configured" in out.stderr and "--nocan" in out.stderr
    out = subprocess.run([str(VENV_BIN / "daemon"), "--nocan", "--no-ros", "--sim-pose", "LEP=3"],
                         capture_output=True, text=True, timeout=30, env=env)
    assert out.returncode == 2 and "LEP=3.0 is outside" in out.stderr


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_executable_with_ros(clean_shm, sig: signal.Signals) -> None:
    """`daemon --nocan`: a reference reaches the simulated joint, /diagnostics and the command service work,
    and the signal stops it cleanly (exit 0)."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from diagnostic_msgs.srv import AddDiagnostics

    proc = subprocess.Popen([str(VENV_BIN / "daemon"), "--nocan", "--rate", "20", "--sim-pose", "LEP=-1.0",
                             "--ros-args", "-r", "__node:=mds_daemon"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = rclpy.create_node("test_daemon_client")
    diags: list[DiagnosticArray] = []
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    client = node.create_client(AddDiagnostics, "/mds_daemon/command")
    state_in = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    ref_out = StructChannel(mds.MDS_CHAN_REF_NAME, MDS_REF)
    try:
        first = wait_for(lambda: state_in.latest(), 20.0, what="mds-state from the daemon")
        assert first.joint[0x4C].pos == pytest.approx(-1.0, abs=1e-6) and first.joint[0x4C].ref == pytest.approx(
            -1.0, abs=1e-6)
        ref = MDS_REF()
        for j in TABLE:
            ref.joint[j.address].ref, ref.joint[j.address].mode = first.joint[j.address].ref, mds.MDS_REF_MODE_REF
        ref.joint[0x4C].ref = -0.7
        ref_out.put(ref)

        def reached() -> bool:
            st = state_in.latest()
            return st is not None and abs(st.joint[0x4C].pos - (-0.7)) < 1e-4

        wait_for(reached, 20.0, what="LEP at -0.7 in mds-state.pos")

        def spin_until(pred, timeout: float, what: str):
            deadline = time.monotonic() + timeout
            while not pred():
                assert time.monotonic() < deadline, f"timed out waiting for {what}"
                rclpy.spin_once(node, timeout_sec=0.1)

        spin_until(lambda: diags, 15.0, "/diagnostics")
        values = {kv.key: kv.value for kv in diags[-1].status[0].values}
        assert diags[-1].status[0].name == "mds_daemon: control loop"
        assert float(values["bus_load_percent"]) > 0 and values["bus_state"] == "active"
        spin_until(lambda: client.service_is_ready(), 15.0, "the command service")
        future = client.call_async(AddDiagnostics.Request(load_namespace="home LEP"))
        spin_until(future.done, 15.0, "the service reply")
        assert future.result().success and "LEP" in future.result().message
        future = client.call_async(AddDiagnostics.Request(load_namespace="home NOPE"))
        spin_until(future.done, 15.0, "the service reply")
        assert not future.result().success and "unknown joint" in future.result().message
    finally:
        state_in.close()
        ref_out.close()
        node.destroy_node()
        rclpy.try_shutdown()
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "Traceback" not in out


def test_no_ros_mode_stops_on_sigterm(clean_shm) -> None:
    proc = subprocess.Popen([str(VENV_BIN / "daemon"), "--nocan", "--no-ros", "--sim-ideal"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    state_in = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    try:
        wait_for(lambda: state_in.latest(), 20.0, what="mds-state")
    finally:
        state_in.close()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out


def test_status_struct_layout() -> None:
    assert ctypes.sizeof(ds.MDS_DAEMON_STATUS) <= mds.CHANNEL_FRAME_SIZE
    st = ds.MDS_DAEMON_STATUS(rate_hz=10, measured_rate_hz=9.5, bus_load_avg=23.0, stale_count=1, tx_errors=2)
    line = ds.summary_line(st)
    assert "9.5/10 Hz" in line and "23%" in line and "stale 1" in line and "tx-err 2" in line
    assert sys.byteorder == "little"


def test_diagnostics_levels() -> None:
    from diagnostic_msgs.msg import DiagnosticStatus

    st = ds.MDS_DAEMON_STATUS(rate_hz=10, bus_load_avg=20.0)
    assert daemon.diagnostic_status(st, True, []).level == DiagnosticStatus.OK
    st.bus_load_avg = 61.0
    busy = daemon.diagnostic_status(st, True, [])
    assert busy.level == DiagnosticStatus.WARN and "bus load 61 % > 60 %" in busy.message
    st.bus_load_avg, st.stale_count = 10.0, 1
    stale = daemon.diagnostic_status(st, True, ["LEP"])
    assert stale.level == DiagnosticStatus.WARN and "LEP" in stale.message
    st.bus_state = ds.BUS_STATE_BUS_OFF
    off = daemon.diagnostic_status(st, True, ["LEP"])
    assert off.level == DiagnosticStatus.ERROR and "resetbus" in off.message
    assert daemon.diagnostic_status(ds.MDS_DAEMON_STATUS(rate_hz=10), False, []).level == DiagnosticStatus.ERROR
    corrupt = daemon.diagnostic_status(ds.MDS_DAEMON_STATUS(rate_hz=10, channel_errors=4), True, [], 2)
    assert corrupt.level == DiagnosticStatus.WARN and "repair" in corrupt.message
    assert daemon.diagnostic_status(ds.MDS_DAEMON_STATUS(rate_hz=10, channel_errors=4), True, [], 0).level == \
        DiagnosticStatus.OK
    values = {kv.key for kv in off.values}
    assert {"period_error_p99_ms", "overruns", "bus_load_percent", "cpu_per_cycle_ms", "stale_joints"} <= values
