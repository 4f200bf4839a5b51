"""``mds-ach replay FILE.mcap --to-channels`` (issue 30 item 4): the recorded reports back on the channels, in
order and spacing; refused while a daemon is live, stopped when one appears; never a reference or a command."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from support import REPO

import mds_ach as mds
from mds_ach import ach
from mds_ach.record import replay
from mds_ach.record import schema as wire
from mds_ach.record.sink import RecordingSink
from mds_ach.robot import contracts
from mds_ach.robot.channels import StructChannel, make_channels
from mds_ach.robot.joints import lookup
from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS

pytestmark = pytest.mark.usefixtures("clean_shm")
T0 = 1_700_000_000 * 10**9
RSP = lookup("RSP").address
MDS_ACH = [sys.executable, "-m", "mds_ach.tools.cli"]


def recording(path: Path, n: int = 20, dt: float = 0.05) -> list[mds.MDS_STATE]:
    sink = RecordingSink(path)
    states = []
    for k in range(n):
        st = mds.MDS_STATE()
        st.joint[RSP].pos = 0.01 * k
        st.time = 100.0 + k * dt
        states.append(st)
        for name, frame in ((contracts.MDS_CHAN_STATE_NAME, st), (contracts.MDS_CHAN_REF_GATED_NAME, mds.MDS_REF())):
            ws = wire.wire_schema(contracts.contract(name).struct)
            ns = T0 + int(k * dt * 1e9)
            sink.write(wire.topic(name), (ws.name, ws.text), ws.to_message(frame), ns, ns)
    sink.close()
    return states


def test_replay_writes_the_recorded_state_in_order_and_spacing(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    states = recording(path)
    make_channels()
    got: list[tuple[float, bytes]] = []
    stop = threading.Event()
    gated_before = ach.Channel(mds.MDS_CHAN_REF_GATED_NAME, create=False)
    seq_before = gated_before.last_seq

    def read() -> None:
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
            while not stop.is_set():
                frame = ch.wait_next(0.1)
                if frame is not None:
                    got.append((time.monotonic(), bytes(frame)))

    reader = threading.Thread(target=read)
    reader.start()
    time.sleep(0.2)
    try:
        result = replay.replay(path)
    finally:
        time.sleep(0.2)
        stop.set()
        reader.join(10)
    assert result.stopped == "" and result.frames == len(states)
    assert [b for _, b in got] == [bytes(s) for s in states]
    span = got[-1][0] - got[0][0]
    assert 0.8 * 19 * 0.05 <= span <= 19 * 0.05 + 1.0  # spaced as recorded
    assert gated_before.last_seq == seq_before  # the daemon's input was never written
    gated_before.close()


def writer(name: str, ctype: Any, stop: threading.Event) -> threading.Thread:
    def body() -> None:
        with StructChannel(name, ctype, create=False) as ch:
            while not stop.is_set():
                ch.put(ctype())
                time.sleep(0.05)

    t = threading.Thread(target=body)
    t.start()
    return t


def test_replay_refuses_while_a_daemon_is_live(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    recording(path)
    make_channels()
    stop = threading.Event()
    t = writer(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS, stop)
    try:
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
            seq = ch.channel.last_seq
            out = subprocess.run([*MDS_ACH, "replay", str(path), "--to-channels"], cwd=REPO, capture_output=True,
                                 text=True, timeout=60)
            assert ch.channel.last_seq == seq  # nothing written
    finally:
        stop.set()
        t.join()
    assert out.returncode == 1 and "refused" in out.stderr and "mds-daemon-status is being written" in out.stderr
    assert "Traceback" not in out.stderr


def test_replay_stops_when_another_writer_appears(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    recording(path, n=60)
    make_channels()
    box: dict[str, Any] = {}
    t = threading.Thread(target=lambda: box.setdefault("r", replay.replay(path)))
    t.start()
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
        deadline = time.monotonic() + 30
        while ch.channel.last_seq < 3:  # the replay is writing
            assert time.monotonic() < deadline
            time.sleep(0.01)
    stop = threading.Event()
    w = writer(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, stop)
    t.join(30)
    stop.set()
    w.join()
    result = box["r"]
    assert "another writer" in result.stopped and result.frames < 60


def test_replay_cli_never_writes_references(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    recording(path, n=2)
    out = subprocess.run([*MDS_ACH, "replay", str(path), "--to-channels", "--channels", "mds-ref-gated"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "not replayed" in out.stderr
    out = subprocess.run([*MDS_ACH, "replay", str(path)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "--to-channels" in out.stderr
