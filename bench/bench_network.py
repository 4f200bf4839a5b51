"""mds-state latency over a network link: achd protocol over UDP, over TCP, and through an SSH tunnel.

A simulated robot host (its own network namespace and /dev/shm, joined to this namespace by a veth pair,
see ``test/support/netsim.py``) runs a writer that puts ``MDS_STATE`` frames (14051 B) at 100 Hz with
CLOCK_MONOTONIC in ``time``, and our achd server. Here (the operator station) an achd client process
(``python -m mds_ach.net.achd -l pull ...``) brings them into the local ``mds-state`` and this process reads
each with a blocking get and subtracts the stamp (both namespaces share the clock). SSH: the same client
through ``ssh -L`` to a real sshd on the robot (OpenSSH, ed25519 keys).

Baseline, same run, same method: the writer and the reader on one host through a local shared-memory
channel (what a process on the robot itself sees). Needs root inside ``tools/netns-run`` (``make bench``).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import Row, median, percentile

GROUP = "network"
REPO = Path(__file__).resolve().parent.parent
OP_IP = "10.78.0.1"
ROBOT_IP = "10.78.0.2"
RATE_HZ = 100.0
WARMUP = 10
TARGET_P50_MS = 5.0  # one tick of a 200 Hz loop: a remote operator sees the state within a tick


def role_writer(channel: str, rate: float, seconds: float) -> None:
    """Put stamped MDS_STATE frames on ``channel`` at ``rate`` Hz for ``seconds`` (absolute-time pacing)."""
    from mds_ach import ach
    from mds_ach.robot import msgs

    chan = ach.Channel(channel, 10, 3000)
    st = msgs.MDS_STATE()
    period = 1.0 / rate
    t = time.monotonic()
    end = t + seconds
    while t < end:
        st.time = time.monotonic()
        chan.put(st)
        t += period
        delay = t - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _collect(channel: str, count: int, timeout: float) -> list[float]:
    """``count`` one-way latencies (s) of frames arriving on the local ``channel`` after WARMUP frames."""
    from mds_ach import ach
    from mds_ach.robot import msgs

    deadline = time.monotonic() + timeout
    while not ach.exists(channel):
        if time.monotonic() > deadline:
            raise RuntimeError(f"channel {channel} never appeared")
        time.sleep(0.05)
    chan = ach.Channel(channel, create=False)
    chan.flush()
    st = msgs.MDS_STATE()
    samples: list[float] = []
    seen = 0
    while len(samples) < count:
        if time.monotonic() > deadline:
            raise RuntimeError(f"only {len(samples)} of {count} frames arrived on {channel} in {timeout:.0f} s")
        status, size = chan.get(st, wait=True, timeout=0.5)
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME) or size != 14051:
            continue
        now = time.monotonic()
        seen += 1
        if seen > WARMUP:
            samples.append(now - st.time)
    chan.close()
    return samples


def _python(*args: str) -> list[str]:
    return [sys.executable, *args]


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


def _measure_pull(argv: list[str], count: int) -> list[float]:
    """Run one achd client pulling the robot's mds-state here, and measure what arrives."""
    from mds_ach import ach

    if ach.exists("mds-state"):
        ach.unlink("mds-state")
    client = subprocess.Popen(_python("-m", "mds_ach.net.achd", *argv), cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        return _collect("mds-state", count, timeout=30 + count / RATE_HZ)
    except RuntimeError as exc:
        _stop(client)
        raise RuntimeError(f"{exc}; achd client said: {client.stderr.read()[-500:] if client.stderr else ''}") from exc
    finally:
        if client.poll() is None:
            _stop(client)


def run(quick: bool = False) -> list[Row]:
    from support import netsim

    from mds_ach import ach
    from mds_ach.net.remote import SshTunnel

    count = 60 if quick else 300
    case_s = (count + WARMUP) / RATE_HZ + 30
    # baseline: local shared memory, same writer, same reader
    if ach.exists("bench-local"):
        ach.unlink("bench-local")
    ach.create("bench-local", 10, 3000)
    writer = subprocess.Popen(_python("-m", "bench.bench_network", "writer", "bench-local", str(RATE_HZ),
                                      str(case_s)), cwd=REPO)
    try:
        local = _collect("bench-local", count, case_s)
    finally:
        _stop(writer)
        ach.unlink("bench-local")

    results: dict[str, list[float]] = {}
    with netsim.Host("bench-robot") as robot, tempfile.TemporaryDirectory() as tmp:
        veth = netsim.Veth("mdsb", robot, OP_IP, ROBOT_IP)
        procs = [
            robot.popen(_python("-m", "bench.bench_network", "writer", "mds-state", str(RATE_HZ), str(4 * case_s)),
                        cwd=REPO),
            robot.popen(_python("-m", "mds_ach.net.achd", "serve", "--bind", ROBOT_IP, "--bind", "127.0.0.1"),
                        cwd=REPO),
        ]
        sshd = tunnel = None
        try:
            deadline = time.monotonic() + 20
            while not netsim.reachable(ROBOT_IP, 8076):
                if time.monotonic() > deadline:
                    raise RuntimeError("the robot's achd server did not start")
                time.sleep(0.05)
            results["UDP"] = _measure_pull(["-r", "-l", "-t", "udp", "pull", ROBOT_IP, "mds-state"], count)
            results["TCP"] = _measure_pull(["-r", "-l", "-t", "tcp", "pull", ROBOT_IP, "mds-state"], count)
            sshd = netsim.Sshd(robot, ROBOT_IP, Path(tmp), "127.0.0.1:8076")
            tunnel = SshTunnel(f"root@{ROBOT_IP}", 8076, identity=str(sshd.identity),
                               known_hosts=str(sshd.known_hosts)).start()
            results["SSH tunnel (TCP)"] = _measure_pull(
                ["-r", "-l", "-p", str(tunnel.local_port), "pull", "127.0.0.1", "mds-state"], count)
        finally:
            if tunnel is not None:
                tunnel.stop()
            if sshd is not None:
                sshd.close()
            for proc in procs:
                _stop(proc)
            veth.close()

    rows: list[Row] = []
    for name, samples in results.items():
        for q, label in ((50, "p50"), (99, "p99")):
            value = (median(samples) if q == 50 else percentile(samples, q)) * 1e3
            base = (median(local) if q == 50 else percentile(local, q)) * 1e3
            rows.append(Row(
                GROUP, f"mds-state over veth, {name}, {label}", value, "ms",
                baseline_name=f"local shm channel, {label}", baseline_value=base,
                target=f"p50 <= {TARGET_P50_MS:g} ms" if q == 50 else "",
                passed=(value <= TARGET_P50_MS) if q == 50 else None,
            ))
    return rows


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "writer":
        role_writer(sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
    else:
        for row in run(quick="--quick" in sys.argv):
            print(row)
