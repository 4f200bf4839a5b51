"""The one background-process helper (mds_ach.procs) and its users' pid-file handling (launcher, remote, viewer)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import wait_for

from mds_ach import procs
from mds_ach.net import remote
from mds_ach.tools import launcher, viewer

SLEEPER = "import time; time.sleep(60)"


@pytest.fixture
def run_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("MDS_ACH_RUNTIME_DIR", str(tmp_path))
    return tmp_path


@pytest.fixture
def children() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for proc in started:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


def _sleeper(children: list[subprocess.Popen[bytes]], *tag: str) -> subprocess.Popen[bytes]:
    """A process whose command line carries ``tag`` (what the pid-file owners look for)."""
    proc = subprocess.Popen([sys.executable, "-c", SLEEPER, *tag])
    children.append(proc)
    wait_for(lambda: tag[0] in procs.proc_argv(proc.pid) if tag else procs.alive(proc.pid), 10, what="sleeper")
    return proc


def _zombie(children: list[subprocess.Popen[bytes]], *tag: str) -> subprocess.Popen[bytes]:
    """An exited child that nobody reaped: its /proc entry stays, with state Z."""
    proc = _sleeper(children, *tag)
    os.kill(proc.pid, signal.SIGKILL)
    wait_for(lambda: (procs._read_stat(proc.pid) or " Z").rsplit(")", 1)[1].split()[0] == "Z", 10, what="zombie")
    return proc


def test_zombies_and_dead_tasks_are_not_alive(children: list[subprocess.Popen[bytes]],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    live = _sleeper(children)
    assert procs.alive(live.pid)
    zombie = _zombie(children)
    assert Path(f"/proc/{zombie.pid}").exists() and not procs.alive(zombie.pid)
    # state X (dead, being torn down) after a comm that itself contains ") ": the state follows the last ')'
    monkeypatch.setattr(procs, "_read_stat", lambda pid: f"{pid} (odd) S name) X 1 2 3")
    assert not procs.alive(live.pid)
    assert not procs.alive(2**22 + 12345)  # no such pid


def test_pid_files_are_trusted_only_for_our_live_process(tmp_path: Path,
                                                        children: list[subprocess.Popen[bytes]]) -> None:
    path = tmp_path / "x.pid"
    assert procs.running_pid(path, lambda argv: True) is None  # missing
    for garbage in ("", "abc\n", "-5\n", "0\n"):
        path.write_text(garbage)
        assert procs.running_pid(path, lambda argv: True) is None, garbage
    other = _sleeper(children, "some-other-program")
    procs.write_pid_file(path, other.pid)
    assert path.read_text() == f"{other.pid}\n"
    assert procs.running_pid(path, lambda argv: "mds_ach.tools.viewer" in argv) is None  # a reused pid
    assert procs.running_pid(path, lambda argv: "some-other-program" in argv) == other.pid


def test_stop_pid_escalates_and_tolerates_a_process_that_is_already_gone(
        children: list[subprocess.Popen[bytes]]) -> None:
    stubborn = subprocess.Popen([sys.executable, "-c", "import signal, sys, time\n"
                                 "signal.signal(signal.SIGTERM, signal.SIG_IGN); print(flush=True); time.sleep(60)"],
                                stdout=subprocess.PIPE)
    children.append(stubborn)
    assert stubborn.stdout is not None and stubborn.stdout.readline() == b"\n"  # SIGTERM is ignored from here on
    assert procs.stop_pid(stubborn.pid, grace=0.2, reap=stubborn.poll) is True  # needed SIGKILL
    assert stubborn.poll() == -signal.SIGKILL
    assert procs.stop_pid(stubborn.pid, grace=0.2) is False  # gone: no error, nothing to do
    assert procs.signal_pid(stubborn.pid, signal.SIGTERM) is False


def test_viewer_ignores_a_zombie_or_dead_viewer_and_stops_a_live_one(
        run_dir: Path, children: list[subprocess.Popen[bytes]], monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The viewer's own copy of the liveness check knew zombies (Z) but not dead tasks (X): `mds-ach sim` then
    said "already running" for a viewer that was gone, and `sim kill` signalled it."""
    pid_file = run_dir / viewer.SIM_PID
    zombie = _zombie(children, "mds_ach.tools.viewer")
    procs.write_pid_file(pid_file, zombie.pid)
    assert viewer.running_viewer() is None
    live = _sleeper(children, "mds_ach.tools.viewer")
    procs.write_pid_file(pid_file, live.pid)
    assert viewer.running_viewer() == live.pid
    real_read_stat = procs._read_stat
    monkeypatch.setattr(procs, "_read_stat", lambda pid: f"{pid} (python3) X 1" if pid == live.pid
                        else real_read_stat(pid))
    assert viewer.running_viewer() is None
    monkeypatch.undo()
    monkeypatch.setenv("MDS_ACH_RUNTIME_DIR", str(run_dir))
    assert viewer.stop_background(timeout=5.0) == 0
    assert f"viewer stopped (pid {live.pid})" in capsys.readouterr().out
    wait_for(lambda: live.poll() is not None, 10, what="viewer stub stopped")
    assert not pid_file.exists()
    assert viewer.stop_background() == 0 and "not running" in capsys.readouterr().out


def test_launcher_and_remote_read_pid_files_through_the_helper(run_dir: Path,
                                                               children: list[subprocess.Popen[bytes]]) -> None:
    node = _sleeper(children, "/usr/bin/filter")
    procs.write_pid_file(launcher.pid_path("filter", run_dir), node.pid)
    assert launcher.read_pid("filter", run_dir) == node.pid
    assert launcher.read_pid("mux", run_dir) is None
    procs.write_pid_file(launcher.pid_path("mux", run_dir), node.pid)  # the filter's pid in the mux's file
    assert launcher.read_pid("mux", run_dir) is None
    session = _sleeper(children, "mds_ach.net.remote")
    procs.write_pid_file(run_dir / "remote.pid", session.pid)
    assert remote.read_pid(run_dir / "remote.pid") == session.pid
    procs.write_pid_file(run_dir / "remote.pid", node.pid)
    assert remote.read_pid(run_dir / "remote.pid") is None


def test_a_log_is_appended_with_a_start_marker_and_rotated_when_large(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """Each start appends ``===== start <time> pid <pid>: <command> =====`` and its output (a crash's lines
    survive the restart); ``log_tail`` shows the newest run; an oversized log moves to ``.log.1`` at a start."""
    log = tmp_path / "node.log"
    pids = []
    for word in ("first", "second"):
        proc = procs.spawn_detached([sys.executable, "-c", f"print('{word} run')"], log)
        proc.wait()
        pids.append(proc.pid)
    lines = log.read_text().splitlines()
    assert [line.split(" pid ", 1)[1].split(":")[0] for line in lines[::2]] == [str(p) for p in pids]
    assert all(line.startswith(procs.START_MARKER) for line in lines[::2]) and lines[1::2] == ["first run",
                                                                                               "second run"]
    assert procs.log_tail(log, 10) == ["second run"]
    monkeypatch.setattr(procs, "LOG_ROTATE_BYTES", log.stat().st_size - 1)
    proc = procs.spawn_detached([sys.executable, "-c", "print('third run')"], log)
    proc.wait()
    assert (tmp_path / "node.log.1").read_text().splitlines()[1::2] == ["first run", "second run"]
    assert log.read_text().splitlines()[1:] == ["third run"]
