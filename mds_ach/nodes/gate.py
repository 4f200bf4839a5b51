"""The collision gate's decision (``Gate``): one reference in, the reference the daemon may have out, with the
report. Pure computation on numpy arrays and the collision model; ``mds_ach.nodes.collision`` runs it on the
channels (``GateRunner``) and as a ROS node.

Every reference is checked before it can reach the daemon, in this order:

1. **Validation.** NaN/Inf or out-of-limit values (the effective limits, ``mds_ach.kinematics.limits``: URDF
   & joint table, the numbers every entry point refuses) and unknown ref modes (not 0..3) are never passed on:
   those joints keep their last sent value and mode. The refusal is logged once per change of what is refused
   and counted (``refused_count`` in ``mds/collision``).
2. **Speed bound.** No joint moves faster than ``max_velocity`` between two outputs (wall time; a pause
   credits at most ``max_dt``; the first reference after start moves nothing). Joints that were held come
   back at ``release_velocity`` (the filter's speed) until they have caught up with the input.
3. **Collision check** of what the robot will really do (``mds_ach.kinematics.collision``: self-collision and world
   objects, clearance ``margin``). The robot is somewhere between where it is (``mds-state`` ``pos`` of fresh
   joints) and where it is sent (the reference); in mode 2 the daemon's target *is* the measured position,
   in mode 3 a blend. So every combination of {reference, measured pose} of the three units left arm, right
   arm and body (waist + neck) is checked: up to 8 configurations in one batched check (a unit measured
   within 1e-4 rad of its reference counts once; without a recent ``mds-state``, the reference alone).
   A reference is *blocked* when, in some configuration, it adds a colliding pair or lowers the total
   clearance of the colliding pairs (signed distance of the un-inflated shapes) below what the previous
   output had there, with the same measured pose. The arm(s) whose reference moved into the contact are held
   at their previous output while the rest goes through; if the waist or neck moved it, every modelled joint
   is held. So an arm in contact, measured or commanded, can always be moved out of it (such a move is
   reported as *escaping*), never further in. An arm in contact whose input does not ask it to move is held
   too.
4. **Approach to contact** (paper §4.2/§4.3: the hands stop when the parts of the collision model touch). An
   arm never goes where it could no longer stop before a contact: the poses it would pass through if it braked
   now (its step's direction kept, the fastest joint decelerating at ``brake_accel``, below the daemon's bound)
   are checked with the step, and when they block, the arms that moved into the contact move by the largest
   fraction of their step (the same for all of them) from which they can still stop, found by bisection
   (``approach_iterations``: within step / 2**n). So the reference decelerates onto the contact within the
   daemon's bounds, and the daemon follows it there instead of passing an abrupt stop by v²/2a. When even
   step / 2**n blocks, an arm first *rests*: its reference frozen but not flagged (not a hold: the daemon
   withholds nothing and sees no reference move) until ``mds-state`` shows the daemon's rate-limited target
   there (at most ``release_wait``), because a flag would stop the arm where that target lags. Then it is held
   as in 3. An arm whose own measured pose is in contact is held at once. "Touching" is on the gate's model:
   the shapes inflated by ``margin / 2`` touch, i.e. the un-inflated clearance is the margin; they never
   overlap. ``approach_iterations: 0``: no braking, an arm is held at its last safe step.

**Stopped at contact: the command ends.** An arm held because its *own* reference moved into the contact (the
arm taken at its reference in a blocking configuration and its input moved this frame) is *stopped at contact*:
once per hold episode the runner puts a ``HOLD_CANCEL`` on ``mds-hold`` for its joints at the reference it is
held at (source ``collision``, reason ``stopped at contact: right hand / left hand``), so the mux ends that
target and the arm does not go on to it later when the obstacle moves away; only a new command moves it. An arm
held because the other arm (or the waist, or its measured pose) came to it is not cancelled: its command did not
fail. ``mds/collision`` reports ``stopped`` (arm -> ``stopped at contact: <its part> / <the other part>``) until
that arm's reference moves again. Until then its input does not bring it back toward the contact: what is left of
the cancelled command (the mux may not have applied the cancel yet) finds the arm resting or held, as at the stop,
never approaching it again (which would stop it at another point and cancel again).

**Holding and releasing agree with ``mds-collide``.** The daemon withholds the targets of an arm whose parts
``mds-collide`` flags (``daemon_loop._collision_held``). So the gate flags exactly the arms it holds, keeps an
arm held for ``release_time`` after the last blocked reference (the legacy hysteresis, now on the hold itself,
not only on the report), then clears the flag and keeps publishing the held reference until the daemon has
taken a report without the flag (``mds-state`` echoes ``mds-collide`` in ``state.collide``; ``release_wait``
bounds the wait), and only then moves the arm on, at ``release_velocity``. The daemon therefore never sees an
arm's reference move while it withholds that arm, and never sends accumulated distance in one frame.
"""


from __future__ import annotations

import ctypes
import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import mds_ach as mds
from mds_ach import paths
from mds_ach.kinematics.collision import CheckResult, load_yaml
from mds_ach.kinematics.limits import EffectiveLimits, current_limits
from mds_ach.nodes import filters
from mds_ach.nodes.pipeline import (
    KNOWN_ADDRESSES,
    labels,
)
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, MODEL_JOINTS, NECK, RIGHT_ARM, TORSO
from mds_ach.robot.msgs import MDS_COLLIDE, MDS_COLLIDE_JNT_NUM, MDS_JOINT_COUNT, MDS_JOINT_STATE, MDS_STATE

ARM_ADDRESSES: dict[str, np.ndarray] = {
    "left": np.array([BY_SHORT[n].address for n in LEFT_ARM]),
    "right": np.array([BY_SHORT[n].address for n in RIGHT_ARM]),
}
MODEL_ADDRESSES = np.array([BY_SHORT[n].address for n in MODEL_JOINTS])
COLLIDE_BLOCKED = 1
COLLIDE_OVERRIDDEN = 2
COLLIDE_CONTACT = 3

# Units the gate holds independently: each arm, and the body (waist + neck), whose motion moves both arms.
UNITS: tuple[str, ...] = ("left", "right", "body")
UNIT_ADDRESSES: dict[str, np.ndarray] = {
    **ARM_ADDRESSES, "body": np.array([BY_SHORT[n].address for n in TORSO + NECK])}
_UNIT_Q = {u: np.array([list(MODEL_ADDRESSES).index(a) for a in UNIT_ADDRESSES[u]]) for u in UNITS}  # in q
_UNIT_OF_GROUP = {"left": "left", "right": "right", "body": "body", "head": "body"}  # 'world' moves with nothing
ARM_PARTS: dict[str, tuple[int, ...]] = {
    "left": (mds.COLLIDE_L_HAND, mds.COLLIDE_L_SHOULDER, mds.COLLIDE_L_FOREARM, mds.COLLIDE_L_ELBOW,
             mds.COLLIDE_L_WRIST),
    "right": (mds.COLLIDE_R_HAND, mds.COLLIDE_R_SHOULDER, mds.COLLIDE_R_FOREARM, mds.COLLIDE_R_ELBOW,
              mds.COLLIDE_R_WRIST),
}
SAME_POSE = 1e-4  # rad: a unit measured this close to its reference is checked once (0.06 mm at the hand)
CLOSER = 1e-6  # m: colliding pairs whose total clearance drops by more than this are "brought closer"

Choice = tuple[bool, bool, bool]  # per unit (left, right, body): True = its measured pose, False = its reference
# Every choice of {reference, measured} per unit in itertools.product order, and for each the q columns taken
# measured: _config_rows builds all the configurations of many poses in one array operation.
_CHOICES: tuple[Choice, ...] = tuple(itertools.product((False, True), (False, True), (False, True)))
_UNIT_COLUMNS = np.zeros((len(UNITS), len(MODEL_ADDRESSES)), dtype=bool)
for _k, _u in enumerate(UNITS):
    _UNIT_COLUMNS[_k, _UNIT_Q[_u]] = True
_CHOICE_MASK = np.array([np.any(_UNIT_COLUMNS[list(c)], axis=0) for c in _CHOICES])
# Which units are measured away from their reference -> the choices to check (a unit at its reference: once).
_CHOICES_FOR = {apart: [c for c in _CHOICES if all(a or not m for m, a in zip(c, apart, strict=True))]
                for apart in _CHOICES}
# The same by the code of a pattern (its row in _CHOICES: 4 left + 2 right + body), for many poses at once: which of
# the 8 rows of _CHOICE_MASK a pose with that pattern is checked in.
_APART_CODE = np.array([4, 2, 1])
_ROWS_FOR_CODE = np.array([[c in _CHOICES_FOR[apart] for c in _CHOICES] for apart in _CHOICES])

FREE, HELD, RELEASING = "free", "held", "releasing"
STOPPED_AT_CONTACT = "stopped at contact"
IDLE_REPORT_PERIOD = 0.5  # s: mds-collide at rest (no input, nothing held, no contact, no override for 1 s)
STOP_TOUCH = 0.005  # m beyond the margin: an arm stopped at contact still rests there (held, flagged, reported)
AHEAD_STEP = 0.05  # rad (fastest joint): spacing of the poses checked along an arm's braking path
_FRACTIONS: dict[int, np.ndarray] = {}  # n -> (1..n) / n as a column: where the n poses of a braking path lie


@dataclass(frozen=True)
class GateConfig:
    max_velocity: float | None = 2.0  # rad/s, None = no bound
    max_dt: float = 0.05  # s, longest interval the speed bound credits (>= 2 filter periods)
    release_time: float = 0.1  # s, hysteresis of a hold (and of its report)
    counter_max: int = 240
    override_max: float = 10.0  # s
    report_rate: float = 10.0  # Hz
    release_velocity: float | None = None  # rad/s of a released joint; None = filters.DEFAULT_MAX_VELOCITY
    state_timeout: float = 0.5  # s: an older mds-state gives no measured pose
    release_wait: float = 1.0  # s: longest wait for the daemon to echo a cleared report
    approach_iterations: int = 6  # bisection steps toward a contact (resolution: step / 2**n); 0 = hold at once
    brake_accel: float = 4.0  # rad/s^2: an arm approaching a contact brakes at this rate (<= the daemon's bound)
    input_period: float = 0.025  # s: the filter's period; a late frame's step counts as made in this time

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], where: str = "collision config") -> GateConfig:
        def num(key: str, default: float | None, positive: bool = True, allow_none: bool = False) -> float | None:
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
            release_velocity=num("release_velocity", None, allow_none=True),
            state_timeout=num("state_timeout", 0.5),  # type: ignore[arg-type]
            release_wait=num("release_wait", 1.0),  # type: ignore[arg-type]
            approach_iterations=_count(data, "approach_iterations", 6, where),
            brake_accel=num("brake_accel", 4.0),  # type: ignore[arg-type]
            input_period=num("input_period", 0.025),  # type: ignore[arg-type]
        )


def _count(data: Mapping[str, Any], key: str, default: int, where: str) -> int:
    value = data.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 20:
        raise ValueError(f"{where}: {key} must be an integer 0..20, got {value!r}")
    return value


_JOINT_STATE = np.dtype({"names": ["ref", "pos", "active"], "formats": ["<f8", "<f8", "u1"],
                         "offsets": [MDS_JOINT_STATE.ref.offset, MDS_JOINT_STATE.pos.offset,
                                     MDS_JOINT_STATE.active.offset],
                         "itemsize": ctypes.sizeof(MDS_JOINT_STATE)})
"""The fields of ``MDS_JOINT_STATE`` (packed, the wire layout) that ``Observed`` reads."""


@dataclass(frozen=True)
class Observed:
    """What the daemon reports back on ``mds-state``: the measured pose and the ``mds-collide`` it acted on."""

    pos: np.ndarray  # (100) measured position, NaN where the joint is not fresh (state.joint[].active == 0)
    time: float  # state.time (CLOCK_MONOTONIC)
    collide_time: float  # state.collide.time: the stamp of the newest gate report the daemon has taken
    sent: np.ndarray | None = None  # (100) state.joint[].ref: the daemon's last target sent (None: not known)

    @classmethod
    def from_state(cls, state: MDS_STATE) -> Observed:
        """Stale joints (``active`` 0) count as unknown: the gate then takes them where they are commanded. Read as
        one numpy view of ``state.joint[]`` (2 us, 160 us field by field): the gate does this on every mds-state
        frame, also at rest."""
        j = np.frombuffer(memoryview(state).cast("B"), dtype=_JOINT_STATE, count=MDS_JOINT_COUNT)
        pos = np.where(j["active"] != 0, j["pos"], math.nan)
        return cls(pos, float(state.time), float(state.collide.time), j["ref"].astype(float))


@dataclass
class Decision:
    """What the gate did with one reference."""

    ref: np.ndarray
    mode: np.ndarray
    result: Any  # CheckResult: predicted collisions of the (validated, speed-bounded) input, every configuration
    held: tuple[str, ...] = ()  # 'left', 'right' or 'all': flagged on mds-collide, reference frozen
    refused: tuple[int, ...] = ()  # addresses refused by validation
    overridden: bool = False  # a predicted collision passed because of the expert override
    releasing: tuple[str, ...] = ()  # units no longer flagged, frozen until the daemon has taken the clear report
    escaping: tuple[str, ...] = ()  # arms in contact whose reference moves them out of it (passed)
    contacts: Any = None  # CheckResult: contacts of the output (with the measured pose) -- in contact now
    measured: bool = False  # the measured pose was part of the check
    stopped: dict[str, str] = field(default_factory=dict)  # arms stopped at contact in THIS frame -> the pair


@dataclass
class _PartState:
    last: float = -math.inf  # last contact (held or not)
    held: float = -math.inf  # last time its arm was held for a contact of this part
    start: float = -math.inf
    count: int = 0


@dataclass
class _Unit:
    state: str = FREE
    held_at: float = -math.inf  # last (re)hold: held while now - held_at <= release_time
    released_at: float = -math.inf
    stamp: float | None = None  # time of the first report without the hold (what the daemon must echo)


def _merge(results: Iterable[Any]) -> Any:
    """One CheckResult with every pair of ``results`` once (the smallest clearance)."""
    best: dict[tuple[str, str], Any] = {}
    for r in results:
        for c in r.contacts:
            old = best.get((c.a, c.b))
            if old is None or c.clearance < old.clearance:
                best[(c.a, c.b)] = c
    return CheckResult(tuple(best[k] for k in sorted(best)))


@dataclass
class Gate:
    """The gate's decision logic on arrays (no channels, no ROS): ``process()`` one reference at a time."""

    model: Any  # mds_ach.kinematics.collision.CollisionModel
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
        self.current = self.model.check(self.model.q_from_ref(self.ref))  # contacts of the output
        self.override_until = -math.inf
        self.parts = [_PartState() for _ in range(MDS_COLLIDE_JNT_NUM)]
        self.units = {u: _Unit() for u in UNITS}
        self.release_velocity = self.config.release_velocity or filters.DEFAULT_MAX_VELOCITY
        self._ramp = np.zeros(MDS_JOINT_COUNT, dtype=bool)  # released joints still catching up with the input
        self._cache: dict[bytes, Any] = {}  # configuration -> CheckResult (a pure function of it), see _check
        self._model_limits = (self.lower[self.model.addresses], self.upper[self.model.addresses])
        self._columns: dict[tuple[str, ...], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self.last_report = self.now
        self._override_time = -math.inf
        self._contact_time = -math.inf
        self._known = np.zeros(MDS_JOINT_COUNT, dtype=bool)
        self._known[list(KNOWN_ADDRESSES)] = True
        self.stopped: dict[str, str] = {}  # arm -> "right hand / left hand" while it rests where it was stopped
        self._stop_contact: dict[str, Any] = {}  # arm -> the contact it was stopped at (followed while it rests)
        self._settle_since: dict[str, float] = {}  # arm -> when it came to rest at a contact, unflagged
        # the measured pose of this frame and its model joints (NaN: unknown), see _measured_q; reset every frame
        self._measured: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._base: tuple[np.ndarray | None, dict[Choice, np.ndarray], dict[Choice, Any]] | None = None  # a frame's
        self._ref_q: np.ndarray | None = None  # the previous output in model joints, see _output_q; every frame

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

    # ----- holds

    def held(self, now: float) -> tuple[str, ...]:
        """Units flagged as held at ``now`` (hysteresis ``release_time``), as reported: 'all' or the arms."""
        units = {u for u, s in self.units.items() if now - s.held_at <= self.config.release_time}
        return ("all",) if units == set(UNITS) else tuple(sorted(units - {"body"}))

    def _update_units(self, observed: Observed | None, now: float) -> None:
        """HELD -> RELEASING once ``release_time`` passed without a new hold; RELEASING -> FREE once the daemon
        echoed a report stamped at or after the release (or ``release_wait`` passed, or nothing echoes)."""
        for u in self.units.values():
            if u.state == HELD and now - u.held_at > self.config.release_time:
                u.state, u.released_at, u.stamp = RELEASING, now, None
            if u.state == RELEASING and (
                    observed is None
                    or (u.stamp is not None and observed.collide_time >= u.stamp)
                    or now - u.released_at > self.config.release_wait):
                u.state = FREE

    def _hold(self, units: Iterable[str], now: float) -> None:
        for name in units:
            u = self.units[name]
            u.state, u.held_at = HELD, now

    # ----- configurations

    def _measured_q(self, pos: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
        """The measured pose ``pos`` in model joints, taken at ``q_ref`` (one row or many) where it is not known."""
        if self._measured is None or self._measured[0] is not pos:  # once per frame: the measured joints in q
            measured = pos.take(self.model.addresses)
            self._measured = (pos, measured, np.isnan(measured))
        return np.where(self._measured[2], q_ref, self._measured[1])

    def _config_rows(self, q_ref: np.ndarray, pos: np.ndarray | None) -> tuple[list[list[Choice]], np.ndarray]:
        """Every distinct configuration of each output candidate ``q_ref`` (rows of model joint vectors), in one
        array operation for all of them: per candidate its choices, and the configurations of all candidates
        stacked (candidate by candidate, each in the order of its choices). A unit measured within ``SAME_POSE``
        of its reference counts once (taken at it)."""
        if pos is None:
            return [[(False, False, False)]] * len(q_ref), q_ref
        q_pos = self._measured_q(pos, q_ref)
        codes = (np.abs(q_pos - q_ref) > SAME_POSE) @ _UNIT_COLUMNS.T @ _APART_CODE  # bool @: any per unit
        every = np.where(_CHOICE_MASK, q_pos[:, None], q_ref[:, None])  # (candidates, 8 choices, joints)
        return [_CHOICES_FOR[_CHOICES[k]] for k in codes.tolist()], every[_ROWS_FOR_CODE[codes]]

    def _analyze(self, x: np.ndarray, pos: np.ndarray | None,
                 new_only: bool = False) -> tuple[dict[Choice, Any], list[tuple[Choice, Any]]]:
        """Check output candidate ``x`` in every configuration. Compared with the previous output in the same
        configuration (same measured pose), a new colliding pair blocks, and so do the pairs that came closer
        when the colliding pairs' total clearance dropped: a move out of contact may trade a little of one pair
        for more of the others (the straight way home from an interlock often does), never the total.
        ``new_only``: only new pairs block (a pose further ahead: the step rule governs pairs already in contact)."""
        choices, rows = self._config_rows(x.take(self.model.addresses)[None], pos)
        results = self._check(rows)
        return dict(zip(choices[0], results, strict=True)), self._compare(choices[0], rows, results, pos, new_only)

    def _output_q(self) -> np.ndarray:
        """The previous output's model joint vector (made once a frame)."""
        if self._ref_q is None:
            self._ref_q = self.ref.take(self.model.addresses)
        return self._ref_q

    def _base_configs(self, pos: np.ndarray | None) -> tuple[dict[Choice, np.ndarray], dict[Choice, dict[Any, float]]]:
        """The previous output in every choice (``_config_rows``: the baseline of ``_compare``), made once a frame, and
        the colliding pairs found there so far (pair -> clearance, filled by ``_compare``)."""
        if self._base is None or self._base[0] is not pos:
            q_ref = self._output_q()
            if pos is None:
                rows = {(False, False, False): q_ref}
            else:
                rows = dict(zip(_CHOICES, np.where(_CHOICE_MASK, self._measured_q(pos, q_ref), q_ref), strict=True))
            self._base = (pos, rows, {})
        return self._base[1], self._base[2]

    def _compare(self, choices: Sequence[Choice], rows: np.ndarray | Sequence[np.ndarray], results: Sequence[Any],
                 pos: np.ndarray | None, new_only: bool) -> list[tuple[Choice, Any]]:
        """The blocking contacts of ``_analyze``: configurations ``rows`` (``choices``) with their ``results``
        against the previous output in the same configurations."""
        hit = [i for i, r in enumerate(results) if r.contacts]
        if not hit:
            return []
        base, pairs = self._base_configs(pos)
        changed = [i for i in hit if not (rows[i] == base[choices[i]]).all()]
        todo = list(dict.fromkeys(choices[i] for i in changed if choices[i] not in pairs))
        for c, r in zip(todo, self._check([base[c] for c in todo]), strict=True):
            pairs[c] = {(k.a, k.b): k.clearance for k in r.contacts}
        blocking = []
        for i in changed:
            c, old, contacts = choices[i], pairs[choices[i]], results[i].contacts
            new = [k for k in contacts if (k.a, k.b) not in old]
            kept = [k for k in contacts if (k.a, k.b) in old]
            closer = sum(k.clearance - old[(k.a, k.b)] for k in kept) < -CLOSER
            blocking += [(c, k) for k in new]
            if closer and not new_only:
                blocking += [(c, k) for k in kept if k.clearance < old[(k.a, k.b)]]
        return blocking

    def _check(self, qs: np.ndarray | Sequence[np.ndarray]) -> list[Any]:
        """``model.check_many``, remembering the answers of recent frames: the previous output's configurations
        (the baseline of every comparison) were checked in the previous frame, a held arm's configurations
        repeat frame after frame, and so do those of a braking path where its arms are taken measured."""
        if not len(qs):
            return []
        rows = qs if type(qs) is np.ndarray else np.array(qs, dtype=float)
        raw, width = rows.tobytes(), rows.shape[1] * rows.itemsize
        keys = [raw[k:k + width] for k in range(0, len(raw), width)]
        cache = self._cache
        todo: dict[bytes, int] = {}
        for k, key in enumerate(keys):
            if key not in cache and key not in todo:
                todo[key] = k
        if todo:
            new = rows if len(todo) == len(keys) else rows[list(todo.values())]
            cache.update(zip(todo, self.model.check_many(new), strict=True))
        return [cache[k] for k in keys]

    def _moves(self, x: np.ndarray, unit: str) -> bool:
        """Whether output candidate ``x`` moves ``unit`` from the previous output."""
        return not np.array_equal(x[UNIT_ADDRESSES[unit]], self.ref[UNIT_ADDRESSES[unit]])

    def _movers(self, blocking: list[tuple[Choice, Any]], x: np.ndarray) -> set[str]:
        """Units whose reference moved into the blocking contacts; every unit if the body (waist, neck) did."""
        moved = {u: self._moves(x, u) for u in UNITS}
        out: set[str] = set()
        for choice, contact in blocking:
            for group in (contact.group_a, contact.group_b):
                unit = _UNIT_OF_GROUP.get(group)
                if unit is None:
                    continue
                if unit != "body" and not choice[UNITS.index(unit)] and moved[unit]:
                    out.add(unit)
                if not choice[2] and moved["body"]:
                    out.add("body")
        return set(UNITS) if "body" in out or not out else out

    def _own_contacts(self, blocking: list[tuple[Choice, Any]], x: np.ndarray) -> dict[str, Any]:
        """Arm -> the closest blocking contact its OWN reference moved into (the arm taken at its reference in
        that configuration, and its reference moved this frame). Contacts another unit brought to a resting arm,
        or that only its measured pose is in, are not its own."""
        out: dict[str, Any] = {}
        for arm in ("left", "right"):
            if not self._moves(x, arm):
                continue
            mine = [k for c, k in blocking if not c[UNITS.index(arm)] and arm in (k.group_a, k.group_b)]
            if mine:
                out[arm] = min(mine, key=lambda k: k.clearance)
        return out

    def _braking_path(self, x: np.ndarray, arms: Iterable[str], dt: float) -> np.ndarray:
        """``x`` and the poses it would pass through if its moving ``arms`` started braking now, as model joint
        vectors (rows; ``x`` first): each arm keeps the direction of its step from the previous output (all its
        joints scaled alike, so the hand stays on its path) while its fastest joint decelerates at
        ``brake_accel``; checked every ``AHEAD_STEP`` rad and where they stop. A step is taken as made in at most
        ``input_period`` (a late frame does not make it slower)."""
        q = x.take(self.model.addresses)
        h = min(dt, self.config.input_period)
        if h <= 0:
            return q[None]
        step = q - self._output_q()  # from the previous output
        moving: list[str] = []
        scale: list[float] = []
        reach = 0.0
        for arm in arms:
            fastest = float(np.abs(step[_UNIT_Q[arm]]).max())
            if fastest > 0:  # stopping distance v^2 / 2a of the fastest joint, v = fastest / h
                k = fastest / (2.0 * self.config.brake_accel * h * h)
                moving.append(arm)
                scale.append(k)
                reach = max(reach, fastest * k)
        n = math.ceil(reach / AHEAD_STEP) if moving else 0
        path = np.empty((n + 1, len(q)))
        path[:] = q
        if n:
            idx, sizes, lower, upper = self._arm_columns(tuple(moving))
            fraction = _FRACTIONS.get(n)
            if fraction is None:
                fraction = _FRACTIONS[n] = np.arange(1, n + 1)[:, None] / n
            e = step[idx] * np.repeat(scale, sizes)
            path[1:, idx] = np.minimum(np.maximum(q[idx] + e * fraction, lower), upper)
        return path

    def _arm_columns(self, arms: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The model joint columns of ``arms`` (in order), their count per arm, and their limits."""
        out = self._columns.get(arms)
        if out is None:
            idx = np.concatenate([_UNIT_Q[a] for a in arms])
            lower, upper = self._model_limits
            out = self._columns[arms] = (idx, np.array([len(_UNIT_Q[a]) for a in arms]), lower[idx], upper[idx])
        return out

    def _blocks(self, x: np.ndarray, pos: np.ndarray | None, arms: Iterable[str],
                dt: float) -> list[tuple[Choice, Any]]:
        """The blocking contacts of output candidate ``x``, or else of the first pose on its ``arms``' braking
        path that has any: an arm must not go where it could no longer stop before a contact. ``x`` and its path
        are checked a few poses per call (the C screen's loop, not one call per pose: the bisection of
        ``_approach`` runs this up to ``approach_iterations`` times a frame), then judged in order, as one by one."""
        choices, rows = self._config_rows(self._braking_path(x, arms, dt), pos)
        ends = list(itertools.accumulate(len(cs) for cs in choices))
        results: list[Any] = []
        k, size = 0, 2
        for pose, cs in enumerate(choices):
            if len(results) < ends[pose]:  # x and the next pose, then the next 4, 8...: a path that blocks early
                results += self._check(rows[k:ends[min(len(ends), pose + size) - 1]])  # ends its checks early
                size *= 2
            got = results[k:k + len(cs)]
            if any(r.contacts for r in got):
                blocking = self._compare(cs, rows[k:k + len(cs)], got, pos, new_only=pose > 0)
                if blocking:
                    return blocking
            k += len(cs)
        return []

    def _approach(self, cand: np.ndarray, cand_mode: np.ndarray, frozen: set[str], arms: set[str],
                  pos: np.ndarray | None, dt: float) -> np.ndarray | None:
        """The blocked ``arms`` moved by the largest fraction of their step (the same for all of them) from which
        they can still brake before the contact, found by bisection in ``approach_iterations`` steps; frozen
        units stay, the rest moves as input. None when even the smallest fraction tried blocks: the arms
        are at the contact, hold them. Braking this way, the reference decelerates within ``brake_accel`` and
        the daemon follows it onto the contact instead of passing it by its own braking distance."""
        base, _ = self._freeze(cand, cand_mode, frozen)
        idx = np.concatenate([UNIT_ADDRESSES[u] for u in sorted(arms)])
        start, step = self.ref[idx], cand[idx] - self.ref[idx]
        lo, hi, best = 0.0, 1.0, None
        for _ in range(self.config.approach_iterations):
            mid = 0.5 * (lo + hi)
            x = base.copy()
            x[idx] = start + mid * step
            if self._blocks(x, pos, arms, dt):
                hi = mid
            else:
                lo, best = mid, x
        return best

    def _freeze(self, cand: np.ndarray, cand_mode: np.ndarray, units: Iterable[str]) -> tuple[np.ndarray, np.ndarray]:
        out, out_mode = cand.copy(), cand_mode.copy()
        for u in units:
            idx = UNIT_ADDRESSES[u]
            out[idx], out_mode[idx] = self.ref[idx], self.mode[idx]
        return out, out_mode

    # ----- the decision

    def _invalid(self, ref: np.ndarray, mode: np.ndarray) -> np.ndarray:
        """The entries validation refuses (kept at their last output): NaN/Inf, out of limits, unknown mode."""
        return ~np.isfinite(ref) | (ref < self.lower) | (ref > self.upper) | (mode < 0) | (mode > 3)

    def pending(self, ref: np.ndarray, mode: np.ndarray) -> bool:
        """Would processing the same input ``ref``/``mode`` again change something? True while a unit is held or
        releasing, an arm settles at a contact, a released joint ramps back, or a valid input value is not
        passed yet (the speed bound, a hold, a rest). The runner then re-processes its newest input at the
        filter's period (``input_period``): the input stream stops when the filter comes to rest, the gate's
        timed transitions (``release_time``, the daemon's echo, the ramp back) must not."""
        if self._settle_since or self._ramp.any() or any(u.state != FREE for u in self.units.values()):
            return True
        ref = np.asarray(ref, dtype=float)
        differs = (ref != self.ref) & self._known & ~self._invalid(ref, np.asarray(mode))
        return bool(differs.any())

    def process(self, ref: np.ndarray, mode: np.ndarray, now: float, observed: Observed | None = None) -> Decision:
        self._measured = self._base = self._ref_q = None
        ref = np.asarray(ref, dtype=float)
        mode = np.asarray(mode, dtype=np.int16)
        cand = ref.copy()
        cand_mode = mode.copy()
        bad = self._invalid(ref, mode)
        cand[bad] = self.ref[bad]
        cand_mode[bad] = self.mode[bad]
        refused = tuple(int(a) for a in np.flatnonzero(bad & self._known))
        # The first reference after start gets no credit: whatever the input says, the output starts from where
        # the daemon is (a restarted gate must not step).
        dt = 0.0 if self._first else min(max(now - self.last_time, 0.0), self.config.max_dt)
        if self.config.max_velocity is not None:
            step = self.config.max_velocity * dt
            cand = self.ref + np.clip(cand - self.ref, -step, step)
        # Joints released from a hold come back at the release speed until they have caught up.
        step = self.release_velocity * dt
        lag = cand - self.ref
        cand[self._ramp] = self.ref[self._ramp] + np.clip(lag[self._ramp], -step, step)
        self._ramp &= np.abs(lag) > step

        overriding = self.override_remaining(now) > 0
        if overriding:  # nothing is held: clear the flags at once, release through the daemon echo as usual
            for u in self.units.values():
                u.held_at = -math.inf
            for p in self.parts:
                p.held = -math.inf
        pos = None
        if observed is not None and now - observed.time <= self.config.state_timeout:
            pos = observed.pos
        self._update_units(observed, now)

        if len(self._cache) > 512:
            self._cache.clear()
        res, blocking = self._analyze(cand, pos)
        result = _merge(res.values())
        frozen = {n for n, u in self.units.items() if u.state != FREE}
        if not blocking and not overriding and self.config.approach_iterations > 0:
            moving = [a for a in ("left", "right") if self._moves(cand, a)]
            blocking = self._blocks(cand, pos, moving, dt) if moving else []  # could it still stop in time?
        out, out_mode, res_out, blocked = cand, cand_mode, res, set()
        overridden = bool(blocking) and overriding
        seen = list(blocking)  # contacts that decide holds and flags
        stopping: dict[str, Any] = {}  # arm -> the contact its own reference is stopped at in this frame
        own: dict[str, Any] = {}  # arm -> the blocking contact its own reference moved into
        settle: set[str] = set()  # arms resting at the contact, unflagged, until the daemon's target is there
        if overridden and frozen:  # released by the override: still waiting for the daemon's echo
            out, out_mode = self._freeze(cand, cand_mode, frozen)
            res_out = self._analyze(out, pos)[0]
        elif not overridden:
            blocked = self._movers(blocking, cand) if blocking else set()
            own = self._own_contacts(blocking, cand) if blocking else {}
            approach = blocked - frozen
            if approach and "body" not in blocked and self.config.approach_iterations > 0:
                # Approach to contact: the arms that moved into it go the safe part of their step.
                # An arm already stopped at contact does not approach it again on what is left of its cancelled
                # command (the gate's cancel may not have reached the mux yet): it rests or is held, as at the stop.
                part = None if approach <= set(self.stopped) else \
                    self._approach(cand, cand_mode, frozen, approach, pos, dt)
                settle = set() if part is not None else self._settling(approach, observed, now)
                if part is not None or settle:  # replaces their input; the rules below apply as to any input
                    arms = approach if part is not None else settle
                    idx = np.concatenate([UNIT_ADDRESSES[u] for u in sorted(arms)])
                    cand, cand_mode = cand.copy(), cand_mode.copy()
                    if part is not None:
                        cand[idx] = part[idx]
                        self._ramp[idx] = True  # braking behind the input: catch up at the release speed later
                    else:  # at the contact: rest there, unflagged, until the daemon's target has arrived
                        cand[idx], cand_mode[idx] = self.ref[idx], self.mode[idx]
                        stopping = {a: k for a, k in own.items() if a in settle}
                    res_out, blocking = self._analyze(cand, pos)
                    out, out_mode, seen = cand, cand_mode, list(blocking)
                    blocked = self._movers(blocking, cand) if blocking else set()
                    own = self._own_contacts(blocking, cand) if blocking else {}
            held = frozen | blocked
            if held:
                out, out_mode = self._freeze(cand, cand_mode, held)
                res_out, more = self._analyze(out, pos)
                while more:  # the rest of the input runs into a frozen unit: hold those units too
                    extra = (self._movers(more, out) - held) or set(UNITS) - held
                    if not extra:
                        break
                    seen += more
                    held |= extra
                    blocked |= extra
                    out, out_mode = self._freeze(cand, cand_mode, held)
                    res_out, more = self._analyze(out, pos)
        contacts = _merge(res_out.values())
        # An arm in contact whose input does not ask it to move stays held (and flagged); one that moves passes.
        involved = [(c, k) for c, r in res_out.items() for k in r.contacts] + seen
        static = {u for u in ("left", "right")  # (an arm settling at a contact is not flagged yet)
                  if u not in settle and not self._moves(cand, u)}
        resting = {} if overridden else self._resting(static, out, pos)
        involved += [((False, False, False), k) for k in resting.values()]
        touching = {_UNIT_OF_GROUP.get(g) for _, k in involved for g in (k.group_a, k.group_b)}
        renewed = set() if overridden else blocked | (static & touching) | set(resting)
        if renewed - blocked:
            out, out_mode = self._freeze(out, out_mode, renewed - blocked)  # the mode stays too
        stopping.update({a: k for a, k in own.items() if a in renewed})
        stopped = self._stop_at_contact({} if overridden else stopping)
        self._settle_since = {a: t for a, t in self._settle_since.items() if a in settle}
        self._hold(renewed, now)
        for n, u in self.units.items():
            if u.state != FREE:
                self._ramp[UNIT_ADDRESSES[n]] = True
        escaping = tuple(sorted(u for u in ("left", "right") if u in touching and self.units[u].state == FREE))
        self._track(involved, renewed, now, overridden)
        self.ref, self.mode, self.current, self.last_time = out, out_mode, contacts, now
        self._first = False
        releasing = tuple(n for n, u in self.units.items() if u.state == RELEASING)
        return Decision(out.copy(), out_mode.copy(), result, self.held(now), refused, overridden, releasing,
                        escaping, contacts, pos is not None, stopped)

    def _settling(self, arms: set[str], observed: Observed | None, now: float) -> set[str]:
        """Arms at a contact between references whose daemon target has not arrived there yet: they rest at the
        contact unflagged (a flag would make the daemon withhold them where its rate-limited target happens to
        be, short of the contact), for at most ``release_wait`` s; then, or when nothing echoes, they are held as
        usual. An arm whose measured pose is in contact now (a compliant arm, an arm moved by hand) is held at
        once. A blocking contact that only involves the lagging measured pose of a moving arm is not a reason:
        the frozen reference passed every configuration before, so the daemon may take the arm there."""
        out: set[str] = set()
        if observed is None or observed.sent is None or now - observed.time > self.config.state_timeout:
            return out
        touching: set[str] = set()
        choices, rows = self._config_rows(self._output_q()[None], observed.pos)
        for choice, result in zip(choices[0], self._check(rows), strict=True):
            touching |= {u for u in ("left", "right") if choice[UNITS.index(u)]
                         and any(u in (k.group_a, k.group_b) for k in result.contacts)}
        for arm in arms - touching:
            start = self._settle_since.setdefault(arm, now)
            idx = UNIT_ADDRESSES[arm]
            if now - start <= self.config.release_wait and \
                    np.abs(observed.sent[idx] - self.ref[idx]).max() > SAME_POSE:
                out.add(arm)
        return out

    def _stop_at_contact(self, stopping: Mapping[str, Any]) -> dict[str, str]:
        """Arms stopped at contact in this frame (held or settling there because their own reference moved into
        the contact) that were not stopped already: their command ends there (the runner cancels it on
        ``mds-hold``). ``self.stopped`` keeps the pair for the reports until the arm is free again and not
        pushing on (after the cancel the mux sends it the held reference: it rests, is released, and clears)."""
        for arm in list(self.stopped):
            if arm not in stopping and self.units[arm].state == FREE:
                del self.stopped[arm]
                self._stop_contact.pop(arm, None)
        new = {}
        for arm, contact in stopping.items():
            if arm not in self.stopped:
                new[arm] = self.stopped[arm] = contact_pair(contact, arm)
                self._stop_contact[arm] = contact
        return new

    def _resting(self, static: set[str], out: np.ndarray, pos: np.ndarray | None) -> dict[str, Any]:
        """Arms stopped at contact that still rest there: input unchanged and the stop's pair still touching
        (clearance within ``margin`` + ``STOP_TOUCH``, with the rest of the robot at its reference or measured).
        They stay held and flagged with that pair, so ``mds-collide`` reports the stop for as long as it lasts
        (the cancel made their input the held reference, which by itself would no longer collide)."""
        out_of_reach = self.model.margin + STOP_TOUCH
        resting = {}
        for arm, contact in self._stop_contact.items():
            if arm not in static:
                continue
            poses = [out]
            if pos is not None:
                mixed = pos.copy()
                mixed[UNIT_ADDRESSES[arm]] = out[UNIT_ADDRESSES[arm]]
                poses.append(mixed)
            if min(self.model.clearance(self.model.q_from_ref(q), contact.a, contact.b) for q in poses) \
                    <= out_of_reach:
                resting[arm] = contact
        return resting

    def reseed(self, addresses: np.ndarray, positions: np.ndarray) -> None:
        """Restart these joints' output where they are (``pipeline.ReseedWatch``: after HOME, reset, resetbus)."""
        self.ref[addresses] = positions
        self.current = self.model.check(self.model.q_from_ref(self.ref))

    # ----- reporting

    def _track(self, involved: list[tuple[Choice, Any]], renewed: set[str], now: float, overridden: bool) -> None:
        """Part states: contact times, and hold times for the parts of the arms held now."""
        arms = {"left", "right"} & renewed
        hit: set[int] = set()
        held: set[int] = set()
        touching: set[str] = set()
        for _, k in involved:
            for group, part in ((k.group_a, k.part_a), (k.group_b, k.part_b)):
                touching.add(group)
                if part >= 0:
                    hit.add(part)
                    if group in arms:
                        held.add(part)
        for arm in arms & touching:  # held for a primitive without a legacy part: flag the whole arm
            if not held & set(ARM_PARTS[arm]):
                held |= set(ARM_PARTS[arm])
        for p, st in enumerate(self.parts):
            if p in hit or p in held:
                if now - st.last > self.config.release_time:
                    st.start, st.count = now, 0
                st.last = now
                st.count = min(st.count + 1, self.config.counter_max)
            elif now - st.last > self.config.release_time:
                st.count = 0
            if p in held:
                st.held = now
        if involved:
            self._contact_time = now
            if overridden:
                self._override_time = now

    def report(self, now: float) -> MDS_COLLIDE:
        """The legacy ``mds-collide`` frame for ``now`` (hysteresis on wall time); see the module doc."""
        rt = self.config.release_time
        c = MDS_COLLIDE()
        holding = bool(self.held(now))
        if holding:
            c.isCollide = COLLIDE_BLOCKED
        elif now - self._override_time <= rt:
            c.isCollide = COLLIDE_OVERRIDDEN
        elif now - self._contact_time <= rt:
            c.isCollide = COLLIDE_CONTACT
        for p, st in enumerate(self.parts):
            active = now - st.last <= rt
            j = c.joint[p]
            j.collision = st.count if active else 0
            j.isCollide = int(now - st.held <= rt if holding else active and c.isCollide != 0)
            j.time = st.last if math.isfinite(st.last) else 0.0
            j.time_dt = now - st.start if active else 0.0
        c.time = now
        c.time_dt = now - self.last_report
        self.last_report = now
        for u in self.units.values():
            if u.state == RELEASING and u.stamp is None:
                u.stamp = now  # the first report without its hold: once the daemon echoes it, the unit moves
        return c


def part_label(primitive: str) -> str:
    """A primitive's name for people: 'right_hand_link' -> 'right hand', 'world:table' -> 'table'."""
    name = primitive.removeprefix("world:").split("#", 1)[0].removesuffix("_link")
    return name.replace("_", " ")


def contact_pair(contact: Any, arm: str) -> str:
    """'right hand / left hand': the stopped arm's part first, then what it touches."""
    a, b = part_label(contact.a), part_label(contact.b)
    return f"{a} / {b}" if contact.group_a == arm else f"{b} / {a}"


def decision_to_dict(d: Decision | None, gate: Gate, now: float, refused_count: int = 0) -> dict[str, Any]:
    """The JSON document of mds/collision (``refused_count``: references refused by validation so far)."""
    res = d.result if d is not None else gate.current
    now_contacts = d.contacts if d is not None else gate.current
    return {
        "time": now,
        "collision": bool(res.collides),
        "pairs": sorted([c.a, c.b] for c in res.contacts),
        "parts": [mds.COLLIDE_PART_NAMES[p] for p in sorted(res.parts)],
        "contact": sorted([c.a, c.b] for c in now_contacts.contacts),
        "held": list(gate.held(now)),
        "releasing": list(d.releasing) if d is not None else [],
        "escaping": list(d.escaping) if d is not None else [],
        "measured": bool(d.measured) if d is not None else False,
        "refused": [labels([a]) for a in d.refused] if d is not None else [],
        "refused_count": refused_count,
        "overridden": bool(d.overridden) if d is not None else False,
        "override_remaining": round(gate.override_remaining(now), 3),
        "margin": gate.model.margin,
        "stopped": {arm: f"{STOPPED_AT_CONTACT}: {pair}" for arm, pair in sorted(gate.stopped.items())},
    }


def joint_limits(model: Any, limits: EffectiveLimits | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-address limits: the effective limits (``mds_ach.kinematics.limits``: URDF & joint table, ``mds-limits``
    when the daemon published them), narrowed further by this gate's model when it was given another URDF."""
    lower, upper = (limits or current_limits()).arrays()
    lower[model.addresses] = np.maximum(lower[model.addresses], model.lower)
    upper[model.addresses] = np.minimum(upper[model.addresses], model.upper)
    return lower, upper


def load_config(path: str | Path | None = None) -> dict[str, Any]:
    path = Path(path) if path else paths.config_path("collision.yaml")
    if not path.is_file():
        raise ValueError(f"collision config {path} not found")
    return load_yaml(path)


