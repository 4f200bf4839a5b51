"""The reference pipeline hands a command on as an event and costs next to nothing at rest (#26 items 5, 6).

On the whole system (``mds-ach start nocan``): a 50 Hz stream on ``mds-ref-filter`` reaches ``mds-ref-gated`` (the
daemon's input: the daemon's own period is not in it) within 5 ms p99 of each put, not at the filter's next tick;
at rest every node together uses at most 5 % of one core, counted in CPU time (utime + stime of every process and
its children), so a busy machine does not inflate it. The measurements are ``bench/bench_events.py``'s, the rows
of ``make bench``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
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


def test_stream_reaches_the_daemon_input_within_5ms_p99(system: Path) -> None:
    """Up to three runs of 300 puts (6 s each): the best p99 must be within 5 ms. A stage that polls at the filter's
    40 Hz gives a p99 near its 25 ms period in every run; an event-driven pipeline on a machine shared with other
    work can still see one run's tail stretched by the scheduler (three processes woken in turn)."""
    runs = []
    for _ in range(3):
        lat = bench_events.handoff_latency(mds.MDS_CHAN_REF_FILTER_NAME, count=300)
        gated = np.array(lat[mds.MDS_CHAN_DAEMON_INPUT_NAME]) * 1e3
        assert len(gated) >= 290, f"only {len(gated)} of 300 puts reached mds-ref-gated"
        runs.append({name: (float(np.percentile(np.array(v) * 1e3, 50)), float(np.percentile(np.array(v) * 1e3, 99)))
                     for name, v in lat.items()})
        if runs[-1][mds.MDS_CHAN_DAEMON_INPUT_NAME][1] <= 5.0:
            break
    best = min(r[mds.MDS_CHAN_DAEMON_INPUT_NAME][1] for r in runs)
    text = "; ".join(", ".join(f"{n} p50 {a:.2f} p99 {b:.2f}" for n, (a, b) in r.items()) for r in runs)
    assert best <= 5.0, f"mds-ref-filter -> each stage (ms), per run: {text}"


def test_whole_system_at_rest_uses_at_most_5_percent_of_a_core(system: Path) -> None:
    time.sleep(3.0)  # the stream of the other test (or the start) has come to rest
    pids = bench_events.node_pids(system)
    assert set(pids) >= {"daemon", "mux", "filter", "collision"}, f"nodes found: {sorted(pids)}"
    cpu = bench_events.idle_cpu(pids, 60.0)
    each = ", ".join(f"{n} {v * 100:.2f} %" for n, v in cpu.items())
    assert cpu["total"] <= 0.05, f"CPU at rest over 60 s, fraction of one core: {each}"
