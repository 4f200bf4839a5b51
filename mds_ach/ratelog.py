"""Rate-limited logging for messages that can repeat at the frame rate (refusals, faults, drops).

A writer can send 1,000 bad frames a second; a node that logged each one with its full value filled its log by
megabytes a second (issue #25, item 9). :class:`RateLimitedLog` writes one line per *change* and counts the rest:

* the first message of a stream (``key``, e.g. one controller's refusals) is written at once, and so is a message
  whose ``kind`` (the reason, without the values that differ frame to frame) differs from the previous one, at most
  ``burst`` such lines per ``every`` seconds per stream (an input alternating two reasons cannot flood either);
* every other message is counted, and a summary line -- the newest message with how many were not written and the
  stream's total -- follows at most every ``every`` seconds (from the next message, or from :meth:`tick`, which a
  node's loop calls so that the count of a burst that stopped is still written).

So a stream writes at most ``burst + 1`` lines per ``every`` seconds, whatever the frame rate, and nothing is lost
from the counts. Imports: the standard library only (a leaf module usable from every layer).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass

LogFn = Callable[[str, str], None]
"""``log(level, message)``, level ``"error"``, ``"warn"`` or ``"info"``: the nodes' log callback."""

EVERY_S = 5.0
"""Default: at most one summary per stream per this many seconds."""

BURST = 3
"""Default: at most this many lines for changes of kind per stream per ``every`` seconds."""

MAX_STREAMS = 1024
"""Streams kept (keys from peers are not bounded): beyond this, quiet streams with nothing pending are dropped."""

_LEVELS = {"error": logging.ERROR, "warn": logging.WARNING, "info": logging.INFO}


def logger_fn(logger: logging.Logger) -> LogFn:
    """A :data:`LogFn` writing to a standard-library logger (the daemon, the network server)."""
    return lambda level, msg: logger.log(_LEVELS.get(level, logging.WARNING), msg)


@dataclass
class _Stream:
    kind: Hashable
    level: str
    text: str = ""
    total: int = 0  # every message of the stream, written or not
    pending: int = 0  # messages not written since the last line
    window: float = -math.inf  # start of the current ``every`` window
    lines: int = 0  # change lines written in the current window
    last_line: float = -math.inf


class RateLimitedLog:
    """One line per change of a stream's kind, repeats counted and summarized (see the module docstring).

    Thread-safe: the mux logs from its loop while a node may call :meth:`tick` from another thread.
    """

    def __init__(self, log: LogFn, every: float = EVERY_S, burst: int = BURST,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self.every = every
        self.burst = burst
        self._clock = clock
        self._streams: dict[str, _Stream] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, text: str, *, kind: Hashable = None, level: str = "warn",
                 every: float | None = None) -> bool:
        """Log ``text`` for stream ``key`` unless it only repeats the stream's ``kind``; True when a line was
        written. ``every`` overrides the instance's period for this stream."""
        period = self.every if every is None else every
        now = self._clock()
        with self._lock:
            s = self._streams.get(key)
            first = s is None
            if s is None:
                if len(self._streams) >= MAX_STREAMS:
                    self._prune(now, period)
                s = self._streams[key] = _Stream(kind, level)
            s.total += 1
            s.text, s.level = text, level
            if now - s.window >= period:
                s.window, s.lines = now, 0
            changed = first or kind != s.kind
            s.kind = kind
            if changed and s.lines < self.burst:
                s.lines += 1
                line = text if not s.pending else f"{text} [{s.pending} earlier not logged; {s.total} in all]"
            elif now - s.last_line >= period:
                s.pending += 1
                line = self._summary(s, now)
            else:
                s.pending += 1
                return False
            s.pending, s.last_line = 0, now
        self._log(level, line)
        return True

    def tick(self) -> None:
        """Write the summary of every stream whose repeats are pending and due (a burst that stopped)."""
        now = self._clock()
        lines = []
        with self._lock:
            for s in self._streams.values():
                if s.pending and now - s.last_line >= self.every:
                    lines.append((s.level, self._summary(s, now)))
                    s.pending, s.last_line = 0, now
        for level, line in lines:
            self._log(level, line)

    def total(self, key: str) -> int:
        """Every message of stream ``key`` so far, written or not."""
        with self._lock:
            s = self._streams.get(key)
            return 0 if s is None else s.total

    @staticmethod
    def _summary(s: _Stream, now: float) -> str:
        since = now - s.last_line
        span = f" in {since:.1f} s" if math.isfinite(since) else ""
        return f"{s.text} [repeated {s.pending}x{span}, {s.total} in all]"

    def _prune(self, now: float, period: float) -> None:
        quiet = [k for k, s in self._streams.items() if not s.pending and now - s.last_line >= period]
        for k in quiet:
            del self._streams[k]
        if len(self._streams) >= MAX_STREAMS:  # everything busy: forget the oldest line's stream
            del self._streams[min(self._streams, key=lambda k: self._streams[k].last_line)]
