"""A wire struct as a ROS 2 message: its ``.msg`` definition, the message of a frame, and the frame of a message.

Why ROS 2 definitions (``ros2msg`` schemas, CDR messages): Foxglove, the reference ``mcap`` reader (with
``mcap-ros2-support``) and ROS 2's own MCAP storage all decode them from the schema stored in the file, so a
recording opens without this package. The definitions are made from the ctypes structs of
:mod:`mds_ach.robot.msgs` (the one definition of every frame), never written by hand, so a struct that gains a
field is recorded with it.

The shape follows the struct with two changes that make it plottable and ROS-valid:

* an array of structs (``MDS_STATE.joint[100]``) becomes one message of columns, one fixed array per field
  (``joint.pos[100]``, ``joint.ref[100]``): Foxglove plots ``/ach/mds_state.joint.pos[3]`` directly;
* field names are ROS's snake case (``refWait`` -> ``ref_wait``, ``HomeType`` -> ``home_type``) and ``char[N]``
  fields are strings (the bytes up to the NUL, Latin-1, so every byte comes back unchanged).

Type names are ``mds_ach_wire/msg/<Struct>`` (``MDS_STATE`` -> ``MdsState``); no ROS package of that name needs
to be installed to read them. The measured joint state is also written as ``sensor_msgs/msg/JointState`` on
``/joint_states`` (:func:`joint_state`), the type every ROS tool knows.

Imports: ctypes, the wire structs and the joint table of :mod:`mds_ach.robot` (no rclpy, no mcap).
"""

from __future__ import annotations

import ctypes
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mds_ach.robot.msgs import MDS_STATE, Packed

WIRE_PACKAGE = "mds_ach_wire"
_SEPARATOR = "=" * 80
CHANNEL_TOPIC_PREFIX = "/ach/"
JOINT_STATES_TOPIC = "/joint_states"

_PRIMITIVES: dict[Any, str] = {
    ctypes.c_double: "float64", ctypes.c_float: "float32", ctypes.c_int8: "int8", ctypes.c_uint8: "uint8",
    ctypes.c_int16: "int16", ctypes.c_uint16: "uint16", ctypes.c_int32: "int32", ctypes.c_uint32: "uint32",
    ctypes.c_int64: "int64", ctypes.c_uint64: "uint64",
}
# ctypes' little-endian structures store their fields as the swapped or native variants; map them by size/kind
for _t in list(_PRIMITIVES):
    for _variant in (getattr(_t, "__ctype_le__", None), getattr(_t, "__ctype_be__", None)):
        if _variant is not None:
            _PRIMITIVES.setdefault(_variant, _PRIMITIVES[_t])


def snake(name: str) -> str:
    """ROS field name of a C field: ``refWait`` -> ``ref_wait``, ``MCB_KP`` -> ``mcb_kp``."""
    return re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", name).lower()


def type_name(struct: type[Packed], columns: bool = False) -> str:
    """``MDS_JOINT_STATE`` -> ``MdsJointState`` (``MdsJointStateColumns`` for an array of them)."""
    base = "".join(part.capitalize() for part in struct.__name__.split("_"))
    return base + ("Columns" if columns else "")


def topic(channel: str) -> str:
    """The MCAP topic of an Ach channel: ``mds-ref-gated`` -> ``/ach/mds_ref_gated`` (ROS topic names have no '-')."""
    return CHANNEL_TOPIC_PREFIX + channel.replace("-", "_")


def channel_of(topic_name: str) -> str | None:
    """The channel a topic records (``topic``'s inverse), None for other topics."""
    if not topic_name.startswith(CHANNEL_TOPIC_PREFIX):
        return None
    return topic_name[len(CHANNEL_TOPIC_PREFIX):].replace("_", "-")


def _is_text(t: Any) -> bool:
    return isinstance(t, type) and issubclass(t, ctypes.Array) and t._type_ is ctypes.c_char


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1")


@dataclass(frozen=True)
class _Field:
    c_name: str
    ros_name: str
    kind: str  # prim, text, prims, texts, struct, structs
    sub: WireSchema | None = None
    length: int = 0


@dataclass(frozen=True)
class WireSchema:
    """How frames of ``struct`` are recorded: the ROS 2 type ``name`` and its definition ``text`` (with every
    nested type, in the concatenated ``.msg`` form MCAP stores), and the conversions both ways."""

    struct: type[Packed]
    name: str
    text: str
    fields: tuple[_Field, ...]
    columns: bool = False

    def to_message(self, frame: Packed) -> dict[str, Any]:
        """The message (a dict the CDR encoder takes) of one frame."""
        out: dict[str, Any] = {}
        for f in self.fields:
            value = getattr(frame, f.c_name)
            if f.kind == "prim":
                out[f.ros_name] = value
            elif f.kind == "text":
                out[f.ros_name] = _text(value)
            elif f.kind == "prims":
                out[f.ros_name] = list(value)
            elif f.kind == "texts":
                out[f.ros_name] = [_text(bytes(v)) for v in value]
            elif f.kind == "struct":
                assert f.sub is not None
                out[f.ros_name] = f.sub.to_message(value)
            else:
                assert f.sub is not None
                out[f.ros_name] = f.sub.to_columns(value)
        return out

    def to_columns(self, items: Any) -> dict[str, Any]:
        """One array of structs as columns (this schema is the columns type)."""
        out: dict[str, Any] = {}
        for f in self.fields:
            if f.kind == "text":
                out[f.ros_name] = [_text(getattr(item, f.c_name)) for item in items]
            else:
                out[f.ros_name] = [getattr(item, f.c_name) for item in items]
        return out

    def from_message(self, msg: Any) -> Packed:
        """The frame a recorded message (a decoded object, or a dict) was made from."""
        frame = self.struct()
        self.fill(frame, msg)
        return frame

    def fill(self, frame: Any, msg: Any) -> None:
        for f in self.fields:
            value = _get(msg, f.ros_name)
            if f.kind == "prim":
                setattr(frame, f.c_name, value)
            elif f.kind == "text":
                setattr(frame, f.c_name, str(value).encode("latin-1", "replace"))
            elif f.kind == "prims":
                target = getattr(frame, f.c_name)
                for i, v in enumerate(list(value)[: f.length]):
                    target[i] = v
            elif f.kind == "texts":
                target = getattr(frame, f.c_name)
                for i, v in enumerate(list(value)[: f.length]):
                    target[i].value = str(v).encode("latin-1", "replace")
            elif f.kind == "struct":
                assert f.sub is not None
                f.sub.fill(getattr(frame, f.c_name), value)
            else:
                assert f.sub is not None
                f.sub.fill_columns(getattr(frame, f.c_name), value, f.length)

    def fill_columns(self, items: Any, msg: Any, length: int) -> None:
        for f in self.fields:
            column = list(_get(msg, f.ros_name))[:length]
            for i, v in enumerate(column):
                if f.kind == "text":
                    setattr(items[i], f.c_name, str(v).encode("latin-1", "replace"))
                else:
                    setattr(items[i], f.c_name, v)


def _get(msg: Any, name: str) -> Any:
    return msg[name] if isinstance(msg, Mapping) else getattr(msg, name)


def wire_schema(struct: type[Packed], count: int = 0) -> WireSchema:
    """The recording schema of ``struct``; ``count`` > 0: of an array of ``count`` of them, as columns.
    ``TypeError`` for a layout it cannot express (none of the channel structs: the tests build every one)."""
    key = (struct, count)
    if key not in _SCHEMAS:
        _SCHEMAS[key] = _build(struct, count)
    return _SCHEMAS[key]


_SCHEMAS: dict[tuple[type[Packed], int], WireSchema] = {}


def _build(struct: type[Packed], count: int) -> WireSchema:
    fields: list[_Field] = []
    lines: list[str] = []
    nested: dict[str, str] = {}
    for c_name, t, *_ in struct._fields_:
        ros = snake(c_name)
        if t in _PRIMITIVES:
            f, ros_type = _Field(c_name, ros, "prim"), _PRIMITIVES[t]
        elif _is_text(t):
            f, ros_type = _Field(c_name, ros, "text"), "string"
        elif isinstance(t, type) and issubclass(t, Packed):
            sub = wire_schema(t)
            f, ros_type = _Field(c_name, ros, "struct", sub), f"{WIRE_PACKAGE}/{type_name(t)}"
            nested.update(_definitions(sub))
        elif isinstance(t, type) and issubclass(t, ctypes.Array):
            array: Any = t
            elem, n = array._type_, int(array._length_)
            if elem in _PRIMITIVES:
                f, ros_type = _Field(c_name, ros, "prims", length=n), f"{_PRIMITIVES[elem]}[{n}]"
            elif _is_text(elem):
                f, ros_type = _Field(c_name, ros, "texts", length=n), f"string[{n}]"
            elif isinstance(elem, type) and issubclass(elem, Packed) and not count:
                sub = wire_schema(elem, n)
                f, ros_type = _Field(c_name, ros, "structs", sub, n), f"{WIRE_PACKAGE}/{type_name(elem, True)}"
                nested.update(_definitions(sub))
            else:
                raise TypeError(f"{struct.__name__}.{c_name}: nested array type {t} cannot be recorded")
        else:
            raise TypeError(f"{struct.__name__}.{c_name}: field type {t} cannot be recorded")
        if count:
            if f.kind not in ("prim", "text"):
                raise TypeError(f"{struct.__name__}.{c_name}: an array of structs with array fields")
            ros_type = f"{ros_type}[{count}]"
        fields.append(f)
        lines.append(f"{ros_type} {ros}")
    name = f"{WIRE_PACKAGE}/msg/{type_name(struct, bool(count))}"
    text = "\n".join(lines) + "".join(f"\n{_SEPARATOR}\nMSG: {n}\n{d}" for n, d in nested.items())
    return WireSchema(struct, name, text, tuple(fields), bool(count))


def _definitions(schema: WireSchema) -> dict[str, str]:
    """``{type: own definition}`` of ``schema`` and of every type it nests (``MSG:`` names are ``pkg/Type``)."""
    blocks = schema.text.split(f"\n{_SEPARATOR}\n")
    out = {schema.name.replace("/msg/", "/"): blocks[0]}
    for block in blocks[1:]:
        header, _nl, body = block.partition("\n")
        out[header.removeprefix("MSG: ")] = body
    return out


def frame_time(frame: Packed) -> float | None:
    """The frame's own time stamp (CLOCK_MONOTONIC s: ``time`` or ``stamp``), None when it has none (yet)."""
    for name in ("time", "stamp"):
        value = getattr(frame, name, None)
        if isinstance(value, float) and math.isfinite(value) and value > 0:
            return value
    return None


# ------------------------------------------------------------------------------------------ sensor_msgs/JointState

HEADER_DEFINITIONS = f"""{_SEPARATOR}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{_SEPARATOR}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec"""
"""The nested definitions every schema with a ``std_msgs/Header header`` field ends with."""

JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
JOINT_STATE_TEXT = f"""std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort
{HEADER_DEFINITIONS}"""


def joint_state(state: MDS_STATE, stamp_ns: int) -> dict[str, Any]:
    """``sensor_msgs/JointState`` of the measured state: every joint the daemon named (position ``pos`` rad,
    velocity ``vel`` rad/s, effort the motor current ``cur`` A), stamped ``stamp_ns`` (wall clock)."""
    names, pos, vel, cur = [], [], [], []
    for j in state.joint:
        name = _text(j.name)
        if name:
            names.append(name)
            pos.append(j.pos)
            vel.append(j.vel)
            cur.append(j.cur)
    return {"header": {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
                       "frame_id": ""},
            "name": names, "position": pos, "velocity": vel, "effort": cur}
