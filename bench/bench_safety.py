"""Safe near people (issue #31): the collaborative mode's Cartesian bound and the category-1 e-stop, measured on the
simulated robot (the daemon loop on a simulated clock and bus, through the real Ach channels in a private /dev/shm).

* the hands' and elbows' fastest speed between sends in collaborative mode under an adversarial reference (every
  upper-body joint commanded to a random far pose each cycle, and a fast trajectory), audited by ``mds-ach
  check-log``'s audit (FK on the sent targets): bound <= 250 mm/s, 0 violations; the same in normal mode as the
  baseline;
* the planning's CPU cost per cycle in collaborative mode (wall time, this machine);
* the e-stop with the left arm at full joint speed: time and distance until the sent targets stand still, until the
  simulated joints stand still (they follow at the MCB's own MOVETO acceleration), and the latency from the command
  to the first braking target and to the first DISABLE on the bus.

Usage: python -m bench.bench_safety [--quick]   (re-runs itself in tools/netns-run)
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from bench.common import Row

REPO = Path(__file__).resolve().parents[1]
GROUP = "safety"


class _Rig:
    """The daemon loop on a simulated clock and bus (what test/support/rig.py does, without the test helpers)."""

    def __init__(self, rate: float, pose: dict[str, float], ideal: bool) -> None:
        import mds_ach as mds
        from mds_ach.bus import canio
        from mds_ach.bus.simbus import ManualClock, SimNetwork
        from mds_ach.nodes.daemon_loop import DaemonChannels, DaemonLoop
        from mds_ach.robot import config
        from mds_ach.robot.channels import StructChannel
        from mds_ach.robot.msgs import MDS_CMD, MDS_REF

        self.table = config.load("default")
        self.clock = ManualClock()
        self.net = SimNetwork.from_table(self.table, pose=pose, clock=self.clock,
                                         bitrate=None if ideal else 1_000_000)
        self.io = canio.make_canio(nocan=True, network=self.net)
        self.frames: list = []
        self.io.recorder = _Memory(self.frames, self.clock, self.io.wall_offset)  # type: ignore[assignment]
        self.channels = DaemonChannels.open()
        self.modes: list[tuple[float, float]] = []
        self.loop = DaemonLoop(self.table, self.io, self.channels, rate_hz=rate, nocan=True, clock=self.clock)
        self.loop.mode_log = lambda t, s: self.modes.append((t, s))
        self.ref_out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, MDS_REF)
        self.cmd_out = StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD)
        self.seq = 0
        self.loop.start_up()

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            start = self.clock.now
            self.loop.cycle(deadline=start, start=start)
            self.clock.now = max(self.clock.now, start + self.loop.period)

    def put(self, **refs: float) -> None:
        import mds_ach as mds
        from mds_ach.robot.msgs import MDS_REF

        ref = MDS_REF()
        for j in self.table:
            ref.joint[j.address].ref = self.loop.state.joint[j.address].ref
            ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
        for short, value in refs.items():
            ref.joint[self.table[short].address].ref = self.table[short].clamp(value)
        self.ref_out.put(ref)

    def command(self, code: int, value: float = 0.0) -> None:
        from mds_ach.robot.msgs import MDS_CMD

        self.seq += 1
        self.cmd_out.put(MDS_CMD(seq=self.seq, cmd=code, value=value))

    def close(self) -> None:
        self.loop.stop()
        self.io.close()
        self.channels.close()
        self.ref_out.close()
        self.cmd_out.close()


class _Memory:
    """A CanIO recorder keeping (simulated time, frame): sent frames with the stamp the daemon gave them."""

    def __init__(self, frames: list, clock, wall: float) -> None:
        self.frames, self.clock, self.wall = frames, clock, wall

    def __call__(self, m) -> None:
        self.frames.append((self.clock() if m.is_rx else m.timestamp - self.wall, m))

    def close(self) -> None:
        pass


POSE = {"LEP": -1.0, "REP": -1.0, "LSP": -0.3, "RSP": -0.3}
GROUP_JOINTS = ("WST", "LSP", "LSR", "LSY", "LEP", "LWY", "LWR", "RSP", "RSR", "RSY", "REP", "RWY", "RWR")


def adversarial(rate: float, collaborative: bool, seconds: float, ideal: bool) -> dict:
    """Every upper-body joint sent to a random pose (uniform in its range) every 0.3 s, in between a fast streamed
    sinusoid: the audit's fastest hand/elbow and its violations."""
    import mds_ach as mds
    from mds_ach.tools import checklog

    rig = _Rig(rate, POSE, ideal)
    rng = np.random.default_rng(31)
    plan_time: list[float] = []
    original = rig.loop._cartesian_plan

    def timed(held):  # wall time of the collaborative planning (FK and the scaling)
        t0 = time.perf_counter()
        out = original(held)
        if out:
            plan_time.append(time.perf_counter() - t0)
        return out

    rig.loop._cartesian_plan = timed  # type: ignore[method-assign]
    try:
        if collaborative:
            rig.command(mds.MDS_CMD_MODE, 1.0)
            rig.step()
        n = round(seconds * rate)
        goal: dict[str, float] = {}
        for k in range(n):
            if k % max(1, round(0.3 * rate)) == 0:
                goal = {s: float(rng.uniform(rig.table[s].lower, rig.table[s].upper)) for s in GROUP_JOINTS}
            wobble = 0.4 * math.sin(2 * math.pi * k / rate)
            rig.put(**{s: q + (wobble if s in ("LSP", "RSP") else 0.0) for s, q in goal.items()})
            rig.step()
        report = checklog.audit_frames(rig.frames, rig.table, rig.loop.bounds, rig.loop.stale_after, whole_run=True,
                                       modes=rig.modes)
        return {"max": report.cartesian_max, "max_collab": report.cartesian_max_collaborative,
                "checked": report.cartesian_checked, "cartesian": report.counts()["cartesian"],
                "joint": sum(report.counts()[k] for k in checklog.KINDS if k != "cartesian"),
                "plan_ms": 1e3 * float(np.percentile(plan_time, 99)) if plan_time else 0.0,
                "plan_ms_median": 1e3 * float(np.median(plan_time)) if plan_time else 0.0,
                "slowed": rig.loop.status.cartesian_slowed}
    finally:
        rig.close()


def estop(rate: float) -> dict:
    """The left arm (LSP, LEP) at full joint speed, then ``MDS_CMD_ESTOP``."""
    import mds_ach as mds
    from mds_ach.bus.mcb import Command, StateArg
    from mds_ach.robot.msgs import daemon_status as ds

    rig = _Rig(rate, POSE, ideal=rate > 50)
    try:
        rig.put(LSP=-2.5, LEP=0.0)
        rig.step(round(0.6 * rate))
        lsp = rig.table["LSP"].address
        v0 = rig.loop.joints[lsp].track.v
        q0, m0 = rig.loop.joints[lsp].track.q, rig.net.position(lsp)
        t0 = rig.clock.now
        rig.command(mds.MDS_CMD_ESTOP)
        measured: list[tuple[float, float]] = []
        for _ in range(round(5 * rate)):
            rig.step()
            measured.append((rig.clock.now, rig.table["LSP"].to_joint(rig.net.position(lsp))))
            if rig.loop.status.estop == ds.ESTOP_STOPPED:
                break
        sent = [(t, f) for t, f in rig.net.commands if t >= t0]
        movetos = [(t, f) for t, f in sent if f.arbitration_id == lsp and f.command == Command.SET
                   and f.argument == StateArg.MOVETO_TARGET]
        disables = [t for t, f in sent if f.command == Command.DISABLE]
        first_brake = movetos[0][0] - t0 if movetos else math.nan
        stand = (movetos[-1][0] + 1 / rate - t0) if movetos else math.nan
        q_end = rig.loop.joints[lsp].track.q
        joint = rig.table["LSP"]
        m_end = measured[-1][1]
        still = next((t for t, q in measured if abs(q - m_end) < 1e-3), measured[-1][0])
        return {"v0": v0, "stand_s": stand, "stand_rad": abs(q_end - q0), "first_brake_s": first_brake,
                "disable_s": (disables[0] - t0) if disables else math.nan, "joint_stand_s": still - t0,
                "joint_stand_rad": abs(m_end - joint.to_joint(m0))}
    finally:
        rig.close()


def suite(quick: bool) -> list[Row]:
    from mds_ach.kinematics.cartesian import MAX_SPEED

    rows: list[Row] = []
    seconds = 3.0 if quick else 10.0
    for rate, ideal in ((10.0, False), (100.0, True)):
        c = adversarial(rate, True, seconds, ideal)
        n = adversarial(rate, False, seconds, ideal)
        wire = " (ideal wire)" if ideal else ""
        rows.append(Row(GROUP, f"collab: fastest hand/elbow @ {rate:g} Hz{wire}", c["max_collab"] * 1e3, "mm/s",
                        "normal mode, same references", n["max"] * 1e3, f"<= {MAX_SPEED * 1e3:g} mm/s",
                        c["max_collab"] <= MAX_SPEED and c["checked"] > 0))
        rows.append(Row(GROUP, f"collab: violations @ {rate:g} Hz ({c['checked']} batches, slowed {c['slowed']})",
                        c["cartesian"] + c["joint"], "", "normal mode, Cartesian if it were collab",
                        None, "0", c["cartesian"] + c["joint"] == 0))
        rows.append(Row(GROUP, f"collab: planning per cycle median @ {rate:g} Hz (p99 {c['plan_ms']:.2f} ms)",
                        c["plan_ms_median"], "ms", "", None, "< 2 ms", c["plan_ms_median"] < 2.0))
    for rate in (10.0, 100.0):
        e = estop(rate)
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz from {abs(e['v0']):.2f} rad/s: targets at rest", e["stand_s"],
                        "s", "v/(0.9 a_max) + 1 period", abs(e["v0"]) / 7.2 + 1 / rate))
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz: target distance to rest", e["stand_rad"], "rad",
                        "v^2/(2*0.9 a_max)", e["v0"] ** 2 / 14.4))
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz: sim joint at rest (MCB accel)", e["joint_stand_s"], "s"))
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz: sim joint distance to rest", e["joint_stand_rad"], "rad"))
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz: command -> first braking target", e["first_brake_s"] * 1e3,
                        "ms", "", None, "<= 1 period", e["first_brake_s"] <= 1 / rate + 1e-9))
        rows.append(Row(GROUP, f"estop @ {rate:g} Hz: command -> first DISABLE on the bus", e["disable_s"], "s",
                        "", None, "<= 2 s (BRAKE_TIMEOUT)", e["disable_s"] <= 2.0 + 1 / rate))
    return rows


def run(quick: bool = False) -> list[Row]:
    if os.environ.get("MDS_NETNS_ACTIVE") == "1":
        return suite(quick)
    out = subprocess.run([str(REPO / "tools/netns-run"), sys.executable, "-m", "bench.bench_safety", "suite",
                          *(["--quick"] if quick else [])], cwd=REPO, capture_output=True, text=True, check=True)
    return [Row(**r) for r in json.loads(out.stdout.strip().splitlines()[-1])]


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    if argv and argv[0] == "suite":
        print(json.dumps([asdict(r) for r in suite(quick)]))
        return 0
    for r in run(quick):
        print(f"{r.name}: {r.value:.4g} {r.unit}" + (f" (baseline {r.baseline_value:.4g})" if r.baseline_value
                                                      is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
