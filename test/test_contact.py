"""The paper's collision scenes through the real system (``mds-ach start nocan --world FILE``: daemon on the
simulated bus, mux, filter, collision gate, IK), asked as a user asks: Cartesian requests on ``mds-ik``.

* §4.2: both hands sent to the same point stop with the hand spheres touching, never interpenetrating;
* §4.3: with a table switched on by ``--world``, the hand driven down stops above the table top;
* the IK answers twice: solved (sent), then "stopped at contact: <pair>" (same seq) when the gate stopped it;
  the gate cancels that arm's command on ``mds-hold``.

"Touching" is defined on the gate's collision model: every primitive is inflated by margin / 2, so two parts
touch when the clearance of the un-inflated shapes equals the margin. Stopped at contact = margin <= clearance
<= margin + 5 mm on the daemon's commanded pose (``mds-state`` ``ref``) and on the measured pose once settled.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import wait_for
from support.system import mds_ach, running_system, system_env

import mds_ach as mds
from mds_ach.kinematics.collision import load_model
from mds_ach.nodes.ik_client import IkClient
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs.hold import HOLD_CANCEL, MDS_HOLD
from mds_ach.robot.msgs.ik_status import IK_SOLVED
from mds_ach.tools.launcher import node_args

TOUCH = 0.005  # m: stopped within 5 mm of touching (paper §4.2 hands, §4.3 table)
TABLE = {"frame": "robot", "objects": [{"name": "table", "enabled": True, "shape": "box", "size": [0.6, 1.4, 0.04],
                                        "xyz": [0.6, 0.0, -0.42]}]}
LEFT = [BY_SHORT[n].address for n in LEFT_ARM]
RIGHT = [BY_SHORT[n].address for n in RIGHT_ARM]


def test_world_goes_to_the_gate_and_the_ik_only() -> None:
    assert node_args("collision", True, "/w.yaml") == ["--world", "/w.yaml"]
    assert node_args("ik", False, "/w.yaml") == ["--world", "/w.yaml"]
    assert node_args("daemon", True, "/w.yaml") == ["--nocan"]
    assert node_args("mux", True, None) == []


@pytest.mark.parametrize(("content", "says"), [
    (None, "not found"),
    ("objects: [ {name: t, shape: box", "not valid YAML"),
    ("objects: [{name: t, shape: cone, radius: 1}]", "shape must be one of"),
])
def test_a_bad_world_file_is_refused_before_anything_starts(clean_shm: None, tmp_path: Path, content: str | None,
                                                            says: str) -> None:
    world = tmp_path / "world.yaml"
    if content is not None:
        world.write_text(content)
    env = system_env(tmp_path)
    for verb in ("start", "run"):
        proc = mds_ach(verb, "nocan", "--world", str(world), env=env)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert f"mds-ach {verb}: --world:" in proc.stderr and says in proc.stderr and str(world) in proc.stderr
        assert "started" not in proc.stdout


# --------------------------------------------------------------------------------------------- the system


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory):
    runtime = tmp_path_factory.mktemp("contact")
    world = runtime / "table.yaml"
    world.write_text(yaml.safe_dump(TABLE))
    with running_system(runtime, extra=("--world", str(world))) as env:
        yield env


def _refs(state: mds.MDS_STATE, field: str = "ref") -> np.ndarray:
    return np.array([getattr(state.joint[a], field) for a in range(mds.MDS_JOINT_COUNT)])


def _settled(chan: StructChannel, arm: list[int], seconds: float = 1.0, timeout: float = 60.0) -> mds.MDS_STATE:
    """The newest mds-state once the arm's reference has not moved for ``seconds`` and its measured pose is
    within 1 mrad of it."""
    deadline = time.monotonic() + timeout
    last, since = None, time.monotonic()
    while True:
        st = chan.wait(5.0)
        assert st is not None, "no mds-state"
        ref = _refs(st)[arm]
        if last is None or np.abs(ref - last).max() > 1e-9:
            last, since = ref, time.monotonic()
        elif time.monotonic() - since >= seconds and np.abs(_refs(st, "pos")[arm] - ref).max() < 1e-3:
            return st
        assert time.monotonic() < deadline, "the arm did not come to rest"


def _clearance(model, q100: np.ndarray, pair: tuple[str, str]) -> float:
    return model.distances(model.q_from_ref(q100))[pair]


@pytest.mark.ros
@pytest.mark.slow
def test_the_papers_scenes_stop_at_contact(system: dict[str, str], monkeypatch: pytest.MonkeyPatch) -> None:
    for key, value in system.items():
        monkeypatch.setenv(key, value)
    model = load_model(world=TABLE)
    margin = model.margin
    state = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
    holds = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
    holds.flush()
    commanded: list[np.ndarray] = []
    try:
        with IkClient() as client:
            # §4.3 with the table of --world: the left hand driven 10 cm below the table top.
            reply = client.request("left", 3, [0.40, 0.25, -0.50], timeout=30)
            assert reply.status == IK_SOLVED and "stops at contact" in reply.message, reply.message
            msg = wait_for(lambda: client.stopped(reply), 60, what="the left arm stopped at contact")
            assert msg == "stopped at contact: left hand / table"
            st = _settled(state, LEFT)
            for q in (_refs(st), _refs(st, "pos")):
                gap = _clearance(model, q, ("left_hand_link", "world:table"))
                print(f"table: {(gap - margin) * 1e3:.2f} mm from touching")
                assert margin - 1e-6 <= gap <= margin + TOUCH, f"left hand {gap * 1e3:.1f} mm above the table"
            cancel = wait_for(lambda: holds.next(), 5, what="the gate's cancel on mds-hold")
            assert cancel.action == HOLD_CANCEL and [a for a in LEFT if cancel.joints[a]] == LEFT
            np.testing.assert_allclose([cancel.target[a] for a in LEFT], _refs(st)[LEFT], atol=1e-9)

            # §4.2: the left hand to a point above the table, then the right hand to the same point.
            point = [0.40, 0.05, -0.10]
            reply = client.request("left", 3, point, timeout=30)
            assert reply.status == IK_SOLVED and "contact" not in reply.message, reply.message
            _settled(state, LEFT)
            reply = client.request("right", 3, point, timeout=30)
            assert reply.status == IK_SOLVED and "stops at contact" in reply.message, reply.message
            msg = wait_for(lambda: client.stopped(reply), 60, what="the right arm stopped at contact")
            assert msg == "stopped at contact: right hand / left hand"
            st = _settled(state, RIGHT)
            for q in (_refs(st), _refs(st, "pos")):
                gap = _clearance(model, q, ("left_hand_link", "right_hand_link"))
                print(f"hands: {(gap - margin) * 1e3:.2f} mm from touching")
                assert margin - 1e-6 <= gap <= margin + TOUCH, f"hand spheres {gap * 1e3:.1f} mm from touching"
            commanded.append(_refs(st))

            # The stop ended the right arm's command (the gate's CANCEL, honoured by the mux): when the left hand
            # moves out of the way, the right arm stays where it stopped instead of going on to the old goal.
            stopped_at = _refs(st)[RIGHT]
            reply = client.request("left", 3, [0.40, 0.30, -0.10], timeout=30)
            assert reply.status == IK_SOLVED and "contact" not in reply.message, reply.message
            _settled(state, LEFT)
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:
                now = state.wait(5.0)
                assert now is not None, "no mds-state"
                np.testing.assert_allclose(_refs(now)[RIGHT], stopped_at, atol=1e-6,
                                           err_msg="a command stopped at contact moved the arm later")

            # §4.2 as the paper ran it: both hands sent to one point at once. Both brake (the gate's braking
            # lookahead) and stop touching; the daemon's targets follow them onto the contact, never into it.
            point = [0.40, 0.0, -0.10]
            replies = [client.request(arm, 3, point, timeout=30) for arm in ("left", "right")]
            assert all(r.status == IK_SOLVED for r in replies), [r.message for r in replies]
            st = _settled(state, LEFT + RIGHT)
            for q in (_refs(st), _refs(st, "pos")):
                gap = _clearance(model, q, ("left_hand_link", "right_hand_link"))
                print(f"hands at once: {(gap - margin) * 1e3:.2f} mm from touching")
                assert margin - 1e-6 <= gap <= margin + TOUCH, f"hand spheres {gap * 1e3:.1f} mm from touching"
    finally:
        state.close()
        holds.close()
    assert commanded


@pytest.mark.slow
def test_the_readme_table_tour_works_as_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 28 item 3: the README's step 5 (`make run WORLD=config/table.yaml`, then the `ik … wait` it gives):
    the hand stops at the table, the viewer draws the world the running gate uses, and no probe WARN in ik.log."""
    from support import REPO

    from mds_ach.tools import viewer

    table = REPO / "config" / "table.yaml"
    readme = (REPO / "README.md").read_text()
    assert "make run\n   WORLD=config/table.yaml" in readme or "make run WORLD=config/table.yaml" in readme
    command = 'ik left 3 0.35 0.25 -0.5 wait'
    assert command in readme
    with running_system(tmp_path, extra=("--world", str(table))) as env:
        rt = Path(env["MDS_ACH_RUNTIME_DIR"])
        assert viewer.system_world(rt) == table, "the world the running gate uses is recorded for the viewer"
        for key, value in env.items():
            monkeypatch.setenv(key, value)
        v = viewer.Viewer(viewer.ViewerOptions(port=viewer.free_port("127.0.0.1")))
        try:
            assert v.world_path == table and not v.problems
        finally:
            v.close()
        proc = mds_ach("console", "-c", command, env=env, timeout=120)
        assert proc.returncode == 1 and "the left arm stopped at contact: left hand / table" in proc.stdout + \
            proc.stderr, proc.stdout + proc.stderr
        status = mds_ach("status", "--window", "0.2", env=env).stdout
        assert "collision  BLOCKED: L_HAND" in status, status
        assert "got -1" not in (rt / "ik.log").read_text(), "the launcher's probe is no warning"
