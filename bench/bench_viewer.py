"""Viewer benchmark: the cost of one scene update and the update rate sustained against a live mds-state.

* Tick: read a new mds-state frame (arms moving), pose the solid robot, the reference ghost and the collision
  primitives with the numpy FK, queue the changed poses to viser. Baseline, same run, same server: the stock
  approach of viser's ``ViserUrdf`` helper (yourdfpy scene-graph FK, every joint frame re-sent) for the two
  robots.
* Sustained: the viewer loop at its default 30 Hz while a writer puts a new state every 20 ms; updates/s is the
  number of state frames the scene actually followed. The issue asks for >= 20 per second. No browser is
  connected (that cost is the browser's, on another machine).

Run: ``python -m bench --only bench_viewer [--quick]`` (inside tools/netns-run: it creates the channels).
"""

from __future__ import annotations

import math
import threading
import time

from bench.common import Row, median, percentile
from mds_ach.robot.joints import LEFT_ARM, RIGHT_ARM, lookup
from mds_ach.tools import viewer


def _state(t: float):  # -> mds.MDS_STATE
    import mds_ach as mds

    state = mds.MDS_STATE()
    for k, name in enumerate(LEFT_ARM + RIGHT_ARM):
        joint = state.joint[lookup(name).address]
        joint.pos = 0.4 * math.sin(t + k) - 0.5
        joint.ref = joint.pos + 0.05
    state.time = time.monotonic()
    return state


def run(quick: bool = False) -> list[Row]:
    from pathlib import Path

    from viser.extras import ViserUrdf

    import mds_ach as mds
    from mds_ach import paths
    from mds_ach.robot.channels import StructChannel, make_channels

    make_channels()
    n = 100 if quick else 400
    v = viewer.Viewer(viewer.ViewerOptions(port=viewer.free_port("127.0.0.1")))
    rows: list[Row] = []
    try:
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as chan:
            ticks = []
            for i in range(n):
                chan.put(_state(i * 0.05))
                t0 = time.perf_counter()
                v.tick()
                ticks.append(time.perf_counter() - t0)

            urdf = Path(paths.urdf_path())
            solid = ViserUrdf(v.server, urdf, root_node_name="/bench_solid")
            ghost = ViserUrdf(v.server, urdf, root_node_name="/bench_ghost", mesh_color_override=(90, 170, 255, 0.35))
            names = solid.get_actuated_joint_names()
            base = []
            for i in range(n):
                state = _state(i * 0.05)
                pos = [state.joint[lookup(name).address].pos for name in names]
                ref = [state.joint[lookup(name).address].ref for name in names]
                t0 = time.perf_counter()
                with v.server.atomic():
                    solid.update_cfg(pos)
                    ghost.update_cfg(ref)
                base.append(time.perf_counter() - t0)
            solid.remove()
            ghost.remove()
            rows.append(
                Row(
                    "viewer",
                    "scene update per state frame (median)",
                    median(ticks) * 1e3,
                    "ms",
                    "ViserUrdf + yourdfpy FK, 2 robots",
                    median(base) * 1e3,
                )
            )
            p99 = percentile(ticks, 99) * 1e3
            rows.append(
                Row(
                    "viewer",
                    "scene update per state frame (p99)",
                    p99,
                    "ms",
                    "ViserUrdf + yourdfpy FK, 2 robots",
                    percentile(base, 99) * 1e3,
                    target="< 50 ms (20 /s)",
                    passed=p99 < 50.0,
                )
            )

            duration = 2.0 if quick else 5.0
            stop = threading.Event()
            loop = threading.Thread(target=v.run, args=(stop,), daemon=True)
            written = 0
            first = v.state_frames
            loop.start()
            t_start = time.monotonic()
            next_t = t_start
            while time.monotonic() - t_start < duration:
                chan.put(_state(time.monotonic()))
                written += 1
                next_t += 0.02
                time.sleep(max(0.0, next_t - time.monotonic()))
            elapsed = time.monotonic() - t_start
            applied = v.state_frames - first
            stop.set()
            loop.join(timeout=5)
            rate = applied / elapsed
            rows.append(
                Row(
                    "viewer",
                    "state frames shown per second (30 Hz loop)",
                    rate,
                    "/s",
                    "state frames written per second",
                    written / elapsed,
                    target=">= 20 /s",
                    passed=rate >= 20.0,
                    higher_is_better=True,
                )
            )
    finally:
        v.close()
    return rows


if __name__ == "__main__":
    import sys

    for row in run(quick="--quick" in sys.argv):
        print(row)
