"""Filter node: per-joint modes (shared maths in mds_ach.nodes.filters), config, late start, node life."""

from __future__ import annotations

import math
import signal
import subprocess
import threading

import numpy as np
import pytest
from support import VENV_BIN, wait_for

import mds_ach as mds
from mds_ach.nodes import filters
from mds_ach.nodes.filter import EMA, ENC, PASS, VEL, FilterCore, FilterRunner, load_config, parse_config
from mds_ach.nodes.pipeline import make_ref, ref_arrays

N = mds.MDS_JOINT_COUNT
ZERO_MODE = np.zeros(N, dtype=np.int16)


def _target(**joints: float) -> np.ndarray:
    t = np.zeros(N)
    for name, value in joints.items():
        t[getattr(mds, name)] = value
    return t


# --------------------------------------------------------------------------------------------- config


def test_default_config_is_the_deployed_velocity_limiter() -> None:
    p = load_config()
    assert p.rate == 40.0
    assert np.all(p.mode == VEL)
    assert np.all(p.max_velocity == 1.57)
    assert np.all(p.max_accel == 4.0)  # below the daemon's 0.9 x 8 rad/s^2 (config/joints.yaml motion:)
    assert p.length[mds.LSP] == pytest.approx(filters.filter_length(40.0, 4.0, 0.95))


def test_per_joint_overrides_apply_in_order() -> None:
    p = parse_config({
        "rate": 20,
        "default": {"mode": "ema", "settle_time": 2.0},
        "joints": [
            {"joints": "left_arm", "mode": "velocity_limit", "max_velocity": 1.0},
            {"joints": ["LSP"], "max_accel": 4.0},
            {"joints": "neck", "mode": "enc_filter"},
            {"joints": "WST", "mode": "pass"},
        ],
    })
    assert p.rate == 20 and p.dt == 0.05
    assert p.mode[mds.RSP] == EMA and p.length[mds.RSP] == pytest.approx(filters.filter_length(20, 2.0))
    assert p.mode[mds.LEP] == VEL and p.max_velocity[mds.LEP] == 1.0 and math.isinf(p.max_accel[mds.LEP])
    assert p.mode[mds.LSP] == VEL and p.max_velocity[mds.LSP] == 1.0 and p.max_accel[mds.LSP] == 4.0
    assert p.mode[mds.NKY] == ENC and p.mode[mds.WST] == PASS


@pytest.mark.parametrize(
    "data, message",
    [
        ({"default": {"mode": "spline"}}, "mode must be one of"),
        ({"default": {"max_velocity": 0}}, "max_velocity"),
        ({"default": {"max_accel": -1}}, "max_accel"),
        ({"rate": 0}, "rate"),
        ({"default": {"settle_fraction": 1.0}}, "settle_fraction"),
        ({"joints": [{"mode": "ema"}]}, "needs 'joints'"),
        ({"joints": [{"joints": "XYZ", "mode": "ema"}]}, "unknown joint"),
        ({"smoothing": 1}, "unknown keys"),
    ],
)
def test_bad_filter_config_is_refused(data: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_config(data)


# --------------------------------------------------------------------------------------------- modes


def test_velocity_limiter_ramps_at_max_speed_and_snaps() -> None:
    p = parse_config({"rate": 40})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    core.set_target(_target(LSP=1.0, REP=-0.01), ZERO_MODE)
    out = core.step()
    assert out[mds.LSP] == pytest.approx(1.57 / 40)
    assert out[mds.REP] == -0.01  # within one step: lands on the target
    steps = [core.step()[mds.LSP] for _ in range(40)]
    assert np.all(np.diff([1.57 / 40, *steps]) <= 1.57 / 40 + 1e-12)
    assert steps[-1] == 1.0
    assert steps.index(1.0) + 2 == math.ceil(1.0 / (1.57 / 40))  # constant speed until the last step


def test_ema_covers_95_percent_in_settle_time() -> None:
    p = parse_config({"rate": 40, "default": {"mode": "ema"}})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    core.set_target(_target(LEP=-1.0), ZERO_MODE)
    values = [core.step()[mds.LEP] for _ in range(int(4.0 * 40))]
    assert values[-1] == pytest.approx(-0.95, abs=1e-9)
    assert values[-2] > -0.95
    assert values[0] == pytest.approx(-1.0 / p.length[mds.LEP])


def test_enc_filter_follows_measured_position() -> None:
    p = parse_config({"rate": 10, "default": {"mode": "enc_filter"}})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    core.set_target(_target(LSR=1.0), ZERO_MODE)
    measured = _target(LSR=0.5)
    out = core.step(measured)
    L = p.length[mds.LSR]
    assert out[mds.LSR] == pytest.approx((0.5 * (L - 1) + 1.0) / L)
    # without a measurement it behaves as the plain first-order filter from its own output
    out2 = core.step(None)
    assert out2[mds.LSR] == pytest.approx((out[mds.LSR] * (L - 1) + 1.0) / L)


def test_acceleration_limit_ramps_speed_up_and_brakes_onto_target() -> None:
    p = parse_config({"rate": 100, "default": {"max_velocity": 1.0, "max_accel": 2.0}})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    core.set_target(_target(WST=0.3), ZERO_MODE)
    pos = [0.0] + [core.step()[mds.WST] for _ in range(200)]
    vel = np.diff(pos) * 100
    acc = np.abs(np.diff(vel)) * 100
    landing = int(np.argmax(np.array(pos) == 0.3))  # index of the first sample on the target
    assert 0 < landing < 100
    assert np.all(acc[: landing - 2] <= 2.0 + 1e-6)  # |accel| bounded while speeding up and braking
    assert np.all(acc <= 1.25 * 2.0)  # the landing steps: discretisation only
    assert np.max(vel) <= 1.0 + 1e-9
    assert pos[-1] == 0.3 and np.all(np.diff(pos) >= 0)  # no overshoot


def test_pass_mode_and_mode_field_pass_through() -> None:
    p = parse_config({"default": {"mode": "pass"}})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    mode = ZERO_MODE.copy()
    mode[mds.NKY] = mds.MDS_REF_MODE_REF
    core.set_target(_target(NKY=0.4), mode)
    assert core.step()[mds.NKY] == 0.4 and core.mode[mds.NKY] == mds.MDS_REF_MODE_REF


def test_joints_the_direct_controller_owns_pass_unsmoothed() -> None:
    """config/filter.yaml `controllers: direct: mode: pass`: a joint owned by the mux's `direct` controller (mds-ref,
    expert clients) takes its target in one step; the others keep smoothing; released, a joint smooths again from
    rest."""
    from mds_ach.nodes.filter import owner_names
    from mds_ach.robot.msgs import MDS_MUX_STATE

    assert load_config().controllers["direct"][0] == PASS  # the shipped default
    st = MDS_MUX_STATE()
    st.count = 2
    st.name[0] = type(st.name[0]).from_buffer_copy(b"ros".ljust(30, b"\0"))
    st.name[1] = type(st.name[1]).from_buffer_copy(b"direct".ljust(30, b"\0"))
    for a in range(N):
        st.owner[a] = -1
    st.owner[mds.LSP], st.owner[mds.LEP] = 1, 0
    owners = owner_names(st)
    assert owners[mds.LSP] == "direct" and owners[mds.LEP] == "ros" and owners[mds.RSP] is None

    core = FilterCore(parse_config({"rate": 40, "controllers": {"direct": {"mode": "pass"}}}), np.zeros(N), ZERO_MODE)
    core.set_owners(owners)
    core.set_target(_target(LSP=0.5, LEP=0.5), ZERO_MODE)
    out = core.step()
    assert out[mds.LSP] == 0.5, "the direct controller's joint is not smoothed"
    assert 0 < out[mds.LEP] < 0.05, "the other joints still are"
    core.set_owners([None] * N)  # the direct controller went stale: LSP smooths again, from rest
    core.set_target(_target(LSP=0.0, LEP=0.5), ZERO_MODE)
    assert core.vel[mds.LSP] == 0.0 and 0.45 < core.step()[mds.LSP] < 0.5
    with pytest.raises(ValueError, match="controllers.direct"):
        parse_config({"controllers": {"direct": {"mode": "warp"}}})


def test_the_bridges_trajectory_frames_pass_unsmoothed_and_its_position_commands_are_smoothed() -> None:
    """config/filter.yaml `controllers: ros: {mode: pass, modes: [1]}` (issue #26): the bridge's trajectory targets
    (pass-through frames, already timed stopping points) are not smoothed a second time; its position commands (mode
    0) are, as before; a joint switching from one to the other starts from rest where it is."""
    shipped = load_config()
    assert shipped.controllers["ros"][0] == PASS and shipped.controller_modes["ros"] == {mds.MDS_REF_MODE_REF}
    owners = [None] * N
    owners[mds.LSP] = owners[mds.LEP] = "ros"
    config = {"rate": 40, "controllers": {"ros": {"mode": "pass", "modes": [1]}}}
    core = FilterCore(parse_config(config), np.zeros(N), ZERO_MODE)
    core.set_owners(owners)
    mode = ZERO_MODE.copy()
    mode[mds.LSP] = mds.MDS_REF_MODE_REF  # a trajectory's target on LSP, a position command on LEP
    core.set_target(_target(LSP=0.5, LEP=0.5), mode)
    out = core.step()
    assert out[mds.LSP] == 0.5, "a trajectory's target is not smoothed"
    assert 0 < out[mds.LEP] < 0.05, "a position command still is"
    core.set_target(_target(LSP=0.0, LEP=0.5), ZERO_MODE)  # LSP: now a position command
    assert core.vel[mds.LSP] == 0.0 and 0.45 < core.step()[mds.LSP] < 0.5
    with pytest.raises(ValueError, match="controllers.ros: modes"):
        parse_config({"controllers": {"ros": {"mode": "pass", "modes": [7]}}})


def test_smoothed_joints_tell_the_daemon_not_to_filter_again() -> None:
    p = parse_config({"joints": [{"joints": "WST", "mode": "pass"}]})
    core = FilterCore(p, np.zeros(N), ZERO_MODE)
    mode = ZERO_MODE.copy()
    mode[mds.NKY] = mds.MDS_REF_MODE_COMPLIANT
    core.set_target(np.zeros(N), mode)
    out = core.out_mode()
    assert out[mds.LSP] == mds.MDS_REF_MODE_REF  # legacy mode 0 -> already smoothed here
    assert out[mds.NKY] == mds.MDS_REF_MODE_COMPLIANT  # explicit requests pass through
    assert out[mds.WST] == mds.MDS_REF_MODE_REF_FILTER  # not smoothed here: the daemon's filter still applies
    assert np.all(FilterCore(parse_config({"mark_smoothed": False}), np.zeros(N), ZERO_MODE).out_mode() == 0)


def test_non_finite_targets_are_ignored_per_joint() -> None:
    core = FilterCore(parse_config({}), np.zeros(N), ZERO_MODE)
    t = _target(LSP=0.5, RSP=-0.5)
    t[mds.LEP] = float("nan")
    warning = core.set_target(t, ZERO_MODE)
    assert "LEP" in warning
    for _ in range(100):
        out = core.step()
    assert np.all(np.isfinite(out)) and out[mds.LEP] == 0.0 and out[mds.LSP] == 0.5 and out[mds.RSP] == -0.5


# --------------------------------------------------------------------------------------------- channels


def _put(name: str, ref: np.ndarray) -> None:
    from mds_ach.robot.channels import StructChannel

    with StructChannel(name, mds.MDS_REF) as ch:
        ch.put(make_ref(ref, ZERO_MODE))


def test_runner_starts_late_without_jump_and_resumes_the_mux_target(clean_shm: None) -> None:
    from mds_ach.robot.channels import StructChannel

    current = _target(LSR=1.2, RSR=-1.18, LEP=-1.25, REP=-1.25)
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, current)  # what the daemon is commanding now
    _put(mds.MDS_CHAN_REF_MUX_NAME, _target(LSR=1.2, RSR=-1.18, LEP=-0.25, REP=-1.25))  # pending mux target
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    runner = FilterRunner(parse_config({"rate": 100}), log=lambda level, msg: None)
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    try:
        # the runner's very first frame (in order: newest-wins would show a later one if this thread is slow)
        first = wait_for(smooth.next, 10, what="first smoothed frame")
        got = ref_arrays(first)[0]
        step = 1.57 / 100
        assert abs(got[mds.LEP] - current[mds.LEP]) <= step + 1e-12  # starts at the current reference
        assert np.array_equal(np.delete(got, mds.LEP), np.delete(current, mds.LEP))
        newest = smooth.latest() or first  # from here on newest wins, as before
        frames = [ref_arrays(newest)[0][mds.LEP]]

        def arrived() -> bool:
            while (f := smooth.latest()) is not None:
                frames.append(ref_arrays(f)[0][mds.LEP])
            return bool(frames) and frames[-1] == -0.25

        wait_for(arrived, 10, what="the filter to reach the mux target")
        seq = frames
        assert np.all(np.diff(seq) >= 0) and np.all(np.diff(seq) <= 2 * step + 1e-12)  # no jump (newest wins)
    finally:
        runner.stop()
        t.join(5)
        smooth.close()
    assert not t.is_alive()


def test_runner_waits_for_a_reference_instead_of_commanding_zero(clean_shm: None) -> None:
    from mds_ach.robot.channels import StructChannel

    logs: list[str] = []
    runner = FilterRunner(parse_config({}), log=lambda level, msg: logs.append(msg))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    try:
        wait_for(lambda: any("waiting for a current reference" in m for m in logs), 5, what="waiting message")
        assert smooth.latest() is None
        _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, _target(LSR=0.9))
        first = wait_for(lambda: smooth.latest(), 5, what="first frame after the reference appeared")
        assert ref_arrays(first)[0][mds.LSR] == 0.9
    finally:
        runner.stop()
        t.join(5)
        smooth.close()


# --------------------------------------------------------------------------------------------- node


def test_filter_help() -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-filter"), "--help"], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "usage: filter" in proc.stdout and "1.57" in proc.stdout


def test_filter_rejects_bad_config_with_a_clear_message(tmp_path) -> None:
    bad = tmp_path / "filter.yaml"
    bad.write_text("default: {mode: cubic}\n")
    proc = subprocess.run([str(VENV_BIN / "mds-ach-filter"), "--config", str(bad)], capture_output=True, text=True,
                          timeout=30)
    assert proc.returncode == 2
    assert "mode must be one of" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.ros
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_filter_node_streams_and_stops_cleanly(clean_shm: None, sig: int) -> None:
    from mds_ach.robot.channels import StructChannel

    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, _target(LSR=1.2))
    proc = subprocess.Popen([str(VENV_BIN / "mds-ach-filter"), "--rate", "50"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        with StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF) as smooth:
            count = [0]

            def frames() -> bool:
                while smooth.latest() is not None:
                    count[0] += 1
                return count[0] >= 1

            for _ in range(3):  # a steady stream: new frames keep coming without any input change
                count[0] = 0
                wait_for(frames, 20, what="smoothed frames")
    finally:
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=15)
    assert proc.returncode == 0, out
    assert "Traceback" not in out, out


def test_runner_holds_its_output_while_it_cannot_write_it_and_goes_on_without_a_step(clean_shm: None) -> None:
    """mds-ref-smooth scribbled over (issue 25 item 7): the filter keeps running and holds its output where the gate
    last saw it; after `mds-ach repair` re-created the channel it writes it again, one step from there."""
    import os

    from mds_ach import ach
    from mds_ach.robot.channels import StructChannel
    from mds_ach.tools import repair

    current = _target(LSR=1.2, RSR=-1.18, LEP=-1.25, REP=-1.25)
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, current)
    _put(mds.MDS_CHAN_REF_MUX_NAME, _target(LSR=1.2, RSR=-1.18, LEP=0.0, REP=-1.25))  # 1.25 rad away: 0.8 s
    smooth = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
    logged: list[str] = []
    runner = FilterRunner(parse_config({"rate": 100}), log=lambda level, msg: logged.append(msg))
    t = threading.Thread(target=runner.run, daemon=True)
    t.start()
    step = 1.57 / 100
    try:
        first = wait_for(smooth.next, 10, what="first smoothed frame")
        before = [ref_arrays(f)[0][mds.LEP] for f in (first, *iter(smooth.next, None))]
        fd = os.open(ach.shm_path(mds.MDS_CHAN_REF_SMOOTH_NAME), os.O_RDWR)
        os.pwrite(fd, b"X" * 80, 16)
        os.close(fd)
        ticks = runner.ticks
        wait_for(lambda: runner.ticks >= ticks + 30, 10, what="the filter to run on through the outage")
        assert t.is_alive() and any(f"mds-ach repair {mds.MDS_CHAN_REF_SMOOTH_NAME}" in m for m in logged), logged
        assert repair.repair(mds.MDS_CHAN_REF_SMOOTH_NAME).action == "re-created"
        after = ref_arrays(wait_for(smooth.next, 10, what="a smoothed frame after the repair"))[0][mds.LEP]
        # at most the frames put between the last read and the scribble, plus one step: not the 0.3 s it would have
        # travelled meanwhile
        assert before and 0 <= after - before[-1] <= 4 * step + 1e-9, (before[-3:], after)
    finally:
        runner.stop()
        t.join(5)
        smooth.close()
    assert not t.is_alive()
