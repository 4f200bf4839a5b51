#!/usr/bin/env python3
"""Solve IK in this process with the library API (``mds_ach.ik.getIK``), then send the joints.

Port of the original ``examples/mds_ik_solver_example.py``: seed from the current references on
``mds-state``, solve the left arm for (x, y, z) = (0.3, 0.2, 0.0) with the legacy call
``getIK(q0, target, order, arm, err, itr)`` -> ``(q, 0)`` on success, ``(q_last, -1)`` on failure, and write
the six joints to ``mds-ref-filter`` (the mux's default input; filter and collision gate follow).
The modern API is ``mds_ach.ik.solve(target, order, arm, q0)``, returning an ``IKResult``.

Run the system first (``make run`` or ``mds-ach start nocan``), then: ``python examples/ik_solver_local.py``
"""

from __future__ import annotations

import argparse
import ctypes
import sys

import numpy as np

import mds_ach as mds
from mds_ach import ach
from mds_ach.ik import getFkArm, getIK
from mds_ach.robot.joints import LEFT_ARM

ORDER = ["p_x", "p_y", "p_z"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("target", nargs="*", type=float, default=[0.3, 0.2, 0.0], help="x y z in m")
    args = parser.parse_args()
    if len(args.target) != 3:
        parser.error("give three numbers: x y z")
    addresses = [mds.BY_SHORT[n].address for n in LEFT_ARM]  # [SP, SR, SY, EP, WY, WR]

    state = mds.MDS_STATE()
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as s:
        status, size = s.get(state, last=True, copy=True)
    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(state):
        print("no robot state: is the system running?", file=sys.stderr)
        return 1
    q0 = [state.joint[a].ref for a in addresses]

    q, ok = getIK(q0, args.target, ORDER, "left", err=[0.01, 0.01, 0.01], itr=1000)
    if ok != 0:
        print(f"no IK solution for {args.target}; nothing sent", file=sys.stderr)
        return 1
    p = getFkArm(q, "left")[:3, 3]
    print(f"q = {np.round(q, 4).tolist()}  ->  hand at {np.round(p, 4).tolist()}")

    ref = mds.MDS_REF()
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as r:
        status, size = r.get(ref, last=True, copy=True)
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(ref):
            print(f"nothing on {mds.MDS_CHAN_REF_FILTER_NAME}: is the mux running?", file=sys.stderr)
            return 1
        for a, v in zip(addresses, q, strict=True):
            ref.joint[a].ref = float(v)
        r.put(ref)
    print(f"sent to {mds.MDS_CHAN_REF_FILTER_NAME}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
