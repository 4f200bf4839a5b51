"""One limit authority (issue #17): the effective limits (URDF & joint table) are computed in one place, published
on ``mds-limits`` and refused identically by every entry point.

The joints below are where the joint table and the URDF disagree: the table allows the value, the URDF does not.
Before, the console, the bridge, the viewer and the IK accepted them and the gate refused them deep in the
pipeline (forever, silently); now each entry point refuses them with a message, and accepts the same value just
inside the limit.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import xml.etree.ElementTree as ET
from dataclasses import replace

import numpy as np
import pytest
import yaml
from support import VENV_BIN

import mds_ach as mds
from mds_ach import ach, paths
from mds_ach.bus import mcb, simbus
from mds_ach.bus.mcb import StateArg
from mds_ach.kinematics import limits as effective_limits
from mds_ach.kinematics.collision import load_model as load_collision_model
from mds_ach.kinematics.limits import FEEDFORWARD_ACCEL_SHARE, EffectiveLimits, compute, current_limits
from mds_ach.kinematics.model import load_model
from mds_ach.net.achd import RefLimitCheck
from mds_ach.nodes import collision as collision_node
from mds_ach.nodes import filter as filter_node
from mds_ach.nodes import ik as ik_node
from mds_ach.nodes.gate import joint_limits
from mds_ach.nodes.mux import Controller, MuxCore
from mds_ach.nodes.pipeline import make_ref
from mds_ach.robot import config, joints, motion
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
    # achd: a frame a peer pushes into a non-legacy input (mds-ref-ros; into the legacy mds-ref-filter the mux
    # clamps, test_an_out_of_limit_push_into_a_legacy_input_is_clamped_by_the_mux_like_a_local_put)
    with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, MDS_REF) as chan:
        chan.put(make_ref(HOME, np.zeros(N, dtype=np.int16)))
        check = RefLimitCheck.for_channel(chan.channel, chan.name)
    assert check is not None and not check.clamps
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
    with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, MDS_REF) as chan:
        chan.put(make_ref(start, np.zeros(N, dtype=np.int16)))
        check = RefLimitCheck.for_channel(chan.channel, chan.name)
    assert check is not None
    moved = start.copy()
    moved[mds.LSP] = -0.3
    assert check.problem(bytes(make_ref(moved, np.zeros(N, dtype=np.int16)))) is None
    moved[mds.LWR] = -0.9
    assert "LWR" in check.problem(bytes(make_ref(moved, np.zeros(N, dtype=np.int16))))[1]
    assert RefLimitCheck.for_channel(chan.channel, mds.MDS_CHAN_IK_NAME) is None  # not a reference input


@pytest.mark.parametrize("name", [mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_NAME])
def test_an_out_of_limit_push_into_a_legacy_input_is_clamped_by_the_mux_like_a_local_put(
        clean_shm: None, name: str) -> None:
    """The same answer from every door (issue #26): into the original channels the mux clamps an out-of-limit value
    (the original hardware stopped at its limits), so the network server passes a pushed frame on as a local put;
    a non-finite value, which the mux refuses whole, it refuses at once."""
    with StructChannel(name, MDS_REF) as chan:
        chan.put(make_ref(HOME, np.zeros(N, dtype=np.int16)))
        check = RefLimitCheck.for_channel(chan.channel, chan.name)
    assert check is not None and check.clamps
    zero_built = np.zeros(N)  # an original client's frame: zeros, one joint set; REP's range excludes 0
    zero_built[mds.LSP] = -0.3
    assert check.problem(bytes(make_ref(zero_built, np.zeros(N, dtype=np.int16)))) is None
    zero_built[mds.LSP] = math.nan
    got = check.problem(bytes(make_ref(zero_built, np.zeros(N, dtype=np.int16))))
    assert got is not None and got[0] == "invalid" and "LSP" in got[1], got


def test_published_limits_are_what_every_entry_point_reads(clean_shm: None) -> None:
    """With a daemon's mds-limits present, current_limits() takes them (here a narrower LSP to tell them apart)."""
    limits = compute()
    lower = limits.lower.copy()
    lower[mds.LSP] = -0.5
    narrower = replace(limits, lower=lower, source="test")
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


# --- what each joint can follow (issue #26 item 1) ------------------------------------------------------------


def test_the_published_limits_say_what_each_joint_follows(clean_shm: None) -> None:
    """Acceleration = 0.75 x the MOVETO acceleration A the daemon commands (80 deg/s^2, the MCB's own profile; the
    rest lets the MCB catch up with a moving stopping-point target), velocity = min(URDF, 0.9 x the daemon's bound /
    (1 + a / A)), so the stopping points of a trajectory at these limits pass the daemon's limiter (issue #26 item 2).
    Useful, not timid: the arms follow >= 0.75 rad/s and >= 1.0 rad/s^2. Published on mds-limits and read back
    unchanged."""
    table = config.load("default")
    model = load_model()
    limits = compute(table)
    assert table.accel_deg_s2 == 80.0 and motion.LIMIT_MARGIN * table.max_acceleration > math.radians(80.0)
    for short in LEFT_ARM + RIGHT_ARM + ("WST", "NKY"):
        velocity, acceleration = limits.motion(short)
        assert acceleration == FEEDFORWARD_ACCEL_SHARE * math.radians(80.0) == pytest.approx(1.0472, abs=1e-4)
        assert velocity == min(model.joints[short].velocity, motion.LIMIT_MARGIN * table.max_velocity / (1 + 0.75)) \
            == pytest.approx(1.0286, abs=1e-4)
        assert velocity >= 0.75 and acceleration >= 1.0, short
    assert limits.motion("LF1") == limits.motion("LSP")  # not in the URDF: its velocity (1.5 rad/s) bounds nothing
    assert limits.motion(0x01) is None  # no joint at that address
    msg = limits.to_msg(seq=1)
    assert check_limits(msg) is None
    with StructChannel.of(mds.MDS_CHAN_LIMITS_NAME) as chan:
        chan.put(msg)
    got = current_limits()
    assert got.published
    for a in np.flatnonzero(limits.valid):
        assert got.motion(int(a)) == limits.motion(int(a))
    broken = limits.to_msg()
    broken.acceleration[mds.LSP] = 0.0
    assert "acceleration 0.0 at address 0x5f" in check_limits(broken)


def test_the_followable_numbers_take_the_tightest_input() -> None:
    base = config.load("default")
    urdf = load_model()

    def lsp(**changes: float) -> tuple[float, float]:
        motion_ = compute(replace(base, **changes), urdf=urdf).motion("LSP")
        assert motion_ is not None
        return motion_

    share, a80 = FEEDFORWARD_ACCEL_SHARE, math.radians(80.0)
    # the daemon's velocity bound at its margin, shared with the stopping point's lead
    assert lsp(max_velocity=1.0) == (pytest.approx(0.9 / (1 + share)), share * a80)
    assert lsp(accel_deg_s2=40.0) == (pytest.approx(1.8 / (1 + share)), share * math.radians(40.0))  # MOVETO's share
    # the daemon's acceleration bound at its margin
    assert lsp(max_acceleration=1.0) == (pytest.approx(1.8 / (1 + 0.9 / a80)), pytest.approx(0.9))
    # a faster MOVETO, still under 0.9 x 8 rad/s^2; then the URDF's 1.5 rad/s is not the bound either
    assert lsp(accel_deg_s2=120.0) == (pytest.approx(1.8 / (1 + share)), share * math.radians(120.0))
    assert lsp(max_velocity=5.0) == (1.5, share * a80)  # the URDF's velocity


def test_the_daemon_publishes_and_commands_the_followable_acceleration(clean_shm: None) -> None:
    """The daemon publishes the followable numbers on mds-limits, and the acceleration it sends the MCB with every
    MOVETO (TRAJECTORY_ACCELERATION, counts/s^2) is the one the published acceleration is the share of: a trajectory
    within the published limits asks less of the MCB than its profile does."""
    from support.rig import TABLE, DaemonRig

    rig = DaemonRig(pose={"LEP": -1.0})
    try:
        rig.loop.start_up()
        with StructChannel.of(mds.MDS_CHAN_LIMITS_NAME) as chan:
            published = chan.latest()
        assert published is not None and check_limits(published) is None
        limits = EffectiveLimits.from_msg(published)
        expected = compute(TABLE)
        for a in np.flatnonzero(expected.valid):
            assert limits.motion(int(a)) == expected.motion(int(a))
        rig.put_ref(LEP=-0.9)
        rig.step(5)
        lep = TABLE["LEP"]
        sets = [f for f in rig.frames_to(lep.address) if f.argument == StateArg.TRAJECTORY_ACCELERATION]
        assert sets
        for f in sets:
            moveto = f.value * 2 * math.pi / lep.cpr
            assert moveto == pytest.approx(math.radians(TABLE.accel_deg_s2), rel=1e-6)  # float32
            assert limits.motion("LEP")[1] == pytest.approx(FEEDFORWARD_ACCEL_SHARE * moveto, rel=1e-6)
    finally:
        rig.close()


def test_the_simulated_mcb_follows_the_published_limits() -> None:
    """The MCB's MOVETO (its documented model, ``simbus.trajectory_step``) with the acceleration the daemon commands,
    across LSP's whole range: it reaches the published velocity and never changes speed faster than the MOVETO
    acceleration, of which the published one is a share; its own speed limit (0.5 rev/s, an assumption of the model)
    is above the published velocity."""
    table = config.load("default")
    j = table["LSP"]
    velocity, acceleration = compute(table).motion("LSP")
    assert simbus.DEFAULT_MAX_VELOCITY_REV_S * 2 * math.pi > velocity
    pos, vel = np.array([j.to_counts(j.lower)]), np.zeros(1)
    target = np.array([j.to_counts(j.upper)])
    vmax = np.array([j.cpr * simbus.DEFAULT_MAX_VELOCITY_REV_S])
    accel = np.array([table.accel_counts(j)])
    dt = np.array([table.trajectory_period / mcb.TRAJECTORY_TICK_HZ])
    speeds = [0.0]
    while pos[0] != target[0]:
        pos, vel = simbus.trajectory_step(pos, vel, target, vmax, accel, dt)
        speeds.append(abs(float(vel[0])) * 2 * math.pi / j.cpr)
        assert len(speeds) < 1000
    assert max(speeds) >= velocity
    moveto = math.radians(table.accel_deg_s2)
    assert acceleration < moveto
    assert max(abs(b - a) for a, b in zip(speeds, speeds[1:], strict=False)) <= moveto * dt[0] * (1 + 1e-9)


def test_every_stage_lets_a_trajectory_at_the_published_limits_through() -> None:
    """The published numbers are within every stage's own bounds (config defaults): the filter, the collision
    gate's speed bound and the daemon's limiter (at its margin) pass such a trajectory unchanged."""
    limits = compute()
    table = config.load()
    filt = filter_node.load_config()
    gate = collision_node.GateConfig.from_mapping(collision_node.load_config())
    for short in joints.MODEL_JOINTS:
        a = BY_SHORT[short].address
        velocity, acceleration = limits.motion(short)
        assert velocity <= filt.max_velocity[a] and acceleration <= filt.max_accel[a], short
        assert gate.max_velocity is None or velocity <= gate.max_velocity
        assert velocity <= motion.LIMIT_MARGIN * table.max_velocity
        assert acceleration <= motion.LIMIT_MARGIN * table.max_acceleration


def test_robot_description_carries_the_followable_velocity() -> None:
    limits = compute()
    text = effective_limits.urdf_with_limits(paths.urdf_path().read_text(), limits)
    seen = set()
    for joint in ET.fromstring(text).iter("joint"):
        limit = joint.find("limit")
        if limit is None or joint.get("name") not in joints.MODEL_JOINTS:
            continue
        assert float(limit.get("velocity")) == limits.motion(joint.get("name"))[0]
        seen.add(joint.get("name"))
    assert seen == set(joints.MODEL_JOINTS)


MOVEIT_KEYS = ["has_position_limits", "min_position", "max_position", "has_velocity_limits", "max_velocity",
               "has_acceleration_limits", "max_acceleration", "has_jerk_limits"]


def test_moveit_joint_limits_yaml_is_generated_from_the_authority() -> None:
    """config/joint_limits.yaml is what `mds-ach limits --moveit-yaml` writes for the default robot, in MoveIt's
    format (the keys of moveit_resources' panda_moveit_config), every number the authority's."""
    committed = paths.config_path(effective_limits.MOVEIT_YAML)
    limits = compute(robot="default")
    assert committed.read_text() == effective_limits.moveit_yaml(limits), (
        "config/joint_limits.yaml is out of date: run `mds-ach limits --moveit-yaml --robot default`")
    data = yaml.safe_load(committed.read_text())
    assert data["default_velocity_scaling_factor"] == data["default_acceleration_scaling_factor"] == 1.0
    assert list(data["joint_limits"]) == list(joints.MODEL_JOINTS)
    for name, entry in data["joint_limits"].items():
        assert list(entry) == MOVEIT_KEYS
        assert entry["has_position_limits"] and entry["has_velocity_limits"] and entry["has_acceleration_limits"]
        assert not entry["has_jerk_limits"]
        assert (entry["min_position"], entry["max_position"]) == limits.range(name)
        assert (entry["max_velocity"], entry["max_acceleration"]) == limits.motion(name)


def test_the_limits_verb_writes_and_checks_the_moveit_file(tmp_path) -> None:
    mds_ach = str(VENV_BIN / "mds-ach")
    env = {**os.environ, "MDS_ACH_RUNTIME_DIR": str(tmp_path / "rt")}

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([mds_ach, "limits", *args], capture_output=True, text=True, timeout=60, env=env)

    assert cli("--moveit-yaml", "--check", "--robot", "default").returncode == 0  # the committed file
    out = tmp_path / "joint_limits.yaml"
    done = cli("--moveit-yaml", str(out), "--robot", "isaac")
    assert done.returncode == 0 and out.read_text() == effective_limits.moveit_yaml(compute(robot="isaac"))
    stale = cli("--moveit-yaml", str(out), "--check", "--robot", "default")
    assert stale.returncode == 1 and "is out of date" in stale.stderr and "--robot default" in stale.stderr
    table = cli("--robot", "default")
    assert table.returncode == 0
    assert re.search(r"^LSP\s+-1\.9185\s+1\.0185\s+1\.0286\s+1\.0472$", table.stdout, re.M), table.stdout
    bad = cli("--robot", "nosuchrobot")
    assert bad.returncode == 1 and "unknown robot 'nosuchrobot'" in bad.stderr and "Traceback" not in bad.stderr
