"""``mds-ach plot`` (issue 30 item 2): the data behind the figure equal the recording's (not pixels): every stage's
command, measured, limits, hold/cancel and gate intervals, check-log findings; a CAN log plots too."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import REPO

import mds_ach as mds
from mds_ach.record import plot, recording
from mds_ach.record import schema as wire
from mds_ach.record.sink import RecordingSink
from mds_ach.robot import contracts
from mds_ach.robot.joints import lookup
from mds_ach.robot.msgs import MDS_LIMITS, MDS_MUX_STATE
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_HELD

T0 = 1_700_000_000 * 10**9
RSP = lookup("RSP").address
LEP = lookup("LEP").address


def write(path: Path, frames: list[tuple[str, float, Any]]) -> None:
    """A recording of ``frames`` (channel, t s after T0, frame), through the recorder's own sink and schemas."""
    sink = RecordingSink(path)
    for name, t, frame in frames:
        ws = wire.wire_schema(contracts.contract(name).struct)
        ns = T0 + int(t * 1e9)
        sink.write(wire.topic(name), (ws.name, ws.text), ws.to_message(frame), ns, ns)
    sink.close()


def ref(**joints: float) -> mds.MDS_REF:
    r = mds.MDS_REF()
    for short, v in joints.items():
        r.joint[lookup(short).address].ref = v
    return r


def state(pos: float, cmd: float) -> mds.MDS_STATE:
    s = mds.MDS_STATE()
    s.joint[RSP].pos, s.joint[RSP].ref = pos, cmd
    s.joint[RSP].name = b"RSP"
    return s


def scenario(tmp_path: Path) -> Path:
    lim = MDS_LIMITS()
    lim.valid[RSP], lim.lower[RSP], lim.upper[RSP] = 1, -1.5, 0.75
    lim.robot = b"isaac"
    frames: list[tuple[str, float, Any]] = [(contracts.MDS_CHAN_LIMITS_NAME, 0.0, lim)]
    for k in range(20):
        t = 0.1 * k
        frames.append((contracts.MDS_CHAN_REF_FILTER_NAME, t, ref(RSP=0.5)))
        frames.append((contracts.MDS_CHAN_REF_MUX_NAME, t + 0.01, ref(RSP=0.5)))
        frames.append((contracts.MDS_CHAN_REF_SMOOTH_NAME, t + 0.02, ref(RSP=0.025 * k)))
        frames.append((contracts.MDS_CHAN_REF_GATED_NAME, t + 0.03, ref(RSP=0.02 * k)))
        frames.append((contracts.MDS_CHAN_STATE_NAME, t + 0.05, state(0.019 * k, 0.02 * k)))
        ms = MDS_MUX_STATE()
        ms.held[RSP] = MUX_HELD if 5 <= k < 8 else (MUX_CANCELLED if k >= 15 else 0)
        frames.append((contracts.MDS_CHAN_MUX_STATE_NAME, t, ms))
        c = mds.MDS_COLLIDE()
        if 10 <= k < 12:
            c.isCollide = 1
            c.joint[mds.COLLIDE_R_HAND].isCollide = 1  # the right arm: RSP is held, LEP not
        frames.append((contracts.MDS_CHAN_COLLIDE_NAME, t, c))
    path = tmp_path / "run.mcap"
    write(path, frames)
    return path


def test_plot_data_equal_the_recording(tmp_path: Path) -> None:
    path = scenario(tmp_path)
    rec = recording.load(path)
    data = plot.plot_data(rec, ["RSP", "LEP"])
    assert data.title == "run.mcap -- robot isaac"
    rsp, lep = data.joints
    assert list(rsp.commands) == ["input mds-ref-filter", "mux (mds-ref-mux)", "filter (mds-ref-smooth)",
                                  "gate (mds-ref-gated)", "sent (daemon, mds-state ref)"]
    t, v = rsp.commands["gate (mds-ref-gated)"]
    assert np.allclose(t, [0.1 * k + 0.03 for k in range(20)]) and np.array_equal(v, [0.02 * k for k in range(20)])
    t, v = rsp.commands["filter (mds-ref-smooth)"]
    assert np.array_equal(v, [0.025 * k for k in range(20)])
    assert rsp.measured is not None and np.array_equal(rsp.measured[1], [0.019 * k for k in range(20)])
    assert rsp.limits == (-1.5, 0.75) and lep.limits is None
    spans = [(round(i.start, 6), round(i.end, 6), i.kind) for i in rsp.intervals]
    assert spans == [(0.5, 0.8, "hold"), (1.5, round((rec.end_ns - rec.start_ns) / 1e9, 6), "cancel"),
                     (1.0, 1.2, "gate")]
    assert [i.kind for i in lep.intervals] == []  # the right hand's contact does not hold the left arm
    assert "no CAN frames" in data.notes[0]


def test_the_figure_draws_exactly_the_data(tmp_path: Path) -> None:
    path = scenario(tmp_path)
    data = plot.plot_data(recording.load(path), ["RSP"])
    fig = plot.draw(data)
    ax = fig.axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    for label, (t, v) in data.joints[0].commands.items():
        assert np.array_equal(lines[label].get_xdata(), t) and np.array_equal(lines[label].get_ydata(), v), label
    measured = lines["measured (mds-state pos)"]
    assert np.array_equal(measured.get_ydata(), data.joints[0].measured[1])
    assert lines["limits (effective)"].get_ydata()[0] == -1.5
    assert ax.get_ylabel() == "RSP (rad)" and "time" in fig.axes[-1].get_xlabel() and "(s)" in ax.get_xlabel()
    assert "run.mcap -- robot isaac" in fig.get_suptitle()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert {"hold (mux)", "cancel (mux)", "collision gate held the arm"} <= set(legend)
    out = tmp_path / "fig.png"
    plot.save(fig, out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_findings_of_the_recorded_can_frames_are_marked(tmp_path: Path) -> None:
    """A recording with CAN frames: check-log's findings are on the time axis of the joint they concern."""
    import can

    from mds_ach.bus import mcb
    from mds_ach.record import canlog
    from mds_ach.robot import config

    table = config.load(None, None)
    cfg = next(j for j in table if j.short == "RSP")
    path = tmp_path / "can.mcap"
    sink = RecordingSink(path)
    frame = mcb.encode_moveto(cfg.address, cfg.to_counts(cfg.upper + 0.5))  # beyond the limit
    for k, data in enumerate([frame]):
        msg = can.Message(timestamp=T0 / 1e9 + 1.0 + k, arbitration_id=data.arbitration_id, data=data.data,
                          is_extended_id=False, is_rx=False)
        ns = int(msg.timestamp * 1e9)
        sink.write(canlog.CAN_TOPIC, canlog.CAN_SCHEMA, canlog.to_message(msg), ns, ns)
    ws = wire.wire_schema(mds.MDS_STATE)
    sink.write(wire.topic(contracts.MDS_CHAN_STATE_NAME), (ws.name, ws.text), ws.to_message(state(0.0, 0.0)), T0, T0)
    sink.close()
    data = plot.plot_data(recording.load(path), ["RSP"], table)
    assert [f.kind for f in data.joints[0].findings] == ["limit"]
    assert math.isclose(data.joints[0].findings[0].time, 1.0, abs_tol=1e-6)
    fig = plot.draw(data)
    assert any(line.get_label() == "check-log finding" and line.get_xdata()[0] == pytest.approx(1.0)
               for line in fig.axes[0].get_lines())


def test_plot_cli(tmp_path: Path) -> None:
    path = scenario(tmp_path)
    cli = [sys.executable, "-m", "mds_ach.tools.cli", "plot"]
    out = subprocess.run([*cli, str(path), "-o", str(tmp_path / "a.html"), "--joints", "RSP"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "a.html").read_text().startswith("<!DOCTYPE html>")
    out = subprocess.run([*cli, str(path), "--joints", "XYZ"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "unknown joint 'XYZ'" in out.stderr and "Traceback" not in out.stderr
    out = subprocess.run([*cli, str(path), "-o", str(tmp_path / "a.jpg")], cwd=REPO, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n")
    out = subprocess.run([*cli, str(tmp_path / "junk.mcap")], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "damaged" in out.stderr and "Traceback" not in out.stderr
