"""Daemon loop timing, CPU and bus load on the simulated MDS bus, against a naive loop in the same run.

For each rate (10, 100, 200 Hz) a child process runs the real ``DaemonLoop`` (absolute-time schedule,
``clock_nanosleep(TIMER_ABSTIME)``, its own thread) on the simulated bus while a second process writes a new
``mds-ref-gated`` frame (the daemon's input) every period that moves all arm, torso and neck joints (17, sinusoids
in pass-through mode), so every cycle sends 17 four-frame SET sequences, one broadcast query and decodes 43 replies.

* period error = |actual period - nominal|, from the start time of every cycle (first second dropped);
* CPU = process CPU time (loop + simulated robot + channel I/O) per cycle and as % of one core, with the share
  spent inside the simulated robot (what a real bus would not cost in this process);
* bus load = worst-case wire bits (135 per frame) per cycle over 1 Mbit/s, what a real bus would need;
* baseline: the same cycle in a plain absolute-deadline loop (``next += period; time.sleep(next - now)``) on its
  own thread with the same thread settings (``tune_thread``: SCHED_FIFO 50 when allowed, nice -20): what a
  careful Python programmer would write. (A relative ``time.sleep(period)`` loop adds the work time to every
  period; comparing against it would flatter ours by two orders of magnitude.)

The simulated bus runs without wire time here so that the numbers are the software's: at 100 and 200 Hz
the traffic of 17 moving joints needs more than the 1 Mbit/s a real MDS bus has (reported, not hidden).
Targets (issue 3): 200 Hz with p99 period error < 1 ms; 10 Hz under 5 % of one core.
Children raise their priority to nice -20 and both loops run SCHED_FIFO 50 when allowed. Runs inside
``tools/netns-run`` (private /dev/shm);
outside it, the suite re-runs itself there.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from bench.common import Row, median, percentile

GROUP = "daemon"
REPO = Path(__file__).resolve().parent.parent
RATES = (10.0, 100.0, 200.0)
MOVING = ("LSP", "LSR", "LSY", "LEP", "LWY", "LWR", "RSP", "RSR", "RSY", "REP", "RWY", "RWR", "WST",
          "NKY", "NKP1", "NKP2", "NKR")
WARMUP_S = 1.0
RT_PRIORITY = 50  # SCHED_FIFO for both loops when allowed (as a robot's driver would run); else nice -20


def _accounted(fn, total: list[float]):
    def wrapper(*args, **kwargs):
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            total[0] += time.thread_time() - t0

    return wrapper


def _nice() -> None:
    try:
        os.nice(-20)
    except OSError:
        pass


def role_writer(rate: float, seconds: float) -> None:
    """Write a new mds-ref-gated frame every period: every moving joint on a 0.5 Hz sine of 0.15 rad about its home."""
    import mds_ach as mds
    from mds_ach.robot import config
    from mds_ach.robot.channels import StructChannel

    _nice()
    table = config.load("default")
    out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
    ref = mds.MDS_REF()
    for j in table:
        ref.joint[j.address].ref, ref.joint[j.address].mode = j.home, mds.MDS_REF_MODE_REF
    joints = [table[s] for s in MOVING]
    t0 = next_t = time.monotonic()
    print("ready", flush=True)
    while (now := time.monotonic()) - t0 < seconds:
        for k, j in enumerate(joints):
            ref.joint[j.address].ref = j.home + 0.15 * math.sin(2 * math.pi * 0.5 * (now - t0) + k)
        out.put(ref)
        next_t += 1.0 / rate
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    out.close()


def role_loop(kind: str, rate: float, seconds: float) -> None:
    """Run the daemon loop (``abs``: the real scheduled thread; ``deadline``: cycle + time.sleep to absolute
    deadlines on a thread with the same settings) and print JSON."""
    from mds_ach.ach.glibc import tune_thread
    from mds_ach.bus import canio
    from mds_ach.bus.simbus import SimNetwork
    from mds_ach.nodes.daemon_loop import DaemonChannels, DaemonLoop
    from mds_ach.robot import config

    _nice()
    table = config.load("default")
    net = SimNetwork.from_table(table, bitrate=None)
    io = canio.make_canio(nocan=True, network=net)
    channels = DaemonChannels.open()
    loop = DaemonLoop(table, io, channels, rate_hz=rate, nocan=True, rt_priority=RT_PRIORITY)
    loop.start_up(listen=0.2)
    starts: list[float] = []
    cpu_marks: list[float] = []
    original = loop.cycle
    sim_cpu = [0.0]
    for name in ("host_send", "host_recv"):  # account the simulated robot's share of the loop thread's CPU
        setattr(net, name, _accounted(getattr(net, name), sim_cpu))

    def timed(deadline: float | None = None, start: float | None = None) -> None:
        starts.append(time.monotonic())
        cpu_marks.append(time.process_time())
        original(deadline=deadline, start=start)

    loop.cycle = timed  # type: ignore[method-assign]
    t0 = time.monotonic()
    if kind == "abs":
        loop.start()
        time.sleep(seconds)
        loop.stop()
    else:
        def deadline_loop() -> None:
            tune_thread(RT_PRIORITY)  # the daemon loop thread's settings: only the loop body differs
            next_t = time.monotonic()
            while time.monotonic() - t0 < seconds:
                loop.cycle()
                next_t += loop.period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)

        thread = threading.Thread(target=deadline_loop, name="deadline-loop", daemon=True)
        thread.start()
        thread.join()
    skip = next((i for i, t in enumerate(starts) if t - t0 >= WARMUP_S), len(starts))
    periods = [b - a for a, b in zip(starts[skip:-1], starts[skip + 1:], strict=True)]
    errors = [abs(p - loop.period) for p in periods]
    cpu = cpu_marks[-1] - cpu_marks[skip] if len(cpu_marks) > skip + 1 else float("nan")
    sim_share = sim_cpu[0] / (cpu_marks[-1] - cpu_marks[0]) if len(cpu_marks) > 1 else float("nan")
    wall = starts[-1] - starts[skip] if len(starts) > skip + 1 else float("nan")
    n = len(periods)
    loads = loop.stats.view(loop.stats.load)
    sent = io.counters.tx_frames
    print(json.dumps({
        "cycles": n,
        "p50": percentile(errors, 50), "p99": percentile(errors, 99), "max": max(errors) if errors else math.nan,
        "cpu_per_cycle": cpu / n if n else math.nan, "cpu_core": cpu / wall if wall else math.nan,
        "sim_share": sim_share,
        "bus_load": median(list(loads[len(loads) // 2:])), "overruns": loop.status.overruns,
        "frames_per_cycle": sent / max(1, loop.cycle_count), "measured_rate": n / wall if wall else math.nan,
    }), flush=True)
    io.close()
    channels.close()


def _child(args: list[str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bench.bench_daemon", *args], cwd=REPO, text=True,
                            stdout=subprocess.PIPE, **kwargs)


def measure(kind: str, rate: float, seconds: float) -> dict:
    writer = _child(["writer", str(2 * rate), str(seconds + 5)])  # twice the loop rate: every cycle sees new refs
    try:
        assert writer.stdout is not None and writer.stdout.readline().strip() == "ready"
        loop = _child(["loop", kind, str(rate), str(seconds)])
        out, _ = loop.communicate(timeout=seconds + 60)
        if loop.returncode != 0:
            raise RuntimeError(f"daemon loop child failed ({loop.returncode})")
        return json.loads(out.strip().splitlines()[-1])
    finally:
        writer.terminate()
        writer.wait(timeout=10)


def suite(quick: bool) -> list[Row]:
    seconds = {10.0: 4.0, 100.0: 3.0, 200.0: 4.0} if quick else {10.0: 12.0, 100.0: 8.0, 200.0: 12.0}
    rows: list[Row] = []
    for rate in RATES:
        ours = measure("abs", rate, seconds[rate])
        naive = measure("deadline", rate, seconds[rate])
        base = "absolute-deadline sleep loop"
        for key, label in (("p50", "p50"), ("p99", "p99"), ("max", "max")):
            target, passed = "", None
            if rate == 200.0 and key == "p99":
                target, passed = "< 1 ms", ours["p99"] < 1e-3
            rows.append(Row(GROUP, f"period error {label} @ {rate:g} Hz ({ours['cycles']} cycles)",
                            ours[key] * 1e3, "ms", f"{base} {label}", naive[key] * 1e3, target, passed))
        rows.append(Row(GROUP, f"measured rate @ {rate:g} Hz (overruns {ours['overruns']})", ours["measured_rate"],
                        "Hz", base, naive["measured_rate"], f"{rate:g} Hz", abs(ours["measured_rate"] - rate)
                        < 0.01 * rate, higher_is_better=True))
        rows.append(Row(GROUP, f"CPU per cycle @ {rate:g} Hz ({ours['sim_share'] * 100:.0f}% of it the sim)",
                        ours["cpu_per_cycle"] * 1e3, "ms", f"{base} (same work)", naive["cpu_per_cycle"] * 1e3))
        cpu_target, cpu_ok = ("< 5 % of a core", ours["cpu_core"] < 0.05) if rate == 10.0 else ("", None)
        rows.append(Row(GROUP, f"CPU @ {rate:g} Hz, 17 joints moving (incl. sim)", ours["cpu_core"] * 100,
                        "% core", "", None, cpu_target, cpu_ok))
        load_target, load_ok = ("<= 60 % (1 Mbit/s)", ours["bus_load"] <= 60.0) if rate == 10.0 else ("", None)
        rows.append(Row(GROUP, f"bus load @ {rate:g} Hz ({ours['frames_per_cycle']:.0f} frames sent/cycle)",
                        ours["bus_load"], "%", "", None, load_target, load_ok))
    return rows


def run(quick: bool = False) -> list[Row]:
    if os.environ.get("MDS_NETNS_ACTIVE") == "1":
        return suite(quick)
    # Private /dev/shm so the benchmark never touches a running system's channels.
    out = subprocess.run([str(REPO / "tools/netns-run"), sys.executable, "-m", "bench.bench_daemon", "suite",
                          *(["--quick"] if quick else [])], cwd=REPO, capture_output=True, text=True, check=True)
    return [Row(**r) for r in json.loads(out.stdout.strip().splitlines()[-1])]


def main(argv: list[str]) -> int:
    role = argv[0] if argv else "suite"
    if role == "writer":
        role_writer(float(argv[1]), float(argv[2]))
    elif role == "loop":
        role_loop(argv[1], float(argv[2]), float(argv[3]))
    elif role == "suite":
        rows = run(quick="--quick" in argv)
        print(json.dumps([r.__dict__ for r in rows]))
    else:
        print("usage: python -m bench.bench_daemon [suite [--quick] | writer RATE S | loop abs|deadline RATE S]",
              file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
