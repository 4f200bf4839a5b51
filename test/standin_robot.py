"""Stand-in for ``daemon --nocan`` in the network tests while the daemon does not exist yet.

A deliberately tiny simulated robot: every 20 ms it reads the newest ``mds-ref``, moves each enabled
joint's position toward its reference at most 1 rad/s, and writes ``mds-state`` (ref, pos, names,
addresses, time); ``mds-param`` is written once at start. It stops on SIGTERM/SIGINT or after
``--seconds`` (bounded, so a forgotten one goes away by itself).
"""

from __future__ import annotations

import argparse
import signal
import threading
import time

import mds_ach as mds
from mds_ach import msgs
from mds_ach.channels import StructChannel, make_channels

PERIOD_S = 0.02
MAX_SPEED = 1.0  # rad/s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0)
    args = parser.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    make_channels()
    refs = StructChannel(mds.MDS_CHAN_REF_NAME, msgs.MDS_REF)
    states = StructChannel(mds.MDS_CHAN_STATE_NAME, msgs.MDS_STATE)
    params = StructChannel(mds.MDS_CHAN_PARAM_NAME, msgs.MDS_JOINT_PARAM)
    state = msgs.MDS_STATE()
    param = msgs.MDS_JOINT_PARAM()
    for joint in mds.JOINTS:
        js = state.joint[joint.address]
        js.address = joint.address
        js.enabled = 1
        js.active = 1
        msgs.set_name(js, "name", joint.name)
        msgs.set_name(js, "nameshort", joint.short)
        jp = param.joint[joint.address]
        jp.address = joint.address
        jp.enabled = 1
        msgs.set_name(jp, "name", joint.name)
        msgs.set_name(jp, "nameshort", joint.short)
    params.put(param)
    end = time.monotonic() + args.seconds
    next_t = time.monotonic()
    while not stop.is_set() and time.monotonic() < end:
        ref = refs.latest()
        if ref is not None:
            for joint in mds.JOINTS:
                state.joint[joint.address].ref = ref.joint[joint.address].ref
        for joint in mds.JOINTS:
            js = state.joint[joint.address]
            step = max(-MAX_SPEED * PERIOD_S, min(MAX_SPEED * PERIOD_S, js.ref - js.pos))
            js.pos += step
        state.time = time.monotonic()
        states.put(state)
        next_t += PERIOD_S
        stop.wait(max(0.0, next_t - time.monotonic()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
