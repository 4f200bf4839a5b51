#!/usr/bin/env python3
"""Move one joint: LSP (left shoulder pitch) to -0.123 rad through the smoothing path.

Port of the original ``examples/mds_simple_demo_python.py``. Like the original it writes ``mds-ref-filter``
(the default controller input of the mux), so the motion goes through the mux, the smoothing filter and the
collision gate before the daemon sends it. The frame is read first and only LSP is changed: the mux treats a
changed joint as a command, so every other joint keeps what it was doing.

If the joint does not arrive in time, the target is cancelled (``mds_ach.robot.lifecycle``, ``mds-hold``), so
it never moves there later.

Run the system first (``make run`` or ``mds-ach start nocan``), then: ``python examples/one_joint.py``
"""

from __future__ import annotations

import argparse
import ctypes
import sys
import time

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot import lifecycle


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--position", type=float, default=-0.123, help="LSP target in rad (default -0.123)")
    parser.add_argument("--timeout", type=float, default=15.0, help="s to wait for the joint to arrive")
    args = parser.parse_args()

    # Read the newest reference frame (copy=True: even if this handle has seen it), change one joint, put it.
    r = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False)
    ref = mds.MDS_REF()
    status, size = r.get(ref, last=True, copy=True)
    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(ref):
        print(f"nothing on {mds.MDS_CHAN_REF_FILTER_NAME} yet: is the system (the mux) running?", file=sys.stderr)
        return 1
    ref.joint[mds.LSP].ref = args.position
    r.put(ref)
    r.close()
    print(f"LSP -> {args.position} rad written to {mds.MDS_CHAN_REF_FILTER_NAME}")

    # Watch mds-state until the measured position arrives (what example-state-mds-ach.py printed).
    s = ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    state = mds.MDS_STATE()
    deadline = time.monotonic() + args.timeout
    try:
        while time.monotonic() < deadline:
            status, _ = s.get(state, wait=True, last=True, timeout=1.0)
            if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                continue
            pos = state.joint[mds.LSP].pos
            print(f"t = {state.time:10.3f}  LSP pos = {pos: .5f}  ref = {state.joint[mds.LSP].ref: .5f}")
            if abs(pos - args.position) < 0.005:
                print("arrived")
                return 0
    finally:
        s.close()
    # A command that failed must not stay a target (the arm would move to it later, e.g. when the collision gate
    # clears): cancel it where the reference is now, and say whether the mux acknowledged that.
    ack = lifecycle.request(lifecycle.HOLD_CANCEL, [mds.LSP], source="one_joint.py", reason="timed out")
    print("LSP did not arrive in time (see 'mds-ach status' and 'mds-ach read'); "
          + ("target cancelled: LSP holds where it is" if ack.ok else ack.message), file=sys.stderr)
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
