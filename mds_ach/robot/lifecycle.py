"""The command lifecycle client: hold / resume / cancel requests to the mux (``mds-hold``) and its answer.

One small API so every entry point (console ``hold``/``resume`` and a timed-out ``goto ... wait``,
``mds-ach hold``/``resume``, the bridge's ``mds/hold``/``mds/resume`` and aborted trajectories, the
collision gate, examples and user programs) asks the same way and waits for the same acknowledgement: the
mux handles every request in order and echoes the newest ``seq`` in ``mds-mux-state`` (``hold_seq``,
``hold_status``), publishing at once. Semantics: ``mds_ach.robot.msgs.hold``.

    seq = lifecycle.send(HOLD_CANCEL, [mds.LSP], source="console", reason="goto timed out")   # fire and forget
    ack = lifecycle.request(HOLD_HOLD, source="mds-ach")                 # send and wait (bounded) for the mux
    if not ack.ok: print(ack.message)
"""

from __future__ import annotations

import itertools
import math
import os
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import mds_ach as mds
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE
from mds_ach.robot.msgs.hold import HOLD_ACTIONS, HOLD_CANCEL, HOLD_HOLD, HOLD_REASON_SIZE, HOLD_RESUME, MDS_HOLD
from mds_ach.robot.msgs.mux_state import MUX_HOLD_DONE

__all__ = ["ACK_TIMEOUT", "HOLD_CANCEL", "HOLD_HOLD", "HOLD_RESUME", "Ack", "make", "request", "send"]

ACK_TIMEOUT = 1.0
"""s a requester waits for the mux by default (it answers within one queue pass, ~ms; 1 s covers a loaded host)."""

_lock = threading.Lock()
# Unique across writers: the process id in the high bits, a counter below (the mux only echoes; it never
# orders requests by seq, it handles them in channel order).
_counter = itertools.count(1)


def _next_seq() -> int:
    with _lock:
        return ((os.getpid() & 0xFFFF) << 16 | (next(_counter) & 0xFFFF)) or 1


def make(action: int, addresses: Iterable[int] = (), targets: Mapping[int, float] | None = None,
         source: str = "client", reason: str = "") -> MDS_HOLD:
    """An ``MDS_HOLD`` frame: ``addresses`` empty = every joint; ``targets`` (CANCEL) per address, others NaN."""
    if action not in HOLD_ACTIONS:
        raise ValueError(f"unknown hold action {action} (1 hold, 2 resume, 3 cancel)")
    h = MDS_HOLD(seq=_next_seq(), action=action, time=time.monotonic())
    for a in range(MDS_JOINT_COUNT):
        h.target[a] = math.nan
    for a in addresses:
        h.joints[a] = 1
    for a, v in (targets or {}).items():
        h.joints[a] = 1
        h.target[a] = float(v)
    h.source = source.encode("ascii", "replace")[:29]
    h.reason = reason.encode("ascii", "replace")[: HOLD_REASON_SIZE - 1]
    return h


def send(action: int, addresses: Iterable[int] = (), targets: Mapping[int, float] | None = None,
         source: str = "client", reason: str = "") -> int:
    """Write one request to ``mds-hold``; returns its seq (see ``request`` to also wait for the answer)."""
    frame = make(action, addresses, targets, source, reason)
    with StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD) as ch:
        ch.put(frame)
    return int(frame.seq)


@dataclass(frozen=True)
class Ack:
    """The mux's answer to one request: ``ok`` when handled; ``state`` is the acknowledging mds-mux-state."""

    seq: int
    ok: bool
    message: str
    state: MDS_MUX_STATE | None = None


def request(action: int, addresses: Iterable[int] = (), targets: Mapping[int, float] | None = None,
            source: str = "client", reason: str = "", timeout: float = ACK_TIMEOUT) -> Ack:
    """Send a request and wait up to ``timeout`` s for the mux to acknowledge it in ``mds-mux-state``."""
    what = HOLD_ACTIONS.get(action, str(action))
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as states:
        states.flush()  # from here on every state frame is read in order: the acknowledgement cannot be skipped
        seq = send(action, addresses, targets, source, reason)
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            st = states.wait_next(left)
            if st is None:
                continue
            if st.hold_seq == seq:
                if st.hold_status == MUX_HOLD_DONE:
                    return Ack(seq, True, f"{what} acknowledged by the mux (request {seq})", st)
                why = st.hold_reason.decode("ascii", "replace") or "invalid request; see its log"
                return Ack(seq, False, f"{what} refused by the mux (request {seq}): {why}", st)
    return Ack(seq, False, f"{what} not acknowledged: no answer from the mux on {mds.MDS_CHAN_MUX_STATE_NAME} "
                           f"within {timeout:g} s (is it running? mds-ach start --only mux)")
