"""Soak test (``make soak``): minutes of load on the running system, then a verdict on integrity and leaks.

What runs (simulated robot, inside ``tools/netns-run``'s private /dev/shm and network namespace):

* the daemon at 100 Hz (``--nocan``), the mux, the filter and the collision gate, each its own process;
* five writer processes hammering the mux inputs (two on ``mds-ref-filter``, two on ``mds-ref-ik``, one on
  ``mds-ref-ros``) with checksummed ``MDS_REF`` frames. The joints keep the mux's current reference (so the
  frames are legal commands that change nothing), except that the ``mds-ref-ros`` writer swings the neck, so
  motion really flows through mux, filter, gate, daemon and the simulated bus. The spare addresses (not in the
  joint table, ignored by the mux) carry writer id, sequence number, CRC32 and a pattern derived from both;
* one reader process per input channel verifying every frame it gets (size, CRC, pattern), and one on
  ``mds-state`` checking size, time order and finite references.

Pass criteria: zero torn or corrupt frames; every node alive and the state stream never stalled; resident memory
growth < 5 MB per process between the end of the warm-up and the end; no file-descriptor growth; and after
``mds-ach stop`` and ``mds-ach killall``, /dev/shm exactly as it was before. Prints a summary; exit status 1 on
any failure. Usage: ``python -m bench.soak [--minutes 3]`` (``make soak``).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import mds_ach as mds

WRITER_CHANNELS = (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_IK_NAME,
                   mds.MDS_CHAN_REF_IK_NAME, mds.MDS_CHAN_REF_ROS_NAME)
MOVER = 4  # the mds-ref-ros writer swings the neck
RSS_LIMIT_KB = 5 * 1024
FD_SLACK = 2  # a transient socket at the sample instant is not a leak; a leak grows steadily
STALL_LIMIT = 1.0  # s without an mds-state frame
LTTNG_WAIT = re.compile(rf"lttng-ust-wait-\d+(-{os.getuid()})?")  # liblttng-ust's shared wait files (rclpy tracing)
SPARE = tuple(a for a in range(mds.MDS_JOINT_COUNT) if a not in mds.BY_ADDRESS)
_ID, _SEQ, _CRC = SPARE[0], SPARE[1], SPARE[2]
_PATTERN = SPARE[3:]


# --------------------------------------------------------------------------------------------- frames


def _pattern(writer: int, seq: int, k: int) -> float:
    """A value every spare slot must carry for (writer, seq): a torn frame mixes two sequences and shows."""
    return float((seq * 2654435761 + writer * 40503 + k * 97) % 1_000_003)


def make_frame(base: bytes, writer: int, seq: int) -> mds.MDS_REF:
    frame = mds.MDS_REF.from_buffer_copy(base)
    frame.joint[_ID].ref, frame.joint[_SEQ].ref, frame.joint[_CRC].ref = writer, seq, 0.0
    for k, a in enumerate(_PATTERN):
        frame.joint[a].ref = _pattern(writer, seq, k)
        frame.joint[a].mode = (seq + k) & 0x7FFF
    frame.joint[_CRC].ref = float(zlib.crc32(bytes(frame)))
    return frame


def verify(data: bytes) -> str | None:
    """None for an intact soak frame, else what is wrong with it."""
    if len(data) != ctypes.sizeof(mds.MDS_REF):
        return f"torn: {len(data)} bytes"
    frame = mds.MDS_REF.from_buffer_copy(data)
    crc = frame.joint[_CRC].ref
    frame.joint[_CRC].ref = 0.0
    if float(zlib.crc32(bytes(frame))) != crc:
        return f"bad CRC (writer slot {frame.joint[_ID].ref:g}, seq slot {frame.joint[_SEQ].ref:g})"
    writer, seq = int(frame.joint[_ID].ref), int(frame.joint[_SEQ].ref)
    for k, a in enumerate(_PATTERN):
        if frame.joint[a].ref != _pattern(writer, seq, k) or frame.joint[a].mode != (seq + k) & 0x7FFF:
            return f"pattern of writer {writer} seq {seq} broken at address {a}"
    return None


# --------------------------------------------------------------------------------------------- child roles


class _Stop:
    """SIGTERM/SIGINT end a child's loop; it then prints its JSON summary."""

    def __init__(self) -> None:
        self.flag = False
        signal.signal(signal.SIGTERM, self._set)
        signal.signal(signal.SIGINT, self._set)

    def _set(self, *_: object) -> None:
        self.flag = True


def run_writer(writer: int, channel: str, rate: float) -> int:
    from mds_ach import ach

    stop = _Stop()
    with ach.Channel(mds.MDS_CHAN_REF_MUX_NAME, create=False) as mux_out:
        base = bytearray(mux_out.data_size)
        status, size = mux_out.get(base, last=True, copy=True)
    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != ctypes.sizeof(mds.MDS_REF):
        print(json.dumps({"error": f"no mux output to start from ({ach.result_string(status)})"}), flush=True)
        return 1
    base = bytes(base[:size])
    nky = mds.BY_SHORT["NKY"].address
    start_nky = mds.MDS_REF.from_buffer_copy(base).joint[nky].ref
    chan = ach.Channel(channel, create=False)
    seq, errors, period, t0 = 0, 0, 1.0 / rate, time.monotonic()
    while not stop.flag:
        seq += 1
        frame = make_frame(base, writer, seq)
        if writer == MOVER:
            frame.joint[nky].ref = start_nky + 0.2 * math.sin(2 * math.pi * (time.monotonic() - t0) / 10.0)
            frame.joint[_CRC].ref = 0.0
            frame.joint[_CRC].ref = float(zlib.crc32(bytes(frame)))
        try:
            chan.put(frame)
        except ach.AchException:
            errors += 1
        delay = t0 + seq * period - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    chan.close()
    print(json.dumps({"role": "writer", "id": writer, "channel": channel, "frames": seq, "errors": errors}),
          flush=True)
    return 0


def run_reader(channel: str) -> int:
    """Read every frame of ``channel`` in order (no 'newest only'), verify each."""
    from mds_ach import ach

    stop = _Stop()
    chan = ach.Channel(channel, create=False)
    chan.flush()  # only the writers' frames: an input may hold an older frame, e.g. the mux's start-up seed
    buf = bytearray(chan.data_size)
    counts = {"ok": 0, "missed": 0, "bad": 0}
    problems: list[str] = []
    while not stop.flag:
        status, size = chan.get(buf, wait=True, timeout=0.5)
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            continue
        counts["missed"] += status == ach.ACH_MISSED_FRAME  # the reader lagged: frames skipped, none damaged
        problem = verify(bytes(buf[:size]))
        if problem is None:
            counts["ok"] += 1
        else:
            counts["bad"] += 1
            if len(problems) < 5:
                problems.append(problem)
    chan.close()
    print(json.dumps({"role": "reader", "channel": channel, **counts, "problems": problems}), flush=True)
    return 0


def run_state_reader() -> int:
    """Every mds-state frame: right size, newer than the last, finite references; the longest gap."""
    from mds_ach import ach

    stop = _Stop()
    chan = ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    buf = bytearray(chan.data_size)
    counts = {"ok": 0, "bad": 0}
    problems: list[str] = []
    last_time, last_rx, max_gap = -math.inf, None, 0.0
    enabled: list[int] | None = None
    while not stop.flag:
        status, size = chan.get(buf, wait=True, last=True, timeout=0.5)
        now = time.monotonic()
        if last_rx is not None:
            max_gap = max(max_gap, now - last_rx)
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            continue
        last_rx = now
        problem = None
        if size != ctypes.sizeof(mds.MDS_STATE):
            problem = f"torn: {size} bytes"
        else:
            st = mds.MDS_STATE.from_buffer_copy(buf)
            if enabled is None:
                enabled = [a for a in range(mds.MDS_JOINT_COUNT) if st.joint[a].enabled]
            if not st.time > last_time:
                problem = f"time went from {last_time} to {st.time}"
            elif not all(math.isfinite(st.joint[a].ref) for a in enabled):
                problem = "non-finite reference"
            last_time = st.time
        counts["ok" if problem is None else "bad"] += 1
        if problem and len(problems) < 5:
            problems.append(problem)
    chan.close()
    print(json.dumps({"role": "state", **counts, "max_gap": max_gap, "problems": problems}), flush=True)
    return 0


# --------------------------------------------------------------------------------------------- the parent


@dataclass
class Proc:
    name: str
    pid: int
    popen: subprocess.Popen | None = None  # our own children (writers, readers)
    samples: list[tuple[float, int, int]] = field(default_factory=list)  # (t, rss kB, fds)


def rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def fd_count(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None


def shm_listing() -> set[str]:
    return set(os.listdir("/dev/shm"))


def _child(role: str, *args: str, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bench.soak", role, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _cli(*args: str, env: dict[str, str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "mds-ach"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "mds_ach.tools.cli"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, env=env, timeout=timeout)


def soak(minutes: float, rate: float, writer_rate: float, nodes: list[str], warmup: float) -> int:
    from mds_ach import ach
    from mds_ach.robot.channels import make_channels
    from mds_ach.tools import launcher

    duration = minutes * 60.0
    warmup = min(warmup, duration / 3)
    shm_before = shm_listing()
    rt = Path(tempfile.mkdtemp(prefix="mds-soak-"))
    os.environ["MDS_ACH_RUNTIME_DIR"] = str(rt)
    os.environ.setdefault("MDS_ACH_CONFIG_DIR", str(rt / "config"))
    env = dict(os.environ)
    failures: list[str] = []
    procs: dict[str, Proc] = {}
    children: list[Proc] = []
    print(f"soak: {minutes:g} min, daemon {rate:g} Hz, nodes {' '.join(nodes)}, {len(WRITER_CHANNELS)} writers at "
          f"{writer_rate:g} Hz each, runtime dir {rt}", flush=True)
    t_start = time.monotonic()
    try:
        bad = [r for r in make_channels() if not r.ok]
        if bad:
            raise RuntimeError("cannot create channels: " + "; ".join(f"{r.name}: {r.detail}" for r in bad))
        launcher.start_node("daemon", ["--nocan", "--rate", f"{rate:g}", "--over-budget"], rt)
        launcher.launch(True, 180.0, ["daemon", *nodes], rt, out=lambda t: print(t, flush=True))
        for name, pid in launcher.running_nodes(rt).items():
            procs[name] = Proc(name, pid)
        for i, channel in enumerate(WRITER_CHANNELS):
            p = _child("writer", str(i), channel, f"{writer_rate:g}", env=env)
            children.append(Proc(f"writer{i}", p.pid, p))
        for channel in dict.fromkeys(WRITER_CHANNELS):
            p = _child("reader", channel, env=env)
            children.append(Proc(f"reader:{channel}", p.pid, p))
        p = _child("state", env=env)
        children.append(Proc("reader:mds-state", p.pid, p))
        everyone = [*procs.values(), *children]
        t0 = time.monotonic()
        next_report = t0 + 30.0
        shm_counts: list[int] = []
        while (now := time.monotonic()) < t0 + duration:
            for p in everyone:
                rss, fds = rss_kb(p.pid), fd_count(p.pid)
                if rss is None or (p.popen is not None and p.popen.poll() is not None):
                    raise RuntimeError(f"{p.name} (pid {p.pid}) died during the soak")
                p.samples.append((now - t0, rss, fds or 0))
            shm_counts.append(len(shm_listing()))
            if now >= next_report:
                print(f"  {now - t0:5.0f} s: daemon RSS {procs['daemon'].samples[-1][1] / 1024:.1f} MB, "
                      f"/dev/shm {shm_counts[-1]} entries", flush=True)
                next_report += 30.0
            time.sleep(2.0)
        status = _daemon_status()
        results = _collect(children)
    except (RuntimeError, launcher.LaunchError, ach.AchException) as exc:
        failures.append(str(exc))
        results, status = _collect(children), None
    finally:
        for p in children:
            if p.popen is not None and p.popen.poll() is None:
                p.popen.kill()
        stop = _cli("stop", env=env)
        killall = _cli("killall", env=env)
        if stop.returncode or killall.returncode:
            failures.append(f"mds-ach stop/killall failed: {stop.stderr}{killall.stderr}")
    shm_after = shm_listing()
    return _report(procs, children, results, status, shm_before, shm_after, warmup, failures,
                   time.monotonic() - t_start, rate)


def _daemon_status() -> object | None:
    from mds_ach import ach
    from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS

    st = MDS_DAEMON_STATUS()
    with ach.Channel(mds.MDS_CHAN_DAEMON_STATUS_NAME, create=False) as ch:
        status, size = ch.get(st, last=True, copy=True)
    return st if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(st) else None


def _collect(children: list[Proc]) -> list[dict]:
    """SIGTERM the writers first (so the readers see their last frames), then the readers; parse their summaries."""
    results = []
    writers = [p for p in children if p.name.startswith("writer")]
    readers = [p for p in children if p.name.startswith("reader")]
    for group in (writers, readers):
        for p in group:
            if p.popen is not None and p.popen.poll() is None:
                p.popen.send_signal(signal.SIGTERM)
        for p in group:
            if p.popen is None:
                continue
            try:
                out, err = p.popen.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                p.popen.kill()
                out, err = p.popen.communicate()
            lines = [ln for ln in out.splitlines() if ln.startswith("{")]
            results.append({"name": p.name, **(json.loads(lines[-1]) if lines else {"error": err.strip()[-300:]})})
        time.sleep(0.5)  # the readers take the writers' last frames
    return results


def _growth(p: Proc, warmup: float) -> tuple[int, int, int, int]:
    """(rss at warm-up end kB, rss at end kB, fds at warm-up end, fds at end)."""
    after = [s for s in p.samples if s[0] >= warmup] or p.samples
    first, last = after[0], after[-1]
    return first[1], last[1], first[2], last[2]


def _report(procs: dict[str, Proc], children: list[Proc], results: list[dict], status: object | None,
            shm_before: set[str], shm_after: set[str], warmup: float, failures: list[str], elapsed: float,
            rate: float) -> int:
    print("\nresident memory and file descriptors (from the end of the warm-up to the end):")
    print(f"  {'process':<26} {'RSS start':>10} {'RSS end':>10} {'growth':>9} {'fds':>9}")
    for p in [*procs.values(), *children]:
        if not p.samples:
            continue
        r0, r1, f0, f1 = _growth(p, warmup)
        print(f"  {p.name:<26} {r0 / 1024:>8.1f}MB {r1 / 1024:>8.1f}MB {(r1 - r0) / 1024:>+7.2f}MB {f0:>4}->{f1:<4}")
        if r1 - r0 >= RSS_LIMIT_KB:
            failures.append(f"{p.name}: resident memory grew {(r1 - r0) / 1024:.2f} MB (limit 5 MB)")
        if f1 > f0 + FD_SLACK:
            failures.append(f"{p.name}: file descriptors grew from {f0} to {f1}")
    print("\nframes:")
    written = 0
    for r in results:
        if "error" in r:
            failures.append(f"{r['name']}: {r['error']}")
            print(f"  {r['name']:<26} ERROR {r['error']}")
        elif r["role"] == "writer":
            written += r["frames"]
            print(f"  {r['name']:<26} wrote {r['frames']:>8} frames to {r['channel']}, put errors {r['errors']}")
            if r["errors"]:
                failures.append(f"{r['name']}: {r['errors']} put errors")
        elif r["role"] == "reader":
            print(f"  {r['name']:<26} verified {r['ok']:>8}, lagged behind {r['missed']:>5} times (frames "
                  f"overwritten before it read them), torn/corrupt {r['bad']}")
            if r["bad"]:
                failures.append(f"{r['name']}: {r['bad']} torn or corrupt frames: {r['problems']}")
            if r["ok"] == 0:
                failures.append(f"{r['name']}: verified no frame at all")
        else:
            print(f"  {r['name']:<26} verified {r['ok']:>8} state frames ({r['ok'] / max(elapsed, 1):.0f}/s), bad "
                  f"{r['bad']}, longest gap {r['max_gap'] * 1e3:.0f} ms")
            if r["bad"]:
                failures.append(f"mds-state: {r['bad']} bad frames: {r['problems']}")
            if r["max_gap"] > STALL_LIMIT:
                failures.append(f"mds-state stalled for {r['max_gap']:.2f} s")
    if status is not None:
        from mds_ach.robot.msgs.daemon_status import summary_line

        print(f"\ndaemon: {summary_line(status)}; cycles {status.cycle}, period error max "
              f"{status.period_error_max * 1e3:.2f} ms, cpu/cycle {status.cpu_per_cycle * 1e3:.2f} ms")
        if status.rate_hz != rate:
            failures.append(f"the daemon ran at {status.rate_hz:g} Hz, not {rate:g} Hz")
    new = shm_after - shm_before
    tracing = sorted(n for n in new if LTTNG_WAIT.fullmatch(n))
    leaked = sorted(new - set(tracing))
    print(f"\n/dev/shm after mds-ach stop + killall: "
          f"{'nothing left behind' if not leaked else 'left behind: ' + ' '.join(leaked)}")
    if tracing:
        print(f"  (plus {' '.join(tracing)}: LTTng-UST's per-user registration files, created once by the ROS 2 "
              "tracing library in any process and reused; not channels, not per-process)")
    if leaked:
        failures.append(f"/dev/shm not clean after killall: {' '.join(leaked)}")
    print(f"\n{written} frames written in {elapsed:.0f} s")
    if failures:
        print("SOAK FAILED:\n  " + "\n  ".join(failures))
        return 1
    print("SOAK PASSED: no torn or corrupt frames, memory and descriptors stable, /dev/shm clean")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["writer"]:
        return run_writer(int(argv[1]), argv[2], float(argv[3]))
    if argv[:1] == ["reader"]:
        return run_reader(argv[1])
    if argv[:1] == ["state"]:
        return run_state_reader()
    ap = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=3.0, help="duration after start-up (default 3)")
    ap.add_argument("--rate", type=float, default=100.0, help="daemon loop rate in Hz (default 100)")
    ap.add_argument("--writer-rate", type=float, default=250.0, help="frames/s per writer (default 250)")
    ap.add_argument("--nodes", nargs="+", default=["mux", "filter", "collision"],
                    choices=["mux", "filter", "collision", "ik", "bridge"],
                    help="nodes besides the daemon (default: mux filter collision)")
    ap.add_argument("--warmup", type=float, default=30.0,
                    help="s before the memory baseline is taken (default 30, at most a third of the run)")
    ap.add_argument("--allow-host-shm", action="store_true",
                    help="run even outside tools/netns-run (it creates and removes the real MDS channels!)")
    args = ap.parse_args(argv)
    if os.environ.get("MDS_NETNS_ACTIVE") != "1" and not args.allow_host_shm:
        print("bench.soak: run it through 'make soak' (tools/netns-run): it uses the real channel names and ends "
              "with 'mds-ach killall', which would remove the channels of a system running on this machine",
              file=sys.stderr)
        return 2
    if "mux" not in args.nodes:
        print("bench.soak: the writers feed the mux: --nodes must include mux", file=sys.stderr)
        return 2
    if not (args.minutes > 0 and args.rate > 0 and args.writer_rate > 0):
        print("bench.soak: --minutes, --rate and --writer-rate must be > 0", file=sys.stderr)
        return 2
    return soak(args.minutes, args.rate, args.writer_rate, args.nodes, args.warmup)


if __name__ == "__main__":
    raise SystemExit(main())
