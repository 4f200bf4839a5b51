"""/tf and /tf_static from the bridge (what robot_state_publisher gives RViz), and the RViz configuration file.

The transforms are checked against the URDF model the FK uses: every link reachable from the root, the fixed
joints on the latched /tf_static, the moving ones on /tf with the stamp and positions of a /joint_states message.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import REPO
from support.bridgeproc import BridgeProcs, module_harness

from mds_ach.kinematics.model import load_model

MODEL = load_model()


def _matrix(tf) -> np.ndarray:  # type: ignore[no-untyped-def]
    """4x4 of a geometry_msgs/Transform."""
    x, y, z, w = tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = [tf.translation.x, tf.translation.y, tf.translation.z]
    return T


class TfHarness(BridgeProcs):
    """``daemon --nocan`` (a left elbow bent, so the transforms are not the zero pose) and the bridge."""

    def __init__(self, tmp: Path) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from tf2_msgs.msg import TFMessage

        self.start_daemon(tmp, "--sim-pose", "LEP=-1.0", "--sim-pose", "RSP=0.4")
        self.start_bridge()
        self.open_node("tf_test_probe")
        self.tf: list = []
        self.static: list = []
        self.states: list = []
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.node.create_subscription(TFMessage, "/tf", self.tf.append, 100)
        self.node.create_subscription(TFMessage, "/tf_static", self.static.append, latched)
        self.node.create_subscription(JointState, "/joint_states", self.states.append, 100)



@pytest.fixture(scope="module")
def harness(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TfHarness]:
    yield from module_harness(lambda: TfHarness(tmp_path_factory.mktemp("tf")))


@pytest.mark.ros
@pytest.mark.slow
def test_tf_static_has_every_fixed_joint_latched(harness: TfHarness) -> None:
    """A subscriber that joins late still gets the fixed joints (transient local), each its URDF origin."""
    harness.spin_until(lambda: harness.static, 30.0, "/tf_static")
    fixed = {j.child: j for j in MODEL.joints.values() if j.type == "fixed"}
    got = {t.child_frame_id: t for msg in harness.static for t in msg.transforms}
    assert set(got) == set(fixed)
    for child, t in got.items():
        assert t.header.frame_id == fixed[child].parent
        np.testing.assert_allclose(_matrix(t.transform), fixed[child].origin, atol=1e-12)


@pytest.mark.ros
@pytest.mark.slow
def test_tf_is_the_fk_of_the_joint_states_message_with_its_stamp(harness: TfHarness) -> None:
    harness.spin_until(lambda: harness.static and len(harness.tf) > 5 and len(harness.states) > 5, 30.0,
                       "/tf and /joint_states")
    by_stamp = {(m.header.stamp.sec, m.header.stamp.nanosec): m for m in harness.states}
    msg = next(m for m in reversed(harness.tf) if (m.transforms[0].header.stamp.sec,
                                                   m.transforms[0].header.stamp.nanosec) in by_stamp)
    stamp = msg.transforms[0].header.stamp
    js = by_stamp[(stamp.sec, stamp.nanosec)]
    q = dict(zip(js.name, js.position, strict=True))
    assert js.header.frame_id == MODEL.root  # as joint_state_broadcaster's default frame_id
    assert q["LEP"] < -0.5 and q["RSP"] > 0.2, q  # the simulated pose: not the zero pose
    moving = {j.child: j for j in MODEL.joints.values() if j.type != "fixed" and j.name in q}
    assert {t.child_frame_id for t in msg.transforms} == set(moving)
    assert all(t.header.stamp == stamp for t in msg.transforms)
    # Compose the tree from both topics: every link's pose in the root frame is the model's FK of the message.
    edges = {t.child_frame_id: t for t in msg.transforms}
    edges.update({t.child_frame_id: t for m in harness.static for t in m.transforms})
    assert set(edges) | {MODEL.root} == set(MODEL.links), "a link has no transform"
    expected = MODEL.link_poses(q)
    for link in MODEL.links:
        T, frame = np.eye(4), link
        while frame != MODEL.root:
            T = _matrix(edges[frame].transform) @ T
            frame = edges[frame].header.frame_id
        np.testing.assert_allclose(T, expected[link], atol=1e-9, err_msg=link)


def test_rviz_config_shows_the_robot_and_its_frames() -> None:
    """config/mds.rviz (RViz 2's YAML): RobotModel on /robot_description, TF, the URDF root as fixed frame."""
    doc = yaml.safe_load((REPO / "config" / "mds.rviz").read_text())
    manager = doc["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == MODEL.root
    displays = {d["Class"]: d for d in manager["Displays"]}
    robot = displays["rviz_default_plugins/RobotModel"]
    assert robot["Enabled"] and robot["Description Source"] == "Topic"
    assert robot["Description Topic"]["Value"] == "/robot_description"
    assert robot["Description Topic"]["Durability Policy"] == "Transient Local"
    assert displays["rviz_default_plugins/TF"]["Enabled"]
    assert manager["Views"]["Current"]["Class"] == "rviz_default_plugins/Orbit"
    assert {"Class", "Name", "Enabled"} <= set(robot) and math.isfinite(manager["Views"]["Current"]["Distance"])
    assert "Panels" in doc and "Window Geometry" in doc
