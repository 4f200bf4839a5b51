"""The CAN budget (issue #26 item 5): frames and bits of a worst-case daemon cycle, the bus load at a rate, the
highest rate within 60 % of the bitrate (`--rate max`), and what is said of a rate the bus cannot carry.
Numbers checked by hand."""

from __future__ import annotations

import math

import can
import pytest

from mds_ach.bus import mcb
from mds_ach.bus.budget import MAX_LOAD, UNLISTED_NODES, CycleBudget
from mds_ach.bus.simbus import ManualClock, SimNetwork
from mds_ach.robot import config

MBIT = 1_000_000


def test_the_originals_accounting_gives_its_17_to_21_percent() -> None:
    """specs/mds-original.md §b.7: 13 arm/torso joints moving, 48 nodes answering, 1 query: 13 x (4 SET + 4 ACK)
    + 1 + 48 = 153 frames; 153 x 135 bits x 10 Hz = 206 550 bit/s (20.7 %), 153 x 111 = 16 983 bits (17.0 %)."""
    b = CycleBudget(joints=13, nodes=48, bitrate=MBIT, warnings=0)
    assert mcb.FRAME_BITS == 135
    assert b.frames == 153 and b.bits == 20_655
    assert b.load(10) == pytest.approx(0.20655)
    line = b.describe(10)
    assert "20.7 % of 1000000 bit/s worst case (17.0 % without bit stuffing)" in line
    assert "13 joints x (4 SET + 4 ACK) + 1 query + 48 replies = 153 frames x 135 bits" in line
    assert b.max_rate() == 29.0  # 600 000 / 20 655 = 29.05 Hz, rounded down to 0.1 Hz


def test_the_default_robots_worst_case_and_max_rate() -> None:
    """The default joint table: 17 enabled joints, 43 nodes + the 5 the anatomy does not list = 48 replies; each
    joint 4 SET + 4 ACK + 1 done warning: 17 x 9 + 1 + 48 = 202 frames = 27 270 bits. 10 Hz: 27.3 %; the highest
    rate within 60 %: 600 000 / 27 270 = 22.002 -> 22.0 Hz (59.99 %); 22.1 Hz would be 60.3 %."""
    table = config.load("default")
    b = CycleBudget.for_table(table, MBIT)
    assert (b.joints, b.nodes) == (17, 43 + UNLISTED_NODES)
    assert b.frames == 202 and b.bits == 27_270
    assert b.load(10) == pytest.approx(0.2727)
    assert b.max_rate() == 22.0
    assert b.load(22.0) <= MAX_LOAD < b.load(22.1)
    assert b.problem(10) is None and b.problem(22.0) is None


def test_a_rate_the_bus_cannot_carry_is_refused_with_the_highest_it_can() -> None:
    b = CycleBudget.for_table(config.load("default"), MBIT)
    msg = b.problem(100)
    assert msg is not None
    assert msg.startswith("100 Hz needs 273 % of the CAN bus (1000000 bit/s) in the worst case")
    assert "202 frames x 135 bits per cycle" in msg and "more than 60 %: use --rate 22 or less (or --rate max)" in msg
    assert b.problem(10.0) is None and b.problem(22.0) is None and b.max_rate() == 22.0  # --rate max
    assert b.describe(22.0).startswith("CAN budget at 22 Hz: 60.0 % of 1000000 bit/s worst case")
    assert "use --rate 22 or less" in (b.problem(50.0) or "")
    assert CycleBudget(joints=17, nodes=48, bitrate=500_000).max_rate() == 11.0  # half the bitrate: 11.001 Hz


def test_max_rate_is_the_highest_within_the_budget_and_never_above_the_ceiling() -> None:
    for joints in range(0, 44):
        b = CycleBudget(joints=joints, nodes=48, bitrate=MBIT)
        top = b.max_rate()
        assert b.load(top) <= MAX_LOAD < b.load(top + 0.1), joints
    tiny = CycleBudget(joints=1, nodes=1, bitrate=MBIT)  # 11 frames: 600 000 / 1485 = 404.04 Hz
    assert tiny.max_rate() == 404.0
    assert "no rate fits" in (CycleBudget(10**6, 48, 1000).problem(10.0) or "")


def test_a_rate_that_is_no_number_is_a_problem() -> None:
    problem = CycleBudget(1, 1, MBIT).problem(math.nan)
    assert problem is not None and "must be a number > 0" in problem


def test_the_simulated_bus_carries_the_budgets_frames() -> None:
    """One worst-case cycle on the simulated bus (its wire model: every frame FRAME_BITS long): every enabled joint
    gets the 4-SET sequence with a step short enough to end, then the broadcast query. The frames on the wire are
    the budget's, one for one: 4 SET + 4 ACK + 1 done warning per joint, 1 query, 1 reply per node."""
    table = config.load("default")
    clock = ManualClock()
    unlisted = (0x44, 0x45, 0x46, 0x47, 0x58)
    net = SimNetwork.from_table(table, clock=clock, bitrate=MBIT, extra_nodes=unlisted)
    budget = CycleBudget.for_table(table, MBIT)
    assert net.frame_time == pytest.approx(budget.frame_bits / MBIT)
    sent = 0
    for j in table.enabled:
        for raw in mcb.encode_position_sequence(j.address, 5.0, table.accel_counts(j), table.trajectory_period):
            net.host_send(can.Message(arbitration_id=raw.arbitration_id, data=raw.data, is_extended_id=False))
            sent += 1
    query = mcb.encode_query_positions()
    net.host_send(can.Message(arbitration_id=query.arbitration_id, data=query.data, is_extended_id=False))
    sent += 1
    received: list[mcb.McbFrame] = []
    while (msg := net.host_recv(1.0)) is not None:
        received.append(mcb.decode(msg.arbitration_id, bytes(msg.data)))
    acks = [f for f in received if f.command == mcb.Response.ACK]
    replies = [f for f in received if f.command == mcb.Response.STATE]
    warnings = [f for f in received if f.command == mcb.Response.WARNING]
    assert (len(acks), len(replies), len(warnings)) == (4 * budget.joints, budget.nodes, budget.joints)
    assert sent + len(received) == budget.frames


@pytest.mark.parametrize("rate, expected, extra",
                         [("max", 22.0, ()), ("10", 10.0, ()), ("100", 100.0, ("--over-budget",))])
def test_the_daemon_says_its_budget_at_start_and_runs_at_max(clean_shm: None, rate: str, expected: float,
                                                             extra: tuple[str, ...]) -> None:
    """`--rate max` runs the highest rate within 60 % of the bus; every start says the budget at its rate; a rate over
    it runs only with --over-budget, and says so (the motion bounds hold at every rate, issue #25 item 5)."""
    import subprocess
    import sys

    from support.channels import newest

    import mds_ach as mds
    from mds_ach.robot.msgs import daemon_status as ds

    proc = subprocess.run([sys.executable, "-m", "mds_ach.nodes.daemon", "--nocan", "--no-ros", "--rt-priority", "0",
                           "--duration", "1.0", "--rate", rate, *extra], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"CAN budget at {expected:g} Hz" in proc.stderr, proc.stderr
    assert ("more than 60 %" in proc.stderr) == bool(extra), proc.stderr
    status = newest(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    assert status is not None and status.rate_hz == expected


@pytest.mark.parametrize("extra", [(), ("--sim-ideal",)], ids=["bus", "ideal-wire"])
def test_a_rate_the_bus_cannot_carry_is_refused_unless_asked_for(clean_shm: None, extra: tuple[str, ...]) -> None:
    """Issue #26 item 5: a rate whose worst-case traffic exceeds 60 % of the bus is refused at start with the
    highest rate that fits (exit 2, one line, nothing started); the simulated bus without wire time (--sim-ideal)
    has no budget to exceed."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "mds_ach.nodes.daemon", "--nocan", "--no-ros", "--rt-priority", "0",
                           "--duration", "1.0", "--rate", "50", *extra], capture_output=True, text=True, timeout=120)
    if extra:
        assert proc.returncode == 0, proc.stderr
        return
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert "more than 60 %: use --rate 22 or less (or --rate max)" in last and "--over-budget" in last, last
