"""The mux's dead-man (issue #31 item 3): a controller that declares a heartbeat and stops streaming gets a
protective stop (its joints held, the filter brakes them to rest), not a continuation of its last command."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from support import wait_for
from test_mux import ALL, ARMS, ZERO_MODE, _frame, _newest, _put, _start_ref

import mds_ach as mds
from mds_ach.nodes.mux import MDS_MUX_STATE, Controller, MuxCore, MuxRunner, parse_controllers
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs.mux_state import MUX_FREE, MUX_HELD

HEARTBEAT = 0.2


def _controllers() -> list[Controller]:
    return [Controller("ros", "mds-ref-ros", 30, ALL, 1.0, heartbeat=HEARTBEAT),
            Controller("ik", "mds-ref-ik", 20, ARMS, 2.0),
            Controller("default", "mds-ref-filter", 10, ALL, None, seed=True, legacy=True)]


def test_a_stopped_stream_holds_its_joints_until_a_new_command() -> None:
    ref, mode = _start_ref()
    core = MuxCore(_controllers(), ref, mode)
    frame = _frame(ref, LSP=-0.5, NKY=0.1)
    for k in range(5):  # streaming at 20 Hz: the same frame re-put counts as a beat
        core.update(0, frame, ZERO_MODE, 0.05 * k)
        assert core.heartbeats(0.05 * k + 0.01) == []
    assert core.next_heartbeat() == pytest.approx(0.2 + HEARTBEAT)
    assert core.heartbeats(0.2 + HEARTBEAT - 1e-3) == []
    lost = core.heartbeats(0.2 + HEARTBEAT + 1e-3)
    assert len(lost) == 1 and "protective stop" in lost[0] and "LSP" in lost[0]
    assert core.held[mds.LSP] == MUX_HELD and core.held[mds.NKY] == MUX_HELD
    assert core.held[mds.LEP] == MUX_FREE  # never commanded by it: not its joint
    assert core.heartbeats(1.0) == [] and core.next_heartbeat() == np.inf  # said once
    core.update(0, frame, ZERO_MODE, 1.0)  # the stream is back, re-putting the old command: still held
    assert core.held[mds.LSP] == MUX_HELD
    core.update(0, _frame(frame, LSP=-0.4), ZERO_MODE, 1.05)  # a new command releases what it commands
    assert core.held[mds.LSP] == MUX_FREE and core.held[mds.NKY] == MUX_HELD
    # a controller without a heartbeat is never held for a silence
    core.update(1, _frame(ref, REP=-1.0), ZERO_MODE, 2.0)
    lost = core.heartbeats(100.0)
    assert [m.split()[0] for m in lost] == ["'ros'"] and core.held[mds.REP] == MUX_FREE


def test_the_heartbeat_is_configured_per_controller() -> None:
    entry = {"name": "teleop", "channel": "mds-ref-ros", "priority": 30, "joints": "all", "timeout": 1.0}
    assert parse_controllers([{**entry, "heartbeat": 0.1}])[0].heartbeat == 0.1
    assert parse_controllers([entry])[0].heartbeat is None
    for bad in (0, -1, "fast", float("nan")):
        with pytest.raises(ValueError, match="heartbeat must be > 0 s"):
            parse_controllers([{**entry, "heartbeat": bad}])


def test_the_running_mux_holds_a_silent_teleoperation_stream(clean_shm: None) -> None:
    ref, mode = _start_ref()
    _put(mds.MDS_CHAN_DAEMON_INPUT_NAME, ref)
    out = StructChannel(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
    state = StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
    logs: list[str] = []
    r = MuxRunner(_controllers(), state_rate=10.0, log=lambda level, msg: logs.append(f"{level}: {msg}"))
    t = threading.Thread(target=r.run, daemon=True)
    t.start()
    try:
        assert r.ready.wait(10), logs
        _newest(out)
        for k in range(10):  # a teleoperation client streaming at 20 Hz
            _put(mds.MDS_CHAN_REF_ROS_NAME, _frame(ref, LSP=-0.05 * k))
            time.sleep(0.05)
        stopped = time.monotonic()

        def held() -> bool:
            st = state.latest()
            return st is not None and st.held[mds.LSP] == MUX_HELD

        wait_for(held, 5.0, what="the protective stop in mds-mux-state")
        # well before the 10 Hz state tick plus the 1 s stale timeout: the heartbeat's deadline wakes the mux
        assert time.monotonic() - stopped < HEARTBEAT + 0.15 + 0.5
        assert any("heartbeat" in m and "protective stop" in m for m in logs), logs
        assert r.core is not None and r.core.ref[mds.LSP] == pytest.approx(-0.45)  # the output is not moved on
    finally:
        r.stop()
        t.join(5)
        out.close()
        state.close()
