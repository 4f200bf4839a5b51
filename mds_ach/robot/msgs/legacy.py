"""Packed little-endian ctypes layouts of the original MDS-Ach messages (``mds.h``, develop branch), plus
``MDS_CMD`` for ``mds-cmd`` (a channel the original declared but never gave a struct).

These are wire contracts: C clients compiled against ``mds.h`` read and write the same bytes on the
same Ach channels, so every size and offset is asserted in the tests. Arrays are indexed by CAN address.
"""

from __future__ import annotations

import ctypes
from typing import Self

MDS_JOINT_COUNT = 100
MDS_ARM_COUNT = 2
MDS_COLLIDE_JNT_NUM = 10
MDS_CHAR_PARAM_BUFFER_SIZE = 30


class _Packed(ctypes.LittleEndianStructure):
    """Base for every MDS struct: byte-packed, little-endian, like ``__attribute__((packed))``."""

    _pack_ = 1

    def to_bytes(self) -> bytes:
        return bytes(self)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> Self:
        """Build from exactly ``sizeof(cls)`` bytes; anything else is refused."""
        if len(data) != ctypes.sizeof(cls):
            raise ValueError(f"{cls.__name__} needs {ctypes.sizeof(cls)} bytes, got {len(data)}")
        return cls.from_buffer_copy(data)


Name30: type[ctypes.Array[ctypes.c_char]] = ctypes.c_char * MDS_CHAR_PARAM_BUFFER_SIZE


MDS_REF_MODE_REF_FILTER = 0
MDS_REF_MODE_REF = 1
MDS_REF_MODE_COMPLIANT = 2
MDS_REF_MODE_ENC_FILTER = 3
MDS_REF_MODES: tuple[int, ...] = (MDS_REF_MODE_REF_FILTER, MDS_REF_MODE_REF, MDS_REF_MODE_COMPLIANT,
                                  MDS_REF_MODE_ENC_FILTER)
"""``MDS_JOINT_REF.mode``: 0 filter (EMA), 1 pass-through, 2 compliant, 3 encoder-filter."""


class MDS_JOINT_REF(_Packed):  # noqa: N801 - legacy name
    """One joint's reference: radians in joint space plus the legacy ref mode (10 B)."""

    _fields_ = [("ref", ctypes.c_double), ("mode", ctypes.c_int16)]


class MDS_REF(_Packed):  # noqa: N801
    """``mds_ref_t``: references for all 100 addresses (1000 B)."""

    _fields_ = [("joint", MDS_JOINT_REF * MDS_JOINT_COUNT)]


class MDS_JOINT_STATE(_Packed):  # noqa: N801
    """``mds_joint_state_t`` (develop, 138 B)."""

    _fields_ = [
        ("ref_r", ctypes.c_double),
        ("ref", ctypes.c_double),
        ("ref_c_send", ctypes.c_double),
        ("ref_c", ctypes.c_double),
        ("pos", ctypes.c_double),
        ("cur", ctypes.c_double),
        ("vel", ctypes.c_double),
        ("offset", ctypes.c_double),
        ("direction", ctypes.c_double),
        ("enabled", ctypes.c_int16),
        ("address", ctypes.c_int16),
        ("active", ctypes.c_uint8),
        ("homed", ctypes.c_uint8),
        ("name", Name30),
        ("nameshort", Name30),
    ]


class MDS_JNT_COLLIDE(_Packed):  # noqa: N801
    """``mds_jnt_collide_t`` (20 B): per-part collision counter and flag."""

    _fields_ = [
        ("collision", ctypes.c_int16),
        ("isCollide", ctypes.c_int16),
        ("time", ctypes.c_double),
        ("time_dt", ctypes.c_double),
    ]


class MDS_COLLIDE(_Packed):  # noqa: N801
    """``mds_collide_t`` (218 B): parts indexed by the ``COLLIDE_*`` constants."""

    _fields_ = [
        ("joint", MDS_JNT_COLLIDE * MDS_COLLIDE_JNT_NUM),
        ("isCollide", ctypes.c_int16),
        ("time", ctypes.c_double),
        ("time_dt", ctypes.c_double),
    ]


class MDS_POWER(_Packed):  # noqa: N801
    """``mds_power_t`` (24 B)."""

    _fields_ = [("voltage", ctypes.c_double), ("current", ctypes.c_double), ("power", ctypes.c_double)]


class MDS_STATE(_Packed):  # noqa: N801
    """``mds_state_t`` (develop, 14051 B). ``refWait`` is uint8 as in C (the old Python mirror was wrong)."""

    _fields_ = [
        ("joint", MDS_JOINT_STATE * MDS_JOINT_COUNT),
        ("collide", MDS_COLLIDE),
        ("power", MDS_POWER),
        ("time", ctypes.c_double),
        ("refWait", ctypes.c_uint8),
    ]


_PARAM_DOUBLES = (
    "rom",
    "encoderresolution",
    "gearratio",
    "HomeAcceleration",
    "HomeVelocity",
    "HomeError",
    "HomeBuffer",
    "HomeTimeout",
    "MCB_KP",
    "MCB_KI",
    "MCB_KD",
    "MCB_KM",
    "safetymargin",
    "encoderconfig_tickspercount",
    "rom_margin",
    "offset",
    "direction",
)


class MDS_JNT_PARAM(_Packed):  # noqa: N801
    """``mds_jnt_param_t`` (290 B): one node's anatomy + overlay parameters."""

    _fields_ = [
        *((n, ctypes.c_double) for n in _PARAM_DOUBLES),
        ("enabled", ctypes.c_int16),
        ("address", ctypes.c_uint16),
        ("coordsys", Name30),
        ("HomeType", Name30),
        ("HomeTarget", Name30),
        ("name", Name30),
        ("nameshort", Name30),
    ]


class MDS_JOINT_PARAM(_Packed):  # noqa: N801
    """``mds_joint_param_t`` (29000 B), published once on ``mds-param``."""

    _fields_ = [("joint", MDS_JNT_PARAM * MDS_JOINT_COUNT)]


class MDS_IK_ARM(_Packed):  # noqa: N801
    """``mds_ik_arm_t`` (50 B): Cartesian target and number of task DOF (1..6)."""

    _fields_ = [
        ("t_x", ctypes.c_double),
        ("t_y", ctypes.c_double),
        ("t_z", ctypes.c_double),
        ("r_x", ctypes.c_double),
        ("r_y", ctypes.c_double),
        ("r_z", ctypes.c_double),
        ("ik_method", ctypes.c_int16),
    ]


class MDS_IK(_Packed):  # noqa: N801
    """``mds_ik_t`` (102 B): ``arm[RIGHT=0]``, ``arm[LEFT=1]``, ``move`` selects the arm to solve."""

    _fields_ = [("arm", MDS_IK_ARM * MDS_ARM_COUNT), ("move", ctypes.c_int16)]


def set_name(field_owner: ctypes.Structure, field: str, text: str) -> None:
    """Write ``text`` into a char[30] field, NUL padded; refuse names that do not fit."""
    raw = text.encode("ascii")
    if len(raw) >= MDS_CHAR_PARAM_BUFFER_SIZE:
        raise ValueError(f"name {text!r} longer than {MDS_CHAR_PARAM_BUFFER_SIZE - 1} characters")
    setattr(field_owner, field, raw)


def set_padded(field_owner: ctypes.Structure, field: str, text: str) -> None:
    """Write ``text`` into a char[30] field padded with spaces to all 30 bytes, as the original's Python parser
    wrote ``mds-param`` (``get_name`` reads both paddings); refuse names that do not fit."""
    raw = text.encode("ascii")
    if len(raw) > MDS_CHAR_PARAM_BUFFER_SIZE:
        raise ValueError(f"name {text!r} longer than {MDS_CHAR_PARAM_BUFFER_SIZE} characters")
    ctypes.memmove(ctypes.addressof(field_owner) + getattr(type(field_owner), field).offset,
                   raw.ljust(MDS_CHAR_PARAM_BUFFER_SIZE, b" "), MDS_CHAR_PARAM_BUFFER_SIZE)


def get_name(raw: bytes) -> str:
    """Decode a char[30] field: stop at NUL, drop the space padding the old parser added."""
    return raw.split(b"\0", 1)[0].decode("ascii", "replace").strip()


class MDS_CMD(_Packed):  # noqa: N801
    """New ``mds-cmd`` frame (the original declared the channel but never used it): a setup command
    for the daemon. ``address`` 0 means every enabled joint."""

    _fields_ = [
        ("seq", ctypes.c_uint32),
        ("cmd", ctypes.c_uint16),
        ("address", ctypes.c_uint16),
        ("value", ctypes.c_double),
    ]
