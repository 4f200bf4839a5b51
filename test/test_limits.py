"""One limit authority (issue #17): the effective limits (URDF & joint table) are computed in one place, published
on ``mds-limits`` and refused identically by every entry point.

The joints below are where the joint table and the URDF disagree: the table allows the value, the URDF does not.
Before, the console, the bridge, the viewer and the IK accepted them and the gate refused them deep in the
pipeline (forever, silently); now each entry point refuses them with a message, and accepts the same value just
inside the limit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import mds_ach as mds
from mds_ach import ach
from mds_ach.kinematics import limits as effective_limits
from mds_ach.kinematics.collision import load_model as load_collision_model
from mds_ach.kinematics.limits import EffectiveLimits, compute, current_limits
from mds_ach.net.achd import RefLimitCheck
from mds_ach.nodes import ik as ik_node
from mds_ach.nodes.collision import joint_limits
from mds_ach.nodes.mux import Controller, MuxCore
from mds_ach.nodes.pipeline import make_ref
from mds_ach.robot import config
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs import MDS_LIMITS, MDS_REF
from mds_ach.robot.msgs.limits import check_limits
from mds_ach.tools.monitor import limits_line
from mds_ach_bridge.commands import CommandError, positions_by_name
from mds_ach_bridge.limits import load_limits

# (joint, a value the table allows but the URDF does not, the effective limit on that side)
DISAGREE = [("LSR", -0.15, 0.0), ("RSR", 0.15, 0.0), ("LEP", -2.45, -2.4), ("REP", -2.45, -2.4),
            ("LWR", -1.0, -0.4712), ("RWR", 1.0, 0.4712)]
IDS = [d[0] for d in DISAGREE]
N = mds.MDS_JOINT_COUNT
HOME = np.zeros(N)
for _name, _value in {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2,
                      "LEP": -1.25, "LSY": -0.25, "LWR": -0.28}.items():
    HOME[BY_SHORT[_name].address] = _value


@pytest.fixture(scope="module")
def gate_model():
    return load_collision_model(world={})


def _mux() -> MuxCore:
    ctrl = Controller("default", mds.MDS_CHAN_REF_FILTER_NAME, 0, tuple(range(1, N)), None)
    return MuxCore([ctrl], HOME, np.zeros(N, dtype=np.int16), compute())


def _ik_bounds(short: str) -> tuple[float, float]:
    arm = 1 if short in LEFT_ARM else 0
    names = LEFT_ARM if arm == 1 else RIGHT_ARM
    solver = ik_node.IkService(ik_node.IkNodeConfig(), ik_node.arm_limits()).solvers[arm]
    i = names.index(short)
    return float(solver.lower[i]), float(solver.upper[i])


@pytest.mark.parametrize(("short", "value", "limit"), DISAGREE, ids=IDS)
def test_every_entry_point_refuses_what_the_urdf_refuses(clean_shm: None, gate_model, short: str, value: float,
                                                         limit: float) -> None:
    table = config.load()
    address = BY_SHORT[short].address
    assert table[short].within_limits(value), "the joint table alone would accept it"
    limits = compute()
    lo, hi = limits.range(short)
    assert limit in (lo, hi)
    # the shared check, with the message every entry point passes on
    problem = limits.problem(address, value)
    assert problem is not None and f"outside {short}'s range" in problem and "URDF & joint table" in problem
    assert limits.problem(address, limit) is None
    # console (tools/console.py _check_target) and viewer sliders: current_limits(), computed without a daemon
    assert current_limits().range(short) == (lo, hi) and not current_limits().published
    # bridge
    with pytest.raises(CommandError, match="outside the limits"):
        positions_by_name([short], [value], load_limits())
    assert positions_by_name([short], [limit], load_limits()) == {short: limit}
    # IK solver bounds
    assert _ik_bounds(short) == (lo, hi)
    # collision gate
    g_lo, g_hi = joint_limits(gate_model)
    assert (g_lo[address], g_hi[address]) == (lo, hi)
    # mux: a frame modifying the joint out of limits is refused as a whole, with the message
    mux = _mux()
    frame = HOME.copy()
    frame[address] = value
    frame[mds.NKY] = 0.1  # a valid change in the same frame is not applied either
    changed, message = mux.update(0, frame, np.zeros(N, dtype=np.int16), 1.0)
    assert not changed and message is not None and "nothing applied" in message and short in message
    assert mux.ref[mds.NKY] == 0.0 and mux.ref[address] == HOME[address]
    frame[address] = limit
    assert mux.update(0, frame, np.zeros(N, dtype=np.int16), 2.0) == (True, None)
    # achd: a frame a peer pushes into mds-ref-filter
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, MDS_REF) as chan:
        chan.put(make_ref(HOME, np.zeros(N, dtype=np.int16)))
        check = RefLimitCheck.for_channel(chan.channel, chan.name)
    assert check is not None
    frame = HOME.copy()
    frame[address] = value
    got = check.problem(bytes(make_ref(frame, np.zeros(N, dtype=np.int16))))
    assert got is not None and got[0] == "invalid" and f"outside {short}'s range" in got[1]
    frame[address] = limit
    assert check.problem(bytes(make_ref(frame, np.zeros(N, dtype=np.int16)))) is None
    # daemon: the table it clamps to
    narrowed = effective_limits.narrow_table(table, limits)
    assert (narrowed[short].lower, narrowed[short].upper) == (lo, hi)


def test_joints_outside_the_urdf_keep_the_table_range() -> None:
    table = config.load()
    limits = compute(table)
    for j in table:
        if j.short in ("LF1", "RF2", "JAP", "LYY"):
            assert limits.range(j.short) == (j.lower, j.upper)
    assert limits.range(0x01) is None  # no joint at that address
    assert "no limits" in limits.problem(0x01, 0.0)


def test_the_achd_check_only_judges_joints_the_frame_changes(clean_shm: None) -> None:
    """A read-modify-write client re-sends the pose the robot is at, perhaps outside the limits after power-on:
    only what it changes is judged, as the mux does."""
    start = HOME.copy()
    start[mds.LWR] = -0.8  # where the joint is (the table allows it), outside the URDF
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, MDS_REF) as chan:
        chan.put(make_ref(start, np.zeros(N, dtype=np.int16)))
        check = RefLimitCheck.for_channel(chan.channel, chan.name)
    assert check is not None
    moved = start.copy()
    moved[mds.LSP] = -0.3
    assert check.problem(bytes(make_ref(moved, np.zeros(N, dtype=np.int16)))) is None
    moved[mds.LWR] = -0.9
    assert "LWR" in check.problem(bytes(make_ref(moved, np.zeros(N, dtype=np.int16))))[1]
    assert RefLimitCheck.for_channel(chan.channel, mds.MDS_CHAN_IK_NAME) is None  # not a reference input


def test_published_limits_are_what_every_entry_point_reads(clean_shm: None) -> None:
    """With a daemon's mds-limits present, current_limits() takes them (here a narrower LSP to tell them apart)."""
    limits = compute()
    lower = limits.lower.copy()
    lower[mds.LSP] = -0.5
    narrower = EffectiveLimits(lower, limits.upper, limits.valid, limits.robot, "test")
    msg = narrower.to_msg(seq=1)
    assert check_limits(msg) is None
    with StructChannel.of(mds.MDS_CHAN_LIMITS_NAME) as chan:
        chan.put(msg)
    got = current_limits()
    assert got.published and got.source == "test" and got.range("LSP") == (-0.5, limits.range("LSP")[1])
    assert load_limits()["LSP"][0] == -0.5
    assert ik_node.arm_limits()[1][0][LEFT_ARM.index("LSP")] == -0.5
    assert current_limits("lucas").robot == "lucas"  # another robot than the daemon's: computed, never mixed


def test_a_broken_limits_frame_is_not_used(clean_shm: None) -> None:
    bad = compute().to_msg()
    bad.lower[mds.LSP], bad.upper[mds.LSP] = 1.0, -1.0
    assert "empty range" in check_limits(bad)
    ach.create(mds.MDS_CHAN_LIMITS_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    with StructChannel(mds.MDS_CHAN_LIMITS_NAME, MDS_LIMITS) as chan:
        chan.put(bad)
    assert not current_limits().published


def test_status_line_names_what_the_gate_refuses() -> None:
    limits = compute()
    ref = make_ref(HOME, np.zeros(N, dtype=np.int16))
    assert limits_line(limits, ref).endswith("nothing refused")
    ref.joint[mds.LWR].ref = -1.0
    line = limits_line(limits, ref)
    assert "the gate REFUSES" in line and "-1.00000 rad is outside LWR's range [-0.47120, 0.47120]" in line
    ref.joint[mds.LWR].ref = math.nan
    assert "LWR: nan is not a finite position" in limits_line(limits, ref)


def test_viewer_sliders_span_the_effective_limits() -> None:
    from mds_ach.kinematics.model import load_model
    from mds_ach.tools.viewer import _slider_range

    model, limits = load_model(), compute(config.load("isaac"))
    for name in BY_SHORT:
        if name in model.joints and model.joints[name].actuated:
            assert _slider_range(model.joints[name], limits.range(name)) == limits.range(name), name
