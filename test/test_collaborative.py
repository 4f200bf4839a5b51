"""Collaborative mode (issue #31 item 1): the hands and elbows within the Cartesian bound on every sent target.

The daemon is driven on the simulated robot with a fast MoveIt-style goal (a trajectory streamed on both arms and
the torso pan near the joint speed bound, then a step to a far pose) and every MOVETO it sent is audited by
``mds-ach check-log``'s audit, joint bounds and Cartesian bound together (FK on the sent targets).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.rig import TABLE, DaemonRig

import mds_ach as mds
from mds_ach.kinematics import cartesian
from mds_ach.nodes.collaborative import ModeLog
from mds_ach.robot import config
from mds_ach.robot.msgs import MDS_CMD
from mds_ach.robot.msgs import daemon_status as ds
from mds_ach.tools import checklog

POSE = {"LEP": -1.0, "REP": -1.0, "LSP": -0.3, "RSP": -0.3}
# A fast goal: each joint's excursion (rad) over one second, peak speed pi/2 * excursion rad/s.
GOAL = {"WST": 0.3, "LSP": -1.1, "LSR": 0.5, "LSY": 0.6, "LEP": 0.8, "RSP": -1.1, "RSR": -0.5, "REP": 0.8}


@pytest.fixture
def modes() -> list[tuple[float, float]]:
    return []


# At 100 Hz the simulated 1 Mbit/s wire cannot carry 8 moving joints' SET sequences and every node's reply each
# cycle (the daemon's sends back up, ENOBUFS): that rate runs on an ideal wire here.
@pytest.fixture(params=[(10.0, 1_000_000), (100.0, None)], ids=["10Hz", "100Hz-ideal-wire"])
def rig(clean_shm: None, request: pytest.FixtureRequest, modes: list[tuple[float, float]]) -> Iterator[DaemonRig]:
    rate, bitrate = request.param
    r = DaemonRig(rate=rate, pose=POSE, bitrate=bitrate)
    r.loop.mode_log = lambda t, speed: modes.append((t, speed))
    r.loop.start_up()
    yield r
    r.close()


def set_mode(rig: DaemonRig, collaborative: bool) -> None:
    rig.cmd_seq += 1
    rig.cmd_out.put(MDS_CMD(seq=rig.cmd_seq, cmd=mds.MDS_CMD_MODE, value=1.0 if collaborative else 0.0))
    rig.step()
    st = rig.status()
    assert (st.cmd_seq, st.cmd_result, st.collaborative) == (rig.cmd_seq, ds.CMD_OK, int(collaborative))


def fast_goal(rig: DaemonRig, seconds: float = 1.0, there_and_back: bool = True) -> None:
    """A trajectory streamed every cycle (cosine profile, peak 1.7 rad/s on LSP), then a step back to the start."""
    start = {s: rig.loop.state.joint[TABLE[s].address].ref for s in GOAL}
    n = round(seconds * rig.loop.rate)
    for k in range(1, n + 1):
        f = 0.5 * (1 - math.cos(math.pi * k / n))
        rig.put_ref(**{s: start[s] + f * d for s, d in GOAL.items()})
        rig.step()
    if there_and_back:
        rig.put_ref(**start)  # a goal far away, at once (a console goto)
        rig.step(round(3.0 * rig.loop.rate))


def audit(rig: DaemonRig, modes: list[tuple[float, float]]) -> checklog.FileReport:
    return checklog.audit_frames(rig.log.frames, TABLE, rig.loop.bounds, rig.loop.stale_after, whole_run=True,
                                 modes=modes)


def test_the_fast_goal_is_too_fast_for_people_in_normal_mode(rig: DaemonRig, modes: list) -> None:
    """The scenario is meaningful: in normal mode (joint bounds only) a hand moves well above 250 mm/s."""
    fast_goal(rig)
    report = audit(rig, modes)
    assert report.findings == []
    assert report.cartesian_max > 2 * cartesian.MAX_SPEED, report.cartesian_max
    assert rig.status().cartesian_slowed == 0


def test_collaborative_mode_bounds_the_hands_and_elbows_on_every_sent_target(rig: DaemonRig, modes: list) -> None:
    set_mode(rig, True)
    fast_goal(rig)
    report = audit(rig, modes)
    assert report.findings == [], [f.line() for f in report.findings[:5]]  # joint bounds and Cartesian bound
    assert report.cartesian_checked > rig.loop.rate  # every moving batch: more than the 1 s trajectory
    assert report.cartesian_max <= cartesian.MAX_SPEED
    assert report.cartesian_max > 0.8 * cartesian.MAX_SPEED  # slowed to the bound, not stopped
    st = rig.status()
    assert st.cartesian_slowed > 0 and st.cartesian_braking == 0  # reported as slowed
    assert st.cartesian_speed_max <= cartesian.MAX_SPEED
    # ... and it still arrives: back where it started
    for s in GOAL:
        a = TABLE[s].address
        assert rig.loop.state.joint[a].ref == pytest.approx(rig.loop.state.joint[a].ref_r, abs=1e-6)


def test_switching_into_collaborative_mode_during_a_fast_motion_ramps(rig: DaemonRig, modes: list) -> None:
    """Switched on mid-motion, the joints brake at the joint bounds (no step: the joint audit passes) and are within
    the Cartesian bound after the ramp; switched off, they ramp up again."""
    start = {s: rig.loop.state.joint[TABLE[s].address].ref for s in GOAL}
    rig.put_ref(**{s: start[s] + d for s, d in GOAL.items()})
    rig.step(round(0.4 * rig.loop.rate))  # at full joint speed by now
    assert rig.status().cartesian_speed == 0.0  # (not computed in normal mode)
    set_mode(rig, True)
    rig.step(round(1.5 * rig.loop.rate))
    set_mode(rig, False)
    rig.put_ref(**start)
    rig.step(round(2.0 * rig.loop.rate))
    report = audit(rig, modes)
    assert report.findings == [], [f.line() for f in report.findings[:5]]
    assert report.cartesian_checked > 0
    assert report.cartesian_max_collaborative <= cartesian.MAX_SPEED
    assert report.cartesian_max > 2 * cartesian.MAX_SPEED  # before the switch and after it
    assert rig.status().cartesian_braking > 0  # it was braking into the bound


def test_check_log_finds_a_log_too_fast_for_collaborative_mode(rig: DaemonRig, modes: list, tmp_path: Path) -> None:
    """The auditor is independent of the daemon: a normal-mode log audited as collaborative has violations, with
    the joint velocities that made them; the mode log next to a --can-log file tells when the mode was on."""
    fast_goal(rig, there_and_back=False)
    report = checklog.audit_frames(rig.log.frames, TABLE, rig.loop.bounds, rig.loop.stale_after, whole_run=True,
                                   modes=[(-math.inf, cartesian.MAX_SPEED)])
    kinds = {f.kind for f in report.findings}
    assert kinds == {"cartesian"}, kinds
    worst = max(report.findings, key=lambda f: f.value)
    assert worst.value == pytest.approx(report.cartesian_max) and worst.bound == cartesian.MAX_SPEED
    # the mode log's format round-trips through the file check-log reads
    log = ModeLog(tmp_path / "run.log", wall_offset=0.0)
    log._append(f"{rig.log.frames[0][0]:.6f} collaborative 200\n")
    from mds_ach.nodes.collaborative import read_modes
    assert read_modes(log.path.read_text().splitlines()) == [(pytest.approx(rig.log.frames[0][0]), 0.2)]


def test_the_bound_is_configurable_down_only(tmp_path: Path) -> None:
    text = (Path(config.__file__).parents[2] / "config" / "joints.yaml").read_text()
    for value, ok in (("200", True), ("250", True), ("300", False)):
        path = tmp_path / "joints.yaml"
        path.write_text(text.replace("collaborative_speed_mm_s: 250", f"collaborative_speed_mm_s: {value}")
                            .replace("collaborative: false", "collaborative: true"))
        if ok:
            table = config.load(path=path)
            assert table.collaborative and table.collaborative_speed == float(value) / 1e3
        else:
            with pytest.raises(config.ConfigError, match="only be set lower"):
                config.load(path=path)
    with pytest.raises(ValueError, match="configurable down only"):
        cartesian.CartesianBound(0.3)
