"""A simulated MDS CAN bus: MCB nodes that answer the real protocol, in the daemon's own process.

:class:`SimNetwork` holds the nodes (one per joint-table entry, plus optional extra addresses) and, if a
bitrate is given, a wire model: every frame occupies the bus for its worst-case bit time, replies queue
behind each other, and a sender that runs too far ahead gets ``CanOperationError`` like a full socket
buffer. :class:`SimBus` is a python-can ``BusABC`` on top of it, so the daemon cannot tell it from a real
interface; re-opening a bus (bus-off recovery) attaches a new ``SimBus`` to the same network.

Node behaviour, from the captures and the vendor header (inferences marked):

* every SET is ACKed (``06 25 <addr> <arg> <counter>``); ENABLE, DISABLE, RESET, ZERO_ENCODER and HOME are
  ACKed the same way (inference: the captures only show SETs);
* QUERY_STATE is answered with a STATE reply: ACTUAL_POSITION as float counts, DESIRED_POSITION (the
  trajectory setpoint), CURRENT (uint16, a simple model), IS_TRAJECTORY_RUNNING, IS_ENABLED, ENCODER ...;
* a MOVETO runs an acceleration-limited trajectory to the target with the commanded acceleration, its
  setpoint updated once per commanded trajectory period; the position follows the setpoint exactly;
  a finished move sends WARNING TRAJECTORY_BUFFER_EMPTY carrying the target, as in the captures;
* ZERO_ENCODER and RESET restart the encoder count at 0 where the joint is (inference); HOME drives the
  joint to the middle of its ROM and zeroes the count there; a disabled node does not move.

Fault injection: :meth:`SimNetwork.drop_replies`, :meth:`delay_replies`, :meth:`set_offline`,
:meth:`offset_positions`, :meth:`inject_error_frame`, :meth:`bus_off`, :meth:`inject_frame`; from another process
through :class:`FaultControl` (``daemon --nocan --sim-faults PATH``, test-only).
"""

from __future__ import annotations

import heapq
import json
import logging
import math
import os
import random
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import can
import numpy as np

from mds_ach.bus import mcb
from mds_ach.bus.constants import (
    CAN_ERR_BUSERROR,
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_RX_PASSIVE,
    CAN_ERR_CRTL_TX_PASSIVE,
    CAN_ERR_PROT,
    CAN_ERR_RESTARTED,
)
from mds_ach.bus.mcb import Command, ErrorCode, StateArg, TrajectoryMode

_WORD = struct.Struct("<IHBB")  # value word, address, argument, command (see mds_ach.bus.mcb)
log = logging.getLogger(__name__)

DEFAULT_MAX_VELOCITY_REV_S = 0.5  # motor revolutions/s when nothing set it (assumption: not in any source)
DEFAULT_ACCEL_DEG_S2 = 80.0
NODE_LATENCY = 100e-6  # s from a command's end on the wire to the node's reply being ready (assumption)


def trajectory_step(pos: np.ndarray, vel: np.ndarray, target: np.ndarray, vmax: np.ndarray, accel: np.ndarray,
                    dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One trajectory-period update of an acceleration-limited move (the MCB's MOVETO, modelled).

    Works in the frame pointing at the target: ``u`` is the speed towards it and ``e`` the distance. The
    speed at the end of the period is the largest that can still stop at the target with deceleration
    ``a`` after moving ``(u + u') dt / 2`` during the period, i.e. the root of
    ``u'^2 + a dt u' + a dt u - 2 a e = 0``; it is capped by ``vmax`` and changes by at most ``a dt``.
    The position advances by the period's mean speed (exact for constant acceleration); a period that
    reaches the target (or would have to end at rest there anyway) lands on it at rest.
    """
    err = target - pos
    s = np.where(err < 0, -1.0, 1.0)
    e = np.abs(err)
    u = s * vel
    adt = accel * dt
    stop = 0.5 * (-adt + np.sqrt(np.maximum(0.0, adt * adt - 4.0 * adt * u + 8.0 * accel * e)))
    new_u = np.clip(np.minimum(vmax, stop), u - adt, u + adt)
    travel = 0.5 * (u + new_u) * dt
    # stop <= 0: even braking to rest within this period covers the distance, so the move ends now.
    landed = (travel >= e - 1e-9 * np.maximum(1.0, e)) | ((stop <= 0.0) & (u >= 0.0))
    return np.where(landed, target, pos + s * travel), np.where(landed, 0.0, s * new_u)


class ManualClock:
    """A clock for deterministic tests: time moves only when told to."""

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, dt: float) -> None:
        self.now += dt


@dataclass
class _NodeFaults:
    offline: bool = False
    drop_count: int = 0  # drop this many of the next replies (-1: all)
    drop_probability: float = 0.0
    delay: float = 0.0
    position_offset: float = 0.0  # counts added to ACTUAL_POSITION replies (a bogus reading)
    offset_replies: int = 0  # that many of the next position replies (-1: until cleared with 0)


class _Joint(Protocol):
    """What ``SimNetwork.from_table`` reads of a joint (``mds_ach.robot.config.JointConfig``; the bus layer
    must not import the robot layer)."""

    @property
    def address(self) -> int: ...
    @property
    def cpr(self) -> float: ...
    @property
    def rom(self) -> float: ...
    def to_counts(self, q: float) -> float: ...


class _JointTable(Protocol):
    """What ``SimNetwork.from_table`` reads of a ``mds_ach.robot.config.JointTable``."""

    def __iter__(self) -> Iterator[_Joint]: ...
    def __getitem__(self, key: str) -> _Joint: ...


class SimNetwork:
    """The simulated nodes and the wire between them and the host."""

    def __init__(
        self,
        nodes: dict[int, float],
        *,
        initial_counts: dict[int, float] | None = None,
        rom_counts: dict[int, float] | None = None,
        bitrate: float | None = 1_000_000,
        clock: Callable[[], float] = time.monotonic,
        tx_backlog_s: float = 0.05,
        done_warnings: bool = True,
        seed: int = 0,
    ) -> None:
        """``nodes`` maps address -> counts per revolution (for the default acceleration and speed)."""
        self.clock = clock
        self.bitrate = bitrate
        self.frame_time = mcb.FRAME_BITS / bitrate if bitrate else 0.0
        self.tx_backlog_s = tx_backlog_s
        self.done_warnings = done_warnings
        self.addresses = tuple(sorted(nodes))
        self.index = {a: i for i, a in enumerate(self.addresses)}
        n = len(self.addresses)
        cpr = np.array([nodes[a] for a in self.addresses], dtype=float)
        self.cpr = cpr
        init = initial_counts or {}
        self.physical = np.array([float(init.get(a, 0.0)) for a in self.addresses])  # counts from ROM middle
        self.encoder_offset = np.zeros(n)  # measured = physical - encoder_offset
        self.velocity = np.zeros(n)
        self.target = self.physical.copy()  # physical frame
        self.accel = cpr * DEFAULT_ACCEL_DEG_S2 / 360.0
        self.max_velocity = cpr * DEFAULT_MAX_VELOCITY_REV_S
        self.period = np.full(n, float(mcb.TrajectoryPeriod.P19_53125MS))
        self.mode = np.full(n, int(TrajectoryMode.NEXTPOINT))
        self.enabled = np.ones(n, dtype=bool)
        self.running = np.zeros(n, dtype=bool)
        self.homing = np.zeros(n, dtype=bool)
        self.rom = np.array([float((rom_counts or {}).get(a, 0.0)) for a in self.addresses])
        self.ack_counter = np.zeros(n, dtype=int)
        self.faults = {a: _NodeFaults() for a in self.addresses}
        self.rng = random.Random(seed)
        self._next_tick = np.full(n, math.inf)  # next trajectory tick per node
        self._lock = threading.Condition()
        self._queue: list[tuple[float, int, can.Message]] = []  # heap of (due, seq, frame)
        self._seq = 0
        self._wire_free = 0.0
        self._earliest_tick = math.inf  # no trajectory tick due before this time
        self.state = can.BusState.ACTIVE
        self.bus_off_active = False
        # statistics (what crossed the simulated wire)
        self.rx_frames = 0  # frames the nodes received
        self.tx_frames = 0  # frames the nodes sent
        self.frames_by_address: dict[int, int] = {}
        self._sent: list[tuple[float, int, bytes]] = []  # every host frame as (time, id, data), bounded
        self.keep_commands = 20_000

    @classmethod
    def from_table(cls, table: _JointTable, pose: dict[str, float] | None = None, extra_nodes: Iterable[int] = (),
                   **kwargs: Any) -> SimNetwork:
        """Nodes for every joint of a :class:`mds_ach.robot.config.JointTable`; ``pose``: joint rad by short name."""
        nodes = {j.address: j.cpr for j in table}
        for a in extra_nodes:
            nodes.setdefault(a, 51200.0)
        init = {table[s].address: table[s].to_counts(q) for s, q in (pose or {}).items()}
        rom = {j.address: j.rom for j in table}
        return cls(nodes, initial_counts=init, rom_counts=rom, **kwargs)

    # --- positions in counts, for tests and tools ------------------------------------------------------

    def position(self, address: int) -> float:
        """What the node's encoder reads now (counts)."""
        with self._lock:
            self._advance(self.clock())
            i = self.index[address]
            return float(self.physical[i] - self.encoder_offset[i])

    def set_position(self, address: int, counts: float) -> None:
        """Move a joint by hand (back-drive it): physical position jumps, the node's target follows."""
        with self._lock:
            i = self.index[address]
            self.physical[i] = counts + self.encoder_offset[i]
            self._stop(i)

    def is_running(self, address: int) -> bool:
        with self._lock:
            self._advance(self.clock())
            return bool(self.running[self.index[address]])

    # --- fault injection -------------------------------------------------------------------------------

    def set_offline(self, address: int, offline: bool = True) -> None:
        """An offline node neither answers nor acts on commands (power loss, broken cable)."""
        with self._lock:
            self.faults[address].offline = offline

    def drop_replies(self, address: int | None = None, count: int = -1, probability: float = 0.0) -> None:
        """Drop the next ``count`` replies (-1: all until cleared with count=0) or each with ``probability``."""
        with self._lock:
            for a in [address] if address is not None else self.addresses:
                self.faults[a].drop_count = count
                self.faults[a].drop_probability = probability

    def delay_replies(self, address: int | None, delay: float) -> None:
        """Late replies: extra seconds before a node's replies reach the wire."""
        with self._lock:
            for a in [address] if address is not None else self.addresses:
                self.faults[a].delay = delay

    def offset_positions(self, address: int, counts: float, replies: int = 1) -> None:
        """Bogus readings: the node's next ``replies`` ACTUAL_POSITION replies (-1: all until cleared with 0) are
        off by ``counts``; the node itself does not move."""
        with self._lock:
            self.faults[address].position_offset = float(counts)
            self.faults[address].offset_replies = replies

    def inject_frame(self, arbitration_id: int, data: bytes, *, is_extended_id: bool = False,
                     dlc: int | None = None) -> None:
        """Put an arbitrary frame on the wire towards the host (unknown nodes, malformed frames)."""
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=is_extended_id,
                          dlc=len(data) if dlc is None else dlc, check=False)
        with self._lock:
            self._enqueue(msg, self.clock())

    def inject_error_frame(self, error_class: int = CAN_ERR_PROT | CAN_ERR_BUSERROR, status: int = 0) -> None:
        """An error frame as SocketCAN reports it (class bits in the ID, controller status in data[1])."""
        data = bytes([0, status, 0, 0, 0, 0, 0, 0])
        msg = can.Message(arbitration_id=error_class, data=data, is_error_frame=True, is_extended_id=False)
        with self._lock:
            if status & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE):
                self.state = can.BusState.PASSIVE
            elif status & CAN_ERR_CRTL_ACTIVE and not self.bus_off_active:
                self.state = can.BusState.ACTIVE
            self._enqueue(msg, self.clock(), wire=False)

    def bus_off(self) -> None:
        """The host controller goes bus-off: an error frame, then every send fails until a restart."""
        with self._lock:
            self.bus_off_active = True
            self.state = can.BusState.ERROR
            self._queue.clear()
            msg = can.Message(arbitration_id=CAN_ERR_BUSOFF, data=bytes(8), is_error_frame=True)
            self._enqueue(msg, self.clock(), wire=False)

    def restart(self) -> None:
        """Controller restart (``ip link set canX type can restart``): back to error-active."""
        with self._lock:
            was_off = self.bus_off_active
            self.bus_off_active = False
            self.state = can.BusState.ACTIVE
            self._wire_free = 0.0
            if was_off:
                msg = can.Message(arbitration_id=CAN_ERR_RESTARTED, data=bytes(8), is_error_frame=True)
                self._enqueue(msg, self.clock(), wire=False)

    # --- the wire ----------------------------------------------------------------------------------------

    def _enqueue(self, msg: can.Message, ready: float, wire: bool = True) -> None:
        if wire and self.frame_time:
            start = max(ready, self._wire_free)
            due = start + self.frame_time
            self._wire_free = due
        else:
            due = ready
        self._seq += 1
        heapq.heappush(self._queue, (due, self._seq, msg))
        self._lock.notify_all()

    def host_send(self, msg: can.Message) -> None:
        """A frame from the host: occupies the wire, then every addressed node handles it."""
        with self._lock:
            if self.bus_off_active:
                raise can.CanOperationError("simulated bus is bus-off (ENETDOWN)")
            now = self.clock()
            self._advance(now)
            if self.frame_time:
                start = max(now, self._wire_free)
                if start - now > self.tx_backlog_s:
                    raise can.CanOperationError("simulated transmit buffer full (ENOBUFS)")
                end = start + self.frame_time
                self._wire_free = end
            else:
                end = now
            if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id or msg.dlc != mcb.DLC:
                return  # MCB nodes only understand 8-byte standard data frames
            data = bytes(msg.data)
            if len(self._sent) < self.keep_commands:
                self._sent.append((now, msg.arbitration_id, data))
            if msg.arbitration_id == mcb.BROADCAST_SID:
                targets = self.addresses
            elif msg.arbitration_id in self.index:
                targets = (msg.arbitration_id,)
            else:
                return
            word, _, arg, cmd = _WORD.unpack(data)
            for address in targets:
                self._handle(address, cmd, arg, word, end)

    @property
    def commands(self) -> list[tuple[float, mcb.McbFrame]]:
        """Every frame the host sent (up to ``keep_commands``), decoded, with the simulated time it was sent."""
        with self._lock:
            sent = list(self._sent)
        return [(t, mcb.decode(i, d)) for t, i, d in sent]

    def host_recv(self, timeout: float | None) -> can.Message | None:
        """The next frame for the host whose wire time has come; waits up to ``timeout`` seconds.

        With a :class:`ManualClock` the wait is simulated: time jumps to the next delivery (or to the end of
        the timeout), so a test's loop runs as fast as the CPU allows and exactly as scheduled.
        """
        manual_clock = self.clock if isinstance(self.clock, ManualClock) else None
        manual = manual_clock is not None
        wall = self.clock if manual else time.monotonic
        deadline = None if timeout is None else wall() + timeout
        with self._lock:
            while True:
                now = self.clock()
                self._advance(now)
                if self._queue and self._queue[0][0] <= now:
                    msg = heapq.heappop(self._queue)[2]
                    msg.timestamp = time.time()
                    return msg
                wait = None if deadline is None else deadline - wall()
                if wait is not None and wait <= 0:
                    return None
                if self._queue:
                    until_due = self._queue[0][0] - now
                    wait = until_due if wait is None else min(wait, until_due)
                if manual_clock is not None:
                    if wait is None:
                        return None  # nothing will arrive in simulated time
                    manual_clock.advance(wait)
                else:
                    self._lock.wait(wait)

    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    # --- node behaviour ------------------------------------------------------------------------------------

    def _reply(self, address: int, raw: mcb.RawFrame, ready: float) -> None:
        f = self.faults[address]
        if f.drop_count != 0:
            if f.drop_count > 0:
                f.drop_count -= 1
            return
        if f.drop_probability and self.rng.random() < f.drop_probability:
            return
        self.tx_frames += 1
        msg = can.Message(arbitration_id=raw.arbitration_id, data=raw.data, is_extended_id=False)
        self._enqueue(msg, ready + NODE_LATENCY + f.delay)

    def _ack(self, address: int, i: int, command: int, argument: int, ready: float) -> None:
        self.ack_counter[i] = (self.ack_counter[i] + 1) % mcb.ACK_COUNTER_MODULO
        self._reply(address, mcb.encode_ack(address, command, argument, int(self.ack_counter[i])), ready)

    def _handle(self, address: int, cmd: int, arg: int, word: int, ready: float) -> None:
        if self.faults[address].offline:
            return
        i = self.index[address]
        self.rx_frames += 1
        self.frames_by_address[address] = self.frames_by_address.get(address, 0) + 1
        if cmd == Command.QUERY_STATE:
            value = self._read(i, arg)
            f = self.faults[address]
            if arg == StateArg.ACTUAL_POSITION and f.offset_replies != 0 and value is not None:  # never None here
                value += f.position_offset
                if f.offset_replies > 0:
                    f.offset_replies -= 1
            if value is not None:
                self._reply(address, mcb.encode_state_reply(address, arg, value), ready)
            return
        if cmd == Command.SET:
            self._set(i, arg, mcb.typed_value(arg, word))
            self._start(i, ready)
        elif cmd == Command.ENABLE:
            self.enabled[i] = True
            self._start(i, ready)
        elif cmd == Command.DISABLE:
            self.enabled[i] = False
            self._stop(i)
        elif cmd in (Command.RESET, Command.ZERO_ENCODER):
            self.encoder_offset[i] = self.physical[i]
            self._stop(i)
            if cmd == Command.RESET:
                self.mode[i] = TrajectoryMode.NEXTPOINT
                self.ack_counter[i] = 0
        else:
            return  # not modelled: no reply
        self._ack(address, i, cmd, arg if cmd == Command.SET else 0, ready)

    def _stop(self, i: int) -> None:
        """Abort any move: the node holds where it is."""
        self.target[i], self.velocity[i], self.running[i], self.homing[i] = self.physical[i], 0.0, False, False
        self._next_tick[i] = math.inf

    def _start(self, i: int, t: float) -> None:
        """A node that has a move to run and is not ticking yet starts at the next tick of its period.

        Ticks lie on a common grid per period length (the nodes' clocks are not modelled as independent), so
        all moving nodes step together in one vectorised update.
        """
        if self.running[i] and self.enabled[i] and math.isinf(self._next_tick[i]):
            dt = self.period[i] / mcb.TRAJECTORY_TICK_HZ
            tick = math.ceil(t / dt) * dt
            self._next_tick[i] = tick
            self._earliest_tick = min(self._earliest_tick, tick)

    def _set(self, i: int, arg: int, value: float | int) -> None:
        if arg == StateArg.TRAJECTORY_ACCELERATION and value > 0:
            self.accel[i] = float(value)
        elif arg == StateArg.TRAJECTORY_MAX_VELOCITY and value > 0:
            self.max_velocity[i] = float(value)
        elif arg == StateArg.TRAJECTORY_PERIOD and value > 0:
            self.period[i] = float(value)
        elif arg == StateArg.MOVETO_TARGET:
            self.target[i] = float(value) + self.encoder_offset[i]
            self.homing[i] = False
            if self.mode[i] == TrajectoryMode.MOVETO:
                self.running[i] = True
        elif arg == StateArg.TRAJECTORY_MODE:
            self.mode[i] = int(value)
            if value == TrajectoryMode.MOVETO:
                self.running[i] = True
            elif value == TrajectoryMode.HOME:
                self.target[i], self.homing[i], self.running[i] = 0.0, True, True
        elif arg == StateArg.ENCODER:
            self.encoder_offset[i] = self.physical[i] - float(value)

    def _read(self, i: int, arg: int) -> float | int | None:
        measured = self.physical[i] - self.encoder_offset[i]
        if arg == StateArg.ACTUAL_POSITION:
            return float(measured)
        if arg in (StateArg.DESIRED_POSITION, StateArg.TRAJECTORY_POSITION):
            return float(measured)  # the setpoint: position tracks it exactly here
        if arg == StateArg.MOVETO_TARGET:
            return float(self.target[i] - self.encoder_offset[i])
        if arg == StateArg.TRAJECTORY_VELOCITY:
            return float(self.velocity[i])
        if arg == StateArg.ENCODER:
            return int(round(measured))
        if arg == StateArg.CURRENT:
            # A plain model: idle current plus a share proportional to speed while moving (uint16, mA-ish).
            if not self.enabled[i]:
                return 0
            return int(12 + 400 * abs(self.velocity[i]) / self.max_velocity[i])
        if arg == StateArg.IS_TRAJECTORY_RUNNING:
            return int(bool(self.running[i]))
        if arg == StateArg.IS_ENABLED:
            return int(bool(self.enabled[i]))
        if arg == StateArg.TRAJECTORY_MODE:
            return int(self.mode[i])
        if arg == StateArg.TRAJECTORY_ACCELERATION:
            return float(self.accel[i])
        if arg == StateArg.TRAJECTORY_MAX_VELOCITY:
            return float(self.max_velocity[i])
        if arg == StateArg.TRAJECTORY_PERIOD:
            return int(self.period[i])
        if arg in (StateArg.UPPER_LIMIT, StateArg.LOWER_LIMIT):
            half = self.rom[i] / 2.0
            return int(round(half if arg == StateArg.UPPER_LIMIT else -half))
        return None

    def _advance(self, now: float) -> None:
        """Integrate every running trajectory up to ``now`` in steps of each node's trajectory period."""
        if now < self._earliest_tick:
            return
        while True:
            moving = self.running & self.enabled
            if not moving.any():
                self._next_tick[:] = math.inf
                self._earliest_tick = math.inf
                return
            tick = float(self._next_tick[moving].min())
            if tick > now:
                self._earliest_tick = tick
                return
            due = moving & (self._next_tick <= tick + 1e-6)  # same grid tick despite float rounding
            dt = self.period[due] / mcb.TRAJECTORY_TICK_HZ
            pos, vel = trajectory_step(self.physical[due], self.velocity[due], self.target[due],
                                       self.max_velocity[due], self.accel[due], dt)
            self.physical[due], self.velocity[due] = pos, vel
            self._next_tick[due] = tick + dt
            arrived = due & (self.physical == self.target) & (self.velocity == 0.0)
            for i in np.flatnonzero(arrived):
                self.running[i] = False
                self._next_tick[i] = math.inf
                address = self.addresses[i]
                if self.homing[i]:
                    self.encoder_offset[i], self.homing[i] = self.physical[i], False
                if self.done_warnings and not self.faults[address].offline:
                    counts = float(self.target[i] - self.encoder_offset[i])
                    word = mcb.value_word(StateArg.MOVETO_TARGET, counts)
                    self._reply(address, mcb.encode_warning(address, ErrorCode.TRAJECTORY_BUFFER_EMPTY, word),
                                tick)


class SimBus(can.BusABC):
    """python-can bus onto a :class:`SimNetwork` (what ``--nocan`` opens)."""

    def __init__(self, channel: str = "sim", network: SimNetwork | None = None, **kwargs: object) -> None:
        if network is None:
            raise can.CanInitializationError("SimBus needs a SimNetwork (network=...)")
        self.network = network
        self.channel_info = f"simulated MDS bus ({len(network.addresses)} nodes)"
        network.restart()  # opening the interface restarts the controller, as `ip link set up` does
        super().__init__(channel, can_filters=None, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._is_shutdown:
            raise can.CanOperationError("bus is shut down")
        self.network.host_send(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """Straight to the network: python-can's retry loop counts real time, which a simulated clock breaks."""
        if self._is_shutdown:
            raise can.CanOperationError("bus is shut down")
        return self.network.host_recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False

    @property
    def state(self) -> can.BusState:
        return self.network.state

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        raise NotImplementedError("the simulated bus state follows the network")

    def shutdown(self) -> None:
        super().shutdown()


class FaultControl:
    """Test-only remote control of a running simulated bus: fault injection from another process.

    A Unix stream socket (mode 0600, replaced if it exists) takes one JSON request per connection, e.g.
    ``{"op": "offline", "address": 76, "on": true}``, and answers ``ok`` (or ``ok <value>``) or ``error: ...``.
    Operations: ``offline`` (address, on), ``bogus_positions`` (address, counts, replies), ``drop_replies``
    (address, count), ``delay_replies`` (address, delay), ``error_frame`` (error_class, status), ``bus_off``,
    ``position`` (address: the node's encoder reading). It exists only inside ``daemon --nocan --sim-faults
    PATH``: on a real bus there is nothing to inject into.
    """

    def __init__(self, path: str | Path, network: SimNetwork) -> None:
        self.path = Path(path)
        self.network = network
        if self.path.is_socket():
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old = os.umask(0o177)
        try:
            self._sock.bind(str(self.path))
        finally:
            os.umask(old)
        self._sock.listen(4)
        self._thread = threading.Thread(target=self._serve, name="sim-faults", daemon=True)
        self._thread.start()

    def apply(self, request: dict[str, Any]) -> str:
        """Carry out one request; the answer text ('ok ...'), ValueError/KeyError/TypeError for a bad one."""
        net, op = self.network, request.get("op")
        args = {k: v for k, v in request.items() if k != "op"}
        if op == "offline":
            net.set_offline(int(args["address"]), bool(args.get("on", True)))
        elif op == "bogus_positions":
            net.offset_positions(int(args["address"]), float(args["counts"]), int(args.get("replies", 1)))
        elif op == "drop_replies":
            net.drop_replies(int(args["address"]), int(args.get("count", -1)))
        elif op == "delay_replies":
            net.delay_replies(int(args["address"]), float(args["delay"]))
        elif op == "error_frame":
            net.inject_error_frame(int(args.get("error_class", CAN_ERR_PROT | CAN_ERR_BUSERROR)),
                                   int(args.get("status", 0)))
        elif op == "bus_off":
            net.bus_off()
        elif op == "position":
            return f"ok {net.position(int(args['address'])):.6f}"
        else:
            raise ValueError(f"unknown op {op!r}")
        return "ok"

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return  # closed
            with conn:
                try:
                    conn.settimeout(5.0)
                    data = b""
                    while not data.endswith(b"\n") and len(data) < 4096:
                        chunk = conn.recv(4096)
                        if not chunk:
                            break
                        data += chunk
                    try:
                        answer = self.apply(json.loads(data))
                    except (ValueError, KeyError, TypeError, AttributeError) as exc:
                        answer = f"error: {type(exc).__name__}: {exc}"
                    log.warning("sim-faults: %s -> %s", data.decode(errors="replace").strip(), answer)
                    conn.sendall(answer.encode() + b"\n")
                except OSError as exc:
                    log.warning("sim-faults: %s", exc)

    def close(self) -> None:
        self._sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


def send_fault(path: str | Path, op: str, timeout: float = 10.0, **args: Any) -> str:
    """Ask a running ``daemon --nocan --sim-faults PATH`` to inject a fault; returns its answer ('ok ...'),
    RuntimeError if it refused."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(str(path))
        sock.sendall(json.dumps({"op": op, **args}).encode() + b"\n")
        answer = b""
        while not answer.endswith(b"\n"):
            chunk = sock.recv(4096)
            if not chunk:
                break
            answer += chunk
    text = answer.decode().strip()
    if not text.startswith("ok"):
        raise RuntimeError(f"sim-faults {path}: {op} {args}: {text or 'no answer'}")
    return text
