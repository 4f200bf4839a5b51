"""The one system start-up of the tests: the simulated robot's processes, started the way an operator starts
them, and the readers of the running robot.

* ``running_system(runtime)``: the whole system with ``mds-ach start nocan`` in a clean /dev/shm, ``mds-ach
  stop`` + ``killall`` afterwards (operator-tool tests; each module starts it once to keep the suite fast).
* ``Pipeline``: the nodes one by one, each its own process started by its console script (= ``ros2 run
  mds_ach <exe>``), for tests that kill and restart single nodes.
* ``isolated_run(env, python)``: ``tools/netns-run ... mds-ach run --nocan`` in namespaces of its own (nested in the
  tests' one), as ``make run`` starts it; for the tests that reach it from outside (``mds-ach ros``).
* ``wait_heartbeat``: the one readiness rule both use for a node process: two new frames on the channel it
  writes periodically (``HEARTBEATS``), or a line in its log for a node without one.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import mds_ach as mds
from mds_ach import ach
from mds_ach.paths import bin_name

from . import REPO, VENV_BIN, in_netns, remove_mds_channels
from .channels import newest, state
from .reference_chain import chain_fk

__all__ = ["HEARTBEATS", "START_TIMEOUT", "Pipeline", "arm_pos", "arm_refs", "chain_fk", "joint_pos", "joint_ref",
           "isolated_run", "mds_ach", "newest", "running_system", "state", "system_env", "wait_heartbeat"]

START_TIMEOUT = 150.0  # s: cold start imports fcl and rclpy on a shared 2-core machine (5 engineers' tests)
HEARTBEATS = {  # node -> a channel it writes periodically (mds-collide: at least every 0.5 s, even without input)
    "daemon": mds.MDS_CHAN_STATE_NAME,
    "mux": mds.MDS_CHAN_MUX_STATE_NAME,
    "filter": mds.MDS_CHAN_REF_SMOOTH_NAME,
    "collision": mds.MDS_CHAN_COLLIDE_NAME,
}
READY_LINES = {"ik": "waiting for requests"}  # nodes without a periodic output: a line in their log


def system_env(runtime: Path) -> dict[str, str]:
    """Environment for the system and its clients: private runtime and config dirs, the default robot."""
    env = dict(os.environ)
    env["MDS_ACH_RUNTIME_DIR"] = str(runtime)
    env["MDS_ACH_CONFIG_DIR"] = str(runtime / "config")
    env["MDS_ACH_HISTORY"] = str(runtime / "console_history")
    env.pop("MDS_ACH_ROBOT", None)
    return env


def mds_ach(*args: str, env: dict[str, str] | None = None, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run the ``mds-ach`` front-end (``env`` None: this process's environment)."""
    return subprocess.run([str(VENV_BIN / "mds-ach"), *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


def wait_heartbeat(channel: str, alive: Callable[[], bool], log: Callable[[], str], what: str,
                   timeout: float = START_TIMEOUT, frames: int = 2, flushed: ach.Channel | None = None) -> None:
    """Wait for ``frames`` new frames on ``channel`` (new since ``flushed`` was flushed, if given: open and flush
    it before starting the process, or frames already there count); fail as soon as ``alive()`` is False, or
    after ``timeout`` s, with the log."""
    watch = flushed if flushed is not None else _flushed(channel)
    buf = bytearray(watch.data_size)
    seen = 0
    deadline = time.monotonic() + timeout
    try:
        while seen < frames:
            assert alive(), f"{what} exited:\n{log()}"
            status, _ = watch.get(buf, last=True)
            seen += status in (ach.ACH_OK, ach.ACH_MISSED_FRAME)
            assert time.monotonic() < deadline, f"{what} not up after {timeout} s:\n{log()}"
            time.sleep(0.02)
    finally:
        watch.close()


def _flushed(channel: str) -> ach.Channel:
    watch = ach.Channel(channel, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    watch.flush()
    return watch


@contextmanager
def running_system(runtime: Path, robot: str | None = None, extra: Sequence[str] = ()) -> Iterator[dict[str, str]]:
    """``mds-ach start nocan [extra...]`` in a clean /dev/shm (after ``changerobot robot`` if given); yields the
    environment; ``mds-ach stop`` and ``killall`` afterwards."""
    assert in_netns(), "run the tests through tools/netns-run (private /dev/shm and network namespace)"
    remove_mds_channels()
    env = system_env(runtime)
    if robot:
        proc = mds_ach("changerobot", robot, env=env)
        assert proc.returncode == 0, proc.stderr
    proc = mds_ach("start", "nocan", "--timeout", str(START_TIMEOUT), *extra, env=env, timeout=START_TIMEOUT + 60)
    assert proc.returncode == 0, f"mds-ach start nocan failed:\n{proc.stdout}\n{proc.stderr}"
    try:
        yield env
    finally:
        mds_ach("stop", env=env, timeout=60)
        mds_ach("killall", env=env, timeout=60)
        remove_mds_channels()


@contextmanager
def isolated_run(env: dict[str, str], prefix: tuple[str, ...] = (), python: str | None = None,
                 ) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``[prefix] tools/netns-run PYTHON -m mds_ach.tools.cli run --nocan`` in new namespaces (``MDS_NETNS_ACTIVE``
    dropped, so netns-run makes them even inside the tests' own); yields the process and what it printed up to
    "Press Ctrl-C"; SIGINT (as Ctrl-C) afterwards, which must stop it cleanly."""
    env = {k: v for k, v in env.items() if k != "MDS_NETNS_ACTIVE"}
    argv = [*prefix, str(REPO / "tools" / "netns-run"), python or str(VENV_BIN / "python"), "-m", "mds_ach.tools.cli",
            "run", "--nocan", "--timeout", str(START_TIMEOUT)]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    assert proc.stdout is not None
    lines: list[str] = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if "Press Ctrl-C" in line:
                break
        assert proc.poll() is None, "mds-ach run ended:\n" + "".join(lines)
        yield proc, "".join(lines)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            rest, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            rest, _ = proc.communicate()
    assert proc.returncode == 0, "mds-ach run did not stop cleanly:\n" + "".join(lines) + rest


class Pipeline:
    """Node processes started one by one from their console scripts, each logging to ``logs/<name>.log``."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *args: str) -> None:
        """Start ``name`` and wait until it is up (``wait_heartbeat``, or its ready line in the log)."""
        log = open(self.logs / f"{name}.log", "a")  # noqa: SIM115 - closed with the process
        log.write(f"--- start {name} {' '.join(args)}\n")
        log.flush()
        channel = HEARTBEATS.get(name)
        watch = _flushed(channel) if channel else None
        proc = self.procs[name] = subprocess.Popen([str(VENV_BIN / bin_name(name)), *args], stdout=log,
                                                   stderr=subprocess.STDOUT)
        if watch is not None:
            wait_heartbeat(channel, lambda: proc.poll() is None, lambda: self.log_text(name), name, flushed=watch)
            return
        deadline = time.monotonic() + START_TIMEOUT
        while READY_LINES[name] not in self.log_text(name).rsplit("--- start", 1)[-1]:
            assert proc.poll() is None, f"{name} exited:\n{self.log_text(name)}"
            assert time.monotonic() < deadline, f"{name} not up after {START_TIMEOUT} s:\n{self.log_text(name)}"
            time.sleep(0.05)

    def kill(self, name: str, sig: int) -> None:
        """Stop a node with ``sig`` and wait for it to be gone."""
        proc = self.procs.pop(name)
        proc.send_signal(sig)
        proc.wait(20)

    def stop_all(self) -> dict[str, int]:
        """SIGTERM every node, the daemon last; their exit codes (-9: had to be killed)."""
        codes = {}
        for name in [n for n in self.procs if n != "daemon"] + ["daemon"]:
            proc = self.procs.get(name)
            if proc is None:
                continue
            proc.send_signal(signal.SIGTERM)
            try:
                codes[name] = proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = -9
        self.procs.clear()
        return codes

    def assert_clean(self, codes: dict[str, int]) -> None:
        """Every node of ``stop_all()`` exited with 0; else fail with the unclean ones' log tails."""
        bad = {n: c for n, c in codes.items() if c != 0}
        assert not bad, f"unclean exits {bad}:\n" + "\n".join(self.log_text(n)[-3000:] for n in bad)

    def log_text(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""


# ----- the running robot, as a client sees it


def joint_pos(short: str) -> float:
    return float(state().joint[mds.BY_SHORT[short].address].pos)


def joint_ref(short: str) -> float:
    return float(state().joint[mds.BY_SHORT[short].address].ref)


def arm_refs(arm: str) -> list[float]:
    names = mds.joints.LEFT_ARM if arm == "left" else mds.joints.RIGHT_ARM
    return [joint_ref(n) for n in names]


def arm_pos(arm: str) -> list[float]:
    names = mds.joints.LEFT_ARM if arm == "left" else mds.joints.RIGHT_ARM
    return [joint_pos(n) for n in names]
