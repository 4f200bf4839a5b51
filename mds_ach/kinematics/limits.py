"""The one limit authority: effective joint limits = URDF ``<limit>`` intersected with the active joint table,
and what each joint can *follow* (velocity, acceleration).

Before this module the collision gate clamped to URDF and joint table while the console, the bridge, the viewer
and the IK used the joint table alone, so a command could be accepted at the door and refused (forever, silently)
deep in the pipeline. Now every entry point asks :func:`current_limits` and refuses the same numbers with a
message (``EffectiveLimits.problem``).

* :func:`compute` does the intersection (joints the URDF does not model, the hands, eyes and jaw, keep the
  table's range). The table is the robot variant's, after its calibration (``mds_ach.robot.config``).
* The daemon owns the table choice (``--robot``, ``--config``), so it computes them once at start and publishes
  them on ``mds-limits`` (``MDS_LIMITS``); it also narrows its own table with them (:func:`narrow_table`), so it
  clamps to the same numbers as everything upstream.
* :func:`current_limits` reads ``mds-limits`` when a daemon published it and otherwise computes them the same
  way (robot by the one rule, ``mds_ach.robot.choice``), so tools work without a daemon.
* :func:`urdf_with_limits` rewrites a URDF's ``<limit lower/upper velocity>`` so ``/robot_description`` says
  the same.

What a joint can follow (issue #26: a planner must not be told 1.5 rad/s while nothing says what acceleration the
robot can follow), per joint (:func:`followable`):

* acceleration = min(``FEEDFORWARD_ACCEL_SHARE`` (0.75) x the MOVETO acceleration ``A`` the daemon commands
  (``trajectory: acceleration_deg_s2``), ``LIMIT_MARGIN`` x ``motion: max_acceleration_rad_s2``). The MCB runs every
  MOVETO with the commanded acceleration, so no joint follows a faster change of speed; the daemon executes a
  trajectory by sending its stopping point at ``A`` (``mds_ach.robot.feedforward``), and the MCB needs a share of
  ``A`` to catch up with a target that moves. 80 deg/s^2 (1.396 rad/s^2) is ``A``: it is what the original daemon
  sent (``specs/mds-original.md`` section b.4); the only other value on record is 5 deg/s^2 (the June 2015
  captures, LEB and NKY); nothing shows the MCBs or the arms take more, so the daemon does not command more.
  Published: 1.047 rad/s^2;
* velocity = min(the URDF's ``<limit velocity>``, ``LIMIT_MARGIN`` x the daemon's bound ``motion:
  max_velocity_rad_s`` / (1 + acceleration / ``A``)): the stopping-point targets of a trajectory at that speed
  and acceleration move at most ``v (1 + a / A)``, which passes the daemon's limiter unchanged. Published:
  1.029 rad/s;
* jerk: not bounded by this design (a MOVETO switches its acceleration at once), so none is published.

:func:`moveit_yaml` writes these as MoveIt's ``joint_limits.yaml`` (``config/joint_limits.yaml``, by
``mds-ach limits --moveit-yaml``).
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import mds_ach as mds
from mds_ach import paths
from mds_ach.kinematics.model import RobotModel, load_model
from mds_ach.robot import config as joint_config
from mds_ach.robot.joints import BY_ADDRESS, MODEL_JOINTS, lookup
from mds_ach.robot.motion import LIMIT_MARGIN
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_LIMITS, get_name, set_name
from mds_ach.robot.msgs.limits import LIMITS_SOURCE_SIZE, check_limits

CHANNEL = mds.MDS_CHAN_LIMITS_NAME


def _label(address: int) -> str:
    joint = BY_ADDRESS.get(address)
    return joint.short if joint is not None else f"{address:#04x}"


FEEDFORWARD_ACCEL_SHARE = 0.75
"""The share of the MOVETO acceleration a trajectory may use: the MCB needs the rest to catch up with a target
that moves (the daemon sends the trajectory's stopping point, ``mds_ach.robot.feedforward``)."""


def followable(table: joint_config.JointTable, urdf_velocity: float | None = None) -> tuple[float, float]:
    """(velocity rad/s, acceleration rad/s^2) a joint of ``table`` can follow (see the module doc).

    The daemon executes a trajectory by sending, each cycle, its *stopping point* at the MOVETO acceleration ``A``
    (``q + v|v| / 2A``, ``mds_ach.robot.feedforward``): that target sequence moves at up to ``v (1 + a / A)``, and it
    must pass the daemon's limiter (``LIMIT_MARGIN`` x ``motion: max_velocity_rad_s``) unchanged. So: acceleration =
    min(``FEEDFORWARD_ACCEL_SHARE`` x ``A``, the daemon's acceleration bound at its margin); velocity = min(the
    URDF's velocity if modelled (a missing or non-positive one bounds nothing), the daemon's velocity bound at its
    margin / (1 + acceleration / A))."""
    moveto = math.radians(table.accel_deg_s2)
    acceleration = min(FEEDFORWARD_ACCEL_SHARE * moveto, LIMIT_MARGIN * table.max_acceleration)
    velocity = LIMIT_MARGIN * table.max_velocity / (1.0 + acceleration / moveto)
    if urdf_velocity is not None and math.isfinite(urdf_velocity) and urdf_velocity > 0:
        velocity = min(velocity, urdf_velocity)
    return velocity, acceleration


def _nan() -> np.ndarray:
    return np.full(MDS_JOINT_COUNT, math.nan)


@dataclass(frozen=True)
class EffectiveLimits:
    """Per-address ``lower``/``upper`` (rad), ``velocity`` (rad/s) and ``acceleration`` (rad/s^2) a joint can
    follow (NaN where ``valid`` is False), with where they came from."""

    lower: np.ndarray
    upper: np.ndarray
    valid: np.ndarray
    robot: str
    source: str
    published: bool = False
    """Read from ``mds-limits`` (a daemon published them), not computed here."""
    velocity: np.ndarray = field(kw_only=True)
    acceleration: np.ndarray = field(kw_only=True)

    def range(self, joint: int | str) -> tuple[float, float] | None:
        """``(lower, upper)`` of a joint by address or name; None for a joint without limits."""
        address = joint if isinstance(joint, int) else lookup(joint).address
        if not 0 <= address < MDS_JOINT_COUNT or not self.valid[address]:
            return None
        return float(self.lower[address]), float(self.upper[address])

    def motion(self, joint: int | str) -> tuple[float, float] | None:
        """``(velocity, acceleration)`` a joint (address or name) can follow; None for a joint without limits."""
        address = joint if isinstance(joint, int) else lookup(joint).address
        if not 0 <= address < MDS_JOINT_COUNT or not self.valid[address]:
            return None
        return float(self.velocity[address]), float(self.acceleration[address])

    def problem(self, address: int, value: float) -> str | None:
        """Why ``value`` must not be commanded to joint ``address`` (None: it may). Inclusive bounds, no
        tolerance: every stage compares the same doubles the same way."""
        rng = self.range(address)
        if rng is None:
            return f"{_label(address)} has no limits (not in the joint table)"
        if not math.isfinite(value):
            return f"{_label(address)}: {value} is not a finite position"
        lo, hi = rng
        if not lo <= value <= hi:
            return (f"{value:.5f} rad is outside {_label(address)}'s range [{lo:.5f}, {hi:.5f}] rad (the effective "
                    f"limits: {self.describe()})")
        return None

    def problems(self, targets: Mapping[int, float]) -> list[str]:
        """``problem`` of every (address, value), in address order; empty when all may be commanded."""
        return [p for a, v in sorted(targets.items()) if (p := self.problem(a, v)) is not None]

    def out_of_limits(self, refs: np.ndarray, addresses: Iterable[int]) -> list[int]:
        """Those of ``addresses`` whose value in the 100-entry ``refs`` is outside (or non-finite)."""
        return [int(a) for a in addresses if self.problem(int(a), float(refs[a])) is not None]

    def describe(self) -> str:
        """Where the numbers come from, for messages: 'URDF & joint table, robot default'."""
        return f"URDF & joint table, robot {self.robot}"

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-address (lower, upper) with -inf/+inf where a joint has no limits (the gate's form)."""
        lo = np.where(self.valid, self.lower, -math.inf)
        hi = np.where(self.valid, self.upper, math.inf)
        return lo, hi

    def by_short(self, names: Sequence[str]) -> dict[str, tuple[float, float]]:
        """``{short name: (lower, upper)}`` for those of ``names`` that have limits."""
        out = {}
        for n in names:
            rng = self.range(n)
            if rng is not None:
                out[lookup(n).short] = rng
        return out

    def of(self, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) vectors for ``names`` in that order (the IK solver's bounds)."""
        addresses = [lookup(n).address for n in names]
        return self.lower[addresses].copy(), self.upper[addresses].copy()

    def to_msg(self, seq: int = 1, now: float | None = None) -> MDS_LIMITS:
        msg = MDS_LIMITS()
        msg.seq = seq
        for a in range(MDS_JOINT_COUNT):
            msg.valid[a] = int(bool(self.valid[a]))
            msg.lower[a] = float(self.lower[a]) if self.valid[a] else math.nan
            msg.upper[a] = float(self.upper[a]) if self.valid[a] else math.nan
            msg.velocity[a] = float(self.velocity[a]) if self.valid[a] else math.nan
            msg.acceleration[a] = float(self.acceleration[a]) if self.valid[a] else math.nan
        set_name(msg, "robot", self.robot)
        msg.source = self.source.encode("ascii", "replace")[: LIMITS_SOURCE_SIZE - 1]
        msg.time = time.monotonic() if now is None else now
        return msg

    @classmethod
    def from_msg(cls, msg: MDS_LIMITS) -> EffectiveLimits:
        valid = np.array([bool(msg.valid[a]) for a in range(MDS_JOINT_COUNT)])
        lower = np.where(valid, np.array(msg.lower[:]), math.nan)
        upper = np.where(valid, np.array(msg.upper[:]), math.nan)
        velocity = np.where(valid, np.array(msg.velocity[:]), math.nan)
        acceleration = np.where(valid, np.array(msg.acceleration[:]), math.nan)
        return cls(lower, upper, valid, get_name(bytes(msg.robot)), msg.source.decode("ascii", "replace"),
                   published=True, velocity=velocity, acceleration=acceleration)


def _short_path(path: str | Path) -> str:
    p = Path(path)
    try:
        return str(p.resolve().relative_to(paths.share_dir()))
    except (ValueError, FileNotFoundError):
        return str(p)


def compute(table: joint_config.JointTable | None = None, robot: str | None = None,
            urdf: str | Path | RobotModel | None = None) -> EffectiveLimits:
    """URDF ``<limit>`` intersected with ``table`` (default: the chosen robot's, ``config.load(robot)``), and what
    each joint can follow (:func:`followable`).

    A joint the URDF models takes ``[max(lowers), min(uppers)]``; the others keep the table's range. An empty
    intersection is a configuration error, refused with both ranges named.
    """
    table = joint_config.load(robot) if table is None else table
    model = urdf if isinstance(urdf, RobotModel) else load_model(urdf)
    lower, upper, velocity, acceleration = _nan(), _nan(), _nan(), _nan()
    valid = np.zeros(MDS_JOINT_COUNT, dtype=bool)
    for j in table:
        lo, hi = j.lower, j.upper
        modelled = model.joints.get(j.short)
        if modelled is not None and not modelled.actuated:
            modelled = None
        if modelled is not None:
            lo, hi = max(lo, modelled.lower), min(hi, modelled.upper)
            if lo > hi:
                raise joint_config.ConfigError(
                    f"joint {j.short}: the joint table's range [{j.lower:.4f}, {j.upper:.4f}] and the URDF's "
                    f"[{modelled.lower:.4f}, {modelled.upper:.4f}] ({model.source}) do not overlap")
        lower[j.address], upper[j.address], valid[j.address] = lo, hi, True
        velocity[j.address], acceleration[j.address] = followable(table, modelled.velocity if modelled else None)
    files = [_short_path(model.source)] + [_short_path(s) for s in table.sources]
    return EffectiveLimits(lower, upper, valid, table.robot, f"{files[0]} & {' + '.join(files[1:]) or 'table'}",
                           velocity=velocity, acceleration=acceleration)


def narrow_table(table: joint_config.JointTable, limits: EffectiveLimits) -> joint_config.JointTable:
    """``table`` with every joint's ``lower``/``upper`` narrowed to ``limits`` (the daemon clamps to these);
    a home pose outside is moved to the nearest limit."""
    joints = []
    for j in table:
        rng = limits.range(j.address)
        if rng is not None:
            lo, hi = max(j.lower, rng[0]), min(j.upper, rng[1])
            j = replace(j, lower=lo, upper=hi, home=min(max(j.home, lo), hi))
        joints.append(j)
    return replace(table, joints=tuple(joints))


def read_published() -> EffectiveLimits | None:
    """The limits on ``mds-limits``, or None when no daemon published any (no channel, no frame, or a frame that
    fails the contract's check)."""
    from mds_ach.robot.channels import StructChannel  # Ach only when a running system is asked

    try:
        chan = StructChannel.of(CHANNEL, create=False)
    except Exception:  # no channel (no system on this machine), or one the stack must not trust
        return None
    try:
        msg = chan.latest()
    except Exception:
        return None
    finally:
        chan.close()
    if msg is None or msg.seq == 0 or check_limits(msg) is not None:
        return None
    return EffectiveLimits.from_msg(msg)


def current_limits(robot: str | None = None) -> EffectiveLimits:
    """What every entry point checks against: the daemon's published limits, else :func:`compute` for ``robot``
    (default: the one rule of ``mds_ach.robot.choice``). An explicit ``robot`` other than the published one is
    computed, never mixed."""
    published = read_published()
    if published is not None and (robot is None or robot.strip().lower() == published.robot):
        return published
    return compute(robot=robot)


_LIMIT = re.compile(r"<limit\b[^>]*/?>", re.S)
_JOINT = re.compile(r"<joint\b[^>]*\bname\s*=\s*[\"']([^\"']+)[\"'][^>]*>(.*?)</joint>", re.S)


def _set_attr(tag: str, name: str, value: float) -> str:
    text = f'{name}="{float(value)!r}"'
    pattern = re.compile(rf"\b{name}\s*=\s*[\"'][^\"']*[\"']")
    if pattern.search(tag):
        return pattern.sub(text, tag, count=1)
    return tag.replace("<limit", f"<limit {text}", 1)


def urdf_with_limits(text: str, limits: EffectiveLimits) -> str:
    """The URDF text with each modelled joint's ``<limit lower upper velocity>`` replaced by the effective values
    (everything else byte for byte), so ``/robot_description`` agrees with ``mds-limits``: a planner reading only
    the URDF gets the velocity the joint follows (URDF has no acceleration: ``config/joint_limits.yaml``)."""

    def joint(m: re.Match[str]) -> str:
        try:
            rng, dyn = limits.range(m.group(1)), limits.motion(m.group(1))
        except KeyError:  # a fixed joint or one the MDS node table does not know
            return m.group(0)
        if rng is None or dyn is None:
            return m.group(0)

        def limit(t: re.Match[str]) -> str:
            tag = _set_attr(_set_attr(t.group(0), "lower", rng[0]), "upper", rng[1])
            return _set_attr(tag, "velocity", dyn[0]) if math.isfinite(dyn[0]) else tag

        body = _LIMIT.sub(limit, m.group(2))
        return m.group(0)[: m.start(2) - m.start(0)] + body + m.group(0)[m.end(2) - m.start(0):]

    return _JOINT.sub(joint, text)


MOVEIT_YAML = "joint_limits.yaml"
"""MoveIt's joint limits file in ``config/``, generated by :func:`moveit_yaml` (``mds-ach limits --moveit-yaml``)."""


def _num(value: float) -> str:
    """A float as YAML that reads back as the same double (repr round-trips; YAML 1.1 readers such as PyYAML need
    a '.' in the mantissa of an exponent form: 1e-05 -> 1.0e-05)."""
    mantissa, e, exponent = repr(float(value)).partition("e")
    return f"{mantissa}.0e{exponent}" if e and "." not in mantissa else mantissa + e + exponent


def moveit_yaml(limits: EffectiveLimits, names: Sequence[str] = MODEL_JOINTS) -> str:
    """MoveIt's ``joint_limits.yaml`` for ``names`` (the URDF's joints) from ``limits``: positions (as in
    ``/robot_description``), velocity and acceleration the joints follow, no jerk limit (none is bounded)."""
    joints = [(n, rng, dyn) for n in names if (rng := limits.range(n)) is not None and
              (dyn := limits.motion(n)) is not None]
    accel = sorted({d[1] for _n, _r, d in joints})
    lines = [
        "# MoveIt joint limits of the MDS, generated by `mds-ach limits --moveit-yaml` from the limit authority",
        "# (mds_ach.kinematics.limits, the numbers the daemon publishes on mds-limits). Do not edit: change the URDF",
        "# or the joint table and regenerate; test_limits.py keeps this file in step.",
        f"# robot {limits.robot}: {limits.source}",
        "# min/max_position: the effective limits, URDF <limit> & joint table (= /robot_description).",
        f"# max_velocity: min(URDF <limit velocity>, {LIMIT_MARGIN:g} x the joint table's motion: "
        "max_velocity_rad_s).",
        "# max_acceleration: min(the MOVETO acceleration the daemon commands, i.e. the MCB's own profile (joint table",
        f"# trajectory: acceleration_deg_s2), {LIMIT_MARGIN:g} x motion: max_acceleration_rad_s2): "
        f"{', '.join(f'{a:.4f}' for a in accel)} rad/s^2.",
        "# No jerk limit: a MOVETO switches its acceleration at once, nothing bounds jerk.",
        "# The limits are what the robot follows, so plans may use them in full (MoveIt's default scaling is 0.1).",
        "default_velocity_scaling_factor: 1.0",
        "default_acceleration_scaling_factor: 1.0",
        "joint_limits:",
    ]
    for name, (lo, hi), (velocity, acceleration) in joints:
        lines += [
            f"  {name}:",
            "    has_position_limits: true",
            f"    min_position: {_num(lo)}",
            f"    max_position: {_num(hi)}",
            "    has_velocity_limits: true",
            f"    max_velocity: {_num(velocity)}",
            "    has_acceleration_limits: true",
            f"    max_acceleration: {_num(acceleration)}",
            "    has_jerk_limits: false",
        ]
    return "\n".join(lines) + "\n"
