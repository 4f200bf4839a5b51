"""The calibrated frame survives encoder commands (issue #25 item 1).

ZERO_ENCODER and RESET restart a node's count at 0 where the joint stands (``mds_ach.bus.simbus``): from then on its
replies, and the MOVETO targets the daemon computes in counts, are in a frame shifted by the count it had. The
daemon marks such a joint *unreferenced*: no target goes to it until HOME re-establishes the frame, and
``mds-state`` never shows a shifted reading as its position. Every check here is on the *true* (simulated physical)
position of the joint, which no count-based audit can see.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import pytest
from support import wait_for
from support.rig import TABLE, DaemonRig, unsafe_commands
from support.system import mds_ach

import mds_ach as mds
from mds_ach.bus import canio
from mds_ach.bus.mcb import Command
from mds_ach.bus.simbus import SimNetwork
from mds_ach.nodes import daemon
from mds_ach.nodes.daemon_loop import DaemonChannels, DaemonLoop
from mds_ach.robot.msgs import daemon_status as ds
from mds_ach.tools import monitor


def true_position(rig: DaemonRig, short: str) -> float:
    """Where the joint really is: the simulated physical count (from the ROM middle, the calibrated zero) in rad."""
    j = TABLE[short]
    return j.to_joint(float(rig.net.physical[rig.net.index[j.address]]))


def track_extremes(rig: DaemonRig, short: str, cycles: int) -> tuple[float, float]:
    """Step ``cycles`` cycles; the lowest and highest true position of the joint on the way."""
    lo = hi = true_position(rig, short)
    for _ in range(cycles):
        start = rig.clock.now
        rig.loop.cycle(deadline=start, start=start)
        for k in range(1, 11):  # the simulated robot moves between cycles too: sample within the period
            rig.clock.now = max(rig.clock.now, start + k * rig.loop.period / 10)
            q = true_position(rig, short)
            lo, hi = min(lo, q), max(hi, q)
    return lo, hi


@pytest.fixture
def rig(clean_shm: None) -> Iterator[DaemonRig]:
    r = DaemonRig(pose={"LSP": -0.9, "LEP": -2.0})
    r.loop.start_up()
    r.state()
    yield r
    try:
        assert unsafe_commands(r.net.commands) == []
        assert r.audit().violations == []
    finally:
        r.close()


@pytest.mark.parametrize(("code", "short", "start", "goto"), [
    (mds.MDS_CMD_ZERO_ENCODER, "LSP", -0.9, -1.85),
    (mds.MDS_CMD_RESET, "LEP", -2.0, -2.3),
])
def test_an_in_limit_goto_after_an_encoder_command_never_leaves_the_joint_range(
        rig: DaemonRig, code: int, short: str, start: float, goto: float) -> None:
    """The issue's scenarios: ZERO_ENCODER on LSP at -0.9 then goto -1.85; RESET on LEP at -2.0 then goto -2.3.
    Both gotos are inside the limits; today the joint really went 0.38 and 0.26 rad past them. The joint is
    unreferenced: it gets no target until HOME, it shows no position, and it is flagged."""
    j = TABLE[short]
    assert true_position(rig, short) == pytest.approx(start, abs=1e-6)
    rig.command(code, j.address)
    rig.step(3)
    rig.put_ref(**{short: goto})
    lo, hi = track_extremes(rig, short, 60)
    assert j.lower - 1e-6 <= lo and hi <= j.upper + 1e-6, f"{short} went to [{lo:.4f}, {hi:.4f}] rad, " \
                                                           f"range [{j.lower:.4f}, {j.upper:.4f}]"
    assert true_position(rig, short) == pytest.approx(start, abs=1e-6)  # refused: it stays where it was
    assert not [f for f in rig.frames_to(j.address) if f.command is Command.SET]
    st, status = rig.state(), rig.status()
    s = st.joint[j.address]
    assert math.isnan(s.pos) and s.active == 0  # the shifted reading is never a position for the gate/IK/viewer
    assert status.joint_flags[j.address] & ds.JOINT_UNREFERENCED
    assert not status.joint_flags[j.address] & ds.JOINT_FRESH
    assert "UNREFERENCED" in ds.flags_text(status.joint_flags[j.address])
    # ENABLE does not re-establish the frame; HOME does.
    rig.command(mds.MDS_CMD_ENABLE, j.address)
    rig.step(3)
    assert rig.status().joint_flags[j.address] & ds.JOINT_UNREFERENCED
    rig.command(mds.MDS_CMD_HOME, j.address)
    rig.step(60)
    st, status = rig.state(), rig.status()
    assert not status.joint_flags[j.address] & ds.JOINT_UNREFERENCED
    assert st.joint[j.address].active == 1
    assert st.joint[j.address].pos == pytest.approx(true_position(rig, short), abs=1e-6) == pytest.approx(j.home)
    assert status.joint_reseed[j.address] >= 1  # the pipeline restarts the joint there (as it would do:)
    rig.put_ref(**{short: j.home})
    rig.step()
    rig.put_ref(**{short: goto})
    lo, hi = track_extremes(rig, short, 60)
    assert j.lower - 1e-6 <= lo and hi <= j.upper + 1e-6
    assert true_position(rig, short) == pytest.approx(goto, abs=1e-4)  # in the calibrated frame again


def test_unreferenced_joints_leave_the_others_alone(rig: DaemonRig) -> None:
    """Only the zeroed joint is refused; the others move as before."""
    lsp, rsp = TABLE["LSP"], TABLE["RSP"]
    rig.command(mds.MDS_CMD_ZERO_ENCODER, lsp.address)
    rig.step(2)
    rig.put_ref(LSP=-1.2, RSP=0.3)
    rig.step(40)
    assert true_position(rig, "RSP") == pytest.approx(0.3, abs=1e-4)
    assert true_position(rig, "LSP") == pytest.approx(-0.9, abs=1e-6)
    assert rig.status().joint_flags[rsp.address] & ds.JOINT_FRESH


# --- who may send encoder commands ---------------------------------------------------------------------------


def test_the_ros_service_refuses_encoder_commands_unless_allowed() -> None:
    """Any ROS peer can call /mds_daemon/command; zero and reset need the operators' authority (mds-cmd) unless the
    daemon was started with allow_encoder_commands. (test_daemon.py::test_executable_with_ros calls the service.)"""
    for code, name in ((mds.MDS_CMD_ZERO_ENCODER, "zero"), (mds.MDS_CMD_RESET, "reset")):
        why = daemon.refused_from_ros(code, allow_encoder_commands=False)
        assert why is not None and f"mds-ach {name} JOINT" in why and "allow_encoder_commands" in why
        assert daemon.refused_from_ros(code, allow_encoder_commands=True) is None
    for code in (mds.MDS_CMD_HOME, mds.MDS_CMD_ENABLE, mds.MDS_CMD_DISABLE, mds.MDS_CMD_RESET_BUS):
        assert daemon.refused_from_ros(code, allow_encoder_commands=False) is None
    assert "--allow-encoder-commands" in daemon.build_parser().format_help()


def test_operators_zero_and_home_with_mds_ach(clean_shm: None) -> None:
    """`mds-ach zero LSP` (mds-cmd) against a running daemon loop: LSP is unreferenced and says so in `mds-ach read`;
    `mds-ach home LSP` references it again. A bad name is a clear usage error."""
    net = SimNetwork.from_table(TABLE, bitrate=None, pose={"LSP": -0.9})
    io = canio.make_canio(nocan=True, network=net)
    channels = DaemonChannels.open()
    loop = DaemonLoop(TABLE, io, channels, rate_hz=50.0, nocan=True)
    lsp = TABLE["LSP"]
    try:
        loop.start_up()
        loop.start()
        proc = mds_ach("zero", "LSP")
        assert proc.returncode == 0, proc.stderr
        assert "unreferenced" in proc.stdout and "mds-ach home LSP" in proc.stdout
        flags = loop.snapshot().joint_flags[lsp.address]
        assert flags & ds.JOINT_UNREFERENCED and monitor.joint_fresh(loop.snapshot(), lsp.address) == "UNREF"
        proc = mds_ach("home", "LSP", "--timeout", "5")
        assert proc.returncode == 0, proc.stderr
        wait_for(lambda: not loop.snapshot().joint_flags[lsp.address] & ds.JOINT_UNREFERENCED, 30.0,
                 what="LSP referenced again after HOME")
        assert loop.state.joint[lsp.address].pos == pytest.approx(lsp.home, abs=1e-6)
        proc = mds_ach("zero", "NOPE")
        assert proc.returncode == 2 and "unknown joint 'NOPE'" in proc.stderr and "Traceback" not in proc.stderr
        proc = mds_ach("reset", "LSP", "--timeout", "nan")
        assert proc.returncode == 2 and "--timeout" in proc.stderr
    finally:
        loop.stop()
        io.close()
        channels.close()
