"""The reference pipeline hands a command on as an event and costs next to nothing at rest (#26 items 5, 6).

On the whole system (``mds-ach start nocan``): a 50 Hz stream on ``mds-ref-filter`` reaches ``mds-ref-gated`` (the
daemon's input: the daemon's own period is not in it) within 5 ms p99 of each put, not at the filter's next tick,
on a busy machine (CPU hogs beside it: the hand-off threads run SCHED_FIFO, ``pipeline.HANDOFF_RT_PRIORITY``); a
ROS position command is written by the bridge when it arrives, not at the next ``mds-state`` frame; at
rest every node together uses at most 5 % of one core, counted in CPU time (utime + stime of every process and its
children), so a busy machine does not inflate it. The measurements are ``bench/bench_events.py``'s, the rows of
``make bench``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support import may_use_sched_fifo
from support.hogs import CpuHogs
from support.system import running_system

import mds_ach as mds

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench import bench_events  # noqa: E402  (bench/ is not an installed package)


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    runtime = tmp_path_factory.mktemp("events")
    with running_system(runtime):
        yield runtime


def test_stream_reaches_the_daemon_input_within_5ms_p99_beside_cpu_hogs(system: Path) -> None:
    """One run of 300 puts (6 s) beside two CPU hogs. At normal priority the three hops (mux, filter, gate) each
    wait for a CPU behind busy processes: 30-50 ms p99 on the shared 2-core machine. The harness's own threads
    (putter, recorders) also run SCHED_FIFO, so their wake-ups are not counted against the pipeline."""
    if not may_use_sched_fifo():
        pytest.skip("no SCHED_FIFO here: neither the hand-off threads nor the harness can run real-time, and the "
                    "latency bound is given for real-time hand-offs (docs/reliability.md E)")
    with CpuHogs(2, 60.0):
        lat = bench_events.handoff_latency(mds.MDS_CHAN_REF_FILTER_NAME, count=300)
    assert lat.realtime, "the harness did not get SCHED_FIFO"
    gated = np.array(lat.stages[mds.MDS_CHAN_DAEMON_INPUT_NAME]) * 1e3
    assert len(gated) >= 290, f"only {len(gated)} of 300 puts reached mds-ref-gated"
    text = ", ".join(f"{n} p50 {np.percentile(v, 50) * 1e3:.2f} p99 {np.percentile(v, 99) * 1e3:.2f}"
                     for n, v in lat.stages.items())
    assert np.percentile(gated, 99) <= 5.0, f"mds-ref-filter -> each stage (ms): {text}"


def test_a_ros_position_command_is_written_at_once_not_at_the_next_state_frame(system: Path) -> None:
    """A 50 Hz stream of ``/mds/joint_command`` messages: the bridge writes each command when it arrives, so the
    median latency to ``mds-ref-gated`` is a few ms. Written at the next ``mds-state`` frame (the daemon's 10 Hz), it
    was half a daemon period (25-50 ms). Only the median: the ROS side (DDS receive thread, executor) runs at normal
    priority, so its tail on a busy machine is the scheduler's (docs/reliability.md E)."""
    lat = bench_events.handoff_latency(bench_events.ROS, count=150)
    gated = np.array(lat.stages[mds.MDS_CHAN_DAEMON_INPUT_NAME]) * 1e3
    assert len(gated) >= 140, f"only {len(gated)} of 150 commands reached mds-ref-gated"
    assert np.percentile(gated, 50) <= 10.0, (f"/mds/joint_command -> mds-ref-gated p50 {np.percentile(gated, 50):.1f}"
                                              f" ms, p99 {np.percentile(gated, 99):.1f} ms")


def test_whole_system_at_rest_uses_at_most_5_percent_of_a_core(system: Path) -> None:
    time.sleep(3.0)  # the stream of the other test (or the start) has come to rest
    pids = bench_events.node_pids(system)
    assert set(pids) >= {"daemon", "mux", "filter", "collision"}, f"nodes found: {sorted(pids)}"
    cpu = bench_events.idle_cpu(pids, 60.0)
    each = ", ".join(f"{n} {v * 100:.2f} %" for n, v in cpu.items())
    assert cpu["total"] <= 0.05, f"CPU at rest over 60 s, fraction of one core: {each}"
