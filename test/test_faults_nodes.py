"""Fault injection on the running system (daemon --nocan, mux, filter, collision gate, IK, bridge; each its own
process): SIGKILL each node while the arms move. The daemon holds the last safe reference, the state stream goes
on, and restarting the node resumes the motion without a jump. A writer killed inside a put on a pipeline
channel is reported and repaired with ``mds-ach repair`` while everything keeps running. Every daemon's CAN log
obeys the motion bounds.
"""


from __future__ import annotations

import ctypes
import math
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from support import in_netns, remove_mds_channels, wait_for
from support.faults import PUT_STAGES, StuckWriter
from support.motion_audit import audit, read_log
from support.rig import TABLE, unsafe_commands
from support.system import HEARTBEATS, START_TIMEOUT, mds_ach, wait_heartbeat

import mds_ach as mds
from mds_ach import ach
from mds_ach.bus import mcb
from mds_ach.bus.mcb import StateArg
from mds_ach.robot.channels import StructChannel, make_channels, replaced
from mds_ach.robot.msgs import MDS_DAEMON_STATUS, MDS_REF, MDS_STATE
from mds_ach.tools import launcher, repair

# ============================================================================================ 3. the running system

# Kill order: the filter and the daemon wait on no channel; the others block in get(wait=True) when killed.
NODES = ("filter", "mux", "collision", "ik", "bridge")
SYSTEM_MOVING = ("LSP", "LEP", "RSP", "REP")  # driven through mds-ref-filter (the mux's default input)
SYSTEM_AMPLITUDE = 0.2  # rad
SYSTEM_PERIOD = 3.0  # s: at most 0.42 rad/s, well inside the filter's 1.57 rad/s
GATE_SPEED = 2.0  # rad/s, config/collision.yaml max_velocity: no reference may move faster
MODEL = [mds.BY_SHORT[n].address for n in mds.joints.MODEL_JOINTS]


def bounded(fn: Callable[[], object], timeout: float, what: str) -> object:
    """Run ``fn`` on a helper thread; fail (instead of hanging the test run) if it does not return in time. Ach
    calls from this process go through here when a killed node may have wedged the channel."""
    result: list[object] = []
    error: list[BaseException] = []

    def body() -> None:
        try:
            result.append(fn())
        except BaseException as exc:  # handed to the test thread
            error.append(exc)

    t = threading.Thread(target=body, name=what, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"{what} hangs (more than {timeout:g} s)"
    if error:
        raise error[0]
    return result[0] if result else None


class Driver:
    """A legacy client moving both arms: read-modify-write of mds-ref-filter at 20 Hz (sinusoids around the pose
    the mux seeded). Put errors (a corrupt channel) are counted and retried, as a careful client would."""

    def __init__(self) -> None:
        with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, MDS_REF) as seeded:
            base = seeded.latest()
        assert base is not None, "the mux did not seed mds-ref-filter"
        self.base = base
        self.centre = {s: TABLE[s].clamp(base.joint[TABLE[s].address].ref) for s in SYSTEM_MOVING}
        self.chan = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False)
        self.errors = 0
        self.puts = 0
        self.last_put = time.monotonic()
        self.phase = 0.0
        self.offset = 0.0  # added to every target (to move the commanded pose away from where the robot is)
        self.frozen: float | None = None  # hold the sinusoid at this phase
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="driver", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self._stop.wait(0.05):
            frame = MDS_REF.from_buffer_copy(self.base)
            phase = math.sin(2 * math.pi * (time.monotonic() - t0) / SYSTEM_PERIOD)
            if self.frozen is not None:
                phase = self.frozen
            self.phase = phase
            for s in SYSTEM_MOVING:
                target = self.centre[s] + SYSTEM_AMPLITUDE * phase + self.offset
                frame.joint[TABLE[s].address].ref = TABLE[s].clamp(target)
            try:
                self.chan.put(frame)
                self.puts += 1
            except ach.AchException:
                self.errors += 1
                if replaced(self.chan):  # `mds-ach repair` re-created it: a careful client re-opens it
                    old, self.chan = self.chan, ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False)
                    old.close()
            self.last_put = time.monotonic()

    @property
    def stuck(self) -> bool:
        """Its put has not returned for two seconds: the channel is wedged (or a lock is held)."""
        return time.monotonic() - self.last_put > 2.0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        if not self._thread.is_alive():  # a put stuck in the channel: leave the handle to the process exit
            self.chan.close()


@dataclass
class Frame:
    received: float  # time.monotonic() at receipt
    time: float  # state.time
    ref: np.ndarray  # by address
    pos: np.ndarray


class Recorder:
    """Every mds-state frame, with its receipt time, from a background thread (it polls: it can never hang on a
    wedged channel)."""

    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._chan = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                st = self._chan.latest()  # polled: a blocking wait could hang on a condvar wedged by a killed node
            except ach.AchException:  # a damaged mds-state: nothing to record until it is repaired (re-opened)
                st = None
            if st is None:
                time.sleep(0.005)
            else:
                ref = np.array([st.joint[a].ref for a in range(mds.MDS_JOINT_COUNT)])
                pos = np.array([st.joint[a].pos for a in range(mds.MDS_JOINT_COUNT)])
                with self._lock:
                    self.frames.append(Frame(time.monotonic(), st.time, ref, pos))

    def mark(self) -> int:
        with self._lock:
            return len(self.frames)

    def since(self, mark: int) -> list[Frame]:
        with self._lock:
            return self.frames[mark:]

    def last(self) -> Frame:
        wait_for(lambda: self.mark() > 0, 10, what="an mds-state frame")
        with self._lock:
            return self.frames[-1]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._chan.close()


def travel(frames: list[Frame], short: str) -> float:
    a = TABLE[short].address
    values = [f.ref[a] for f in frames]
    return max(values) - min(values) if values else 0.0


def assert_no_jump(frames: list[Frame], what: str) -> None:
    """Between consecutive state frames no modelled joint's reference moves faster than the gate allows, and every
    reference is inside its joint's limits.

    A state frame is stamped when it is published, after the cycle's reply window (up to half a period, shorter when
    every node answered early), while the reference changed when the targets were sent, before that window: two
    frames' stamps can be up to one reply window closer than the sends they report. The exact bound, on the bus, is
    checked from the daemon's CAN log at the end of the test (``motion_audit``: speed and acceleration)."""
    reply_window = 0.5 * mds.MDS_LOOP_PERIOD
    for f0, f1 in zip(frames, frames[1:], strict=False):
        dt = f1.time - f0.time
        step = np.abs(f1.ref[MODEL] - f0.ref[MODEL])
        k = int(np.argmax(step))
        assert step[k] <= GATE_SPEED * (dt + reply_window), \
            f"{what}: {mds.BY_ADDRESS[MODEL[k]].short} jumped {step[k]:.3f} rad in {dt:.3f} s"
    for f in frames:
        for j in TABLE.enabled:
            assert j.lower - 1e-9 <= f.ref[j.address] <= j.upper + 1e-9, f"{what}: {j.short} ref outside its limits"


def live(channel: str, within: float = 1.5) -> bool:
    """Does someone still publish on ``channel`` (a new frame within ``within`` s)? Polls without waiting on the
    channel's condvar, which a killed node may have wedged."""
    with ach.Channel(channel, create=False) as ch:
        ch.flush()
        buf = bytearray(ch.data_size)
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            if ch.get(buf)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                return True
            time.sleep(0.02)
    return False


def pipeline_lsp() -> str:
    """LSP's newest reference and mode on each pipeline channel: where a motion stops when it does not arrive (a
    channel whose lock is held is reported with the holder instead of being read)."""
    parts = []
    for name in (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME,
                 mds.MDS_CHAN_DAEMON_INPUT_NAME):
        health = repair.check(name, timeout=0.2)
        if not health.ok:
            parts.append(f"{name}: {health.state}: {health.detail}")
            continue
        frame = MDS_REF()
        with ach.Channel(name, create=False) as ch:
            status, size = ch.get(frame, last=True, copy=True)
            seq = ch.last_seq
        j = frame.joint[TABLE["LSP"].address]
        parts.append(f"{name} seq {seq}: {j.ref:.4f}/{j.mode}" if size == ctypes.sizeof(frame) else f"{name}: -")
    return "LSP " + ", ".join(parts)


class System:
    """daemon --nocan (with a CAN log), then `mds-ach start --only` the other nodes; the driver and the recorder."""

    def __init__(self, rt: Path) -> None:
        self.rt = rt
        self.can_logs: list[Path] = []
        self.driver: Driver | None = None
        self.recorder: Recorder | None = None

    def cli(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        return mds_ach(*args, timeout=timeout)

    def start(self, pose: dict[str, float] | None = None) -> None:
        assert all(r.ok for r in make_channels())
        self.start_daemon(pose)
        self.start_nodes(*NODES)
        self.recorder = Recorder()
        self.driver = Driver()
        self.moving(20)

    def start_daemon(self, pose: dict[str, float] | None = None) -> None:
        log = self.rt / f"can-{len(self.can_logs) + 1}.asc"
        self.can_logs.append(log)
        args = ["--nocan", "--can-log", str(log)]
        if pose:
            args += ["--sim-pose", ",".join(f"{k}={v:.6f}" for k, v in pose.items())]
        watch = ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
        watch.flush()
        proc = launcher.start_node("daemon", args, self.rt)
        wait_heartbeat(mds.MDS_CHAN_STATE_NAME, lambda: proc.poll() is None,
                       lambda: launcher.log_tail("daemon", rt=self.rt), "daemon", flushed=watch)

    def start_nodes(self, *names: str) -> None:
        proc = self.cli("start", "--only", *names, "--timeout", str(START_TIMEOUT), timeout=START_TIMEOUT + 30)
        assert proc.returncode == 0, f"mds-ach start --only {' '.join(names)}:\n{proc.stdout}\n{proc.stderr}"

    def pid(self, name: str) -> int | None:
        return launcher.read_pid(name, self.rt)

    def kill(self, name: str) -> None:
        pid = self.pid(name)
        assert pid is not None, f"{name} is not running"
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: self.pid(name) is None, 10, what=f"{name} to die")

    def log(self, name: str) -> str:
        path = launcher.log_path(name, self.rt)
        return path.read_text(errors="replace") if path.exists() else ""

    def moving(self, timeout: float = 10.0) -> None:
        """Wait until the arms are seen moving (the driver's motion reaches the daemon)."""
        mark = self.recorder.mark()
        deadline = time.monotonic() + timeout
        while travel(self.recorder.since(mark), "LSP") <= 0.05:
            if time.monotonic() > deadline:
                stuck = [n for n, ch in HEARTBEATS.items() if not live(ch)]
                raise AssertionError(f"the arms do not move within {timeout:g} s; nodes not publishing: {stuck}; "
                                     f"client put {'hangs' if self.driver.stuck else 'works'}; {pipeline_lsp()}")
            time.sleep(0.05)

    def healthy(self) -> bool:
        """Every node runs and publishes, the channels are sound, and the client's motion reaches the robot."""
        if self.driver is None or self.recorder is None:
            return False
        if not (all(self.pid(n) for n in ("daemon", *NODES)) and all(live(ch) for ch in HEARTBEATS.values())
                and not self.driver.stuck and all(r.ok for r in repair.scan())):
            return False
        try:
            self.moving(5)
        except AssertionError:
            return False
        return True

    def heal(self) -> None:
        """After a test that left the system broken (a hung node, a wedged channel), start it again from scratch
        where the robot stands, so the next test does not inherit the damage."""
        if self.healthy():
            return
        pose = self.pose()
        self.stop()
        self.start(pose)

    def pose(self) -> dict[str, float]:
        """Where the simulated joints are now (the robot stays there while its driver is down)."""
        if self.recorder is None:
            return {}
        last = self.recorder.last()
        return {n: TABLE[n].clamp(float(last.pos[mds.BY_SHORT[n].address])) for n in mds.joints.MODEL_JOINTS
                if math.isfinite(last.pos[mds.BY_SHORT[n].address]) and TABLE[n].enabled}

    def stop(self) -> None:
        for obj in (self.driver, self.recorder):
            if obj is not None:
                obj.close()
        self.driver = self.recorder = None
        self.cli("stop")
        self.cli("killall")


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:
    assert in_netns(), "run through tools/netns-run (private /dev/shm and network namespace)"
    rt = tmp_path_factory.mktemp("runtime")
    mp = pytest.MonkeyPatch()
    mp.setenv("MDS_ACH_RUNTIME_DIR", str(rt))
    mp.setenv("MDS_ACH_CONFIG_DIR", str(rt / "config"))
    mp.delenv("MDS_ACH_ROBOT", raising=False)
    remove_mds_channels()
    s = System(rt)
    try:
        s.start()
        yield s
        # Everything any daemon sent during the whole module, from its CAN logs: never outside a joint's limits.
        s.stop()
        import can

        sent = []
        for path in s.can_logs:
            for msg in can.LogReader(str(path)):
                if not msg.is_error_frame and msg.arbitration_id != mcb.HOST_SID and len(msg.data) == mcb.DLC:
                    sent.append((msg.timestamp, mcb.decode(msg.arbitration_id, bytes(msg.data))))
        # (a SIGKILLed daemon loses the tail of its log; the last one is stopped cleanly)
        assert any(f.argument == StateArg.MOVETO_TARGET for _, f in sent), "no motion was logged"
        assert unsafe_commands(sent) == []
        for path in s.can_logs:  # every daemon run on its own: each restarts from the joints' first replies
            bounded = audit(read_log(str(path)), TABLE, TABLE.motion_bounds(),
                            3.5 * mds.MDS_LOOP_PERIOD)
            assert bounded.violations == [], f"{path.name}: {bounded.violations}"
    finally:
        s.stop()
        mp.undo()
        remove_mds_channels()


@pytest.mark.ros
@pytest.mark.slow
def test_sigkill_daemon_while_the_arms_move(system: System) -> None:
    """The pipeline survives its daemon; a restarted daemon starts where the robot stands and resumes the motion
    without a jump (the simulated robot lives in the daemon's process: it is restarted where it stood)."""
    s = system
    s.moving()
    s.kill("daemon")
    pose = s.pose()
    mark = s.recorder.mark()
    # The operator's client goes on commanding while the daemon is down: the pipeline's reference moves 0.6 rad
    # away from where the robot stands (the robot cannot follow without its daemon).
    s.driver.frozen, s.driver.offset = s.driver.phase, -0.6
    time.sleep(1.5)
    try:
        assert s.recorder.since(mark) == [], "frames on mds-state without a daemon"
        assert all(s.pid(n) is not None for n in NODES), "a node died with the daemon"
        s.start_daemon(pose)
        time.sleep(1.0)
        s.driver.frozen, s.driver.offset = None, 0.0
        s.moving()
        after = s.recorder.since(mark)
        for n, q in pose.items():
            assert after[0].ref[TABLE[n].address] == pytest.approx(q, abs=1e-3), f"{n} does not start where it stands"
        assert_no_jump(after, "daemon killed and restarted")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
def test_client_killed_inside_a_put_on_a_mux_input(system: System) -> None:
    """A legacy client dies inside its put on mds-ref-filter: the mux reports the corrupt input and the robot stays
    safe; `mds-ach repair` fixes the channel in place and the client's frames move the robot again, through the same
    mux (no node restarted)."""
    s = system
    s.moving()
    mark = s.recorder.mark()
    StuckWriter(mds.MDS_CHAN_REF_FILTER_NAME, before=0, marker=PUT_STAGES["copying the data"][0]).kill()
    corrupt = s.recorder.mark()
    try:
        wait_for(lambda: s.driver.errors > 0, 5, what="the client to see ACH_CORRUPT")
        time.sleep(1.5)
        assert len(s.recorder.since(corrupt)) >= 10 and all(s.pid(n) for n in ("daemon", *NODES))
        check = s.cli("repair", "--check")
        assert check.returncode == 1
        assert [ln.split()[0] for ln in check.stderr.splitlines()] == [mds.MDS_CHAN_REF_FILTER_NAME], check.stderr
        assert "corrupt" in s.log("mux").lower(), "the mux did not report its corrupt input"
        fixed = s.cli("repair")
        assert fixed.returncode == 0 and "repaired in place" in fixed.stdout, fixed.stdout + fixed.stderr
        errors = s.driver.errors
        s.moving(timeout=10)  # the client's frames reach the robot again, through the same mux
        assert s.driver.errors == errors
        assert_no_jump(s.recorder.since(mark), "corrupt mux input repaired")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
def test_writer_killed_inside_a_put_on_the_daemon_input(system: System) -> None:
    """mds-ref-gated (collision gate -> daemon) left corrupt: the daemon keeps publishing mds-state and holds the last
    reference; `mds-ach repair`, plus `mds-ach start --only` for any node that stopped, resume the motion."""
    s = system
    s.moving()
    mark = s.recorder.mark()
    StuckWriter(mds.MDS_CHAN_DAEMON_INPUT_NAME, before=0, marker=PUT_STAGES["copying the data"][0]).kill()
    corrupt = s.recorder.mark()
    try:
        time.sleep(2.0)
        frames = s.recorder.since(corrupt)
        assert len(frames) >= 10, f"the daemon stopped publishing mds-state ({len(frames)} frames in 2 s)"
        held = [f for f in frames if f.received > frames[0].received + 0.3]
        assert held and all(np.array_equal(f.ref[MODEL], held[0].ref[MODEL]) for f in held), \
            "the reference moved while mds-ref-gated was corrupt"
        check = s.cli("repair", "--check")
        assert check.returncode == 1 and mds.MDS_CHAN_DAEMON_INPUT_NAME in check.stderr
        assert s.cli("repair").returncode == 0
        stopped = [n for n in NODES if s.pid(n) is None]
        if stopped:
            s.start_nodes(*stopped)
        s.moving()
        assert_no_jump(s.recorder.since(mark), "corrupt daemon input repaired")
    finally:
        s.heal()


# An operator may write these channels; scribbled over, each killed a node (issue 25 item 7). -> the node that
# reports it in its log.
SCRIBBLED = {
    mds.MDS_CHAN_REF_MUX_NAME: "mux",
    mds.MDS_CHAN_MUX_STATE_NAME: "mux",
    mds.MDS_CHAN_IK_NAME: "ik",
    mds.MDS_CHAN_HOLD_NAME: "ik",
    mds.MDS_CHAN_STATE_NAME: "bridge",
    mds.MDS_CHAN_BOARD_CMD_NAME: "daemon",  # the daemon lived through it already; it must read commands again
    mds.MDS_CHAN_REF_FILTER_NAME: "mux",  # a controller input
    mds.MDS_CHAN_REF_SMOOTH_NAME: "filter",  # filter -> gate: the filter holds its output meanwhile
    mds.MDS_CHAN_COLLIDE_NAME: "collision",  # gate -> daemon
}
RECOVERED = {"daemon": "re-opened it, commands are read again"}  # the daemon logs its own way (no ChannelGuard)


def scribble(name: str, offset: int = 16, count: int = 80) -> None:
    """80 bytes over the header (name, frame count) of a channel: no handle can use it, and `mds-ach repair` can
    only re-create it."""
    fd = os.open(ach.shm_path(name), os.O_RDWR)
    try:
        os.pwrite(fd, b"X" * count, offset)
    finally:
        os.close(fd)


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("channel", SCRIBBLED)
def test_a_scribbled_channel_kills_no_node_and_repair_brings_it_back(system: System, channel: str) -> None:
    """Every node lives through a channel whose header was overwritten: it reports the channel and the fix, holds,
    and after `mds-ach repair` (which re-creates the file) it re-opens the channel and works again; no restart."""
    from mds_ach.robot import lifecycle

    s = system
    s.moving()
    pids = {n: s.pid(n) for n in ("daemon", *NODES)}
    mark = s.recorder.mark()
    reporter = SCRIBBLED[channel]
    scribble(channel)
    try:
        wait_for(lambda: f"mds-ach repair {channel}" in s.log(reporter), 20,
                 what=f"{reporter} to report the damaged {channel}")
        time.sleep(1.0)  # the outage goes on for a while: nobody dies of it
        assert {n: s.pid(n) for n in pids} == pids, f"a node died of the damaged {channel}"
        check = s.cli("repair", "--check")
        assert check.returncode == 1 and channel in check.stderr and "broken" in check.stderr, check.stderr
        fixed = s.cli("repair", channel)
        assert fixed.returncode == 0 and "re-created" in fixed.stdout, fixed.stdout + fixed.stderr
        s.moving(timeout=20)  # the motion reaches the robot again, through the same processes
        again = RECOVERED.get(reporter, f"channel {channel} works again")
        wait_for(lambda: again in s.log(reporter), 20, what=f"{reporter} to say {channel} works again")
        if channel in (mds.MDS_CHAN_IK_NAME, mds.MDS_CHAN_HOLD_NAME, mds.MDS_CHAN_MUX_STATE_NAME):
            assert_ik_answers(s)
        if channel in (mds.MDS_CHAN_HOLD_NAME, mds.MDS_CHAN_MUX_STATE_NAME):  # the mux takes and answers requests
            ack = bounded(lambda: lifecycle.request(lifecycle.HOLD_RESUME, source="test", reason="after repair"),
                          30, "a RESUME through mds-hold")
            assert ack.ok, ack.message
        if channel == mds.MDS_CHAN_BOARD_CMD_NAME:  # a command is executed again (an unknown code: refused, harmless)
            seq = launcher.send_command(99)
            with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS) as status:
                wait_for(lambda: (st := status.latest()) is not None and st.cmd_seq == seq, 10,
                         what="the daemon to answer a command on the re-created mds-cmd")
        if channel == mds.MDS_CHAN_STATE_NAME:  # /joint_states flows again and a ROS command moves the robot
            bounded(lambda: assert_bridge_commands_reach_the_robot(s), 60, "a ROS command through the bridge")
        assert {n: s.pid(n) for n in pids} == pids, "a node was restarted"
        assert_no_jump(s.recorder.since(mark), f"{channel} scribbled and repaired")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("node", NODES)
def test_sigkill_node_while_the_arms_move(system: System, node: str) -> None:
    s = system
    s.moving()
    mark = s.recorder.mark()
    s.kill(node)
    time.sleep(2.0)
    dead = s.recorder.since(mark)
    try:
        assert len(dead) >= 10, f"the state stream stopped when {node} died ({len(dead)} frames in 2 s)"
        assert s.pid("daemon") is not None
        if node in ("filter", "collision"):  # the daemon holds the last reference that passed the gate
            held = [f for f in dead if f.received > dead[0].received + 0.3]
            assert all(np.array_equal(f.ref[MODEL], held[0].ref[MODEL]) for f in held), f"{node} dead, ref moved"
        elif node in ("ik", "bridge"):  # not on the driver's path: the motion goes on
            assert travel(dead, "LSP") > 0.05
        s.start_nodes(node)
        s.moving()
        if node == "ik":  # it answers requests again
            assert_ik_answers(s)
        if node == "bridge":
            bounded(lambda: assert_bridge_commands_reach_the_robot(s), 60, "a ROS command through the bridge")
        assert_no_jump(s.recorder.since(mark), f"{node} killed and restarted")
    finally:
        s.heal()


def assert_ik_answers(s: System) -> None:
    from mds_ach.nodes.ik_client import IkClient
    from mds_ach.tools.console import fk_pose

    last = s.recorder.last()
    q = [last.ref[mds.BY_SHORT[n].address] for n in mds.joints.LEFT_ARM]
    pos, _ = fk_pose(q, "left")

    def ask() -> object:
        with IkClient() as client:
            return client.request("left", 3, [pos[0], pos[1], pos[2] + 0.02], timeout=30)

    reply = bounded(ask, 40, "an IK request")
    assert reply.success, reply.message


def assert_bridge_commands_reach_the_robot(s: System) -> None:
    """A ROS JointState command on mds/joint_command moves the neck (no one else commands it)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    nky = TABLE["NKY"]
    # A goal away from where NKY is and from the bridge's newest frame: a mux restarted since (heal) took that
    # frame as already seen, so the same value again would not be a command.
    with StructChannel(mds.MDS_CHAN_REF_ROS_NAME, MDS_REF) as ros:
        newest = ros.latest()
    before = [s.recorder.last().ref[nky.address], math.nan if newest is None else newest.joint[nky.address].ref]
    goal = next(g for g in map(nky.clamp, (0.25, -0.05, 0.1)) if all(not abs(g - v) < 0.05 for v in before))
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("fault_test_client", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        states: list[JointState] = []
        node.create_subscription(JointState, "joint_states", states.append, qos_profile_sensor_data)
        pub = node.create_publisher(JointState, "mds/joint_command", 10)
        deadline = time.monotonic() + 30
        while not (states and pub.get_subscription_count() > 0):
            assert time.monotonic() < deadline, "the restarted bridge does not publish joint_states / subscribe"
            executor.spin_once(timeout_sec=0.1)
        pub.publish(JointState(name=["NKY"], position=[goal]))
        deadline = time.monotonic() + 15
        while abs(s.recorder.last().ref[nky.address] - goal) > 1e-6:
            assert time.monotonic() < deadline, "the bridge's command did not reach the daemon"
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


