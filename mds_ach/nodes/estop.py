"""The category-1 e-stop: brake every joint at the motion bounds, then DISABLE the drives; latched until reset.

IEC 60204-1 stop category 1: a controlled stop with power available to the drives, then power removed. Here:

1. ``MDS_CMD_ESTOP`` (``mds-ach estop``, the console, the ROS command service, an e-stop input :class:`EStopInput`)
   latches the e-stop (``ESTOP_STOPPING``) and persists it (:class:`Latch`);
2. every cycle each enabled joint whose position the daemon knows gets the hardest braking step the acceleration
   bound allows from its current velocity (``motion.Track``: the very tracks and bounds of every target, so the
   stop is audited like any motion) until its target stands still; then the daemon waits for the measured
   positions to settle (at most ``SETTLE_TIMEOUT``);
3. the daemon sends DISABLE to every drive of the joint table (``ESTOP_STOPPED``). Protocol evidence for DISABLE:
   command 0x1A in the MCB opcode table (/work/shared/specs/mds-original.md section b.3) and in Xitome's log-parser
   table (``CommandHex.txt``: ``1a Disable``); the original daemon never sent it (section b.4: "no ENABLE/DISABLE"),
   so no capture shows a node's reaction: that DISABLE removes motor power (PWM off) is an inference from its name,
   and the simulated bus models it as "a disabled node does not move" (``simbus``). ENABLE_WDT/DISABLE_WDT (0x27,
   0x28) concern a watchdog, RESET (0x1F) restarts the node's count (the joint would be unreferenced): neither is a
   power-off;
4. while latched nothing moves: no target goes out whatever arrives on ``mds-ref-gated`` (a reference, a trajectory,
   a legacy put), and ENABLE, HOME, RESET and ZERO_ENCODER are refused;
5. ``MDS_CMD_ESTOP_RESET`` (``mds-ach estop reset``) clears the latch once the drives are disabled; the joints stay
   disabled until ENABLE, which restarts each joint where it stands (the re-seed rule) and asks the pipeline to
   restart its references there.

Latched across restarts: :class:`Latch` is a file in the runtime directory (``$MDS_ACH_RUNTIME_DIR``), written before
the stop begins. A file, not an Ach channel: ``mds-ach killall`` removes every channel and ``repair`` re-creates
them, and neither must clear an e-stop; the runtime directory outlives every node and is only cleared by a reboot,
which power-cycles the drives too. A daemon that starts and finds the latch sends DISABLE to every drive at once (its
predecessor may have died mid-stop; it does not know the tracks that stop would brake from) and reports
``ESTOP_STOPPED``.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from mds_ach.paths import runtime_dir
from mds_ach.robot.msgs import daemon_status as ds

log = logging.getLogger("mds_ach.nodes.daemon")

LATCH_NAME = "estop.latched"
SETTLE_TIMEOUT = 1.0  # s after the targets stand still: DISABLE even if a joint still reports motion
REST_SPEED = 0.05  # rad/s: a joint's measured speed below this is at rest
BRAKE_TIMEOUT = 2.0  # s: DISABLE even if a joint's targets have not come to rest by then (a stalled loop)


def default_latch_path() -> Path:
    return runtime_dir() / LATCH_NAME


class Latch:
    """The persisted e-stop: present means latched. ``path`` None keeps it in memory (tests, embedded loops)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._latched = path is not None and path.exists()

    @property
    def latched(self) -> bool:
        return self._latched

    def set(self, reason: str) -> None:
        """Latch, on disk first (atomically: written aside, then renamed)."""
        self._latched = True
        if self.path is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(self.path.name + ".tmp")
            tmp.write_text(f"{time.time():.3f} {reason}\n")
            os.replace(tmp, self.path)
        except OSError as exc:  # the stop goes on regardless; only a restart would forget it
            log.error("e-stop: cannot persist the latch at %s: %s (a restarted daemon would not know)", self.path,
                      exc)

    def clear(self) -> None:
        self._latched = False
        if self.path is not None:
            try:
                self.path.unlink(missing_ok=True)
            except OSError as exc:
                log.error("e-stop: cannot remove the latch %s: %s", self.path, exc)


class EStopState:
    """What the loop needs between cycles: the state, since when, and the stop's progress."""

    def __init__(self, latch: Latch) -> None:
        self.latch = latch
        self.state = ds.ESTOP_STOPPED if latch.latched else ds.ESTOP_OFF
        self.since = -float("inf")  # loop clock: when this daemon latched it (or found it latched)
        self.at_rest_since: float | None = None  # when every braked target stood still
        self.pending_disable: set[int] = set()  # addresses still to be sent DISABLE
        self.found_at_start = latch.latched

    @property
    def active(self) -> bool:
        return self.state != ds.ESTOP_OFF

    def trigger(self, now: float, reason: str) -> bool:
        """Latch (persisted) and start stopping; False if it already was."""
        if self.active:
            return False
        self.latch.set(reason)
        self.state, self.since, self.at_rest_since = ds.ESTOP_STOPPING, now, None
        return True


class EStopInput(Protocol):
    """A source of e-stop presses (a button wired to a serial line, a GPIO exported as a file, a USB device...).

    ``wait(timeout)`` returns True when the e-stop was pressed (or the input failed: fail-safe), False when nothing
    happened within ``timeout``; ``close`` releases the input."""

    name: str

    def wait(self, timeout: float) -> bool: ...

    def close(self) -> None: ...


class SimulatedInput:
    """An e-stop button for tests and demos: ``press()``."""

    name = "simulated"

    def __init__(self) -> None:
        self._pressed = threading.Event()

    def press(self) -> None:
        self._pressed.set()

    def wait(self, timeout: float) -> bool:
        if self._pressed.wait(timeout):
            self._pressed.clear()
            return True
        return False

    def close(self) -> None:
        self._pressed.set()


class LineInput:
    """A line-based input: a FIFO, a serial line (``/dev/ttyUSB0``: set its speed with ``stty``), a pipe: each line
    ``1``, ``estop``, ``stop`` or ``press`` (any case) is a press; other lines are ignored. Opened read-write, so a
    FIFO without a writer blocks instead of reporting an end; an end or a read error is a press (fail-safe: a broken
    input must not leave the robot without its e-stop unnoticed)."""

    PRESS = frozenset({"1", "estop", "stop", "press"})

    def __init__(self, path: str | Path) -> None:
        self.name = str(path)
        self._fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        self._buf = b""
        self._failed = False

    def wait(self, timeout: float) -> bool:
        import select

        if self._failed:
            return False  # reported once; the e-stop stays latched until reset anyway
        deadline = time.monotonic() + timeout
        while True:
            lines = self._buf.split(b"\n")
            self._buf = lines.pop()
            if any(line.strip().decode(errors="replace").lower() in self.PRESS for line in lines):
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            try:
                ready, _, _ = select.select([self._fd], [], [], remaining)
                if not ready:
                    return False
                chunk = os.read(self._fd, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:
                log.error("e-stop input %s failed: %s: e-stop", self.name, exc)
                self._failed = True
                return True
            if not chunk:
                log.error("e-stop input %s ended: e-stop", self.name)
                self._failed = True
                return True
            self._buf += chunk

    def close(self) -> None:
        try:
            os.close(self._fd)
        except OSError:
            pass


class InputWatcher:
    """Reads an :class:`EStopInput` on its own thread and calls ``trigger`` on each press (``DaemonLoop.submit`` of
    ``MDS_CMD_ESTOP``: the loop runs it at its next cycle)."""

    def __init__(self, source: EStopInput, trigger: Callable[[], object]) -> None:
        self.source = source
        self._trigger = trigger
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="estop-input", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.source.wait(0.2) and not self._stop.is_set():
                log.warning("e-stop input %s: pressed", self.source.name)
                self._trigger()

    def close(self) -> None:
        self._stop.set()
        self.source.close()
        self._thread.join(2.0)


def open_input(spec: str) -> EStopInput:
    """``--estop-input``: a path (FIFO, serial line, pipe) read line by line."""
    try:
        return LineInput(spec)
    except OSError as exc:
        raise ValueError(f"--estop-input {spec}: {exc.strerror or exc}") from None
