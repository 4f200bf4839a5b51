"""Adversarial safety scenario: the whole stack on the simulated robot, attacked by a seeded random sequence of
commands and faults, then ``mds-ach check-log`` on everything the daemon sent.

What runs (inside ``tools/netns-run``): the daemon (``--nocan``, recording its traffic with ``--can-log``, one
log per daemon run, and taking test-only faults with ``--sim-faults``), mux, filter, collision gate, IK and
bridge, each its own process. A ``random.Random(seed)`` picks, until the time is up, among:

* ``goto`` a random joint of the arms, neck or torso to a random value in its range, through the console
  (``mds-ach console -c "goto ..."``) or by a legacy client's read-modify-write of ``mds-ref-filter``;
* ``mode``: a joint's legacy mode field set to 0..3 (what a legacy client writes);
* ``stop-daemon``: SIGSTOP of the daemon for 0.5-3 s; ``stop-node``: SIGSTOP of the mux, filter or gate;
* ``kill``: SIGKILL of any node, then its restart (``mds-ach start --only``; the daemon where the robot stands);
* ``bogus``: position replies 5 rad off from one node for a while; ``offline``: a node silent for 1-4 s;
* ``collide``: both hands sent to the same point (the gate must hold them), later sent apart (it releases);
* ``home``: HOME of a joint (``mds-cmd``); ``busoff``: the simulated bus goes bus-off, then ``mds-ach resetbus``.

Overload (``--hogs N``, ``make soak``: 3): for the last ``--hog-fraction`` of the scenario (half) N busy-loop
processes load every core beside the stack. The phase starts with a restart of the daemon, and meanwhile the
daemon is neither stopped nor killed (those draws hit another node), so the daemon's own ``stall_max`` in
``mds-daemon-status`` is the worst stall the overload caused; it is reported with the loop's scheduling (the
daemon asks for SCHED_FIFO by default; ``--rt-priority 0`` measures it without), the stall count and the worst
period error. A stall is reported, never a violation: a stalled loop sends nothing and ramps afterwards.

Afterwards the daemon is stopped (SIGTERM: its log is complete) and every log is audited: no target may be
non-finite, outside its joint's limits, to a wrong address, faster or more accelerated than the joint table's
motion bounds, and (``collisions``) the commanded pose may never collide. ``python -m bench.adversary
[--minutes M] [--seed N]`` prints the actions and the audit; ``test/test_safety_audit.py`` runs a minute of it.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from support.channels import newest  # test/support/, on sys.path via bench/__init__.py
from support.hogs import CpuHogs

import mds_ach as mds
from mds_ach import ach
from mds_ach.bus import simbus
from mds_ach.kinematics.limits import compute as effective_limits
from mds_ach.robot import config
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import LEFT_ARM, NECK, RIGHT_ARM, TORSO
from mds_ach.robot.msgs import daemon_status as ds
from mds_ach.tools import checklog, launcher

TABLE = config.load("default")
LIMITS = effective_limits(TABLE)  # what every entry point accepts (URDF & joint table): valid gotos stay inside
NODES = ("daemon", "mux", "filter", "collision", "ik", "bridge")
STOPPABLE = ("mux", "filter", "collision")
MOVABLE = tuple(n for n in LEFT_ARM + RIGHT_ARM + NECK + TORSO if TABLE[n].enabled)
HOME_POSE = {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2, "LEP": -1.25,
             "LSY": -0.25, "LWR": -0.28}  # the collision model's free start pose (test_collision.py)
MEETING_POINT = [0.40, 0.0, -0.10]  # m in the torso frame: both hands there collide
START_TIMEOUT = 180.0  # s: cold imports (torch, fcl, rclpy) on a shared 2-core machine
# Relative weight of each action in the random choice.
WEIGHTS = {"goto": 6, "mode": 3, "stop-daemon": 2, "stop-node": 2, "kill": 1, "bogus": 2, "offline": 2,
           "collide": 1, "home": 1, "busoff": 1}


@dataclass
class Overload:
    """How the daemon's loop fared while CPU hogs ran (from its ``mds-daemon-status``, sampled twice a second)."""

    hogs: int
    seconds: float = 0.0  # how long the hogs ran
    loop: str = "?"  # the loop thread's scheduling (ds.loop_scheduling_text)
    stalls: int = 0  # mds-daemon-status stalls: loop stalls and targets withheld for being late
    stall_max: float = 0.0  # s, the longest gap between two cycle starts of a stall (0: none over 2 periods)
    period_error_max: float = 0.0  # s, the worst |period error| seen in the daemon's 10 s windows
    overruns: int = 0

    def line(self, rate: float) -> str:
        return (f"daemon loop under {self.hogs} CPU hogs ({self.seconds:.0f} s, {rate:g} Hz, {self.loop}): "
                f"worst stall {self.stall_max:.3f} s (0: no gap over 2 periods), worst period error "
                f"{self.period_error_max * 1e3:.1f} ms, overruns {self.overruns}, stalls and late sends withheld "
                f"{self.stalls}")


@dataclass
class Result:
    seed: int
    actions: list[str] = field(default_factory=list)  # "t=  12.3 s kill mux" ...
    counts: Counter = field(default_factory=Counter)
    can_logs: list[Path] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # the stack misbehaved (a node did not come back...)
    overload: Overload | None = None  # with hogs: the daemon's stalls meanwhile


class Stack:
    """The system on the simulated robot; the daemon records its CAN traffic and takes test-only faults."""

    def __init__(self, rt: Path, rate: float, rt_priority: int | None = None) -> None:
        self.rt = rt
        self.rate = rate
        self.rt_priority = rt_priority  # the daemon's --rt-priority (None: its default)
        self.socket = rt / "sim-faults.sock"
        self.can_logs: list[Path] = []
        self.daemon: subprocess.Popen | None = None

    def start(self) -> None:
        from mds_ach.robot.channels import make_channels

        bad = [r for r in make_channels() if not r.ok]
        if bad:
            raise RuntimeError("cannot create the channels: " + "; ".join(f"{r.name}: {r.detail}" for r in bad))
        self.start_daemon()
        launcher.launch(True, START_TIMEOUT, NODES, self.rt, out=lambda _t: None)

    def start_daemon(self, pose: dict[str, float] | None = None) -> None:
        log = self.rt / f"can-{len(self.can_logs) + 1}.asc"
        self.can_logs.append(log)
        args = ["--nocan", "--rate", f"{self.rate:g}", "--over-budget", "--can-log", str(log),
                "--sim-faults", str(self.socket)]
        if self.rt_priority is not None:
            args += ["--rt-priority", str(self.rt_priority)]
        if pose:
            args += ["--sim-pose", ",".join(f"{k}={v:.6f}" for k, v in pose.items())]
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as state:
            state.flush()
            self.daemon = launcher.start_node("daemon", args, self.rt)
            deadline = time.monotonic() + START_TIMEOUT
            frames = 0
            while frames < 2 or not self.socket.exists():  # its loop runs, its fault control listens
                if self.daemon.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the daemon did not come up:\n{launcher.log_tail('daemon', rt=self.rt)}")
                frames += state.latest() is not None
                time.sleep(0.02)

    def pid(self, name: str) -> int | None:
        return launcher.read_pid(name, self.rt)

    def signal(self, name: str, sig: int) -> None:
        pid = self.pid(name)
        if pid is None:
            raise RuntimeError(f"{name} is not running:\n{launcher.log_tail(name, rt=self.rt)}")
        os.kill(pid, sig)

    def kill(self, name: str) -> None:
        """SIGKILL, then start it again (the daemon where the simulated robot stood: it lives in its process)."""
        pose = self.pose() if name == "daemon" else None
        self.signal(name, signal.SIGKILL)
        if name == "daemon" and self.daemon is not None:
            self.daemon.wait(10)  # our child: reap it
        deadline = time.monotonic() + 10
        while self.pid(name) is not None:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{name} survived SIGKILL")
            time.sleep(0.02)
        if name == "daemon":
            self.socket.unlink(missing_ok=True)
            self.start_daemon(pose)
        else:
            launcher.launch(True, START_TIMEOUT, [name], self.rt, out=lambda _t: None)

    def pose(self) -> dict[str, float]:
        """Where the enabled model joints are (mds-state), clamped into their limits."""
        st = newest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        if st is None:
            return {}
        return {n: TABLE[n].clamp(float(st.joint[TABLE[n].address].pos)) for n in MOVABLE
                if math.isfinite(st.joint[TABLE[n].address].pos)}

    def fault(self, op: str, **args: object) -> str:
        return simbus.send_fault(self.socket, op, **args)

    def stop(self) -> None:
        launcher.stop_nodes(NODES, rt=self.rt, out=lambda _t: None)
        if self.daemon is not None:
            self.daemon.wait(10)


def legacy_write(refs: dict[str, float] | None = None, modes: dict[str, int] | None = None) -> None:
    """What a legacy client does: read the newest mds-ref-filter frame, change some joints, put it back."""
    frame = newest(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF)
    if frame is None:
        raise RuntimeError("mds-ref-filter has no frame (the mux seeds it when it starts)")
    for short, q in (refs or {}).items():
        frame.joint[TABLE[short].address].ref = q
    for short, m in (modes or {}).items():
        frame.joint[TABLE[short].address].mode = m
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
        chan.put(frame)


def meeting_pose() -> dict[str, float]:
    """Both arms' joints putting the hands at MEETING_POINT (IK from the free start pose)."""
    from mds_ach import ik

    out: dict[str, float] = {}
    for arm, names in (("left", LEFT_ARM), ("right", RIGHT_ARM)):
        res = ik.solve(MEETING_POINT, "p-x p-y p-z", arm, np.array([HOME_POSE.get(n, 0.0) for n in names]))
        if not res.success:
            raise RuntimeError(f"IK for the meeting point failed: {res.message}")
        out.update({n: TABLE[n].clamp(float(q)) for n, q in zip(names, res.q, strict=True)})
    return out


def cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "mds-ach"
    return subprocess.run([str(exe), *args], capture_output=True, text=True, timeout=timeout)


class LoopWatch:
    """Samples ``mds-daemon-status`` twice a second on a thread: the daemon's stalls and worst period error."""

    def __init__(self, report: Overload) -> None:
        self.report = report
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="loop-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.5):
            self.sample()

    def sample(self) -> None:
        st = newest(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
        if st is None:
            return
        r = self.report
        r.loop, r.stalls, r.stall_max, r.overruns = ds.loop_scheduling_text(st), st.stalls, st.stall_max, st.overruns
        r.period_error_max = max(r.period_error_max, st.period_error_max)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.sample()


class Adversary:
    """Draws actions from ``random.Random(seed)`` and carries them out on a Stack until ``seconds`` are over; with
    ``hogs``, the last ``hog_fraction`` of it runs beside that many CPU hogs (see the module's docstring)."""

    def __init__(self, stack: Stack, seed: int, seconds: float, out: Callable[[str], None] = print,
                 hogs: int = 0, hog_fraction: float = 0.5) -> None:
        self.stack = stack
        self.rng = random.Random(seed)
        self.seconds = seconds
        self.out = out
        self.result = Result(seed)
        self.meeting = meeting_pose()
        self.hogs = hogs
        self.hog_fraction = hog_fraction
        self.overloaded = False  # in the overload phase: the daemon is neither stopped nor killed
        self.t0 = time.monotonic()

    def log(self, text: str) -> None:
        line = f"t={time.monotonic() - self.t0:6.1f} s  {text}"
        self.result.actions.append(line)
        self.out(line)

    def run(self) -> Result:
        legacy_write(HOME_POSE)
        self.pause(2.0, 3.0)
        names, weights = zip(*WEIGHTS.items(), strict=True)
        hog_start = self.seconds * (1.0 - self.hog_fraction) if self.hogs > 0 else math.inf
        hogs = watch = None
        try:
            while (elapsed := time.monotonic() - self.t0) < self.seconds:
                if hogs is None and elapsed >= hog_start:
                    hogs, watch = self.overload(self.seconds - elapsed)
                action = self.rng.choices(names, weights)[0]
                self.result.counts[action] += 1
                getattr(self, "do_" + action.replace("-", "_"))()
                self.pause(0.2, 1.5)
        finally:
            if hogs is not None and watch is not None and self.result.overload is not None:
                hogs.close()
                watch.close()
                self.result.overload.seconds = time.monotonic() - self.t0 - hog_start
                self.log(f"CPU hogs stopped; {self.result.overload.line(self.stack.rate)}")
        self.log("end: everything back to pass-through, the free pose")
        legacy_write(HOME_POSE, {n: mds.MDS_REF_MODE_REF for n in MOVABLE})
        self.pause(3.0, 3.0)
        return self.result

    def overload(self, seconds: float) -> tuple[CpuHogs, LoopWatch]:
        """Restart the daemon (its stall_max then covers this phase only), then start the hogs and the watch."""
        self.log(f"overload: SIGKILL daemon, restart, then {self.hogs} CPU hogs for {seconds:.0f} s (the daemon is "
                 "neither stopped nor killed meanwhile)")
        self.stack.kill("daemon")
        self.overloaded = True
        self.result.overload = Overload(self.hogs)
        return CpuHogs(self.hogs, seconds + 60.0), LoopWatch(self.result.overload)

    def pause(self, lo: float, hi: float) -> None:
        time.sleep(self.rng.uniform(lo, hi))

    def joint(self) -> str:
        return self.rng.choice(MOVABLE)

    # ----- actions

    def do_goto(self) -> None:
        short = self.joint()
        (lower,), (upper,) = LIMITS.of([short])
        q = round(self.rng.uniform(lower + 0.1 * (upper - lower), upper - 0.1 * (upper - lower)), 4)
        if self.rng.random() < 0.3:
            self.log(f"goto {short} {q} (console)")
            proc = cli("console", "-c", f"goto {short} {q}")
            if proc.returncode != 0:
                self.result.problems.append(f"console goto {short} {q}: {proc.stdout}{proc.stderr}")
        else:
            self.log(f"goto {short} {q} (mds-ref-filter)")
            legacy_write({short: q})

    def do_mode(self) -> None:
        short, mode = self.joint(), self.rng.randrange(4)
        self.log(f"mode {short} {mode}")
        legacy_write(modes={short: mode})

    def do_stop_daemon(self) -> None:
        self._stop(self.rng.choice(STOPPABLE) if self.overloaded else "daemon")

    def do_stop_node(self) -> None:
        self._stop(self.rng.choice(STOPPABLE))

    def _stop(self, name: str) -> None:
        seconds = self.rng.uniform(0.5, 3.0)
        self.log(f"SIGSTOP {name} for {seconds:.2f} s")
        self.stack.signal(name, signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            self.stack.signal(name, signal.SIGCONT)

    def do_kill(self) -> None:
        name = self.rng.choice([n for n in NODES if n != "daemon"] if self.overloaded else NODES)
        self.log(f"SIGKILL {name}, restart")
        self.stack.kill(name)

    def do_bogus(self) -> None:
        short, replies = self.joint(), self.rng.randint(1, 20)
        j = TABLE[short]
        counts = j.direction * j.rad_to_counts(5.0)  # +5 rad in joint space
        self.log(f"bogus position replies from {short}: +5 rad, {replies} replies")
        self.stack.fault("bogus_positions", address=j.address, counts=counts, replies=replies)

    def do_offline(self) -> None:
        short, seconds = self.joint(), self.rng.uniform(1.0, 4.0)
        self.log(f"{short} offline for {seconds:.2f} s")
        self.stack.fault("offline", address=TABLE[short].address, on=True)
        try:
            time.sleep(seconds)
        finally:
            self.stack.fault("offline", address=TABLE[short].address, on=False)

    def do_collide(self) -> None:
        seconds = self.rng.uniform(2.0, 4.0)
        self.log(f"both hands to {MEETING_POINT} for {seconds:.2f} s, then apart")
        legacy_write(self.meeting, {n: mds.MDS_REF_MODE_REF for n in self.meeting})
        time.sleep(seconds)
        legacy_write({n: q for n, q in HOME_POSE.items() if n in self.meeting})

    def do_home(self) -> None:
        short = self.joint()
        self.log(f"HOME {short}")
        launcher.send_command(mds.MDS_CMD_HOME, TABLE[short].address)

    def do_busoff(self) -> None:
        seconds = self.rng.uniform(0.5, 2.0)
        self.log(f"bus-off for {seconds:.2f} s, then mds-ach resetbus")
        self.stack.fault("bus_off")
        time.sleep(seconds)
        proc = cli("resetbus")
        if proc.returncode != 0:
            self.result.problems.append(f"mds-ach resetbus: {proc.stdout}{proc.stderr}")


def run(seed: int, seconds: float, rt: Path, rate: float = 10.0, out: Callable[[str], None] = print,
        hogs: int = 0, hog_fraction: float = 0.5, rt_priority: int | None = None) -> Result:
    """Start the stack in ``rt``, run the scenario, stop the stack; the daemon's CAN logs are in the result."""
    stack = Stack(rt, rate, rt_priority)
    out(f"adversary: seed {seed}, {seconds:g} s of scenario, daemon {rate:g} Hz"
        + (f", {hogs} CPU hogs for the last {hog_fraction:.0%}" if hogs else "") + f", runtime dir {rt}")
    try:
        stack.start()
        result = Adversary(stack, seed, seconds, out, hogs, hog_fraction).run()
        dead = [n for n in NODES if stack.pid(n) is None]
        if dead:
            result.problems.append(f"not running at the end: {', '.join(dead)}")
    finally:
        stack.stop()
    result.can_logs = list(stack.can_logs)
    return result


def audit(result: Result, collisions: bool = True) -> checklog.Report:
    model = checklog.collision_model() if collisions else None
    return checklog.audit(result.can_logs, TABLE, model=model, whole_run=True)  # each log: one daemon from its start


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.adversary", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="scenario length (default 10)")
    ap.add_argument("--seed", type=int, help="random seed (default: a fresh one, printed)")
    ap.add_argument("--rate", type=float, default=10.0, help="daemon loop rate in Hz (default 10, the daemon's)")
    ap.add_argument("--hogs", type=int, default=0, help="CPU hogs (busy-loop processes) for the overload phase "
                                                       "(default 0: none; make soak: 3)")
    ap.add_argument("--hog-fraction", type=float, default=0.5,
                    help="the last fraction of the scenario that runs beside the hogs (default 0.5)")
    ap.add_argument("--rt-priority", type=int, help="the daemon's --rt-priority (default: the daemon's own, "
                                                    "SCHED_FIFO 50 where allowed; 0 measures it without)")
    ap.add_argument("--allow-host-shm", action="store_true",
                    help="run even outside tools/netns-run (it creates and removes the real MDS channels!)")
    args = ap.parse_args(argv)
    if os.environ.get("MDS_NETNS_ACTIVE") != "1" and not args.allow_host_shm:
        print("bench.adversary: run it through tools/netns-run (make soak): it uses the real channel names",
              file=sys.stderr)
        return 2
    if args.hogs < 0 or not 0 < args.hog_fraction <= 1 or not args.minutes > 0:
        print("bench.adversary: --minutes > 0, --hogs >= 0, 0 < --hog-fraction <= 1", file=sys.stderr)
        return 2
    seed = args.seed if args.seed is not None else random.SystemRandom().randrange(2**32)
    rt = Path(tempfile.mkdtemp(prefix="mds-adversary-"))
    os.environ["MDS_ACH_RUNTIME_DIR"] = str(rt)
    os.environ.setdefault("MDS_ACH_CONFIG_DIR", str(rt / "config"))
    try:
        result = run(seed, args.minutes * 60.0, rt, args.rate, hogs=args.hogs, hog_fraction=args.hog_fraction,
                     rt_priority=args.rt_priority)
    finally:
        cli("killall")  # the channels too: the next run starts clean
    report = audit(result)
    print("\nactions: " + ", ".join(f"{k} {n}" for k, n in sorted(result.counts.items())))
    print(checklog.format_report(report, TABLE, max_listed=50))
    for p in result.problems:
        print(f"problem: {p}")
    stall = f"; {result.overload.line(args.rate)}" if result.overload is not None else ""
    if report.exit_code or result.problems:
        print(f"ADVERSARY FAILED at {args.rate:g} Hz (seed {seed}; repeat with --seed {seed}): "
              f"{len(report.findings)} violation(s){stall}")
        return 1
    print(f"ADVERSARY PASSED at {args.rate:g} Hz: {len(result.actions)} actions, no violation in "
          f"{len(result.can_logs)} CAN log(s){stall}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
