"""The one reference writer of the operator tools: read-modify-write of a controller input (``mds-ref-filter``).

Why read-modify-write: the mux takes only the joints that *changed* in a controller's frame as commands, so a tool
that moves one joint must send the controller's newest frame with just that joint changed. With no usable frame
yet (the mux seeds the channel when it starts) the base is the reference the daemon holds now (``mds-state``). A
base with a non-finite reference is refused here, with the joints named: the mux would refuse the whole frame,
and substituting a number would command that joint to it. The channel is never created: no running system, no
references. Used by ``mds-ach console`` and the viewer's sliders.

Imports: :mod:`mds_ach.ach` and the robot's structs.
"""

from __future__ import annotations

import ctypes
import math
import threading
from collections.abc import Mapping

import mds_ach as mds
from mds_ach import ach


class RefWriteError(RuntimeError):
    """Nothing was written; the message says why."""


class RefWriter:
    """Writes joint targets into one controller input channel; thread-safe, opens the channel on first use."""

    def __init__(self, name: str = mds.MDS_CHAN_REF_FILTER_NAME) -> None:
        self.name = name
        self._chan: ach.Channel | None = None
        self._lock = threading.Lock()

    def open(self) -> None:
        """Open the channel for writing (never create it); RefWriteError if it is missing or unusable."""
        with self._lock:
            self._open()

    def _open(self) -> ach.Channel:
        if self._chan is None:
            if not ach.exists(self.name):
                raise RefWriteError(f"channel {self.name} does not exist; is MDS-Ach running? (mds-ach start)")
            try:
                self._chan = ach.Channel(self.name, create=False)
            except (OSError, ach.AchException) as exc:
                raise RefWriteError(str(exc)) from None
        return self._chan

    def put(self, targets: Mapping[int, float], state: mds.MDS_STATE) -> mds.MDS_REF:
        """Write the newest frame (or ``state``'s references) with ``targets`` (address -> rad) applied; returns
        the frame written. Targets must be finite; range checks are the caller's (it knows the joint table)."""
        bad = [a for a, v in targets.items() if not math.isfinite(v)]
        if bad:
            raise RefWriteError(f"non-finite target for {', '.join(mds.BY_ADDRESS[a].short for a in bad)}")
        with self._lock:
            chan = self._open()
            ref = mds.MDS_REF()
            status, size = chan.get(ref, last=True, copy=True)  # the newest, even if seen before
            if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(ref) or \
                    not all(math.isfinite(ref.joint[i].ref) for i in range(mds.MDS_JOINT_COUNT)):
                ref = mds.MDS_REF()
                for i in range(mds.MDS_JOINT_COUNT):
                    ref.joint[i].ref = state.joint[i].ref
            unknown = [i for i in range(mds.MDS_JOINT_COUNT)
                       if i not in targets and not math.isfinite(ref.joint[i].ref)]
            if unknown:
                names = ", ".join(mds.BY_ADDRESS[a].short if a in mds.BY_ADDRESS else str(a) for a in unknown)
                raise RefWriteError(f"no finite reference to keep for {names}; nothing sent")
            for address, value in targets.items():
                ref.joint[address].ref = value
            chan.put(ref)
            return ref

    def close(self) -> None:
        with self._lock:
            if self._chan is not None:
                chan, self._chan = self._chan, None
                chan.close()
