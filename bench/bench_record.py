"""Recorder benchmark (issue 30): what ``mds-ach record`` costs the writers, how big a recording grows, how long a
plot of ten minutes takes.

* Writers' put latency with and without the recorder, same run: a writer thread puts ``mds-state`` and
  ``mds-ref-gated`` at 100 Hz each (ten times the daemon's default rate); put latency p50/p99 in alternating
  windows without a recorder and with ``mds-ach record`` (every channel) running as its own process. The recorder
  is a normal reader that polls: it takes the channel lock only to copy a frame and a put never wakes it, so the
  target is p99 within 2x of the baseline (or < 50 us).
* File size per minute: the whole simulated system (``mds-ach start nocan``: daemon 10 Hz, filter and gate 40 Hz,
  mux, IK, bridge) with a client moving both arms (``mds-ref-filter``), recorded for 20 s (8 with --quick), scaled
  to a minute. No target: the number is for planning disks (``--split``).
* Plot time for a 10-minute recording: the system recording above repeated (re-stamped) to ten minutes, then
  ``mds-ach plot`` (read, compute, draw, PNG). Target < 60 s.

Run: ``python -m bench --only bench_record [--quick]`` inside tools/netns-run (it starts a system in its /dev/shm).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.common import Row, median, percentile

GROUP = "record"
REPO = Path(__file__).resolve().parent.parent
RATE_HZ = 100.0
MDS_ACH = [sys.executable, "-m", "mds_ach.tools.cli"]


def _put_latencies(seconds: float) -> list[float]:
    """Put latency (s) of mds-state and mds-ref-gated frames at RATE_HZ each, for ``seconds``."""
    import mds_ach as mds
    from mds_ach.robot.channels import StructChannel

    state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False)
    gated = StructChannel(mds.MDS_CHAN_REF_GATED_NAME, mds.MDS_REF, create=False)
    st, ref = mds.MDS_STATE(), mds.MDS_REF()
    out: list[float] = []
    t0 = next_t = time.monotonic()
    k = 0
    try:
        while time.monotonic() - t0 < seconds:
            st.joint[k % 40].pos = math.sin(k * 0.01)
            st.time = time.monotonic()
            ref.joint[k % 40].ref = math.sin(k * 0.01)
            for ch, frame in ((state, st), (gated, ref)):
                a = time.perf_counter()
                ch.put(frame)
                out.append(time.perf_counter() - a)
            k += 1
            next_t += 1.0 / RATE_HZ
            time.sleep(max(0.0, next_t - time.monotonic()))
    finally:
        state.close()
        gated.close()
    return out


def _overhead(seconds: float, tmp: Path, rounds: int) -> list[Row]:
    """Alternating windows without and with a recorder process (``rounds`` of each), so that the load of the
    machine (shared) weighs on both alike."""
    from mds_ach.robot.channels import make_channels

    make_channels()
    base: list[float] = []
    with_rec: list[float] = []
    for _ in range(rounds):
        base += _put_latencies(seconds / rounds)
        rec = subprocess.Popen([*MDS_ACH, "record", "-q", "--force", str(tmp / "overhead.mcap")], cwd=REPO,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(2.0)  # the recorder has opened every channel
            with_rec += _put_latencies(seconds / rounds)
        finally:
            rec.send_signal(signal.SIGINT)
            rec.wait(60)
    p50b, p99b, p50, p99 = median(base), percentile(base, 99), median(with_rec), percentile(with_rec, 99)
    ok = p99 <= max(2 * p99b, 50e-6)
    return [
        Row(GROUP, "writer put p50, recorder running", p50 * 1e6, "us", "no recorder (same run)", p50b * 1e6),
        Row(GROUP, "writer put p99, recorder running", p99 * 1e6, "us", "no recorder (same run)", p99b * 1e6,
            target="p99 <= 2x baseline or 50 us", passed=ok),
        Row(GROUP, "writer put max, recorder running", max(with_rec) * 1e6, "us", "no recorder (same run)",
            max(base) * 1e6),
    ]


def _mover(stop: threading.Event) -> None:
    """A client moving both shoulders and elbows on slow sines through mds-ref-filter (the console's input)."""
    import mds_ach as mds
    from mds_ach.robot.channels import StructChannel
    from mds_ach.robot.joints import lookup

    joints = [lookup(s).address for s in ("LSP", "LEP", "RSP", "REP")]
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF, create=False) as ch:
        ref = mds.MDS_REF()
        t0 = time.monotonic()
        while not stop.is_set():
            t = time.monotonic() - t0
            for k, a in enumerate(joints):
                ref.joint[a].ref = -0.3 + 0.2 * math.sin(0.5 * t + k)
            ch.put(ref)
            time.sleep(0.05)


def _system_recording(seconds: float, tmp: Path) -> tuple[Path, list[Row]]:
    env = dict(os.environ)
    env["MDS_ACH_RUNTIME_DIR"] = str(tmp / "run")
    env["MDS_ACH_CONFIG_DIR"] = str(tmp / "config")
    env.pop("MDS_ACH_ROBOT", None)
    subprocess.run([*MDS_ACH, "killall"], env=env, capture_output=True, timeout=60)
    start = subprocess.run([*MDS_ACH, "start", "nocan", "--timeout", "150"], env=env, capture_output=True, text=True,
                           timeout=240)
    if start.returncode != 0:
        raise RuntimeError(f"bench_record: mds-ach start nocan failed: {start.stderr[-2000:]}")
    stop = threading.Event()
    mover = threading.Thread(target=_mover, args=(stop,))
    path = tmp / "system.mcap"
    try:
        mover.start()
        time.sleep(1.0)
        rec = subprocess.run([*MDS_ACH, "record", "-q", "--duration", str(seconds), str(path)], env=env,
                             capture_output=True, text=True, timeout=seconds + 120)
        if rec.returncode != 0:
            raise RuntimeError(f"bench_record: mds-ach record failed: {rec.stderr[-2000:]}")
    finally:
        stop.set()
        mover.join()
        subprocess.run([*MDS_ACH, "stop"], env=env, capture_output=True, timeout=120)
        subprocess.run([*MDS_ACH, "killall"], env=env, capture_output=True, timeout=60)
    from mds_ach.record.recording import load

    rec_data = load(path)
    per_min = path.stat().st_size / seconds * 60
    msgs = rec_data.count / seconds
    return path, [Row(GROUP, "recording size per minute (whole system)", per_min / 1e6, "MB",
                      target="for planning (--split)"),
                  Row(GROUP, "messages recorded per second", msgs, "msg/s", higher_is_better=True)]


def _ten_minutes(src: Path, out: Path, minutes: float) -> int:
    """``src`` repeated, re-stamped, until ``minutes`` of recording."""
    from mds_ach.record.recording import iter_messages
    from mds_ach.record.sink import RecordingSink

    msgs = list(iter_messages(src))
    schemas: dict[str, tuple[str, str]] = {}
    from mcap.reader import make_reader

    with open(src, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        for ch in summary.channels.values():
            sc = summary.schemas[ch.schema_id]
            schemas[ch.topic] = (sc.name, sc.data.decode())
    t0, t1 = msgs[0].log_ns, max(m.log_ns for m in msgs)
    span = max(1, t1 - t0)
    sink = RecordingSink(out)
    n = 0
    shift = 0
    while shift < minutes * 60e9:
        for m in msgs:
            sink.write(m.topic, schemas[m.topic], m.message, m.log_ns + shift, m.publish_ns + shift)
            n += 1
        shift += span
    sink.close()
    return n


def _plot_time(src: Path, tmp: Path, minutes: float) -> list[Row]:
    from mds_ach.record import plot
    from mds_ach.record.recording import load

    big = tmp / "ten.mcap"
    n = _ten_minutes(src, big, minutes)
    t = time.monotonic()
    data = plot.plot_data(load(big))
    plot.save(plot.draw(data), tmp / "ten.png")
    took = time.monotonic() - t
    return [Row(GROUP, f"plot a {minutes:g}-minute recording ({n} msgs)", took, "s", target="< 60 s",
                passed=took < 60)]


def run(quick: bool = False) -> list[Row]:
    with tempfile.TemporaryDirectory(prefix="bench-record-") as d:
        tmp = Path(d)
        rows = _overhead(4.0 if quick else 30.0, tmp, 2 if quick else 5)
        system, size_rows = _system_recording(8.0 if quick else 20.0, tmp)
        rows += size_rows
        rows += _plot_time(system, tmp, 2.0 if quick else 10.0)
        return rows


if __name__ == "__main__":
    for r in run(quick="--quick" in sys.argv):
        print(r)
