"""The fixed MDS node table: CAN address, anatomy (long) name and short name for all 43 nodes.

Arrays in the legacy structs are indexed by CAN address, so the address *is* the index. Short names
are unique here; the original ``mdsach.xml`` gave ``LYP`` to two eye joints and ``RYP`` to the right
eye pan, which the original console already renamed to ``LYY``/``EYP``/``RYY`` -- we follow the console.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Joint:
    address: int
    name: str  # anatomy (long) name, e.g. "LeftElbowFlex"
    short: str  # MDS-Ach short name, e.g. "LEP"


JOINTS: tuple[Joint, ...] = tuple(
    Joint(a, n, s)
    for a, n, s in (
        (0x30, "HeadRoll", "NKR"),
        (0x31, "LeftEyePan", "LYY"),
        (0x32, "EyePitch", "EYP"),
        (0x33, "JawPitch", "JAP"),
        (0x34, "LeftUpperEyelidPitch", "LUYP"),
        (0x35, "LeftEyebrowPitch", "LYBP"),
        (0x36, "RightEyelidRoll", "RYLR"),
        (0x37, "RightEyebrowPitch", "RYBP"),
        (0x38, "HeadPitch", "NKP1"),
        (0x39, "NeckPitch", "NKP2"),
        (0x3A, "HeadPan", "NKY"),
        (0x3B, "JawRoll", "JAR"),
        (0x3C, "RightUpperEyelidPitch", "RUYLP"),
        (0x3D, "RightLowerEyelidPitch", "RLYLP"),
        (0x3E, "RightEyebrowRoll", "RYBR"),
        (0x3F, "RightEyePan", "RYY"),
        (0x40, "LeftEyebrowRoll", "LYBR"),
        (0x41, "LeftEyelidRoll", "LYLR"),
        (0x42, "LeftLowerEyelidPitch", "LLYLP"),
        (0x43, "JawJut", "JAJ"),
        (0x48, "RightElbowFlex", "REP"),
        (0x49, "RightUpperArmRoll", "RSY"),
        (0x4A, "RightMiddleFlex", "RF3"),
        (0x4B, "RightShoulderAbd", "RSR"),
        (0x4C, "LeftElbowFlex", "LEP"),
        (0x4D, "LeftUpperArmRoll", "LSY"),
        (0x4E, "LeftMiddleFlex", "LF3"),
        (0x4F, "LeftShoulderAbd", "LSR"),
        (0x50, "RightWristFlex", "RWR"),
        (0x51, "RightIndexFlex", "RF2"),
        (0x52, "RightWristRoll", "RWY"),
        (0x53, "RightThumbRoll", "RF0"),
        (0x54, "LeftWristFlex", "LWR"),
        (0x55, "LeftIndexFlex", "LF2"),
        (0x56, "LeftWristRoll", "LWY"),
        (0x57, "LeftThumbRoll", "LF0"),
        (0x59, "RightThumbFlex", "RF1"),
        (0x5A, "RightPinkieFlex", "RF4"),
        (0x5B, "RightShoulderExt", "RSP"),
        (0x5C, "TorsoPan", "WST"),
        (0x5D, "LeftThumbFlex", "LF1"),
        (0x5E, "LeftPinkieFlex", "LF4"),
        (0x5F, "LeftShoulderExt", "LSP"),
    )
)

ORIGINAL_SHORT: dict[int, str] = {0x31: "LYP", 0x32: "LYP", 0x3F: "RYP"}
"""The short names the original ``mdsach.xml`` gave the nodes renamed here (two of them the same): what its
``mds-param`` and ``mds-state`` carried in ``nameshort``, and so what ours carry (``published_short``)."""

BY_ADDRESS: dict[int, Joint] = {j.address: j for j in JOINTS}
BY_SHORT: dict[str, Joint] = {j.short: j for j in JOINTS}
BY_NAME: dict[str, Joint] = {j.name: j for j in JOINTS}

# Arm joints in the IK order [SP, SR, SY, EP, WY, WR].
LEFT_ARM: tuple[str, ...] = ("LSP", "LSR", "LSY", "LEP", "LWY", "LWR")
RIGHT_ARM: tuple[str, ...] = ("RSP", "RSR", "RSY", "REP", "RWY", "RWR")
NECK: tuple[str, ...] = ("NKY", "NKP1", "NKP2", "NKR")
TORSO: tuple[str, ...] = ("WST",)
# The joints the URDF models and /joint_states carries, in a fixed documented order.
MODEL_JOINTS: tuple[str, ...] = LEFT_ARM + RIGHT_ARM + TORSO + NECK


def published_short(address: int, short: str) -> str:
    """The ``nameshort`` the legacy frames carry for the joint at ``address`` (``ORIGINAL_SHORT``, else
    ``short``)."""
    return ORIGINAL_SHORT.get(address, short)


def lookup(name: str) -> Joint:
    """Find a joint by short name (``LSP``), long name (``LeftShoulderExt``) or address (``0x5f``).

    Matching of names is case-insensitive; an unknown name raises ``KeyError`` listing what is valid.
    """
    text = name.strip()
    up = text.upper()
    if up in BY_SHORT:
        return BY_SHORT[up]
    for j in JOINTS:
        if j.name.lower() == text.lower():
            return j
    try:
        addr = int(text, 0)
    except ValueError:
        addr = -1
    if addr in BY_ADDRESS:
        return BY_ADDRESS[addr]
    raise KeyError(f"unknown joint {name!r}; use a short name such as LSP or a long name such as LeftShoulderExt")


def getAddress(name: str, state: object = None) -> int:  # noqa: N802 - legacy API
    """Legacy helper: the array index (= CAN address) of a joint given by short or long name (any case, or an
    address such as '0x5f'); -1 for an unknown name, like the original (``lookup`` raises, naming valid ones).

    ``state`` is accepted for compatibility with the original signature and not needed.
    """
    try:
        return lookup(str(name)).address
    except KeyError:
        return -1
