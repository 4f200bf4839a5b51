"""Readers for the original Xitome / MDS-Ach XML configuration files, taken as they are.

* ``anatomy.xml`` (and ``<Robot>.anatomy.xml``, ``<Robot>.head.anatomy.xml``): one ``<muscle address name>``
  per node with ``<parameter name value>`` children. "x%" means x/100; a repeated parameter overrides the
  earlier one (what the original parser did); an empty value means "not set".
* ``mdsach.xml``: the MDS-Ach overlay matched **by muscle name**: short name, offset, direction, enabled.
* ``nrl00x.xml``: MCB node settings, a concatenation of ``<node>`` documents (not one well-formed file).

Every refusal names the file and the line (``anatomy.xml:212: muscle LeftElbowFlex: parameter rom: not a
number``), so an operator can fix a hand-edited calibration file without guessing. Numbers are checked for sense
too (margins 0-50 %, whole encoder counts, reduction gears, a ROM of at most one turn: :mod:`calibsense`).

A document type declaration with an external subset or any entity declaration (external, or internal: the
"billion laughs") is refused naming the file and line: expat would drop an external entity silently (the value
would vanish from the calibration) and expand internal ones without bound; no calibration file needs either.

The original overlay gave the short name LYP to two eye joints and RYP to the right eye pan; those are
mapped to the unique names of :mod:`mds_ach.robot.joints` (LYY, EYP, RYY) with a logged note.
"""

from __future__ import annotations

import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from xml.parsers import expat

from mds_ach.robot import calibsense
from mds_ach.robot import joints as joint_table

log = logging.getLogger(__name__)

ANATOMY_NUMBERS = (
    "rom",
    "encoderresolution",
    "gearratio",
    "HomeAcceleration",
    "HomeVelocity",
    "HomeError",
    "HomeBuffer",
    "HomeTimeout",
    "MCB.P",
    "MCB.I",
    "MCB.D",
    "MCB.M",
    "safetymargin",
    "encoderconfig.tickspercount",
    "rom.margin",
)
REQUIRED_NUMBERS = ("rom", "encoderresolution", "gearratio", "encoderconfig.tickspercount")  # > 0 in every muscle
# Anatomy parameter -> the field name of the bounds of sense (mds_ach.robot.calibsense, the YAML's names).
SENSE_FIELDS = {
    "encoderresolution": calibsense.RESOLUTION, "gearratio": calibsense.GEAR_RATIO,
    "encoderconfig.tickspercount": calibsense.TICKS, "rom": calibsense.ROM, "rom.margin": calibsense.ROM_MARGIN,
    "safetymargin": calibsense.SAFETY_MARGIN, "HomeAcceleration": "homing.acceleration",
    "HomeVelocity": "homing.velocity", "HomeError": "homing.error", "HomeBuffer": "homing.buffer",
    "HomeTimeout": "homing.timeout",
}
ANATOMY_TEXTS = ("coordsys", "HomeType", "HomeTarget")


class XmlConfigError(ValueError):
    """A Xitome XML file that cannot be used; the message names file, muscle and parameter."""


@dataclass
class Muscle:
    """One ``<muscle>`` of an anatomy file: numbers (None when empty) and texts by parameter name."""

    address: int
    name: str
    numbers: dict[str, float | None] = field(default_factory=dict)
    texts: dict[str, str] = field(default_factory=dict)
    homed: bool | None = None

    def number(self, key: str) -> float:
        """A number ``load_anatomy`` requires (``REQUIRED_NUMBERS``): never None in a loaded muscle."""
        value = self.numbers[key]
        if value is None:
            raise XmlConfigError(f"muscle {self.name}: parameter {key} must be a positive number, got None")
        return value


@dataclass
class Overlay:
    """One ``<muscle>`` of mdsach.xml."""

    name: str
    short: str
    offset: float
    direction: float
    enabled: bool


@dataclass
class NodeConfig:
    """One ``<node>`` of an nrl00x.xml MCB settings file."""

    address: int
    mode: int
    maxpwm: int
    p: float
    i: float
    d: float
    deadzone: int
    accumulator_limit: float
    qei_config: int
    qei_frequency: int


def parse_number(text: str | None, where: str) -> float | None:
    """'5%' -> 0.05, '28592' -> 28592.0, '' -> None; anything else is refused naming ``where``."""
    if text is None or text.strip() == "":
        return None
    raw = text.strip()
    scale = 1.0
    if raw.endswith("%"):
        raw, scale = raw[:-1], 0.01
    try:
        value = float(raw) * scale
    except ValueError:
        raise XmlConfigError(f"{where}: not a number: {text!r}") from None
    if not math.isfinite(value):
        raise XmlConfigError(f"{where}: not a finite number: {text!r}")
    return value


class _Lines(dict[int, int]):
    """Source line of each element of a parsed file (by ``id``; the tree keeps the elements alive)."""

    def at(self, path: Path, el: ET.Element) -> str:
        return f"{path}:{self.get(id(el), 0)}"


def _parse(path: Path) -> tuple[ET.Element, _Lines]:
    """The file's tree and its elements' line numbers (ElementTree alone does not keep them)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise XmlConfigError(f"{path}: cannot read: {exc.strerror}") from None
    builder = ET.TreeBuilder()
    lines = _Lines()
    parser = expat.ParserCreate()

    def start(tag: str, attrs: dict[str, str]) -> None:
        lines[id(builder.start(tag, attrs))] = parser.CurrentLineNumber

    def refuse(what: str) -> None:
        raise XmlConfigError(f"{path}:{parser.CurrentLineNumber}: {what}: a calibration file may declare no "
                             "entities and no external DTD (an external entity would be dropped silently, an "
                             "internal one expanded); remove the <!DOCTYPE> declaration")

    def doctype(name: str, system_id: str | None, public_id: str | None, _internal: int) -> None:
        if system_id or public_id:
            refuse(f"<!DOCTYPE {name}> names an external document type {system_id or public_id!r}")

    def entity(name: str, is_parameter: int, *_rest: object) -> None:
        refuse(f"<!DOCTYPE> declares the {'parameter ' if is_parameter else ''}entity {name!r}")

    parser.StartDoctypeDeclHandler = doctype
    parser.EntityDeclHandler = entity
    parser.SkippedEntityHandler = lambda name, _is_parameter: refuse(f"reference to the undeclared entity {name!r}")
    parser.StartElementHandler = start
    parser.EndElementHandler = builder.end
    parser.CharacterDataHandler = builder.data
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise XmlConfigError(f"{path}:{exc.lineno}: malformed XML: {expat.ErrorString(exc.code)} "
                             f"(column {exc.offset + 1})") from None
    return builder.close(), lines


def _params(muscle: ET.Element) -> dict[str, ET.Element]:
    """Parameters of a muscle by name; later duplicates override earlier ones, as in the original parser."""
    return {p.get("name", ""): p for p in muscle.findall("parameter")}


def _muscle(path: Path, lines: _Lines, el: ET.Element, address: int, name: str) -> Muscle:
    """One ``<muscle>``'s numbers and texts; a bad parameter is refused naming its own line."""
    params = _params(el)

    def text(key: str) -> str | None:
        p = params.get(key)
        return None if p is None else p.get("value", "")

    def where(key: str) -> str:
        p = params.get(key)
        return f"{lines.at(path, p if p is not None else el)}: muscle {name}: parameter {key}"

    muscle = Muscle(address, name)
    for key in ANATOMY_NUMBERS:
        muscle.numbers[key] = parse_number(text(key), where(key))
    for key in ANATOMY_TEXTS:
        muscle.texts[key] = text(key) or ""
    homed = el.get("homed")
    muscle.homed = None if homed is None else homed.strip().lower() == "true"
    for key in REQUIRED_NUMBERS:
        value = muscle.numbers[key]
        if value is None or value <= 0:
            raise XmlConfigError(f"{where(key)} must be a positive number, got {text(key)!r}")
    bad = calibsense.problem({SENSE_FIELDS[k]: muscle.numbers[k] for k in SENSE_FIELDS})
    if bad is not None:
        key = next(k for k, f in SENSE_FIELDS.items() if f == bad[0])
        raise XmlConfigError(f"{where(key)}: {bad[1]}")
    return muscle


def load_anatomy(path: str | Path) -> dict[int, Muscle]:
    """All muscles of an anatomy file by address."""
    path = Path(path)
    root, lines = _parse(path)
    if root.tag != "anatomy":
        raise XmlConfigError(f"{lines.at(path, root)}: root element is <{root.tag}>, expected <anatomy>")
    out: dict[int, Muscle] = {}
    seen_at: dict[int, int] = {}
    for el in root.findall("muscle"):
        name = el.get("name", "")
        addr_text = el.get("address")
        where = f"{lines.at(path, el)}: muscle {name or '?'}"
        if not name or addr_text is None:
            raise XmlConfigError(f"{where}: needs both 'name' and 'address' attributes")
        try:
            address = int(addr_text, 0)
        except ValueError:
            raise XmlConfigError(f"{where}: address {addr_text!r} is not an integer") from None
        if address in out:
            raise XmlConfigError(f"{where}: duplicate address 0x{address:02X} (also {out[address].name}, line "
                                 f"{seen_at[address]})")
        muscle = _muscle(path, lines, el, address, name)
        out[address] = muscle
        seen_at[address] = lines.get(id(el), 0)
    if not out:
        raise XmlConfigError(f"{path}: no <muscle> elements")
    _check_parts(out, lines.at(path, root))
    return out


# Nodes that an anatomy holds all of or none of: the head (the Xitome head-only anatomies, 0x30-0x43) and the
# body (arms, hands, torso). A part with some of its nodes missing is a damaged file, not a smaller robot.
PARTS = {"head": tuple(j for j in joint_table.JOINTS if j.address <= 0x43),
         "arms and torso": tuple(j for j in joint_table.JOINTS if j.address > 0x43)}


def _check_parts(muscles: dict[int, Muscle], where: str) -> None:
    for part, nodes in PARTS.items():
        present = [j for j in nodes if j.address in muscles]
        if present and len(present) < len(nodes):
            missing = [j for j in nodes if j.address not in muscles]
            raise XmlConfigError(
                f"{where}: missing muscle {missing[0].name} (0x{missing[0].address:02X}): the anatomy has "
                f"{len(present)} of the {len(nodes)} {part} nodes (missing: "
                f"{', '.join(f'{j.name} 0x{j.address:02X}' for j in missing)})")


def missing_parts(addresses: Collection[int]) -> list[str]:
    """The parts (``PARTS``) a set of nodes leaves out entirely, e.g. ``['arms and torso']`` for a head-only one."""
    return [part for part, nodes in PARTS.items() if not any(j.address in addresses for j in nodes)]


def load_overlay(path: str | Path) -> dict[str, Overlay]:
    """mdsach.xml entries by anatomy (long) name, with short names made unique (see module doc)."""
    path = Path(path)
    root, lines = _parse(path)
    out: dict[str, Overlay] = {}
    for el in root.findall("muscle"):
        name = el.get("name", "")
        where = f"{lines.at(path, el)}: muscle {name or '?'}"
        if not name:
            raise XmlConfigError(f"{where}: missing 'name' attribute")
        if name in out:
            raise XmlConfigError(f"{where}: duplicate muscle {name}")
        elements = _params(el)
        params = {k: p.get("value", "") for k, p in elements.items()}
        short = params.get("mdsachname", "").strip()
        canonical = joint_table.BY_NAME.get(name)
        if canonical is not None and canonical.short != short:
            log.info("%s: short name %r for %s mapped to the unique name %r", path.name, short, name, canonical.short)
            short = canonical.short
        if not short:
            raise XmlConfigError(f"{where}: parameter mdsachname missing")
        offset_at = lines.at(path, elements.get("offset", el)) + f": muscle {name}: parameter offset"
        offset = parse_number(params.get("offset", "0"), offset_at) or 0.0
        bad = calibsense.problem({calibsense.OFFSET: offset})
        if bad is not None:
            raise XmlConfigError(f"{offset_at}: {bad[1]}")
        direction = parse_number(params.get("direction", "1"), f"{where}: parameter direction")
        enabled = parse_number(params.get("enabled", "0"), f"{where}: parameter enabled") or 0.0
        if direction not in (1.0, -1.0):
            raise XmlConfigError(f"{where}: parameter direction must be 1 or -1, got {params.get('direction')!r}")
        out[name] = Overlay(name, short, offset, direction, enabled != 0)
    shorts = [o.short for o in out.values()]
    dup = sorted({s for s in shorts if shorts.count(s) > 1})
    if dup:
        raise XmlConfigError(f"{path}: duplicate short names {dup}")
    return out


_XML_DECL = re.compile(r"<\?xml[^>]*\?>")


def _child(el: ET.Element, tag: str) -> ET.Element:
    """The required ``<tag>`` of ``el``; load_node_configs reports a missing one as a bad or missing field."""
    child = el.find(tag)
    if child is None:
        raise ValueError(f"no <{tag}>")
    return child


def load_node_configs(path: str | Path) -> dict[int, NodeConfig]:
    """The ``<node>`` documents of an nrl00x.xml file by address."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise XmlConfigError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        root = ET.fromstring("<nodes>" + _XML_DECL.sub("", text) + "</nodes>")
    except ET.ParseError as exc:
        raise XmlConfigError(f"{path}: malformed XML: {exc}") from None
    out: dict[int, NodeConfig] = {}
    for el in root.findall("node"):
        where = f"{path}: node {el.get('address')}"
        try:
            gains, ctrl, qei = _child(el, "gains"), _child(el, "controlparameters"), _child(el, "qei")
            node = NodeConfig(
                address=int(el.get("address", ""), 0),
                mode=int((el.findtext("mode") or "").strip(), 0),
                maxpwm=int((el.findtext("maxpwm") or "").strip(), 0),
                p=float(gains.get("p", "")),
                i=float(gains.get("i", "")),
                d=float(gains.get("d", "")),
                deadzone=int(ctrl.get("dz", ""), 0),
                accumulator_limit=float(ctrl.get("al", "")),
                qei_config=int(qei.get("config", ""), 0),
                qei_frequency=int(qei.get("frequency", ""), 0),
            )
        except (ValueError, AttributeError) as exc:
            raise XmlConfigError(f"{where}: bad or missing field ({exc})") from None
        if node.address in out:
            raise XmlConfigError(f"{where}: duplicate address")
        out[node.address] = node
    if not out:
        raise XmlConfigError(f"{path}: no <node> documents")
    return out
