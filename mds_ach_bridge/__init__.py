"""ROS 2 bridge for mds_ach: ``mds-state`` -> ``/joint_states``, ROS commands -> the bridge's mux input.

The node lives in :mod:`mds_ach_bridge.bridge` (``ros2 run mds_ach bridge``). The helper modules
(limits, commands, trajectory, ik_request) are plain Python without rclpy, so they are unit-testable and
cheap to import.
"""
