"""What the mux did with the bridge's frames, and who held its joints: read once per state cycle, never waited on.

The IK node writes one frame per request and can wait for the mux's verdict (``robot.muxverdict``). The bridge
streams (a trajectory is a frame per state cycle), so its state thread must not block: each cycle it reads the
``mds-mux-state`` frames published since the last one, in order. The mux publishes a state at once after every
refusal and every hold request, so nothing is skipped, and each state tells:

* refusals of the bridge's frames: ``refused[i]`` grew; the state names the owner or the forbidden joint
  (``muxverdict.describe``), when the refused frame arrived (``time - age[i]``), which the bridge maps to the
  command that frame carried, and which joints the bridge owned then (a frame of it the mux applied);
* joints that became held or cancelled (a HOLD or CANCEL from anyone), when, and who asked;
* who owns each joint now, so a CANCEL from the bridge never takes a joint away from another controller.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import mds_ach as mds
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE, get_name
from mds_ach.robot.msgs.hold import HOLD_ACTIONS
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_FREE, MUX_HELD
from mds_ach.robot.muxverdict import LIVE_AGE, describe


@dataclass(frozen=True)
class Refusal:
    """The mux refused ``count`` frames of the bridge; the newest arrived at ``frame_time`` (CLOCK_MONOTONIC)."""

    frame_time: float
    count: int
    message: str  # e.g. "LSP owned by 'teleop' (priority 40)"
    owner: str  # the owning controller's name, "" when the frame was refused for another reason
    owned: frozenset[int] = frozenset()  # addresses the refused controller owned in that state (a refusal changes none)


@dataclass(frozen=True)
class NewHold:
    """Joints that went from free to held or cancelled in the state published at ``time``."""

    time: float
    addresses: frozenset[int]
    source: str  # who sent the newest hold request ("console", "mds-ach", "ros", ...)
    action: str  # its action: "hold", "cancel", ...


@dataclass
class MuxNews:
    refusals: list[Refusal] = field(default_factory=list)
    holds: list[NewHold] = field(default_factory=list)


class MuxTracker:
    """The pure part: fed every mux state in order, it reports what changed for ``controller``."""

    def __init__(self, controller: str, baseline: MDS_MUX_STATE | None = None) -> None:
        self.controller = controller
        self.newest: MDS_MUX_STATE | None = None
        self._refused = 0
        self._held = [MUX_FREE] * MDS_JOINT_COUNT
        if baseline is not None:  # what happened before the bridge started is not news
            self._remember(baseline)

    def index(self, st: MDS_MUX_STATE) -> int | None:
        return st.controller_index(self.controller)

    def _remember(self, st: MDS_MUX_STATE) -> None:
        i = self.index(st)
        self._refused = int(st.refused[i]) if i is not None else 0
        self._held = [int(st.held[a]) for a in range(MDS_JOINT_COUNT)]
        self.newest = st

    def feed(self, st: MDS_MUX_STATE, news: MuxNews) -> None:
        """Add what ``st`` says since the previous state to ``news``."""
        if self.newest is not None and st.seq < self.newest.seq:  # the mux restarted: counters from zero
            self._refused = 0
            self._held = [MUX_FREE] * MDS_JOINT_COUNT
        i = self.index(st)
        if i is not None:
            refused = int(st.refused[i])
            if refused > self._refused:
                b = st.blocker[i]
                owner = get_name(bytes(st.name[b])) if 0 <= b < st.count else ""
                owned = frozenset(a for a in range(MDS_JOINT_COUNT) if st.owner[a] == i)
                news.refusals.append(Refusal(st.time - st.age[i], refused - self._refused, describe(st, i), owner,
                                             owned))
            self._refused = refused
        held = [int(st.held[a]) for a in range(MDS_JOINT_COUNT)]
        new = frozenset(a for a in range(MDS_JOINT_COUNT) if held[a] != MUX_FREE and self._held[a] == MUX_FREE)
        if new:
            news.holds.append(NewHold(st.time, new, get_name(bytes(st.hold_source)) or "?",
                                      HOLD_ACTIONS.get(st.hold_action, str(st.hold_action))))
        self._held = held
        self.newest = st

    def others_own(self, addresses: Iterable[int]) -> set[int]:
        """Those of ``addresses`` another controller owns in the newest state (a CANCEL must leave them alone)."""
        st = self.newest
        if st is None:
            return set()
        mine = self.index(st)
        return {a for a in addresses if st.owner[a] >= 0 and st.owner[a] != mine}

    def held(self) -> tuple[list[int], list[int]]:
        """(held, cancelled) addresses in the newest state."""
        st = self.newest
        if st is None:
            return [], []
        h = [a for a in range(MDS_JOINT_COUNT) if st.held[a] == MUX_HELD]
        c = [a for a in range(MDS_JOINT_COUNT) if st.held[a] == MUX_CANCELLED]
        return h, c


class MuxWatch(MuxTracker):
    """``MuxTracker`` on the ``mds-mux-state`` channel: ``poll()`` reads every state published since the last call."""

    MAX_PER_POLL = 256  # a bridge that was stopped for long catches up in steps, never stalls its cycle

    def __init__(self, controller: str) -> None:
        self.states = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        super().__init__(controller, self.states.latest())  # also moves the read position to the newest frame

    def poll(self) -> MuxNews:
        news = MuxNews()
        for _ in range(self.MAX_PER_POLL):
            st = self.states.next()
            if st is None:
                break
            self.feed(st, news)
        return news

    def live(self) -> bool:
        """Is a mux running (a state younger than ``LIVE_AGE``)?"""
        return self.newest is not None and time.monotonic() - self.newest.time <= LIVE_AGE

    def close(self) -> None:
        self.states.close()
