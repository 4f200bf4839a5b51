#!/usr/bin/env python3
"""Move two joints at once: LEP (left elbow) to -0.2 rad and RSP (right shoulder pitch) to 0.1 rad.

Same pattern as ``one_joint.py``: read the newest ``mds-ref-filter`` frame, change the two joints, put it
once. Both joints start together and each is smoothed by the filter; the collision gate checks the pair.

Run the system first (``make run`` or ``mds-ach start nocan``), then: ``python examples/two_joints.py``
"""

from __future__ import annotations

import argparse
import ctypes
import sys
import time

import mds_ach as mds
from mds_ach import ach

TARGETS = {mds.LEP: -0.2, mds.RSP: 0.1}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=15.0, help="s to wait for the joints to arrive")
    args = parser.parse_args()

    r = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False)
    ref = mds.MDS_REF()
    status, size = r.get(ref, last=True, copy=True)
    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(ref):
        print(f"nothing on {mds.MDS_CHAN_REF_FILTER_NAME} yet: is the system (the mux) running?", file=sys.stderr)
        return 1
    for address, value in TARGETS.items():
        ref.joint[address].ref = value
    r.put(ref)
    r.close()
    print("LEP -> -0.2 rad, RSP -> 0.1 rad written to", mds.MDS_CHAN_REF_FILTER_NAME)

    s = ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    state = mds.MDS_STATE()
    deadline = time.monotonic() + args.timeout
    try:
        while time.monotonic() < deadline:
            status, _ = s.get(state, wait=True, last=True, timeout=1.0)
            if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                continue
            pos = {a: state.joint[a].pos for a in TARGETS}
            print(f"t = {state.time:10.3f}  LEP = {pos[mds.LEP]: .5f}  RSP = {pos[mds.RSP]: .5f}")
            if all(abs(pos[a] - v) < 0.005 for a, v in TARGETS.items()):
                print("arrived")
                return 0
    finally:
        s.close()
    print("the joints did not arrive in time (see 'mds-ach status' and 'mds-ach read')", file=sys.stderr)
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
