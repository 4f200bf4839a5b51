"""C writers -> Python readers through the project's libach (issue #18 part 5), on mixed channels.

A C writer puts stamped frames at 200 Hz on a channel that a Python writer (another process) also writes at 200 Hz;
a Python reader (C fast path, ``get(wait=True)``) measures how long each C frame took to reach it. Two C writers:

* ``libach``: the project's libach (``ach_put``: futex wake + condvar broadcast) -- the reader is woken;
* ``broadcast-only``: the same put but waking only the condvar, as golems' libach 2.0 does -- the reader does not
  wait in the condvar (a reader killed there wedges every writer), so after the first such frame it looks at
  last_seq every ``UNWOKEN_POLL`` (inside C) for ``UNWOKEN_HOLD`` s. The first frame is reported on its own row
  (up to ``IDLE_SLICE`` late), the percentiles are over the frames after it.

Baseline (same run): the C writer -> a C reader of the same library. Target: C -> Python p99 <= 1 ms.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from support import REPO
from support import libach as lib

from bench.common import Row, median, percentile
from mds_ach import ach
from mds_ach.ach.glibc import tune_thread

GROUP = "libach"
HZ = 200.0
NAME = "bench-libach"
FRAME = struct.Struct("<QQc7x")  # struct frame of ach_latency.c (24 bytes)
RT_PRIORITY = 50  # SCHED_FIFO of the reader in the real-time rows (as bench_daemon's loops)
SKIP = 5  # frames before the statistics: the first frame of a broadcast-only writer (<= IDLE_SLICE late)

_PY_WRITER = """
import struct, sys, time
from mds_ach import ach
from mds_ach.ach.glibc import tune_thread
ch = ach.Channel(sys.argv[1], create=False)
frame = struct.Struct("<QQc7x")
period = 1e9 / float(sys.argv[2])
end = time.monotonic() + float(sys.argv[3])
t = time.monotonic_ns()
i = 0
while time.monotonic() < end:
    t += period
    time.sleep(max(0.0, (t - time.monotonic_ns()) / 1e9))
    ch.put(frame.pack(time.monotonic_ns(), i, b"P"))
    i += 1
"""


def _build() -> Path:
    out = Path(tempfile.mkdtemp(prefix="bench-libach-")) / "ach_latency"
    return lib.build(REPO / "bench" / "c" / "ach_latency.c", out, f"-I{REPO / 'mds_ach' / 'ach'}")


def _python_reader(prog: Path, mode: str, count: int, rt_priority: int = 0) -> tuple[list[float], float, float]:
    """Latencies (us) of the C frames after SKIP, the first frame's latency, and the reader's CPU share. With
    ``rt_priority`` the reader runs in a thread at that SCHED_FIFO priority (as a robot's real-time node would)."""
    result: list[tuple[list[float], float, float]] = []

    def reader() -> None:
        if rt_priority:
            tune_thread(rt_priority)
        result.append(_read(prog, mode, count))

    t = threading.Thread(target=reader, name="bench-libach-reader")
    t.start()
    t.join()
    return result[0]


def rt_allowed() -> bool:
    """SCHED_FIFO can be had here (root or CAP_SYS_NICE and an RT budget)."""
    got: list[bool] = []

    def probe() -> None:
        got.append(not tune_thread(RT_PRIORITY))

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return got[0]


def _read(prog: Path, mode: str, count: int) -> tuple[list[float], float, float]:
    ach.create(NAME, 16, 64, truncate=True)
    seconds = count / HZ + 3
    py = subprocess.Popen([sys.executable, "-c", _PY_WRITER, NAME, str(HZ), str(seconds)])
    buf = bytearray(64)
    lat: list[float] = []
    with ach.Channel(NAME, create=False) as r:
        r.flush()
        time.sleep(0.5)  # the Python writer runs: the reader is in its woken rhythm when the C writer starts
        c = subprocess.Popen([str(prog), "write", NAME, str(HZ), str(count), mode])
        cpu0, wall0 = time.thread_time(), time.monotonic()
        deadline = time.monotonic() + seconds + 10
        while len(lat) < count and time.monotonic() < deadline:
            status, size = r.get(buf, wait=True, timeout=2)
            now = time.monotonic_ns()
            if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == FRAME.size:
                stamp, _, tag = FRAME.unpack_from(buf)
                if tag == b"C":
                    lat.append((now - stamp) / 1e3)
        cpu = (time.thread_time() - cpu0) / max(1e-9, time.monotonic() - wall0)
        c.wait(30)
    py.wait(seconds + 30)
    ach.unlink(NAME)
    return lat[SKIP:], lat[0] if lat else float("nan"), cpu


def _c_reader(prog: Path, count: int) -> tuple[float, float]:
    """C writer -> C reader (this library), on the same mixed channel: median and p99 (us)."""
    ach.create(NAME, 16, 64, truncate=True)
    seconds = count / HZ + 3
    py = subprocess.Popen([sys.executable, "-c", _PY_WRITER, NAME, str(HZ), str(seconds)])
    reader = subprocess.Popen([str(prog), "read", NAME, str(count), str(SKIP)], stdout=subprocess.PIPE, text=True)
    time.sleep(0.5)
    c = subprocess.Popen([str(prog), "write", NAME, str(HZ), str(count), "libach"])
    out, _ = reader.communicate(timeout=seconds + 30)
    c.wait(30)
    py.wait(seconds + 30)
    ach.unlink(NAME)
    med, p99, _ = (float(v) for v in out.split())
    return med, p99


def run(quick: bool = False) -> list[Row]:
    count = 400 if quick else 2000  # at 200 Hz: 2 s / 10 s per run
    prog = _build()
    rows: list[Row] = []
    c_med, c_p99 = _c_reader(prog, count)
    rows.append(Row(GROUP, "C libach writer -> C reader median (baseline)", c_med, "us"))
    rt = RT_PRIORITY if rt_allowed() else 0
    for mode, label in (("libach", "C libach"), ("broadcast", "C broadcast-only")):
        lat, first, cpu = _python_reader(prog, mode, count)
        p99 = percentile(lat, 99)
        rows.append(Row(GROUP, f"{label} -> Python median (mixed)", median(lat), "us",
                        "C libach -> C reader median", c_med))
        rows.append(Row(GROUP, f"{label} -> Python p99 (mixed)", p99, "us", "C libach -> C reader p99", c_p99,
                        target="p99 <= 1000 us", passed=p99 <= 1000.0))
        rows.append(Row(GROUP, f"{label} -> Python first frame", first, "us"))
        rows.append(Row(GROUP, f"{label}: reader CPU while waiting", 100.0 * cpu, "%"))
        if rt:
            lat, _, _ = _python_reader(prog, mode, count, rt)
            p99 = percentile(lat, 99)
            rows.append(Row(GROUP, f"{label} -> Python p99, reader FIFO {rt}", p99, "us",
                            "C libach -> C reader p99", c_p99, target="p99 <= 1000 us", passed=p99 <= 1000.0))
    return rows


if __name__ == "__main__":  # python -m bench.bench_libach [--quick]
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    for row in run(quick="--quick" in sys.argv):
        print(row)
