"""The one daemon rig: ``DaemonLoop`` on a simulated clock and a simulated MDS bus, through the real Ach
channels, with client handles on every channel the daemon reads or writes.

A second of robot time costs milliseconds and every assertion is about behaviour, never timing. Two ways to
drive it: ``step(n)`` runs cycles and leaves the references to the test (``put_ref``); ``run(seconds)`` also
plays a client that moves the arms and neck every cycle (sinusoids around where they started) and records
every state, for the fault and fuzz tests (``DaemonRig.moving()`` starts one with the arms bent and moving).
Every frame on the bus is stamped with the simulated time (``log``) for the motion audit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import mds_ach as mds
from mds_ach.bus import canio, mcb
from mds_ach.bus.mcb import Command, StateArg
from mds_ach.bus.simbus import ManualClock, SimNetwork
from mds_ach.nodes.daemon_loop import DaemonChannels, DaemonLoop
from mds_ach.robot import config
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_CMD, MDS_COLLIDE, MDS_REF, MDS_STATE
from mds_ach.robot.msgs import daemon_status as ds

from .channels import Newest
from .motion_audit import Audit, MemoryLog, audit

TABLE = config.load("default")
MOVING = ("LSP", "LEP", "LWY", "RSP", "REP", "NKY")  # arms and neck, commanded every cycle by run()
AMPLITUDE = 0.15  # rad
MOTION_PERIOD = 4.0  # s
ARMS_BENT = {"LEP": -1.0, "REP": -1.0, "LSP": -0.3, "RSP": -0.3}  # room to move both ways


class DaemonRig:
    """A daemon loop on a simulated clock, its simulated robot, and client handles on the channels."""

    def __init__(self, rate: float = 10.0, pose: dict[str, float] | None = None, bitrate: int | None = 1_000_000,
                 **loop_kwargs: object) -> None:
        self.clock = ManualClock()
        self.net = SimNetwork.from_table(TABLE, pose=pose, clock=self.clock, bitrate=bitrate)
        self.io = canio.make_canio(nocan=True, network=self.net)
        self.log = MemoryLog(self.clock, self.io.wall_offset)
        self.io.recorder = self.log  # every frame, stamped with the simulated time, for the motion audit
        self.channels = DaemonChannels.open()
        self.loop = DaemonLoop(TABLE, self.io, self.channels, rate_hz=rate, nocan=True, clock=self.clock,
                               **loop_kwargs)
        self.ref_out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, MDS_REF)
        self.state_in = Newest(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
        self.status_in = StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
        self.collide_out = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, MDS_COLLIDE)
        self.cmd_out = StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD)
        self.cmd_seq = 0
        self.centre: dict[str, float] = {}  # run(): where each MOVING joint's sinusoid is centred
        self.states: list[MDS_STATE] = []  # run(): the state after every cycle
        self.t = 0.0  # run(): robot time of the client's motion

    @classmethod
    def moving(cls, rate: float = 10.0) -> DaemonRig:
        """Started up with the arms bent (``ARMS_BENT``), ready for ``run()`` to move them."""
        rig = cls(rate=rate, pose=ARMS_BENT)
        rig.loop.start_up()
        rig.centre = {s: rig.loop.state.joint[TABLE[s].address].ref for s in MOVING}
        return rig

    def close(self) -> None:
        self.loop.stop()
        self.io.close()
        self.channels.close()
        for ch in (self.ref_out, self.state_in, self.status_in, self.collide_out, self.cmd_out):
            ch.close()

    # ----- driving

    def step(self, n: int = 1) -> MDS_STATE:
        """``n`` cycles on the simulated clock; the newest mds-state a client sees."""
        for _ in range(n):
            self._cycle()
        return self.state()

    def _cycle(self) -> None:
        start = self.clock.now
        self.loop.cycle(deadline=start, start=start)
        self.clock.now = max(self.clock.now, start + self.loop.period)

    def target(self, short: str, t: float) -> float:
        """Where run()'s client commands a MOVING joint at robot time ``t``."""
        j = TABLE[short]
        return j.clamp(self.centre[short] + AMPLITUDE * math.sin(2 * math.pi * t / MOTION_PERIOD))

    def run(self, seconds: float, inject: Callable[[DaemonRig], None] | None = None, move: bool = True,
            mode: int = mds.MDS_REF_MODE_REF) -> None:
        """Run ``seconds`` of robot time; with ``move`` one mds-ref-gated frame per cycle moves the arms (``mode``
        for the moving joints, pass-through by default; the others hold their reference). ``inject`` runs before each
        cycle (a fault on the bus)."""
        for _ in range(max(1, round(seconds / self.loop.period))):
            if move:
                ref = MDS_REF()
                for j in TABLE:
                    r = self.loop.state.joint[j.address].ref_r
                    ref.joint[j.address].ref = r if math.isfinite(r) else self.loop.state.joint[j.address].ref
                    ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
                for s in MOVING:
                    ref.joint[TABLE[s].address].ref = self.target(s, self.t)
                    ref.joint[TABLE[s].address].mode = mode
                self.ref_out.put(ref)
            if inject is not None:
                inject(self)
            self._cycle()
            self.t += self.loop.period
            self.states.append(MDS_STATE.from_buffer_copy(self.loop.state))

    def put_ref(self, mode: int = mds.MDS_REF_MODE_REF, **refs: float) -> None:
        """Like a client: start from what the daemon commands now, change some joints."""
        ref = MDS_REF()
        st = self.loop.state
        for j in TABLE:
            ref.joint[j.address].ref = st.joint[j.address].ref
            ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
        for short, value in refs.items():
            ref.joint[TABLE[short].address].ref = value
            ref.joint[TABLE[short].address].mode = mode
        self.ref_out.put(ref)

    def command(self, code: int, address: int = 0, seq: int | None = None) -> None:
        """An mds-cmd frame; ``seq`` defaults to one more than the last command's."""
        self.cmd_seq = self.cmd_seq + 1 if seq is None else seq
        self.cmd_out.put(MDS_CMD(seq=self.cmd_seq, cmd=code, address=address))

    # ----- observation

    def state(self) -> MDS_STATE:
        """The newest mds-state a client sees (the last one again if nothing new was published)."""
        return self.state_in.require()

    def status(self) -> ds.MDS_DAEMON_STATUS:
        """The newest mds-daemon-status frame, else the loop's own (not yet published) status."""
        frame = self.status_in.latest()
        return frame if frame is not None else ds.MDS_DAEMON_STATUS.from_buffer_copy(self.loop.status)

    def frames_to(self, address: int) -> list[mcb.McbFrame]:
        return [f for _, f in self.net.commands if f.arbitration_id == address]

    def measured(self, short: str) -> float:
        """The joint's physical position on the simulated robot (rad)."""
        j = TABLE[short]
        return j.to_joint(self.net.position(j.address))

    def pos(self, short: str) -> float:
        """The position the daemon reports."""
        return self.loop.state.joint[TABLE[short].address].pos

    def travel(self, short: str, since: int) -> float:
        """How far the joint's measured position moved over the states run() recorded since index ``since``."""
        a = TABLE[short].address
        values = [s.joint[a].pos for s in self.states[since:] if s.joint[a].active]
        return max(values) - min(values) if values else 0.0

    def audit(self) -> Audit:
        """Every MOVETO so far against the motion bounds (``mds-ach check-log``'s audit of a whole daemon run)."""
        return audit(self.log.frames, TABLE, self.loop.bounds, self.loop.stale_after)

    def targets(self, short: str) -> list[float]:
        """The MOVETO targets the joint was sent (rad)."""
        return [q for _, q in self.audit().targets[short]]


def counts_range(j: config.JointConfig) -> tuple[float, float]:
    a, b = j.to_counts(j.lower), j.to_counts(j.upper)
    return min(a, b), max(a, b)


def unsafe_commands(sent: list[tuple[float, mcb.McbFrame]]) -> list[str]:
    """Every frame on the bus that could move a joint somewhere it must not go: a MOVETO (or SET_TARGET) outside the
    joint's limits in counts, not finite, or addressed to a joint that is disabled or not in the table."""
    bad = []
    for _, f in sent:
        target = (f.command == Command.SET and f.argument == StateArg.MOVETO_TARGET) or f.command == Command.SET_TARGET
        if not target:
            continue
        j = TABLE.get(f.arbitration_id)
        if j is None or not j.enabled:
            bad.append(f"{f} to a joint that is not enabled")
            continue
        lo, hi = counts_range(j)
        if not (math.isfinite(f.value) and lo - 0.5 <= f.value <= hi + 0.5):
            bad.append(f"{f}: {j.short} limits are [{lo:.1f}, {hi:.1f}] counts")
    return bad
