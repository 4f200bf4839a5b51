"""``/tf`` and ``/tf_static`` from the measured joints: what robot_state_publisher does, done by the bridge.

Why here: the bridge already has every ``joint_states`` message and the URDF it publishes as ``robot_description``,
so RViz shows the robot with the bridge alone, from the same model as the FK (``mds_ach.kinematics.model``).
Like robot_state_publisher: one transform per moving joint named in ``joint_states`` (parent link -> child link,
the message's stamp), the fixed joints once on ``/tf_static`` (transient local, so late subscribers get them).
"""

from __future__ import annotations

from collections.abc import Sequence

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, Transform, TransformStamped, Vector3
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from mds_ach.kinematics.model import Joint, RobotModel, joint_transform, quaternion_wxyz

TF = "tf"  # relative: /tf outside a namespace (where tf2's listeners look); /NS/tf under one, so two robots' same
TF_STATIC = "tf_static"  # link names never mix on one tree (RViz: remap or set its TF topic to /NS/tf)
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


def transform_stamped(joint: Joint, value: float, stamp: Time) -> TransformStamped:
    """The child link's frame in the parent link's frame for the joint at ``value``."""
    T = joint_transform(joint, value)
    w, x, y, z = quaternion_wxyz(T)
    tx, ty, tz = (float(v) for v in T[:3, 3])
    msg = TransformStamped(transform=Transform(translation=Vector3(x=tx, y=ty, z=tz),
                                               rotation=Quaternion(x=x, y=y, z=z, w=w)))
    msg.header.stamp = stamp
    msg.header.frame_id = joint.parent
    msg.child_frame_id = joint.child
    return msg


class TfPublisher:
    """Publishes the moving joints' transforms per ``joint_states`` message and the fixed ones once."""

    def __init__(self, node: Node, model: RobotModel, names: Sequence[str]) -> None:
        index = {name: i for i, name in enumerate(names)}
        self._moving = [(index[j.name], j) for j in model.joints.values() if j.type != "fixed" and j.name in index]
        self._pub = node.create_publisher(TFMessage, TF, TF_QOS)
        self._static_pub = node.create_publisher(TFMessage, TF_STATIC, TF_STATIC_QOS)
        now = node.get_clock().now().to_msg()
        self._static_pub.publish(TFMessage(transforms=[transform_stamped(j, 0.0, now)
                                                       for j in model.joints.values() if j.type == "fixed"]))

    def publish(self, positions: Sequence[float], stamp: Time) -> None:
        """One TFMessage for one ``joint_states`` message (same positions, same stamp); none while nobody listens
        (17 transforms are built per frame: the bridge's largest cost at rest; a listener gets the next frame's)."""
        if self._pub.get_subscription_count() == 0:
            return
        self._pub.publish(TFMessage(transforms=[transform_stamped(j, positions[i], stamp) for i, j in self._moving]))
