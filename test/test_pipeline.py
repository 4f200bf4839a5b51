"""The whole reference pipeline on the simulated robot: daemon --nocan, mux, filter, collision gate and IK, each
its own process started by its console script (= `ros2 run mds_ach <exe>`).

* an IK request moves the simulated hand to the target smoothly, without collisions, within the expected time;
* killing the filter or the collision gate freezes the robot at its last reference (zero-order hold at the
  daemon); killing the mux lets the filter finish the last mux reference and then holds;
* restarting the node resumes without a jump.

"Smooth / no jump": between two consecutive mds-state frames no joint reference moves faster than the
gate's speed bound allows; "frozen": the daemon's reference does not change at all. Whatever a test did, every
MOVETO in the daemon's CAN log obeys the motion bounds (``motion_audit``).
"""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import VENV_BIN, in_netns, wait_for
from motion_audit import audit, read_log

import mds_ach as mds
from mds_ach import ach, config
from mds_ach import daemon_status as ds
from mds_ach.channels import StructChannel
from mds_ach.collision import load_model
from mds_ach.ik_msgs import IK_SOLVED, MDS_IK_STATUS
from mds_ach.joints import BY_SHORT, LEFT_ARM, MODEL_JOINTS
from mds_ach.kinematics import arm_kinematics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LEFT = np.array([BY_SHORT[n].address for n in LEFT_ARM])
MODEL = np.array([BY_SHORT[n].address for n in MODEL_JOINTS])
FILTER_SPEED = 1.57  # rad/s, config/filter.yaml default
GATE_SPEED = 2.0  # rad/s, config/collision.yaml max_velocity
START_TIMEOUT = 90.0  # s: cold imports on a shared 2-core machine
READY_LINES = {"ik": "waiting for requests"}


class System:
    """The pipeline processes, their logs, and readers of the channels the test watches."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.procs: dict[str, subprocess.Popen] = {}
        self.state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        self.collide = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
        self.ik_req = StructChannel(mds.MDS_CHAN_IK_NAME, mds.MDS_IK)
        self.ik_state = StructChannel(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS)
        self.model = load_model()
        self.collide_flags: list[int] = []
        self.trace: list[tuple[float, np.ndarray, np.ndarray]] = []  # (state.time, ref[100], pos[100])
        self.seq = 0

    # ----- processes

    def start(self, name: str, *args: str) -> None:
        log = open(self.logs / f"{name}.log", "a")  # noqa: SIM115 - closed with the process
        log.write(f"--- start {name} {' '.join(args)}\n")
        log.flush()
        ready = {"mux": mds.MDS_CHAN_MUX_STATE_NAME, "filter": mds.MDS_CHAN_REF_SMOOTH_NAME,
                 "collision": mds.MDS_CHAN_COLLIDE_NAME, "daemon": mds.MDS_CHAN_STATE_NAME}.get(name)
        watch = ach.Channel(ready, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE) if ready else None
        if watch is not None:
            watch.flush()
        buf = bytearray(watch.data_size if watch is not None else 0)
        frames = 0
        self.procs[name] = subprocess.Popen([str(VENV_BIN / name), *args], stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + START_TIMEOUT
        while True:
            assert self.procs[name].poll() is None, f"{name} exited:\n{self.log_text(name)}"
            if watch is not None:
                status, _ = watch.get(buf, last=True)
                frames += status in (ach.ACH_OK, ach.ACH_MISSED_FRAME)
                if frames >= 2:  # two new frames of the node's periodic output
                    watch.close()
                    return
            elif READY_LINES[name] in self.log_text(name).rsplit("--- start", 1)[-1]:
                return
            assert time.monotonic() < deadline, f"{name} not up after {START_TIMEOUT} s:\n{self.log_text(name)}"
            time.sleep(0.05)

    def kill(self, name: str, sig: int) -> None:
        """Stop a node with ``sig`` and wait for it to be gone."""
        proc = self.procs.pop(name)
        proc.send_signal(sig)
        proc.wait(20)

    def stop_all(self) -> dict[str, int]:
        codes = {}
        for name in [n for n in self.procs if n != "daemon"] + ["daemon"]:
            proc = self.procs.get(name)
            if proc is None:
                continue
            proc.send_signal(signal.SIGTERM)
            try:
                codes[name] = proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = -9
        self.procs.clear()
        return codes

    def log_text(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    # ----- observation

    def frame(self, timeout: float = 5.0) -> tuple[float, np.ndarray, np.ndarray]:
        """The next mds-state frame (ref and measured pos by address), also checked for collisions."""
        st = self.state.wait(timeout)
        assert st is not None, "no mds-state frame: is the daemon alive?"
        ref = np.array([st.joint[a].ref for a in range(mds.MDS_JOINT_COUNT)])
        pos = np.array([st.joint[a].pos for a in range(mds.MDS_JOINT_COUNT)])
        c = self.collide.latest()
        if c is not None:
            self.collide_flags.append(int(c.isCollide))
        assert not self.model.check(self.model.q_from_ref(ref)).collides, "the daemon commands a collision"
        self.trace.append((st.time, ref, pos))
        return st.time, ref, pos

    def follow(self, until, timeout: float) -> np.ndarray:
        """Read state frames until ``until(ref, pos)``; returns the last ref. Fails after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while True:
            _, ref, pos = self.frame()
            if until(ref, pos):
                return ref
            assert time.monotonic() < deadline, f"condition not met within {timeout} s; ref {ref[LEFT]}"

    def ik(self, point: np.ndarray) -> np.ndarray:
        """Ask the IK node to put the left tool point at ``point``; returns the solution's six joint values."""
        self.ik_state.flush()
        req = mds.MDS_IK()
        req.move = mds.LEFT
        arm = req.arm[mds.LEFT]
        arm.t_x, arm.t_y, arm.t_z = (float(v) for v in point)
        arm.ik_method = 3
        self.ik_req.put(req)
        deadline = time.monotonic() + 30
        while True:
            st = self.ik_state.wait(1.0)
            if st is not None:
                assert st.status == IK_SOLVED, bytes(st.message)
                return np.array(st.q[:])
            assert time.monotonic() < deadline, f"no IK answer:\n{self.log_text('ik')}"

    def close(self) -> None:
        for ch in (self.state, self.collide, self.ik_req, self.ik_state):
            ch.close()


SAMPLING_SLACK = 0.05  # s: the daemon samples mds-ref at a slightly different point of each cycle than it stamps


def assert_smooth(trace: list[tuple[float, np.ndarray, np.ndarray]], what: str) -> None:
    """No modelled joint's reference moves faster than the gate's bound between consecutive state frames
    (a jump would be the whole remaining distance, up to 1.5 rad here)."""
    for (t0, r0, _), (t1, r1, _) in zip(trace, trace[1:], strict=False):
        step = np.abs(r1[MODEL] - r0[MODEL]).max()
        assert step <= GATE_SPEED * (t1 - t0 + SAMPLING_SLACK), f"{what}: jump of {step:.3f} rad in {t1 - t0:.3f} s"


def assert_frozen(system: System, seconds: float, what: str) -> np.ndarray:
    system.frame()
    _, held, _ = system.frame()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        _, ref, _ = system.frame()
        assert np.array_equal(ref, held), f"{what}: the reference moved ({np.abs(ref - held).max():.4f} rad)"
    return held


@pytest.fixture
def system(clean_shm: None, tmp_path: Path):
    assert in_netns(), "run through tools/netns-run"
    s = System(tmp_path)
    can_log = tmp_path / "can.asc"
    try:
        s.start("daemon", "--nocan", "--can-log", str(can_log))
        for name in ("collision", "filter", "mux", "ik"):  # any order works; this one is the least obvious
            s.start(name)
        yield s
    finally:
        codes = s.stop_all()
        s.close()
    bad = {n: c for n, c in codes.items() if c != 0}
    assert not bad, f"unclean exits {bad}:\n" + "\n".join(s.log_text(n)[-3000:] for n in bad)
    table = config.load()
    result = audit(read_log(str(can_log)), table, table.motion_bounds(mds.MDS_LOOP_PERIOD), 3.5 * mds.MDS_LOOP_PERIOD)
    assert result.violations == [], result.violations


def test_ik_moves_the_hand_smoothly_and_nodes_can_die_and_come_back(system: System) -> None:
    # Nodes are killed with SIGTERM. A SIGKILL of a node blocked in an Ach wait can currently wedge that
    # channel's condvar for the next waiter (mds_ach.ach; reported), so a crash is not tested here yet.
    sig = signal.SIGTERM
    s = system
    _, home, _ = s.frame()
    kin = arm_kinematics("left")
    # left tool points (robot frame) far enough apart that each move takes about a second at 1.57 rad/s
    targets = [np.array(p) for p in ((0.20, 0.45, -0.45), (0.50, 0.45, 0.20), (0.15, 0.60, -0.40),
                                     (0.35, 0.55, 0.25), (0.30, 0.30, -0.30))]

    # 1. an IK request reaches the target smoothly, without collisions, in the expected time
    q = s.ik(targets[0])
    distance = np.abs(q - home[LEFT]).max()
    t0 = time.monotonic()
    s.trace.clear()
    s.follow(lambda ref, pos: np.abs(ref[LEFT] - q).max() < 1e-9, timeout=distance / FILTER_SPEED + 3.0)
    s.follow(lambda ref, pos: np.abs(pos[LEFT] - q).max() < 0.01, timeout=5.0)
    elapsed = time.monotonic() - t0
    assert elapsed <= distance / FILTER_SPEED + 5.0
    _, tool = kin.fk(s.trace[-1][2][LEFT])  # measured joints -> hand position
    assert np.linalg.norm(tool - targets[0]) < 0.02
    assert_smooth(s.trace, "IK move")
    assert s.collide_flags and not any(s.collide_flags)

    # 2. filter and collision gate: killed mid-move -> frozen; restarted -> the move resumes without a jump
    for k, name in enumerate(("filter", "collision")):
        start = s.frame()[1]
        q = s.ik(targets[k + 1])
        s.follow(lambda ref, pos, start=start: np.abs(ref[LEFT] - start[LEFT]).max() > 0.05, timeout=10)
        s.kill(name, sig)
        held = assert_frozen(s, 1.5, f"{name} killed")
        assert np.abs(held[LEFT] - q).max() > 0.02, "the move had already finished: nothing to resume"
        s.trace.clear()
        s.start(name)
        s.follow(lambda ref, pos, q=q: np.abs(ref[LEFT] - q).max() < 1e-9, timeout=15)
        assert_smooth(s.trace, f"{name} restarted")

    # 3. mux: killed mid-move -> the filter finishes the last mux reference, then everything holds;
    #    restarted -> starts from the current reference (no jump) and takes new requests
    start = s.frame()[1]
    q = s.ik(targets[3])
    s.follow(lambda ref, pos: np.abs(ref[LEFT] - start[LEFT]).max() > 0.05, timeout=10)
    s.kill("mux", sig)
    s.trace.clear()
    s.follow(lambda ref, pos: np.abs(ref[LEFT] - q).max() < 1e-9, timeout=15)
    held = assert_frozen(s, 1.0, "mux killed")
    s.start("mux")
    assert_frozen(s, 1.0, "mux restarted")
    assert np.array_equal(s.frame()[1], held)
    q = s.ik(targets[4])
    s.follow(lambda ref, pos: np.abs(ref[LEFT] - q).max() < 1e-9, timeout=15)
    assert_smooth(s.trace, "mux killed and restarted")
    assert not any(s.collide_flags)


def goto(**targets: float) -> None:
    """What `mds-ach console` goto does: read-modify-write of mds-ref-filter (the mux's legacy input)."""
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF) as ch:
        frame = ch.latest()
        assert frame is not None, "the mux did not seed mds-ref-filter"
        for short, value in targets.items():
            frame.joint[BY_SHORT[short].address].ref = value
        ch.put(frame)


def test_home_then_a_small_goto_starts_from_home(system: System) -> None:
    """HOME through mds-cmd while the pipeline's reference for LEP is elsewhere: once LEP is homed every stage
    restarts it at home (mds-daemon-status joint_reseed), so a small goto from home moves it from home to the
    goal, never back via the old reference (which used to make the daemon step 0.4 rad)."""
    s = system
    lep = BY_SHORT["LEP"].address
    home = config.load()["LEP"].home
    goto(LEP=-0.6)
    s.follow(lambda ref, pos: abs(pos[lep] - -0.6) < 1e-3, timeout=20)
    with StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, mds.MDS_CMD) as cmd:
        cmd.put(mds.MDS_CMD(seq=1, cmd=mds.MDS_CMD_HOME, address=lep))
    s.follow(lambda ref, pos: abs(pos[lep] - home) < 1e-6 and abs(ref[lep] - home) < 1e-6, timeout=30)
    with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS) as status, \
            StructChannel(mds.MDS_CHAN_REF_NAME, mds.MDS_REF) as daemon_input:
        wait_for(lambda: (st := status.latest()) is not None and st.joint_reseed[lep] == 1, 10, what="the re-seed")
        wait_for(lambda: (f := daemon_input.latest()) is not None and abs(f.joint[lep].ref - home) < 1e-9, 10,
                 what="mds-ref re-seeded at home")
    s.trace.clear()
    goto(LEP=home + 0.05)
    s.follow(lambda ref, pos: abs(pos[lep] - (home + 0.05)) < 1e-4, timeout=20)
    refs = [ref[lep] for _, ref, _ in s.trace]
    assert all(home - 1e-6 <= q <= home + 0.05 + 1e-6 for q in refs), f"LEP went elsewhere: {min(refs)}..{max(refs)}"
