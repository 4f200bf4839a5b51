"""Compliant (mode 2) and encoder-filter (mode 3) joints cannot feed back on a wrong reply (issue #25 item 3).

In those modes the target follows the reported position. A reply offset that is plausible (inside the range, no
impossible jump once it persists: two boards on one address, a slipped encoder) used to be followed, the joint
driven after it, the next reply as wrong again: LSP ran from -0.50 rad to its limit in bounded steps. Now the target
follows at most ``FOLLOW_SPEED`` and a chase that never closes is a follow fault that holds the joint; a joint
that is really pushed (and stands where it was pushed) is still followed.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest
from support.rig import TABLE, DaemonRig, unsafe_commands

import mds_ach as mds
from mds_ach.bus import mcb
from mds_ach.bus.mcb import StateArg
from mds_ach.nodes.daemon_loop import FOLLOW_DRIFT, FOLLOW_RUNAWAY_BOUND, FOLLOW_SPEED
from mds_ach.robot.msgs import daemon_status as ds

START = -0.50


def true_position(rig: DaemonRig, short: str) -> float:
    j = TABLE[short]
    return j.to_joint(float(rig.net.physical[rig.net.index[j.address]]))


def push_to(rig: DaemonRig, short: str, q: float) -> None:
    """A hand moves the joint to ``q`` (the node stops there; its next target moves it again)."""
    j = TABLE[short]
    rig.net.set_position(j.address, j.to_counts(q))


@pytest.fixture
def rig(clean_shm: None) -> Iterator[DaemonRig]:
    """LSP moved (pass-through) to -0.50 rad, so its track is the last target sent, then at rest."""
    r = DaemonRig(pose={"LSP": START - 0.05})
    r.loop.start_up()
    r.put_ref(LSP=START)
    r.step(30)
    assert true_position(r, "LSP") == pytest.approx(START, abs=1e-5)
    yield r
    try:
        assert unsafe_commands(r.net.commands) == []
        assert r.audit().violations == []
    finally:
        r.close()


def counts_for(short: str, rad: float) -> float:
    """A position offset of ``rad`` in counts (the joint's direction and scale)."""
    j = TABLE[short]
    return j.to_counts(rad) - j.to_counts(0.0)


@pytest.mark.parametrize("mode", [mds.MDS_REF_MODE_COMPLIANT, mds.MDS_REF_MODE_ENC_FILTER])
def test_a_constant_reply_offset_does_not_run_the_joint_away(rig: DaemonRig, mode: int,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    """The issue's scenario: every reply +0.8 rad off, 40 of them, in mode 2 (and 3) on LSP at -0.50. Today the
    joint runs to +1.0185; now it moves at most FOLLOW_RUNAWAY_BOUND, holds, is flagged, and is logged once."""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mode, LSP=START)
    rig.step(3)
    rig.net.offset_positions(lsp.address, counts_for("LSP", 0.8), replies=-1)
    caplog.set_level(logging.INFO, logger="mds_ach.nodes.daemon")
    worst = 0.0
    for _ in range(40):
        rig.step()
        worst = max(worst, abs(true_position(rig, "LSP") - START))
    assert worst <= FOLLOW_RUNAWAY_BOUND, f"LSP ran {worst:.3f} rad from {START} on a +0.8 rad reply offset"
    status = rig.status()
    assert status.joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT
    assert "FOLLOW-FAULT" in ds.flags_text(status.joint_flags[lsp.address])
    assert "follow-fault 1" in ds.summary_line(status)
    assert len([r for r in caplog.records if "follow fault" in r.getMessage()]) == 1  # logged once
    held = true_position(rig, "LSP")
    rig.step(20)
    assert true_position(rig, "LSP") == pytest.approx(held, abs=1e-6)  # held: no more targets from the feedback
    # The fault survives the offset going away: it clears only by an explicit ENABLE (or HOME).
    rig.net.offset_positions(lsp.address, 0.0, replies=0)
    rig.step(5)
    assert rig.status().joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT
    rig.command(mds.MDS_CMD_ENABLE, lsp.address)
    rig.step(5)
    assert not rig.status().joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT
    assert true_position(rig, "LSP") == pytest.approx(held, abs=1e-6)  # compliant with correct replies: stays


def test_the_target_follows_at_a_bounded_speed(rig: DaemonRig) -> None:
    """One cycle's target moves at most FOLLOW_SPEED x period towards the reported position, whatever it says."""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, LSP=START)
    rig.step(3)
    sent = len(rig.targets("LSP"))
    rig.net.offset_positions(lsp.address, counts_for("LSP", 0.8), replies=-1)
    rig.step(40)
    targets = rig.targets("LSP")[sent - 1:]
    assert len(targets) > 1
    assert max(abs(b - a) for a, b in zip(targets, targets[1:], strict=False)) <= FOLLOW_SPEED * 0.1 + 1e-6


def test_a_slow_push_is_followed(rig: DaemonRig) -> None:
    """A hand moves LSP 0.4 rad at 0.2 rad/s in compliant mode, holds it there half a second, then moves it another
    0.4 rad and holds it: the target follows it all the way, no fault; released, the joint stays. (One continuous
    push longer than FOLLOW_DRIFT without a rest is a fault: test_a_small_reply_offset_drifts_a_bounded_distance.)"""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, LSP=START)
    rig.step(3)
    for k in range(1, 51):
        push_to(rig, "LSP", START + 0.02 * (min(k, 20) + min(max(0, k - 25), 20)))
        rig.step()
    rig.step(5)
    st, status = rig.state(), rig.status()
    assert not status.joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT
    assert st.joint[lsp.address].ref == pytest.approx(START + 0.8, abs=1e-4)
    assert true_position(rig, "LSP") == pytest.approx(START + 0.8, abs=1e-4)


@pytest.mark.parametrize("offset", [0.01, 0.05, -0.09])
def test_a_small_reply_offset_drifts_a_bounded_distance(rig: DaemonRig, offset: float) -> None:
    """An offset smaller than FOLLOW_GAP looks like a hand moving the joint; but the reported position never comes
    to rest, so after FOLLOW_DRIFT of following one way the joint faults and holds."""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, LSP=START)
    rig.step(3)
    rig.net.offset_positions(lsp.address, counts_for("LSP", offset), replies=-1)
    worst = 0.0
    for _ in range(round(FOLLOW_DRIFT / abs(offset) * 3) + 20):  # the drift moves up to the offset per cycle
        rig.step()
        worst = max(worst, abs(true_position(rig, "LSP") - START))
    assert worst <= FOLLOW_DRIFT + 0.05, f"LSP drifted {worst:.3f} rad on a {offset} rad reply offset"
    assert rig.status().joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT


def test_a_joint_pushed_and_held_is_caught_up_with(rig: DaemonRig) -> None:
    """A hand pushes LSP 0.4 rad at once and holds it there: the target comes at the follow speed (far more than
    FOLLOW_FAULT_TRAVEL) and the gap closes as it comes, so this is no fault; released, the joint stays."""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, LSP=START)
    rig.step(3)
    for _ in range(15):
        push_to(rig, "LSP", START - 0.4)
        rig.step()
    assert not rig.status().joint_flags[lsp.address] & ds.JOINT_FOLLOW_FAULT
    assert rig.state().joint[lsp.address].ref == pytest.approx(START - 0.4, abs=1e-4)
    rig.step(10)
    assert true_position(rig, "LSP") == pytest.approx(START - 0.4, abs=1e-4)


def test_two_different_replies_to_one_query_are_not_a_position(rig: DaemonRig) -> None:
    """Two nodes answering on one address: every query gets two different positions. Neither is taken; the joint
    is not trusted (BAD-REPLY) and in mode 2 holds, however long it lasts."""
    lsp = TABLE["LSP"]
    rig.put_ref(mode=mds.MDS_REF_MODE_COMPLIANT, LSP=START)
    rig.step(3)

    def second_board() -> None:
        rig.net.inject_frame(mcb.HOST_SID, bytes(mcb.encode_state_reply(
            lsp.address, StateArg.ACTUAL_POSITION, lsp.to_counts(true_position(rig, "LSP") + 0.5)).data))

    for _ in range(30):
        rig.step()
        second_board()
    status = rig.status()
    assert status.joint_flags[lsp.address] & ds.JOINT_BAD_REPLY and status.joint_bad_replies[lsp.address] >= 20
    assert rig.state().joint[lsp.address].active == 0
    assert true_position(rig, "LSP") == pytest.approx(START, abs=1e-6)
