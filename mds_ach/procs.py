"""Background processes: pid files, liveness, start detached, stop (SIGTERM, then SIGKILL).

The launcher (nodes), ``mds-ach remote`` (session and servers) and ``mds-ach sim`` (the viewer) all leave
processes running after the command returns and find them again through a pid file in
``paths.runtime_dir()``. Getting that right has sharp corners, handled once here:

* a pid file is trusted only while its pid is alive *and* its command line says it is ours, so a stale file whose
  pid was reused by another program never gets that program killed;
* "alive" excludes zombies (``Z``) and dead tasks (``X``): an exited child nobody reaped yet still has a
  ``/proc`` entry, and a stop that waited for the entry to vanish would wait for nothing, then SIGKILL a corpse;
* a process may exit between any check and the ``kill``: ``ProcessLookupError`` means "already stopped".

Imports: the standard library only (a leaf module usable from every layer).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO

POLL_S = 0.02  # how often a stop looks whether the process is gone


def proc_argv(pid: int) -> list[str]:
    """The command line of ``pid`` (empty if it is gone or unreadable)."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return []
    return [a.decode("utf-8", "replace") for a in raw.split(b"\0") if a]


def _read_stat(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None


def alive(pid: int) -> bool:
    """True while ``pid`` exists and is neither a zombie (exited, not reaped) nor dead (``X``)."""
    stat = _read_stat(pid)
    if stat is None:
        return False
    # "pid (comm) S ...": comm may itself contain ") ", so the state follows the *last* parenthesis
    return stat[stat.rfind(")") + 2:][:1] not in ("Z", "X")


def read_pid_file(path: Path) -> int | None:
    """The positive pid written in ``path`` (first word), or None when missing or garbled."""
    try:
        pid = int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return pid if pid > 0 else None


def write_pid_file(path: Path, pid: int) -> None:
    """Write ``pid`` atomically, so a concurrent reader never sees a half-written number."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(f"{pid}\n")
    os.replace(tmp, path)


def remove_pid_file(path: Path) -> None:
    path.unlink(missing_ok=True)


def running_pid(path: Path, is_ours: Callable[[list[str]], bool]) -> int | None:
    """The pid in ``path`` if that process is alive and ``is_ours(its argv)``, else None."""
    pid = read_pid_file(path)
    if pid is None or not alive(pid):
        return None
    return pid if is_ours(proc_argv(pid)) else None


def signal_pid(pid: int, sig: int) -> bool:
    """Send ``sig``; False when the process was already gone (not an error: it may exit any moment)."""
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        return False
    return True


def wait_gone(pids: Sequence[int], timeout: float, reap: Callable[[], object] | None = None) -> list[int]:
    """Wait up to ``timeout`` s until none of ``pids`` is alive; returns those still alive. ``reap`` is called
    each round (e.g. ``Popen.poll`` of our own children, so they do not stay zombies)."""
    deadline = time.monotonic() + timeout
    while True:
        if reap is not None:
            reap()
        left = [p for p in pids if alive(p)]
        if not left or time.monotonic() >= deadline:
            return left
        time.sleep(POLL_S)


def stop_pid(pid: int, grace: float = 5.0, sig: int = signal.SIGTERM,
             reap: Callable[[], object] | None = None) -> bool:
    """``sig``, then SIGKILL if it is still alive after ``grace`` s. True if SIGKILL was needed."""
    if not signal_pid(pid, sig):
        return False
    if not wait_gone([pid], grace, reap):
        return False
    signal_pid(pid, signal.SIGKILL)
    wait_gone([pid], 2.0, reap)
    return True


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def _parent_death_signal(sig: int) -> Callable[[], None]:
    """A ``preexec_fn`` that has the kernel send ``sig`` to the child when the process that started it dies (even
    by SIGKILL), and ends the child at once if that already happened between fork and exec. ``prctl`` is looked up
    here, in the parent: the child only calls it."""
    prctl = ctypes.CDLL(None, use_errno=True).prctl
    parent = os.getpid()

    def arm() -> None:
        prctl(PR_SET_PDEATHSIG, ctypes.c_ulong(sig), 0, 0, 0)
        if os.getppid() != parent:
            os._exit(1)

    return arm


LOG_ROTATE_BYTES = 8 * 1024 * 1024
"""A log larger than this at a start is moved to ``<log>.1`` (the one before is dropped): logs are appended across
restarts, so they are bounded here."""

START_MARKER = "===== start"
"""Opens the line a start appends to the log (``===== start <UTC time> pid <pid>: <command> =====``): where one
run's lines end and the next one's begin."""


def _open_log(log_path: Path, append: bool) -> BinaryIO:
    """The log opened for a new run: appended to (the previous run's lines, e.g. a crash's traceback, stay; the
    documented recovery ``start --only NODE`` must not erase them), rotated to ``.1`` first when it grew too large;
    truncated with ``append=False``."""
    if append:
        try:
            if log_path.stat().st_size > LOG_ROTATE_BYTES:
                os.replace(log_path, log_path.with_name(log_path.name + ".1"))
        except FileNotFoundError:
            pass
    return open(log_path, "ab" if append else "wb")


def _write_marker(argv: Sequence[str], then: Callable[[], None] | None) -> Callable[[], None]:
    """A ``preexec_fn`` writing the start marker with the child's own pid to its stdout (the log: the child's
    descriptors are set up before preexec_fn runs), before the program can write anything; then ``then``."""
    stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    command = " ".join(argv)[:200]

    def mark() -> None:
        os.write(1, f"{START_MARKER} {stamp} pid {os.getpid()}: {command} =====\n".encode(errors="replace"))
        if then is not None:
            then()

    return mark


def spawn_detached(argv: Sequence[str], log_path: Path, env: dict[str, str] | None = None,
                   append: bool = True, die_with_parent: bool = False) -> subprocess.Popen[bytes]:
    """Start ``argv`` in its own session (a terminal's Ctrl-C does not reach it), stdout and stderr to the log
    (appended after a start marker line, see :func:`_open_log`; a fresh log with ``append=False``).
    ``die_with_parent``: the child gets SIGTERM when this process dies, however it dies (a foreground supervisor
    killed by SIGKILL leaves no orphan); otherwise it outlives it (a background service)."""
    preexec = _parent_death_signal(signal.SIGTERM) if die_with_parent else None
    with _open_log(log_path, append) as log:
        return subprocess.Popen(list(argv), stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True, env=env, preexec_fn=_write_marker(argv, preexec))


def log_tail(path: Path, lines: int) -> list[str]:
    """The last ``lines`` lines of the newest run in a log (after its last start marker; at most the log's last
    64 KiB are read); empty if there is none or that run wrote nothing."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 64 * 1024))
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return []
    run = text.splitlines()
    starts = [i for i, line in enumerate(run) if line.startswith(START_MARKER)]
    if starts:
        run = run[starts[-1] + 1:]
    return run[-lines:]
