"""Bounded numbers for command-line options: the one argparse ``type`` every tool's numeric option uses.

``type=float`` takes ``nan``, ``inf``, ``-1`` and ``1e308``: a negative timeout passed silently, a huge one
overflowed deep inside a wait and traced back (issue #25, item 9). :func:`bounded` refuses, at parse time, any
value that is not a finite number inside the option's range, so argparse prints one line naming the option and
exits 2 (a usage error).

Imports: the standard library only (a leaf module usable from every layer).
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable

SECONDS_MAX = 3600.0
"""The longest wait or timeout an option accepts (an hour): longer ones are typos or probes, never needed."""

PORT = (1, 65535)


def bounded(minimum: float, maximum: float, *, integer: bool = False, above: bool = False,
            unit: str = "") -> Callable[[str], float]:
    """An argparse ``type``: a finite number in [``minimum``, ``maximum``] (``above``: strictly more than
    ``minimum``), an ``int`` with ``integer``. The error names the range (and ``unit``)."""
    low = "more than" if above else "at least"
    suffix = f" {unit}" if unit else ""
    what = "a whole number" if integer else "a number"
    want = f"{what} {low} {_show(minimum)} and at most {_show(maximum)}{suffix}"

    def parse(text: str) -> float:
        try:
            value: float = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}: give {want}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not a finite number: give {want}")
        if value > maximum or value < minimum or (above and value == minimum):
            raise argparse.ArgumentTypeError(f"{text} is out of range: give {want}")
        return value

    parse.__name__ = "integer" if integer else "number"  # argparse names the type in some messages
    return parse


def _show(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def seconds(maximum: float = SECONDS_MAX, *, zero: bool = False) -> Callable[[str], float]:
    """A duration in seconds: positive (or 0 with ``zero``), finite, at most ``maximum``."""
    return bounded(0.0, maximum, above=not zero, unit="s")


def rate(minimum: float, maximum: float) -> Callable[[str], float]:
    """A rate in Hz, positive and bounded."""
    return bounded(minimum, maximum, unit="Hz")


def count(minimum: int, maximum: int) -> Callable[[str], float]:
    """A whole number in [``minimum``, ``maximum``]."""
    return bounded(minimum, maximum, integer=True)


def port() -> Callable[[str], float]:
    """A TCP/UDP port, 1..65535."""
    return count(*PORT)


ROS_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def ros_namespace(text: str) -> str:
    """A ROS 2 namespace for ``--namespace``: ``robot1``, ``/robot1`` or ``lab/robot1``, returned absolute
    (``/robot1``). Each token is a ROS name token (a letter or ``_``, then letters, digits, ``_``): rcl would
    refuse anything else at node start, six times, after the channels were made."""
    tokens = text.strip("/").split("/")
    if not text.strip("/") or not all(ROS_NAME_TOKEN.fullmatch(t) for t in tokens):
        raise argparse.ArgumentTypeError(
            f"{text[:80]!r} is not a ROS namespace: give names of letters, digits and '_' (not starting with a digit) "
            "separated by '/', e.g. robot1 or lab/robot1")
    return "/" + "/".join(tokens)
