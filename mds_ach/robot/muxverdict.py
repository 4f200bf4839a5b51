"""What the mux did with a controller's frame: the bounded wait a writer uses before it says "applied".

The mux reports per controller the verdict on its newest frame (``mds-mux-state`` ``verdict[]``, ``blocker[]``,
``blocked_joint[]``; ``mds_ach.robot.msgs.mux_state``) and publishes at once when a verdict changes. A writer
(the IK node, the bridge) notes the time before it writes, then waits here for a state whose frame for its
controller arrived at or after that time.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import mds_ach as mds
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_ADDRESS
from mds_ach.robot.msgs import MDS_MUX_STATE, get_name
from mds_ach.robot.msgs.mux_state import VERDICT_CLAMPED, VERDICT_INVALID, VERDICT_NOT_PERMITTED, VERDICT_OWNED

VERDICT_TIMEOUT = 0.5
"""s a writer waits for the mux's verdict (it answers within one queue pass; this covers a loaded host)."""
LIVE_AGE = 1.0
"""s: a mux whose newest state is older than this is not running (it publishes at >= 10 Hz)."""


@dataclass(frozen=True)
class Verdict:
    applied: bool
    message: str  # "" when applied as sent; else why not (naming the owner) or which joints were clamped


def describe(st: MDS_MUX_STATE, i: int) -> str:
    """Why controller ``i``'s newest frame was refused, e.g. "right arm joint RSP owned by 'ros' (priority 30)"."""
    joint = BY_ADDRESS[st.blocked_joint[i]].short if st.blocked_joint[i] in BY_ADDRESS else "a joint"
    v = st.verdict[i]
    if v == VERDICT_OWNED and 0 <= st.blocker[i] < st.count:
        b = st.blocker[i]
        return f"{joint} owned by '{get_name(bytes(st.name[b]))}' (priority {st.priority[b]})"
    if v == VERDICT_NOT_PERMITTED:
        return f"{joint} is not permitted to this controller (config/mux.yaml)"
    if v == VERDICT_INVALID:
        return f"non-finite reference for {joint}"
    if v == VERDICT_CLAMPED:
        shorts = [BY_ADDRESS[a].short for a in st.clamped_joints(i) if a in BY_ADDRESS]
        return f"clamped to the limits: {', '.join(shorts) or joint}"
    return "refused"


class VerdictWatch:
    """Reads ``mds-mux-state`` for one controller: is the mux running, and what did it do with my frame."""

    def __init__(self, controller: str) -> None:
        self.controller = controller
        self.states = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        self.newest: MDS_MUX_STATE | None = None

    def close(self) -> None:
        self.states.close()

    def live(self) -> bool:
        """Is a mux running (newest state younger than ``LIVE_AGE``)?"""
        st = self.states.latest()
        if st is not None:
            self.newest = st
        return self.newest is not None and time.monotonic() - self.newest.time <= LIVE_AGE

    def wait(self, sent_at: float, timeout: float = VERDICT_TIMEOUT) -> Verdict:
        """Wait up to ``timeout`` s for the verdict on the controller's frame written at or after ``sent_at``."""
        deadline = time.monotonic() + timeout
        while True:
            st = self.states.wait(max(0.0, deadline - time.monotonic()))
            if st is not None:
                self.newest = st
                i = st.controller_index(self.controller)
                if i is None:
                    return Verdict(False, f"not applied: the mux has no controller '{self.controller}'")
                if st.age[i] >= 0 and st.time - st.age[i] >= sent_at - 1e-6:
                    if st.verdict[i] in (VERDICT_OWNED, VERDICT_NOT_PERMITTED, VERDICT_INVALID):
                        return Verdict(False, "not applied: " + describe(st, i))
                    return Verdict(True, describe(st, i) if st.verdict[i] == VERDICT_CLAMPED else "")
            if time.monotonic() >= deadline:
                return Verdict(False, f"not applied: no verdict from the mux within {timeout:g} s")
