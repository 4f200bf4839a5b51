"""Which channel files the stack trusts, and the mode each MDS channel gets (who may write it).

Why: ``/dev/shm`` is world-writable (mode 1777). Any local user can create ``/dev/shm/achshm-mds-ref`` before
the stack starts, mode 0666, and a stack that merely opens "an existing channel of the right size" would then
execute references that user writes, obey its ``mds-cmd`` commands, and die when it truncates ``mds-state``.
So the stack (``mds-ach make``/``start``, the daemon and the pipeline nodes) accepts a channel file only when

* it is a regular file owned by the stack's user (the user running the stack: ``os.geteuid()``) or root.
  Only the owner can change a file's mode or group, and the sticky bit of ``/dev/shm`` stops everybody else
  from removing or replacing it;
* its permission bits give nobody more than the channel's mode: ``CHANNEL_MODE`` (0660: the stack's user and
  the channels' group, i.e. the operators, read and write) except ``STACK_ONLY`` channels, the daemon's input,
  which get 0640: only the stack's user writes what the daemon executes. Ach readers open a channel read-write
  (they take its mutex), so group members cannot open a 0640 channel at all;
* when a group is configured (``mds-ach make --group``), it belongs to that group.

A refused file is re-created by ``mds-ach repair --recreate NAME`` (as root when another user owns it: the
sticky bit keeps the stack's user from removing it). One the stack's own user made too open (the original's
``ach mk`` gives 0644, its ``mds-ach make`` ran ``chmod 777``) is tightened in place instead (:func:`tighten`,
at ``mds-ach make``/``start``), but only while no other process has it open: a handle opened while the file was
open to everybody keeps its write access after a chmod.

Operator clients (console, read, hold, examples, the legacy API) run as other users, so they cannot demand the
stack's rules of ownership and mode; but they must not read or write a file a third user planted either (it
would show them that user's data and take their commands). Every channel open -- client or node -- therefore
refuses a symbolic link (``O_NOFOLLOW``) and anything but a regular file (``mds_ach.ach.files``), and a client
refuses a file owned by anyone but root, itself or the stack's user (:func:`client_problem`, installed in the
``ach`` layer when ``mds_ach`` is imported). The stack's user, as a client sees it, is the owner of the daemon's
input ``mds-ref-gated`` when that is a regular file with the daemon input's mode (0640 or narrower): only the
stack creates it, and the stack refuses to start on one another user planted.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat

from mds_ach import ach
from mds_ach.paths import user_label
from mds_ach.robot import contracts

CHANNEL_MODE = 0o660
"""Owner and group read-write: the stack's user runs the nodes, the channels' group the operator clients."""
DAEMON_INPUT = contracts.MDS_CHAN_DAEMON_INPUT_NAME
STACK_ONLY: frozenset[str] = contracts.STACK_ONLY
"""Channels only the stack's own processes may write (``Contract.stack_only``): group write is removed from
their mode."""

_enforced = False


class UntrustedChannelError(ValueError):
    """A channel file the stack must not use (wrong owner, mode or group); the message says how to fix it."""


def recreate_hint(name: str) -> str:
    return (f"re-create it: mds-ach repair --recreate {name} (as root if another user owns the file: "
            "/dev/shm's sticky bit keeps you from removing it)")


def channel_mode(name: str, mode: int = CHANNEL_MODE) -> int:
    """The mode channel ``name`` is created with when ``mode`` is configured: no group/other write on
    ``STACK_ONLY`` channels (0660 -> 0640)."""
    return mode & ~0o022 if name in STACK_ONLY else mode


def check_configured_mode(mode: int) -> None:
    """Refuse a configured mode that gives more than ``CHANNEL_MODE`` (it may only restrict it, e.g. 0600)."""
    extra = mode & ~CHANNEL_MODE
    if extra:
        what = "world-writable" if extra & 0o002 else "beyond owner and group read-write"
        raise ValueError(f"mode {mode:04o} is {what} (bits {extra:04o}); Ach channels get at most "
                         f"{CHANNEL_MODE:04o}: give operators access with a group (--group) instead")


def trusted_owners() -> set[int]:
    """The stack's user (whoever runs this process) and root."""
    return {os.geteuid(), 0}


def problem(name: str, st: os.stat_result, mode: int = CHANNEL_MODE, gid: int | None = None) -> str | None:
    """Why the stack must not use channel ``name`` whose file has status ``st``, or None when it may.

    ``mode`` is the configured channel mode (``channel_mode`` narrows it for ``STACK_ONLY`` channels), ``gid``
    the configured group (None: any group of the owner's choosing).
    """
    if not stat.S_ISREG(st.st_mode):
        return f"{ach.shm_path(name)} is not a regular file"
    owners = trusted_owners()
    if st.st_uid not in owners:
        me = user_label(os.geteuid())
        return (f"{ach.shm_path(name)} is owned by {user_label(st.st_uid)}, not by the stack's user ({me}) or root: "
                "another user created it and can write or truncate it")
    allowed = channel_mode(name, mode)
    extra = st.st_mode & 0o777 & ~allowed
    if extra:
        return (f"{ach.shm_path(name)} has mode {st.st_mode & 0o777:04o}, which allows more than {allowed:04o} "
                f"(extra bits {extra:04o})" + (": only the stack may write the daemon's input" if
                                             name in STACK_ONLY and extra & 0o020 else ""))
    if gid is not None and st.st_gid != gid:
        return f"{ach.shm_path(name)} belongs to group {st.st_gid}, not to the configured group {gid}"
    return None


def _open_elsewhere(path: str) -> bool:
    """Does any other open file description (any process, any user) have the file at ``path`` open for writing
    or mapped? Every Ach handle opens and maps its channel read-write, so this is "does anybody use it now".

    A write lease is granted only when no other file description writes the file (``fcntl(2)``,
    ``F_SETLEASE``); only the file's owner may ask for one, which the stack's user is here."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        fcntl.fcntl(fd, fcntl.F_SETLEASE, fcntl.F_WRLCK)
        fcntl.fcntl(fd, fcntl.F_SETLEASE, fcntl.F_UNLCK)
        return False
    except OSError as exc:
        if exc.errno in (errno.EAGAIN, errno.EBUSY):
            return True
        raise
    finally:
        os.close(fd)


def tighten(name: str, mode: int = CHANNEL_MODE) -> str | None:
    """Give channel ``name`` -- a regular file of the stack's own user that allows more than the configured
    mode -- that mode, in place. Returns what changed (``"mode 0644 -> 0660"``), or None when the file is not
    such a file (``problem`` then says whether and why it is refused).

    Raises ``UntrustedChannelError`` when another process has it open (it may have opened it while the file was
    open to others, and keeps that access after a chmod); nothing is changed then. The check is repeated after
    the chmod, for an ``open()`` that passed its permission check just before it."""
    path = ach.shm_path(name)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return None
    allowed = channel_mode(name, mode)
    if not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid() or st.st_mode & 0o777 & ~allowed == 0:
        return None
    busy = (f"refusing channel '{name}': {path} has mode {st.st_mode & 0o777:04o} and is open in another "
            "process, which may have opened it while it was open to others; stop the processes using it and run "
            f"this again, or {recreate_hint(name)}")
    if _open_elsewhere(path):
        raise UntrustedChannelError(busy)
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    try:
        now = os.fstat(fd)
        if (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
            return None  # replaced meanwhile: the caller's check judges the new file
        os.fchmod(fd, allowed)
    finally:
        os.close(fd)
    if _open_elsewhere(path):
        raise UntrustedChannelError(busy)
    return f"mode {st.st_mode & 0o777:04o} -> {allowed:04o}"


def stack_owner() -> int | None:
    """The stack's user as a client sees it: the owner of the daemon's input (module docstring), or None when
    there is no such file (no stack made its channels here)."""
    try:
        st = os.lstat(ach.shm_path(DAEMON_INPUT))
    except OSError:
        return None
    if not stat.S_ISREG(st.st_mode) or st.st_mode & 0o777 & ~channel_mode(DAEMON_INPUT):
        return None
    return st.st_uid


def client_problem(name: str, path: str, st: os.stat_result) -> str | None:
    """Why a client must not use channel ``name`` (file status ``st``), or None: it must be owned by root, this
    user or the stack's user (:func:`stack_owner`). The rule every channel open applies (``ach.set_open_check``);
    a node of the stack (:func:`enforce_in_this_process`) applies the stricter :func:`require_trusted` instead."""
    if _enforced or st.st_uid in trusted_owners():
        return None
    stack = stack_owner()
    if st.st_uid == stack:
        return None
    who = f"the stack's user ({user_label(stack)}, owner of {DAEMON_INPUT})" if stack is not None else \
        f"the stack's user (unknown: no {DAEMON_INPUT})"
    return (f"refused: {path} is owned by {user_label(st.st_uid)}, neither you ({user_label(os.geteuid())}), "
            f"root nor {who}: another user created it and would see what you write and choose what you read; "
            f"{recreate_hint(name)}")


def install_client_rule() -> None:
    """Make every channel this process opens pass :func:`client_problem` (called once by ``mds_ach``)."""
    ach.set_open_check(client_problem)


def path_problem(name: str, mode: int = CHANNEL_MODE, gid: int | None = None) -> str | None:
    """``problem`` for the file at the channel's path (not following a symlink); None if it does not exist."""
    try:
        st = os.lstat(ach.shm_path(name))
    except FileNotFoundError:
        return None
    return problem(name, st, mode, gid)


def require_trusted(chan: ach.Channel) -> None:
    """Raise ``UntrustedChannelError`` unless the file behind the open handle ``chan`` is one the stack may use.

    Checks the open file (fstat), and that the path still names that same file (not a symlink to it)."""
    st = os.fstat(chan.fileno())
    why = problem(chan.name, st)
    if why is None:
        try:
            at_path = os.lstat(ach.shm_path(chan.name))
        except FileNotFoundError:
            at_path = None
        if at_path is None or (at_path.st_dev, at_path.st_ino) != (st.st_dev, st.st_ino):
            why = f"{ach.shm_path(chan.name)} was replaced or removed while it was being opened"
    if why is not None:
        raise UntrustedChannelError(f"refusing channel '{chan.name}': {why}; {recreate_hint(chan.name)}")


def enforce_in_this_process() -> None:
    """Declare this process part of the stack: from now on ``StructChannel`` refuses untrusted channel files.

    Called once at start by every node's ``main`` (``mds_ach.nodes.rosnode.run_node`` for all six, and
    ``daemon --no-ros``); clients never call it."""
    global _enforced
    _enforced = True


def enforced() -> bool:
    return _enforced
