"""The category-1 e-stop (issue #31 item 2): brake at the bounds, then DISABLE every drive; latched until reset,
across a daemon restart too; nothing moves meanwhile, whatever arrives; an e-stop input triggers it."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from pathlib import Path

import pytest
from support import VENV_BIN, wait_for
from support.rig import TABLE, DaemonRig

import mds_ach as mds
from mds_ach.bus.mcb import Command, StateArg
from mds_ach.nodes.estop import BRAKE_TIMEOUT, InputWatcher, LineInput, SimulatedInput
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_CMD
from mds_ach.robot.msgs import daemon_status as ds

POSE = {"LEP": -1.0, "LSP": -0.3, "REP": -1.0}


def command(rig: DaemonRig, code: int, value: float = 0.0) -> ds.MDS_DAEMON_STATUS:
    rig.cmd_seq += 1
    rig.cmd_out.put(MDS_CMD(seq=rig.cmd_seq, cmd=code, value=value))
    rig.step()
    st = rig.status()
    assert st.cmd_seq == rig.cmd_seq
    return st


def moveto_times(rig: DaemonRig, address: int, since: float = -1.0) -> list[float]:
    return [t for t, f in rig.net.commands if f.arbitration_id == address and f.command == Command.SET
            and f.argument == StateArg.MOVETO_TARGET and t >= since]


def disable_times(rig: DaemonRig) -> dict[int, float]:
    out: dict[int, float] = {}
    for t, f in rig.net.commands:
        if f.command == Command.DISABLE:
            out.setdefault(f.arbitration_id, t)
    return out


def at_full_speed(rig: DaemonRig) -> None:
    """LSP and LEP on their way far away at the joint speed bound."""
    rig.put_ref(LSP=-2.5, LEP=-0.1)
    rig.step(round(0.6 * rig.loop.rate))
    assert abs(rig.loop.joints[TABLE["LSP"].address].track.v) > 1.7


@pytest.fixture
def latch(tmp_path: Path) -> Path:
    return tmp_path / "estop.latched"


@pytest.mark.parametrize("rate", [10.0, 100.0])
def test_estop_during_motion_brakes_at_the_bound_then_disables_and_nothing_moves_until_reset(
        clean_shm: None, latch: Path, rate: float) -> None:
    rig = DaemonRig(rate=rate, pose=POSE, estop_latch=latch, bitrate=None if rate > 50 else 1_000_000)
    try:
        rig.loop.start_up()
        at_full_speed(rig)
        t_estop = rig.clock.now
        st = command(rig, mds.MDS_CMD_ESTOP)
        assert st.cmd_result == ds.CMD_OK and st.estop in (ds.ESTOP_STOPPING, ds.ESTOP_STOPPED) and latch.exists()
        for _ in range(round(3 * rate)):
            if rig.status().estop == ds.ESTOP_STOPPED:
                break
            rig.put_ref(LSP=-2.5, LEP=-0.1)  # upstream keeps commanding: ignored
            rig.step()
        assert rig.status().estop == ds.ESTOP_STOPPED
        # braked within the bounds (the audit of every target), at the bound: the targets stand still after
        # v / (0.9 a) = 0.25 s (the last changing target one step before)
        assert rig.audit().violations == []
        lsp = TABLE["LSP"].address
        last_target = moveto_times(rig, lsp)[-1]
        assert 0.2 <= last_target + 1 / rate - t_estop <= 0.3, last_target - t_estop  # its step ends at rest
        # then, once the joints settled (the nodes follow their targets at the MOVETO acceleration), DISABLE to
        # every drive of the table
        disabled = disable_times(rig)
        assert set(disabled) == {j.address for j in TABLE if j.enabled}
        assert last_target < min(disabled.values()) <= t_estop + BRAKE_TIMEOUT + 2 / rate
        travelled = abs(rig.loop.joints[lsp].track.q - rig.loop.joints[lsp].ref_r)
        assert travelled > 0.5  # stopped far from where it was going
        stopped_at = {a: rig.measured(TABLE[a].short) for a in (lsp, TABLE["LEP"].address)}

        # nothing moves: references (a new goal, a legacy-style put), ENABLE, HOME are refused or ignored
        sent = len(rig.net.commands)
        rig.put_ref(LSP=-1.0, LEP=-0.5)
        rig.step(round(0.5 * rate))
        assert command(rig, mds.MDS_CMD_ENABLE).cmd_result == ds.CMD_REFUSED
        assert command(rig, mds.MDS_CMD_HOME).cmd_result == ds.CMD_REFUSED
        moves = [f for _, f in rig.net.commands[sent:] if f.command != Command.QUERY_STATE]
        assert moves == []
        for a, q in stopped_at.items():
            assert rig.measured(TABLE[a].short) == pytest.approx(q, abs=1e-6)

        # reset: the latch goes, the drives stay disabled; enable restarts every joint where it stands
        st = command(rig, mds.MDS_CMD_ESTOP_RESET)
        assert (st.cmd_result, st.estop) == (ds.CMD_OK, ds.ESTOP_OFF) and not latch.exists()
        rig.step(round(0.3 * rate))
        assert [f for _, f in rig.net.commands[sent:] if f.command == Command.SET] == []
        assert command(rig, mds.MDS_CMD_ENABLE).cmd_result == ds.CMD_OK
        rig.step(round(0.5 * rate))
        assert rig.loop.joints[lsp].track.q == pytest.approx(stopped_at[lsp], abs=1e-3)  # re-seeded, no jump
        rig.put_ref(LSP=stopped_at[lsp] + 0.2)
        rig.step(round(1.0 * rate))
        assert rig.measured("LSP") == pytest.approx(stopped_at[lsp] + 0.2, abs=0.02)
        assert rig.audit().violations == []
    finally:
        rig.close()


def test_the_estop_stays_latched_across_a_daemon_restart(clean_shm: None, latch: Path) -> None:
    rig = DaemonRig(pose=POSE, estop_latch=latch)
    rig.loop.start_up()
    at_full_speed(rig)
    command(rig, mds.MDS_CMD_ESTOP)
    rig.close()  # the daemon dies mid-stop (SIGKILL-like: nothing more is sent)
    assert latch.exists()

    again = DaemonRig(pose={s: q for s, q in POSE.items()}, estop_latch=latch)
    try:
        again.loop.start_up()
        st = again.step()
        assert again.status().estop == ds.ESTOP_STOPPED
        assert set(disable_times(again)) == {j.address for j in TABLE if j.enabled}  # DISABLE at once
        sent = len(again.net.commands)
        again.put_ref(LSP=0.2, LEP=-0.3)
        again.step(10)
        assert [f for _, f in again.net.commands[sent:] if f.command != Command.QUERY_STATE] == []
        assert command(again, mds.MDS_CMD_ENABLE).cmd_result == ds.CMD_REFUSED
        assert command(again, mds.MDS_CMD_ESTOP_RESET).estop == ds.ESTOP_OFF and not latch.exists()
        assert st is not None
    finally:
        again.close()


def test_a_simulated_input_triggers_the_estop(clean_shm: None, latch: Path) -> None:
    rig = DaemonRig(pose=POSE, estop_latch=latch)
    button = SimulatedInput()
    watcher = InputWatcher(button, lambda: rig.loop.submit(mds.MDS_CMD_ESTOP))
    try:
        rig.loop.start_up()
        at_full_speed(rig)
        button.press()
        wait_for(lambda: not rig.loop.commands.empty(), 5.0, what="the e-stop command of the input")
        rig.step()
        assert rig.status().estop == ds.ESTOP_STOPPING and latch.exists()
    finally:
        watcher.close()
        rig.close()


def test_a_line_input_presses_on_a_line_and_fails_safe(tmp_path: Path) -> None:
    fifo = tmp_path / "button"
    os.mkfifo(fifo)
    source = LineInput(fifo)
    try:
        assert not source.wait(0.05)
        writer = threading.Thread(target=lambda: fifo.write_text("noise\nESTOP\n"))
        writer.start()
        assert source.wait(5.0)
        writer.join()
        assert not source.wait(0.05)
    finally:
        source.close()
    plain = tmp_path / "file"
    plain.write_text("0\n")
    source = LineInput(plain)
    try:
        assert source.wait(1.0)  # a regular file ends: the input is gone, so that is a press (fail-safe)
    finally:
        source.close()


def _daemon(env: dict[str, str], *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen([str(VENV_BIN / "mds-ach-daemon"), "--nocan", "--no-ros", "--sim-ideal", "--rate", "50",
                             "--rt-priority", "0", *extra], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def _cli(env: dict[str, str], *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(VENV_BIN / "mds-ach"), *args], env=env, capture_output=True, text=True, timeout=60)


def test_mds_ach_estop_latches_across_a_daemon_restart_until_reset(clean_shm: None, tmp_path: Path) -> None:
    """The operator's commands against the real daemon process: `mds-ach estop` stops it; the daemon, killed and
    started again, is still stopped; `mds-ach estop reset` clears it; `mds-ach mode` switches and shows the mode."""
    env = {**os.environ, "MDS_ACH_RUNTIME_DIR": str(tmp_path)}
    proc = _daemon(env)
    status = StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    try:
        wait_for(lambda: status.latest(), 30.0, what="mds-daemon-status")
        done = _cli(env, "mode", "collaborative")
        assert done.returncode == 0 and "collaborative <= 250 mm/s" in done.stdout, done
        done = _cli(env, "estop")
        assert done.returncode == 0 and "E-STOP" in done.stdout, done
        assert (tmp_path / "estop.latched").exists()
        proc.kill()
        proc.communicate(timeout=20)
        proc = _daemon(env)
        wait_for(lambda: (st := status.latest()) is not None and st.pid == proc.pid, 30.0, what="the new daemon")
        shown = _cli(env, "estop", "show")
        assert shown.returncode == 0 and "E-STOP STOPPED" in shown.stdout, shown
        refused = _cli(env, "enable", "all")
        assert refused.returncode == 1 and "refused" in refused.stderr, refused
        done = _cli(env, "estop", "reset")
        assert done.returncode == 0 and "E-STOP" not in done.stdout, done
        assert not (tmp_path / "estop.latched").exists()
        assert _cli(env, "enable", "all").returncode == 0
        assert "normal mode" in _cli(env, "mode").stdout  # (the table's default again after the restart)
    finally:
        status.close()
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
