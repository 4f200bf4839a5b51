"""Ach channel latency and throughput, with rclpy measured in the same run as the baseline.

Measured (each for a 1 KB frame and a 14051 B ``MDS_STATE`` frame):
* in one process: ``put`` then ``get(last=True)`` on a second handle, per-pair latency and pairs per second;
* across processes, newest-frame latency at 1 kHz: a writer process stamps CLOCK_MONOTONIC into the frame and
  puts; a reader process takes it with a blocking ``get(wait=True, last=True)`` (condvar wake-up) or with the
  busy-poll path ``poll()`` (spins on ``last_seq``) and subtracts the stamp from its own clock;
* across processes, throughput: the writer puts back to back, a blocking in-order reader counts what it gets
  (10-frame ring: a writer that outruns the reader overwrites the oldest frames, by design, as in libach);
* baseline: rclpy ``sensor_msgs/JointState`` (17 joints) publish -> receive across two processes, the same
  stamp-in-message method, same rate, default QoS. This needs the private network namespace of
  ``tools/netns-run`` (``make bench`` provides it); outside it the baseline is skipped.
* peer: iceoryx2's Python binding (``bench/requirements.txt``), the same 14 KB frame at 1 kHz with a blocking
  newest-frame wait: the writer loans a sample, copies the frame in, sends it and notifies an event service;
  the reader blocks on the event's listener, takes the newest sample (subscriber buffer 1, safe overflow) and
  copies the frame out, as ``get(WAIT | LAST)`` does. Ach and iceoryx2 run in alternating rounds so that a
  busy machine slows both alike.

Every role runs in a fresh child process (``python -m bench.bench_ach ROLE ...``), so the numbers do not
depend on what other benchmarks loaded into the parent. All children (Ach and rclpy alike) raise their
priority to nice -20 when allowed, as a robot's real-time processes would run; on a shared, loaded machine this
keeps other load from dominating either side.
Targets (issue 2): blocking >= 5x lower median than rclpy, busy-poll >= 20x lower, in-process put+get of
MDS_STATE <= 10 us median. Issue 20: blocking newest-frame 14 KB >= 1.5x lower median than iceoryx2 and p99 at or
below iceoryx2's. They apply to the default implementation (the C fast path ``mds_ach.ach._achfast`` when
built); the pure-Python path (``MDS_ACH_PURE_PYTHON=1``) is measured in the same run and printed for reference.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import subprocess
import sys
import time
from pathlib import Path

from bench.common import Row, median, percentile

GROUP = "ach"
REPO = Path(__file__).resolve().parent.parent
SIZES = {"1 KB": 1024, "14 KB MDS_STATE": 14051}
STAMP = struct.Struct("<qq")  # CLOCK_MONOTONIC ns at put, frame counter (-1 = end)
WARMUP = 50
RATE_HZ = 1000.0


# --- child roles ---------------------------------------------------------------------------------


def _pace(period_s: float, count: int):
    """Yield ``count`` times on an absolute-time schedule (sleep to each deadline, no drift)."""
    t = time.monotonic()
    for i in range(count):
        t += period_s
        delay = t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        yield i


def role_ach_writer(name: str, size: int, count: int, rate: float) -> None:
    """Put ``WARMUP + count`` stamped frames at ``rate`` Hz (0 = back to back), then an end marker."""
    from mds_ach import ach

    ch = ach.Channel(name, create=False)
    buf = bytearray(size)
    view = memoryview(buf)
    put = ch.put
    sys.stdin.readline()  # the reader is ready
    ticks = _pace(1.0 / rate, WARMUP + count) if rate > 0 else range(WARMUP + count)
    for i in ticks:
        STAMP.pack_into(buf, 0, time.monotonic_ns(), i)
        put(view)
    STAMP.pack_into(buf, 0, time.monotonic_ns(), -1)
    put(view)
    ch.close()


def role_ach_reader(name: str, size: int, mode: str) -> None:
    """Read until the end marker; print latencies (ns) or the in-order delivery count as JSON."""
    from mds_ach import ach

    ch = ach.Channel(name, create=False)
    buf = bytearray(size)
    view = memoryview(buf)
    ch.flush()
    print("ready", flush=True)
    lat: list[int] = []
    received = missed = 0
    first = last = 0
    if mode == "throughput":
        get = ch.get_status
        while True:
            status, _ = get(view, ach.ACH_O_WAIT)
            now = time.monotonic_ns()
            i = STAMP.unpack_from(buf, 0)[1]
            if i < 0:
                break
            received += 1
            missed += status == ach.ACH_MISSED_FRAME
            first = first or now
            last = now
        print(json.dumps({"received": received, "missed": missed, "seconds": (last - first) / 1e9}), flush=True)
        return
    if mode == "poll":
        while True:
            ch.poll(view)
            now = time.monotonic_ns()
            stamp, i = STAMP.unpack_from(buf, 0)
            if i < 0:
                break
            if i >= WARMUP:
                lat.append(now - stamp)
    else:
        get = ch.get_status
        options = ach.ACH_O_WAIT | ach.ACH_O_LAST
        while True:
            get(view, options)
            now = time.monotonic_ns()
            stamp, i = STAMP.unpack_from(buf, 0)
            if i < 0:
                break
            if i >= WARMUP:
                lat.append(now - stamp)
    print(json.dumps({"latency_ns": lat}), flush=True)


def _iox_frame(size: int):  # noqa: ANN202 - a ctypes Structure class built for the frame size
    import ctypes

    class BenchFrame(ctypes.Structure):
        _fields_ = [("data", ctypes.c_uint8 * size)]

    return BenchFrame


def _iox_ports(name: str, size: int):  # noqa: ANN202 - iceoryx2 objects (not typed)
    import iceoryx2 as iox2

    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    node = iox2.NodeBuilder.new().create(iox2.ServiceType.Ipc)
    service = iox2.ServiceName.new(name)
    pubsub = (node.service_builder(service).publish_subscribe(_iox_frame(size)).subscriber_max_buffer_size(1)
              .history_size(0).enable_safe_overflow(True).open_or_create())
    event = node.service_builder(service).event().open_or_create()
    return iox2, node, pubsub, event


def role_iox_writer(name: str, size: int, count: int, rate: float) -> None:
    """iceoryx2 twin of ``role_ach_writer``: loan, copy the stamped frame in, send, notify."""
    import ctypes

    _iox2, _node, pubsub, event = _iox_ports(name, size)
    publisher = pubsub.publisher_builder().create()
    notifier = event.notifier_builder().create()
    buf = (ctypes.c_uint8 * size)()
    sys.stdin.readline()  # the reader is ready
    time.sleep(0.2)  # let the publisher see the subscriber
    for i in itertools.chain(_pace(1.0 / rate, WARMUP + count), [-1]):
        STAMP.pack_into(buf, 0, time.monotonic_ns(), i)
        sample = publisher.loan_uninit()
        ctypes.memmove(sample.payload_ptr, buf, size)
        sample.assume_init().send()
        notifier.notify()
    time.sleep(0.2)


def role_iox_reader(name: str, size: int) -> None:
    """iceoryx2 twin of the blocking ``role_ach_reader``: wait for the event, take the newest sample, copy out."""
    import ctypes

    _iox2, _node, pubsub, event = _iox_ports(name, size)
    subscriber = pubsub.subscriber_builder().buffer_size(1).create()
    listener = event.listener_builder().create()
    buf = (ctypes.c_uint8 * size)()
    print("ready", flush=True)
    lat: list[int] = []
    while True:
        listener.blocking_wait()
        newest = None
        while (sample := subscriber.receive()) is not None:
            newest = sample
        if newest is None:
            continue
        ctypes.memmove(buf, newest.payload_ptr, size)
        now = time.monotonic_ns()
        stamp, i = STAMP.unpack_from(buf, 0)
        if i < 0:
            break
        if i >= WARMUP:
            lat.append(now - stamp)
    print(json.dumps({"latency_ns": lat}), flush=True)


def role_ros_publisher(count: int, rate: float) -> None:
    import rclpy
    from sensor_msgs.msg import JointState

    from mds_ach.robot.joints import MODEL_JOINTS

    rclpy.init()
    node = rclpy.create_node("bench_ach_publisher")
    pub = node.create_publisher(JointState, "bench_ach/joint_states", 10)
    msg = JointState(name=list(MODEL_JOINTS), position=[0.0] * len(MODEL_JOINTS),
                     velocity=[0.0] * len(MODEL_JOINTS), effort=[0.0] * len(MODEL_JOINTS))
    deadline = time.monotonic() + 30
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            raise SystemExit("no subscriber matched within 30 s")
        time.sleep(0.01)
    time.sleep(0.2)  # let the subscriber's side of the match settle too
    for i in _pace(1.0 / rate, WARMUP + count):
        t = time.monotonic_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t, 1_000_000_000)
        msg.header.frame_id = str(i)
        pub.publish(msg)
    for _ in range(20):  # end marker; repeated in case the reader's queue overflowed
        msg.header.frame_id = "-1"
        pub.publish(msg)
        time.sleep(0.01)
    node.destroy_node()
    rclpy.shutdown()


def role_ros_subscriber() -> None:
    import rclpy
    from sensor_msgs.msg import JointState

    rclpy.init()
    node = rclpy.create_node("bench_ach_subscriber")
    lat: list[int] = []
    done = []

    def on_msg(msg: JointState) -> None:
        now = time.monotonic_ns()
        i = int(msg.header.frame_id)
        if i < 0:
            done.append(True)
        elif i >= WARMUP:
            lat.append(now - (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec))

    node.create_subscription(JointState, "bench_ach/joint_states", on_msg, 10)
    print("ready", flush=True)
    deadline = time.monotonic() + 120
    while not done and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(json.dumps({"latency_ns": lat}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


# --- orchestration ---------------------------------------------------------------------------------


def _spawn(*args: object, pure: bool = False) -> subprocess.Popen[str]:
    env = dict(os.environ, MDS_ACH_PURE_PYTHON="1") if pure else None
    return subprocess.Popen([sys.executable, "-m", "bench.bench_ach", *map(str, args)], cwd=REPO, text=True, env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _expect_ready(proc: subprocess.Popen[str]) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline().strip()
    if line != "ready":
        proc.kill()
        raise RuntimeError(f"benchmark child failed to start: {line!r} {proc.stderr.read() if proc.stderr else ''}")


def _result(proc: subprocess.Popen[str], timeout: float = 300) -> dict:
    out, err = proc.communicate(timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark child exited with {proc.returncode}: {err.strip()[-2000:]}")
    return json.loads(out.strip().splitlines()[-1])


def cross_process(name: str, size: int, mode: str, count: int, rate: float, pure: bool = False) -> dict:
    """One writer process and one reader process on a fresh channel; returns the reader's JSON."""
    from mds_ach import ach

    if ach.exists(name):
        ach.unlink(name)
    ach.create(name, 10, max(size, 3000))
    try:
        reader = _spawn("ach-reader", name, size, mode, pure=pure)
        _expect_ready(reader)
        writer = _spawn("ach-writer", name, size, count, rate, pure=pure)
        assert writer.stdin is not None
        writer.stdin.write("go\n")
        writer.stdin.flush()
        result = _result(reader)
        writer.communicate(timeout=60)
        return result
    finally:
        ach.unlink(name)


def iceoryx_latency(size: int, count: int, rate: float) -> list[float]:
    name = f"mds-bench/ach-vs-iox/{os.getpid()}/{time.monotonic_ns()}"
    reader = _spawn("iox-reader", name, size)
    _expect_ready(reader)
    writer = _spawn("iox-writer", name, size, count, rate)
    assert writer.stdin is not None
    writer.stdin.write("go\n")
    writer.stdin.flush()
    result = _result(reader)
    writer.communicate(timeout=60)
    return [x / 1e3 for x in result["latency_ns"]]


def peer_rows(ros: list[float], n_lat: int) -> list[Row]:
    """Ach's blocking newest-frame wait (14 KB, 1 kHz) against iceoryx2's, in alternating rounds."""
    size, rounds = SIZES["14 KB MDS_STATE"], 4
    ours: list[float] = []
    iox: list[float] = []
    try:
        for _ in range(rounds):
            ours += [x / 1e3 for x in cross_process("bench-ach-vs-iox", size, "block", n_lat // rounds,
                                                    RATE_HZ)["latency_ns"]]
            iox += iceoryx_latency(size, n_lat // rounds, RATE_HZ)
    except (ImportError, RuntimeError, subprocess.TimeoutExpired, json.JSONDecodeError) as exc:
        print(f"[bench_ach] iceoryx2 peer failed (make bench installs bench/requirements.txt): {exc}",
              file=sys.stderr)
        iox = []
    label = f"x-proc blocking newest 14 KB @1 kHz ({rounds} rounds)"
    rows = []
    med, p99 = median(ours), percentile(ours, 99)
    iox_med = median(iox) if iox else None
    iox_p99 = percentile(iox, 99) if iox else None
    rows.append(Row(GROUP, f"{label} median", med, "us", "iceoryx2 (Python), same rounds", iox_med,
                    ">= 1.5x lower", (iox_med / med >= 1.5) if iox_med else False))
    rows.append(Row(GROUP, f"{label} p99", p99, "us", "iceoryx2 (Python) p99", iox_p99, "<= iceoryx2",
                    (p99 <= iox_p99) if iox_p99 else False))
    if ros:
        rows.append(Row(GROUP, f"{label} median", med, "us", "rclpy JointState (17 joints)", median(ros),
                        ">= 5x lower", median(ros) / med >= 5))
    return rows


def rclpy_latency(count: int, rate: float) -> list[float]:
    sub = _spawn("ros-subscriber")
    _expect_ready(sub)
    pub = _spawn("ros-publisher", count, rate)
    result = _result(sub)
    pub.communicate(timeout=60)
    if pub.returncode != 0:
        raise RuntimeError(f"rclpy publisher failed: {pub.stderr.read() if pub.stderr else ''}")
    return [x / 1e3 for x in result["latency_ns"]]


def in_process(size: int, count: int, pure: bool = False) -> tuple[list[float], float]:
    """put + get(last) pairs on two handles of one channel: per-pair latency (us) and pairs per second."""
    from mds_ach import ach

    name = "bench-ach-inproc"
    if ach.exists(name):
        ach.unlink(name)
    ach.create(name, 10, max(size, 3000))
    try:
        with ach.Channel(name, fast=not pure) as w, ach.Channel(name, fast=not pure) as r:
            src = memoryview(bytearray(size))
            dst = memoryview(bytearray(size))
            put, get = w.put, r.get_status
            clock = time.perf_counter_ns
            for _ in range(WARMUP * 20):
                put(src)
                get(dst, ach.ACH_O_LAST)
            samples = []
            for _ in range(count):
                t0 = clock()
                put(src)
                get(dst, ach.ACH_O_LAST)
                samples.append(clock() - t0)
            t0 = clock()
            for _ in range(count):
                put(src)
                get(dst, ach.ACH_O_LAST)
            rate = count / ((clock() - t0) / 1e9)
        return [s / 1e3 for s in samples], rate
    finally:
        ach.unlink(name)


def run(quick: bool = False) -> list[Row]:
    n_lat = 300 if quick else 2000
    n_inproc = 5000 if quick else 50000
    n_tput = 2000 if quick else 20000
    rows: list[Row] = []
    print(f"[bench_ach] load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cpus "
          "(latencies on a shared, loaded machine are much noisier)", file=sys.stderr)
    in_netns = os.environ.get("MDS_NETNS_ACTIVE") == "1"
    ros: list[float] = []
    if in_netns:
        try:
            ros = rclpy_latency(n_lat, RATE_HZ)
        except (RuntimeError, subprocess.TimeoutExpired, json.JSONDecodeError) as exc:
            print(f"[bench_ach] rclpy baseline failed, ratios omitted: {exc}", file=sys.stderr)
    else:
        print("[bench_ach] not inside tools/netns-run: rclpy baseline skipped", file=sys.stderr)
    ros_med = median(ros) if ros else None
    if ros:
        rows.append(Row(GROUP, "rclpy JointState x-proc median (baseline)", ros_med, "us"))
        rows.append(Row(GROUP, "rclpy JointState x-proc p99", percentile(ros, 99), "us"))

    rows += peer_rows(ros, n_lat)

    from mds_ach import ach

    impls = [False, True] if ach.FAST_AVAILABLE else [True]
    print(f"[bench_ach] default implementation: {'C fast path' if ach.FAST_AVAILABLE else 'pure Python'}",
          file=sys.stderr)
    for pure in impls:
        default = pure == impls[0]  # the targets apply to what users get by default
        tag = " [pure Python]" if pure and not default else ""
        for label, size in SIZES.items():
            rows += _size_rows(label + tag, size, pure, default, ros, ros_med, n_lat, n_inproc, n_tput)
    return rows


def _size_rows(label: str, size: int, pure: bool, default: bool, ros: list[float], ros_med: float | None,
               n_lat: int, n_inproc: int, n_tput: int) -> list[Row]:
    rows: list[Row] = []
    samples, rate = in_process(size, n_inproc, pure)
    med = median(samples)
    is_state = size == 14051 and default
    rows.append(Row(GROUP, f"in-proc put+get {label} median", med, "us",
                    target="<= 10 us" if is_state else "", passed=(med <= 10.0) if is_state else None))
    rows.append(Row(GROUP, f"in-proc put+get {label} p99", percentile(samples, 99), "us"))
    rows.append(Row(GROUP, f"in-proc put+get {label} throughput", rate, "pairs/s", higher_is_better=True))

    for mode, factor in (("block", 5.0), ("poll", 20.0)):
        result = cross_process(f"bench-ach-{mode}", size, mode, n_lat, RATE_HZ, pure)
        lat = [x / 1e3 for x in result["latency_ns"]]
        med = median(lat)
        what = "blocking get" if mode == "block" else "busy-poll"
        ratio_ok = (ros_med / med >= factor) if ros_med and default else None
        rows.append(Row(GROUP, f"x-proc {what} {label} median", med, "us",
                        baseline_name="rclpy JointState median" if ros else "", baseline_value=ros_med,
                        target=f">= {factor:g}x lower" if ros and default else "", passed=ratio_ok))
        rows.append(Row(GROUP, f"x-proc {what} {label} p99", percentile(lat, 99), "us",
                        baseline_name="rclpy JointState p99" if ros else "",
                        baseline_value=percentile(ros, 99) if ros else None))

    result = cross_process("bench-ach-tput", size, "throughput", n_tput, 0, pure)
    rows.append(Row(GROUP, f"x-proc throughput {label} (in-order reader)",
                    result["received"] / result["seconds"] if result["seconds"] else 0.0, "frames/s",
                    higher_is_better=True))
    rows.append(Row(GROUP, f"x-proc throughput {label}: frames delivered",
                    100.0 * (result["received"]) / (n_tput + WARMUP), "%", higher_is_better=True))
    return rows


def _raise_priority() -> None:
    try:
        os.setpriority(os.PRIO_PROCESS, 0, -20)
    except (PermissionError, OSError):
        pass  # unprivileged: measure at normal priority


def main(argv: list[str]) -> int:
    role, *args = argv
    if role != "all" and not role.startswith("-"):
        _raise_priority()
    if role == "ach-writer":
        role_ach_writer(args[0], int(args[1]), int(args[2]), float(args[3]))
    elif role == "ach-reader":
        role_ach_reader(args[0], int(args[1]), args[2])
    elif role == "iox-writer":
        role_iox_writer(args[0], int(args[1]), int(args[2]), float(args[3]))
    elif role == "iox-reader":
        role_iox_reader(args[0], int(args[1]))
    elif role == "ros-publisher":
        role_ros_publisher(int(args[0]), float(args[1]))
    elif role == "ros-subscriber":
        role_ros_subscriber()
    else:
        for row in run(quick=role == "--quick"):
            print(row)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:] or ["all"]))
