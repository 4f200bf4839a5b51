#!/usr/bin/env python3
"""The IK "box": the left hand visits the corners of a box in front of the robot, one every 5 s.

Port of the original ``examples/mds_ik_box_example.py`` (points from the original, robot frame, m):
(0.3, 0.2, 0), (0.4, 0.45, 0.25), (0.4, -0.05, 0.25), (0.4, -0.05, -0.25), (0.4, 0.45, -0.25).
Each point is a 3-DOF request to the IK node on ``mds-ik``; the motion goes through mux, filter and collision
gate. A point the IK node cannot reach (or that would collide) is reported and skipped; nothing moves then.

Run the system first (``make run`` or ``mds-ach start nocan``), then: ``python examples/ik_box.py``
(Ctrl-C stops; ``--cycles N`` stops after N rounds).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import mds_ach as mds
from mds_ach.ik import getFkArm
from mds_ach.nodes.ik_client import IkClient, IkTimeout
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import LEFT_ARM

BOX = [(0.3, 0.2, 0.0), (0.4, 0.45, 0.25), (0.4, -0.05, 0.25), (0.4, -0.05, -0.25), (0.4, 0.45, -0.25)]


def hand_position(state: mds.MDS_STATE) -> np.ndarray:
    q = [state.joint[mds.BY_SHORT[n].address].pos for n in LEFT_ARM]
    return getFkArm(q, "left")[:3, 3]


def visit(ik: IkClient, states: StructChannel, point: tuple[float, float, float], period: float) -> bool:
    """Request one corner; watch the hand until it arrives or the period is over. True if it arrived."""
    start = time.monotonic()
    reply = ik.request("left", 3, point)
    if not reply.success:
        print(f"  {point}: {reply.message}")
        time.sleep(max(0.0, period - (time.monotonic() - start)))
        return False
    arrived = False
    p = None
    while time.monotonic() - start < period:
        state = states.wait(timeout=0.5)
        if state is None:
            continue
        p = hand_position(state)
        if not arrived and np.linalg.norm(p - np.array(point)) < 0.02:
            arrived = True
            print(f"  {point}: arrived after {time.monotonic() - start:.1f} s")
    if not arrived:
        where = "unknown" if p is None else f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f})"
        print(f"  {point}: not reached within {period:g} s, hand at {where}")
    return arrived


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--period", type=float, default=5.0, help="s per corner (default 5, as the original)")
    parser.add_argument("--cycles", type=int, default=0, help="rounds to run (default 0: until Ctrl-C)")
    args = parser.parse_args()

    reached = missed = 0
    try:
        with IkClient() as ik, StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as states:
            cycle = 0
            while args.cycles == 0 or cycle < args.cycles:
                cycle += 1
                print(f"round {cycle}")
                for point in BOX:
                    if visit(ik, states, point, args.period):
                        reached += 1
                    else:
                        missed += 1
    except IkTimeout as exc:
        print(exc, file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        pass
    print(f"{reached} corners reached, {missed} not")
    return 0 if missed == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
