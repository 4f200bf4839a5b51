"""Collision gate (``ros2 run mds_ach collision``): ``mds-ref-smooth`` -> checks -> ``mds-ref-gated``
(the daemon's input; the gate is its only writer).

What the gate decides and why is ``mds_ach.nodes.gate`` (validation, speed bound, collision check, approach to
contact, stopped at contact, holding and releasing); this module runs it on the channels and as a ROS node.

Reports: ``mds-collide`` (legacy ``MDS_COLLIDE``, part indices ``COLLIDE_*``) and ``mds/collision``
(``mds_ach_interfaces/msg/CollisionState``: predicted pairs, current contacts, parts, per unit held / releasing /
escaping / stopped, refusals and the override state; made from the document of ``decision_to_dict``). Top-level
``isCollide``: **1** = the gate holds an arm: the flagged parts are those of the held arms, and the daemon holds
exactly those arms; **2** = a predicted collision was passed by the expert override; **3** = in contact (measured or
commanded) but nothing held: only moves out of it are passed, the flagged parts are the parts in contact, the daemon
holds nothing; 0 = clear. Per part: ``isCollide`` as above; ``collision`` counts the checks of the current episode
(saturating at ``counter_max``, 0 when clear); ``time`` = CLOCK_MONOTONIC of its last contact; ``time_dt`` = duration
of the episode. ``time`` = CLOCK_MONOTONIC of the report (the stamp the daemon echoes), ``time_dt`` = time since the
previous report.

**Expert override** (never the default, never silent): publish the number of seconds on
``mds/collision/override`` (std_msgs/Float64), e.g.
``ros2 topic pub --once mds/collision/override std_msgs/msg/Float64 "{data: 3.0}"``. For that long (at most
``override_max``, config) predicted collisions are reported but not blocked; validation and the speed bound
still apply, and held arms are released as above. It expires by itself; 0 or a negative value ends it at once.
Start, every second while active, and end are logged at WARN/ERROR level; mds-collide shows ``isCollide = 2``
while it passes a collision and ``mds/collision`` carries ``override_remaining``.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from mds_ach_interfaces.msg import CollisionState
from rclpy.node import Node
from std_msgs.msg import Float64

import mds_ach as mds
from mds_ach.kinematics.collision import check_world_file, load_model
from mds_ach.nodes import filter as filter_node
from mds_ach.nodes.gate import (
    IDLE_REPORT_PERIOD,
    MODEL_ADDRESSES,
    STOPPED_AT_CONTACT,
    UNIT_ADDRESSES,
    Decision,
    Gate,
    GateConfig,
    Observed,
    decision_to_dict,
    joint_limits,
    load_config,
)
from mds_ach.nodes.pipeline import (
    HANDOFF_RT_PRIORITY,
    ChannelGuard,
    ReseedWatch,
    Wakeup,
    handoff_thread,
    labels,
    make_ref,
    ref_arrays,
    wait_current_reference,
)
from mds_ach.nodes.rosnode import Param, declare, find, ros_log, run_node, start_worker
from mds_ach.nodes.status_msgs import COLLISION_TOPIC, collision_state_msg
from mds_ach.ratelog import RateLimitedLog
from mds_ach.robot import lifecycle
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_COLLIDE, MDS_STATE
from mds_ach.robot.msgs.hold import HOLD_CANCEL, MDS_HOLD

# --------------------------------------------------------------------------------------------- Ach side


class DecisionTimes:
    """The newest ``size`` decision times (s) in a ring allocated once: the node's memory does not grow with the
    number of references it gates (a list trimmed at 10,000 entries grew it by ~0.3 MB over its first 10,000
    references, 250 s at the filter's 40 Hz: issue 25 item 10)."""

    def __init__(self, size: int = 4096) -> None:
        self._ring = np.zeros(size)
        self._count = 0

    def add(self, seconds: float) -> None:
        self._ring[self._count % len(self._ring)] = seconds
        self._count += 1

    def __len__(self) -> int:
        return min(self._count, len(self._ring))

    def values(self) -> np.ndarray:
        """The recorded times (a copy; order does not matter for the statistics)."""
        return self._ring[:len(self)].copy()


class _StateNews:
    """Is an ``mds-state`` frame news for the gate: a measured pose that moved (beyond ``tolerance`` rad since the
    frame that last woke it) or became known or unknown, or the daemon's echo of a newer report? At rest the daemon
    puts the same pose every cycle: the gate's loop is not woken for it (``pipeline.Wakeup``, its reader's thread)."""

    def __init__(self, tolerance: float = 1e-4) -> None:
        self.tolerance = tolerance
        self._pos: np.ndarray | None = None
        self._echo = -math.inf

    def __call__(self, state: MDS_STATE) -> bool:
        seen = Observed.from_state(state)
        moved = self._pos is None or seen.collide_time != self._echo or _differs(self._pos, seen.pos, self.tolerance)
        if moved:
            self._pos, self._echo = seen.pos, seen.collide_time
        return moved


def _differs(a: np.ndarray, b: np.ndarray, tolerance: float) -> bool:
    """Do two measured poses differ: a joint known in one and not the other, or beyond ``tolerance`` rad?"""
    known = np.isfinite(a)
    if not np.array_equal(known, np.isfinite(b)):
        return True
    return bool(np.any(np.abs(a[known] - b[known]) > tolerance))


def _pose(observed: Observed | None, now: float, timeout: float) -> np.ndarray | None:
    """The measured pose the gate decides with (None: no recent ``mds-state``, as in ``Gate.process``)."""
    return observed.pos if observed is not None and now - observed.time <= timeout else None


def _moved(seen: np.ndarray | None, observed: Observed | None, now: float, timeout: float,
           tolerance: float = 1e-4) -> bool:
    """Has the measured pose changed (beyond ``tolerance`` rad, or become known or unknown) since the newest
    decision? The gate then decides again on the same input: a joint pushed into contact at rest is held."""
    pos = _pose(observed, now, timeout)
    if pos is None or seen is None:
        return (pos is None) != (seen is None)
    return _differs(pos, seen, tolerance)


class GateRunner:
    """Channels around ``Gate``: wait for ``mds-ref-smooth``, decide with the newest ``mds-state`` (measured pose,
    echoed ``mds-collide``), put ``mds-ref-gated`` and ``mds-collide``."""

    def __init__(self, model: Any, config: GateConfig, lower: np.ndarray, upper: np.ndarray,
                 log: Callable[[str, str], None] | None = None,
                 on_report: Callable[[Decision | None, Gate, float], None] | None = None,
                 sources: Sequence[str] = (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_STATE_NAME),
                 rt_priority: int = 0) -> None:
        self.rt_priority = rt_priority  # SCHED_FIFO of the loop and its Wakeup readers (pipeline.HANDOFF_RT_PRIORITY)
        self.model = model
        self.config = config
        self.lower, self.upper = lower, upper
        self.log = log or (lambda level, msg: print(f"[collision] {level}: {msg}", flush=True))
        # One line per change of what is refused, and an input alternating at the frame rate still cannot flood
        # the log (mds_ach.ratelog); refused_count counts every refused reference.
        self.refusals = RateLimitedLog(self.log)
        self.on_report = on_report
        self.sources = tuple(sources)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._override_requests: list[float] = []
        self._wakeup: Wakeup | None = None  # the gate's inputs (mds-ref-smooth, mds-state), from run() on
        self.gate: Gate | None = None
        self.ready = threading.Event()
        self.processed = 0
        self.refused_count = 0  # references with at least one refused joint (mds/collision "refused_count")
        self.cancels = 0  # HOLD_CANCEL frames sent for arms stopped at contact
        self.check_times = DecisionTimes()

    def stop(self) -> None:
        self._stop.set()
        if self._wakeup is not None:
            self._wakeup.cancel()

    def request_override(self, seconds: float) -> None:
        """Thread-safe: queue an expert-override request (applied by the gate thread)."""
        with self._lock:
            self._override_requests.append(float(seconds))

    def run(self) -> None:
        handoff_thread(self.rt_priority, "gate", self.log)
        found = wait_current_reference(self._stop, lambda m: self.log("info", m), self.sources)
        if found is None:
            return
        ref, mode, source = found
        gate = Gate(self.model, self.config, ref, mode, time.monotonic(), self.lower, self.upper)
        inp = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
        out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
        collide = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, MDS_COLLIDE)
        state_ch = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
        hold_ch = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
        observed: Observed | None = None
        inp.latest()  # a frame already waiting is an old command: act only on frames that arrive from now on
        self._wakeup = wakeup = Wakeup((inp.name, state_ch.name), (mds.MDS_REF, MDS_STATE), self.log,
                                             self.rt_priority, news={state_ch.name: _StateNews()})
        self.gate = gate
        report_period = 1.0 / self.config.report_rate
        override_log = 0.0
        last_override_log = -math.inf
        refusing: tuple[int, ...] = ()  # what the last reference had refused: logged once per change
        guard = ChannelGuard(self.log, self._stop)
        watch = ReseedWatch(self.log, self._stop)
        try:
            msg = f"started from {source}; margin {self.model.margin:g} m, {len(self.model.pairs)} pairs"
            if gate.current.collides:
                self.log("error", f"{msg}; the current reference is IN COLLISION: "
                                  f"{sorted(gate.current.pairs)} - only moves out of it are passed")
            else:
                self.log("info", msg)
            collide.put(gate.report(time.monotonic()))
            self.ready.set()
            last_active = time.monotonic()
            # the newest input (ref, mode); until one arrives, the reference the gate started from
            latest: tuple[np.ndarray, np.ndarray] = (gate.ref.copy(), gate.mode.copy())
            seen_pos: np.ndarray | None = None  # the measured pose the newest decision was made with
            wait = report_period
            while not self._stop.is_set():
                # Event-driven: a new mds-ref-smooth frame wakes the gate at once, and so does an mds-state frame with a
                # measured pose that moved (_StateNews), so it is decided on within one daemon cycle. Between
                # frames it wakes for its report (report_rate) or, while a decision on the newest input is still
                # unfolding, at the filter's period (Gate.pending).
                wakeup.wait(wait)
                frame = guard.call(inp.name, inp.latest)  # broken input: hold, report
                now = time.monotonic()
                override_log = self._apply_overrides(gate, now, override_log)
                state = guard.call(state_ch.name, state_ch.latest)  # a broken state: keep the last one
                if state is not None:
                    observed = Observed.from_state(state)
                reseed = watch.poll()  # HOME, reset, resetbus: restart those joints where they are
                if reseed is not None:
                    gate.reseed(*reseed)
                    latest[0][reseed[0]] = reseed[1]  # the input is old there too (the filter re-seeds them)
                    self.log("info", f"re-seeded {labels(reseed[0])} where the joints are")
                moved = _moved(seen_pos, observed, now, self.config.state_timeout)
                repeat = False  # the input again (the filter's heartbeat at rest): nothing to decide anew
                if frame is not None:
                    new = ref_arrays(frame)
                    repeat = (np.array_equal(new[0], latest[0])
                              and np.array_equal(new[1], latest[1]) and reseed is None and not moved
                              and not gate.pending(*new) and not gate.current.collides
                              and gate.override_until == -math.inf)
                    latest = new
                    if repeat:
                        frame = None
                elif gate.pending(*latest) or reseed is not None or moved:
                    frame = make_ref(*latest)  # the same input again: its timed decision goes on, or the robot moved
                if repeat:  # the same output again, with its report first (as after a decision), counted the same
                    guard.call(collide.name, collide.put, gate.report(now))
                    guard.call(out.name, out.put, make_ref(gate.ref, gate.mode))
                    self.processed += 1
                    self.refused_count += bool(refusing)
                decision = None
                if frame is not None:
                    seen_pos = _pose(observed, now, self.config.state_timeout)
                    t0 = time.perf_counter()
                    decision = gate.process(*latest, now, observed)
                    self.check_times.add(time.perf_counter() - t0)
                    # The report before the reference: the daemon reads the reference first, then the report, so
                    # whenever it sees a held reference it also sees the hold.
                    guard.call(collide.name, collide.put, gate.report(now))
                    guard.call(out.name, out.put, make_ref(decision.ref, decision.mode))
                    self.processed += 1
                    self.refused_count += bool(decision.refused)
                    if decision.refused != refusing:
                        self._log_refusal(decision.refused, refusing, frame)
                        refusing = decision.refused
                    for arm, pair in decision.stopped.items():
                        self._cancel(hold_ch, guard, arm, decision.ref, pair, now)
                    if decision.overridden and now - last_override_log > 1.0:
                        self.log("error", f"EXPERT OVERRIDE passed a predicted collision: "
                                          f"{sorted(decision.result.pairs)}")
                        last_override_log = now
                self.refusals.tick()
                busy = gate.pending(*latest)
                if frame is not None or busy or gate.current.collides or gate.override_remaining(now) > 0:
                    last_active = now
                # reports at report_rate while anything goes on (and 1 s after), every IDLE_REPORT_PERIOD at rest
                period = report_period if now - last_active <= 1.0 else max(report_period, IDLE_REPORT_PERIOD)
                reported = frame is not None or repeat
                if not reported and now - gate.last_report >= period - 1e-3:
                    guard.call(collide.name, collide.put, gate.report(now))
                    reported = True
                if reported and self.on_report is not None:
                    self.on_report(decision, gate, now)
                wait = self.config.input_period if busy else period
        finally:
            for ch in (wakeup, inp, out, collide, state_ch, hold_ch, watch):
                ch.close()
            if len(self.check_times):
                ms = self.check_times.values() * 1e3
                self.log("info", f"{self.processed} references gated; decision time median {np.median(ms):.2f} ms, "
                                 f"p99 {np.percentile(ms, 99):.2f} ms, max {ms.max():.2f} ms")

    def _log_refusal(self, refused: tuple[int, ...], before: tuple[int, ...], frame: Any) -> None:
        """One message per change of what is refused (not one per reference: a refusal lasts while the input
        does), with the values and the limits they broke."""
        if not refused:
            self.refusals("refusal", f"references for {labels(before)} accepted again ({self.refused_count} refused "
                                     f"so far)", kind=refused, level="info")
            return
        ref, mode = ref_arrays(frame)
        why = []
        for a in refused:
            value, lo, hi = float(ref[a]), float(self.lower[a]), float(self.upper[a])
            if not 0 <= int(mode[a]) <= 3:
                why.append(f"{labels([a])}: unknown mode {int(mode[a])}")
            elif not math.isfinite(value):
                why.append(f"{labels([a])}: non-finite {value}")
            else:
                why.append(f"{labels([a])}: {value:.5f} rad outside [{lo:.5f}, {hi:.5f}]")
        self.refusals("refusal", f"refusing references (held at their last value until the input is valid again): "
                                 f"{'; '.join(why)}", kind=refused, level="error")

    def _cancel(self, hold_ch: StructChannel[MDS_HOLD], guard: ChannelGuard, arm: str, ref: np.ndarray, pair: str,
                now: float) -> None:
        """End the command of an arm stopped at contact: ``HOLD_CANCEL`` on ``mds-hold`` for its joints at the
        reference it was stopped at, so the mux drops that target and the arm does not go on to it later when
        the obstacle moves away (only a new command moves it)."""
        reason = f"{STOPPED_AT_CONTACT}: {pair}"
        frame = lifecycle.make(HOLD_CANCEL, targets={int(a): float(ref[a]) for a in UNIT_ADDRESSES[arm]},
                               source="collision", reason=reason)
        guard.call(hold_ch.name, hold_ch.put, frame)
        self.cancels += 1
        self.log("warn", f"{arm} arm {reason}; its command is cancelled (held at {labels(UNIT_ADDRESSES[arm])})")

    def _apply_overrides(self, gate: Gate, now: float, last_log: float) -> float:
        with self._lock:
            requests, self._override_requests = self._override_requests, []
        for seconds in requests:
            granted = gate.set_override(seconds, now)
            if granted > 0:
                self.log("error", f"EXPERT OVERRIDE ON for {granted:.1f} s (requested {seconds:g} s): predicted "
                                  f"collisions are reported but NOT blocked")
            else:
                self.log("warn", "expert override cancelled: collision checking blocks again")
            last_log = now
        remaining = gate.override_remaining(now)
        if remaining > 0 and now - last_log >= 1.0:
            self.log("error", f"EXPERT OVERRIDE active, {remaining:.1f} s left")
            return now
        if remaining == 0 and gate.override_until > -math.inf and gate.override_until <= now:
            self.log("warn", "expert override expired: collision checking blocks again")
            gate.override_until = -math.inf
        return last_log


# --------------------------------------------------------------------------------------------- ROS node


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="collision",
        description="Collision gate: reads mds-ref-smooth, writes mds-ref-gated (the daemon's input). Checks each "
                    "reference (limits, speed bound, self-collision and world objects with python-fcl) and holds "
                    "the affected arm at its last safe reference on a predicted collision. Reports on mds-collide "
                    "and mds/collision. "
                    "Expert override: publish seconds (std_msgs/Float64) on mds/collision/override.",
        epilog="Example: ros2 run mds_ach collision --world my_world.yaml --margin 0.03",
    )
    p.add_argument("--config", help="gate YAML (default: the package's config/collision.yaml)")
    p.add_argument("--world", help="world objects YAML (default: the package's config/world.yaml)")
    p.add_argument("--urdf", help="robot URDF (default: the package's urdf/mds.urdf)")
    p.add_argument("--margin", type=find(PARAMETERS, "margin").arg_type(),
                   help="minimum clearance in m (overrides the config)")
    return p


def build_gate_parts(config_path: str | None = None, world: str | None = None, urdf: str | None = None,
                     margin: float | None = None) -> tuple[Any, GateConfig, np.ndarray, np.ndarray]:
    """Model, gate config and limits from the files (shared by the node and the tests)."""
    cfg = dict(load_config(config_path))
    if margin is not None:
        cfg["margin"] = margin
    model = load_model(urdf, cfg, world)
    lower, upper = joint_limits(model)
    if cfg.get("release_velocity") is None:
        cfg["release_velocity"] = filter_speed()
    return model, GateConfig.from_mapping(cfg), lower, upper


def filter_speed(path: str | Path | None = None) -> float:
    """The slowest ``max_velocity`` of any modelled joint in the filter's config (config/filter.yaml): how fast a
    released joint comes back, so that it never outruns what the filter itself would have commanded."""
    return float(filter_node.load_config(path).max_velocity[MODEL_ADDRESSES].min())


NODE_NAME = "collision"  # the ROS node name (`ros2 param`, the sections of a params file)

PARAMETERS = (
    Param("config", "", "gate YAML; empty: the package's config/collision.yaml (option --config)"),
    Param("world", "", "world objects YAML; empty: the package's config/world.yaml (option --world)"),
    Param("urdf", "", "robot URDF; empty: the package's urdf/mds.urdf (option --urdf)"),
    Param("margin", 0.02, "minimum clearance in m: a reference bringing two parts (or a part and a world object) "
                          "closer is held; overrides the config's margin (option --margin)",
          range=(0.0, 0.5), default_doc="config `margin` (`0.02`)"),
)


class CollisionNode(Node):
    """The collision gate: ``GateRunner`` on its own thread; reports on ``mds/collision`` (typed), takes expert
    overrides (seconds) on ``mds/collision/override``."""

    def __init__(self, config: str | None = None, world: str | None = None, urdf: str | None = None,
                 margin: float | None = None) -> None:
        super().__init__(NODE_NAME)
        path = declare(self, find(PARAMETERS, "config"), config) or None
        world_path = declare(self, find(PARAMETERS, "world"), world) or None
        urdf_path = declare(self, find(PARAMETERS, "urdf"), urdf) or None
        if world_path is not None:
            check_world_file(world_path)  # a bad file stops the node with its reason (exit 2)
        configured = float(load_config(path).get("margin", find(PARAMETERS, "margin").default))
        self.margin: float = declare(self, find(PARAMETERS, "margin"), configured if margin is None else margin)
        model, gate_cfg, lower, upper = build_gate_parts(path, world_path, urdf_path, self.margin)
        self.pub = self.create_publisher(CollisionState, COLLISION_TOPIC, 10)
        self.create_subscription(Float64, COLLISION_TOPIC + "/override", self._on_override, 10)
        self._last_pub = -math.inf
        self._last_doc = ""
        self.runner = GateRunner(model, gate_cfg, lower, upper, log=ros_log(self), on_report=self._on_report,
                                 rt_priority=HANDOFF_RT_PRIORITY)
        self.thread = start_worker(self, self.runner.run, "collision")

    def _on_override(self, msg: Float64) -> None:
        self.get_logger().warning(f"expert override request received: {msg.data:g} s")
        self.runner.request_override(float(msg.data))

    def _on_report(self, decision: Decision | None, gate: Gate, now: float) -> None:
        if self.pub.get_subscription_count() == 0:
            return  # nobody listening: no document to build (a subscriber gets the next report, within 1/report_rate)
        doc = decision_to_dict(decision, gate, now, self.runner.refused_count)
        key = json.dumps({k: v for k, v in doc.items() if k != "time"})
        if not self.context.ok():  # shutting down after SIGINT/SIGTERM
            return
        if key != self._last_doc or now - self._last_pub >= 1.0 / gate.config.report_rate:
            self.pub.publish(collision_state_msg(doc, self.get_clock().now().to_msg()))
            self._last_doc, self._last_pub = key, now

    def shutdown(self) -> None:
        self.runner.stop()
        self.thread.join(timeout=3.0)


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(argv, _build_parser(), lambda args: CollisionNode(config=args.config, world=args.world,
                                                                      urdf=args.urdf, margin=args.margin))


if __name__ == "__main__":
    raise SystemExit(main())
