"""Direct writers of ``mds-ref`` (issue #18 §2): the channel the original daemon executed is a pipeline input again.

Legacy expert clients (and a remote station's ``achd push mds-ref``) write ``mds-ref``; here it is the mux's
``direct`` controller (config/mux.yaml), unsmoothed (config/filter.yaml ``controllers: direct``), limit-checked
by the mux and collision-gated; the daemon executes ``mds-ref-gated``, which only the gate writes. On the
simulated robot, with the real node processes:

* one put on ``mds-ref`` moves the robot there, as a bounded ramp (the filter passes the step, the gate and the
  daemon bound its speed), and it stays there after the controller's timeout;
* a put outside the effective limits is clamped to them by the mux (issue 26: the original stopped at its
  limits), with a log line and the verdict 'clamped' naming the joint;
* a remote ``achd push`` into ``mds-ref`` through the robot's achd server moves the robot the same way;
* a direct put that drives one arm into the other is stopped by the collision gate.
"""

from __future__ import annotations

import ctypes
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support import in_netns, remove_mds_channels, wait_for
from support.system import Pipeline

import mds_ach as mds
from mds_ach import ach
from mds_ach.kinematics.collision import load_model
from mds_ach.kinematics.limits import current_limits
from mds_ach.net import achd
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, MODEL_JOINTS, RIGHT_ARM
from mds_ach.robot.msgs.mux_state import MDS_MUX_STATE, VERDICT_CLAMPED

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LEFT = np.array([BY_SHORT[n].address for n in LEFT_ARM])
RIGHT = np.array([BY_SHORT[n].address for n in RIGHT_ARM])
MODEL = np.array([BY_SHORT[n].address for n in MODEL_JOINTS])
LEP = BY_SHORT["LEP"].address
GATE_SPEED = 2.0  # rad/s, config/collision.yaml max_velocity: the bound on a direct step
SLACK = 0.05  # s: the daemon samples its input at a slightly different point of each cycle than it stamps
DIRECT_TIMEOUT = 1.0  # s, config/mux.yaml direct timeout


class Robot(Pipeline):
    """daemon --nocan, collision gate, filter and mux, and readers of what the daemon does."""

    def __init__(self, logs: Path) -> None:
        super().__init__(logs)
        self.state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        self.model = load_model()

    def frame(self, timeout: float = 5.0) -> tuple[float, np.ndarray, np.ndarray]:
        """The next mds-state frame: (time, ref, measured pos) by address; the commanded pose never collides."""
        st = self.state.wait(timeout)
        assert st is not None, "no mds-state frame: is the daemon alive?"
        ref = np.array([st.joint[a].ref for a in range(mds.MDS_JOINT_COUNT)])
        pos = np.array([st.joint[a].pos for a in range(mds.MDS_JOINT_COUNT)])
        touching = [(c.a, c.b) for c in self.model.check(self.model.q_from_ref(ref)).contacts if c.clearance <= 0.0]
        assert not touching, f"the daemon commands a collision: {touching}"
        return st.time, ref, pos

    def follow(self, until, timeout: float) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """State frames until ``until(ref, pos)``; fails after ``timeout`` s."""
        trace = []
        deadline = time.monotonic() + timeout
        while True:
            trace.append(self.frame())
            if until(trace[-1][1], trace[-1][2]):
                return trace
            assert time.monotonic() < deadline, f"condition not met within {timeout} s"

    def close(self) -> None:
        self.state.close()


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    assert in_netns(), "run through tools/netns-run"
    remove_mds_channels()
    r = Robot(tmp_path_factory.mktemp("direct"))
    try:
        r.start("daemon", "--nocan")
        for name in ("collision", "filter", "mux"):
            r.start(name)
        yield r
    finally:
        codes = r.stop_all()
        r.close()
        remove_mds_channels()
    r.assert_clean(codes)
    assert "not put by the collision gate" not in r.log_text("daemon"), "the gate is the daemon input's only writer"


def legacy_put(**targets: float) -> None:
    """What a C client of the original does: ach_open("mds-ref"), ach_get (newest), change joints, ach_put once."""
    ref = mds.MDS_REF()
    with ach.Channel(mds.MDS_CHAN_REF_NAME, create=False) as chan:
        status, size = chan.get(ref, last=True, copy=True)
        assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(ref), \
            "the mux seeds mds-ref with the current reference (config/mux.yaml direct seed: true)"
        for short, value in targets.items():
            ref.joint[BY_SHORT[short].address].ref = value
        chan.put(ref)


def assert_bounded(trace: list[tuple[float, np.ndarray, np.ndarray]]) -> None:
    """No modelled joint of the daemon's reference moves faster than the gate's bound between state frames."""
    for (t0, r0, _), (t1, r1, _) in zip(trace, trace[1:], strict=False):
        step = np.abs(r1[MODEL] - r0[MODEL]).max()
        assert step <= GATE_SPEED * (t1 - t0 + SLACK), f"jump of {step:.3f} rad in {t1 - t0:.3f} s"


def assert_stays(robot: Robot, where: np.ndarray, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        _, ref, pos = robot.frame()
        assert np.abs(ref[MODEL] - where[MODEL]).max() < 1e-9, "the daemon's reference moved on"
        assert np.abs(pos[MODEL] - where[MODEL]).max() < 1e-3, "the robot moved on"


def test_one_legacy_put_on_mds_ref_moves_the_robot_there_and_it_stays(robot: Robot) -> None:
    _, start, _ = robot.frame()
    target = start[LEP] - 0.4
    with StructChannel(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF) as smooth:
        smooth.flush()
        legacy_put(LEP=target)
        trace = robot.follow(lambda ref, pos: abs(pos[LEP] - target) < 1e-4, timeout=20)
        seen = []
        while (frame := smooth.wait(0.5)) is not None and len(seen) < 200:
            seen.append(frame.joint[LEP].ref)
            if abs(seen[-1] - target) < 1e-12:
                break
    assert_bounded(trace)
    between = [q for q in seen if abs(q - start[LEP]) > 1e-9 and abs(q - target) > 1e-9]
    assert len(between) <= 2, f"the filter smoothed a direct step ({len(between)} intermediate frames): not passed"
    ramp = [r[LEP] for _, r, _ in trace if abs(r[LEP] - start[LEP]) > 1e-9 and abs(r[LEP] - target) > 1e-9]
    assert ramp, "the daemon's reference jumped: the gate or the daemon must bound the step"
    _, there, _ = robot.frame()
    others = MODEL[MODEL != LEP]
    assert abs(there[LEP] - target) < 1e-9 and np.abs(there[others] - start[others]).max() < 1e-9, "only LEP moves"
    assert_stays(robot, there, DIRECT_TIMEOUT + 1.0)  # past the direct controller's timeout: it stays


def test_an_out_of_limit_put_on_mds_ref_is_clamped_to_the_limit_with_a_verdict(robot: Robot) -> None:
    """Issue 26: as the original hardware stopped at its limits, the joint goes to the limit (not a silent
    refusal); the mux logs it and its verdict ('clamped') names the joint."""
    _, start, _ = robot.frame()
    upper = float(current_limits().arrays()[1][LEP])
    legacy_put(LEP=upper + 0.2)
    with StructChannel(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE) as mux_state:
        def clamped() -> bool:
            st = mux_state.latest()
            names = [bytes(st.name[i]).split(b"\0")[0].decode() for i in range(st.count)] if st else []
            return st is not None and "direct" in names and st.verdict[names.index("direct")] == VERDICT_CLAMPED \
                and st.clamped_joints(names.index("direct")) == [LEP]
        wait_for(clamped, 10, what="the mux's verdict on the direct frame")
    wait_for(lambda: "clamped a frame from 'direct'" in robot.log_text("mux"), 10, what="the clamping log line")
    line = [s for s in robot.log_text("mux").splitlines() if "clamped a frame from 'direct'" in s][-1]
    assert "LEP" in line and "nearest limit" in line, line
    trace = robot.follow(lambda ref, pos: abs(pos[LEP] - upper) < 1e-4, timeout=20)
    assert max(r[LEP] for _, r, _ in trace) <= upper + 1e-12, "never past the limit"
    legacy_put(LEP=start[LEP])  # back where it was, for the next tests
    robot.follow(lambda ref, pos: abs(pos[LEP] - start[LEP]) < 1e-4, timeout=20)


def test_a_remote_achd_push_into_mds_ref_moves_the_robot(robot: Robot) -> None:
    """A station running `achd push mds-ref` (here our achd client, the same protocol) to the robot's server with
    its default write rules: the frame goes through the mux, filter and gate like a local put."""
    _, start, _ = robot.frame()
    target = start[LEP] + 0.2
    station = "test-station-ref"
    ach.create(station, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    server = achd.Server(("127.0.0.1",), 0, policy=achd.AccessPolicy(), dead_after_s=2.0).start()
    link = None
    try:
        with StructChannel(mds.MDS_CHAN_REF_NAME, mds.MDS_REF, create=False) as robot_ref, \
                StructChannel(station, mds.MDS_REF) as local:
            frame = robot_ref.latest()  # the station's copy of the pose (in the original it pulled mds-ref too)
            assert frame is not None
            link = achd.Link("push", "127.0.0.1", station, remote_channel=mds.MDS_CHAN_REF_NAME,
                             port=server.ports[0]).start()
            assert link.connected.wait(20), link.stats.last_error  # achd flushes the local channel first
            frame.joint[LEP].ref = target
            local.put(frame)
            trace = robot.follow(lambda ref, pos: abs(pos[LEP] - target) < 1e-4, timeout=20)
        assert link.stats.sent >= 1 and not link.stats.last_error, link.stats.last_error
        assert_bounded(trace)
    finally:
        if link is not None:
            link.stop()
        server.stop()
        server.join()
    _, there, _ = robot.frame()
    assert_stays(robot, there, 1.0)


def test_a_colliding_put_on_mds_ref_is_stopped_by_the_gate(robot: Robot) -> None:
    """Left hand to a point in front of the body, then the right hand to the same point, each by one put on
    mds-ref: the gate holds the right arm short of the left one and flags it on mds-collide."""
    from mds_ach import ik

    _, start, _ = robot.frame()
    point = [0.40, 0.05, -0.10]
    left = ik.solve(point, "p-x p-y p-z", "left", start[LEFT])
    right = ik.solve(point, "p-x p-y p-z", "right", start[RIGHT])
    assert left.success and right.success, (left.message, right.message)
    legacy_put(**{n: float(q) for n, q in zip(LEFT_ARM, left.q, strict=True)})
    robot.follow(lambda ref, pos: np.abs(pos[LEFT] - left.q).max() < 1e-3, timeout=20)
    legacy_put(**{n: float(q) for n, q in zip(RIGHT_ARM, right.q, strict=True)})
    flagged = False
    trace = []
    end = time.monotonic() + 6.0
    with StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE) as collide:
        while time.monotonic() < end:
            trace.append(robot.frame())
            contact = robot.model.check(robot.model.q_from_ref(trace[-1][2]))
            assert not contact.collides, f"measured poses in contact: {sorted(contact.pairs)}"
            c = collide.latest()
            flagged |= c is not None and c.isCollide != 0
    assert_bounded(trace)
    final = trace[-1][1]
    assert np.abs(final[RIGHT] - right.q).max() > 0.05, "the right arm reached the left one: not gated"
    assert np.abs(final[RIGHT] - start[RIGHT]).max() > 0.05, "the right arm did not move at all"
    assert flagged, "the gate never reported the hold on mds-collide"
