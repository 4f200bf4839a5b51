"""Joint mux (``ros2 run mds_ach mux``): merges the references of several controllers into ``mds-ref-mux``.

Each controller writes whole ``MDS_REF`` frames to its own input channel (config/mux.yaml). The rule:

* a joint changes only when a controller *modified* it (compared with that controller's previous frame; the
  first frame after start is compared with the mux output) **and** holds write permission for it:
  the joint is in the controller's ``joints`` and no higher-priority controller currently owns it;
* a controller that modifies a permitted joint becomes its owner; ownership lasts while the controller is
  fresh. A controller goes *stale* ``timeout`` seconds after its last frame that changed anything (a client
  re-sending the same frame is holding, not commanding); its joints are then released and fall back to
  whoever changes them next. The output keeps its last value until then: no jump.

The controllers (config/mux.yaml): ``ros`` (``mds-ref-ros``), ``ik`` (``mds-ref-ik``), ``default``
(``mds-ref-filter``) and ``direct`` (``mds-ref``: the channel the original daemon executed, written by expert clients
and ``achd push mds-ref``; highest priority, unsmoothed by the filter, still limit-checked here and gated).

Why "modified" rather than "newest frame wins": legacy clients read-modify-write a whole frame (console
``goto`` changes one joint and re-sends the other 99 as they were). Only real changes are commands.

Legacy inputs (``legacy: true``: ``default`` on ``mds-ref-filter``, ``direct`` on ``mds-ref``): every put is a command,
as on the original, where the daemon executed the newest frame whatever it was. A put (a new Ach sequence number;
the readers wake on each one, identical values included) commands the joints it modified *and* re-asserts the joints
whose value another controller moved away from it -- except joints held or cancelled (or re-seeded after HOME) while
the frame carried that value: a client re-putting the same frame at 50 Hz cannot release a hold or revive a cancelled
command; a different value (a new command) or RESUME (for held joints) does. Values outside the effective limits are
clamped to them (the original hardware stopped at its limits), logged once per change of the clamped joints and
reported as ``VERDICT_CLAMPED`` with ``clamped[]`` naming them; NaN/Inf still refuses the frame. ``ros`` and ``ik``
keep "modified only" and whole-frame refusal: their senders validate and stream on purpose.

Event-based: one thread per input blocks on its channel and queues frames; the mux thread applies them in
arrival order and publishes ``mds-ref-mux`` on every output change. Ownership and ages go to
``mds-mux-state`` (``mds_ach.robot.msgs.MDS_MUX_STATE``) and to the ROS topic ``mds/mux_state``
(``mds_ach_interfaces/msg/MuxState``, made from the document of ``state_to_dict``).

At start the output is the current reference (``mds-ref-gated``, else ``mds-state`` joint[].ref), published once
so the filter holds still; frames already waiting in the input channels are taken as each controller's
previous frame, not applied (they are old commands). Controllers with ``seed: true`` (the legacy
``mds-ref-filter`` and ``mds-ref``) get the start reference written to their channel, as the original mds-filter did, so
read-modify-write clients start from the real pose instead of zeros.
"""

from __future__ import annotations

import argparse
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mds_ach_interfaces.msg import MuxState
from rclpy.node import Node

import mds_ach as mds
from mds_ach.kinematics.limits import EffectiveLimits, current_limits
from mds_ach.nodes.pipeline import (
    HANDOFF_RT_PRIORITY,
    KNOWN_ADDRESSES,
    ChannelGuard,
    ReseedWatch,
    cancel_wait,
    handoff_thread,
    joint_label,
    labels,
    make_ref,
    ref_arrays,
    select_joints,
    wait_current_reference,
)
from mds_ach.nodes.rosnode import Param, declare, find, ros_log, run_node, start_worker
from mds_ach.nodes.status_msgs import MUX_STATE_TOPIC, mux_state_msg
from mds_ach.paths import config_path
from mds_ach.ratelog import EVERY_S, RateLimitedLog
from mds_ach.robot import contracts
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_JOINT_COUNT, Name30, get_name
from mds_ach.robot.msgs.hold import HOLD_ACTIONS, HOLD_HOLD, HOLD_RESUME, MDS_HOLD, check_cancel, check_hold
from mds_ach.robot.msgs.mux_state import (  # noqa: F401  (mux.MDS_MUX_STATE)
    MDS_MUX_STATE,
    MUX_CANCELLED,
    MUX_FREE,
    MUX_HELD,
    MUX_HOLD_DONE,
    MUX_HOLD_REASON_SIZE,
    MUX_HOLD_REFUSED,
    MUX_MAX_CONTROLLERS,
    VERDICT_APPLIED,
    VERDICT_CLAMPED,
    VERDICT_INVALID,
    VERDICT_NAMES,
    VERDICT_NONE,
    VERDICT_NOT_PERMITTED,
    VERDICT_OWNED,
)

DEFAULT_STATE_RATE = 10.0
HOLD_INPUT = -1
"""Queue index of an ``mds-hold`` request (controller inputs are 0..n-1)."""
IDLE_STATE_PERIOD = 0.5
"""s: ``mds-mux-state`` at rest (nothing received, nothing changed); half of ``muxverdict.LIVE_AGE``."""
READER_TIMEOUT = 5.0
"""s: the input readers' wait; a put wakes them at once and ``stop()`` cancels the wait, so this only bounds how
long a reader sleeps (each wake-up costs CPU at rest)."""


# --------------------------------------------------------------------------------------------- config


@dataclass(frozen=True)
class Controller:
    """One mux input (one entry of config/mux.yaml ``controllers``)."""

    name: str
    channel: str
    priority: int
    joints: tuple[int, ...]  # permitted addresses
    timeout: float | None  # s after its last change until it goes stale; None = never stale
    seed: bool = False
    legacy: bool = False  # every put is a command (re-puts re-assert), out-of-limit values clamped (not refused)
    # Dead-man (issue #31): the controller promises a frame at least every ``heartbeat`` s (re-puts count). Once it has
    # streamed, a longer silence holds the joints it owns (a protective stop: the filter brakes them to rest), never
    # a continuation of its last command; only a new command (a modified value) releases them. None: no heartbeat.
    heartbeat: float | None = None


def parse_controllers(entries: Sequence[Mapping[str, Any]], where: str = "mux config") -> list[Controller]:
    """Validate the ``controllers`` list: unique names, channels and priorities, known joints, timeout > 0."""
    if not entries:
        raise ValueError(f"{where}: no controllers configured")
    if len(entries) > MUX_MAX_CONTROLLERS:
        raise ValueError(f"{where}: at most {MUX_MAX_CONTROLLERS} controllers, got {len(entries)}")
    out: list[Controller] = []
    for k, e in enumerate(entries):
        if not isinstance(e, Mapping):
            raise ValueError(f"{where}: controllers[{k}] must be a mapping")
        name = str(e.get("name", "")).strip()
        here = f"{where}: controller {name or k!r}"
        unknown = set(e) - {"name", "channel", "priority", "joints", "timeout", "seed", "legacy", "heartbeat"}
        if unknown:
            raise ValueError(f"{here}: unknown keys {sorted(unknown)}")
        if not name or len(name.encode()) >= 30:
            raise ValueError(f"{here}: needs a name of 1..29 characters")
        channel = str(e.get("channel", "")).strip()
        if not channel:
            raise ValueError(f"{here}: needs an input channel")
        channel = contracts.channel_name(channel)  # the file names the original channels; a prefixed system's own
        if channel in (mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME):
            raise ValueError(f"{here}: {channel} is a pipeline output, not a controller input")
        try:
            priority = int(e["priority"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{here}: needs an integer priority (higher wins)") from None
        joints = select_joints(e.get("joints", "all"), f"{here} joints")
        timeout = e.get("timeout")
        if timeout is not None:
            timeout = float(timeout)
            if not (math.isfinite(timeout) and timeout > 0):
                raise ValueError(f"{here}: timeout must be > 0 s (or null for never stale)")
        heartbeat = e.get("heartbeat")
        if heartbeat is not None:
            try:
                heartbeat = float(heartbeat)
            except (TypeError, ValueError):
                heartbeat = math.nan
            if not (math.isfinite(heartbeat) and heartbeat > 0):
                raise ValueError(f"{here}: heartbeat must be > 0 s (the longest gap between its frames), or null")
        out.append(Controller(name, channel, priority, joints, timeout, bool(e.get("seed", False)),
                              bool(e.get("legacy", False)), heartbeat))
    for attr, plural in (("name", "names"), ("channel", "channels"), ("priority", "priorities")):
        values = [getattr(c, attr) for c in out]
        dupes = sorted({str(v) for v in values if values.count(v) > 1})
        if dupes:
            raise ValueError(f"{where}: controller {plural} must be unique, repeated: {', '.join(dupes)}")
    return out


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    """config/mux.yaml (or ``path``) -> {'controllers': [Controller...], 'state_rate': Hz}."""
    path = Path(path) if path else config_path("mux.yaml")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except FileNotFoundError:
        raise ValueError(f"mux config {path} not found") from None
    if not isinstance(data, Mapping):
        raise ValueError(f"{path}: expected a mapping")
    rate = float(data.get("state_rate", DEFAULT_STATE_RATE))
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"{path}: state_rate must be > 0 Hz")
    return {"controllers": parse_controllers(data.get("controllers") or [], str(path)), "state_rate": rate}


def controller_for(channel: str, path: str | Path | None = None) -> str:
    """The mux controller that reads ``channel`` (config/mux.yaml); the channel name itself if none does."""
    try:
        for c in load_config(path)["controllers"]:
            if c.channel == channel:
                return str(c.name)
    except (ValueError, OSError):
        pass
    return channel


# --------------------------------------------------------------------------------------------- merge logic


class MuxCore:
    """The merge rule and the hold state, without channels or threads (so it can be tested exactly). Times are
    wall seconds."""

    def __init__(self, controllers: Sequence[Controller], ref: np.ndarray, mode: np.ndarray,
                 limits: EffectiveLimits | None = None) -> None:
        self.controllers = list(controllers)
        self.limits = limits  # the one limit authority (mds-limits): refuses (ros, ik) or clamps (legacy inputs)
        bounds = limits.arrays() if limits is not None else (np.empty(0), np.empty(0))
        self._lower: np.ndarray = bounds[0]
        self._upper: np.ndarray = bounds[1]
        n = len(self.controllers)
        self.ref = np.array(ref, dtype=float)
        self.mode = np.array(mode, dtype=np.int16)
        self.owner = np.full(MDS_JOINT_COUNT, -1, dtype=np.int8)
        self._permit = np.zeros((n, MDS_JOINT_COUNT), dtype=bool)
        for i, c in enumerate(self.controllers):
            self._permit[i, list(c.joints)] = True
        self._known = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        self._known[list(KNOWN_ADDRESSES)] = True
        self._prio = np.array([c.priority for c in self.controllers])
        self._prev: list[tuple[np.ndarray, np.ndarray] | None] = [None] * n
        # [i, a]: controller i's current value for joint a was held, cancelled or re-seeded: a re-put of it is not
        # a command (a hold must hold against a client that keeps re-putting); a different value clears it.
        self._settled = np.zeros((n, MDS_JOINT_COUNT), dtype=bool)
        self.clamped = np.zeros(MDS_JOINT_COUNT, dtype=np.uint8)  # bit i: controller i's newest frame clamped here
        self.clamp_message: str | None = None  # the newest update's clamping, for the (rate-limited) log
        self.last_frame = np.full(n, -math.inf)
        self.last_change = np.full(n, -math.inf)
        self.refused = np.zeros(n, dtype=int)
        self.verdict = np.full(n, VERDICT_NONE, dtype=np.int8)
        self.blocker = np.full(n, -1, dtype=np.int8)
        self.blocked_joint = np.full(n, -1, dtype=np.int8)
        self.held = np.full(MDS_JOINT_COUNT, MUX_FREE, dtype=np.uint8)
        self.hold_seq = 0
        self.hold_action = 0
        self.hold_status = MUX_HOLD_DONE
        self.hold_source = ""
        self.hold_reason = ""  # why the newest request was refused (mds-mux-state hold_reason)
        self.dirty = False  # the held mask or a verdict changed: publish mds-mux-state now, not at the next tick
        self.beat_lost = np.zeros(n, dtype=bool)  # its heartbeat stopped and its joints were held

    def absorb(self, index: int, ref: np.ndarray, mode: np.ndarray) -> None:
        """Take a frame as the controller's previous frame without applying it (old frames at start-up)."""
        self._prev[index] = (np.array(ref, dtype=float), np.array(mode, dtype=np.int16))

    def stale(self, index: int, now: float) -> bool:
        timeout = self.controllers[index].timeout
        if self.last_change[index] == -math.inf:
            return True
        return timeout is not None and now - self.last_change[index] > timeout

    def _verdict(self, index: int, verdict: int, blocker: int = -1, joint: int = -1) -> None:
        if (self.verdict[index], self.blocker[index], self.blocked_joint[index]) != (verdict, blocker, joint):
            self.dirty = True
        self.verdict[index], self.blocker[index], self.blocked_joint[index] = verdict, blocker, joint
        if verdict in (VERDICT_OWNED, VERDICT_NOT_PERMITTED, VERDICT_INVALID):
            self.refused[index] += 1
            self.dirty = True

    def refusal_kind(self, index: int) -> tuple[int, int, int]:
        """What controller ``index``'s newest verdict refused, without the values: (verdict, blocker, joint). A
        refusal log writes one line per change of it (mds_ach.ratelog)."""
        return int(self.verdict[index]), int(self.blocker[index]), int(self.blocked_joint[index])

    def clamped_kind(self, index: int) -> tuple[int, ...]:
        """The joints controller ``index``'s newest frame was clamped at (the clamping log's kind)."""
        return tuple(int(a) for a in np.flatnonzero(self.clamped & np.uint8(1 << index)))

    def update(self, index: int, ref: np.ndarray, mode: np.ndarray, now: float) -> tuple[bool, str | None]:
        """Apply one frame (one put) of controller ``index``. Returns (output changed, refusal message or None).

        The joints it commands: those it *modified* (compared with its previous frame) and, for a legacy input
        (``legacy: true``: every put is a command, as on the original), those whose value differs from the output
        because another controller moved them (``reasserted``) unless held or cancelled while the controller's
        frame carried that value (``_settled``: only a different value, a new command, releases them).

        Atomic: the frame is applied to all of the joints it commands or to none. Refused as a whole when it has
        NaN/Inf in a known joint, when it commands a joint the controller is not permitted (config ``joints``),
        or when a fresh, higher-priority controller owns one of them (the message names it). A non-legacy input's
        frame commanding a value outside the effective limits (mds-limits) is refused too; a legacy input's value
        is clamped to them instead (``VERDICT_CLAMPED``, ``clamp_message``). A commanded joint that was held or
        cancelled is released: a new command for it.
        """
        ref = np.asarray(ref, dtype=float)
        mode = np.asarray(mode, dtype=np.int16)
        name = self.controllers[index].name
        legacy = self.controllers[index].legacy
        self.last_frame[index] = now
        self.beat_lost[index] = False  # streaming again (the joints it held stay held until a new command)
        self.clamp_message = None
        bad = self._known & ~np.isfinite(ref)
        if bad.any():
            self._verdict(index, VERDICT_INVALID, joint=int(np.flatnonzero(bad)[0]))
            return False, f"refused a frame from '{name}': non-finite reference for {labels(np.flatnonzero(bad))}"
        prev = self._prev[index]
        base_ref, base_mode = prev if prev is not None else (self.ref, self.mode)
        modified = self._known & ((ref != base_ref) | (mode != base_mode))
        self._prev[index] = (ref.copy(), mode.copy())
        self._settled[index, modified] = False  # a different value: a new command, holds no longer apply
        target = ref
        outside = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        if self.limits is not None:
            outside = self._known & ((ref < self._lower) | (ref > self._upper))
            if legacy:
                target = np.where(outside, np.clip(ref, self._lower, self._upper), ref)
        command = modified.copy()
        if legacy:
            command |= self._known & ~self._settled[index] & ((target != self.ref) | (mode != self.mode))
        if not command.any():
            return False, None
        outside &= command
        if outside.any() and not legacy:
            self._verdict(index, VERDICT_INVALID, joint=int(np.flatnonzero(outside)[0]))
            assert self.limits is not None
            why = "; ".join(self.limits.problems({int(a): float(ref[a]) for a in np.flatnonzero(outside)}))
            return False, f"refused a frame from '{name}' as a whole: {why}; nothing applied"
        self.last_change[index] = now
        self.release_stale(now)
        forbidden = command & ~self._permit[index]
        if forbidden.any():
            self._verdict(index, VERDICT_NOT_PERMITTED, joint=int(np.flatnonzero(forbidden)[0]))
            return False, (f"refused a frame from '{name}' as a whole: it may not move "
                           f"{labels(np.flatnonzero(forbidden))} (config/mux.yaml joints); nothing applied")
        owner = self.owner.astype(int)
        owned = owner >= 0
        owner_prio = np.where(owned, self._prio[np.maximum(owner, 0)], np.iinfo(np.int64).min)
        blocked = command & owned & (owner != index) & (owner_prio > self._prio[index])
        if blocked.any():
            first = int(np.flatnonzero(blocked)[0])
            by = int(owner[first])
            self._verdict(index, VERDICT_OWNED, blocker=by, joint=first)
            blocker = self.controllers[by]
            return False, (f"refused a frame from '{name}' as a whole: {labels(np.flatnonzero(blocked))} owned by "
                           f"'{blocker.name}' (priority {blocker.priority}); nothing applied")
        bit = np.uint8(1 << index)
        clamped = (self.clamped & bit) != 0
        if (clamped != outside).any():
            self.clamped = np.where(outside, self.clamped | bit, self.clamped & ~bit).astype(np.uint8)
            self.dirty = True
        if outside.any():
            self._verdict(index, VERDICT_CLAMPED, joint=int(np.flatnonzero(outside)[0]))
            assert self.limits is not None
            why = "; ".join(self.limits.problems({int(a): float(ref[a]) for a in np.flatnonzero(outside)}))
            self.clamp_message = (f"clamped a frame from '{name}' to the limits: {why}; "
                                  f"{labels(np.flatnonzero(outside))} go to the nearest limit, the rest as sent")
        else:
            self._verdict(index, VERDICT_APPLIED)
        if (self.owner[command] != index).any():
            self.dirty = True  # the filter smooths per owner (config/filter.yaml controllers): tell it now
        self.owner[command] = index
        if (self.held[command] != MUX_FREE).any():
            self.held[command] = MUX_FREE
            self.dirty = True
        changed = command & ((self.ref != target) | (self.mode != mode))
        self.ref[command] = target[command]
        self.mode[command] = mode[command]
        return bool(changed.any()), None

    def hold(self, request: MDS_HOLD, current: np.ndarray | None = None) -> tuple[bool, str]:
        """Handle one ``mds-hold`` request. ``current``: the reference now (``mds-ref-gated``) by address, where a
        CANCEL leaves a joint (None or NaN: the mux output). Returns (output changed, log message).

        HOLD marks the joints held: the filter brakes them to rest and keeps them there (the output keeps the
        controllers' targets, for RESUME). RESUME releases held joints, never cancelled ones. CANCEL drops
        ownership and stops the joints where their reference is now, whoever owns them (stopping is every
        writer's right): NaN joints stay held as cancelled, their output becomes ``current`` and no RESUME
        releases them; only a controller frame that modifies them (a new command) does. Joints with an explicit
        target (the sender's word where the reference stopped, e.g. the collision gate's) get the same output, not
        held; the request is refused as a whole unless every such target is within the limits and near
        ``current`` (``check_cancel``): a CANCEL never moves a joint.
        """
        self.hold_seq = int(request.seq)
        self.hold_action = int(request.action)
        self.hold_source = get_name(bytes(request.source))
        self.dirty = True
        who = f"{HOLD_ACTIONS.get(self.hold_action, str(self.hold_action))} #{self.hold_seq} from " \
              f"'{self.hold_source or '?'}'"
        now = self.ref.copy()
        if current is not None:
            found = np.isfinite(current)
            now[found] = np.asarray(current)[found]
        problem = check_hold(request) or check_cancel(request, self.limits, now.tolist())
        if problem:
            self.hold_status = MUX_HOLD_REFUSED
            self.hold_reason = problem
            return False, f"refused {who}: {problem}; nothing changed"
        self.hold_status = MUX_HOLD_DONE
        self.hold_reason = ""
        mask = np.frombuffer(bytes(request.joints), dtype=np.uint8).astype(bool) & self._known
        if not mask.any():
            mask = self._known.copy()
        reason = request.reason.decode("ascii", "replace")
        text = f"{who}: {labels(np.flatnonzero(mask))}" + (f" ({reason})" if reason else "")
        changed = False
        if self.hold_action == HOLD_HOLD:
            self.held[mask & (self.held == MUX_FREE)] = MUX_HELD
            self._settled[:, mask] = True
        elif self.hold_action == HOLD_RESUME:
            resumed = mask & (self.held == MUX_HELD)
            self.held[resumed] = MUX_FREE
            self._settled[:, resumed] = False  # the hold is over: a re-put commands again
        else:
            self._settled[:, mask] = True
            target = np.array(request.target, dtype=float)
            self.owner[mask] = -1
            given = mask & np.isfinite(target)
            here = mask & ~given
            new = np.where(mask, now, self.ref)
            changed = bool((new != self.ref).any())
            self.ref = new
            self.held[given] = MUX_FREE
            self.held[here] = MUX_CANCELLED
        return changed, text

    def heartbeats(self, now: float) -> list[str]:
        """Hold the joints of every controller whose heartbeat stopped (its newest frame is older than its
        ``heartbeat``, after it streamed at all); one message per controller that stopped."""
        out = []
        for i, c in enumerate(self.controllers):
            if c.heartbeat is None or self.beat_lost[i] or self.last_frame[i] == -math.inf:
                continue
            if now - self.last_frame[i] <= c.heartbeat:
                continue
            self.beat_lost[i] = True
            mine = (self.owner == i) & self._known
            stop = mine & (self.held == MUX_FREE)
            self.held[stop] = MUX_HELD
            self._settled[:, mine] = True  # a re-put of the old values is no command: only a new one releases
            self.dirty = True
            out.append(f"'{c.name}' sent nothing for {now - self.last_frame[i]:.3f} s (heartbeat {c.heartbeat:g} s): "
                       + (f"protective stop, {labels(np.flatnonzero(stop))} held until a new command or resume"
                          if stop.any() else "it owns no joint"))
        return out

    def next_heartbeat(self) -> float:
        """When the next heartbeat expires (monotonic s; inf: none pending)."""
        due = [self.last_frame[i] + c.heartbeat for i, c in enumerate(self.controllers)
               if c.heartbeat is not None and not self.beat_lost[i] and self.last_frame[i] > -math.inf]
        return min(due, default=math.inf)

    def reseed(self, addresses: np.ndarray, positions: np.ndarray) -> None:
        """Restart these joints' output where they are (``pipeline.ReseedWatch``); ownership is unchanged. A
        client re-putting its pre-HOME frame does not drive them back: only a new value does."""
        self.ref[addresses] = positions
        self._settled[:, addresses] = True

    def release_stale(self, now: float) -> bool:
        """Release the joints of stale controllers (values stay). True if any ownership changed."""
        changed = False
        for i in range(len(self.controllers)):
            if self.stale(i, now):
                mine = self.owner == i
                if mine.any():
                    self.owner[mine] = -1
                    changed = True
        self.dirty |= changed
        return changed

    def next_stale(self) -> float:
        """When the next controller that owns joints goes stale (``release_stale`` then changes something), or inf:
        the runner waits until then, not a polling period."""
        due = math.inf
        for i, c in enumerate(self.controllers):
            if c.timeout is not None and self.last_change[i] > -math.inf and (self.owner == i).any():
                due = min(due, float(self.last_change[i]) + c.timeout + 1e-3)
        return due

    def state(self, now: float, seq: int = 0) -> MDS_MUX_STATE:
        st = MDS_MUX_STATE()
        for a in range(MDS_JOINT_COUNT):
            st.owner[a] = int(self.owner[a])
            st.held[a] = int(self.held[a])
            st.clamped[a] = int(self.clamped[a])
        st.count = len(self.controllers)
        for i, c in enumerate(self.controllers):
            st.priority[i] = c.priority
            st.stale[i] = int(self.stale(i, now))
            st.age[i] = now - self.last_frame[i] if self.last_frame[i] > -math.inf else -1.0
            st.change_age[i] = now - self.last_change[i] if self.last_change[i] > -math.inf else -1.0
            st.name[i] = Name30.from_buffer_copy(c.name.encode("ascii").ljust(30, b"\0"))
            st.verdict[i] = int(self.verdict[i])
            st.blocker[i] = int(self.blocker[i])
            st.blocked_joint[i] = int(self.blocked_joint[i])
            st.refused[i] = int(self.refused[i]) & 0xFFFFFFFF
        st.hold_seq = self.hold_seq
        st.hold_action = self.hold_action
        st.hold_status = self.hold_status
        st.hold_source = self.hold_source.encode("ascii", "replace")[:29]
        st.hold_reason = self.hold_reason.encode("ascii", "replace")[: MUX_HOLD_REASON_SIZE - 1]
        st.time = now
        st.seq = seq
        self.dirty = False
        return st


def state_to_dict(st: MDS_MUX_STATE) -> dict[str, Any]:
    """The JSON document of mds/mux_state: controllers (name, priority, stale, ages, newest verdict, refusals),
    joint owners, held joints and the newest hold request handled."""
    names = st.controller_names()
    held = {MUX_HELD: "held", MUX_CANCELLED: "cancelled"}

    def blocked(i: int) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if st.blocker[i] >= 0 and st.blocker[i] < st.count:
            out["blocker"] = names[st.blocker[i]]
        if st.blocked_joint[i] >= 0:
            out["blocked_joint"] = joint_label(st.blocked_joint[i])
        return out

    return {
        "time": st.time,
        "controllers": [
            {"name": names[i], "priority": st.priority[i], "stale": bool(st.stale[i]),
             "age": None if st.age[i] < 0 else round(st.age[i], 4),
             "change_age": None if st.change_age[i] < 0 else round(st.change_age[i], 4),
             "verdict": VERDICT_NAMES.get(st.verdict[i], str(st.verdict[i])), "refused": st.refused[i],
             "clamped": [joint_label(a) for a in st.clamped_joints(i)], **blocked(i)}
            for i in range(st.count)
        ],
        "owners": {joint_label(a): names[st.owner[a]] for a in KNOWN_ADDRESSES if st.owner[a] >= 0},
        "held": {joint_label(a): held[st.held[a]] for a in KNOWN_ADDRESSES if st.held[a] in held},
        "hold": {"seq": st.hold_seq, "action": HOLD_ACTIONS.get(st.hold_action, ""),
                 "source": get_name(bytes(st.hold_source)),
                 "status": "refused" if st.hold_status == MUX_HOLD_REFUSED else "done",
                 "reason": st.hold_reason.decode("ascii", "replace")},
    }


# --------------------------------------------------------------------------------------------- Ach side


class MuxRunner:
    """Channels and threads around ``MuxCore``. ``run()`` blocks until ``stop()``; no ROS in here."""

    def __init__(self, controllers: Sequence[Controller], state_rate: float = DEFAULT_STATE_RATE,
                 log: Callable[[str, str], None] | None = None,
                 on_state: Callable[[MDS_MUX_STATE], None] | None = None,
                 output: str = mds.MDS_CHAN_REF_MUX_NAME,
                 sources: Sequence[str] = (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_STATE_NAME),
                 log_every: float = EVERY_S, rt_priority: int = 0) -> None:
        self.controllers = list(controllers)
        self.rt_priority = rt_priority  # SCHED_FIFO of the readers and the loop (pipeline.HANDOFF_RT_PRIORITY)
        self.state_period = 1.0 / state_rate
        self.log = log or (lambda level, msg: print(f"[mux] {level}: {msg}", flush=True))
        # A refused frame can repeat at the writer's rate: one line per change of reason, repeats counted
        # (the exact count per controller is `refused` in mds-mux-state).
        self.refusals = RateLimitedLog(self.log, every=log_every)
        self.on_state = on_state
        self.output_name = output
        self.sources = tuple(sources)
        self._stop = threading.Event()
        self._queue: queue.Queue[tuple[int, Any, float]] = queue.Queue()  # index HOLD_INPUT: an MDS_HOLD
        self._inputs: list[Any] = []
        self._threads: list[threading.Thread] = []
        self.core: MuxCore | None = None
        self._hold_ch: Any = None
        self._current: Any = None
        self._current_ref: np.ndarray | None = None
        # The mux thread's channels (each reader thread has its own guard). No pause after an error: the thread
        # blocks on its queue anyway, and a pause per frame would let the queue grow while a channel is damaged.
        self._guard = ChannelGuard(self.log, self._stop, pause=0.0)
        self._unsent = False  # the newest output could not be written (a damaged mds-ref-mux): write it again
        self.ready = threading.Event()
        self.published = 0
        self.hold_refusals = 0  # mds-hold requests refused since the start

    def stop(self) -> None:
        self._stop.set()
        for ch in self._inputs:
            cancel_wait(ch)
        if self._hold_ch is not None:
            cancel_wait(self._hold_ch)

    def run(self) -> None:
        handoff_thread(self.rt_priority, "mux", self.log)
        found = wait_current_reference(self._stop, lambda m: self.log("info", m), self.sources)
        if found is None:
            return
        ref, mode, source = found
        out = StructChannel(self.output_name, mds.MDS_REF)
        state_ch = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        watch = ReseedWatch(self.log, self._stop)
        core = MuxCore(self.controllers, ref, mode, current_limits())
        hold_ch = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
        hold_ch.flush()  # requests from before this start are old: the output restarts from the reference anyway
        self._hold_ch = hold_ch
        self._current = StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF)
        try:
            for i, c in enumerate(self.controllers):
                ch = StructChannel(c.channel, mds.MDS_REF)
                self._inputs.append(ch)
                old = ch.latest()
                if c.seed:
                    ch.put(make_ref(ref, mode))
                    ch.latest()  # the seed is ours, not a client's put (legacy inputs: every put is a command)
                    core.absorb(i, ref, mode)
                elif old is not None:
                    core.absorb(i, *ref_arrays(old))
            self.core = core
            out.put(make_ref(core.ref, core.mode))
            self.published += 1
            self.log("info", f"started from {source}; inputs: " + ", ".join(
                f"{c.name} <- {c.channel} (priority {c.priority})" for c in self.controllers))
            for i in range(len(self.controllers)):
                t = threading.Thread(target=self._reader, args=(i,), name=f"mux-in-{self.controllers[i].name}",
                                     daemon=True)
                t.start()
                self._threads.append(t)
            t = threading.Thread(target=self._hold_reader, name="mux-hold", daemon=True)
            t.start()
            self._threads.append(t)
            self.ready.set()
            self._loop(core, out, state_ch, watch)
        finally:
            self._stop.set()
            for ch in (*self._inputs, hold_ch):
                cancel_wait(ch)
            for t in self._threads:
                t.join(timeout=2.0)
            for ch in (*self._inputs, hold_ch, self._current):
                ch.close()
            out.close()
            state_ch.close()
            watch.close()

    def _reader(self, index: int) -> None:
        """Block on one input channel; hand every new frame to the mux thread with its arrival time."""
        ch = self._inputs[index]
        # A client that died inside a put leaves its input ACH_CORRUPT: keep this thread alive, say so, and pick
        # the channel up again once `mds-ach repair` fixed it.
        handoff_thread(self.rt_priority, f"mux-in {self.controllers[index].name}")
        guard = ChannelGuard(self.log, self._stop)
        while not self._stop.is_set():
            frame = guard.call(ch.name, ch.wait, timeout=READER_TIMEOUT)
            if frame is not None:
                self._queue.put((index, frame, time.monotonic()))

    def _hold_reader(self) -> None:
        """Every ``mds-hold`` request in order (StructChannel.wait_next): each one counts, none is skipped."""
        handoff_thread(self.rt_priority, "mux-hold")
        guard = ChannelGuard(self.log, self._stop)
        while not self._stop.is_set():
            frame = guard.call(self._hold_ch.name, self._hold_ch.wait_next, timeout=READER_TIMEOUT)
            if frame is not None:
                self._queue.put((HOLD_INPUT, frame, time.monotonic()))

    def _reference_now(self) -> np.ndarray | None:
        """The newest ``mds-ref-gated`` (what the daemon is sent): where a CANCEL without target leaves a joint."""
        frame = self._guard.call(self._current.name, self._current.latest)
        if frame is not None:
            self._current_ref = ref_arrays(frame)[0]
        return self._current_ref

    def _loop(self, core: MuxCore, out: Any, state_ch: Any, watch: ReseedWatch) -> None:
        """Apply the queued frames in arrival order. ``mds-mux-state`` goes out at once after a hold or a verdict
        change, within ``state_period`` after any other frame, at the moment a controller goes stale
        (``MuxCore.next_stale``) and otherwise every ``IDLE_STATE_PERIOD``: at rest the mux sleeps."""
        seq = 0
        next_state = time.monotonic()
        last_state = -math.inf
        while not self._stop.is_set():
            lost = core.heartbeats(time.monotonic())  # (checked on every pass: other inputs may keep the queue busy)
            for text in lost:
                self.log("warning", text)
            if lost:
                next_state = time.monotonic()  # the filter hears of the hold now
            timeout = max(0.0, min(next_state, core.next_stale(), core.next_heartbeat()) - time.monotonic())
            try:
                index, frame, t = self._queue.get(timeout=timeout)
            except queue.Empty:
                self._reseed(core, out, watch)
            else:
                self._reseed(core, out, watch)  # before the frame: a command after HOME starts at the joint
                if index == HOLD_INPUT:
                    before = core.held.copy()
                    changed, text = core.hold(frame, self._reference_now())
                    if core.hold_status == MUX_HOLD_REFUSED:
                        self._log_refusal(text)
                    else:
                        self.log("info", text)
                    if ((core.held != MUX_FREE) & (before == MUX_FREE)).any():
                        # Newly held joints: the state first, then the output again (a put on mds-ref-mux wakes
                        # the filter, which then reads the hold mask): the filter stops them within milliseconds,
                        # in time to hold the daemon's last reference rather than the newest (filter.FilterCore.hold).
                        seq += 1
                        last_state = time.monotonic()
                        self._put_state(core, state_ch, seq, last_state)
                        changed = True
                else:
                    changed, problem = core.update(index, *ref_arrays(frame), t)
                    if problem:
                        self.refusals(self.controllers[index].name, problem, kind=core.refusal_kind(index),
                                      level="error")
                    elif core.clamp_message:  # one line per change of the clamped joints, repeats counted
                        name = self.controllers[index].name
                        self.refusals(f"{name} clamped", core.clamp_message, kind=core.clamped_kind(index))
                if changed:
                    self._publish(core, out)
                next_state = min(next_state, last_state + self.state_period)  # its verdict within a state period
                if core.dirty:  # a hold or a verdict: the filter and the requester hear it now
                    next_state = time.monotonic()
                elif not self._queue.empty():
                    continue
            now = time.monotonic()
            if core.release_stale(now):  # a controller went stale: its joints are free now, and said so
                next_state = now
            if now >= next_state:
                self.refusals.tick()
                if self._unsent:  # mds-ref-mux was unwritable: try the newest merge again, once a state period
                    self._publish(core, out)
                core.release_stale(now)
                seq += 1
                self._put_state(core, state_ch, seq, now)
                last_state = now
                next_state = now + IDLE_STATE_PERIOD

    def _put_state(self, core: MuxCore, state_ch: Any, seq: int, now: float) -> None:
        """Write ``mds-mux-state`` (a damaged channel: the next period tries again)."""
        st = core.state(now, seq)
        self._guard.put(state_ch, st)
        if self.on_state is not None:
            self.on_state(st)

    def _log_refusal(self, text: str) -> None:
        """A refused hold request: counted, logged through the refusal log (the first, then a count per window)."""
        self.hold_refusals += 1
        self.refusals("hold", text, kind="hold-refused", level="error")

    def _publish(self, core: MuxCore, out: Any) -> None:
        """Write the merged reference. While ``mds-ref-mux`` is damaged the write fails (``ChannelGuard`` reports
        it) and the filter downstream keeps smoothing to the last target it has; the loop writes the newest merge
        again every state period until it gets through (after ``mds-ach repair``), so nothing the controllers sent
        meanwhile is lost and the filter ramps to it."""
        self._unsent = not self._guard.put(out, make_ref(core.ref, core.mode))
        if not self._unsent:
            self.published += 1

    def _reseed(self, core: MuxCore, out: Any, watch: ReseedWatch) -> None:
        """Restart the joints the daemon asks for (HOME, reset, resetbus) where they are, and publish that."""
        found = watch.poll()
        if found is not None:
            core.reseed(*found)
            self._publish(core, out)
            self.log("info", f"re-seeded {labels(found[0])} where the joints are (after HOME, reset or resetbus)")


# --------------------------------------------------------------------------------------------- ROS node


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mux",
        description="Joint mux: merges the controllers' reference channels (config/mux.yaml) into mds-ref-mux. "
                    "A joint changes only when a permitted controller changed it and no fresher, higher-priority "
                    "controller owns it. Ownership: mds-mux-state channel and mds/mux_state (JSON).",
        epilog="Example: ros2 run mds_ach mux --config my_mux.yaml   (ROS args: --ros-args -r __node:=mux2)",
    )
    p.add_argument("--config", help="mux YAML (default: the package's config/mux.yaml)")
    return p


NODE_NAME = "mux"  # the ROS node name (`ros2 param`, the sections of a params file)

PARAMETERS = (
    Param("config", "", "mux YAML (controllers, priorities, timeouts); empty: the package's config/mux.yaml "
                        "(option --config)"),
    Param("state_rate", DEFAULT_STATE_RATE, "rate of mds-mux-state and mds/mux_state in Hz while frames arrive (at "
                                            "rest every 0.5 s, at once on a hold, a verdict change or a release); "
                                            "overrides the config's state_rate", range=(0.1, 1000.0),
          default_doc="config `state_rate` (`10.0`)"),
)


class MuxNode(Node):
    """The mux: ``MuxRunner`` on its own thread, its state also on ``mds/mux_state`` (typed)."""

    def __init__(self, config: str | None = None) -> None:
        super().__init__(NODE_NAME)
        path = declare(self, find(PARAMETERS, "config"), config) or None
        cfg = load_config(path)
        self.state_rate: float = declare(self, find(PARAMETERS, "state_rate"), cfg["state_rate"])
        self.pub = self.create_publisher(MuxState, MUX_STATE_TOPIC, 10)
        self._joints = [joint_label(a) for a in KNOWN_ADDRESSES]
        self.runner = MuxRunner(cfg["controllers"], self.state_rate, log=ros_log(self), on_state=self._on_state,
                                rt_priority=HANDOFF_RT_PRIORITY)
        self.thread = start_worker(self, self.runner.run, "mux")

    def _on_state(self, st: MDS_MUX_STATE) -> None:
        listening = self.pub.get_subscription_count() > 0
        if listening and self.context.ok():  # nobody listening: nothing to build; not after SIGINT/SIGTERM
            doc = state_to_dict(st)
            self.pub.publish(mux_state_msg(doc, self._joints, self.get_clock().now().to_msg()))

    def shutdown(self) -> None:
        self.runner.stop()
        self.thread.join(timeout=3.0)


def main(argv: Sequence[str] | None = None) -> int:
    return run_node(argv, _build_parser(), lambda args: MuxNode(config=args.config))


if __name__ == "__main__":
    raise SystemExit(main())
