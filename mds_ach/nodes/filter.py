"""Reference smoother (``ros2 run mds_ach filter``): ``mds-ref-mux`` -> per-joint filter -> ``mds-ref-smooth``.

Event-driven, time-based: a new ``mds-ref-mux`` frame is stepped at once (no tick to wait for), the ramps advance
by the time since the previous step (at most one period), and while the output moves it ticks at ``rate``
(parameter, by default config/filter.yaml ``rate``: 40 Hz like the deployed mds-filter) so a ramp goes on with no
new input. At rest (every joint on its target, at rest) it sleeps until the next input, re-publishing its output
once per ``IDLE_PERIOD`` (1 s) as a heartbeat; the collision gate re-decides by itself while its own decision
unfolds (``collision.Gate.pending``).
Per-joint modes (the maths is ``mds_ach.nodes.filters``, shared with the daemon):

* ``velocity_limit`` (default): constant-speed ramp, 1.57 rad/s, snapping onto the target within one step,
  what the original deployment ran (``src/mds-filter.c``). Optional ``max_accel`` (rad/s^2) adds an
  acceleration limit that also brakes onto the target; config/filter.yaml sets 4 rad/s^2, below the daemon's
  last-line bounds (``mds_ach.robot.motion``), so smoothed references reach the robot unchanged.
* ``ema``: the paper's first-order filter theta_n = (theta_{n-1} (L - 1) + theta_des) / L with L from
  ``settle_time``/``settle_fraction`` at this rate (default: 95 % of a step within 4.0 s).
* ``enc_filter``: the same update started from the measured position (``mds-state`` joint[].pos) each tick,
  so the reference stays compliant to where the joint really is. Falls back to ``ema`` without a state.
* ``pass``: no smoothing.

**Per controller** (config ``controllers``): the joints a given mux controller owns (``mds-mux-state`` owner[]) use
that controller's parameters instead (with ``modes``: only for its frames in those ref modes; the bridge's
trajectory targets, mode 1, pass unsmoothed while its position commands, mode 0, are smoothed). By default the mux's
``direct`` controller (``mds-ref``, the channel the original daemon executed, written by expert clients) is
``pass``: "unsmoothed" means only this stage is skipped for those joints. The filter stays in the path and nothing
else is bypassed: the mux still refuses out-of-limit frames, the collision gate still checks every reference (and
bounds its speed, ``max_velocity`` in config/collision.yaml), and the daemon still limits speed and acceleration
(config/joints.yaml ``motion:``), so a step put on ``mds-ref`` reaches the motors as a bounded ramp.

Why the velocity limiter is the default: its timing is predictable (a move of d rad takes d / 1.57 s, small
moves are quick), it never overshoots, and it is what the robot ran in 2015; the EMA makes every move take
~4 s and approaches the target only asymptotically.

The legacy mode field of each joint travels with the reference, except that mode 0 ("first-order filter",
what zero-initialised legacy frames carry) leaves a smoothing joint as mode 1 (pass-through): the reference
is already smooth, so the daemon must not filter it a second time (config ``mark_smoothed``, default true).

No jump when started late or restarted: the output starts at the current reference (``mds-ref-gated``, else
``mds-state`` joint[].ref) and the newest ``mds-ref-mux`` frame (if any) becomes the target, so an
interrupted move resumes from where the robot is. NaN/Inf targets are ignored per joint (with a warning).
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from rclpy.node import Node

import mds_ach as mds
from mds_ach.nodes import filters
from mds_ach.nodes.pipeline import (
    HANDOFF_RT_PRIORITY,
    ChannelGuard,
    ReseedWatch,
    cancel_wait,
    handoff_thread,
    labels,
    make_ref,
    ref_arrays,
    select_joints,
    state_positions,
    wait_current_reference,
)
from mds_ach.nodes.rosnode import Param, declare, find, ros_log, run_node, start_worker
from mds_ach.paths import config_path
from mds_ach.ratelog import RateLimitedLog
from mds_ach.robot import feedforward
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_MUX_STATE
from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS

MODES = ("pass", "ema", "enc_filter", "velocity_limit")
PASS, EMA, ENC, VEL = range(4)
DEFAULT_RATE = 40.0
_PARAM_KEYS = {"mode", "max_velocity", "max_accel", "settle_time", "settle_fraction"}
_PARAM_ARRAYS = ("mode", "max_velocity", "max_accel", "length")


@dataclass(frozen=True)
class FilterParams:
    """Per-address arrays (length 100) of the smoothing parameters, plus the loop rate."""

    rate: float
    mode: np.ndarray  # int codes PASS/EMA/ENC/VEL
    max_velocity: np.ndarray  # rad/s
    max_accel: np.ndarray  # rad/s^2, inf = no acceleration limit
    length: np.ndarray  # EMA L at this rate
    mark_smoothed: bool = True  # mode 0 out of a smoothing joint becomes mode 1 (the daemon passes it through)
    controllers: Mapping[str, tuple[int, float, float, float]] = field(default_factory=dict)
    """Mux controller name -> (mode, max_velocity, max_accel, length) for the joints it owns."""
    controller_modes: Mapping[str, frozenset[int]] = field(default_factory=dict)
    """Mux controller name -> the ref modes of its frames its parameters apply to (absent: every mode)."""

    def for_owners(self, owners: Sequence[str | None], ref_modes: Sequence[int] | np.ndarray | None = None,
                   ) -> FilterParams:
        """These parameters with the joints owned (``owners[address]``: controller name or None) by a configured
        controller switched to that controller's parameters (only where the joint's frame mode, ``ref_modes``, is one
        of the controller's ``modes``, if it has any)."""
        arrays = {k: getattr(self, k).copy() for k in _PARAM_ARRAYS}
        for a, name in enumerate(owners):
            values = self.controllers.get(name) if name is not None else None
            only = self.controller_modes.get(name) if name is not None else None
            if only is not None and (ref_modes is None or int(ref_modes[a]) not in only):
                values = None
            if values is not None:
                for k, v in zip(_PARAM_ARRAYS, values, strict=True):
                    arrays[k][a] = v
        return replace(self, **arrays)

    @property
    def dt(self) -> float:
        return 1.0 / self.rate

    def describe(self) -> str:
        parts = []
        for code, name in enumerate(MODES):
            idx = np.flatnonzero(self.mode == code)
            if len(idx):
                parts.append(f"{name}: {len(idx)} joints")
        return ", ".join(parts)


def _joint_params(entry: Mapping[str, Any], base: dict[str, Any], where: str) -> dict[str, Any]:
    unknown = set(entry) - _PARAM_KEYS - {"joints"}
    if unknown:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)} (allowed: {sorted(_PARAM_KEYS)})")
    out = dict(base)
    out.update({k: v for k, v in entry.items() if k in _PARAM_KEYS})
    if out["mode"] not in MODES:
        raise ValueError(f"{where}: mode must be one of {', '.join(MODES)}, got {out['mode']!r}")
    for key in ("max_velocity", "settle_time"):
        val = float(out[key])
        if not (math.isfinite(val) and val > 0):
            raise ValueError(f"{where}: {key} must be > 0, got {out[key]!r}")
        out[key] = val
    if out["max_accel"] is not None:
        out["max_accel"] = float(out["max_accel"])
        if not (math.isfinite(out["max_accel"]) and out["max_accel"] > 0):
            raise ValueError(f"{where}: max_accel must be > 0 or null")
    out["settle_fraction"] = float(out["settle_fraction"])
    if not 0 < out["settle_fraction"] < 1:
        raise ValueError(f"{where}: settle_fraction must be in (0, 1)")
    return out


def parse_config(data: Mapping[str, Any], where: str = "filter config", rate: float | None = None) -> FilterParams:
    """Validate filter.yaml: ``rate``, ``default`` parameters, ``joints`` overrides (applied in order)."""
    unknown = set(data) - {"rate", "default", "joints", "mark_smoothed", "controllers"}
    if unknown:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)}")
    rate = float(rate if rate is not None else data.get("rate", DEFAULT_RATE))
    if not (math.isfinite(rate) and 0 < rate <= 1000):
        raise ValueError(f"{where}: rate must be in (0, 1000] Hz, got {rate}")
    base: dict[str, Any] = {"mode": "velocity_limit", "max_velocity": filters.DEFAULT_MAX_VELOCITY, "max_accel": None,
            "settle_time": filters.DEFAULT_SETTLE_TIME, "settle_fraction": filters.DEFAULT_SETTLE_FRACTION}
    base = _joint_params(data.get("default") or {}, base, f"{where}: default")
    per = [base] * MDS_JOINT_COUNT
    for k, entry in enumerate(data.get("joints") or []):
        here = f"{where}: joints[{k}]"
        if not isinstance(entry, Mapping) or "joints" not in entry:
            raise ValueError(f"{here}: needs 'joints' (names, groups or patterns) and the parameters to set")
        for a in select_joints(entry["joints"], here):
            per[a] = _joint_params(entry, per[a], here)
    controllers = data.get("controllers") or {}
    if not isinstance(controllers, Mapping):
        raise ValueError(f"{where}: controllers must map mux controller names to parameters")
    by_controller: dict[str, tuple[int, float, float, float]] = {}
    modes_of: dict[str, frozenset[int]] = {}
    for name, entry in controllers.items():
        here = f"{where}: controllers.{name}"
        if not isinstance(entry, Mapping) or "joints" in entry:
            raise ValueError(f"{here}: needs parameters ({', '.join(sorted(_PARAM_KEYS))}) for the joints that "
                             "controller owns")
        if "modes" in entry:
            given = entry["modes"]
            if not isinstance(given, list) or not given or any(m not in (0, 1, 2, 3) for m in given):
                raise ValueError(f"{here}: modes must be a list of ref modes (0 filter, 1 pass-through, 2 compliant, "
                                 f"3 encoder filter), got {given!r}")
            modes_of[str(name)] = frozenset(int(m) for m in given)
            entry = {k: v for k, v in entry.items() if k != "modes"}
        c = _joint_params(entry, base, here)
        by_controller[str(name)] = (MODES.index(c["mode"]), c["max_velocity"],
                                    math.inf if c["max_accel"] is None else c["max_accel"],
                                    filters.filter_length(rate, c["settle_time"], c["settle_fraction"]))
    return FilterParams(
        rate=rate,
        mode=np.array([MODES.index(p["mode"]) for p in per]),
        max_velocity=np.array([p["max_velocity"] for p in per]),
        max_accel=np.array([math.inf if p["max_accel"] is None else p["max_accel"] for p in per]),
        length=np.array([filters.filter_length(rate, p["settle_time"], p["settle_fraction"]) for p in per]),
        mark_smoothed=bool(data.get("mark_smoothed", True)),
        controllers=by_controller,
        controller_modes=modes_of,
    )


def load_config(path: str | Path | None = None, rate: float | None = None) -> FilterParams:
    path = Path(path) if path else config_path("filter.yaml")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except FileNotFoundError:
        raise ValueError(f"filter config {path} not found") from None
    if not isinstance(data, Mapping):
        raise ValueError(f"{path}: expected a mapping")
    return parse_config(data, str(path), rate)


# --------------------------------------------------------------------------------------------- filter state


ENC_REST = 1e-4  # rad: an enc_filter joint this close to its target rests (it follows the noisy measurement)
IDLE_PERIOD = 1.0  # s: at rest the output is re-published this often (a heartbeat: the node is alive)
RETRACTION_POLL = 0.005  # s: how often a hold's retraction looks for the daemon's next cycle (one or two cycles)


def _length_for(length: float, periods: float) -> float:
    """The EMA length that covers in ``periods`` configured periods what ``length`` covers in one: the
    remaining error (1 - 1/L)^n is the same after the same time, whatever the step spacing."""
    if periods == 1.0:
        return length
    return 1.0 / (1.0 - (1.0 - 1.0 / length) ** periods)


class FilterCore:
    """The smoother's state (output, velocity, target) and one ``step()`` per tick. No channels here."""

    def __init__(self, params: FilterParams, ref: np.ndarray, mode: np.ndarray) -> None:
        self.base = params  # the configured parameters; ``p``: those in effect (``set_owners``)
        self.p = params
        self.owners: tuple[str | None, ...] = (None,) * MDS_JOINT_COUNT
        self.out = np.array(ref, dtype=float)
        self.vel = np.zeros(MDS_JOINT_COUNT)
        self.target = self.out.copy()
        self.wanted = self.out.copy()  # the mux's target; ``target`` differs from it while a joint is held
        self.mode = np.array(mode, dtype=np.int16)
        self._accel = np.isfinite(params.max_accel)
        self.held = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        self.braking = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        # Joints whose last output was passed unsmoothed (a trajectory's stopping points): a hold stops them at the
        # daemon's last reference when there is time (``hold``); kept from the step, a CANCEL changes the owner first.
        self.unsmoothed = params.mode == PASS
        # Held joints whose output was taken back to the daemon's reference: address -> (newest output, held at),
        # until the daemon's next cycle tells which of the two it took (``settle_retractions``).
        self.retracted: dict[int, tuple[float, float]] = {}

    def set_target(self, ref: np.ndarray, mode: np.ndarray) -> str | None:
        """New desired reference; non-finite entries keep their old target; held joints keep their rest point
        (the new value waits for their release). Returns a warning or None."""
        ref = np.asarray(ref, dtype=float)
        ok = np.isfinite(ref)
        self.wanted[ok] = ref[ok]
        take = ok & ~self.held
        self.target[take] = ref[take]
        self.mode[ok] = np.asarray(mode, dtype=np.int16)[ok]
        if self.base.controller_modes:  # a controller's parameters may depend on its frames' mode
            self._apply_params()
        if not ok.all():
            return f"ignored non-finite targets for {labels(np.flatnonzero(~ok))}"
        return None

    def set_owners(self, owners: Sequence[str | None]) -> None:
        """The mux's joint owners (controller names, None = nobody): joints owned by a controller with its own
        parameters (config ``controllers``) use them. A joint whose mode changes starts from rest (a pass-through
        joint's step 'speed' is not a speed to carry into a ramp). Joints whose parameters stay are left alone."""
        owners = tuple(owners)
        if owners == self.owners or not self.base.controllers:
            self.owners = owners
            return
        self.owners = owners
        self._apply_params()

    def _apply_params(self) -> None:
        """The parameters in effect for the current owners and frame modes (``set_owners``)."""
        new = self.base.for_owners(self.owners, self.mode)
        switched = new.mode != self.p.mode
        self.vel[switched] = 0.0
        self.p = new
        self._accel = np.isfinite(new.max_accel)

    def hold(self, held: np.ndarray, reference: np.ndarray | None = None, taken: np.ndarray | None = None) -> None:
        """The mux's held mask (``mds-mux-state`` held[]: a HOLD, a CANCEL, a heartbeat's stop). Newly held joints
        stop advancing toward their target at once: acceleration-limited joints brake at ``max_accel`` (never
        reversing, so no overshoot-and-return and no step), the other modes stop where their output is. A newly
        held joint whose output is more than two steps away from ``reference`` (``mds-ref-gated``: the collision
        gate or a limit held it back) restarts at ``reference`` instead, where the robot is sent, so it never moves
        on when the gate clears. Released joints go back to the mux's target.

        ``taken``: the daemon's reference of its last cycle (``mds-state`` ``ref_r``) when the stop may still take
        back the newest output (``feedforward.retraction_in_time``; None: it may not). A newly held joint passed
        unsmoothed (a trajectory's stopping points, each aimed at the daemon's next send and the one after) then
        stops there, at the last target the daemon took, instead of at the newest still waiting for its next send:
        the joint brakes from the commanded state onto a target the MCB is already running to. Until the daemon's
        next cycle tells which it took, ``retracted`` keeps the newest (``settle_retractions``)."""
        held = np.asarray(held, dtype=bool)
        new = held & ~self.held
        released = ~held & self.held
        self.held = held.copy()
        if released.any():
            self.braking[released] = False
            self.target[released] = self.wanted[released]
            for a in np.flatnonzero(released):
                self.retracted.pop(int(a), None)
        if not new.any():
            return
        if reference is not None:
            lag = np.abs(self.out - reference)
            behind = new & np.isfinite(reference) & (lag > 2.0 * self.p.max_velocity * self.p.dt + 1e-6)
            if behind.any():
                self.reseed(np.flatnonzero(behind), np.asarray(reference)[behind])
                new &= ~behind
        back = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        if taken is not None:
            taken = np.asarray(taken, dtype=float)
            back = new & self.unsmoothed & np.isfinite(taken) & (taken != self.out)
            for a in np.flatnonzero(back):
                self.retracted[int(a)] = (float(self.out[a]), float(taken[a]))
            self.out[back] = taken[back]
        brake = new & ~back & (self.p.mode == VEL) & self._accel & (self.vel != 0.0)
        self.braking |= brake
        stop = new & ~brake
        self.target[stop] = self.out[stop]
        self.vel[stop] = 0.0

    def settle_retractions(self, taken: np.ndarray) -> list[int]:
        """The daemon's reference after its next cycle (``mds-state`` ``ref_r``) for the ``retracted`` joints: one
        whose newest output the daemon took first (the retraction reached it after its cycle,
        ``feedforward.took_newest``) goes back to that output, its last target, before the next cycle (else that
        target would be taken back: a reversal). Returns those joints; ``retracted`` is empty afterwards."""
        undone = []
        for a, (newest, hold) in self.retracted.items():
            if self.held[a] and self.out[a] == hold and feedforward.took_newest(float(taken[a]), newest, hold):
                self.out[a] = self.target[a] = newest
                self.vel[a] = 0.0
                undone.append(a)
        self.retracted = {}
        return undone

    def reseed(self, addresses: np.ndarray, positions: np.ndarray) -> None:
        """Restart these joints where they are, at rest (``pipeline.ReseedWatch``): output and target."""
        self.out[addresses] = self.target[addresses] = positions
        self.vel[addresses] = 0.0
        self.braking[addresses] = False

    def stay(self, out: np.ndarray) -> None:
        """The step just computed could not be published (a damaged output channel): go back to ``out``, the last
        output downstream has, at rest. Targets stay, so once the channel works again the output ramps on from
        there (acceleration-limited joints from rest) instead of jumping to where it would have got meanwhile."""
        self.out = np.array(out, dtype=float)
        self.vel[:] = 0.0

    def moving(self) -> bool:
        """Will the next step change the output? False once every joint rests on its target (then the runner
        sleeps until a new input instead of ticking). An ``enc_filter`` joint follows the measured position, which
        never settles exactly: it counts as resting within ``ENC_REST`` of its target."""
        p = self.p
        gap = np.abs(self.target - self.out)
        enc = p.mode == ENC
        return bool(np.any(gap[~enc] > 0.0) or np.any(gap[enc] > ENC_REST) or np.any(self.vel != 0.0)
                    or self.braking.any())

    def step(self, measured: np.ndarray | None = None, dt: float | None = None) -> np.ndarray:
        """Advance by ``dt`` seconds (None: one period of the configured rate). ``measured``: mds-state
        joint[].pos for the enc_filter joints (None = unknown). Time-based: a step taken when an input arrives
        between two ticks advances the ramps by the time since the previous step, so the speed and acceleration
        limits hold whatever the spacing of the steps; the EMA covers the same fraction per second."""
        p, out, tgt = self.p, self.out, self.target
        dt = p.dt if dt is None else dt
        if not dt > 0:
            return out.copy()
        new = out.copy()
        m = p.mode == PASS
        new[m] = tgt[m]
        enc = p.mode == ENC
        use_enc = enc & np.isfinite(measured) if measured is not None else np.zeros(MDS_JOINT_COUNT, dtype=bool)
        groups = [((p.mode == EMA) | (enc & ~use_enc), out)]
        if measured is not None:
            groups.append((use_enc, measured))
        for mask, source in groups:
            for length in np.unique(p.length[mask]):
                sel = mask & (p.length == length)
                new[sel] = filters.ema_step(source[sel], tgt[sel], _length_for(float(length), dt / p.dt))
        vel = p.mode == VEL
        plain = vel & ~self._accel
        if plain.any():
            new[plain] = filters.velocity_limit_step(out[plain], tgt[plain], p.max_velocity[plain], dt)
        acc = vel & self._accel & ~self.braking
        brk = self.braking.copy()
        if brk.any():  # held while moving: decelerate at max_accel to rest, never reversing
            speed = np.maximum(np.abs(self.vel[brk]) - p.max_accel[brk] * dt, 0.0)
            v = np.sign(self.vel[brk]) * speed
            new[brk] = out[brk] + v * dt
            self.vel[brk] = v
            stopped = np.flatnonzero(brk)[speed == 0.0]
            self.braking[stopped] = False
            self.target[stopped] = new[stopped]
        if acc.any():
            pos, v = filters.accel_limit_step(out[acc], self.vel[acc], tgt[acc], p.max_velocity[acc],
                                              p.max_accel[acc], dt)
            new[acc] = pos
            self.vel[acc] = v
        rest = ~acc & ~self.braking & ~brk
        self.vel[rest] = (new[rest] - out[rest]) / dt
        self.out = new
        self.unsmoothed = p.mode == PASS
        return new

    def out_mode(self) -> np.ndarray:
        """The mode field to publish: mode 0 of a smoothing joint becomes 1 (see the module doc)."""
        if not self.p.mark_smoothed:
            return self.mode.copy()
        smoothed = (self.mode == mds.MDS_REF_MODE_REF_FILTER) & (self.p.mode != PASS)
        return np.where(smoothed, np.int16(mds.MDS_REF_MODE_REF), self.mode).astype(np.int16)


# --------------------------------------------------------------------------------------------- Ach side


def state_references(state: mds.MDS_STATE) -> np.ndarray:
    """``state.joint[i].ref_r`` (the reference the daemon took at its cycle, rad) for all 100 addresses."""
    return np.array([state.joint[i].ref_r for i in range(MDS_JOINT_COUNT)], dtype=float)


def owner_names(st: MDS_MUX_STATE) -> tuple[str | None, ...]:
    """The controller name owning each address (None: nobody) from an ``mds-mux-state`` frame."""
    names = st.controller_names()
    return tuple(names[o] if 0 <= o < len(names) else None for o in (int(v) for v in st.owner))


class FilterRunner:
    """The loop: channels + ``FilterCore``, stepped on each input and at ``rate`` while moving (module doc).
    ``run()`` blocks until ``stop()``."""

    def __init__(self, params: FilterParams, log: Callable[[str, str], None] | None = None,
                 sources: Sequence[str] = (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_STATE_NAME),
                 rt_priority: int = 0) -> None:
        self.rt_priority = rt_priority  # SCHED_FIFO of the loop (pipeline.HANDOFF_RT_PRIORITY)
        self.params = params
        self.log = log or (lambda level, msg: print(f"[filter] {level}: {msg}", flush=True))
        self.ignored = RateLimitedLog(self.log)  # a bad input can repeat every cycle: one line per change
        self.sources = tuple(sources)
        self._stop = threading.Event()
        self.ready = threading.Event()
        self.core: FilterCore | None = None
        self.ticks = 0
        self.overruns = 0
        self._inp: Any = None

    def stop(self) -> None:
        self._stop.set()
        if self._inp is not None:
            cancel_wait(self._inp)

    @staticmethod
    def _daemon_reference(guard: ChannelGuard, state_ch: Any, status_ch: Any) -> tuple[float, np.ndarray] | None:
        """For a hold arriving now: (the daemon's newest ``mds-state`` stamp, its reference then: ``ref_r``) when the
        hold may still take the newest output back to that reference (``feedforward.retraction_in_time``, the
        daemon's period from its configured rate, ``mds-daemon-status``), else None (no daemon yet, a stall, too
        close to its next send: the newest is its last target)."""
        st = guard.call(state_ch.name, state_ch.latest)
        status = guard.call(status_ch.name, status_ch.latest)
        if st is None or status is None or not status.rate_hz > 0:
            return None
        if not feedforward.retraction_in_time(float(st.time), 1.0 / float(status.rate_hz), time.monotonic()):
            return None
        return float(st.time), state_references(st)

    def run(self) -> None:
        handoff_thread(self.rt_priority, "filter", self.log)
        found = wait_current_reference(self._stop, lambda m: self.log("info", m), self.sources)
        if found is None:
            return
        ref, mode, source = found
        core = FilterCore(self.params, ref, mode)
        inp = StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
        out = StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)
        state_ch = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        daemon_status = StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)
        mux_state = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        gate_out = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
        reference: np.ndarray | None = None
        needs_state = bool(np.any(self.params.mode == ENC))
        measured: np.ndarray | None = None
        warned_state = False
        retracted_at = 0.0  # the daemon's frame (mds-state stamp) whose reference held joints were taken back to
        self.core = core
        guard = ChannelGuard(self.log, self._stop, pause=0.0)  # the schedule paces the loop
        watch = ReseedWatch(self.log, self._stop)
        try:
            self.log("info", f"started from {source} at {self.params.rate:g} Hz ({self.params.describe()})")
            period = self.params.dt
            last_step = time.monotonic() - period
            frame = None
            self._inp = inp
            self.ready.set()
            while not self._stop.is_set():
                if frame is None:
                    frame = guard.call(inp.name, inp.latest)  # a broken input: keep smoothing to the last target
                if frame is not None:
                    problem = core.set_target(*ref_arrays(frame))
                    if problem:
                        self.ignored("target", problem, kind=problem)
                self.ignored.tick()
                sent = guard.call(gate_out.name, gate_out.latest)
                if sent is not None:
                    reference = ref_arrays(sent)[0]
                mux = guard.call(mux_state.name, mux_state.latest)
                if mux is not None:  # the mux's hold mask: brake newly held joints, release the others
                    core.set_owners(owner_names(mux))  # before the hold: braking depends on the joint's mode
                    held = np.frombuffer(bytes(mux.held), dtype=np.uint8) != 0
                    taken = None
                    if (held & ~core.held & core.unsmoothed).any():
                        daemon = self._daemon_reference(guard, state_ch, daemon_status)
                        if daemon is not None:
                            retracted_at, taken = daemon
                    core.hold(held, reference, taken)
                if core.retracted:  # which did the daemon take at its next cycle: the retraction or the newest?
                    st = guard.call(state_ch.name, state_ch.latest)
                    if st is not None and st.time != retracted_at:
                        undone = core.settle_retractions(state_references(st))
                        if undone:
                            self.log("info", f"{labels(undone)} held at their newest target: the daemon took it "
                                             f"before the hold's retraction reached it")
                reseed = watch.poll()  # after the new target: a re-seed (HOME, reset, resetbus) wins
                if reseed is not None:
                    core.reseed(*reseed)
                    self.log("info", f"re-seeded {labels(reseed[0])} where the joints are (after HOME, reset or "
                                     f"resetbus)")
                if needs_state:
                    st = guard.call(state_ch.name, state_ch.latest)
                    if st is not None:
                        measured = state_positions(st)
                    elif measured is None and not warned_state:
                        self.log("warn", "enc_filter joints have no mds-state yet: using ema until it arrives")
                        warned_state = True
                now = time.monotonic()
                if now - last_step > period + 0.5 * period and core.moving():
                    self.overruns += 1  # a tick came late (a busy machine): the ramp advances one period, no jump
                dt = min(max(now - last_step, 0.0), period)
                last_step = now
                published = core.out.copy()
                if not guard.put(out, make_ref(core.step(measured, dt), core.out_mode())):
                    core.stay(published)  # a damaged mds-ref-smooth: hold, so the gate sees no step after repair
                self.ticks += 1
                # Event-driven: a new mds-ref-mux frame wakes the loop at once (stepped by the time since the
                # previous step). Without one: the next tick while the output moves, a heartbeat at rest.
                deadline = last_step + (period if core.moving() else IDLE_PERIOD)
                if core.retracted:  # the daemon's next cycle must be seen before the one after (``settle_retractions``)
                    deadline = min(deadline, time.monotonic() + RETRACTION_POLL)
                frame = guard.call(inp.name, inp.wait, timeout=max(0.0, deadline - time.monotonic()))
                if frame is None and guard.failing(inp.name):  # a broken input answers at once: keep the pace
                    self._stop.wait(max(0.0, last_step + period - time.monotonic()))
        finally:
            inp.close()
            out.close()
            state_ch.close()
            daemon_status.close()
            mux_state.close()
            gate_out.close()
            watch.close()


# --------------------------------------------------------------------------------------------- ROS node


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="filter",
        description="Reference smoother: reads mds-ref-mux, writes mds-ref-smooth at a fixed rate with a "
                    "per-joint mode (velocity_limit 1.57 rad/s, 4 rad/s^2 by default, ema, enc_filter, pass; "
                    "config/filter.yaml). Starts from the current reference: no jump when started late.",
        epilog="Example: ros2 run mds_ach filter --rate 50",
    )
    p.add_argument("--config", help="filter YAML (default: the package's config/filter.yaml)")
    p.add_argument("--rate", type=find(PARAMETERS, "rate").arg_type(),
                   help="loop rate in Hz (overrides the config; default 40)")
    return p


NODE_NAME = "filter"  # the ROS node name (`ros2 param`, the sections of a params file)

PARAMETERS = (
    Param("config", "", "filter YAML; empty: the package's config/filter.yaml (option --config)"),
    Param("rate", DEFAULT_RATE, "loop and publish rate in Hz; overrides the config's rate (option --rate)",
          range=(0.1, 1000.0), default_doc="config `rate` (`40.0`)"),
)


class FilterNode(Node):
    """The filter: ``FilterRunner`` on its own thread; parameters ``config`` and ``rate`` are read at start."""

    def __init__(self, config: str | None = None, rate: float | None = None) -> None:
        super().__init__(NODE_NAME)
        path = declare(self, find(PARAMETERS, "config"), config) or None
        configured = load_config(path).rate  # the config's own rate is the parameter's default
        self.rate: float = declare(self, find(PARAMETERS, "rate"), configured if rate is None else rate)
        self.params = load_config(path, self.rate)
        self.runner = FilterRunner(self.params, log=ros_log(self), rt_priority=HANDOFF_RT_PRIORITY)
        self.thread = start_worker(self, self.runner.run, "filter")

    def shutdown(self) -> None:
        self.runner.stop()
        self.thread.join(timeout=3.0)


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(argv, _build_parser(), lambda args: FilterNode(config=args.config, rate=args.rate))


if __name__ == "__main__":
    raise SystemExit(main())
