"""The simulated MDS bus answers the real protocol; faults can be injected; traffic records and replays."""

from __future__ import annotations

import math
from pathlib import Path

import can
import pytest

from mds_ach.bus import canio, mcb
from mds_ach.bus.constants import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED
from mds_ach.bus.mcb import Command, ErrorCode, Response, StateArg
from mds_ach.bus.simbus import ManualClock, SimBus, SimNetwork
from mds_ach.robot import config


@pytest.fixture(scope="module")
def table() -> config.JointTable:
    return config.load("default")


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def net(table: config.JointTable, clock: ManualClock) -> SimNetwork:
    return SimNetwork.from_table(table, pose={"LEP": -1.0, "RSR": -0.5, "NKY": 0.2}, clock=clock, bitrate=None)


@pytest.fixture
def bus(net: SimNetwork):
    b = SimBus(network=net)
    yield b
    b.shutdown()


def send(bus: can.BusABC, raw: mcb.RawFrame) -> None:
    bus.send(can.Message(arbitration_id=raw.arbitration_id, data=raw.data, is_extended_id=False))


def drain(bus: can.BusABC, clock: ManualClock | None = None, dt: float = 0.001) -> list[mcb.McbFrame]:
    if clock is not None:
        clock.advance(dt)
    out = []
    while (m := bus.recv(0)) is not None:
        assert not m.is_error_frame
        out.append(mcb.decode(m.arbitration_id, m.data))
    return out


def query(bus, clock, address: int, arg: StateArg) -> float | int:
    send(bus, mcb.encode_query_state(arg, address))
    replies = [f for f in drain(bus, clock) if f.command is Response.STATE and f.argument is arg]
    assert len(replies) == 1 and replies[0].address == address
    return replies[0].value


def test_broadcast_query_every_node_answers_with_float_counts(table, net, bus, clock) -> None:
    send(bus, mcb.encode_query_positions())
    replies = drain(bus, clock)
    assert sorted(f.address for f in replies) == sorted(table.addresses)
    for f in replies:
        assert f.is_response and f.arbitration_id == mcb.HOST_SID
        assert f.command is Response.STATE and f.argument is StateArg.ACTUAL_POSITION
        assert isinstance(f.value, float)
    pos = {f.address: f.value for f in replies}
    assert table["LEP"].to_joint(pos[0x4C]) == pytest.approx(-1.0, abs=1e-6)
    assert table["RSR"].to_joint(pos[0x4B]) == pytest.approx(-0.5, abs=1e-6)
    assert table["NKY"].to_joint(pos[0x3A]) == pytest.approx(0.2, abs=1e-6)
    assert pos[0x5C] == 0.0  # WST untouched: ROM middle


def test_set_sequence_is_acked_like_the_captures(table, bus, clock) -> None:
    j = table["LEP"]
    counters = []
    for _ in range(9):  # 36 SETs: the counter wraps after 0x1D like the captures
        for raw in mcb.encode_position_sequence(j.address, 100.0, table.accel_counts(j)):
            send(bus, raw)
        acks = drain(bus, clock)
        assert [a.acked_argument for a in acks] == [StateArg.TRAJECTORY_ACCELERATION, StateArg.MOVETO_TARGET,
                                                     StateArg.TRAJECTORY_MODE, StateArg.TRAJECTORY_PERIOD]
        for a in acks:
            assert (a.command, a.acked_command, a.address) == (Response.ACK, Command.SET, j.address)
            assert a.raw & 0xFF == 0 and (a.raw >> 8) & 0xFF == (a.raw >> 16) & 0xFF  # "24 0c 0c 00"
        counters += [a.ack_counter for a in acks]
    assert counters[:3] == [1, 2, 3] and max(counters) == 0x1D and counters[29] == 0 and counters[30] == 1


@pytest.mark.parametrize(("distance", "accel_deg"), [(0.5, 80.0), (0.05, 80.0), (1.0, 20.0), (-0.8, 150.0)])
def test_moveto_follows_the_commanded_acceleration(table, net, bus, clock, distance: float, accel_deg: float) -> None:
    j = table["LEP"]
    start = j.to_joint(net.position(j.address))
    accel = j.rad_to_counts(math.radians(accel_deg))
    for raw in mcb.encode_position_sequence(j.address, j.to_counts(start + distance), accel):
        send(bus, raw)
    drain(bus)
    t0 = clock.now
    samples = [(0.0, start)]
    while net.is_running(j.address):
        clock.advance(0.001)
        samples.append((clock.now - t0, j.to_joint(net.position(j.address))))
        assert clock.now - t0 < 30
    took = clock.now - t0
    a = math.radians(accel_deg)
    vmax = math.pi  # the simulator's default: half a motor revolution per second
    peak = math.sqrt(a * abs(distance))
    expected = 2 * peak / a if peak <= vmax else abs(distance) / vmax + vmax / a
    period = mcb.TrajectoryPeriod.P19_53125MS.seconds
    assert abs(took - expected) <= 2 * period, (took, expected)
    assert samples[-1][1] == pytest.approx(start + distance, abs=1e-5)
    # The setpoint moves only once per commanded trajectory period (positions change in steps).
    changes = [t for (t, q), (_, q0) in zip(samples[1:], samples[:-1], strict=True) if q != q0]
    gaps = [b - a_ for a_, b in zip(changes[:-1], changes[1:], strict=True)]
    assert min(gaps) == pytest.approx(period, abs=0.0011)
    # Never more than the commanded acceleration: per-period steps grow or shrink by at most a*T^2.
    levels = [start] + [q for (t, q) in samples if t in changes]
    steps = [q1 - q0 for q0, q1 in zip(levels[:-1], levels[1:], strict=True)]
    second = [abs(s1 - s0) for s0, s1 in zip(steps[:-1], steps[1:], strict=True)]
    assert max(second) <= a * period**2 * 1.001 + 1e-6
    assert max(second) >= a * period**2 * 0.9  # ... and it does use it
    # The finished move is reported like in the captures: WARNING trajectory buffer empty, carrying the target.
    done = [f for f in drain(bus, clock) if f.command is Response.WARNING]
    assert len(done) == 1 and done[0].argument is ErrorCode.TRAJECTORY_BUFFER_EMPTY
    target_f32 = mcb.decode(*mcb.encode_moveto(j.address, j.to_counts(start + distance))).raw
    assert done[0].raw == target_f32


def test_state_queries(table, net, bus, clock) -> None:
    j = table["RSP"]
    assert query(bus, clock, j.address, StateArg.IS_TRAJECTORY_RUNNING) == 0
    assert query(bus, clock, j.address, StateArg.IS_ENABLED) == 1
    idle_current = query(bus, clock, j.address, StateArg.CURRENT)
    for raw in mcb.encode_position_sequence(j.address, j.to_counts(j.home + 1.0), table.accel_counts(j)):
        send(bus, raw)
    drain(bus, clock, 0.5)
    assert query(bus, clock, j.address, StateArg.IS_TRAJECTORY_RUNNING) == 1
    moving_current = query(bus, clock, j.address, StateArg.CURRENT)
    assert isinstance(moving_current, int) and moving_current > idle_current > 0
    assert query(bus, clock, j.address, StateArg.TRAJECTORY_PERIOD) == 0x0727
    assert query(bus, clock, j.address, StateArg.MOVETO_TARGET) == pytest.approx(j.to_counts(j.home + 1.0))
    pos = query(bus, clock, j.address, StateArg.ACTUAL_POSITION)
    assert query(bus, clock, j.address, StateArg.DESIRED_POSITION) == pos
    assert query(bus, clock, j.address, StateArg.ENCODER) == round(pos)
    upper = query(bus, clock, j.address, StateArg.UPPER_LIMIT)
    assert upper == round(j.rom / 2)


def test_enable_disable_zero_reset_home(table, net, bus, clock) -> None:
    j = table["LEP"]
    start = net.position(j.address)
    send(bus, mcb.encode_disable(j.address))
    for raw in mcb.encode_position_sequence(j.address, start + 5000, table.accel_counts(j)):
        send(bus, raw)
    acks = drain(bus, clock, 1.0)
    assert [a.acked_command for a in acks][0] is Command.DISABLE
    clock.advance(3.0)
    assert net.position(j.address) == start  # disabled: does not move
    send(bus, mcb.encode_enable(j.address))
    clock.advance(3.0)
    assert net.position(j.address) == pytest.approx(start + 5000, abs=0.01)
    send(bus, mcb.encode_zero_encoder(j.address))
    drain(bus, clock)
    assert net.position(j.address) == 0.0  # count restarts where the joint is
    send(bus, mcb.encode_home(j.address))
    clock.advance(5.0)
    # Homing drives to the ROM middle (the physical zero) and zeroes the count there.
    assert not net.is_running(j.address) and net.position(j.address) == 0.0
    assert net.physical[net.index[j.address]] == 0.0
    send(bus, mcb.encode_moveto(j.address, 300.0))
    send(bus, mcb.encode_reset(j.address))
    frames = drain(bus, clock, 1.0)
    assert any(f.acked_command is Command.RESET for f in frames)
    assert query(bus, clock, j.address, StateArg.TRAJECTORY_MODE) == mcb.TrajectoryMode.NEXTPOINT


def test_fault_injection(table, net, bus, clock) -> None:
    n = len(table)
    net.drop_replies(0x4C, count=1)
    send(bus, mcb.encode_query_positions())
    assert len(drain(bus, clock)) == n - 1
    send(bus, mcb.encode_query_positions())
    assert len(drain(bus, clock)) == n  # only one dropped
    net.set_offline(0x5F)
    send(bus, mcb.encode_moveto(0x5F, 1000.0))
    send(bus, mcb.encode_trajectory_mode(0x5F))
    send(bus, mcb.encode_query_positions())
    frames = drain(bus, clock, 1.0)
    assert 0x5F not in {f.address for f in frames} and len(frames) == n - 1
    assert net.position(0x5F) == 0.0  # offline: no motion either
    net.set_offline(0x5F, False)
    net.delay_replies(0x30, 0.050)
    send(bus, mcb.encode_query_positions())
    early = drain(bus, clock, 0.010)
    assert 0x30 not in {f.address for f in early}
    late = drain(bus, clock, 0.050)
    assert [f.address for f in late if f.command is Response.STATE] == [0x30]
    net.delay_replies(None, 0.0)
    net.drop_replies(None, count=0, probability=0.5)
    send(bus, mcb.encode_query_positions())
    got = len(drain(bus, clock))
    assert 0 < got < n
    net.drop_replies(None, count=0, probability=0.0)
    # Error frames as SocketCAN delivers them.
    net.inject_error_frame(status=0x20)
    err = bus.recv(0)
    assert err.is_error_frame and err.data[1] == 0x20 and bus.state is can.BusState.PASSIVE
    # Unknown node and malformed frames reach the host untouched.
    net.inject_frame(0x10, bytes([0, 0, 0, 0, 0xB0, 0, 4, 5]))
    net.inject_frame(0x10, bytes([1, 2, 3]))
    assert mcb.decode(0x10, bus.recv(0).data).address == 0xB0
    assert bus.recv(0).dlc == 3


def test_bus_off_and_restart(table, net, clock) -> None:
    bus = SimBus(network=net)
    net.bus_off()
    msg = bus.recv(0)
    assert msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF
    assert bus.state is can.BusState.ERROR
    with pytest.raises(can.CanOperationError, match="bus-off"):
        send(bus, mcb.encode_query_positions())
    bus.shutdown()
    bus = SimBus(network=net)  # re-opening the interface restarts the controller
    restarted = bus.recv(0)
    assert restarted.is_error_frame and restarted.arbitration_id & CAN_ERR_RESTARTED
    send(bus, mcb.encode_query_positions())
    assert len(drain(bus, clock)) == len(table) and bus.state is can.BusState.ACTIVE
    bus.shutdown()


def test_wire_time_and_transmit_buffer(table, clock) -> None:
    net = SimNetwork.from_table(table, clock=clock, bitrate=1_000_000, tx_backlog_s=0.005)
    bus = SimBus(network=net)
    try:
        frame_time = 135e-6
        send(bus, mcb.encode_query_positions())
        clock.advance(frame_time * 20)
        first = drain(bus)
        assert 15 <= len(first) <= 20  # one reply per 135 us after the query's own frame time
        clock.advance(frame_time * (len(table) - len(first) + 2))
        assert len(first) + len(drain(bus)) == len(table)
        # A sender far ahead of the wire gets ENOBUFS like a full socket buffer (to a silent address, so
        # that no ACKs share the wire).
        silent = 0
        with pytest.raises(can.CanOperationError, match="buffer full"):
            for _ in range(1000):
                send(bus, mcb.encode_moveto(0x70, 1.0))
                silent += 1
        assert silent == pytest.approx(0.005 / frame_time, abs=2)
        # With ACKs every command costs at least two frame times.
        clock.advance(1.0)
        acked = 0
        with pytest.raises(can.CanOperationError, match="buffer full"):
            for _ in range(1000):
                send(bus, mcb.encode_moveto(0x4C, 1.0))
                acked += 1
        assert acked <= silent / 2 + 1
    finally:
        bus.shutdown()


def test_real_time_recv_waits_for_the_reply(table) -> None:
    """With the real clock, recv() blocks until the wire delivers, and times out when nothing comes."""
    net = SimNetwork.from_table(table, bitrate=1_000_000)
    bus = SimBus(network=net)
    try:
        send(bus, mcb.encode_query_positions())
        got = []
        while len(got) < len(table) and (m := bus.recv(0.5)) is not None:
            got.append(m)
        assert len(got) == len(table)
        assert bus.recv(0.01) is None
    finally:
        bus.shutdown()


def test_nodes_ignore_frames_they_do_not_understand(table, net, bus, clock) -> None:
    bus.send(can.Message(arbitration_id=0x4C, data=b"\x01\x02", is_extended_id=False))
    bus.send(can.Message(arbitration_id=0x4C, data=bytes(8), is_extended_id=True))
    bus.send(can.Message(arbitration_id=0x70, data=bytes(mcb.encode_enable(0x4C).data), is_extended_id=False))
    assert drain(bus, clock) == []


@pytest.mark.parametrize("suffix", [".asc", ".log", ".blf"])
def test_record_and_replay(table, tmp_path: Path, suffix: str) -> None:
    clock = ManualClock()
    net = SimNetwork.from_table(table, pose={"LSP": 0.3}, clock=clock, bitrate=None)
    path = tmp_path / f"traffic{suffix}"
    io = canio.make_canio(nocan=True, network=net, can_log=str(path))
    sent = [mcb.encode_enable(0x5F), mcb.encode_query_positions()]
    for raw in sent:
        assert io.send(raw)
    clock.advance(0.001)
    received = []
    while (m := io.recv(0)) is not None:
        received.append(m)
    io.close()
    assert io.counters.tx_frames == 2 and io.counters.rx_frames == len(received) == len(table) + 1
    assert io.counters.bits == (2 + len(received)) * 135
    logged = list(can.LogReader(str(path)))
    assert len(logged) == 2 + len(received)
    assert [bytes(m.data) for m in logged[:2]] == [r.data for r in sent]
    replay = canio.ReplayBus(path=str(path), speed=0)
    frames = []
    while (m := replay.recv(0)) is not None:
        frames.append(mcb.decode(m.arbitration_id, m.data))
    replay.shutdown()
    assert len(frames) == len(received)  # only node -> host frames come back
    pos = {f.address: f.value for f in frames if f.argument is StateArg.ACTUAL_POSITION}
    assert table["LSP"].to_joint(pos[0x5F]) == pytest.approx(0.3, abs=1e-6)


def test_recorder_refuses_unknown_format(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown log format"):
        canio.Recorder(tmp_path / "x.pcap")


def test_bus_config(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    for var in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(canio.BusConfigError, match="--nocan"):
        canio.bus_config()
    cfg = canio.bus_config("virtual", "mds-test", 500000)
    assert (cfg["interface"], cfg["channel"], cfg["bitrate"]) == ("virtual", "mds-test", 500000)
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "envchan")
    assert canio.bus_config()["channel"] == "envchan"
    conf = tmp_path / "can.ini"
    conf.write_text("[default]\ninterface = virtual\nchannel = filechan\nbitrate = 250000\n")
    monkeypatch.delenv("CAN_INTERFACE")
    monkeypatch.delenv("CAN_CHANNEL")
    cfg = canio.bus_config(config_file=str(conf))
    assert (cfg["channel"], cfg["bitrate"]) == ("filechan", 250000)
    io = canio.make_canio(config_file=str(conf))
    assert io.bitrate == 250000 and io.send(mcb.encode_query_positions())
    io.close()
    with pytest.raises(canio.BusConfigError, match="unknown CAN interface"):
        canio.bus_config("nosuchbus", "x")
