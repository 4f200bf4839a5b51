"""Fault injection: CAN faults on the daemon loop (simulated clock and bus, ``support.rig.DaemonRig``) while the
arms move: a silent node, error frames, bus-off, garbled frames. Each is flagged in ``mds-daemon-status``,
recovers, and every MOVETO that reaches the bus is inside the joint's limits and obeys the motion bounds
(``motion_audit``).
"""


from __future__ import annotations

import math
import struct
from collections.abc import Iterator

import pytest
from support.motion_audit import audit
from support.rig import MOVING, TABLE, DaemonRig, unsafe_commands

import mds_ach as mds
from mds_ach.bus import mcb
from mds_ach.bus.constants import (
    CAN_ERR_BUSERROR,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_RX_PASSIVE,
    CAN_ERR_CRTL_TX_WARNING,
    CAN_ERR_PROT,
)
from mds_ach.bus.mcb import StateArg
from mds_ach.robot.msgs import daemon_status as ds

# ============================================================================================ 2. CAN faults

@pytest.fixture
def can_rig(clean_shm: None) -> Iterator[DaemonRig]:
    rig = DaemonRig.moving()
    rig.run(2.0)
    assert rig.travel("LSP", 0) > 0.05, "the arms do not move"
    yield rig
    try:
        assert unsafe_commands(rig.net.commands) == []
        assert all(math.isfinite(s.joint[TABLE[n].address].ref) for s in rig.states for n in MOVING)
        bounded = audit(rig.log.frames, TABLE, rig.loop.bounds, rig.loop.stale_after)
        assert bounded.violations == [], bounded.violations
    finally:
        rig.close()


def test_silent_node_is_flagged_and_recovers_while_the_arms_move(can_rig: DaemonRig) -> None:
    rig = can_rig
    lep = TABLE["LEP"]
    rig.net.set_offline(lep.address)  # it finishes the move it had, then takes no new target
    mark = len(rig.states)
    rig.run(rig.loop.stale_after + 1.0)
    st = rig.status()
    assert st.stale_count == 1 and st.joint_flags[lep.address] & ds.JOINT_STALE
    assert rig.loop.state.joint[lep.address].active == 0
    frozen_at = rig.measured("LEP")
    rig.run(0.5)
    assert rig.measured("LEP") == frozen_at and rig.loop.state.joint[lep.address].active == 0
    assert rig.travel("RSP", mark) > 0.05 and rig.travel("LSP", mark) > 0.05  # everything else moves on
    rig.net.set_offline(lep.address, False)
    mark = len(rig.states)
    rig.run(2.0)
    st = rig.status()
    assert st.stale_count == 0 and st.joint_flags[lep.address] & ds.JOINT_FRESH
    assert rig.travel("LEP", mark) > 0.05  # back under control: it follows its reference again
    assert rig.pos("LEP") == pytest.approx(rig.measured("LEP"), abs=0.02)


def test_error_frames_are_flagged_and_motion_goes_on(can_rig: DaemonRig) -> None:
    rig = can_rig
    mark = len(rig.states)
    rig.run(1.0, inject=lambda r: r.net.inject_error_frame(CAN_ERR_PROT | CAN_ERR_BUSERROR))
    st = rig.status()
    assert st.error_frames >= 10 and st.bus_state == ds.BUS_STATE_ACTIVE  # bus errors alone change no state
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_WARNING)
    rig.run(1.0)
    assert rig.status().bus_state == ds.BUS_STATE_PASSIVE
    assert rig.travel("LSP", mark) > 0.05 and rig.status().stale_count == 0  # frames still get through
    rig.command(mds.MDS_CMD_RESET_BUS)  # what `mds-ach resetbus` sends
    rig.run(0.5)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_ACTIVE and st.bus_resets == 1 and st.cmd_result == ds.CMD_OK


def test_error_passive_clears_when_the_controller_reports_error_active(can_rig: DaemonRig) -> None:
    """SocketCAN reports the way back too: CAN_ERR_CRTL with data[1] = CAN_ERR_CRTL_ACTIVE (0x40). A transient
    error-passive phase must not leave the daemon warning until someone resets a healthy bus."""
    rig = can_rig
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_RX_PASSIVE)
    rig.run(0.5)
    assert rig.status().bus_state == ds.BUS_STATE_PASSIVE
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_ACTIVE)
    rig.run(0.5)
    assert rig.status().bus_state == ds.BUS_STATE_ACTIVE


def test_bus_off_sends_nothing_and_resetbus_recovers(can_rig: DaemonRig) -> None:
    rig = can_rig
    rig.net.bus_off()
    sent_before = len(rig.net.commands)
    rig.run(1.5)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_BUS_OFF and st.bus_off_count == 1 and st.tx_errors > 0
    assert len(rig.net.commands) == sent_before  # nothing reached the bus
    assert rig.states[-1].time > rig.states[-15].time  # the state stream goes on
    held = rig.measured("LSP")
    rig.run(0.5)
    assert rig.measured("LSP") == held  # the robot stands still (its last move had ended)
    rig.command(mds.MDS_CMD_RESET_BUS)
    mark = len(rig.states)
    rig.run(2.0)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_ACTIVE and st.bus_resets == 1 and st.stale_count == 0
    assert rig.travel("LSP", mark) > 0.05  # moving again


def test_garbled_frames_are_counted_and_never_taken_as_positions(can_rig: DaemonRig) -> None:
    rig = can_rig
    lsp = TABLE["LSP"]
    nan = struct.unpack("<I", struct.pack("<f", math.nan))[0]
    inf = struct.unpack("<I", struct.pack("<f", math.inf))[0]

    def garble(r: DaemonRig) -> None:
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, nan, lsp.address))
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, inf, lsp.address))
        r.net.inject_frame(mcb.HOST_SID, b"\x01\x02\x03")  # short
        r.net.inject_frame(mcb.HOST_SID, bytes(8), is_extended_id=True)
        r.net.inject_frame(mcb.HOST_SID, bytes([0xFF] * 8))  # unknown response from node 0xFFFF
        r.net.inject_frame(0x7FF, bytes(range(8)))  # another host's traffic
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, 0, 0x3F))

    mark = len(rig.states)
    rig.run(1.0, inject=garble)
    st = rig.status()
    assert st.malformed_frames >= 40 and st.unknown_node_frames >= 20, ds.summary_line(st)
    positions = [s.joint[lsp.address].pos for s in rig.states[mark:]]
    assert all(math.isfinite(p) for p in positions)
    assert rig.travel("LSP", mark) > 0.05 and st.stale_count == 0
    assert rig.pos("LSP") == pytest.approx(rig.measured("LSP"), abs=0.05)


