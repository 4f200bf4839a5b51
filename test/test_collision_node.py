"""Collision gate: holding the affected arm, table, the other arm moving on, resuming, refusing bad references,
the expert override, reporting on mds-collide, the channel runner and the node."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
from support import VENV_BIN, wait_for

import mds_ach as mds
from mds_ach import ik
from mds_ach.kinematics.collision import load_model
from mds_ach.nodes.collision import GateRunner
from mds_ach.nodes.filter import FilterCore, parse_config
from mds_ach.nodes.gate import Gate, GateConfig, decision_to_dict, joint_limits
from mds_ach.nodes.pipeline import make_ref, ref_arrays
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM

N = mds.MDS_JOINT_COUNT
ZERO_MODE = np.zeros(N, dtype=np.int16)
L = np.array([BY_SHORT[n].address for n in LEFT_ARM])
R = np.array([BY_SHORT[n].address for n in RIGHT_ARM])
HOME = np.zeros(N)
for _name, _value in {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2,
                      "LEP": -1.25, "LSY": -0.25, "LWR": -0.28}.items():
    HOME[BY_SHORT[_name].address] = _value
TABLE = {"objects": [{"name": "table", "shape": "box", "size": [0.6, 1.4, 0.04], "xyz": [0.6, 0.0, -0.42]}]}
TABLE_TOP = -0.40
DT = 0.025
MODEL_ADDR = np.array(sorted(set(L) | set(R) | {mds.WST, mds.NKY, mds.NKP1, mds.NKP2, mds.NKR}))
LEFT_PARTS = (mds.COLLIDE_L_HAND, mds.COLLIDE_L_SHOULDER, mds.COLLIDE_L_FOREARM, mds.COLLIDE_L_ELBOW,
              mds.COLLIDE_L_WRIST)
RIGHT_PARTS = (mds.COLLIDE_R_HAND, mds.COLLIDE_R_SHOULDER, mds.COLLIDE_R_FOREARM, mds.COLLIDE_R_ELBOW,
               mds.COLLIDE_R_WRIST)
FILTER_SPEED = 1.57  # rad/s, the filter's default velocity limit (config/filter.yaml)


@pytest.fixture(scope="module")
def model():
    return load_model(world={})


@pytest.fixture(scope="module")
def table_model():
    return load_model(world=TABLE)


def flags(report: mds.MDS_COLLIDE, parts: tuple[int, ...]) -> bool:
    return any(report.joint[p].isCollide for p in parts)


APPROACH = 6  # the approach-to-contact option (off by default: config/collision.yaml) in the tests of that option


def make_gate(model, ref=HOME, **cfg) -> Gate:
    lower, upper = joint_limits(model)
    return Gate(model, GateConfig(**cfg), ref.copy(), ZERO_MODE.copy(), 0.0, lower, upper)


def solve(arm: str, point: list[float], seed: np.ndarray = HOME) -> np.ndarray:
    idx = L if arm == "left" else R
    res = ik.solve(point, "p-x p-y p-z", arm, seed[idx])
    assert res.success, res.message
    return res.q


def drive(gate: Gate, target: np.ndarray, seconds: float, t0: float | None = None) -> list:
    """Feed the gate what the default filter (1.57 rad/s at 40 Hz) makes of ``target``, starting from its output."""
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now = gate.last_time if t0 is None else t0
    decisions = []
    for _ in range(int(seconds / DT)):
        now += DT
        decisions.append(gate.process(core.step(), core.mode, now))
    return decisions


def tool(model, q100: np.ndarray, prim: str) -> np.ndarray:
    """Centre of a primitive in the robot (torso at WST = 0) frame."""
    poses = model.primitive_poses(model.q_from_ref(q100))
    torso = model.tree.link_pose("torso", np.zeros(17))
    k = [p.name for p in model.primitives].index(prim)
    return (np.linalg.inv(torso) @ poses[k])[:3, 3]


# --------------------------------------------------------------------------------------------- behaviour


def test_both_hands_to_the_same_point_stop_before_touching(model) -> None:
    gate = make_gate(model)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    assert ("left_hand_link", "right_hand_link") in model.check(model.q_from_ref(target)).pairs
    decisions = drive(gate, target, 6.0)
    held = [d for d in decisions if d.held]
    assert held and set(held[-1].held) == {"left", "right"}
    assert all(("left_hand_link", "right_hand_link") in d.result.pairs for d in held[-10:])
    gap = np.linalg.norm(tool(model, gate.ref, "left_hand_link") - tool(model, gate.ref, "right_hand_link")) - 0.2
    assert gap >= model.margin - 1e-9  # stopped before touching, with the clearance margin
    start_gap = np.linalg.norm(tool(model, HOME, "left_hand_link") - tool(model, HOME, "right_hand_link")) - 0.2
    assert gap < start_gap - 0.2  # they did move towards each other
    assert not model.check(model.q_from_ref(gate.ref)).collides
    report = gate.report(gate.last_time)
    assert report.isCollide == 1
    assert report.joint[mds.COLLIDE_L_HAND].isCollide == 1 and report.joint[mds.COLLIDE_R_HAND].isCollide == 1
    assert report.joint[mds.COLLIDE_L_HAND].collision > 1
    assert report.joint[mds.COLLIDE_R_ELBOW].isCollide == 0


def test_hand_driven_into_table_stops_above_it_while_the_other_arm_moves_on(table_model) -> None:
    gate = make_gate(table_model)
    target = HOME.copy()
    target[L] = solve("left", [0.40, 0.25, -0.50])  # 10 cm below the table top
    target[R] = solve("right", [0.30, -0.45, -0.15])  # free space beside the table
    decisions = drive(gate, target, 6.0)
    assert any(d.held == ("left",) for d in decisions)
    assert not any("right" in d.held or "all" in d.held for d in decisions)
    hand = tool(table_model, gate.ref, "left_hand_link")
    assert hand[2] - 0.1 >= TABLE_TOP + table_model.margin - 1e-9  # the hand sphere stays above the table top
    assert np.abs(gate.ref[L] - target[L]).max() > 0.05  # left arm stopped short
    np.testing.assert_allclose(gate.ref[R], target[R], atol=1e-12)  # right arm reached its target
    assert decisions[-1].result.parts == {mds.COLLIDE_L_HAND} or mds.COLLIDE_L_HAND in decisions[-1].result.parts


def test_safe_command_after_a_blocked_one_goes_through(table_model) -> None:
    gate = make_gate(table_model)
    blocked = HOME.copy()
    blocked[L] = solve("left", [0.40, 0.25, -0.50])
    drive(gate, blocked, 5.0)
    assert gate.report(gate.last_time).isCollide == 1
    safe = HOME.copy()
    safe[L] = solve("left", [0.35, 0.35, -0.05])
    decisions = drive(gate, safe, 5.0)
    assert not decisions[-1].held and not decisions[-1].result.collides
    np.testing.assert_allclose(gate.ref, safe, atol=1e-12)
    later = gate.last_time + gate.config.release_time + 0.01
    report = gate.report(later)
    assert report.isCollide == 0 and report.joint[mds.COLLIDE_L_HAND].isCollide == 0
    assert report.joint[mds.COLLIDE_L_HAND].collision == 0


def test_waist_turn_into_an_obstacle_holds_everything(model) -> None:
    # a ball where the left hand would be after the waist turned 0.45 rad to the left
    hand = tool(model, HOME, "left_hand_link")
    c, s = np.cos(0.45), np.sin(0.45)
    centre = [c * hand[0] - s * hand[1], s * hand[0] + c * hand[1], hand[2]]
    m = load_model(world={"objects": [{"name": "ball", "shape": "sphere", "radius": 0.05, "xyz": centre}]})
    gate = make_gate(m)
    assert not gate.current.collides
    target = HOME.copy()
    target[mds.WST] = 0.38
    target[mds.NKY] = 0.3  # the neck is not involved, but it is a modelled joint: held too
    target[mds.LF1] = 0.2  # an unmodelled finger joint still goes through
    decisions = drive(gate, target, 2.0)
    assert any(d.held == ("all",) for d in decisions)
    report = gate.report(gate.last_time)  # flagged: the arm in contact; frozen but not flagged: the rest
    assert report.isCollide == 1 and flags(report, LEFT_PARTS) and not flags(report, RIGHT_PARTS)
    assert 0 < gate.ref[mds.WST] < 0.38
    assert not m.check(m.q_from_ref(gate.ref)).collides
    assert gate.ref[mds.LF1] == pytest.approx(0.2)


def test_non_finite_and_out_of_limit_references_are_never_passed(model) -> None:
    gate = make_gate(model)
    bad = HOME.copy()
    bad[mds.LEP] = float("nan")
    bad[mds.RSP] = float("inf")
    bad[mds.LSR] = 3.0  # above the limit
    bad[mds.NKY] = 0.1  # fine
    mode = ZERO_MODE.copy()
    mode[mds.WST] = 7  # no such ref mode
    gate.process(HOME, ZERO_MODE, 0.05)  # the first reference after start does not move (speed bound)
    d = gate.process(bad, mode, 0.1)
    assert set(d.refused) == {mds.LEP, mds.RSP, mds.LSR, mds.WST}
    assert d.mode[mds.WST] == 0
    assert np.all(np.isfinite(d.ref))
    assert d.ref[mds.LEP] == HOME[mds.LEP] and d.ref[mds.RSP] == HOME[mds.RSP] and d.ref[mds.LSR] == HOME[mds.LSR]
    assert d.ref[mds.NKY] == pytest.approx(0.1)
    doc = decision_to_dict(d, gate, 0.1)
    assert set(doc["refused"]) == {"LEP", "RSP", "LSR", "WST"}


def test_speed_bound_keeps_a_jump_from_reaching_the_daemon(model) -> None:
    gate = make_gate(model, max_velocity=2.0, max_dt=0.05)
    jump = HOME.copy()
    jump[mds.NKY] = 0.5
    d0 = gate.process(jump, ZERO_MODE, 0.5)  # the first reference after start: no credit at all
    assert d0.ref[mds.NKY] == 0.0
    d1 = gate.process(jump, ZERO_MODE, 0.525)
    assert d1.ref[mds.NKY] == pytest.approx(2.0 * 0.025)
    d2 = gate.process(jump, ZERO_MODE, 2.0)  # a long pause credits at most max_dt
    assert d2.ref[mds.NKY] == pytest.approx(0.05 + 2.0 * 0.05)


def test_expert_override_is_explicit_reported_and_expires(model) -> None:
    gate = make_gate(model)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    drive(gate, target, 5.0, t0=0.0)
    held_at = gate.ref.copy()
    now = gate.last_time
    assert gate.set_override(60.0, now) == gate.config.override_max  # capped
    assert gate.set_override(1.0, now) == 1.0
    d = gate.process(target, ZERO_MODE, now + 0.025)
    assert d.overridden and not d.held and d.result.collides
    assert gate.report(now + 0.025).isCollide == 2  # visible on mds-collide
    from mds_ach.tools.monitor import collision_summary

    assert collision_summary(gate.report(now + 0.025)).startswith("EXPERT OVERRIDE")
    assert decision_to_dict(d, gate, now + 0.025)["override_remaining"] == pytest.approx(0.975)
    assert np.abs(d.ref - held_at).max() > 0  # it moved into the predicted collision
    # expired: back to blocking; the robot is now in collision, so only moves that add no new pair pass
    d = gate.process(target, ZERO_MODE, now + 1.5)
    assert not d.overridden
    home_again = drive(gate, HOME, 5.0)
    assert not home_again[-1].result.collides and np.allclose(gate.ref, HOME)
    assert gate.set_override(0.0, gate.last_time) == 0.0 and gate.override_remaining(gate.last_time) == 0.0


def test_started_inside_a_collision_allows_only_moves_out(model) -> None:
    inside = HOME.copy()
    inside[L], inside[R] = solve("left", [0.40, 0.02, -0.1]), solve("right", [0.40, -0.02, -0.1])
    gate = make_gate(model, ref=inside)
    assert gate.current.collides
    start_pairs = gate.current.pairs
    decisions = drive(gate, HOME, 5.0)
    assert all(d.result.pairs <= start_pairs or not d.held for d in decisions)
    np.testing.assert_allclose(gate.ref, HOME, atol=1e-12)


def test_report_hysteresis_on_wall_time(model) -> None:
    gate = make_gate(model, release_time=0.1)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    drive(gate, target, 4.0, t0=0.0)
    last = gate.last_time
    hand = gate.parts[mds.COLLIDE_L_HAND]
    assert hand.last == pytest.approx(last)
    assert gate.report(last + 0.05).joint[mds.COLLIDE_L_HAND].isCollide == 1
    c = gate.report(last + 0.15)
    assert c.joint[mds.COLLIDE_L_HAND].isCollide == 0 and c.isCollide == 0
    assert c.time == last + 0.15 and c.time_dt == pytest.approx(0.1)


# --------------------------------------------------------------------------------------------- measured pose, release



def test_the_measured_pose_of_a_compliant_arm_holds_the_other_arm(model) -> None:
    """Mode 2: the left arm's reference went home but the arm stays where it is (the daemon's target follows the
    encoder). The right hand sent to where the left hand physically is must stop short of it, reported."""
    from mds_ach.nodes.gate import Observed

    point = [0.40, 0.05, -0.10]
    left_there = solve("left", point)
    gate = make_gate(model)
    target = HOME.copy()
    target[R] = solve("right", point)
    assert not model.check(model.q_from_ref(target)).collides  # the references alone never meet
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now = 0.0
    for _ in range(int(3.0 / DT)):
        now += DT
        pos = gate.ref.copy()  # the right arm is where it is commanded, the left one stays
        pos[L] = left_there
        d = gate.process(core.step(), core.mode, now, Observed(pos, now, now))
        robot = pos.copy()
        robot[R] = d.ref[R]
        assert not model.check(model.q_from_ref(robot)).collides  # where the right arm goes never touches
    assert "right" in d.held and np.abs(d.ref[R] - target[R]).max() > 0.05
    report = gate.report(now)
    assert report.isCollide == 1 and report.joint[mds.COLLIDE_L_HAND].isCollide and \
        report.joint[mds.COLLIDE_R_HAND].isCollide
    doc = decision_to_dict(d, gate, now)
    assert doc["measured"] and "right" in doc["held"] and ["left_hand_link", "right_hand_link"] in doc["pairs"]


def test_a_flagged_arm_never_moves_and_a_released_one_comes_back_at_the_filter_speed(model) -> None:
    """mds-collide and mds-ref-gated agree: while an arm's parts are flagged (the daemon withholds that arm's targets)
    its reference does not change, and when it is released it moves on from the held reference no faster than
    the filter, so the daemon never has a missed distance to send at once. Hands to one point stop apart; then
    the right one goes home and the left one, released, comes on to the point."""
    gate = make_gate(model)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now, prev = 0.0, gate.process(HOME, ZERO_MODE, 0.0).ref  # the first frame after start: no speed credit
    released = False
    for k in range(int(9.0 / DT)):
        if k == int(3.0 / DT):
            assert flags(gate.report(now), LEFT_PARTS) and flags(gate.report(now), RIGHT_PARTS)  # both held
            target[R] = HOME[R]
            core.set_target(target, ZERO_MODE)
        now += DT
        d = gate.process(core.step(), core.mode, now)
        report = gate.report(now)
        for idx, parts in ((L, LEFT_PARTS), (R, RIGHT_PARTS)):
            if report.isCollide == 1 and flags(report, parts):
                assert np.array_equal(d.ref[idx], prev[idx]), f"flagged at {now:.3f} s but moved"
        step = np.abs(d.ref - prev)[MODEL_ADDR].max()
        assert step <= FILTER_SPEED * DT + 1e-9, f"step {step:.4f} rad at {now:.3f} s"
        released |= k > int(3.0 / DT) and not d.held and step > 0
        prev = d.ref
    assert released
    np.testing.assert_allclose(gate.ref[L], target[L], atol=1e-12)
    np.testing.assert_allclose(gate.ref[R], HOME[R], atol=1e-12)


@pytest.mark.parametrize("echo", [True, False])
def test_a_released_arm_waits_until_the_daemon_took_the_cleared_flag(model, echo: bool) -> None:
    """After a hold the flag is cleared first; the arm's reference stays put until mds-state shows that the daemon
    took a report without the flag (its 10 Hz cycle copies mds-collide into state.collide), or release_wait."""
    from mds_ach.nodes.gate import Observed

    gate = make_gate(model)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now, taken, cleared, moved, taken_at_move = 0.0, -1.0, None, None, None
    for k in range(int(8.0 / DT)):
        if k == int(3.0 / DT):
            target[R] = HOME[R]  # the right arm backs off; the left one is released once it is out of the way
            core.set_target(target, ZERO_MODE)
        now += DT
        before = gate.ref[L].copy()
        d = gate.process(core.step(), core.mode, now, Observed(gate.ref.copy(), now, taken))
        report = gate.report(now)
        if k > int(3.0 / DT) and cleared is None and not flags(report, LEFT_PARTS):
            cleared = report.time
        if cleared is not None and moved is None and not np.array_equal(d.ref[L], before):
            moved, taken_at_move = now, taken
        if echo and k % 4 == 0:
            taken = report.time  # the daemon's cycle took this report and echoes it in the next mds-state
    assert cleared is not None and moved is not None
    if echo:
        assert taken_at_move >= cleared and moved - cleared <= 0.1 + 2 * DT
    else:
        assert moved - cleared >= gate.config.release_wait - DT
    assert np.abs(gate.ref[L] - target[L]).max() < 1e-9  # and then it goes on to its target


def test_a_hold_is_released_after_the_filter_came_to_rest(model) -> None:
    """The filter publishes only while its output moves (an event-driven pipeline, #26 item 6), so the input
    stream stops while the gate still holds an arm. The runner then re-processes the newest input at the filter's
    period while ``Gate.pending`` says the decision is unfolding: the held arm is released and reaches its target
    with no new input, and the gate then says it has nothing pending (it sleeps until the next frame)."""
    from mds_ach.nodes.gate import Observed

    gate = make_gate(model)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now, latest, silent_steps = 0.0, None, 0
    for k in range(int(8.0 / DT)):
        if k == int(3.0 / DT):
            target[R] = HOME[R]  # the right arm backs off; the left one is released once it is out of the way
            core.set_target(target, ZERO_MODE)
        now += DT
        if core.moving() or latest is None:
            latest = (core.step(), core.mode.copy())
        elif gate.pending(*latest):
            silent_steps += 1  # the filter rests: the runner re-decides on its newest input
        else:
            continue
        gate.process(*latest, now, Observed(gate.ref.copy(), now, gate.last_report))
        gate.report(now)
    assert silent_steps > 0, "the left arm was released while the filter still moved: the scenario tests nothing"
    assert np.abs(gate.ref[L] - target[L]).max() < 1e-9  # released and on its target with no new input
    assert not gate.pending(*latest)


def test_arms_in_measured_contact_are_held_and_can_be_moved_apart(model) -> None:
    """Both arms pushed into contact (e.g. compliant arms moved by hand): reported and held while their references
    stand still; a reference that brings them closer is refused, one that moves an arm away passes (escaping)."""
    from mds_ach.nodes.gate import Observed

    pos = HOME.copy()
    pos[L], pos[R] = solve("left", [0.40, 0.02, -0.1]), solve("right", [0.40, -0.02, -0.1])
    assert model.check(model.q_from_ref(pos)).collides
    gate = make_gate(model)
    now = 0.0

    def step(ref: np.ndarray) -> tuple:
        nonlocal now
        now += DT
        d = gate.process(ref, ZERO_MODE, now, Observed(pos, now, now))
        return d, gate.report(now)

    d, report = step(HOME)
    assert set(d.held) == {"left", "right"} and report.isCollide == 1
    assert flags(report, LEFT_PARTS) and flags(report, RIGHT_PARTS)
    assert ["left_hand_link", "right_hand_link"] in decision_to_dict(d, gate, now)["contact"]
    closer = HOME.copy()
    closer[R] = solve("right", [0.40, 0.02, -0.1])  # onto the left hand
    for _ in range(int(2.0 / DT)):
        d, report = step(closer)
        towards = pos.copy()
        towards[R] = d.ref[R]  # where the right arm is sent, the left one where it is
        assert not model.check(model.q_from_ref(towards)).collides
    assert "right" in d.held and np.abs(d.ref[R] - closer[R]).max() > 0.05  # stopped short of the left hand
    away = HOME.copy()
    away[R] = solve("right", [0.25, -0.45, -0.25])
    escaping = 0
    for _ in range(int(3.0 / DT)):
        d, report = step(away)
        if "right" in d.escaping:  # passed while in contact: flagged for the left arm only, so the daemon sends it
            escaping += 1
            assert d.held == ("left",) and report.isCollide == 1
            assert flags(report, LEFT_PARTS) and not flags(report, RIGHT_PARTS)
    assert escaping > 10
    np.testing.assert_allclose(d.ref[R], away[R], atol=1e-12)  # the right arm's reference moved out
    pos[R] = away[R]  # ... and the arm followed it: out of contact, nothing is held any more
    for _ in range(10):
        d, report = step(away)
    assert not d.held and not d.contacts.collides and report.isCollide == 0


def test_moving_out_of_a_contact_is_reported_as_contact_not_as_a_hold(model) -> None:
    """isCollide = 3 while the arms are in contact but only moves out of it pass and nothing is held (the daemon
    holds nothing then); operators see it as CONTACT, a hold as BLOCKED."""
    from mds_ach.tools.monitor import collision_summary

    inside = HOME.copy()
    inside[L], inside[R] = solve("left", [0.40, 0.02, -0.1]), solve("right", [0.40, -0.02, -0.1])
    gate = make_gate(model, ref=inside)
    core = FilterCore(parse_config({"rate": 1 / DT}), inside, ZERO_MODE)
    core.set_target(HOME, ZERO_MODE)
    codes, escaping = [], 0
    now = 0.0
    for _ in range(int(4.0 / DT)):
        now += DT
        d = gate.process(core.step(), core.mode, now)
        report = gate.report(now)
        codes.append(report.isCollide)
        if report.isCollide == 3:
            assert not d.held and collision_summary(report).startswith("CONTACT")
            escaping += set(d.escaping) == {"left", "right"} and "L_HAND" in collision_summary(report)
        elif report.isCollide == 1:
            assert collision_summary(report).startswith("BLOCKED")
    assert codes[0] == 1 and escaping > 0 and codes[-1] == 0


# --------------------------------------------------------------------------------------------- approach to contact

# "Touching" on the gate's collision model: every primitive is inflated by margin / 2, so two parts touch when the
# clearance of the un-inflated shapes equals the margin. Stopped at contact = margin <= clearance <= margin + 5 mm:
# the inflated parts are at most 5 mm apart and never overlap.
TOUCH = 0.005


def hand_clearance(model, q100: np.ndarray) -> float:
    return model.distances(model.q_from_ref(q100))[("left_hand_link", "right_hand_link")]


def test_both_hands_to_the_same_point_stop_at_contact(model) -> None:
    """Paper §4.2: both hands sent to the same point stop when the two parts of the collision model touch
    (within 5 mm), never interpenetrating; both arms moved into the contact, so both commands end there."""
    gate = make_gate(model, approach_iterations=APPROACH)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    decisions = drive(gate, target, 4.0)
    gap = hand_clearance(model, gate.ref)
    assert model.margin - 1e-9 <= gap <= model.margin + TOUCH, f"hands stopped {gap * 1e3:.1f} mm apart"
    assert set(decisions[-1].held) == {"left", "right"}
    stops = [d.stopped for d in decisions if d.stopped]
    assert stops == [{"left": "left hand / right hand", "right": "right hand / left hand"}]  # once per episode
    doc = decision_to_dict(decisions[-1], gate, gate.last_time)
    assert doc["stopped"] == {"left": "stopped at contact: left hand / right hand",
                              "right": "stopped at contact: right hand / left hand"}
    for d in decisions:  # never a reference into the contact on the way
        assert not model.check(model.q_from_ref(d.ref)).collides


def test_a_hand_sent_to_a_resting_hand_stops_there_and_only_its_command_ends(model) -> None:
    """Only the arm whose own reference moved into the contact is stopped (and cancelled); the resting arm it came
    to is held while they touch, but its command (none) is not the one that failed."""
    gate = make_gate(model, approach_iterations=APPROACH)
    target = HOME.copy()
    target[L] = solve("left", [0.40, 0.05, -0.10])
    drive(gate, target, 3.0)
    np.testing.assert_allclose(gate.ref[L], target[L], atol=1e-12)
    target[R] = solve("right", [0.40, 0.05, -0.10])
    decisions = drive(gate, target, 4.0)
    gap = hand_clearance(model, gate.ref)
    assert model.margin - 1e-9 <= gap <= model.margin + TOUCH, f"hands stopped {gap * 1e3:.1f} mm apart"
    assert [d.stopped for d in decisions if d.stopped] == [{"right": "right hand / left hand"}]
    np.testing.assert_allclose(gate.ref[L], target[L], atol=1e-12)  # the left arm never moved
    # The right arm's target is cancelled (the mux then sends it the held reference): it rests at the contact, held
    # and reported (no second stop, no second cancel) for as long as it stays there touching; a new command moving
    # it away releases it and ends the report.
    assert gate.stopped == {"right": "right hand / left hand"}
    held = gate.ref.copy()
    decisions = drive(gate, held, 1.0)
    assert "right" in decisions[-1].held and gate.stopped == {"right": "right hand / left hand"}
    assert not any(d.stopped for d in decisions)
    decisions = drive(gate, HOME, 2.0)
    assert not any(d.stopped for d in decisions) and np.allclose(gate.ref, HOME) and gate.stopped == {}


def test_the_hand_driven_down_stops_on_the_table(table_model) -> None:
    """Paper §4.3: the hand driven down toward the table does not move farther than the collision point."""
    gate = make_gate(table_model, approach_iterations=APPROACH)
    target = HOME.copy()
    target[L] = solve("left", [0.40, 0.25, -0.50])  # 10 cm below the table top
    decisions = drive(gate, target, 5.0)
    gap = table_model.distances(table_model.q_from_ref(gate.ref))[("left_hand_link", "world:table")]
    assert table_model.margin - 1e-9 <= gap <= table_model.margin + TOUCH, f"{gap * 1e3:.1f} mm above the table"
    assert [d.stopped for d in decisions if d.stopped] == [{"left": "left hand / table"}]


def test_at_the_contact_the_daemons_target_arrives_before_the_arm_is_flagged(model) -> None:
    """A flag makes the daemon withhold the arm where its rate-limited target is, which lags the reference: so at
    the contact the arm first rests there unflagged (its reference frozen) until mds-state shows the daemon's
    target there, then it is held and flagged as before. The stop (and the cancel) comes at the first frame."""
    from mds_ach.nodes.gate import Observed

    gate = make_gate(model, approach_iterations=APPROACH)
    target = HOME.copy()
    target[L] = solve("left", [0.40, 0.05, -0.10])
    drive(gate, target, 3.0)
    target[R] = solve("right", [0.40, 0.05, -0.10])
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now, sent = gate.last_time, gate.ref.copy()
    stops, rested, flagged_early, held = [], 0, False, False
    for k in range(int(4.0 / DT)):
        now += DT
        if k % 4 == 0 and not held:  # a slow daemon, 10 Hz: its target moves at most 0.04 rad toward the reference
            sent = sent + np.clip(gate.ref - sent, -0.04, 0.04)  # (lags it), withheld while the arm is flagged
        before = gate.ref.copy()
        d = gate.process(core.step(), core.mode, now, Observed(sent.copy(), now, now, sent.copy()))
        stops += [d.stopped] if d.stopped else []
        held = "right" in d.held
        if gate.stopped and not d.held:
            rested += 1
            assert np.array_equal(d.ref[R], before[R])  # resting at the contact: the reference does not move
            flagged_early |= flags(gate.report(now), RIGHT_PARTS)
    assert stops == [{"right": "right hand / left hand"}] and rested > 0 and not flagged_early
    assert "right" in d.held and np.abs(sent[R] - d.ref[R]).max() <= 1e-4  # held once the daemon got there
    gap = hand_clearance(model, gate.ref)
    assert model.margin - 1e-9 <= gap <= model.margin + TOUCH


def _with_the_daemon(gate: Gate, target: np.ndarray, seconds: float, rate: float = 10.0) -> tuple[list, np.ndarray]:
    """The gate between the default filter (40 Hz) and the daemon's limiter (``motion.limit`` at the daemon's bounds
    and loop ``rate``, desired velocity estimated from the references per cycle as the daemon does), which withholds
    flagged arms. A daemon cycle reads the newest gated reference (the frames of the gate's 40 Hz up to it) and the
    gate sees the daemon's newest target. Returns the gate's decisions and the daemon's targets at every cycle."""
    from mds_ach.nodes.gate import Observed
    from mds_ach.robot import config, motion

    period = 1.0 / rate
    bounds = config.load().motion_bounds()  # the daemon's own: the same at every rate
    core = FilterCore(parse_config({"rate": 1 / DT}), gate.ref, gate.mode)
    core.set_target(target, ZERO_MODE)
    now = t_daemon = gate.last_time
    tracks = {int(a): motion.Track(float(gate.ref[a]), 0.0, now) for a in MODEL_ADDR}
    goals = {a: (float(gate.ref[a]), now) for a in tracks}
    sent, ref, withheld = gate.ref.copy(), gate.ref.copy(), set()
    decisions, sends = [], []
    for _ in range(int(seconds / DT)):
        now += DT
        while t_daemon + period <= now + 1e-9:  # the daemon's cycles up to this frame read the previous one
            t_daemon += period
            for a, tr in tracks.items():
                if a in withheld:
                    continue
                prev, t_prev = goals[a]
                h = t_daemon - t_prev
                v = (ref[a] - prev) / h if 0 < h <= bounds.max_interval else 0.0
                goals[a] = (float(ref[a]), t_daemon)
                q = motion.limit(tr, float(ref[a]), t_daemon, bounds, desired_velocity=v)
                tr.advance(q, t_daemon, bounds)
                sent[a] = q
            sends.append(sent.copy())
        d = gate.process(core.step(), core.mode, now, Observed(sent.copy(), now, now, sent.copy()))
        decisions.append(d)
        ref = d.ref
        withheld = set(L) if "left" in d.held or "all" in d.held else set()
        withheld |= set(R) if "right" in d.held or "all" in d.held else set()
    return decisions, np.array(sends)


@pytest.mark.parametrize("rate", [10.0, 100.0, 200.0])
@pytest.mark.parametrize("scene", ["both at once", "to the resting hand"])
def test_the_daemon_follows_the_braking_onto_the_contact_never_into_it(model, scene: str, rate: float) -> None:
    """An arm approaching a contact brakes within ``brake_accel`` (below the daemon's acceleration bound) so that
    it can stop at the margin: the daemon's rate-limited targets -- what the motors are sent -- follow it onto
    the contact and never pass it (an abrupt stop at the margin was passed by up to v^2/2a: 2-6 cm). At 100 and
    200 Hz the daemon's targets trailed the gate's reference and then closed in on it faster than the gate braked
    it: they ran 2 cm past it, the hands into contact (the 100 Hz adversary's collisions)."""
    gate = make_gate(model, approach_iterations=APPROACH)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    if scene == "to the resting hand":
        target[L] = solve("left", point)
        _with_the_daemon(gate, target, 3.0, rate)
    target[L], target[R] = solve("left", point), solve("right", point)
    decisions, sends = _with_the_daemon(gate, target, 5.0, rate)
    gaps = np.array([hand_clearance(model, q) for q in sends])
    assert gaps.min() >= model.margin - 1e-6, f"the daemon's targets {(model.margin - gaps.min()) * 1e3:.1f} mm " \
                                              f"inside the margin (hand clearance {gaps.min() * 1e3:.1f} mm)"
    assert gaps[-1] <= model.margin + TOUCH, f"the daemon stopped the hands {gaps[-1] * 1e3:.1f} mm apart"
    assert np.abs(sends[-1][MODEL_ADDR] - gate.ref[MODEL_ADDR]).max() < 1e-4  # at rest where the gate holds it
    assert decisions[-1].held


def test_approach_can_be_switched_off(model) -> None:
    """approach_iterations 0: the blocked step is not passed at all (the arm stops up to a whole step short)."""
    gate = make_gate(model, approach_iterations=0)
    point = [0.40, 0.0, -0.10]
    target = HOME.copy()
    target[L], target[R] = solve("left", point), solve("right", point)
    drive(gate, target, 4.0)
    assert hand_clearance(model, gate.ref) > model.margin + TOUCH
    with pytest.raises(ValueError, match="approach_iterations"):
        GateConfig.from_mapping({"approach_iterations": -1})


# --------------------------------------------------------------------------------------------- channels


def _put(name: str, ref: np.ndarray) -> None:
    from mds_ach.robot.channels import StructChannel

    with StructChannel(name, mds.MDS_REF) as ch:
        ch.put(make_ref(ref, ZERO_MODE))


def test_runner_gates_the_channels(clean_shm: None, table_model) -> None:
    from mds_ach.robot.channels import StructChannel

    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    stale = HOME.copy()
    stale[mds.NKY] = 0.4
    _put(mds.MDS_CHAN_REF_SMOOTH_NAME, stale)  # left over from before: must not be acted on
    lower, upper = joint_limits(table_model)
    logs: list[str] = []
    runner = GateRunner(table_model, GateConfig(), lower, upper, log=lambda level, msg: logs.append(msg))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
    collide = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    try:
        assert runner.ready.wait(10), logs
        out.latest()  # our own HOME frame
        time.sleep(0.3)
        assert out.latest() is None  # the stale smooth frame was not passed on
        target = HOME.copy()
        target[L] = solve("left", [0.40, 0.25, -0.50])
        core = FilterCore(parse_config({"rate": 40}), HOME, ZERO_MODE)
        core.set_target(target, ZERO_MODE)
        flagged = False
        for k in range(160):  # lock-step, so that every frame is gated (the gate itself takes the newest)
            smooth.put(make_ref(core.step(), ZERO_MODE))
            wait_for(lambda k=k: runner.processed > k, 10, what=f"the gate to process frame {k}")
            c = collide.latest()
            flagged |= c is not None and c.isCollide == 1 and c.joint[mds.COLLIDE_L_HAND].isCollide == 1
        got = ref_arrays(wait_for(lambda: out.latest(), 5, what="gated frame"))[0]
        assert flagged
        hand = tool(table_model, got, "left_hand_link")
        assert hand[2] - 0.1 >= TABLE_TOP + table_model.margin - 1e-9
        assert len(runner.check_times) == 160
    finally:
        runner.stop()
        t.join(5)
        for ch in (out, collide, smooth):
            ch.close()
    assert not t.is_alive()


def _state(pos: np.ndarray) -> mds.MDS_STATE:
    """An mds-state frame as the daemon puts it now: every joint fresh at ``pos``."""
    st = mds.MDS_STATE()
    st.time = time.monotonic()
    for a in range(N):
        st.joint[a].pos = st.joint[a].ref = pos[a]
        st.joint[a].active = 1
    return st


def test_at_rest_a_measured_pose_moved_into_contact_is_held_within_one_daemon_cycle(clean_shm: None, model) -> None:
    """The gate sleeps at rest (no input, its report every 0.5 s), but it wakes on every mds-state frame: two
    compliant arms pushed together by hand while nothing is commanded are reported and held within one daemon
    cycle (10 Hz), not at its next idle report. The contact arrives right after an idle report, the worst phase
    for a gate that only looks at mds-state when it wakes for something else."""
    from mds_ach.robot.channels import StructChannel

    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    lower, upper = joint_limits(model)
    logs: list[str] = []
    runner = GateRunner(model, GateConfig(), lower, upper, log=lambda level, msg: logs.append(msg))
    t = threading.Thread(target=runner.run, daemon=True)
    collide = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
    state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
    pushed = HOME.copy()
    pushed[L], pushed[R] = solve("left", [0.40, 0.05, -0.10]), solve("right", [0.40, 0.05, -0.10])
    assert model.check(model.q_from_ref(pushed)).collides
    measured = [HOME]
    done = threading.Event()

    def daemon() -> None:  # mds-state at the daemon's 10 Hz, with the newest measured pose
        while not done.is_set():
            state.put(_state(measured[0]))
            done.wait(0.1)

    beat = threading.Thread(target=daemon, daemon=True)
    try:
        beat.start()
        t.start()
        assert runner.ready.wait(30), logs
        _put(mds.MDS_CHAN_REF_SMOOTH_NAME, HOME)  # the filter's output, then nothing: it rests
        wait_for(lambda: runner.processed >= 1, 10, what="the gate to pass the filter's frame")
        time.sleep(1.5)  # at rest: nothing new for more than a second
        collide.latest()
        report = wait_for(lambda: collide.wait(timeout=1.0), 5, what="an idle report")
        assert report.isCollide == 0
        measured[0] = pushed
        state.put(_state(pushed))
        t0 = time.monotonic()
        report = wait_for(lambda: (c := collide.wait(timeout=1.0)) is not None and c.isCollide == 1 and c, 5,
                          what="the contact on mds-collide")
        took = time.monotonic() - t0
        assert took <= 0.1, f"the contact was reported {took * 1e3:.0f} ms after the mds-state frame that showed it"
        assert report.joint[mds.COLLIDE_L_HAND].isCollide and report.joint[mds.COLLIDE_R_HAND].isCollide
    finally:
        runner.stop()
        done.set()
        t.join(5)
        beat.join(5)
        for ch in (collide, state):
            ch.close()
    assert not t.is_alive()


def test_the_hold_is_put_on_mds_collide_before_the_held_reference(clean_shm: None, table_model,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """The hand-off to the daemon is ordered: the gate puts a hold's report on mds-collide before the held reference
    on mds-ref-gated, and the daemon reads mds-ref-gated before mds-collide, so a daemon that reads a held reference
    also reads its hold (test_daemon.py::test_a_held_reference_is_read_with_its_hold is the daemon's side). Every put of
    the runner is recorded in order while the left hand is driven into the table: at each mds-ref-gated put, the
    newest mds-collide already flags every arm that reference holds."""
    from mds_ach.robot.channels import StructChannel

    events: list[tuple[str, object]] = []  # (channel, frame copy) per put, ("held", arms) per gated frame
    real_put = StructChannel.put

    def recording_put(self: StructChannel, obj, lock_timeout: float | None = None) -> None:
        real_put(self, obj, lock_timeout)
        if self.name in (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_COLLIDE_NAME):
            events.append((self.name, type(obj).from_buffer_copy(obj)))

    def on_report(decision, gate, now: float) -> None:
        if decision is not None:  # called after the frame's puts
            events.append(("held", decision.held))

    monkeypatch.setattr(StructChannel, "put", recording_put)
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    lower, upper = joint_limits(table_model)
    logs: list[str] = []
    runner = GateRunner(table_model, GateConfig(), lower, upper, log=lambda level, msg: logs.append(msg),
                        on_report=on_report)
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    try:
        assert runner.ready.wait(10), logs
        target = HOME.copy()
        target[L] = solve("left", [0.40, 0.25, -0.50])
        core = FilterCore(parse_config({"rate": 40}), HOME, ZERO_MODE)
        core.set_target(target, ZERO_MODE)
        for k in range(120):  # lock-step: every frame is gated
            smooth.put(make_ref(core.step(), ZERO_MODE))
            wait_for(lambda k=k: runner.processed > k, 10, what=f"the gate to process frame {k}")
    finally:
        runner.stop()
        t.join(5)
        smooth.close()
    assert not t.is_alive()
    parts = {"left": LEFT_PARTS, "right": RIGHT_PARTS, "all": LEFT_PARTS + RIGHT_PARTS}
    newest_collide, newest_ref_flags, holds = None, None, 0
    for name, item in events:
        if name == mds.MDS_CHAN_COLLIDE_NAME:
            newest_collide = item
        elif name == mds.MDS_CHAN_DAEMON_INPUT_NAME:
            newest_ref_flags = newest_collide  # what a daemon reading mds-ref, then mds-collide, could see at best
        elif item:  # the arms the reference just put holds
            holds += 1
            report = newest_ref_flags
            assert report is not None and report.isCollide == 1, f"held {item} without a hold on mds-collide"
            assert all(flags(report, parts[arm]) for arm in item), f"held {item}, mds-collide flags other parts"
    assert holds > 5, "the left hand was never held"


def test_runner_logs_a_refusal_once_per_change_and_counts_it(clean_shm: None, model) -> None:
    """Issue #17: the gate refused an out-of-limit input every frame and logged it every second, forever, while
    nothing said so elsewhere. Now: one message per change of what is refused (values and limits named), a
    counter in the runner and in /mds/collision's JSON."""
    from mds_ach.robot.channels import StructChannel

    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    lower, upper = joint_limits(model)
    logs: list[tuple[str, str]] = []
    docs: list[dict] = []
    runner = GateRunner(model, GateConfig(), lower, upper, log=lambda level, msg: logs.append((level, msg)),
                        on_report=lambda d, g, now: docs.append(decision_to_dict(d, g, now, runner.refused_count)))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    bad = HOME.copy()
    bad[mds.LWR] = -1.0  # inside the joint table's range, outside the URDF's (+-0.4712)
    worse = bad.copy()
    worse[mds.LSR] = -0.15  # the table allows -0.18, the URDF stops at 0
    frames = [HOME] + [bad] * 30 + [worse] * 30 + [HOME] * 5
    try:
        assert runner.ready.wait(10), logs
        for k, ref in enumerate(frames):  # lock-step: every frame is gated (30 frames of one refusal)
            smooth.put(make_ref(ref, ZERO_MODE))
            wait_for(lambda k=k: runner.processed > k, 10, what=f"the gate to process frame {k}")
    finally:
        runner.stop()
        t.join(5)
        smooth.close()
    refusals = [m for level, m in logs if "refus" in m]
    assert len(refusals) == 3, refusals  # LWR, then LWR + LSR, then accepted again
    assert "LWR: -1.00000 rad outside [-0.47120, 0.47120]" in refusals[0]
    assert "LSR: -0.15000 rad outside [0.00000," in refusals[1]
    assert "accepted again (60 refused so far)" in refusals[2]
    assert runner.refused_count == 60
    assert docs[-1]["refused_count"] == 60 and docs[-1]["refused"] == []
    assert any(d["refused"] == ["LSR", "LWR"] and d["refused_count"] >= 31 for d in docs)


def test_an_arm_stopped_at_contact_gets_its_command_cancelled_on_mds_hold(clean_shm: None, table_model) -> None:
    """The gate ends the command of an arm it stopped at contact: one HOLD_CANCEL on mds-hold for that arm's joints at
    the reference it holds, source 'collision', reason 'stopped at contact: <pair>' (the mux drops the target, so
    the arm does not go on later when the obstacle is moved away)."""
    from mds_ach.kinematics.limits import compute as compute_limits
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.msgs.hold import HOLD_CANCEL, MDS_HOLD, check_cancel

    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    lower, upper = joint_limits(table_model)
    logs: list[str] = []
    runner = GateRunner(table_model, GateConfig(approach_iterations=APPROACH), lower, upper,
                        log=lambda level, msg: logs.append(msg))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
    holds = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
    try:
        assert runner.ready.wait(10), logs
        holds.put(MDS_HOLD(seq=41, action=1))  # another writer's request: the gate's seq follows it
        holds.next()
        target = HOME.copy()
        target[L] = solve("left", [0.40, 0.25, -0.50])
        core = FilterCore(parse_config({"rate": 40}), HOME, ZERO_MODE)
        core.set_target(target, ZERO_MODE)
        for k in range(200):  # lock-step: every frame is gated
            smooth.put(make_ref(core.step(), ZERO_MODE))
            wait_for(lambda k=k: runner.processed > k, 10, what=f"the gate to process frame {k}")
        held = ref_arrays(out.latest())[0]
        frames = []
        while (f := holds.next()) is not None:
            frames.append(f)
    finally:
        runner.stop()
        t.join(5)
        for ch in (smooth, out, holds):
            ch.close()
    assert len(frames) == 1 and runner.cancels == 1, [bytes(f.reason) for f in frames]
    f = frames[0]
    assert f.action == HOLD_CANCEL and f.seq not in (0, 41)
    assert bytes(f.source).rstrip(b"\0") == b"collision"
    assert bytes(f.reason).split(b"\0")[0] == b"stopped at contact: left hand / table"
    assert [a for a in range(N) if f.joints[a]] == sorted(L.tolist())
    np.testing.assert_array_equal([f.target[a] for a in L], held[L])
    assert all(np.isnan(f.target[a]) for a in range(N) if a not in L)
    assert any("left arm stopped at contact: left hand / table" in m for m in logs)
    # the mux (and the network server) take it: at the reference the gate holds, inside the limits (issue 25)
    assert check_cancel(f, compute_limits(), held.tolist()) is None


# --------------------------------------------------------------------------------------------- node


def test_collision_help() -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-collision"), "--help"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "usage: collision" in proc.stdout and "override" in proc.stdout


@pytest.mark.ros
@pytest.mark.slow
def test_collision_node_reports_and_takes_an_override(clean_shm: None, tmp_path) -> None:
    """/mds/collision is typed (mds_ach_interfaces/msg/CollisionState): a held left arm with its hand among the
    parts, the expert override taken and reported, each unit in its one state."""
    import rclpy
    from mds_ach_interfaces.msg import CollisionState, CollisionUnit
    from rclpy.node import Node
    from std_msgs.msg import Float64

    world = tmp_path / "world.yaml"
    world.write_text(json.dumps(TABLE))  # JSON is YAML
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    proc = subprocess.Popen([str(VENV_BIN / "mds-ach-collision"), "--world", str(world)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    rclpy.init()
    node = Node("test_collision_client")
    msgs: list[CollisionState] = []
    node.create_subscription(CollisionState, "/mds/collision", msgs.append, 10)

    def held(m: CollisionState) -> list[str]:
        return [u.unit for u in m.units if u.state == CollisionUnit.HELD]
    override = node.create_publisher(Float64, "/mds/collision/override", 10)
    from mds_ach.robot.channels import StructChannel

    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not (msgs and override.get_subscription_count()):
            rclpy.spin_once(node, timeout_sec=0.1)
        assert msgs and override.get_subscription_count(), proc.poll()
        into_table = HOME.copy()
        into_table[L] = solve("left", [0.40, 0.25, -0.50])

        def feed_until(pred, what: str) -> None:
            end = time.monotonic() + 40
            while time.monotonic() < end:
                smooth.put(make_ref(into_table, ZERO_MODE))  # unsmoothed: the gate's speed bound paces it
                rclpy.spin_once(node, timeout_sec=0.025)
                if pred():
                    return
            proc.send_signal(signal.SIGTERM)
            raise AssertionError(f"timed out waiting for {what}; last: {msgs[-1:]}; node: {proc.communicate()[0]}")

        feed_until(lambda: any(held(m) == ["left"] and "L_HAND" in m.parts for m in msgs), "a held left arm")
        override.publish(Float64(data=2.0))
        feed_until(lambda: any(m.overridden and m.override_remaining > 0 for m in msgs), "the override")
        for m in msgs:
            assert [u.unit for u in m.units] == ["left", "right", "body"]
            assert {u.state for u in m.units} <= {CollisionUnit.FREE, CollisionUnit.HELD, CollisionUnit.RELEASING}
            assert m.margin == pytest.approx(0.02) and m.header.stamp.sec > 0
    finally:
        smooth.close()
        node.destroy_node()
        rclpy.shutdown()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=15)
    assert proc.returncode == 0, out
    assert "EXPERT OVERRIDE ON for 2.0 s" in out and "EXPERT OVERRIDE passed a predicted collision" in out
    assert "Traceback" not in out



def test_the_runner_does_not_grow_with_the_references_it_gates(clean_shm: None, model) -> None:
    """Issue 25 item 10: the node's memory grew while it gated (a list of decision times trimmed only at 10,000
    entries, ~0.3 MB). After a warm-up, thousands more gated references leave the Python heap where it was (the
    decision cache is capped at 512 configurations, ~0.1 MB, and is all that may still vary)."""
    import tracemalloc

    from mds_ach.robot.channels import StructChannel

    lower, upper = joint_limits(model)
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, HOME)
    runner = GateRunner(model, GateConfig(), lower, upper, log=lambda level, msg: None)
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    t = threading.Thread(target=runner.run, daemon=True)
    tracemalloc.start()
    try:
        t.start()
        assert runner.ready.wait(30)
        step = [0]

        def gate_until(count: int) -> None:
            while runner.processed < count:  # a moving reference (newest wins: the gate takes what it can)
                step[0] += 1
                ref = HOME.copy()
                ref[L] += 0.1 * np.sin(0.01 * step[0] + np.arange(len(L)))
                ref[R] += 0.1 * np.sin(0.013 * step[0] + np.arange(len(R)))
                smooth.put(make_ref(ref, ZERO_MODE))
                time.sleep(0.0002)
                assert t.is_alive()

        gate_until(1000)
        before = tracemalloc.get_traced_memory()[0]
        gate_until(7000)
        grown = tracemalloc.get_traced_memory()[0] - before
        assert grown < 140_000, f"{grown / 1e3:.0f} kB more after 6,000 more gated references"
    finally:
        tracemalloc.stop()
        runner.stop()
        t.join(5)
        smooth.close()
    assert not t.is_alive()
