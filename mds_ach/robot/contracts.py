"""The channel contracts: every MDS Ach channel, declared once.

Each ``Contract`` says what a channel is for, the struct every frame is (``mds_ach.robot.msgs``), which
processes write and read it, what a frame must satisfy before the stack accepts it from outside (the
validator, where one exists), whether only the stack's own user may write it, and how the launcher sees its
writer is up. Everything that needs one of these facts derives it from ``CHANNELS`` instead of keeping its own
list: the channel names of ``import mds_ach as mds``, ``mds-ach make/rm/dump``, achd's write rules and the
channels ``mds-ach remote`` shares, the daemon's channel set, the launcher's readiness checks, the file modes
(``mds_ach.robot.access``) and ``include/mds.h``.

To add a channel: define its struct in ``mds_ach.robot.msgs`` (if it is new), add a ``Contract`` below, export
its ``MDS_CHAN_*_NAME`` from ``mds_ach/__init__.py`` and regenerate the header (``python -m mds_ach.tools.cheader``).

May import: ``mds_ach.robot.msgs`` and the stdlib only, because ``import mds_ach`` loads it (no Ach, numpy or
rclpy here).
"""

from __future__ import annotations

import ctypes
import math
import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar

from mds_ach.paths import CHANNEL_PREFIX_ENV
from mds_ach.robot.msgs import (
    MDS_CMD,
    MDS_COLLIDE,
    MDS_DAEMON_STATUS,
    MDS_HOLD,
    MDS_IK,
    MDS_IK_STATUS,
    MDS_JOINT_PARAM,
    MDS_LIMITS,
    MDS_MUX_STATE,
    MDS_REF,
    MDS_STATE,
    Packed,
)
from mds_ach.robot.msgs.hold import check_hold
from mds_ach.robot.msgs.legacy import MDS_REF_MODES
from mds_ach.robot.msgs.limits import check_limits

# --- processes (the writers and readers named below) -------------------------------------------------------
DAEMON = "daemon"
MUX = "mux"
FILTER = "filter"
COLLISION = "collision"
IK = "ik"
BRIDGE = "bridge"
CONSOLE = "console"
READ = "read"
VIEWER = "viewer"
CLI = "mds-ach"  # the command-line verbs (start's readiness checks, resetbus, status, dump)
REMOTE = "achd"  # a network peer through our achd server (mds-ach remote, C achd push/pull)
CLIENTS = "clients"  # user programs: legacy C/Python clients, the examples

# --- channel names (the C macros of include/mds.h carry the same names) ------------------------------------
CHANNEL_PREFIX_MAX = 24  # the longest name (mds-daemon-status, 17) + 24 stays far below Ach's 64-byte names
_PREFIX_CHARS = re.compile(r"[a-z0-9][a-z0-9_.-]*")


def prefix_problem(prefix: str) -> str | None:
    """Why ``prefix`` cannot start channel names (it becomes part of a /dev/shm file name), or None."""
    if len(prefix) > CHANNEL_PREFIX_MAX or not _PREFIX_CHARS.fullmatch(prefix):
        return (f"{CHANNEL_PREFIX_ENV}={prefix[:40]!r} is not a channel-name prefix: give 1..{CHANNEL_PREFIX_MAX} "
                "lower-case letters, digits, '.', '_' or '-', starting with a letter or digit (e.g. r2-)")
    return None


def _channel_prefix() -> str:
    """The prefix every MDS channel name gets in this process: ``$MDS_ACH_CHANNEL_PREFIX`` (a second system on one
    host, e.g. ``r2-``: ``r2-mds-state``), empty by default (the original names). Read once, at import: every
    name below is built from it. A bad one stops the program (a silent fallback to the unprefixed names would
    drive the other system's robot)."""
    prefix = os.environ.get(CHANNEL_PREFIX_ENV, "")
    if prefix and (problem := prefix_problem(prefix)):
        raise SystemExit(f"mds_ach: {problem}")
    return prefix


CHANNEL_PREFIX = _channel_prefix()


def base_name(name: str) -> str:
    """A channel name without this process's prefix: the original name (include/mds.h, config/mux.yaml)."""
    return name[len(CHANNEL_PREFIX):] if CHANNEL_PREFIX and name.startswith(CHANNEL_PREFIX) else name


def channel_name(base: str) -> str:
    """The channel named ``base`` in the original (``mds-state``, a config/mux.yaml input) for this process."""
    return CHANNEL_PREFIX + base


MDS_CHAN_REF_NAME = CHANNEL_PREFIX + "mds-ref"
MDS_CHAN_REF_FILTER_NAME = CHANNEL_PREFIX + "mds-ref-filter"
MDS_CHAN_STATE_NAME = CHANNEL_PREFIX + "mds-state"
MDS_CHAN_PARAM_NAME = CHANNEL_PREFIX + "mds-param"
MDS_CHAN_IK_NAME = CHANNEL_PREFIX + "mds-ik"
MDS_CHAN_COLLIDE_NAME = CHANNEL_PREFIX + "mds-collide"
MDS_CHAN_BOARD_CMD_NAME = CHANNEL_PREFIX + "mds-cmd"  # the C name; the old Python's "mds-board-cmd" was a bug
MDS_CHAN_REF_IK_NAME = CHANNEL_PREFIX + "mds-ref-ik"
MDS_CHAN_REF_ROS_NAME = CHANNEL_PREFIX + "mds-ref-ros"
MDS_CHAN_REF_MUX_NAME = CHANNEL_PREFIX + "mds-ref-mux"
MDS_CHAN_REF_SMOOTH_NAME = CHANNEL_PREFIX + "mds-ref-smooth"
MDS_CHAN_IK_STATE_NAME = CHANNEL_PREFIX + "mds-ik-state"
MDS_CHAN_MUX_STATE_NAME = CHANNEL_PREFIX + "mds-mux-state"
MDS_CHAN_DAEMON_STATUS_NAME = CHANNEL_PREFIX + "mds-daemon-status"
MDS_CHAN_HOLD_NAME = CHANNEL_PREFIX + "mds-hold"
MDS_CHAN_LIMITS_NAME = CHANNEL_PREFIX + "mds-limits"
MDS_CHAN_REF_GATED_NAME = CHANNEL_PREFIX + "mds-ref-gated"
MDS_CHAN_DAEMON_INPUT_NAME = MDS_CHAN_REF_GATED_NAME
"""What the daemon executes: the collision gate's output, the one channel only the gate writes (``stack_only``).
Every use goes through this name. It is not ``mds-ref``: in the original the daemon executed ``mds-ref`` and
expert clients wrote it directly, so ``mds-ref`` is a pipeline input here (the mux's ``direct`` controller)."""

CHANNEL_FRAME_COUNT = 10
CHANNEL_FRAME_SIZE = 3000
"""Original sizing, ``ach -1 mk <name> -m 10 -n 3000``: every MDS channel gets it."""

REF_ABS_MAX = 2 * math.pi
"""No joint of the MDS turns more than a full turn: anything larger in a reference is garbage."""

T = TypeVar("T", bound=Packed)
Readiness = Literal["stream", "answer"]
"""How the launcher sees a channel's writer is up: ``stream`` new frames arrive on their own; ``answer`` the
writer only answers requests (the IK node), so the launcher sends it one it must refuse."""


# --- validators: what a frame from outside the stack must satisfy -------------------------------------------


def check_ref(ref: MDS_REF) -> str | None:
    """Every joint finite, within one turn, in a known ref mode (0..3)."""
    for address, joint in enumerate(ref.joint):
        if not math.isfinite(joint.ref):
            return f"non-finite reference {joint.ref} at address {address:#x}"
        if abs(joint.ref) > REF_ABS_MAX:
            return f"reference {joint.ref:.3f} rad at address {address:#x} beyond one turn"
        if joint.mode not in MDS_REF_MODES:
            return f"unknown ref mode {joint.mode} at address {address:#x}"
    return None


def check_ik(ik: MDS_IK) -> str | None:
    """``move`` names an arm, every target component is finite, ``ik_method`` is 0..6."""
    if ik.move not in (0, 1):
        return f"ik move {ik.move} is neither arm"
    for arm in ik.arm:
        values = (arm.t_x, arm.t_y, arm.t_z, arm.r_x, arm.r_y, arm.r_z)
        if not all(math.isfinite(v) for v in values):
            return "non-finite ik target"
        if not 0 <= arm.ik_method <= 6:
            return f"ik method {arm.ik_method} outside 0..6"
    return None


def check_cmd(cmd: MDS_CMD) -> str | None:
    """A finite ``value`` (the daemon answers unknown codes and joints itself, on ``mds-daemon-status``)."""
    if not math.isfinite(cmd.value):
        return "non-finite command value"
    return None


# --- the contract ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Contract(Generic[T]):
    """One channel: its name and C macro, struct, purpose, writers, readers and rules."""

    name: str
    macro: str
    struct: type[T]
    purpose: str
    writers: tuple[str, ...]
    readers: tuple[str, ...]
    legacy: bool
    """The channel is in the original MDS-Ach (``mds.h``); otherwise new in this stack."""
    validator: Callable[[T], str | None] | None = None
    stack_only: bool = False
    """Only the stack's user may write it (created without group write: ``mds_ach.robot.access``)."""
    ready: Readiness | None = None
    """Set on the channel that shows its (first) writer is up; see ``Readiness``."""
    frame_count: int = CHANNEL_FRAME_COUNT
    frame_size: int = CHANNEL_FRAME_SIZE

    @property
    def size(self) -> int:
        """Bytes of one frame (``sizeof`` the struct)."""
        return ctypes.sizeof(self.struct)

    def decode(self, payload: bytes | bytearray | memoryview) -> T:
        """The frame as its struct; ``ValueError`` unless it has exactly the struct's size."""
        return self.struct.from_bytes(payload)

    def problem(self, payload: bytes | bytearray | memoryview) -> tuple[str, str] | None:
        """``(kind, reason)`` why ``payload`` must not be accepted on this channel, kind ``size`` or
        ``invalid``; None when it may."""
        if len(payload) != self.size:
            return "size", f"{len(payload)} bytes, {self.struct.__name__} has {self.size}"
        if self.validator is not None:
            reason = self.validator(self.decode(payload))
            if reason:
                return "invalid", reason
        return None


_PIPELINE = (MUX, FILTER, COLLISION, IK)  # read mds-ref-gated / mds-state for their start reference

CHANNELS: tuple[Contract[Any], ...] = (
    # --- the original MDS-Ach channels -----------------------------------------------------------------
    Contract(MDS_CHAN_REF_NAME, "MDS_CHAN_REF_NAME", MDS_REF,
             "the mux's 'direct' controller input: legacy expert clients and remote achd push, unsmoothed, "
             "limit-checked and collision-gated (the daemon executes mds-ref-gated)",
             writers=(CLIENTS, REMOTE, MUX), readers=(MUX,), legacy=True, validator=check_ref),
    Contract(MDS_CHAN_REF_FILTER_NAME, "MDS_CHAN_REF_FILTER_NAME", MDS_REF,
             "the mux's 'default' controller input: legacy clients, console goto, the viewer",
             writers=(CLIENTS, CONSOLE, VIEWER, REMOTE, MUX), readers=(MUX,), legacy=True, validator=check_ref),
    Contract(MDS_CHAN_STATE_NAME, "MDS_CHAN_STATE_NAME", MDS_STATE,
             "joint state once per daemon cycle (pos measured, ref commanded)",
             writers=(DAEMON,), readers=(*_PIPELINE, BRIDGE, CONSOLE, READ, VIEWER, CLI, REMOTE, CLIENTS),
             legacy=True, ready="stream"),
    Contract(MDS_CHAN_PARAM_NAME, "MDS_CHAN_PARAM_NAME", MDS_JOINT_PARAM,
             "the joint table, published once when the daemon starts",
             writers=(DAEMON,), readers=(READ, REMOTE, CLIENTS), legacy=True),
    Contract(MDS_CHAN_IK_NAME, "MDS_CHAN_IK_NAME", MDS_IK,
             "Cartesian requests for the IK node",
             writers=(CLIENTS, CONSOLE, VIEWER, BRIDGE, REMOTE, CLI), readers=(IK,), legacy=True,
             validator=check_ik),
    Contract(MDS_CHAN_COLLIDE_NAME, "MDS_CHAN_COLLIDE_NAME", MDS_COLLIDE,
             "the collision gate's verdict per part (copied into mds-state)",
             writers=(COLLISION,), readers=(DAEMON, CONSOLE, READ, VIEWER, CLI, REMOTE, CLIENTS), legacy=True,
             ready="stream"),
    Contract(MDS_CHAN_BOARD_CMD_NAME, "MDS_CHAN_BOARD_CMD_NAME", MDS_CMD,
             "setup commands for the daemon (enable, home, reset, zero, resetbus)",
             writers=(CLI, CLIENTS), readers=(DAEMON,), legacy=True, validator=check_cmd),
    # --- new pipeline channels --------------------------------------------------------------------------
    Contract(MDS_CHAN_REF_IK_NAME, "MDS_CHAN_REF_IK_NAME", MDS_REF,
             "the mux's 'ik' controller input: IK solutions",
             writers=(IK,), readers=(MUX,), legacy=False, validator=check_ref),
    Contract(MDS_CHAN_REF_ROS_NAME, "MDS_CHAN_REF_ROS_NAME", MDS_REF,
             "the mux's 'ros' controller input: the bridge's references",
             writers=(BRIDGE,), readers=(MUX,), legacy=False, validator=check_ref),
    Contract(MDS_CHAN_REF_MUX_NAME, "MDS_CHAN_REF_MUX_NAME", MDS_REF,
             "the mux's merged output",
             writers=(MUX,), readers=(FILTER, IK, CONSOLE, BRIDGE), legacy=False, validator=check_ref),
    Contract(MDS_CHAN_REF_SMOOTH_NAME, "MDS_CHAN_REF_SMOOTH_NAME", MDS_REF,
             "the filter's smoothed output, the collision gate's input",
             writers=(FILTER,), readers=(COLLISION,), legacy=False, validator=check_ref, ready="stream"),
    Contract(MDS_CHAN_REF_GATED_NAME, "MDS_CHAN_REF_GATED_NAME", MDS_REF,
             "what the daemon executes: the collision gate's output (limit-checked, collision-free)",
             writers=(COLLISION,), readers=(DAEMON, *_PIPELINE, BRIDGE), legacy=False,
             validator=check_ref, stack_only=True),
    Contract(MDS_CHAN_IK_STATE_NAME, "MDS_CHAN_IK_STATE_NAME", MDS_IK_STATUS,
             "the IK node's answer to each mds-ik request",
             writers=(IK,), readers=(CONSOLE, VIEWER, BRIDGE, CLI, REMOTE, CLIENTS), legacy=False, ready="answer"),
    Contract(MDS_CHAN_MUX_STATE_NAME, "MDS_CHAN_MUX_STATE_NAME", MDS_MUX_STATE,
             "joint owners, controller freshness and verdicts, held joints, the newest hold request handled",
             writers=(MUX,), readers=(FILTER, IK, BRIDGE, CONSOLE, CLI, REMOTE, CLIENTS), legacy=False,
             ready="stream"),
    Contract(MDS_CHAN_DAEMON_STATUS_NAME, "MDS_CHAN_DAEMON_STATUS_NAME", MDS_DAEMON_STATUS,
             "the daemon's health each cycle: timing, bus load, faults, joint freshness",
             writers=(DAEMON,), readers=(MUX, FILTER, COLLISION, READ, CLI, REMOTE, CLIENTS), legacy=False),
    Contract(MDS_CHAN_HOLD_NAME, "MDS_CHAN_HOLD_NAME", MDS_HOLD,
             "hold / resume / cancel requests to the mux (the command lifecycle)",
             writers=(CONSOLE, CLI, BRIDGE, COLLISION, VIEWER, REMOTE, CLIENTS), readers=(MUX, IK), legacy=False,
             validator=check_hold),
    Contract(MDS_CHAN_LIMITS_NAME, "MDS_CHAN_LIMITS_NAME", MDS_LIMITS,
             "the effective joint limits (URDF and joint table) and what each joint can follow (velocity, "
             "acceleration), published once when the daemon starts",
             writers=(DAEMON,), readers=(MUX, COLLISION, IK, BRIDGE, CONSOLE, VIEWER, READ, CLI, REMOTE, CLIENTS),
             legacy=False, validator=check_limits, stack_only=True),
)

BY_NAME: Mapping[str, Contract[Any]] = {c.name: c for c in CHANNELS}
LEGACY_CHANNELS: tuple[str, ...] = tuple(c.name for c in CHANNELS if c.legacy)
PIPELINE_CHANNELS: tuple[str, ...] = tuple(c.name for c in CHANNELS if not c.legacy)
ALL_CHANNELS: tuple[str, ...] = tuple(c.name for c in CHANNELS)
STACK_ONLY: frozenset[str] = frozenset(c.name for c in CHANNELS if c.stack_only)
REMOTE_WRITABLE: tuple[str, ...] = tuple(c.name for c in CHANNELS if REMOTE in c.writers)
"""What a network peer may write by default: pipeline inputs only (``mds-ref`` included: the mux's ``direct``
controller), so a remote reference still passes the mux, filter and collision gate. Never the daemon's input
(``mds-ref-gated``) or mds-cmd."""
REMOTE_READABLE: tuple[str, ...] = tuple(c.name for c in CHANNELS if REMOTE in c.readers)
"""What the robot side of ``mds-ach remote`` shares: everything an operator monitors."""

REF_INPUT_PREFIX = CHANNEL_PREFIX + "mds-ref-"


def reference_input(name: str) -> Contract[MDS_REF]:
    """The contract of an extra mux controller input ``mds-ref-<controller>`` from config/mux.yaml."""
    return Contract(name, "", MDS_REF, "a mux controller input (config/mux.yaml)", writers=(CLIENTS, REMOTE),
                    readers=(MUX,), legacy=False, validator=check_ref)


def lookup(name: str) -> Contract[Any] | None:
    """The contract of channel ``name``; every unregistered ``mds-ref-*`` channel is a reference input (mux
    controllers configured in config/mux.yaml); None for channels that are not MDS channels."""
    found = BY_NAME.get(name)
    if found is None and name.startswith(REF_INPUT_PREFIX):
        return reference_input(name)
    return found


def contract(name: str) -> Contract[Any]:
    """``lookup`` that raises ``KeyError`` for a channel that is not an MDS channel."""
    found = lookup(name)
    if found is None:
        raise KeyError(f"{name!r} is not an MDS channel (known: {', '.join(ALL_CHANNELS)})")
    return found


def struct_of(name: str) -> type[Packed]:
    """The struct channel ``name`` carries (``KeyError`` if it is not an MDS channel)."""
    return contract(name).struct


def used_by(process: str) -> tuple[Contract[Any], ...]:
    """The channels ``process`` writes or reads, in registry order."""
    return tuple(c for c in CHANNELS if process in c.writers or process in c.readers)


def readiness() -> dict[str, tuple[str, Readiness]]:
    """``{process: (channel, how)}``: where the launcher sees each node is up (its writer's first entry)."""
    return {c.writers[0]: (c.name, c.ready) for c in CHANNELS if c.ready is not None}


def wire_structs() -> tuple[type[Packed], ...]:
    """Every struct on a channel and every struct nested in one, nested ones first, each once (C order)."""
    out: list[type[Packed]] = []

    def visit(cls: type[Packed]) -> None:
        for _name, declared, *_ in cls._fields_:
            ftype: Any = declared
            while issubclass(ftype, ctypes.Array):
                ftype = ftype._type_
            if isinstance(ftype, type) and issubclass(ftype, Packed):
                visit(ftype)
        if cls not in out:
            out.append(cls)

    for c in CHANNELS:
        visit(c.struct)
    return tuple(out)
