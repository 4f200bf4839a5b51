"""The rest of the original ``mds_ach.py`` / ``mds.h`` vocabulary: constants and name helpers old clients use.

``import mds_ach as mds`` re-exports everything here, so the original programs run with one line changed
(``import ach`` -> ``from mds_ach import ach``), and ``include/mds.h`` (``mds_ach.tools.cheader``) emits the C
side from the same values.

Two choices, both documented in docs/operator.md ("Migrating from the original MDS-Ach"):

* The original ``mds_ach.py`` gave Hubo-era *index* values (``LSP = 4``, ``LEB = 7``, ...) that index nothing
  on the MDS, while ``mds.h`` and this package use CAN addresses (``mds.LSP == 0x5f``). The Hubo-era names
  of joints the MDS has (``LEB`` = left elbow, ``NYH`` = neck yaw, ...) are therefore the address of that joint,
  like every other joint constant here; the two wrist *pitch* names of a joint the MDS lacks (``LWP``,
  ``RWP``) keep their original values, which are no MDS node (a reference written there moves nothing, as
  in the original).
* ``getAddress`` (``mds_ach.robot.joints``) of an unknown name returns -1 like the original (``mds.lookup``
  raises with the valid names instead). Names come from the fixed node table, so no state frame is needed.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from mds_ach.robot.contracts import MDS_CHAN_COLLIDE_NAME
from mds_ach.robot.joints import BY_NAME, BY_SHORT
from mds_ach.robot.msgs.legacy import MDS_CHAR_PARAM_BUFFER_SIZE, MDS_JOINT_COUNT

# --- mds.h / mds_ach.py constants that were not otherwise needed ---------------------------------------------
TRUE = 1
FALSE = 0
RIGTH = 0  # sic: the original mds_ach.py's misspelling of RIGHT, kept so scripts using it still run
MAX_EFF = 6  # the number of end-effector task components (x, y, z, rx, ry, rz)

# IK methods (mds_ik_arm_t.ik_method: the number of task DOFs); the original mds.h wrote them malformed
# ("#define IK1 = 1"); the header here gives the values the Python side always had.
IK1 = 1
IK2 = 2
IK3 = 3
IK4 = 4
IK5 = 5
IK6 = 6

# mds_collide_t.joint[] indices under the original names (mds.COLLIDE_* are the same numbers).
COLLISION_L_HAND = 0
COLLISION_R_HAND = 1
COLLISION_R_SHOULDER = 2
COLLISION_L_SHOULDER = 3
COLLISION_R_FOREARM = 4
COLLISION_L_FOREARM = 5
COLLISION_R_ELBOW = 6
COLLISION_L_ELBOW = 7
COLLISION_R_WRIST = 8
COLLISION_L_WRIST = 9

# mds.h values the original declared but did not use; C clients may still name them.
MDS_CAN_CHAN_NUM = 4
MDS_CAN_TIMEOUT_DEFAULT = 0.00018  # s
MDS_CAN_BUFFER_CLEAR_I = 1000
MDS_STARTUP_SEND_REF_DELAY = 0.8  # s
MAX_SAFE_STACK = 1024 * 1024  # bytes

# Channel names the original header declared and nothing created or used (Hubo leftovers); no channel here.
MDS_CHAN_CAN_DAEMON_NAME = "mds-can-daemon"
MDS_CHAN_VIRTUAL_TO_SIM_NAME = "mds-virtual-to-sim"
MDS_CHAN_VIRTUAL_FROM_SIM_NAME = "mds-virtual-from-sim"
MDS_CHAN_COLLLIDE_NAME = MDS_CHAN_COLLIDE_NAME  # sic: the original mds_ach.py's spelling of MDS_CHAN_COLLIDE_NAME

# The original mds.h's jointNames[] (a Hubo leftover: 42 names indexed 0..41, not by CAN address).
HUBO_JOINT_NAMES: tuple[str, ...] = (
    "WST", "NKY", "NK1", "NK2",
    "LSP", "LSR", "LSY", "LEB", "LWY", "LWR", "LWP",
    "RSP", "RSR", "RSY", "REB", "RWY", "RWR", "RWP", "N/A",
    "LHY", "LHR", "LHP", "LKN", "LAP", "LAR", "N/A",
    "RHY", "RHR", "RHP", "RKN", "RAP", "RAR",
    "RF1", "RF2", "RF3", "RF4", "RF5",
    "LF1", "LF2", "LF3", "LF4", "LF5",
)  # fmt: skip

# Hubo-era joint names of mds_ach.py -> the MDS joint they name (see the module docstring).
HUBO_ERA_ALIASES: dict[str, str] = {
    "H": "NKR",  # neck roll
    "NYH": "NKY",  # neck yaw
    "NPL": "NKP2",  # neck pitch, lower
    "NPH": "NKP1",  # neck pitch, high (head)
    "LEB": "LEP",  # left elbow
    "REB": "REP",  # right elbow
    "LFR": "LF0",  # left thumb roll
    "RFR": "RF0",  # right thumb roll
}
# Hubo-era names of joints the MDS does not have: their original values, which are no MDS node.
HUBO_ERA_ABSENT: dict[str, int] = {"LWP": 10, "RWP": 17}

NO_SHORT_NAME = "-------"  # what the original getNameShort gave a joint it did not know


def hubo_era_constants() -> dict[str, int]:
    """``{name: value}`` of every Hubo-era joint constant (addresses, or the original value of absent joints)."""
    out = {name: BY_SHORT[short].address for name, short in HUBO_ERA_ALIASES.items()}
    out.update(HUBO_ERA_ABSENT)
    return out


# --- helpers of the original mds_ach.py (camelCase kept: they are the legacy API) -----------------------------


def p2f(x: str) -> float:
    """'5%' -> 0.05 (the anatomy files' percentages)."""
    return float(x.strip().strip("%")) / 100


def ubytes2str(ubarray: Any) -> str:
    """A name field (bytes, a ctypes char/ubyte array or a list of ints) as text, up to its first NUL, trailing
    blanks removed (the original parser padded names with spaces)."""
    if isinstance(ubarray, bytes | bytearray | memoryview):
        raw = bytes(ubarray)
    else:
        raw = b"".join(c if isinstance(c, bytes) else bytes([int(c)]) for c in ubarray)
    return raw.split(b"\0", 1)[0].decode("latin-1").rstrip()


def str2ubytes(text: str) -> bytes:
    """``text`` space-padded to a 30-byte name field, as the original wrote names (assignable to
    ``state.joint[a].name``: the fields are ``char[30]``, which ctypes sets from bytes); a name that does not
    fit raises ``ValueError``."""
    raw = text.encode("latin-1")
    if len(raw) > MDS_CHAR_PARAM_BUFFER_SIZE:
        raise ValueError(f"name {text!r} longer than {MDS_CHAR_PARAM_BUFFER_SIZE} characters")
    return raw.ljust(MDS_CHAR_PARAM_BUFFER_SIZE)


def getNameAndAddress(state: Any) -> list[list[Any]]:  # noqa: N802 - legacy API
    """``[[name, address], ...]`` of all 100 entries of a state frame (empty name where there is no joint)."""
    out: list[list[Any]] = []
    for a in range(MDS_JOINT_COUNT):
        jnt = state.joint[a]
        out.append([ubytes2str(jnt.name), int(jnt.address)])
    return out


def getNameShort(a: Sequence[Sequence[Any]], state: Any = None) -> list[list[Any]]:  # noqa: N802
    """``getNameAndAddress`` rows with the short name appended: ``[name, address, short]`` (``'-------'`` for a
    name not in the node table). ``state`` is accepted for the original signature and not needed."""
    del state
    out: list[list[Any]] = []
    for row in a:
        name, address = row[0], row[1]
        joint = BY_NAME.get(name)
        out.append([name, address, joint.short if joint is not None else NO_SHORT_NAME])
    return out


def getAddressOnly(name: str, a: Iterable[Sequence[Any]]) -> int:  # noqa: N802 - legacy API
    """The address of ``name`` (long or short) in ``getNameShort`` rows; -1 when absent, like the original."""
    for row in a:
        if name in (row[0], row[2]):
            return int(row[1])
    return -1

