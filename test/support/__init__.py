"""Shared test support: one place for what more than one test module (or a benchmark) needs.

Tests import it as ``support`` (``test/`` is on ``sys.path``: pytest's ``pythonpath = test`` in setup.cfg;
``bench/__init__.py`` adds it for the benchmarks). Not ``test.support``: that name is the standard library's.
``conftest.py`` keeps only fixtures; helpers live here, so no test module imports ``conftest``.

* this module: paths (``REPO``, ``VENV_BIN``, ``SHARED``), ``wait_for``, ``in_netns``, ``remove_mds_channels``,
  ``run_as``, ``other_ids_missing``, ``realtime_threads`` and ``may_use_sched_fifo`` (standard library only, so
  the benchmarks can use the package without pytest);
* ``support.channels``: the one "newest frame" reader (``newest``, ``state``, ``Newest``);
* ``support.rig``: the one daemon rig (``DaemonRig``: the daemon loop on a simulated clock and bus);
* ``support.system``: the one system start-up (``running_system`` via ``mds-ach start``, ``Pipeline`` for
  node-by-node control) and the readers of the running robot;
* ``support.faults``: writers that die inside a put (``StuckWriter``) and their checkable payloads;
* ``support.motion_audit``, ``support.pty_session``, ``support.netsim`` (simulated hosts: tests and
  bench/bench_network.py), ``support.reference_chain`` (the original IK chain, written out),
  ``support.torch_kinematics`` (the pytorch-kinematics cross-check; the only user of torch).
"""

from __future__ import annotations

import glob
import os
import sys
import time
from collections.abc import Callable, Iterable
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent
NOBODY = 65534  # uid and gid of user nobody / group nogroup


def _shared_dir() -> Path:
    env = os.environ.get("MDS_SHARED_DIR")
    return Path(env) if env else REPO.parent / "shared"


SHARED = _shared_dir()


def remove_mds_channels() -> None:
    """Unlink every MDS and test channel in this (private) /dev/shm."""
    for path in glob.glob("/dev/shm/achshm-mds*") + glob.glob("/dev/shm/achshm-test*"):
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


def wait_for(predicate: Callable[[], object], timeout: float = 10.0, interval: float = 0.01, what: str = "") -> object:
    """Poll ``predicate`` until it returns a truthy value; fail with ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what or predicate}")
        time.sleep(interval)


def in_netns() -> bool:
    """Are we inside tools/netns-run (private network namespace and /dev/shm)?"""
    return os.environ.get("MDS_NETNS_ACTIVE") == "1"


def realtime_threads(pid: int) -> list[tuple[str, int]]:
    """(kernel thread name, priority) of every thread of process ``pid`` that runs SCHED_FIFO or SCHED_RR."""
    out = []
    for tid in sorted(int(t) for t in os.listdir(f"/proc/{pid}/task")):
        try:
            policy = os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK
            if policy in (os.SCHED_FIFO, os.SCHED_RR):
                comm = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
                out.append((comm, os.sched_getparam(tid).sched_priority))
        except (ProcessLookupError, FileNotFoundError):  # the thread ended meanwhile
            pass
    return out


def may_use_sched_fifo() -> bool:
    """May processes started from here run SCHED_FIFO (root, CAP_SYS_NICE, an rtprio limit; not as a normal user in
    tools/netns-run's user namespace)? Probed on a short-lived thread, which then ends."""
    import threading

    allowed: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            allowed.append(True)
        except PermissionError:
            allowed.append(False)

    thread = threading.Thread(target=probe)
    thread.start()
    thread.join()
    return allowed[0]


def _unmapped(table: str, ids: Iterable[int]) -> list[int]:
    """The ids of ``ids`` that /proc/self/{uid,gid}_map leaves unmapped (all mapped outside a user namespace)."""
    try:
        lines = Path(f"/proc/self/{table}_map").read_text().split("\n")
    except OSError:
        return []
    ranges = [(int(inside), int(count)) for inside, _, count in (line.split() for line in lines if line.strip())]
    return [i for i in ids if not any(start <= i < start + count for start, count in ranges)]


def other_ids_missing(uids: Iterable[int] = (NOBODY,), gids: Iterable[int] = (NOBODY,)) -> str | None:
    """Why this process cannot act as ``uids``/``gids`` (setuid, setgid, setgroups), or None when it can.

    As root on the host every id exists. In the user namespace tools/netns-run makes for a normal user, only that
    user (as root) does, unless it maps the user's subordinate id range too (uidmap + /etc/subuid, /etc/subgid)."""
    if os.geteuid() != 0:
        return f"needs root (or root in tools/netns-run's user namespace) to act as another user, not uid " \
               f"{os.geteuid()}"
    unmapped = [f"uid {i}" for i in _unmapped("uid", uids)] + [f"gid {i}" for i in _unmapped("gid", gids)]
    try:
        setgroups = Path("/proc/self/setgroups").read_text().strip()
    except OSError:
        setgroups = "allow"
    if not unmapped and setgroups == "allow":
        return None
    outside = Path("/proc/self/uid_map").read_text().split()[1]
    try:
        import pwd

        who = pwd.getpwuid(int(outside)).pw_name
    except (KeyError, ValueError):
        who = f"uid {outside}"
    what = ", ".join(unmapped) if unmapped else "setgroups (denied)"
    return (f"needs a second uid inside the user namespace ({what} not available to {who}): install uidmap "
            f"(newuidmap/newgidmap) and give {who} a /etc/subuid and /etc/subgid range (as root: usermod "
            f"--add-subuids 100000-165535 --add-subgids 100000-165535 {who}), then run through tools/netns-run")


def run_as(uid: int, gid: int, func: Callable[[], int], groups: tuple[int, ...] = ()) -> int:
    """Run ``func`` in a forked child as another user (we are root in the test namespace); its return value,
    or 1 after printing the traceback, is the exit status returned here. A fork, not a new interpreter:
    the venv's Python lives under /root, which other users cannot execute. Raises when those ids do not exist
    here (``other_ids_missing``: tests skip first with that reason)."""
    import traceback

    missing = other_ids_missing((uid,), (gid, *groups))
    if missing:
        raise RuntimeError(f"run_as({uid}, {gid}): {missing}")
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.setgroups(list(groups))
            os.setgid(gid)
            os.setuid(uid)
            code = int(func())
        except BaseException:
            traceback.print_exc()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)
