"""``mds-ach record`` (issue 30): every channel to MCAP, read back with the reference reader; Ctrl-C, SIGKILL, a
full disk (a file-size limit), a system re-created while recording, --split; the schemas of every channel."""

from __future__ import annotations

import math
import os
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from support import REPO

import mds_ach as mds
from mds_ach import ach
from mds_ach.record import recorder, recording
from mds_ach.record import schema as wire
from mds_ach.robot import contracts
from mds_ach.robot.channels import StructChannel, make_channels
from mds_ach.robot.joints import lookup
from mds_ach.robot.msgs import MDS_LIMITS

pytestmark = pytest.mark.usefixtures("clean_shm")
MDS_ACH = [sys.executable, "-m", "mds_ach.tools.cli"]


def wait_for(cond: Any, timeout: float = 20.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def state_frame(k: int) -> mds.MDS_STATE:
    st = mds.MDS_STATE()
    for name in ("RSP", "LEP", "NKY"):
        j = st.joint[lookup(name).address]
        j.name = name.encode()
        j.pos = 0.01 * k + lookup(name).address * 1e-3
        j.ref = 0.02 * k
        j.vel = -0.5 * k
    st.time = time.monotonic()
    return st


def ref_frame(k: int, scale: float) -> mds.MDS_REF:
    ref = mds.MDS_REF()
    for name in ("RSP", "LEP"):
        ref.joint[lookup(name).address].ref = scale * k
        ref.joint[lookup(name).address].mode = 1
    return ref


def reference_read(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """The reference reader (mcap + mcap-ros2-support), seeking through the summary as Foxglove does."""
    out: dict[str, list[tuple[int, Any]]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_summary() is not None, "a finished recording has its summary"
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


class Writers:
    """Puts ``n`` frames on mds-state, mds-ref-gated and mds-ref-mux, each only after the recorder took the one
    before (the ring of mds-state holds two frames)."""

    def __init__(self) -> None:
        self.state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False)
        self.gated = StructChannel(mds.MDS_CHAN_REF_GATED_NAME, mds.MDS_REF, create=False)
        self.mux = StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF, create=False)

    def close(self) -> None:
        for c in (self.state, self.gated, self.mux):
            c.close()


def run_record(path: Path, stop: threading.Event, channels: list[str] | None = None,
               **kw: Any) -> tuple[threading.Thread, dict[str, Any]]:
    box: dict[str, Any] = {}

    def body() -> None:
        box["result"] = recorder.record(path, channels or list(contracts.ALL_CHANNELS), stop=stop, **kw)

    t = threading.Thread(target=body)
    t.start()
    return t, box


def test_every_channel_struct_has_a_schema_that_round_trips() -> None:
    """Every channel's struct becomes a ROS 2 definition the mcap-ros2 encoder and decoder take, and a frame comes
    back byte for byte (text fields as text)."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    for c in contracts.CHANNELS:
        ws = wire.wire_schema(c.struct)
        frame = c.struct()
        raw = bytearray(bytes(frame))
        for i in range(0, len(raw), 7):
            raw[i] = (i * 37) % 251 + 1
        frame = c.struct.from_buffer_copy(bytes(raw))
        # text fields hold text up to a NUL (what a char[N] field is)
        for f in ws.fields:
            if f.kind == "text":
                setattr(frame, f.c_name, b"abc")
        data = serialize_dynamic(ws.name, ws.text)[ws.name](ws.to_message(frame))
        back = ws.from_message(generate_dynamic(ws.name, ws.text)[ws.name](data))
        assert ws.to_message(back) == ws.to_message(frame) or _nan_equal(ws.to_message(back), ws.to_message(frame)), \
            c.name


def _nan_equal(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_nan_equal(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(_nan_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return bool(a == b)


def test_recorded_run_reads_back_with_the_reference_reader(tmp_path: Path) -> None:
    """Counts and values equal what the channels carried: every frame put while recording, in order, plus the
    newest frame already in a channel when the recording started (the limits)."""
    make_channels()
    limits = MDS_LIMITS()
    limits.seq = 7
    limits.valid[lookup("RSP").address] = 1
    limits.lower[lookup("RSP").address] = -1.25
    limits.upper[lookup("RSP").address] = 2.5
    with StructChannel(mds.MDS_CHAN_LIMITS_NAME, MDS_LIMITS, create=False) as ch:
        ch.put(limits)
    path = tmp_path / "run.mcap"
    stop = threading.Event()
    t, box = run_record(path, stop)
    w = Writers()
    n = 40
    sent_state, sent_gated = [], []
    try:
        time.sleep(0.5)  # the readers open their channels (a missing reader would show as a missing frame below)
        for k in range(n):
            st = state_frame(k)
            w.state.put(st)
            sent_state.append(st)
            g = ref_frame(k, 0.001)
            w.gated.put(g)
            sent_gated.append(g)
            w.mux.put(ref_frame(k, 0.002))
            time.sleep(0.02)
    finally:
        w.close()
        time.sleep(0.5)
        stop.set()
        t.join(30)
    result = box["result"]
    assert result.stopped_by == "stop"
    got = reference_read(path)
    states = got[wire.topic(mds.MDS_CHAN_STATE_NAME)]
    assert len(states) == n
    for (_log_ns, msg), st in zip(states, sent_state, strict=True):
        a = lookup("RSP").address
        assert msg.joint.pos[a] == st.joint[a].pos and msg.joint.vel[a] == st.joint[a].vel
        assert msg.joint.name[a] == "RSP" and msg.time == st.time
    assert [m.joint.ref[lookup("RSP").address] for _, m in got[wire.topic(mds.MDS_CHAN_REF_GATED_NAME)]] == \
        [g.joint[lookup("RSP").address].ref for g in sent_gated]
    assert len(got[wire.topic(mds.MDS_CHAN_REF_MUX_NAME)]) == n
    js = got[wire.JOINT_STATES_TOPIC]
    assert len(js) == n and list(js[-1][1].name) == sorted(["RSP", "LEP", "NKY"], key=lambda x: lookup(x).address)
    assert list(js[-1][1].position) == [sent_state[-1].joint[lookup(x).address].pos for x in js[-1][1].name]
    (_, lim), = got[wire.topic(mds.MDS_CHAN_LIMITS_NAME)]
    assert lim.seq == 7 and lim.upper[lookup("RSP").address] == 2.5
    # our own reader gives the same frames back as structs
    rec = recording.load(path)
    assert rec.cut == ""
    frames = [f for _, f in rec.frames(mds.MDS_CHAN_STATE_NAME)]
    assert [bytes(f) for f in frames] == [bytes(s) for s in sent_state]


def test_ctrl_c_and_sigkill(tmp_path: Path) -> None:
    """SIGINT (Ctrl-C) finishes the file (summary and footer); SIGKILL leaves one that reads up to the cut, with a
    clear note (or is refused with a clear message when nothing was written yet)."""
    make_channels()
    for sig, name in ((signal.SIGINT, "int.mcap"), (signal.SIGKILL, "kill.mcap")):
        path = tmp_path / name
        proc = subprocess.Popen([*MDS_ACH, "record", str(path)], cwd=REPO, stderr=subprocess.PIPE, text=True)
        try:
            with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
                k = 0
                deadline = time.monotonic() + 60
                # enough frames that a chunk (1 MiB before compression) was written before the kill
                while time.monotonic() < deadline and (k < 30 or not path.exists() or path.stat().st_size < 20_000):
                    ch.put(state_frame(k))
                    k += 1
                    time.sleep(0.01)
            proc.send_signal(sig)
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        rec = recording.load(path)
        if sig == signal.SIGINT:
            assert proc.returncode == 0, proc.stderr.read() if proc.stderr else ""
            assert rec.cut == ""
            reference_read(path)  # the summary is there
        else:
            assert "ends early" in rec.cut or "no summary" in rec.cut
            assert len(rec.channel(mds.MDS_CHAN_STATE_NAME)) > 0


def test_cut_file_before_any_message_is_refused_clearly(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"\x89MCAP0\r\n\x01\x05")
    with pytest.raises(recording.RecordingError, match="damaged before its first message"):
        recording.load(bad)
    (tmp_path / "x.mcap").write_text("hello")
    with pytest.raises(recording.RecordingError, match="not an MCAP recording"):
        recording.load(tmp_path / "x.mcap")


def test_full_disk_stops_with_a_clear_message_and_a_valid_file(tmp_path: Path) -> None:
    """Under a file-size limit (ulimit -f, as a small disk): the recorder stops before it, says why, exit 1, and
    the file is complete (summary) with everything up to the stop."""
    make_channels()
    path = tmp_path / "full.mcap"
    limit = 4 * 1024 * 1024

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = subprocess.Popen([*MDS_ACH, "record", str(path)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=limited)
    try:
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
            k = 0
            deadline = time.monotonic() + 120
            while proc.poll() is None and time.monotonic() < deadline:
                st = state_frame(k)
                for a in range(mds.MDS_JOINT_COUNT):  # incompressible values: the file grows fast
                    st.joint[a].cur = math.sin(k * 7.1 + a * 1.3) * 1e3
                ch.put(st)
                k += 1
                time.sleep(0.002)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1, err
    assert "file-size limit" in err + out and "Traceback" not in err
    assert path.stat().st_size <= limit
    got = reference_read(path)
    assert len(got[wire.topic(mds.MDS_CHAN_STATE_NAME)]) > 10


def test_system_restart_while_recording_and_split(tmp_path: Path) -> None:
    """The channels vanish (killall) and come back (a new start): the recorder goes on with the new ones. With
    --split by time each part is a complete file starting with the latched limits."""
    make_channels()
    with StructChannel(mds.MDS_CHAN_LIMITS_NAME, MDS_LIMITS, create=False) as ch:
        lim = MDS_LIMITS()
        lim.seq = 3
        ch.put(lim)
    path = tmp_path / "split.mcap"
    stop = threading.Event()
    t, box = run_record(path, stop, split=(None, 1.0))
    try:
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
            for k in range(20):
                ch.put(state_frame(k))
                time.sleep(0.02)
        time.sleep(0.5)
        for name in contracts.ALL_CHANNELS:
            ach.unlink(name)
        time.sleep(0.8)
        make_channels()
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as ch:
            for k in range(20, 40):
                ch.put(state_frame(k))
                time.sleep(0.1)
        time.sleep(1.5)
    finally:
        stop.set()
        t.join(30)
    result = box["result"]
    assert len(result.parts) >= 2
    assert result.stats[mds.MDS_CHAN_STATE_NAME].reopened >= 1
    pos = []
    for part in result.parts:
        got = reference_read(part)
        assert got[wire.topic(mds.MDS_CHAN_LIMITS_NAME)][0][1].seq == 3  # every part starts with the limits
        pos += [m.joint.pos[lookup("RSP").address] for _, m in got.get(wire.topic(mds.MDS_CHAN_STATE_NAME), [])]
    # Every frame is recorded in order, or counted as missed: mds-state's ring holds two frames, so a recorder starved
    # for over 0.1-0.2 s on a loaded machine (the suite's) misses some -- never silently, never out of order.
    expected = [state_frame(k).joint[lookup("RSP").address].pos for k in range(40)]
    it = iter(expected)
    assert all(any(p == e for e in it) for p in pos), f"recorded out of order or not written: {pos}"
    assert len(pos) + result.stats[mds.MDS_CHAN_STATE_NAME].missed == len(expected), (pos, result.stats)
    assert len(pos) >= 30, f"the recorder missed most frames: {pos}"


def test_record_cli_refuses_bad_input(tmp_path: Path) -> None:
    out = subprocess.run([*MDS_ACH, "record", str(tmp_path / "a.txt")], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 2 and "must end in .mcap" in out.stderr
    out = subprocess.run([*MDS_ACH, "record", "--channels", "mds-nope", str(tmp_path / "a.mcap")], cwd=REPO,
                         capture_output=True, text=True)
    assert out.returncode == 2 and "not MDS channels: mds-nope" in out.stderr
    out = subprocess.run([*MDS_ACH, "record", "--split", "10q", str(tmp_path / "a.mcap")], cwd=REPO,
                         capture_output=True, text=True)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert os.path.exists(tmp_path / "a.mcap") is False


def test_daemon_can_frames_in_the_recording_and_check_log_audits_it(tmp_path: Path) -> None:
    """A real daemon (simulated bus) with --can-log; the recorder adds its CAN frames of the recording's span on
    /can/frames; check-log audits the recording exactly as the CAN log's same frames (item 5)."""
    from mds_ach.record import canlog
    from mds_ach.robot import config
    from mds_ach.tools import checklog

    make_channels()
    can_log = tmp_path / "can.log"
    daemon = subprocess.Popen([sys.executable, "-m", "mds_ach.nodes.daemon", "--nocan", "--no-ros", "--rt-priority",
                               "0", "--can-log", str(can_log)], cwd=REPO, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    path = tmp_path / "run.mcap"
    stop = threading.Event()
    try:
        seen: dict[str, mds.MDS_STATE] = {}

        def live() -> bool:
            frame = st.latest()
            if frame is not None:
                seen["state"] = frame
            return "state" in seen and bool(seen["state"].joint[lookup("RSP").address].active)

        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as st:
            wait_for(live, 60, "a live daemon")
            start = seen["state"]
        t, box = run_record(path, stop, can_log=str(can_log))
        a = lookup("RSP").address
        with StructChannel(mds.MDS_CHAN_REF_GATED_NAME, mds.MDS_REF, create=False) as gated:
            ref = mds.MDS_REF()
            for k in range(30):  # a slow move: within the daemon's speed and acceleration bounds
                ref.joint[a].ref = start.joint[a].pos + 0.002 * k
                ref.joint[a].mode = 1
                gated.put(ref)
                time.sleep(0.05)
        time.sleep(0.5)
        stop.set()
        t.join(60)
    finally:
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
    result = box["result"]
    assert result.can_frames > 0
    frames, cut = canlog.recorded_frames(path)
    assert cut == "" and len(frames) == result.can_frames
    def key(m: Any) -> tuple[float, int, bytes, bool]:
        return round(m.timestamp, 6), m.arbitration_id, bytes(m.data), m.is_rx

    # every recorded frame is the log's, in the log's order; every frame the log has from well inside the recording's
    # span (the daemon's log file may not have flushed its last lines when the recording ended) was recorded
    logged = [key(m) for m in canlog.frames_between(can_log, 0, 2**32)]
    recorded = [key(m) for m in frames]
    it = iter(logged)
    assert all(k in it for k in recorded)
    inner = [k for k in logged if frames[0].timestamp + 0.2 <= k[0] <= frames[-1].timestamp - 1.0]
    assert inner and set(inner) <= set(recorded)
    table = config.load(None, None)
    rep = checklog.audit_file(path, table)
    assert rep.error == "" and rep.format == "MCAP recording" and rep.frames == len(frames)
    assert rep.targets["RSP"] > 0 and rep.findings == []
    out = subprocess.run([*MDS_ACH, "check-log", str(path)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "MCAP recording" in out.stdout, out.stdout + out.stderr
    # a recording without CAN frames is refused with the reason, exit 2
    bare = tmp_path / "bare.mcap"
    recorder.record(bare, [mds.MDS_CHAN_STATE_NAME], duration=0.3)
    out = subprocess.run([*MDS_ACH, "check-log", str(bare)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "no CAN frames" in out.stdout and "Traceback" not in out.stderr


@pytest.mark.parametrize("verb", ["record", "plot", "replay"])
def test_verbs_have_help(verb: str) -> None:
    out = subprocess.run([*MDS_ACH, verb, "--help"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith(f"usage: mds-ach {verb}"), out.stderr
    assert "Foxglove" in out.stdout or "daemon" in out.stdout or "stage" in out.stdout
