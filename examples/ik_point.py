#!/usr/bin/env python3
"""Move the left hand to one point with the IK node: 3 DOF (x, y, z) = (0.3, 0.2, 0.0) m, robot frame.

What the console's ``ik left 3 0.3 0.2 0`` does: an ``MDS_IK`` request on ``mds-ik`` (``move`` = the arm,
``ik_method`` = the task DOF). The IK node solves it from the current reference and writes the six arm
joints to its mux input, so the motion still goes through the mux, filter and collision gate. Its answer
(solved/unreachable, error, iterations, joint solution) comes back on ``mds-ik-state``.

Robot frame: origin midway between the shoulders, x forward, y to the robot's left, z up.
Run the system first (``make run`` or ``mds-ach start nocan``), then: ``python examples/ik_point.py``
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


def hand_position(state: mds.MDS_STATE) -> np.ndarray:
    """Where the left hand really is: FK of the measured joint positions."""
    q = [state.joint[mds.BY_SHORT[n].address].pos for n in LEFT_ARM]
    return getFkArm(q, "left")[:3, 3]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("target", nargs="*", type=float, default=[0.3, 0.2, 0.0], help="x y z in m")
    parser.add_argument("--timeout", type=float, default=20.0, help="s to wait for the hand to arrive")
    args = parser.parse_args()
    if len(args.target) != 3:
        parser.error("give three numbers: x y z")

    try:
        with IkClient() as ik:
            reply = ik.request("left", 3, args.target)
    except IkTimeout as exc:
        print(exc, file=sys.stderr)
        return 1
    if not reply.success:
        print(f"IK: {reply.message}", file=sys.stderr)
        return 1
    print(f"IK solved in {reply.iterations} iterations, error {reply.error:.4f}: "
          f"q = [{', '.join(f'{v:.3f}' for v in reply.q)}]")

    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as states:
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            state = states.wait(timeout=1.0)
            if state is None:
                continue
            p = hand_position(state)
            print(f"left hand at x = {p[0]: .4f}  y = {p[1]: .4f}  z = {p[2]: .4f}")
            if np.linalg.norm(p - np.array(args.target)) < 0.02:
                print("arrived")
                return 0
    print("the hand did not arrive in time (see 'mds-ach read' for collisions)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
