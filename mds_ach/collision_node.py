"""Collision gate (``ros2 run mds_ach collision``): ``mds-ref-smooth`` -> checks -> ``mds-ref`` (the daemon's input).

Every reference is checked before it can reach the daemon, in this order:

1. **Validation.** NaN/Inf or out-of-limit values (URDF limits intersected with the joint table) and unknown
   ref modes (not 0..3) are never passed on: those joints keep their last sent value and mode, and the
   refusal is logged (throttled).
2. **Speed bound.** No joint moves faster than ``max_velocity`` between two outputs (wall time; a pause
   credits at most ``max_dt``; the first reference after start moves nothing). The filter node is the
   smoother; this bound only keeps a restarted gate, a pass-through filter or an arm released from a hold
   from jumping.
3. **Collision check** (``mds_ach.collision``: self-collision and world objects, clearance ``margin``).
   On a predicted collision the joints of the affected arm(s) keep their most recent safe value while the
   rest of the reference goes through; if that mix still collides (e.g. the waist or neck caused it), every
   modelled joint is held. The gate resumes as soon as the commanded reference is safe again. If the robot
   is already in collision (started there, or after an override), only moves out of it pass: no new colliding
   pair, and the colliding parts not brought closer together overall.

Reports: ``mds-collide`` (legacy ``MDS_COLLIDE``, part indices ``COLLIDE_*``) and ``/mds/collision``
(std_msgs/String, JSON with pairs, parts, held arms, refusals and the override state).
Legacy part fields: ``isCollide`` 1 while a contact is predicted and for ``release_time`` s after (wall
time); ``collision`` counts the checks of the current episode (saturating at ``counter_max``, 0 when clear);
``time`` = CLOCK_MONOTONIC of the last predicted contact; ``time_dt`` = duration of the episode.
Top level: ``isCollide`` 1 = a predicted collision was blocked, **2 = it was passed by the expert override**;
``time`` = CLOCK_MONOTONIC of the report, ``time_dt`` = time since the previous report.

**Expert override** (never the default, never silent): publish the number of seconds on
``/mds/collision/override`` (std_msgs/Float64), e.g.
``ros2 topic pub --once /mds/collision/override std_msgs/msg/Float64 "{data: 3.0}"``. For that long (at most
``override_max``, config) predicted collisions are reported but not blocked; validation and the speed bound
still apply. It expires by itself; 0 or a negative value ends it at once. Start, every second while active,
and end are logged at WARN/ERROR level; mds-collide shows ``isCollide = 2`` while it passes a collision and
``/mds/collision`` carries ``override_remaining``.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import mds_ach as mds
from mds_ach.joints import BY_SHORT, LEFT_ARM, MODEL_JOINTS, RIGHT_ARM
from mds_ach.msgs import MDS_COLLIDE, MDS_COLLIDE_JNT_NUM, MDS_JOINT_COUNT
from mds_ach.pipeline import KNOWN_ADDRESSES, cancel_wait, labels

ARM_ADDRESSES: dict[str, np.ndarray] = {
    "left": np.array([BY_SHORT[n].address for n in LEFT_ARM]),
    "right": np.array([BY_SHORT[n].address for n in RIGHT_ARM]),
}
MODEL_ADDRESSES = np.array([BY_SHORT[n].address for n in MODEL_JOINTS])
COLLIDE_BLOCKED = 1
COLLIDE_OVERRIDDEN = 2


@dataclass(frozen=True)
class GateConfig:
    max_velocity: float | None = 2.0  # rad/s, None = no bound
    max_dt: float = 0.05  # s, longest interval the speed bound credits (>= 2 filter periods)
    release_time: float = 0.1  # s, reporting hysteresis
    counter_max: int = 240
    override_max: float = 10.0  # s
    report_rate: float = 10.0  # Hz

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "collision config") -> GateConfig:
        def num(key: str, default: float, positive: bool = True, allow_none: bool = False) -> float | None:
            value = data.get(key, default)
            if value is None and allow_none:
                return None
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: {key} must be a number, got {data.get(key)!r}") from None
            if not math.isfinite(value) or (positive and value <= 0):
                raise ValueError(f"{where}: {key} must be a finite number > 0, got {value}")
            return value

        return cls(
            max_velocity=num("max_velocity", 2.0, allow_none=True),
            max_dt=num("max_dt", 0.05),  # type: ignore[arg-type]
            release_time=num("release_time", 0.1),  # type: ignore[arg-type]
            counter_max=int(num("counter_max", 240)),  # type: ignore[arg-type]
            override_max=num("override_max", 10.0),  # type: ignore[arg-type]
            report_rate=num("report_rate", 10.0),  # type: ignore[arg-type]
        )


@dataclass
class Decision:
    """What the gate did with one reference."""

    ref: np.ndarray
    mode: np.ndarray
    result: Any  # CheckResult of the commanded (validated, speed-bounded) reference
    held: tuple[str, ...] = ()  # 'left', 'right' or 'all'
    refused: tuple[int, ...] = ()  # addresses refused by validation
    overridden: bool = False  # a predicted collision passed because of the expert override


@dataclass
class _PartState:
    last: float = -math.inf
    start: float = -math.inf
    count: int = 0


@dataclass
class Gate:
    """The gate's decision logic on arrays (no channels, no ROS): ``process()`` one reference at a time."""

    model: Any  # mds_ach.collision.CollisionModel
    config: GateConfig
    ref: np.ndarray  # last output (100)
    mode: np.ndarray
    now: float
    lower: np.ndarray = field(default_factory=lambda: np.full(MDS_JOINT_COUNT, -math.inf))
    upper: np.ndarray = field(default_factory=lambda: np.full(MDS_JOINT_COUNT, math.inf))

    def __post_init__(self) -> None:
        self.ref = np.array(self.ref, dtype=float)
        self.mode = np.array(self.mode, dtype=np.int16)
        self.last_time = self.now
        self._first = True
        self.current = self.model.check(self.model.q_from_ref(self.ref))  # the output's own state
        self.override_until = -math.inf
        self.parts = [_PartState() for _ in range(MDS_COLLIDE_JNT_NUM)]
        self.last_report = self.now
        self.last_flag = 0
        self._flag_time = -math.inf
        self._known = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        self._known[list(KNOWN_ADDRESSES)] = True

    # ----- override

    def set_override(self, seconds: float, now: float) -> float:
        """Start (seconds > 0, capped at override_max) or end (<= 0) the expert override; returns its length."""
        if not math.isfinite(seconds) or seconds <= 0:
            self.override_until = -math.inf
            return 0.0
        seconds = min(seconds, self.config.override_max)
        self.override_until = now + seconds
        return seconds

    def override_remaining(self, now: float) -> float:
        return max(0.0, self.override_until - now)

    # ----- the decision

    def _acceptable(self, result: Any) -> bool:
        """Collision-free, or - when the output is already in collision - a move out of it: no new colliding
        pair, and the pairs still colliding are not brought closer together overall (sum of the distances
        between their primitives' centres)."""
        if not result.collides:
            return True
        if not self.current.collides or not result.pairs <= self.current.pairs:
            return False
        now = {(c.a, c.b): c.centre_distance for c in self.current.contacts}
        before = sum(now[(c.a, c.b)] for c in result.contacts)
        return sum(c.centre_distance for c in result.contacts) >= before - 1e-9

    def process(self, ref: np.ndarray, mode: np.ndarray, now: float) -> Decision:
        ref = np.asarray(ref, dtype=float)
        mode = np.asarray(mode, dtype=np.int16)
        cand = ref.copy()
        cand_mode = mode.copy()
        bad = ~np.isfinite(ref) | (ref < self.lower) | (ref > self.upper) | (mode < 0) | (mode > 3)
        cand[bad] = self.ref[bad]
        cand_mode[bad] = self.mode[bad]
        refused = tuple(int(a) for a in np.flatnonzero(bad & self._known))
        if self.config.max_velocity is not None:
            # The first reference after start gets no credit: whatever the input says, the output starts
            # from where the daemon is (a restarted gate must not step).
            dt = 0.0 if self._first else min(max(now - self.last_time, 0.0), self.config.max_dt)
            step = self.config.max_velocity * dt
            cand = self.ref + np.clip(cand - self.ref, -step, step)
        q = self.model.q_from_ref
        result = self.model.check(q(cand))
        held: tuple[str, ...] = ()
        out, out_mode, out_result = cand, cand_mode, result
        overridden = False
        if not self._acceptable(result):
            if self.override_remaining(now) > 0:
                overridden = True
            else:
                arms = tuple(sorted(result.arms))
                mixed, mixed_mode = cand.copy(), cand_mode.copy()
                for arm in arms:
                    idx = ARM_ADDRESSES[arm]
                    mixed[idx] = self.ref[idx]
                    mixed_mode[idx] = self.mode[idx]
                mixed_result = self.model.check(q(mixed)) if arms else result
                if arms and self._acceptable(mixed_result):
                    out, out_mode, out_result, held = mixed, mixed_mode, mixed_result, arms
                else:
                    out, out_mode = cand.copy(), cand_mode.copy()
                    out[MODEL_ADDRESSES] = self.ref[MODEL_ADDRESSES]
                    out_mode[MODEL_ADDRESSES] = self.mode[MODEL_ADDRESSES]
                    out_result, held = self.current, ("all",)
        self._track(result, now, overridden)
        self.ref, self.mode, self.current, self.last_time = out, out_mode, out_result, now
        self._first = False
        return Decision(out.copy(), out_mode.copy(), result, held, refused, overridden)

    def reseed(self, addresses: np.ndarray, positions: np.ndarray) -> None:
        """Restart these joints' output where they are (``pipeline.ReseedWatch``: after HOME, reset, resetbus)."""
        self.ref[addresses] = positions
        self.current = self.model.check(self.model.q_from_ref(self.ref))

    # ----- reporting

    def _track(self, result: Any, now: float, overridden: bool) -> None:
        hit = result.parts
        for p, st in enumerate(self.parts):
            if p in hit:
                if now - st.last > self.config.release_time:
                    st.start, st.count = now, 0
                st.last = now
                st.count = min(st.count + 1, self.config.counter_max)
            elif now - st.last > self.config.release_time:
                st.count = 0
        if result.collides:
            self.last_flag = COLLIDE_OVERRIDDEN if overridden else COLLIDE_BLOCKED
            self._flag_time = now

    def report(self, now: float) -> MDS_COLLIDE:
        """The legacy ``mds-collide`` frame for ``now`` (hysteresis on wall time)."""
        c = MDS_COLLIDE()
        any_part = False
        for p, st in enumerate(self.parts):
            active = now - st.last <= self.config.release_time
            j = c.joint[p]
            j.collision = st.count if active else 0
            j.isCollide = int(active)
            j.time = st.last if math.isfinite(st.last) else 0.0
            j.time_dt = now - st.start if active else 0.0
            any_part |= active
        flag_active = now - self._flag_time <= self.config.release_time
        c.isCollide = self.last_flag if (flag_active or any_part) and self.last_flag else 0
        c.time = now
        c.time_dt = now - self.last_report
        self.last_report = now
        return c


def decision_to_dict(d: Decision | None, gate: Gate, now: float) -> dict[str, Any]:
    """The JSON document of /mds/collision."""
    res = d.result if d is not None else gate.current
    return {
        "time": now,
        "collision": bool(res.collides),
        "pairs": sorted([c.a, c.b] for c in res.contacts),
        "parts": [mds.COLLIDE_PART_NAMES[p] for p in sorted(res.parts)],
        "held": list(d.held) if d is not None else [],
        "refused": [labels([a]) for a in d.refused] if d is not None else [],
        "overridden": bool(d.overridden) if d is not None else False,
        "override_remaining": round(gate.override_remaining(now), 3),
        "margin": gate.model.margin,
    }


def joint_limits(model: Any) -> tuple[np.ndarray, np.ndarray]:
    """Per-address limits: the joint table (config/joints.yaml) intersected with the URDF for modelled joints."""
    lower = np.full(MDS_JOINT_COUNT, -math.inf)
    upper = np.full(MDS_JOINT_COUNT, math.inf)
    from mds_ach import config as joint_config

    for j in joint_config.load():
        lower[j.address], upper[j.address] = j.lower, j.upper
    lower[model.addresses] = np.maximum(lower[model.addresses], model.lower)
    upper[model.addresses] = np.minimum(upper[model.addresses], model.upper)
    return lower, upper


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    from mds_ach.collision import load_yaml
    from mds_ach.paths import config_path

    path = Path(path) if path else config_path("collision.yaml")
    if not path.is_file():
        raise ValueError(f"collision config {path} not found")
    return load_yaml(path)


# --------------------------------------------------------------------------------------------- Ach side


class GateRunner:
    """Channels around ``Gate``: wait for ``mds-ref-smooth``, decide, put ``mds-ref`` and ``mds-collide``."""

    def __init__(self, model: Any, config: GateConfig, lower: np.ndarray, upper: np.ndarray,
                 log: Callable[[str, str], None] | None = None,
                 on_report: Callable[[Decision | None, Gate, float], None] | None = None,
                 sources: Sequence[str] = (mds.MDS_CHAN_REF_NAME, mds.MDS_CHAN_STATE_NAME)) -> None:
        self.model = model
        self.config = config
        self.lower, self.upper = lower, upper
        self.log = log or (lambda level, msg: print(f"[collision] {level}: {msg}", flush=True))
        self.on_report = on_report
        self.sources = tuple(sources)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._override_requests: list[float] = []
        self._inp: Any = None
        self.gate: Gate | None = None
        self.ready = threading.Event()
        self.processed = 0
        self.check_times: list[float] = []

    def stop(self) -> None:
        self._stop.set()
        if self._inp is not None:
            cancel_wait(self._inp)

    def request_override(self, seconds: float) -> None:
        """Thread-safe: queue an expert-override request (applied by the gate thread)."""
        with self._lock:
            self._override_requests.append(float(seconds))

    def run(self) -> None:
        from mds_ach.channels import StructChannel
        from mds_ach.pipeline import ChannelGuard, ReseedWatch, make_ref, ref_arrays, wait_current_reference

        found = wait_current_reference(self._stop, lambda m: self.log("info", m), self.sources)
        if found is None:
            return
        ref, mode, source = found
        gate = Gate(self.model, self.config, ref, mode, time.monotonic(), self.lower, self.upper)
        self._inp = inp = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
        out = StructChannel(mds.MDS_CHAN_REF_NAME, mds.MDS_REF)
        collide = StructChannel(mds.MDS_CHAN_COLLIDE_NAME, MDS_COLLIDE)
        inp.latest()  # a frame already waiting is an old command: act only on frames that arrive from now on
        self.gate = gate
        report_period = 1.0 / self.config.report_rate
        override_log = 0.0
        last_refusal_log = last_override_log = -math.inf
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
            while not self._stop.is_set():
                frame = guard.call(inp.name, inp.wait, timeout=report_period)  # broken input: hold, report
                now = time.monotonic()
                override_log = self._apply_overrides(gate, now, override_log)
                found = watch.poll()  # HOME, reset, resetbus: restart those joints where they are
                if found is not None:
                    gate.reseed(*found)
                    self.log("info", f"re-seeded {labels(found[0])} where the joints are")
                decision = None
                if frame is not None:
                    t0 = time.perf_counter()
                    decision = gate.process(*ref_arrays(frame), now)
                    self.check_times.append(time.perf_counter() - t0)
                    if len(self.check_times) > 10000:
                        del self.check_times[:5000]
                    guard.call(out.name, out.put, make_ref(decision.ref, decision.mode))
                    self.processed += 1
                    if decision.refused and now - last_refusal_log > 1.0:
                        self.log("error", f"refused out-of-limit/non-finite references or bad modes for "
                                          f"{labels(decision.refused)} (held at their last value)")
                        last_refusal_log = now
                    if decision.overridden and now - last_override_log > 1.0:
                        self.log("error", f"EXPERT OVERRIDE passed a predicted collision: "
                                          f"{sorted(decision.result.pairs)}")
                        last_override_log = now
                if frame is not None or now - gate.last_report >= report_period:
                    guard.call(collide.name, collide.put, gate.report(now))
                    if self.on_report is not None:
                        self.on_report(decision, gate, now)
        finally:
            inp.close()
            out.close()
            collide.close()
            watch.close()

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
        description="Collision gate: reads mds-ref-smooth, writes mds-ref. Checks each reference (limits, speed "
                    "bound, self-collision and world objects with python-fcl) and holds the affected arm at its "
                    "last safe reference on a predicted collision. Reports on mds-collide and /mds/collision. "
                    "Expert override: publish seconds (std_msgs/Float64) on /mds/collision/override.",
        epilog="Example: ros2 run mds_ach collision --world my_world.yaml --margin 0.03",
    )
    p.add_argument("--config", help="gate YAML (default: the package's config/collision.yaml)")
    p.add_argument("--world", help="world objects YAML (default: the package's config/world.yaml)")
    p.add_argument("--urdf", help="robot URDF (default: the package's urdf/mds.urdf)")
    p.add_argument("--margin", type=float, help="minimum clearance in m (overrides the config)")
    return p


def build_gate_parts(config_path: str | None = None, world: str | None = None, urdf: str | None = None,
                     margin: float | None = None) -> tuple[Any, GateConfig, np.ndarray, np.ndarray]:
    """Model, gate config and limits from the files (shared by the node and the tests)."""
    from mds_ach.collision import load_model

    cfg = dict(load_config(config_path))
    if margin is not None:
        cfg["margin"] = margin
    model = load_model(urdf, cfg, world)
    lower, upper = joint_limits(model)
    return model, GateConfig.from_mapping(cfg), lower, upper


def _make_node(args: argparse.Namespace) -> Any:
    from rclpy.node import Node
    from std_msgs.msg import Float64, String

    from mds_ach.pipeline import ros_log, start_worker

    model, gate_cfg, lower, upper = build_gate_parts(args.config, args.world, args.urdf, args.margin)

    class CollisionNode(Node):
        def __init__(self) -> None:
            super().__init__("collision")
            self.declare_parameter("margin", model.margin)
            self.pub = self.create_publisher(String, "/mds/collision", 10)
            self.create_subscription(Float64, "/mds/collision/override", self._on_override, 10)
            log = ros_log(self)
            self._last_pub = -math.inf
            self._last_doc: str = ""
            self.runner = GateRunner(model, gate_cfg, lower, upper, log=log, on_report=self._on_report)
            self.thread = start_worker(self, self.runner.run, "collision")

        def _on_override(self, msg: Any) -> None:
            self.get_logger().warning(f"expert override request received: {msg.data:g} s")
            self.runner.request_override(float(msg.data))

        def _on_report(self, decision: Decision | None, gate: Gate, now: float) -> None:
            doc = decision_to_dict(decision, gate, now)
            key = json.dumps({k: v for k, v in doc.items() if k != "time"})
            if not self.context.ok():  # shutting down after SIGINT/SIGTERM
                return
            if key != self._last_doc or now - self._last_pub >= 1.0 / gate.config.report_rate:
                self.pub.publish(String(data=json.dumps(doc)))
                self._last_doc, self._last_pub = key, now

        def shutdown(self) -> None:
            self.runner.stop()
            self.thread.join(timeout=3.0)

    return CollisionNode()


def main(argv: Sequence[str] | None = None) -> int:
    from mds_ach.pipeline import run_node

    return run_node(argv, _build_parser(), _make_node)


if __name__ == "__main__":
    raise SystemExit(main())
