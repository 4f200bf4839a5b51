"""Binary encode/decode of the Xitome MCB motor-controller CAN frames.

Every frame is an 11-bit ID with 8 data bytes. The 8 bytes are one little-endian word:
``value | address << 32 | argument << 48 | command << 56``, i.e. ``data[0..3]`` value (float32 or an
integer, little-endian), ``data[4..5]`` node address (0 in commands), ``data[6]`` argument, ``data[7]``
command or response code. Commands go to ID = node address (or 0x11 for every node); every node
answers on 0x10 with its own address in the payload. Constants are those of the vendor header
``XitomeMCBCommands.h`` (see ``mds-original.md`` §b).

This module is pure Python (no python-can) so tools can decode without the CAN stack.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

HOST_SID = 0x10  # node -> host replies
BROADCAST_SID = 0x11  # host -> every node
CAN_SID = 0x20
DEFAULT_CAN_SID = 0x21  # an unconfigured node
MAX_STD_ID = 0x7FF
DLC = 8

FCY = 24_000_000
TRAJECTORY_TICK_HZ = FCY / 256  # trajectory period codes count ticks of 1/93 750 s
MAX_TARGET_BUFFER_SIZE = 100
DEFAULT_TRAJECTORY_BUFFER_SIZE = 40
ACK_COUNTER_MODULO = 30  # the ACK counter in the captures wraps 0x1D -> 0x00


class Command(IntEnum):
    """Host -> node command byte (data[7])."""

    SET_TARGET = 0x12
    SET_GAIN = 0x13
    RESET_ACCUMULATOR_AND_REFERENCE = 0x16
    QUERY_STATE = 0x17
    ENABLE = 0x19
    DISABLE = 0x1A
    QUERY_MODE = 0x1C
    QUERY_ID = 0x1D
    QUERY_GAIN = 0x1E
    RESET = 0x1F
    QUERY_VERSION = 0x20
    SAVE = 0x21
    RESTORE = 0x22
    QUERY_RESET = 0x23
    SET = 0x25
    GET_CHECKSUM = 0x26
    ENABLE_WDT = 0x27
    DISABLE_WDT = 0x28
    LOCK_CONFIGURATION = 0x29
    UNLOCK_CONFIGURATION = 0x2A
    ZERO_ENCODER = 0x2B


class BootloaderCommand(IntEnum):
    ERASE = 0x01
    WRITE = 0x02
    READ = 0x03
    READID = 0x04
    EXIT = 0x05


class Response(IntEnum):
    """Node -> host response byte (data[7])."""

    DEBUG = 0x00
    ID = 0x01
    PGM_ECHO = 0x02
    GAIN = 0x03
    VERSION = 0x04
    STATE = 0x05
    ACK = 0x06
    ERROR = 0x07
    FILLBUFFER = 0x08
    CHECKSUM = 0x09
    WARNING = 0x0A
    BOOTLOADER_PAGE_WRITE = 0x0F
    BOOTLOADER_ACK = 0xFF


class Gain(IntEnum):
    """Argument of SET_GAIN / QUERY_GAIN."""

    P = 0x01
    I = 0x02  # noqa: E741 - the gain's name
    D = 0x03


class StateArg(IntEnum):
    """Argument (data[6]) of QUERY_STATE, SET and STATE replies."""

    ACTUAL_POSITION = 0x04
    DESIRED_POSITION = 0x05
    COMMAND_SIGNAL = 0x06
    VELOCITY = 0x07
    CURRENT = 0x08
    POT = 0x09
    RESET = 0x0A
    MODE = 0x0B
    CAN_SID = 0x0C
    DEADZONE = 0x0D
    ACCUMULATOR_LIMIT = 0x0E
    QEI_CONFIG = 0x0F
    ENCODER = 0x10
    LIMITFLAGS = 0x11
    UPPER_LIMIT = 0x12
    LOWER_LIMIT = 0x13
    MAX_PWM_DC = 0x14
    TRAJECTORY_PERIOD = 0x15
    AUTO_UPDATE_VALUE = 0x16
    TRAJECTORY_BUFFER_SIZE = 0x17
    MAX_ENCODER_FREQUENCY = 0x18
    PGAIN = 0x19
    IGAIN = 0x1A
    DGAIN = 0x1B
    CAN_ERROR_COUNT = 0x1C
    HALL_VALUE = 0x1D
    PWM1 = 0x1E
    PWM2 = 0x1F
    PWM3 = 0x20
    IS_TRAJECTORY_RUNNING = 0x21  # read only
    TRAJECTORY_MODE = 0x22
    IS_ENABLED = 0x23  # read only
    TRAJECTORY_ACCELERATION = 0x24
    TRAJECTORY_MAX_VELOCITY = 0x25
    TRAJECTORY_ERROR_THRESHOLD = 0x26
    MOVETO_TARGET = 0x27
    TRAJECTORY_TIME = 0x28  # read only
    TRAJECTORY_POSITION = 0x29  # read only
    TRAJECTORY_VELOCITY = 0x2A  # read only
    TRAJECTORY_TIMESTEP = 0x2B
    TRACKING_ERROR = 0x2C
    HOME_STATE_STOP = 0x2D
    NEXT_BUFFER_POINT = 0x30


class ErrorCode(IntEnum):
    """Argument of ERROR / WARNING replies."""

    TRAJECTORY_BUFFER_OVERFLOW = 0x50
    CANRX_BUFFER_OVERFLOW = 0x51
    CANTX_BUFFER_OVERFLOW = 0x52
    CANT_SET_TRAJECTORY_BUFFER_SIZE = 0x53
    BAD_ENCODER_FREQUENCY = 0x54
    CAN = 0x55
    TRAJECTORY_BUFFER_EMPTY = 0x56
    UNLOCK = 0x57
    UNLOCK_FAILURE = 0x58
    EEPROM_VERIFY = 0x59
    EEPROM_WRITE = 0x5A
    EEPROM_READ = 0x5B
    CANRX_BUFFER_OVERRUN = 0x5C
    TRAJECTORY_CALCULATION = 0x5D
    TRACKING_ERROR = 0x5E


class TrajectoryMode(IntEnum):
    NEXTPOINT = 0x00
    MOVETO = 0x01
    HOME = 0x02


class HomeState(IntEnum):
    IDLE = 0x00
    START = 0x01
    FIND_FIRST = 0x02
    FIND_SECOND = 0x03
    FIND_FINAL = 0x04
    DONE = 0x05


class TrajectoryPeriod(IntEnum):
    """Trajectory period codes in ticks of 1/93 750 s. MDS-Ach used 19.53125 ms."""

    P1MS = 0x005D
    P5MS = 0x01D4
    P10MS = 0x03A9
    P19_53125MS = 0x0727

    @property
    def seconds(self) -> float:
        return self.value / TRAJECTORY_TICK_HZ


class EncoderFrequency(IntEnum):
    KHZ_2000 = 0x0
    KHZ_1000 = 0x1
    KHZ_500 = 0x2
    KHZ_125 = 0x3
    KHZ_62_5 = 0x4
    KHZ_31_25 = 0x5
    KHZ_15_625 = 0x6
    KHZ_7_8125 = 0x7


class DriveMode(IntEnum):
    """Bits of the MODE state variable (drive part | feedback part)."""

    OFF = 0x0000
    BLDC = 0x0001
    BDC = 0x0002
    ALT_HALL = 0x0004
    REVERSE_DRIVE = 0x0008
    PWM_DRIVE = 0x0010
    ENCODER_FEEDBACK = 0x0100
    ANALOG_FEEDBACK = 0x0200
    VELOCITY_FEEDBACK = 0x0400
    CURRENT_FEEDBACK = 0x0800
    NO_FEEDBACK = 0x1000
    REVERSE_FEEDBACK = 0x2000
    ENCODER16 = 0x4000


# Payload type of each state variable, as a struct code on data[0..]: the vendor parser's memcpy widths.
# Variables the parser does not print are typed by what they hold: trajectory quantities are float counts,
# flags and modes small unsigned integers (inference where the vendor code is silent).
_ARG_FORMAT: dict[int, str] = {
    StateArg.ACTUAL_POSITION: "f",
    StateArg.DESIRED_POSITION: "f",
    StateArg.COMMAND_SIGNAL: "h",
    StateArg.VELOCITY: "h",
    StateArg.CURRENT: "H",
    StateArg.POT: "H",
    StateArg.RESET: "H",
    StateArg.MODE: "H",
    StateArg.CAN_SID: "H",
    StateArg.DEADZONE: "h",
    StateArg.ACCUMULATOR_LIMIT: "f",
    StateArg.QEI_CONFIG: "H",
    StateArg.ENCODER: "i",
    StateArg.LIMITFLAGS: "H",
    StateArg.UPPER_LIMIT: "i",
    StateArg.LOWER_LIMIT: "i",
    StateArg.MAX_PWM_DC: "H",
    StateArg.TRAJECTORY_PERIOD: "H",
    StateArg.AUTO_UPDATE_VALUE: "H",
    StateArg.TRAJECTORY_BUFFER_SIZE: "B",
    StateArg.MAX_ENCODER_FREQUENCY: "B",
    StateArg.PGAIN: "f",
    StateArg.IGAIN: "f",
    StateArg.DGAIN: "f",
    StateArg.CAN_ERROR_COUNT: "H",
    StateArg.HALL_VALUE: "B",
    StateArg.PWM1: "H",
    StateArg.PWM2: "H",
    StateArg.PWM3: "H",
    StateArg.IS_TRAJECTORY_RUNNING: "B",
    StateArg.TRAJECTORY_MODE: "B",
    StateArg.IS_ENABLED: "B",
    StateArg.TRAJECTORY_ACCELERATION: "f",
    StateArg.TRAJECTORY_MAX_VELOCITY: "f",
    StateArg.TRAJECTORY_ERROR_THRESHOLD: "f",
    StateArg.MOVETO_TARGET: "f",
    StateArg.TRAJECTORY_TIME: "f",
    StateArg.TRAJECTORY_POSITION: "f",
    StateArg.TRAJECTORY_VELOCITY: "f",
    StateArg.TRAJECTORY_TIMESTEP: "f",
    StateArg.TRACKING_ERROR: "f",
    StateArg.HOME_STATE_STOP: "B",
    StateArg.NEXT_BUFFER_POINT: "f",
}
_STRUCTS = {code: struct.Struct("<" + code) for code in set(_ARG_FORMAT.values()) | {"I"}}
_WORD = struct.Struct("<IHBB")  # value word, address, argument, command

_COMMANDS = {int(c): c for c in Command}
_RESPONSES = {int(r): r for r in Response}
_STATE_ARGS = {int(a): a for a in StateArg}
_ERRORS = {int(e): e for e in ErrorCode}
_GAINS = {int(g): g for g in Gain}


def value_format(argument: int) -> str:
    """struct code of a state variable's payload ('f' float32, else an integer width); 'I' if unknown."""
    return _ARG_FORMAT.get(argument, "I")


def is_float_argument(argument: int) -> bool:
    return _ARG_FORMAT.get(argument) == "f"


class RawFrame(NamedTuple):
    """What goes on the wire: 11-bit ID and the 8 data bytes (python-can independent)."""

    arbitration_id: int
    data: bytes


@dataclass(frozen=True, slots=True)
class McbFrame:
    """A decoded MCB frame.

    ``command`` is the command code for host->node frames and the response code for replies (an enum member
    when known, else the int). ``address`` is the replying node for responses, the destination ID (0x11 for
    broadcast) for commands. ``value`` is a float for float arguments, an int otherwise; ``raw`` is the
    32-bit value word as sent.
    """

    arbitration_id: int
    is_response: bool
    command: int
    argument: int
    address: int
    value: float | int
    raw: int

    @property
    def is_broadcast(self) -> bool:
        return not self.is_response and self.arbitration_id == BROADCAST_SID

    @property
    def acked_command(self) -> int | None:
        """For an ACK: the command it acknowledges (the replies echo it in data[6])."""
        return self.argument if self.is_response and self.command == Response.ACK else None

    @property
    def acked_argument(self) -> int | None:
        """For an ACK: the argument of the acknowledged SET (echoed in data[3])."""
        if self.is_response and self.command == Response.ACK:
            return _STATE_ARGS.get((self.raw >> 24) & 0xFF, (self.raw >> 24) & 0xFF)
        return None

    @property
    def ack_counter(self) -> int | None:
        """For an ACK: the node's receive-buffer index (data[1]; data[2] is normally equal). The captures show
        it counting up by one per received command and wrapping after 0x1D, a 30-entry ring (inference)."""
        if self.is_response and self.command == Response.ACK:
            return (self.raw >> 8) & 0xFF
        return None

    @property
    def meaning(self) -> str:
        """Short human name of what the frame says, e.g. 'STATE ACTUAL_POSITION'."""
        return f"{_name(self.command)} {_arg_name(self.command, self.argument, self.is_response)}".rstrip()

    def to_raw(self) -> RawFrame:
        return RawFrame(self.arbitration_id, pack(self.command, self.argument, self.raw, self.address
                                                  if self.is_response else 0))

    def __str__(self) -> str:
        if self.is_response:
            head = f"0x{self.address:02X} -> host"
        elif self.is_broadcast:
            head = "host -> all"
        else:
            head = f"host -> 0x{self.arbitration_id:02X}"
        if self.is_response and self.command == Response.ACK:
            return f"{head} ACK {_name(self.argument)} {_name(self.acked_argument)} #{self.ack_counter}"
        value = f"{self.value:.6g}" if isinstance(self.value, float) else str(self.value)
        if not self.is_response and self.command in (Command.QUERY_STATE, Command.QUERY_GAIN):
            value = ""
        return f"{head} {self.meaning} {value}".rstrip()


def _name(code: int | None) -> str:
    return code.name if isinstance(code, IntEnum) else f"0x{code:02X}" if code is not None else "?"


def _arg_name(command: int, argument: int, is_response: bool) -> str:
    if is_response and command in (Response.ERROR, Response.WARNING):
        return _name(_ERRORS.get(argument, argument))
    if command in (Command.SET_GAIN, Command.QUERY_GAIN) and not is_response:
        return _name(_GAINS.get(argument, argument))
    if command in (Command.QUERY_STATE, Command.SET, Response.STATE):
        return _name(_STATE_ARGS.get(argument, argument))
    if is_response and command == Response.ACK:
        return _name(_COMMANDS.get(argument, argument))
    return "" if argument == 0 else f"0x{argument:02X}"


def pack(command: int, argument: int, value_word: int, address: int = 0) -> bytes:
    """The 8 data bytes from the four fields (value_word already the raw 32-bit little-endian word)."""
    return _WORD.pack(value_word & 0xFFFFFFFF, address & 0xFFFF, argument & 0xFF, command & 0xFF)


def value_word(argument: int, value: float | int, fmt: str | None = None) -> int:
    """The 32-bit value word for ``value`` typed as ``argument`` needs; non-finite floats are refused."""
    code = fmt or value_format(argument)
    if code == "f":
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"refusing to encode a non-finite value ({v}) for argument 0x{argument:02X}")
        bits: int = _STRUCTS["I"].unpack(_STRUCTS["f"].pack(v))[0]
        return bits
    if isinstance(value, float) and not value.is_integer():
        raise ValueError(f"argument 0x{argument:02X} takes an integer, got {value}")
    buf = _STRUCTS[code].pack(int(value)) + bytes(4 - _STRUCTS[code].size)
    word: int = _STRUCTS["I"].unpack(buf)[0]
    return word


def decode(arbitration_id: int, data: bytes | bytearray | memoryview) -> McbFrame:
    """Decode one frame; ``ValueError`` for a frame that is not an 8-byte MCB frame."""
    if len(data) != DLC:
        raise ValueError(f"MCB frames carry 8 data bytes, got {len(data)} (ID 0x{arbitration_id:03X})")
    if not 0 <= arbitration_id <= MAX_STD_ID:
        raise ValueError(f"MCB frames use 11-bit IDs, got 0x{arbitration_id:X}")
    word, address, argument, code = _WORD.unpack(bytes(data))
    if arbitration_id == HOST_SID:
        command: int = _RESPONSES.get(code, code)
        if code == Response.STATE:
            argument_e: int = _STATE_ARGS.get(argument, argument)
            value: float | int = _typed(argument, word)
        elif code in (Response.ERROR, Response.WARNING):
            argument_e = _ERRORS.get(argument, argument)
            value = word
        elif code == Response.ACK:
            argument_e = _COMMANDS.get(argument, argument)
            value = word
        elif code == Response.GAIN:
            argument_e = argument
            value = _typed(StateArg.PGAIN, word)
        else:
            argument_e = argument
            value = word
        return McbFrame(arbitration_id, True, command, argument_e, address, value, word)
    command = _COMMANDS.get(code, code)
    if code == Command.SET:
        argument_e = _STATE_ARGS.get(argument, argument)
        value = _typed(argument, word)
    elif code == Command.QUERY_STATE:
        argument_e = _STATE_ARGS.get(argument, argument)
        value = word
    elif code in (Command.SET_TARGET, Command.SET_GAIN):
        argument_e = _GAINS.get(argument, argument) if code == Command.SET_GAIN else argument
        value = _typed(StateArg.MOVETO_TARGET, word)
    else:
        argument_e = argument
        value = word
    return McbFrame(arbitration_id, False, command, argument_e, arbitration_id, value, word)


def typed_value(argument: int, word: int) -> float | int:
    """The raw 32-bit value word read as the type ``argument`` carries (float32, int16, uint8...)."""
    code = _ARG_FORMAT.get(argument, "I")
    if code == "I":
        return word
    typed: float | int = _STRUCTS[code].unpack_from(_STRUCTS["I"].pack(word))[0]
    return typed


_typed = typed_value


def decode_position(data: bytes | bytearray | memoryview) -> tuple[int, float] | None:
    """Fast path for the hot loop: (address, counts) when ``data`` is a STATE ACTUAL_POSITION reply."""
    if len(data) == DLC and data[7] == Response.STATE and data[6] == StateArg.ACTUAL_POSITION:
        counts, address = _POS.unpack_from(data)
        return address, counts
    return None


_POS = struct.Struct("<fH")


# --- host -> node frames ---------------------------------------------------------------------------


def _check_address(address: int) -> int:
    if not (0 < address <= MAX_STD_ID) or address in (HOST_SID, BROADCAST_SID):
        raise ValueError(f"invalid MCB node address 0x{address:X}")
    return address


def encode_command(address: int, command: int, argument: int = 0, value: float | int = 0,
                   fmt: str | None = None) -> RawFrame:
    """Generic host -> node frame (``address`` = ``BROADCAST_SID`` for every node)."""
    dest = address if address == BROADCAST_SID else _check_address(address)
    word = value_word(argument, value, fmt) if value != 0 or fmt else 0
    return RawFrame(dest, pack(command, argument, word))


def encode_set(address: int, argument: StateArg | int, value: float | int) -> RawFrame:
    """SET a state variable (value typed by the variable)."""
    return encode_command(address, Command.SET, argument, value, value_format(argument))


def encode_set_acceleration(address: int, counts_per_s2: float) -> RawFrame:
    if not (math.isfinite(counts_per_s2) and counts_per_s2 > 0):
        raise ValueError(f"trajectory acceleration must be finite and > 0, got {counts_per_s2}")
    return encode_set(address, StateArg.TRAJECTORY_ACCELERATION, counts_per_s2)


def encode_moveto(address: int, counts: float) -> RawFrame:
    return encode_set(address, StateArg.MOVETO_TARGET, counts)


def encode_trajectory_mode(address: int, mode: TrajectoryMode = TrajectoryMode.MOVETO) -> RawFrame:
    return encode_set(address, StateArg.TRAJECTORY_MODE, int(mode))


def encode_trajectory_period(address: int, period: int = TrajectoryPeriod.P19_53125MS) -> RawFrame:
    return encode_set(address, StateArg.TRAJECTORY_PERIOD, int(period))


def encode_position_sequence(address: int, target_counts: float, accel_counts_per_s2: float,
                             period: int = TrajectoryPeriod.P19_53125MS) -> list[RawFrame]:
    """The 4-frame MOVETO sequence of the original daemon: acceleration, target, mode, period."""
    return [
        encode_set_acceleration(address, accel_counts_per_s2),
        encode_moveto(address, target_counts),
        encode_trajectory_mode(address, TrajectoryMode.MOVETO),
        encode_trajectory_period(address, period),
    ]


def encode_query_state(argument: StateArg | int, address: int = BROADCAST_SID) -> RawFrame:
    return encode_command(address, Command.QUERY_STATE, argument)


def encode_query_positions() -> RawFrame:
    """The one broadcast per cycle: every node answers with its ACTUAL_POSITION."""
    return encode_query_state(StateArg.ACTUAL_POSITION, BROADCAST_SID)


def encode_enable(address: int) -> RawFrame:
    return encode_command(address, Command.ENABLE)


def encode_disable(address: int) -> RawFrame:
    return encode_command(address, Command.DISABLE)


def encode_reset(address: int) -> RawFrame:
    return encode_command(address, Command.RESET)


def encode_zero_encoder(address: int) -> RawFrame:
    return encode_command(address, Command.ZERO_ENCODER)


def encode_home(address: int) -> RawFrame:
    """Start the node's homing search: trajectory mode HOME (the protocol's homing entry point)."""
    return encode_trajectory_mode(address, TrajectoryMode.HOME)


def encode_query_id() -> RawFrame:
    return encode_command(BROADCAST_SID, Command.QUERY_ID)


# --- node -> host frames (used by the simulated bus) -------------------------------------------------


def encode_reply(address: int, response: int, argument: int, value_word_: int) -> RawFrame:
    return RawFrame(HOST_SID, pack(response, argument, value_word_, address))


def encode_state_reply(address: int, argument: StateArg | int, value: float | int) -> RawFrame:
    return encode_reply(address, Response.STATE, argument, value_word(argument, value))


def encode_ack(address: int, command: int, argument: int, counter: int) -> RawFrame:
    """ACK as the captures show it: data[6] echoes the command, data[3] the argument, data[1..2] the counter."""
    c = counter & 0xFF
    return encode_reply(address, Response.ACK, command, (argument & 0xFF) << 24 | c << 16 | c << 8)


def encode_warning(address: int, code: ErrorCode | int, payload: int = 0, error: bool = False) -> RawFrame:
    return encode_reply(address, Response.ERROR if error else Response.WARNING, code, payload)


# --- bus-load accounting -------------------------------------------------------------------------------


def frame_bits(dlc: int = DLC, extended: bool = False) -> int:
    """Worst-case bits on the wire for one data frame including stuffing and the 3-bit interframe space.

    Standard ID: 34 + 8n bits are subject to stuffing, 13 more are not (CRC delimiter, ACK, EOF, IFS);
    worst-case stuffing adds floor((34 + 8n - 1) / 4). For DLC 8 that is 135 bits (extended: 160).
    """
    g = 54 if extended else 34
    return g + 8 * dlc + 13 + (g + 8 * dlc - 1) // 4


FRAME_BITS = frame_bits()
