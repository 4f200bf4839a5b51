"""The MCB codec against the real CAN captures of June 2015 and the vendor constant tables.

Every frame line of every capture is decoded from its bytes and checked against what the vendor parser
printed on that line (meaning, node, value). The captures print the payload data[7] -> data[0].
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import pytest

from mds_ach.bus import mcb
from mds_ach.bus.mcb import BROADCAST_SID, HOST_SID, Command, ErrorCode, Response, StateArg


@dataclass
class CaptureLine:
    file: str
    lineno: int
    node_text: str  # "0x004C", "0x00FFFFFFB0", "????"
    fields: list[str]  # the text between node and the byte list
    data: bytes  # data[0]..data[7]
    can_id: int

    @property
    def where(self) -> str:
        return f"{self.file}:{self.lineno}"


_BYTES = re.compile(r"\[((?: [0-9a-f]+)+) \]")


def parse_capture(path: Path) -> list[CaptureLine]:
    """Frame lines of one capture: timestamp, node, meaning fields..., [bytes d7..d0], CAN ID (hex)."""
    out = []
    for lineno, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split("\t")
        if len(parts) < 6:
            continue  # header ("T = 0.010 sec", "Start MDS Loop") and blank lines
        groups = _BYTES.findall(parts[-2])
        assert len(groups) == 1, f"{path.name}:{lineno}: no byte list in {line!r}"
        printed = [int(b, 16) for b in groups[0].split()]
        assert len(printed) == 8
        out.append(CaptureLine(path.name, lineno, parts[1], parts[2:-2], bytes(reversed(printed)),
                               int(parts[-1], 16)))
    return out


def node_from_text(text: str) -> int:
    """The vendor parser printed data[5], data[4] as signed chars: 0x00FFFFFFB0 is node 0x00B0."""
    hi, lo = text[2:4], text[4:]
    return int(hi, 16) << 8 | (int(lo, 16) & 0xFF)


@pytest.fixture(scope="module")
def capture_lines(shared_dir: Path) -> list[CaptureLine]:
    files = sorted((shared_dir / "mds-reference/can/logs").iterdir())
    assert len(files) == 8, [f.name for f in files]
    lines = [ln for f in files for ln in parse_capture(f)]
    assert len(lines) > 2900
    return lines


def test_every_capture_frame_agrees_with_the_vendor_text(capture_lines: list[CaptureLine]) -> None:
    seen: dict[str, int] = {}
    for ln in capture_lines:
        frame = mcb.decode(ln.can_id, ln.data)
        # The decoded frame re-encodes to exactly the captured bytes.
        assert frame.to_raw() == (ln.can_id, ln.data), ln.where
        assert frame.is_response == (ln.can_id == HOST_SID), ln.where
        kind = ln.fields[1] if ln.fields[0] == "" else ln.fields[0]
        seen[kind] = seen.get(kind, 0) + 1
        if kind in ("Actual Position", "Desired Position", "Current"):
            text_value = ln.fields[2]
            assert frame.command is Response.STATE, ln.where
            assert frame.address == node_from_text(ln.node_text), ln.where
            if kind == "Actual Position":
                assert frame.argument is StateArg.ACTUAL_POSITION and isinstance(frame.value, float)
                assert f"{frame.value:f}" == text_value, ln.where
                assert mcb.decode_position(ln.data) == (frame.address, frame.value)
            elif kind == "Desired Position":
                assert frame.argument is StateArg.DESIRED_POSITION and isinstance(frame.value, float)
                assert f"{frame.value:.5f}" == text_value, ln.where
            else:
                assert frame.argument is StateArg.CURRENT and isinstance(frame.value, int)
                assert str(frame.value) == text_value, ln.where
        elif kind == "Unknown Argument":
            # The vendor parser had no case for IS_TRAJECTORY_RUNNING; the flag is data[0].
            assert frame.command is Response.STATE and frame.argument == int(ln.fields[2], 16), ln.where
            assert frame.argument is StateArg.IS_TRAJECTORY_RUNNING and frame.value in (0, 1), ln.where
            assert frame.address == node_from_text(ln.node_text)
        elif kind == "ACK":
            assert frame.command is Response.ACK and frame.address == node_from_text(ln.node_text), ln.where
            assert frame.acked_command is Command.SET
            assert frame.acked_argument in (StateArg.TRAJECTORY_ACCELERATION, StateArg.MOVETO_TARGET,
                                             StateArg.TRAJECTORY_MODE, StateArg.TRAJECTORY_PERIOD)
        elif kind == "Unknown packet":
            # Everything the vendor's response parser did not know: our commands, and node warnings.
            signed = [int(b, 16) & 0xFF for b in _BYTES.findall(ln.fields[1])[0].split()]
            assert bytes(reversed(signed)) == ln.data, ln.where
            if ln.can_id == HOST_SID:
                assert frame.command is Response.WARNING, ln.where
                assert frame.argument is ErrorCode.TRAJECTORY_BUFFER_EMPTY
            else:
                assert frame.command in (Command.QUERY_STATE, Command.SET), ln.where
                assert frame.address == ln.can_id
                assert frame.is_broadcast == (ln.can_id == BROADCAST_SID)
                assert ln.can_id == BROADCAST_SID or ln.can_id in (0x3A, 0x4C)
        else:
            raise AssertionError(f"{ln.where}: unexpected line kind {kind!r}")
        assert str(frame)  # readable, never raises
    assert seen["Actual Position"] == 2408 and seen["ACK"] == 32 and seen["Unknown packet"] == 112, seen


def test_captured_set_sequences_reencode_with_the_helpers(capture_lines: list[CaptureLine]) -> None:
    """Each SET the original daemon sent is what our encode_* helpers build from the decoded value."""
    builders = {
        StateArg.TRAJECTORY_ACCELERATION: mcb.encode_set_acceleration,
        StateArg.MOVETO_TARGET: mcb.encode_moveto,
        StateArg.TRAJECTORY_MODE: lambda a, v: mcb.encode_trajectory_mode(a, mcb.TrajectoryMode(v)),
        StateArg.TRAJECTORY_PERIOD: mcb.encode_trajectory_period,
    }
    count = 0
    for ln in capture_lines:
        frame = mcb.decode(ln.can_id, ln.data)
        if not frame.is_response and frame.command is Command.SET:
            assert builders[frame.argument](ln.can_id, frame.value) == (ln.can_id, ln.data), ln.where
            count += 1
        if not frame.is_response and frame.is_broadcast:
            assert mcb.encode_query_positions() == (ln.can_id, ln.data), ln.where
    assert count == 32


def test_known_values_from_the_spec() -> None:
    # LEB early setting: 5 deg/s^2 on a 51200 counts/rev joint, and a 30 degree target.
    accel = mcb.decode(0x4C, bytes(reversed(bytes.fromhex("252400004431c71d"))))
    assert accel.argument is StateArg.TRAJECTORY_ACCELERATION
    assert accel.value == pytest.approx(5 * 51200 / 360, abs=0.01)
    target = mcb.decode(0x4C, bytes(reversed(bytes.fromhex("2527000045855556"))))
    assert target.value == pytest.approx(30 * 51200 / 360, abs=0.01)
    pos = mcb.decode(0x10, bytes(reversed(bytes.fromhex("05040049c4b02000"))))
    assert (pos.address, pos.value) == (0x49, -1409.0)
    period = mcb.decode(0x4C, bytes(reversed(bytes.fromhex("2515000000000727"))))
    assert period.value == mcb.TrajectoryPeriod.P19_53125MS
    assert mcb.TrajectoryPeriod.P19_53125MS.seconds == pytest.approx(0.01953125, abs=1e-6)
    assert mcb.TrajectoryPeriod.P10MS.seconds == pytest.approx(0.010, abs=2e-5)


def test_ack_counter_and_helper_layout() -> None:
    raw = mcb.encode_ack(0x3A, Command.SET, StateArg.TRAJECTORY_PERIOD, 0x12)
    assert bytes(reversed(raw.data)).hex() == "0625003a15121200"
    ack = mcb.decode(*raw)
    assert (ack.acked_command, ack.acked_argument, ack.ack_counter) == (Command.SET, StateArg.TRAJECTORY_PERIOD,
                                                                        0x12)


def test_enum_values_match_the_vendor_tables(shared_dir: Path) -> None:
    tables = shared_dir / "mds-reference/can/xitome-logparser-tables"

    def table(name: str) -> dict[int, str]:
        rows = [ln.split(maxsplit=1) for ln in (tables / name).read_text().splitlines() if ln.strip()]
        return {int(code, 16): text.strip() for code, text in rows}

    def norm(text: str) -> str:
        return text.upper().replace("_", "").replace("STATE", "").replace("RO", "")

    for code, text in table("CommandHex.txt").items():
        assert norm(Command(code).name) == norm(text), (code, text)
    for code, text in table("ResponseHex.txt").items():
        assert norm(Response(code).name) == norm(text), (code, text)
    for code, text in table("ArgumentHex.txt").items():
        if code <= 3:
            assert mcb.Gain(code).name == text[0]
        elif code < 0x50:
            assert norm(StateArg(code).name) == norm(text), (code, text)
        else:
            assert norm(ErrorCode(code).name) == norm(text.removeprefix("Error_")), (code, text)


@pytest.mark.parametrize("address", [0x30, 0x4C, 0x5F])
def test_encode_helpers_round_trip(address: int) -> None:
    seq = mcb.encode_position_sequence(address, -1234.5, 1137.78)
    decoded = [mcb.decode(*f) for f in seq]
    assert [d.argument for d in decoded] == [StateArg.TRAJECTORY_ACCELERATION, StateArg.MOVETO_TARGET,
                                             StateArg.TRAJECTORY_MODE, StateArg.TRAJECTORY_PERIOD]
    assert all(f.arbitration_id == address and d.command is Command.SET for f, d in zip(seq, decoded, strict=True))
    assert decoded[0].value == pytest.approx(1137.78, rel=1e-6)
    assert decoded[1].value == -1234.5
    assert decoded[2].value == mcb.TrajectoryMode.MOVETO and decoded[3].value == 0x0727
    for builder, cmd in ((mcb.encode_enable, Command.ENABLE), (mcb.encode_disable, Command.DISABLE),
                         (mcb.encode_reset, Command.RESET), (mcb.encode_zero_encoder, Command.ZERO_ENCODER)):
        frame = mcb.decode(*builder(address))
        assert frame.command is cmd and frame.address == address and frame.raw == 0
    home = mcb.decode(*mcb.encode_home(address))
    assert home.argument is StateArg.TRAJECTORY_MODE and home.value == mcb.TrajectoryMode.HOME
    reply = mcb.decode(*mcb.encode_state_reply(address, StateArg.CURRENT, 517))
    assert (reply.is_response, reply.address, reply.value) == (True, address, 517)


def test_bad_input_is_refused() -> None:
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match="non-finite"):
            mcb.encode_moveto(0x4C, bad)
    with pytest.raises(ValueError):
        mcb.encode_set_acceleration(0x4C, 0.0)
    with pytest.raises(ValueError, match="address"):
        mcb.encode_moveto(0x10, 1.0)
    with pytest.raises(ValueError, match="address"):
        mcb.encode_enable(0x800)
    with pytest.raises(ValueError, match="8 data bytes"):
        mcb.decode(0x10, b"\x05\x04")
    with pytest.raises(ValueError, match="11-bit"):
        mcb.decode(0x1000, bytes(8))
    with pytest.raises(ValueError, match="integer"):
        mcb.encode_set(0x4C, StateArg.TRAJECTORY_PERIOD, 1.5)
    with pytest.raises(struct.error):
        mcb.encode_set(0x4C, StateArg.TRAJECTORY_PERIOD, 70000)


def test_unknown_codes_decode_as_ints() -> None:
    frame = mcb.decode(0x10, bytes([1, 0, 0, 0, 0x4C, 0, 0x77, 0x0B]))
    assert frame.command == 0x0B and not isinstance(frame.command, Response)
    assert frame.argument == 0x77 and frame.value == 1
    assert "0x0B" in str(frame)


def test_frame_bits_worst_case() -> None:
    assert mcb.frame_bits(8) == 135 == mcb.FRAME_BITS
    assert mcb.frame_bits(0) == 47 + 8  # 34 + 13 + floor(33/4)
    assert mcb.frame_bits(8, extended=True) == 160
