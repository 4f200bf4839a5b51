"""The pipeline restarts a joint where it is when the daemon asks (after HOME, RESET, ZERO_ENCODER, ENABLE or
resetbus): ``joint_reseed`` counters in mds-daemon-status, read by ``pipeline.ReseedWatch`` in the mux, the filter
and the collision gate, which then set their output for the joint to its measured position (mds-state pos)."""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator

import numpy as np
import pytest
from support import wait_for

import mds_ach as mds
from mds_ach.kinematics.collision import load_model
from mds_ach.nodes.collision import GateRunner
from mds_ach.nodes.filter import FilterRunner, parse_config
from mds_ach.nodes.gate import GateConfig, joint_limits
from mds_ach.nodes.mux import Controller, MuxRunner
from mds_ach.nodes.pipeline import KNOWN_ADDRESSES, ReseedWatch, make_ref, ref_arrays
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_SHORT
from mds_ach.robot.msgs import daemon_status as ds

N = mds.MDS_JOINT_COUNT
LEP = BY_SHORT["LEP"].address
HOME = np.zeros(N)
for _name, _value in {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2,
                      "LEP": -1.25, "LSY": -0.25, "LWR": -0.28}.items():
    HOME[BY_SHORT[_name].address] = _value


def publish(reseed: dict[int, int], pos: dict[int, float], pid: int = 4321) -> None:
    """What the daemon publishes in one cycle: mds-state (pos), then mds-daemon-status (joint_reseed)."""
    state = mds.MDS_STATE()
    for a in KNOWN_ADDRESSES:
        state.joint[a].pos = pos.get(a, HOME[a])
    status = ds.MDS_DAEMON_STATUS(version=ds.DAEMON_STATUS_VERSION, pid=pid, start_time=1.0)
    for a, n in reseed.items():
        status.joint_reseed[a] = n
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(state)
    with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS) as ch:
        ch.put(status)


def test_watch_reports_the_joints_to_restart_and_where_they_are(clean_shm: None) -> None:
    logs: list[str] = []
    watch = ReseedWatch(lambda level, msg: logs.append(msg), threading.Event())
    try:
        assert watch.poll() is None  # no daemon yet
        publish({}, {LEP: -0.6})
        assert watch.poll() is None  # the first status seen only sets the baseline
        publish({LEP: 1}, {LEP: -1.25})
        addresses, positions = watch.poll()
        assert list(addresses) == [LEP] and list(positions) == [-1.25]
        assert watch.poll() is None  # nothing new
        publish({LEP: 1}, {LEP: -1.0})
        assert watch.poll() is None  # a new frame, same counters
        publish({LEP: 0}, {LEP: -1.0}, pid=99)
        assert watch.poll() is None  # a restarted daemon: baseline again
        publish({LEP: 1}, {LEP: math.nan}, pid=99)
        assert watch.poll() is None  # no position to restart at
        assert logs == []
    finally:
        watch.close()


@pytest.fixture
def pipeline(clean_shm: None) -> Iterator[dict[str, StructChannel]]:
    """Mux, filter (100 Hz) and collision gate on their threads, started from a reference with LEP at -0.6."""
    start = HOME.copy()
    start[LEP] = -0.6
    with StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF) as ch:
        ch.put(make_ref(start, np.zeros(N, dtype=np.int16)))
    publish({}, {LEP: -0.6})  # the daemon's baseline
    model = load_model(world={})
    lower, upper = joint_limits(model)
    quiet = lambda level, msg: None  # noqa: E731
    runners = [MuxRunner([Controller("default", mds.MDS_CHAN_REF_FILTER_NAME, 0, tuple(KNOWN_ADDRESSES), None, True)],
                         log=quiet),
               FilterRunner(parse_config({"rate": 100}), log=quiet),
               GateRunner(model, GateConfig(), lower, upper, log=quiet)]
    threads = [threading.Thread(target=r.run, daemon=True) for r in runners]
    outputs = {name: StructChannel(name, mds.MDS_REF) for name in
               (mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME)}
    for t in threads:
        t.start()
    try:
        for r in runners:
            assert r.ready.wait(30)
        yield outputs
    finally:
        for r in runners:
            r.stop()
        for t in threads:
            t.join(5)
        for ch in outputs.values():
            ch.close()
    assert not any(t.is_alive() for t in threads)


def newest_lep(ch: StructChannel, seen: list[float]) -> float:
    while (frame := ch.latest()) is not None:
        seen.append(float(ref_arrays(frame)[0][LEP]))
    return seen[-1] if seen else math.nan


def test_mux_filter_and_gate_restart_a_homed_joint_where_it_is(pipeline: dict[str, StructChannel]) -> None:
    """HOME moved LEP from -0.6 to -1.25. Once the daemon says so, every stage's output is -1.25, and a small
    goto from there (-1.2) ramps from -1.25, never back towards -0.6 (where the pipeline had left LEP)."""
    seen: dict[str, list[float]] = {name: [] for name in pipeline}
    for name, ch in pipeline.items():
        wait_for(lambda ch=ch, name=name: newest_lep(ch, seen[name]) == -0.6, 10, what=f"{name} at -0.6")
    publish({LEP: 1}, {LEP: -1.25})
    for name, ch in pipeline.items():
        wait_for(lambda ch=ch, name=name: newest_lep(ch, seen[name]) == -1.25, 10, what=f"{name} re-seeded")
    with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_REF) as legacy:  # a console goto: read-modify-write
        ref, mode = ref_arrays(legacy.latest())
        ref[LEP] = -1.2
        legacy.put(make_ref(ref, mode))
    for name, ch in pipeline.items():
        seen[name].clear()
        wait_for(lambda ch=ch, name=name: abs(newest_lep(ch, seen[name]) - -1.2) < 1e-12, 10, what=f"{name} at -1.2")
        assert all(-1.25 - 1e-12 <= q <= -1.2 + 1e-12 for q in seen[name]), (name, seen[name])
