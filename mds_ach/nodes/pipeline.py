"""Plumbing shared by the reference-pipeline nodes (mux, filter, collision gate).

* ``MDS_REF`` frames <-> numpy arrays (100 refs + 100 modes, indexed by CAN address), so the nodes do their
  per-joint work vectorised;
* joint selections from config (``'all'``, group names, fnmatch patterns such as ``'L*'``, addresses);
* the *current reference* at start-up, so a node started late (or restarted) continues from what the daemon
  is already commanding instead of jumping;
* ``ChannelGuard`` (defined in ``mds_ach.robot.channels``), ``ReseedWatch``, ``Wakeup``, ``Periodic``: a broken
  channel, a re-seed request, a loop woken by any of its inputs, an absolute schedule.

No rclpy here: the helpers are used by tests and tools that never start ROS (the ROS side of the nodes is
``mds_ach.nodes.rosnode``).
"""

from __future__ import annotations

import fnmatch
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.glibc import tune_thread
from mds_ach.robot import contracts
from mds_ach.robot.channels import ChannelGuard, StructChannel
from mds_ach.robot.joints import BY_ADDRESS, BY_SHORT, JOINTS, LEFT_ARM, MODEL_JOINTS, NECK, RIGHT_ARM, TORSO, lookup

REF_DTYPE = np.dtype([("ref", "<f8"), ("mode", "<i2")])  # packed, itemsize 10 == sizeof(MDS_JOINT_REF)
KNOWN_ADDRESSES: tuple[int, ...] = tuple(j.address for j in JOINTS)
JOINT_GROUPS: dict[str, tuple[str, ...]] = {
    "left_arm": LEFT_ARM,
    "right_arm": RIGHT_ARM,
    "arms": LEFT_ARM + RIGHT_ARM,
    "neck": NECK,
    "head": NECK,
    "torso": TORSO,
    "model": MODEL_JOINTS,
    "all": tuple(j.short for j in JOINTS),
}


# --------------------------------------------------------------------------------------------- ref arrays


def ref_arrays(frame: mds.MDS_REF) -> tuple[np.ndarray, np.ndarray]:
    """(ref, mode) arrays of length 100 (copies) from an ``MDS_REF``."""
    a = np.frombuffer(bytes(frame), dtype=REF_DTYPE)
    return a["ref"].astype(float), a["mode"].astype(np.int16)


def make_ref(ref: np.ndarray, mode: np.ndarray) -> mds.MDS_REF:
    """An ``MDS_REF`` from ref/mode arrays of length 100."""
    a = np.empty(mds.MDS_JOINT_COUNT, dtype=REF_DTYPE)
    a["ref"] = ref
    a["mode"] = mode
    return mds.MDS_REF.from_buffer_copy(a.tobytes())


def state_refs(state: mds.MDS_STATE) -> np.ndarray:
    """``state.joint[i].ref`` for all 100 addresses: what the daemon is commanding now."""
    return np.array([state.joint[i].ref for i in range(mds.MDS_JOINT_COUNT)], dtype=float)


def state_positions(state: mds.MDS_STATE) -> np.ndarray:
    """``state.joint[i].pos`` (measured, rad) for all 100 addresses."""
    return np.array([state.joint[i].pos for i in range(mds.MDS_JOINT_COUNT)], dtype=float)


def joint_label(address: int) -> str:
    j = BY_ADDRESS.get(int(address))
    return j.short if j else f"0x{int(address):02X}"


def labels(addresses: Iterable[int]) -> str:
    return ", ".join(joint_label(a) for a in addresses)


# --------------------------------------------------------------------------------------------- joint selections


def select_joints(spec: Any, where: str = "joints") -> tuple[int, ...]:
    """Addresses (sorted) selected by ``spec``: ``'all'``, a group (left_arm, right_arm, arms, neck, torso, model),
    a short/long name or address, an fnmatch pattern on short names (``'L*'``, ``'?SP'``), or a list of those.

    A pattern or name that selects nothing is an error (a typo must not silently drop permissions).
    """
    items = [spec] if isinstance(spec, str | int) else list(spec or [])
    if not items:
        raise ValueError(f"{where}: empty joint selection")
    out: set[int] = set()
    for item in items:
        if isinstance(item, int) and not isinstance(item, bool):
            if item not in BY_ADDRESS:
                raise ValueError(f"{where}: no joint at address {item:#x}")
            out.add(item)
            continue
        text = str(item).strip()
        if text.lower() in JOINT_GROUPS:
            out.update(BY_SHORT[s].address for s in JOINT_GROUPS[text.lower()])
            continue
        if any(ch in text for ch in "*?["):
            hits = [j.address for j in JOINTS if fnmatch.fnmatchcase(j.short, text.upper())]
            if not hits:
                raise ValueError(f"{where}: pattern {text!r} matches no joint short name")
            out.update(hits)
            continue
        try:
            out.add(lookup(text).address)
        except KeyError as exc:
            groups = ", ".join(JOINT_GROUPS)
            raise ValueError(f"{where}: {exc.args[0]}; or use a group ({groups}) or a pattern such as 'L*'") from None
    return tuple(sorted(out))


# --------------------------------------------------------------------------------------------- current reference


def current_reference(sources: Sequence[str] = (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_STATE_NAME)
                      ) -> tuple[np.ndarray, np.ndarray, str] | None:
    """(ref, mode, source) from the newest frame on the first source channel that has one, else None.

    ``mds-ref-gated`` (what the daemon executes; not ``mds-ref``, a controller input since the daemon's input was
    renamed) gives ref and mode; ``mds-state`` gives ``joint[].ref`` (mode 0); any other channel carries an
    ``MDS_REF`` (the contracts registry says which struct; unregistered names are read as ``MDS_REF``). Channels
    are created if missing, so nodes can start in any order.
    """
    for name in sources:
        found = contracts.lookup(name)
        ch = StructChannel(name, found.struct if found is not None else mds.MDS_REF)
        try:
            frame = ch.latest()
        finally:
            ch.close()
        if frame is None:
            continue
        if isinstance(frame, mds.MDS_STATE):
            ref = state_refs(frame)
            if not np.all(np.isfinite(ref)):
                continue
            return ref, np.zeros(mds.MDS_JOINT_COUNT, dtype=np.int16), name
        ref, mode = ref_arrays(frame)
        if np.all(np.isfinite(ref)):
            return ref, mode, name
    return None


def wait_current_reference(stop: threading.Event, log: Callable[[str], None],
                           sources: Sequence[str] = (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_STATE_NAME),
                           poll: float = 0.1) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Poll ``current_reference`` until one exists (None if ``stop`` is set first); logs once while waiting.

    Why wait instead of starting at zero: an all-zero reference would send every joint to its homed zero.
    """
    said = False
    while not stop.is_set():
        found = current_reference(sources)
        if found is not None:
            return found
        if not said:
            log(f"waiting for a current reference on {' or '.join(sources)} (is the daemon running?)")
            said = True
        stop.wait(poll)
    return None


class ReseedWatch:
    """Which joints the daemon asks the pipeline to restart where they are, and where that is.

    After HOME, RESET, ZERO_ENCODER, ENABLE or ``resetbus`` a joint is somewhere else than the pipeline's
    reference for it (HOME moved it, a reset restarted its count, the bus was down while the reference moved).
    Once its position is known the daemon increments ``joint_reseed[address]`` in ``mds-daemon-status``; the mux,
    the filter and the collision gate ``poll()`` this and set their output for those joints to the measured
    position (``mds-state`` pos), so the next command starts from the joint instead of from a stale reference.
    A daemon seen for the first time (or restarted) only sets the baseline. A broken channel reads as nothing
    new (``ChannelGuard`` says so in the node's log).
    """

    def __init__(self, log: Callable[[str, str], None], stop: threading.Event) -> None:
        self._guard = ChannelGuard(log, stop, pause=0.0)  # latest() never blocks: nothing to pace
        self._status = StructChannel.of(mds.MDS_CHAN_DAEMON_STATUS_NAME)
        self._state = StructChannel.of(mds.MDS_CHAN_STATE_NAME)
        self._last_state: mds.MDS_STATE | None = None
        self._seen: np.ndarray | None = None
        self._daemon: tuple[int, float] | None = None

    def poll(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(addresses, measured positions) to re-seed now, or None. Never blocks."""
        st = self._guard.call(self._status.name, self._status.latest)
        if st is None:
            return None
        counts = np.frombuffer(bytes(st.joint_reseed), dtype="<u4").copy()
        daemon = (st.pid, st.start_time)
        if self._seen is None or daemon != self._daemon:
            self._seen, self._daemon = counts, daemon
            return None
        changed = np.flatnonzero(counts != self._seen)
        self._seen = counts
        if not changed.size:
            return None
        state = self._guard.call(self._state.name, self._state.latest) or self._last_state  # published first
        self._last_state = state
        if state is None:
            return None
        pos = state_positions(state)[changed]
        ok = np.isfinite(pos)
        return (changed[ok], pos[ok]) if ok.any() else None

    def close(self) -> None:
        self._status.close()
        self._state.close()


def cancel_wait(channel: Any) -> None:
    """Wake a thread blocked in ``channel.wait()``; a channel that is already closed needs no waking."""
    try:
        channel.cancel()
    except ach.AchException as exc:
        if exc.status != ach.ACH_CLOSED:
            raise


HANDOFF_RT_PRIORITY = 40
"""SCHED_FIFO priority the nodes ask for their hand-off threads (the mux's readers and loop, the filter's loop, the
gate's loop and its ``Wakeup`` readers): below the daemon loop's 50, above every normal process. Each sleeps until a
frame arrives and does bounded work per frame. Why: at normal priority a command crossed the three nodes in 1-2 ms
median but up to 30-50 ms p99 on a loaded 2-core machine (each hop waits for a CPU behind busy processes); at this
priority 2-3 ms p99 beside the same load (#26 item 5, docs/reliability.md E)."""


def handoff_thread(rt_priority: int, name: str, log: Callable[[str, str], None] | None = None) -> bool:
    """Put the calling hand-off thread at SCHED_FIFO ``rt_priority`` (0: normal scheduling) and name it. Refused
    (no privilege): it runs at normal priority and, given ``log``, says so once. True if real-time."""
    problems = [p for p in tune_thread(rt_priority, name=name) if "SCHED_FIFO" in p]
    if problems and log is not None:
        log("warn", f"{problems[0]}: a command may wait for a CPU on a busy machine (docs/reliability.md E)")
    return rt_priority > 0 and not problems


class Wakeup:
    """Wakes one loop on a new frame on any of several channels, so a node with two inputs sleeps until either
    moves instead of polling one of them. A thread per channel blocks on a handle of its own and sets an event; the
    loop waits on the event (``wait``) and then reads its channels itself (``latest``): a frame that arrives while
    the loop works leaves the event set, so no wake-up is lost. ``news`` (per channel name, optional) tells a
    reader which frames are worth a wake-up (called on that reader's thread): e.g. not the same pose again."""

    READER_TIMEOUT = 5.0
    """s: how long a reader sleeps between looks at ``stop`` when nothing arrives (``close`` cancels the wait)."""

    def __init__(self, names: Sequence[str], ctypes: Sequence[type], log: Callable[[str, str], None],
                 rt_priority: int = 0, news: Mapping[str, Callable[[Any], bool]] | None = None) -> None:
        self._rt_priority = rt_priority
        self._news = dict(news or {})
        self._event = threading.Event()
        self._stop = threading.Event()
        self._guard = ChannelGuard(log, self._stop)
        self._channels: list[StructChannel[Any]] = [StructChannel(n, t) for n, t in zip(names, ctypes, strict=True)]
        self._threads = [threading.Thread(target=self._watch, args=(ch,), name=f"wake {ch.name}", daemon=True)
                         for ch in self._channels]
        for t in self._threads:
            t.start()

    def _watch(self, ch: StructChannel[Any]) -> None:
        handoff_thread(self._rt_priority, f"wake {ch.name}")
        news = self._news.get(ch.name, lambda frame: True)
        while not self._stop.is_set():
            if (frame := self._guard.call(ch.name, ch.wait, timeout=self.READER_TIMEOUT)) is not None:
                if news(frame):
                    self._event.set()
            elif self._guard.failing(ch.name):  # a broken channel answers at once: look again later
                self._stop.wait(0.5)

    def wait(self, timeout: float) -> bool:
        """Sleep until a frame arrived on one of the channels since the previous call, at most ``timeout`` s."""
        woken = self._event.wait(max(0.0, timeout))
        self._event.clear()
        return woken

    def cancel(self) -> None:
        """Wake the loop and end the readers (from any thread, e.g. a node's ``stop()``); the loop then finds its
        own stop flag."""
        self._stop.set()
        self._event.set()
        for ch in self._channels:
            cancel_wait(ch)

    def close(self) -> None:
        """``cancel`` and release the channels (by the loop that owns this, when it ends)."""
        self.cancel()
        for t in self._threads:
            t.join(timeout=2.0)
        for ch in self._channels:
            ch.close()


# --------------------------------------------------------------------------------------------- timing


class Periodic:
    """Absolute-time schedule on CLOCK_MONOTONIC: ``wait()`` sleeps until the next tick; overruns re-sync
    (and are counted) instead of bursting to catch up."""

    def __init__(self, period: float) -> None:
        if not period > 0:
            raise ValueError("period must be > 0")
        self.period = period
        self.next = time.monotonic() + period
        self.overruns = 0

    def wait(self, stop: threading.Event) -> bool:
        """Sleep until the next tick; False if ``stop`` was set meanwhile."""
        delay = self.next - time.monotonic()
        if delay > 0:
            if stop.wait(delay):
                return False
        self.next += self.period
        now = time.monotonic()
        if now > self.next:
            self.overruns += 1
            self.next = now + self.period
        return not stop.is_set()
