"""``mds-ach record`` on the whole running system (issue 30): every stage recorded, and the recorded frames of
``mds-state`` and ``mds-ref-gated`` are, frame for frame, what an independent in-order reader took from the
channels over the same time; the reference reader reads the file."""

from __future__ import annotations

import math
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from support import VENV_BIN
from support.system import running_system

import mds_ach as mds
from mds_ach.record import recording
from mds_ach.record import schema as wire
from mds_ach.robot import contracts
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import lookup


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    with running_system(tmp_path_factory.mktemp("record")) as env:
        yield env


def in_order(name: str, ctype: type, stop: threading.Event, out: dict[int, bytes]) -> threading.Thread:
    """Every frame of ``name`` from now on, by its Ach sequence number."""
    def body() -> None:
        with StructChannel(name, ctype, create=False) as ch:
            ch.channel.flush()  # only frames that arrive from now on
            while not stop.is_set():
                frame = ch.wait_next(0.1)
                if frame is not None:
                    out[ch.channel.seq_num] = bytes(frame)

    t = threading.Thread(target=body)
    t.start()
    return t


def test_whole_system_recording(system: dict[str, str], tmp_path: Path) -> None:
    path = tmp_path / "system.mcap"
    rec = subprocess.Popen([str(VENV_BIN / "mds-ach"), "record", str(path)], env=system, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    stop = threading.Event()
    seen: dict[str, dict[int, bytes]] = {mds.MDS_CHAN_STATE_NAME: {}, mds.MDS_CHAN_REF_GATED_NAME: {}}
    readers = [in_order(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, stop, seen[mds.MDS_CHAN_STATE_NAME]),
               in_order(mds.MDS_CHAN_REF_GATED_NAME, mds.MDS_REF, stop, seen[mds.MDS_CHAN_REF_GATED_NAME])]
    try:
        time.sleep(1.5)
        with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF, create=False) as goto:
            ref = mds.MDS_REF()
            t0 = time.monotonic()
            while time.monotonic() - t0 < 3.0:  # LSP down and back, slowly
                ref.joint[lookup("LSP").address].ref = -0.3 * math.sin(time.monotonic() - t0)
                goto.put(ref)
                time.sleep(0.05)
        time.sleep(1.0)
    finally:
        rec.send_signal(signal.SIGINT)
        out, err = rec.communicate(timeout=60)
        stop.set()
        for t in readers:
            t.join(10)
    assert rec.returncode == 0, err
    with open(path, "rb") as f:  # the reference reader, through the summary
        counts = make_reader(f, decoder_factories=[DecoderFactory()]).get_summary().statistics.channel_message_counts
    assert sum(counts.values()) > 50
    data = recording.load(path)
    assert data.cut == ""
    for name in (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME,
                 mds.MDS_CHAN_REF_GATED_NAME, mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_MUX_STATE_NAME,
                 mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_CHAN_DAEMON_STATUS_NAME, mds.MDS_CHAN_LIMITS_NAME,
                 mds.MDS_CHAN_PARAM_NAME):
        assert data.channel(name), f"nothing recorded from {name}"
    assert len(data.messages[wire.JOINT_STATES_TOPIC]) == len(data.channel(mds.MDS_CHAN_STATE_NAME))
    for name, frames in seen.items():
        ws = wire.wire_schema(contracts.contract(name).struct)
        recorded = {r.sequence: bytes(ws.from_message(r.message)) for r in data.channel(name)}
        seqs = sorted(recorded)
        assert seqs == list(range(seqs[0], seqs[-1] + 1)), f"{name}: a frame is missing"
        common = set(recorded) & set(frames)
        assert len(common) >= 10, name
        assert all(recorded[q] == frames[q] for q in common), name  # frame for frame
        # every frame the independent reader saw within the recording's span was recorded
        assert {q for q in frames if seqs[0] <= q <= seqs[-1]} == common, name
    assert "missed" not in out, out
    lsp = [f.joint[lookup("LSP").address].ref for _, f in data.frames(contracts.MDS_CHAN_REF_GATED_NAME)]
    assert min(lsp) < -0.1  # the move went through the pipeline into the recording
