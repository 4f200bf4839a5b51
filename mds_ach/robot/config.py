"""The project's joint table: YAML config, robot variants, limits and the rad <-> motor-count conversion.

Where the table comes from (:func:`load`): an explicit YAML file (``--config``); else the original installation's
calibration XML when there is one (``/etc/mds-ach``, ``$MDS_ACH_ANATOMY``, ``--anatomy``: the rule is
:mod:`mds_ach.robot.calibfiles`), unless a robot variant is named explicitly (``--robot``); else the packaged YAML.
A table read from XML is labelled robot ``xml`` (``XML_ROBOT``), so every process that asks for ``xml`` reads
the same files. ``JointTable.sources`` names the files; ``describe`` says it in one line for logs and tools.

``config/joints.yaml`` holds all 43 MDS nodes (numbers from the default ``anatomy.xml`` + ``mdsach.xml``);
``config/robots/<robot>.yaml`` overrides what the per-robot calibrated anatomies change (ROM counts,
margins, homing tolerances). The robot is chosen by argument, else ``$MDS_ACH_ROBOT``, else ``default``.

Conventions (``mds-original.md`` §b.5, §d.2), per joint with ``cpr = resolution * gear_ratio * ticks``:

* motor angle  ``m = direction * q + offset``          (q = joint-space reference, rad)
* motor counts ``c = m * cpr / 2 pi``                   (what MOVETO carries)
* measured     ``q = direction * (c * 2 pi / cpr - offset)``
* limits: the homed motor zero is the middle of the ROM, so the usable motor range is
  ``|m| <= rom/2 * (1 - rom_margin)`` (rom in counts, converted to rad), and the joint range is
  ``direction * (+-rom_rad/2 * (1 - rom_margin) - offset)``, sorted. Optional ``lower``/``upper`` in the
  YAML may narrow that range, never widen it.
* home pose (start-up reference when the robot does not answer): ``-offset * direction`` unless set,
  i.e. motor angle 0, the ROM middle the Xitome homing leaves the joint at.

Anything malformed or inconsistent is refused with a :class:`ConfigError` naming file, line, joint and field; the
numbers are checked for sense by the same bounds as the XML's (:mod:`mds_ach.robot.calibsense`: margins 0-50 %,
whole encoder counts, reduction gears, a ROM of at most one turn).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from mds_ach.paths import config_path
from mds_ach.robot import anatomy, calibfiles, calibsense, motion
from mds_ach.robot import joints as node_table
from mds_ach.robot.choice import (  # re-exported: config.ROBOT_ENV etc. are public names
    DEFAULT_ROBOT,
    ROBOT_ENV,
    available_robots,
    effective_robot,
)
from mds_ach.robot.msgs import MDS_JOINT_COUNT, MDS_JOINT_PARAM, MDS_JOINT_STATE, MDS_STATE, set_name, set_padded

log = logging.getLogger(__name__)

ROBOTS = ("default", "isaac", "lucas", "octavia")
XML_ROBOT = "xml"  # the label of a table read from the calibration XML (mds_ach.robot.calibfiles)
TWO_PI = 2.0 * math.pi
# The original daemon's MOVETO acceleration and trajectory period code (§b.4).
DEFAULT_ACCEL_DEG_S2 = 80.0
DEFAULT_TRAJECTORY_PERIOD = 0x0727


class ConfigError(ValueError):
    """Refused configuration; the message says which file, joint and field."""


@dataclass(frozen=True)
class Homing:
    type: str = "auto"
    acceleration: float = 0.0
    velocity: float = 0.0
    error: float = 0.0
    buffer: float = 0.0
    timeout: float = 0.0
    target: str = "middle"


@dataclass(frozen=True)
class Gains:
    """MCB.P/I/D/M of the anatomy (empty in every known file: the nodes keep their own gains)."""

    p: float | None = None
    i: float | None = None
    d: float | None = None
    m: float | None = None


@dataclass(frozen=True)
class JointConfig:
    """One node of the joint table with everything needed to command it and read it back."""

    address: int
    name: str
    short: str
    encoder_resolution: float
    gear_ratio: float
    ticks_per_count: float
    rom: float  # counts, full range of motion
    rom_margin: float
    safety_margin: float
    offset: float  # rad
    direction: float  # +1 or -1
    enabled: bool
    home: float  # rad, joint space
    lower: float  # rad, joint space
    upper: float  # rad, joint space
    coordsys: str = "semantic"
    homing: Homing = field(default_factory=Homing)
    gains: Gains = field(default_factory=Gains)
    published: tuple[tuple[str, float | str], ...] = field(default=(), compare=False)
    """``mds-param`` fields to publish as the calibration file gave them where the table uses a default the file
    did not state (from XML: a missing ``rom.margin`` is 0.0 in the original's frame, 5 % in our limits)."""

    @property
    def cpr(self) -> float:
        """Encoder counts per motor-output revolution."""
        return self.encoder_resolution * self.gear_ratio * self.ticks_per_count

    @property
    def rom_rad(self) -> float:
        return self.rom * TWO_PI / self.cpr

    def motor_rad(self, q: float) -> float:
        return self.direction * q + self.offset

    def to_counts(self, q: float) -> float:
        """Joint reference (rad) -> MOVETO target (counts)."""
        return (self.direction * q + self.offset) * self.cpr / TWO_PI

    def to_joint(self, counts: float) -> float:
        """Measured counts -> joint position (rad)."""
        return self.direction * (counts * TWO_PI / self.cpr - self.offset)

    def rad_to_counts(self, rad: float) -> float:
        """A motor-side magnitude (e.g. acceleration rad/s^2) in counts."""
        return rad * self.cpr / TWO_PI

    def clamp(self, q: float) -> float:
        return min(max(q, self.lower), self.upper)

    def within_limits(self, q: float) -> bool:
        return self.lower <= q <= self.upper


def derived_limits(rom: float, cpr: float, rom_margin: float, offset: float, direction: float) -> tuple[float, float]:
    """Joint range from the ROM around the homed middle, shrunk by the margin (see module doc)."""
    half = rom / 2.0 * (1.0 - rom_margin) * TWO_PI / cpr
    a, b = direction * (-half - offset), direction * (half - offset)
    return (min(a, b), max(a, b))


@dataclass(frozen=True)
class JointTable:
    """All nodes by address, plus the trajectory settings the daemon sends with every MOVETO."""

    joints: tuple[JointConfig, ...]
    robot: str = DEFAULT_ROBOT
    sources: tuple[str, ...] = ()
    accel_deg_s2: float = DEFAULT_ACCEL_DEG_S2
    trajectory_period: int = DEFAULT_TRAJECTORY_PERIOD
    max_velocity: float = motion.DEFAULT_MAX_VELOCITY  # rad/s, every sent target (mds_ach.robot.motion)
    max_acceleration: float = motion.DEFAULT_MAX_ACCELERATION  # rad/s^2

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_address", {j.address: j for j in self.joints})
        object.__setattr__(self, "_by_short", {j.short: j for j in self.joints})

    def __len__(self) -> int:
        return len(self.joints)

    def __iter__(self):
        return iter(self.joints)

    def __getitem__(self, key: int | str) -> JointConfig:
        """By address (int) or short/long name (str, case-insensitive)."""
        if isinstance(key, int):
            return self._by_address[key]  # type: ignore[attr-defined]
        up = key.strip().upper()
        if up in self._by_short:  # type: ignore[attr-defined]
            return self._by_short[up]  # type: ignore[attr-defined]
        return self._by_address[node_table.lookup(key).address]  # type: ignore[attr-defined]

    def get(self, address: int) -> JointConfig | None:
        return self._by_address.get(address)  # type: ignore[attr-defined]

    @property
    def addresses(self) -> tuple[int, ...]:
        return tuple(j.address for j in self.joints)

    @property
    def enabled(self) -> tuple[JointConfig, ...]:
        return tuple(j for j in self.joints if j.enabled)

    def motion_bounds(self) -> motion.MotionBounds:
        """The daemon's last-line bounds (mds_ach.robot.motion): the same at every supported loop rate."""
        return motion.MotionBounds(self.max_velocity, self.max_acceleration, motion.MAX_INTERVAL)

    def accel_counts(self, joint: JointConfig) -> float:
        return joint.rad_to_counts(math.radians(self.accel_deg_s2))

    def to_param(self) -> MDS_JOINT_PARAM:
        """The legacy ``mds-param`` frame (``mds_joint_param_t``, indexed by address)."""
        param = MDS_JOINT_PARAM()
        for j in self.joints:
            p = param.joint[j.address]
            p.rom, p.encoderresolution, p.gearratio = j.rom, j.encoder_resolution, j.gear_ratio
            h = j.homing
            p.HomeAcceleration, p.HomeVelocity, p.HomeError = h.acceleration, h.velocity, h.error
            p.HomeBuffer, p.HomeTimeout = h.buffer, h.timeout
            g = j.gains
            p.MCB_KP, p.MCB_KI, p.MCB_KD, p.MCB_KM = (v or 0.0 for v in (g.p, g.i, g.d, g.m))
            p.safetymargin, p.encoderconfig_tickspercount = j.safety_margin, j.ticks_per_count
            p.rom_margin, p.offset, p.direction = j.rom_margin, j.offset, j.direction
            p.enabled, p.address = int(j.enabled), j.address
            texts = {"coordsys": j.coordsys, "HomeType": h.type, "HomeTarget": h.target, "name": j.name,
                     "nameshort": node_table.published_short(j.address, j.short)}
            for key, value in j.published:
                if key in texts:
                    texts[key] = str(value)
                else:
                    setattr(p, key, value)
            for key, text in texts.items():  # as the original parser: space padded, a field not given stays 0
                if text:
                    set_padded(p, key, text)
        return param

    def fill_state(self, state: MDS_STATE) -> None:
        """The static per-joint fields of ``mds-state``: names, address, offset, direction, enabled."""
        for j in self.joints:
            s: MDS_JOINT_STATE = state.joint[j.address]
            s.address, s.enabled, s.offset, s.direction = j.address, int(j.enabled), j.offset, j.direction
            set_name(s, "name", j.name)
            set_name(s, "nameshort", node_table.published_short(j.address, j.short))


# --- YAML ------------------------------------------------------------------------------------------------

_JOINT_KEYS = {
    "name", "address", "enabled", "encoder", "rom", "rom_margin", "safety_margin", "offset", "direction",
    "home", "lower", "upper", "coordsys", "homing", "gains",
}
_ENCODER_KEYS = {"resolution", "gear_ratio", "ticks_per_count"}
_HOMING_KEYS = {"type", "acceleration", "velocity", "error", "buffer", "timeout", "target"}
_GAIN_KEYS = {"p", "i", "d", "m"}
_TOP_KEYS = {"format", "robot", "description", "source", "trajectory", "motion", "joints"}
_OVERLAY_TOP_KEYS = {"format", "robot", "description", "source", "trajectory", "motion", "joints"}


def robot_name(robot: str | None = None) -> str:
    """The robot to load, by the one rule (:func:`mds_ach.robot.choice.effective_robot`), validated."""
    name = effective_robot(robot=robot)[0]
    if name not in available_robots():
        raise ConfigError(f"unknown robot {name!r}; available: {', '.join(available_robots())}")
    return name


def _config_dir() -> Path:
    return config_path("")


def load(robot: str | None = None, path: str | Path | None = None, anatomy_path: str | Path | None = None,
         overlay_path: str | Path | None = None) -> JointTable:
    """The joint table by the rule of the module doc: ``path`` (YAML), else the calibration XML (``anatomy_path``/
    ``overlay_path`` first, see :func:`mds_ach.robot.calibfiles.resolve`) unless ``robot`` names a YAML variant
    explicitly, else ``joints.yaml`` with the chosen robot's overlay; everything validated."""
    if path is None:
        explicit_yaml = bool(robot and robot.strip().lower() != XML_ROBOT) and anatomy_path is None
        try:
            files = None if explicit_yaml else calibfiles.resolve(anatomy_path, overlay_path)
        except calibfiles.CalibrationError as exc:
            raise ConfigError(str(exc)) from None
        if files is not None:
            return load_xml(files)
        if (robot or effective_robot()[0]).strip().lower() == XML_ROBOT:
            raise ConfigError(f"robot {XML_ROBOT!r} is a table read from calibration XML, and there is none here "
                              f"(no {calibfiles.etc_dir()}/anatomy.xml, ${calibfiles.ANATOMY_ENV} unset)")
    return _load_yaml(robot, path)


def load_xml(files: calibfiles.CalibrationFiles) -> JointTable:
    """The table of an anatomy + mdsach.xml pair, as the original loaded it. A head-only anatomy: the nodes it
    lacks are disabled (:func:`complete`), said in one log line."""
    try:
        table = from_xml(files.anatomy, files.overlay, robot=XML_ROBOT)
    except anatomy.XmlConfigError as exc:
        raise ConfigError(str(exc)) from None
    if len(table) < len(node_table.JOINTS):
        parts = anatomy.missing_parts(table.addresses)
        log.info("%s: %s only (%d of %d nodes): %s absent, disabled (never driven)", files.anatomy,
                 " and ".join(p for p in anatomy.PARTS if p not in parts), len(table), len(node_table.JOINTS),
                 " and ".join(parts))
        table = complete(table)
    return table


def complete(table: JointTable) -> JointTable:
    """``table`` plus every MDS node it lacks, disabled, with the packaged default numbers. Why not leave them out:
    every stage works on the whole robot (limits, collision model, IK); a disabled joint is never commanded, and
    one that never answers shows its home pose (the ROM middle), which is in range and collision-free."""
    base = _load_yaml(DEFAULT_ROBOT, None)
    extra = [replace(j, enabled=False) for j in base if table.get(j.address) is None]
    return replace(table, joints=tuple(sorted((*table.joints, *extra), key=lambda j: j.address)))


def describe(table: JointTable) -> str:
    """Where ``table`` came from, in one line: ``robot xml from /etc/mds-ach/configs/anatomy.xml + ...``."""
    kind = "calibration XML" if table.robot == XML_ROBOT else "YAML"
    return (f"robot {table.robot} from {' + '.join(table.sources) or 'defaults'} ({kind}, {len(table.enabled)} of "
            f"{len(table)} nodes enabled)")


def _load_yaml(robot: str | None, path: str | Path | None) -> JointTable:
    base_path = Path(path) if path else _config_dir() / "joints.yaml"
    name = robot_name(robot) if path is None else (robot or os.environ.get(ROBOT_ENV) or DEFAULT_ROBOT).lower()
    base, base_lines = _read_yaml(base_path)
    _check_keys(base, _TOP_KEYS, f"{base_path}")
    raw_joints = _expect(base.get("joints"), dict, f"{base_path}: field 'joints'")
    trajectory = base.get("trajectory") or {}
    motion_cfg = base.get("motion") or {}
    sources = [str(base_path)]
    overrides: dict[str, Any] = {}
    overlay_path: Path | None = None
    overlay_lines: dict[tuple[str, ...], int] = {}
    if name != DEFAULT_ROBOT:
        overlay_path = base_path.parent / "robots" / f"{name}.yaml"
        if not overlay_path.is_file():
            raise ConfigError(f"{overlay_path}: robot {name!r} has no overlay file")
        overlay, overlay_lines = _read_yaml(overlay_path)
        _check_keys(overlay, _OVERLAY_TOP_KEYS, f"{overlay_path}")
        overrides = _expect(overlay.get("joints") or {}, dict, f"{overlay_path}: field 'joints'")
        trajectory = {**trajectory, **(overlay.get("trajectory") or {})}
        motion_cfg = {**motion_cfg, **(overlay.get("motion") or {})}
        sources.append(str(overlay_path))
        for short in overrides:
            if short not in raw_joints:
                raise ConfigError(f"{overlay_path}: joint {short}: not in {base_path.name}")
    joints = []
    for short, entry in raw_joints.items():
        files = [(base_path, base_lines)]
        where = _Where(str(short), tuple(files))
        merged = _expect(entry, dict, str(where))
        if short in overrides and overlay_path is not None:
            files.insert(0, (overlay_path, overlay_lines))
            merged = _merge(merged, _expect(overrides[short], dict, str(_Where(str(short), tuple(files)))))
            where = _Where(str(short), tuple(files))
        joints.append(_joint_from_yaml(str(short), merged, where))
    table = JointTable(
        tuple(sorted(joints, key=lambda j: j.address)),
        robot=name,
        sources=tuple(sources),
        accel_deg_s2=_number(trajectory.get("acceleration_deg_s2", DEFAULT_ACCEL_DEG_S2),
                             f"{base_path}: trajectory: field 'acceleration_deg_s2'", positive=True),
        trajectory_period=_integer(trajectory.get("period", DEFAULT_TRAJECTORY_PERIOD),
                                   f"{base_path}: trajectory: field 'period'"),
        max_velocity=_number(motion_cfg.get("max_velocity_rad_s", motion.DEFAULT_MAX_VELOCITY),
                             f"{base_path}: motion: field 'max_velocity_rad_s'", positive=True),
        max_acceleration=_number(motion_cfg.get("max_acceleration_rad_s2", motion.DEFAULT_MAX_ACCELERATION),
                                 f"{base_path}: motion: field 'max_acceleration_rad_s2'", positive=True),
    )
    validate(table, str(base_path))
    return table


_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _read_yaml(path: Path) -> tuple[dict[str, Any], dict[tuple[str, ...], int]]:
    """The file's mapping and the line of each of its keys by key path (``_key_lines``)."""
    try:
        text = path.read_text()
        data = yaml.load(text, Loader=_YAML_LOADER)
        lines = _key_lines(yaml.compose(text, Loader=_YAML_LOADER))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: malformed YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data, lines


def _key_lines(node: yaml.Node | None, path: tuple[str, ...] = (), out: dict[tuple[str, ...], int] | None = None,
               seen: set[int] | None = None) -> dict[tuple[str, ...], int]:
    """1-based line of every mapping key by its path, e.g. ``("joints", "LEP", "encoder", "gear_ratio")``: the
    loaded data keeps none, and a refusal names the line (the node tree of ``yaml.compose`` has them). Each node
    is walked once: an alias (``*a``) shares its anchor's node, so nested or recursive aliases cannot make the walk
    exponential or endless (the keys under an alias then report the alias's line)."""
    out = {} if out is None else out
    seen = set() if seen is None else seen
    if isinstance(node, yaml.MappingNode) and id(node) not in seen:
        seen.add(id(node))
        for key, value in node.value:
            here = (*path, str(key.value))
            out.setdefault(here, key.start_mark.line + 1)
            _key_lines(value, here, out, seen)
    return out


@dataclass(frozen=True)
class _Where:
    """Where one joint's fields are: ``file:line: joint X`` (the robot overlay first when it sets the field)."""

    short: str
    files: tuple[tuple[Path, dict[tuple[str, ...], int]], ...]

    def _at(self, keys: tuple[str, ...]) -> str:
        for file, lines in self.files:
            line = lines.get(("joints", self.short, *keys))
            if line is not None:
                return f"{file}:{line}"
        return self._at(()) if keys else str(self.files[-1][0])

    def __str__(self) -> str:
        return f"{self._at(())}: joint {self.short}"

    def field(self, key: str) -> str:
        """``file:line: joint X: field 'key'``; ``key`` dotted for nested fields (``encoder.gear_ratio``)."""
        return f"{self._at(tuple(key.split('.')))}: joint {self.short}: field '{key}'"


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            out[key] = {**base[key], **value}
        else:
            out[key] = value
    return out


def _check_keys(mapping: dict[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(map(str, mapping)) - allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown field(s) {unknown}; allowed: {sorted(allowed)}")


def _expect(value: Any, kind: type, where: str) -> Any:
    if not isinstance(value, kind):
        raise ConfigError(f"{where}: expected a {kind.__name__}, got {value!r}")
    return value


def _number(value: Any, where: str, positive: bool = False, allow_none: bool = False) -> float:
    if value is None and allow_none:
        return None  # type: ignore[return-value]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"{where}: expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{where}: must be > 0, got {value!r}")
    return float(value)


def _integer(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    return value


def _joint_from_yaml(short: str, e: dict[str, Any], where: _Where) -> JointConfig:
    _check_keys(e, _JOINT_KEYS, str(where))
    for required in ("name", "address", "encoder", "rom", "offset", "direction", "enabled"):
        if required not in e:
            raise ConfigError(f"{where}: field '{required}' is missing")
    enc = _expect(e["encoder"], dict, where.field("encoder"))
    _check_keys(enc, _ENCODER_KEYS, where.field("encoder"))
    homing = _expect(e.get("homing") or {}, dict, where.field("homing"))
    _check_keys(homing, _HOMING_KEYS, where.field("homing"))
    gains = _expect(e.get("gains") or {}, dict, where.field("gains"))
    _check_keys(gains, _GAIN_KEYS, where.field("gains"))

    def num(key: str, src: dict[str, Any] = e, positive: bool = False, default: Any = ..., prefix: str = "") -> float:
        if key not in src and default is not ...:
            return default
        if key not in src:
            raise ConfigError(f"{where.field(prefix + key)} is missing")
        return _number(src[key], where.field(prefix + key), positive=positive)

    enabled = e["enabled"]
    if not isinstance(enabled, bool) and enabled not in (0, 1):
        raise ConfigError(f"{where.field('enabled')}: expected true/false, got {enabled!r}")
    direction = num("direction")
    if direction not in (1.0, -1.0):
        raise ConfigError(f"{where.field('direction')}: must be 1 or -1, got {e['direction']!r}")
    name = e["name"]
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where.field('name')}: expected the anatomy name, got {name!r}")
    address = _integer(e["address"], where.field("address"))
    res = num("resolution", enc, positive=True, prefix="encoder.")
    gear = num("gear_ratio", enc, positive=True, prefix="encoder.")
    ticks = num("ticks_per_count", enc, positive=True, prefix="encoder.")
    rom = num("rom", positive=True)
    rom_margin = num("rom_margin", default=0.05)
    safety_margin = num("safety_margin", default=0.05)
    offset = num("offset")
    hn = {k: num(k, homing, prefix="homing.") for k in calibsense.HOMING if k in homing}
    bad = calibsense.problem({
        calibsense.RESOLUTION: res, calibsense.GEAR_RATIO: gear, calibsense.TICKS: ticks, calibsense.ROM: rom,
        calibsense.ROM_MARGIN: rom_margin, calibsense.SAFETY_MARGIN: safety_margin, calibsense.OFFSET: offset,
        **{f"homing.{k}": v for k, v in hn.items()}})
    if bad is not None:
        raise ConfigError(f"{where.field(bad[0])}: {bad[1]}")
    lower, upper = derived_limits(rom, res * gear * ticks, rom_margin, offset, direction)
    lo = e.get("lower")
    hi = e.get("upper")
    if lo is not None:
        lo = _number(lo, where.field("lower"))
        if lo < lower - 1e-9:
            raise ConfigError(f"{where.field('lower')}: {lo} is outside the ROM-derived range [{lower:.4f}, "
                              f"{upper:.4f}]")
        lower = lo
    if hi is not None:
        hi = _number(hi, where.field("upper"))
        if hi > upper + 1e-9:
            raise ConfigError(f"{where.field('upper')}: {hi} is outside the ROM-derived range [{lower:.4f}, "
                              f"{upper:.4f}]")
        upper = hi
    empty = calibsense.empty_range(lower, upper)
    if empty is not None:
        raise ConfigError(f"{where.field('lower' if lo is not None else 'upper' if hi is not None else 'rom')}: "
                          f"{empty}")
    home = num("home", default=-offset * direction)
    if not lower <= home <= upper:
        raise ConfigError(f"{where.field('home')}: {home:.4f} is outside the joint range [{lower:.4f}, {upper:.4f}]")
    return JointConfig(
        address=address,
        name=name,
        short=short,
        encoder_resolution=res,
        gear_ratio=gear,
        ticks_per_count=ticks,
        rom=rom,
        rom_margin=rom_margin,
        safety_margin=safety_margin,
        offset=offset,
        direction=direction,
        enabled=bool(enabled),
        home=home,
        lower=lower,
        upper=upper,
        coordsys=str(e.get("coordsys", "semantic")),
        homing=Homing(type=str(homing.get("type", "auto")), target=str(homing.get("target", "middle")), **hn),
        gains=Gains(**{k: _number(v, where.field(f"gains.{k}"), allow_none=True) for k, v in gains.items()}),
    )


def validate(table: JointTable, where: str = "joint table", require_all: bool = True) -> None:
    """Cross-joint checks: unique addresses and names, names agreeing with the MDS node table, no gaps."""
    seen: dict[int, str] = {}
    for j in table.joints:
        jw = f"{where}: joint {j.short}"
        if j.address in seen:
            raise ConfigError(f"{jw}: field 'address': duplicate address 0x{j.address:02X} (also {seen[j.address]})")
        seen[j.address] = j.short
        if not 0 < j.address < MDS_JOINT_COUNT:
            raise ConfigError(f"{jw}: field 'address': 0x{j.address:X} is outside the legacy arrays (1..99)")
        known = node_table.BY_SHORT.get(j.short)
        if known is None:
            raise ConfigError(f"{jw}: unknown short name; the MDS nodes are {', '.join(node_table.BY_SHORT)}")
        if known.address != j.address:
            raise ConfigError(f"{jw}: field 'address': 0x{j.address:02X} but the MDS node {j.short} is "
                              f"0x{known.address:02X}")
        if known.name != j.name:
            raise ConfigError(f"{jw}: field 'name': {j.name!r} but node 0x{j.address:02X} is {known.name!r}")
    if require_all:
        missing = [n.short for n in node_table.JOINTS if n.address not in seen]
        if missing:
            raise ConfigError(f"{where}: joint {missing[0]}: missing (every MDS node must be listed; "
                              f"missing {', '.join(missing)})")


# --- import from the original XML --------------------------------------------------------------------------


def _unstated(numbers: Mapping[str, float | None],
              texts: Mapping[str, str | None]) -> tuple[tuple[str, float | str], ...]:
    """The ``mds-param`` fields the table fills with a default because the file did not state them, as the
    original's frame had them: 0.0 and an empty text (``JointConfig.published``)."""
    out: list[tuple[str, float | str]] = []
    for key, field_name in (("rom.margin", "rom_margin"), ("safetymargin", "safetymargin")):
        if numbers[key] is None:
            out.append((field_name, 0.0))
    out += [(key, "") for key in ("coordsys", "HomeType", "HomeTarget") if not texts[key]]
    return tuple(out)


def from_xml(anatomy_path: str | Path, mdsach_path: str | Path | None = None, robot: str = DEFAULT_ROBOT,
             require_all: bool = False) -> JointTable:
    """A table from Xitome ``anatomy.xml`` (+ MDS-Ach ``mdsach.xml`` overlay), loaded as they are.

    Muscles without an overlay entry keep offset 0, direction 1 and are disabled; overlay entries for
    muscles the anatomy lacks (head-only anatomies) are ignored.
    """
    muscles = anatomy.load_anatomy(anatomy_path)
    overlay = anatomy.load_overlay(mdsach_path) if mdsach_path else {}
    joints = []
    for address, m in sorted(muscles.items()):
        where = f"{anatomy_path}: muscle {m.name}"
        ov = overlay.get(m.name)
        known = node_table.BY_ADDRESS.get(address)
        short = ov.short if ov else (known.short if known else "")
        if not short:
            raise ConfigError(f"{where}: no short name (not in {mdsach_path} nor the MDS node table)")
        offset, direction, enabled = (ov.offset, ov.direction, ov.enabled) if ov else (0.0, 1.0, False)
        if ov is None and mdsach_path:
            log.warning("%s: %s has no entry for muscle %s: disabled (offset 0, direction 1)", where, mdsach_path,
                        m.name)
        n = m.numbers
        rom_margin = n["rom.margin"] if n["rom.margin"] is not None else 0.05
        resolution, ratio = m.number("encoderresolution"), m.number("gearratio")
        ticks, rom = m.number("encoderconfig.tickspercount"), m.number("rom")
        cpr = resolution * ratio * ticks
        lower, upper = derived_limits(rom, cpr, rom_margin, offset, direction)
        empty = calibsense.empty_range(lower, upper)  # each number is in bounds (anatomy): a last guard
        if empty is not None:
            raise ConfigError(f"{where}: {empty} (rom {rom:g}, cpr {cpr:g}, rom.margin {rom_margin:g}, "
                              f"offset {offset:g})")
        joints.append(JointConfig(
            address=address, name=m.name, short=short,
            encoder_resolution=resolution, gear_ratio=ratio,
            ticks_per_count=ticks, rom=rom, rom_margin=rom_margin,
            safety_margin=n["safetymargin"] if n["safetymargin"] is not None else 0.05,
            offset=offset, direction=direction, enabled=enabled, home=-offset * direction,
            lower=lower, upper=upper, coordsys=m.texts["coordsys"] or "semantic",
            homing=Homing(type=m.texts["HomeType"] or "auto", target=m.texts["HomeTarget"] or "middle",
                          acceleration=n["HomeAcceleration"] or 0.0, velocity=n["HomeVelocity"] or 0.0,
                          error=n["HomeError"] or 0.0, buffer=n["HomeBuffer"] or 0.0,
                          timeout=n["HomeTimeout"] or 0.0),
            gains=Gains(n["MCB.P"], n["MCB.I"], n["MCB.D"], n["MCB.M"]),
            published=_unstated(n, m.texts),
        ))
    sources = (str(anatomy_path),) + ((str(mdsach_path),) if mdsach_path else ())
    table = JointTable(tuple(joints), robot=robot, sources=sources)
    validate(table, str(anatomy_path), require_all=require_all)
    return table


def with_overrides(table: JointTable, **per_joint: dict[str, Any]) -> JointTable:
    """A copy with some joints' fields replaced (tests and tools), limits recomputed unless given."""
    joints = []
    for j in table.joints:
        changes = per_joint.get(j.short)
        if changes:
            j = replace(j, **changes)
            if "lower" not in changes and "upper" not in changes:
                lo, hi = derived_limits(j.rom, j.cpr, j.rom_margin, j.offset, j.direction)
                j = replace(j, lower=lo, upper=hi)
        joints.append(j)
    out = replace(table, joints=tuple(joints))
    validate(out, "overrides", require_all=False)
    return out


# --- writing YAML (import of a Xitome calibration) -----------------------------------------------------------


def _fmt(v: float) -> str:
    return str(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def _joint_fields(j: JointConfig) -> dict[str, str]:
    """The per-joint YAML values as text, in file order (flow mappings for the small groups)."""
    h, g = j.homing, j.gains

    def opt(v: float | None) -> str:
        return "null" if v is None else _fmt(v)

    return {
        "name": j.name,
        "address": f"0x{j.address:02X}",
        "enabled": "true" if j.enabled else "false",
        "encoder": f"{{resolution: {_fmt(j.encoder_resolution)}, gear_ratio: {_fmt(j.gear_ratio)}, "
                   f"ticks_per_count: {_fmt(j.ticks_per_count)}}}",
        "rom": _fmt(j.rom),
        "rom_margin": _fmt(j.rom_margin),
        "safety_margin": _fmt(j.safety_margin),
        "offset": _fmt(j.offset),
        "direction": _fmt(j.direction),
        "home": _fmt(j.home),
        "coordsys": j.coordsys,
        "homing": f"{{type: {h.type}, acceleration: {_fmt(h.acceleration)}, velocity: {_fmt(h.velocity)}, "
                  f"error: {_fmt(h.error)}, buffer: {_fmt(h.buffer)}, timeout: {_fmt(h.timeout)}, "
                  f"target: {h.target}}}",
        "gains": f"{{p: {opt(g.p)}, i: {opt(g.i)}, d: {opt(g.d)}, m: {opt(g.m)}}}",
    }


def to_yaml(table: JointTable, description: str = "") -> str:
    """The full joint table as ``joints.yaml`` text (joint range given as a comment: it is derived)."""
    lines = ["# MDS joint table (mds_ach.robot.config). Units: rom in encoder counts, angles in rad.",
             "# motor = direction*q + offset; counts = motor*cpr/(2 pi), cpr = resolution*gear_ratio*ticks_per_count.",
             "# Joint range = direction*(+-rom/2*(1-rom_margin) in rad - offset); 'lower'/'upper' may narrow it.",
             "format: 1", f"robot: {table.robot}"]
    if description:
        lines.append(f"description: {description!r}")
    if table.sources:
        lines.append("source: [" + ", ".join(Path(s).name for s in table.sources) + "]")
    lines += ["trajectory:", f"  acceleration_deg_s2: {_fmt(table.accel_deg_s2)}  # MOVETO acceleration",
              f"  period: 0x{table.trajectory_period:04X}  # ticks of 1/93750 s (0x0727 = 19.53 ms)",
              "motion:  # the daemon's last-line bounds on every sent target (mds_ach.robot.motion)",
              f"  max_velocity_rad_s: {_fmt(table.max_velocity)}",
              f"  max_acceleration_rad_s2: {_fmt(table.max_acceleration)}", "joints:"]
    for j in table.joints:
        lines.append(f"  {j.short}:  # range [{j.lower:.4f}, {j.upper:.4f}] rad, cpr {_fmt(j.cpr)}")
        lines += [f"    {k}: {v}" for k, v in _joint_fields(j).items()]
    return "\n".join(lines) + "\n"


def overlay_yaml(base: JointTable, variant: JointTable, description: str = "") -> str:
    """``robots/<robot>.yaml`` text: only the fields in which ``variant`` differs from ``base``."""
    lines = [f"# Robot variant '{variant.robot}': fields that differ from joints.yaml (same units).",
             "format: 1", f"robot: {variant.robot}"]
    if description:
        lines.append(f"description: {description!r}")
    if variant.sources:
        lines.append("source: [" + ", ".join(Path(s).name for s in variant.sources) + "]")
    lines.append("joints:")
    for j in variant.joints:
        b = base[j.address]
        ours, theirs = _joint_fields(j), _joint_fields(b)
        diff = {k: v for k, v in ours.items() if theirs[k] != v and k not in ("name", "address", "homing")}
        homing = {k: v for k, v in vars(j.homing).items() if getattr(b.homing, k) != v}
        if homing:
            diff["homing"] = "{" + ", ".join(f"{k}: {_fmt(v) if isinstance(v, float) else v}"
                                             for k, v in homing.items()) + "}"
        if diff:
            lines.append(f"  {j.short}: {{" + ", ".join(f"{k}: {v}" for k, v in diff.items()) + "}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """``python -m mds_ach.robot.config``: show the loaded table, or convert Xitome XML into project YAML."""
    ap = argparse.ArgumentParser(prog="python -m mds_ach.robot.config", description=main.__doc__)
    ap.add_argument("--robot", help=f"robot variant (default: ${ROBOT_ENV} or 'default')")
    ap.add_argument("--from-xml", nargs=2, metavar=("ANATOMY", "MDSACH"),
                    help="print joints.yaml text converted from an anatomy.xml and mdsach.xml (a head-only anatomy: "
                         "the other nodes disabled, with the packaged numbers)")
    ap.add_argument("--overlay-of", nargs=2, metavar=("BASE_ANATOMY", "MDSACH"),
                    help="with --from-xml: print a robots/<robot>.yaml overlay relative to BASE_ANATOMY")
    args = ap.parse_args(argv)
    try:
        if args.from_xml:
            anatomy_xml, mdsach_xml = args.from_xml
            table = complete(from_xml(anatomy_xml, mdsach_xml, robot=args.robot or DEFAULT_ROBOT))
            if args.overlay_of:
                base_anatomy, base_mdsach = args.overlay_of
                print(overlay_yaml(from_xml(base_anatomy, base_mdsach, require_all=True), table), end="")
            else:
                print(to_yaml(table), end="")
            return 0
        table = load(args.robot)
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}")
        return 2
    print(f"robot {table.robot} from {', '.join(table.sources)}")
    print(f"{'addr':>4} {'short':<6} {'name':<22} {'en':>2} {'cpr':>9} {'offset':>7} {'dir':>3} "
          f"{'lower':>8} {'upper':>8} {'home':>8}")
    for j in table:
        print(f"0x{j.address:02X} {j.short:<6} {j.name:<22} {int(j.enabled):>2} {j.cpr:>9.1f} {j.offset:>7.3f} "
              f"{int(j.direction):>3} {j.lower:>8.4f} {j.upper:>8.4f} {j.home:>8.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
