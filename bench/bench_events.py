"""The reference pipeline's hand-offs and its cost at rest, on the whole system (``mds-ach start nocan``).

* **Hand-off latency**: a client streams a slow ramp on one joint at 50 Hz on a legacy input (``mds-ref-filter``,
  ``mds-ref``); each stage's output channel (``mds-ref-mux``, ``mds-ref-smooth``, ``mds-ref-gated``) is read by a
  thread blocked on it. The latency of a put at a stage is the time until that stage's first output frame after
  it (an event-driven stage answers the put itself; a polling one at its next tick). The daemon's own period is
  not in it: ``mds-ref-gated`` is the daemon's input.
* **Idle CPU**: CPU time (utime + stime, /proc/<pid>/stat, every thread and child) of every node over a window
  with nothing commanded, as a fraction of one core. CPU time, not wall: on a busy machine our processes' CPU
  time is still ours.

``python -m bench.bench_events [--quick]`` inside ``tools/netns-run`` (it starts and stops its own system in a
private runtime directory); ``test/test_events.py`` uses the same functions.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

import mds_ach as mds
from mds_ach import ach
from mds_ach.nodes.pipeline import make_ref, ref_arrays

try:
    from bench.common import Row, percentile
except ImportError:  # imported by the tests from test/ with the repo root on sys.path
    from common import Row, percentile  # type: ignore[no-redef]

GROUP = "pipeline"
STAGES = (mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME)
NODES = ("daemon", "mux", "filter", "collision", "ik", "bridge")
TICKS = os.sysconf("SC_CLK_TCK")
JOINT = "LWY"  # left wrist yaw: turning it near the rest pose collides with nothing


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants (a node started through a wrapper counts with its children)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out


def cpu_seconds(pid: int) -> float:
    """utime + stime of ``pid`` and its descendants, in s (a process gone meanwhile counts 0)."""
    total = 0
    for p in _tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])
    return total / TICKS


def node_pids(runtime: Path) -> dict[str, int]:
    """The running nodes' pids from the launcher's pid files in ``runtime``."""
    from mds_ach.tools.launcher import read_pid

    return {n: pid for n in NODES if (pid := read_pid(n, runtime)) is not None}


def idle_cpu(pids: dict[str, int], seconds: float) -> dict[str, float]:
    """Each node's CPU time over ``seconds`` of wall time as a fraction of one core (``total``: their sum)."""
    start = {n: cpu_seconds(p) for n, p in pids.items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    wall = time.monotonic() - t0
    out = {n: (cpu_seconds(p) - start[n]) / wall for n, p in pids.items()}
    out["total"] = sum(out.values())
    return out


class _Recorder(threading.Thread):
    """Blocks on one channel and records the arrival time (CLOCK_MONOTONIC) of every new frame."""

    def __init__(self, name: str) -> None:
        super().__init__(name=f"rec-{name}", daemon=True)
        self.chan = ach.Channel(name, create=False)
        self.chan.flush()
        self.times: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        buf = mds.MDS_REF()
        while not self.stop.is_set():
            try:
                status, _ = self.chan.get(buf, wait=True, last=True, timeout=0.2)
            except ach.AchException:
                return
            if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                self.times.append(time.monotonic())

    def close(self) -> None:
        self.stop.set()
        self.join(2.0)
        self.chan.close()


def handoff_latency(channel: str, count: int = 150, rate: float = 50.0, step: float = 0.001) -> dict[str, list[float]]:
    """Stream ``count`` puts at ``rate`` on ``channel`` (a ramp of ``step`` rad per put on ``JOINT``, from the
    current reference); per stage output, the latency in s of each put (until that stage's first frame after it)."""
    address = mds.BY_SHORT[JOINT].address
    inp = ach.Channel(channel, create=False)
    gated = ach.Channel(mds.MDS_CHAN_DAEMON_INPUT_NAME, create=False)
    frame = mds.MDS_REF()
    status, _ = gated.get(frame, last=True, copy=True)
    gated.close()
    assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME), "no reference on mds-ref-gated"
    ref, mode = ref_arrays(frame)
    recorders = {name: _Recorder(name) for name in STAGES}
    for r in recorders.values():
        r.start()
    put_times: list[float] = []
    try:
        time.sleep(0.3)  # the recorders are blocked on their channels
        period = 1.0 / rate
        next_t = time.monotonic()
        for k in range(count):
            ref[address] += step if (k // 50) % 2 == 0 else -step  # back and forth: stays near the rest pose
            out = make_ref(ref, mode)
            next_t += period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            put_times.append(time.monotonic())
            inp.put(bytes(out))
        time.sleep(0.5)
    finally:
        for r in recorders.values():
            r.close()
        inp.close()
    result: dict[str, list[float]] = {}
    for name, r in recorders.items():
        arrivals = np.array(r.times)
        lat = []
        for t in put_times:
            later = arrivals[arrivals >= t]
            if later.size:
                lat.append(float(later[0] - t))
        result[name] = lat
    return result


@contextmanager
def whole_system() -> Iterator[Path]:
    """``mds-ach start nocan`` in a private runtime directory (inside tools/netns-run); stopped afterwards."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
    from support.system import running_system

    with tempfile.TemporaryDirectory(prefix="mds-bench-events-") as tmp, running_system(Path(tmp)):
        yield Path(tmp)


def run(quick: bool = False) -> list[Row]:
    rows: list[Row] = []
    with whole_system() as runtime:
        time.sleep(3.0)  # start-up work (imports, first frames) is not rest
        pids = node_pids(runtime)
        cpu = idle_cpu(pids, 10.0 if quick else 60.0)
        each = ", ".join(f"{n} {cpu[n] * 100:.1f}" for n in pids)
        rows.append(Row(GROUP, f"idle CPU, whole system ({each} %)", cpu["total"] * 100, "% core",
                        target="<= 5 % of one core", passed=cpu["total"] <= 0.05))
        for channel in (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_NAME):
            lat = handoff_latency(channel, count=60 if quick else 300)
            gated = [v * 1e3 for v in lat[mds.MDS_CHAN_DAEMON_INPUT_NAME]]
            for q in (50, 99):
                rows.append(Row(GROUP, f"{channel} -> mds-ref-gated p{q} (50 Hz stream)", percentile(gated, q), "ms",
                                target="p99 <= 5 ms" if q == 99 else "",
                                passed=percentile(gated, q) <= 5.0 if q == 99 else None))
    return rows


def main(argv: list[str]) -> int:
    rows = run(quick="--quick" in argv)
    for r in rows:
        print(f"{r.name}: {r.value:.2f} {r.unit} {'' if r.passed is None else ('ok' if r.passed else 'NO')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
