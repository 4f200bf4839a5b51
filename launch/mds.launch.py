"""``ros2 launch mds_ach mds.launch.py [nocan:=true] [world:=FILE] [params:=FILE]``: what ``mds-ach run`` starts.

Every MDS Ach channel first (``mds-ach make``, as ``mds-ach run`` creates them), then the six nodes, each with
its ROS node name and ``config/params.yaml`` (or ``params:=FILE``); ``nocan:=true`` gives the daemon the simulated
bus, ``world:=FILE`` gives the collision gate and the IK node a world file. Unlike ``mds-ach run`` it does not
bring a SocketCAN link up (``mds-ach start`` prints the ``ip link`` commands), wait for each node's readiness
or stop the others when one fails. test/test_moveit_config.py reads this file against the launcher.
MoveIt: ``config/moveit/`` (mds.srdf, kinematics.yaml) with ``config/joint_limits.yaml`` and
``config/moveit_controllers.yaml``; the bridge publishes ``/robot_description``, ``/tf`` and ``/tf_static``.
"""

import os

from ament_index_python.packages import get_package_prefix, get_package_share_directory
from launch_ros.actions import Node

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    ExecuteProcess,
    LogInfo,
    OpaqueFunction,
    RegisterEventHandler,
    Shutdown,
)
from launch.event_handlers import OnProcessExit
from launch.substitutions import LaunchConfiguration

# (executable, ROS node name): mds_ach.tools.launcher.NODES, in its start order, with the names of params.yaml
NODES = [
    ("daemon", "mds_daemon"),
    ("mux", "mux"),
    ("filter", "filter"),
    ("collision", "collision"),
    ("ik", "ik"),
    ("bridge", "mds_bridge"),
]
WORLD_NODES = ("collision", "ik")  # mds_ach.tools.launcher.WORLD_NODES


def _nodes(context):
    nocan = LaunchConfiguration("nocan").perform(context).lower() in ("true", "1", "yes")
    world = LaunchConfiguration("world").perform(context)
    params = LaunchConfiguration("params").perform(context)
    namespace = LaunchConfiguration("namespace").perform(context)  # mds-ach start --namespace
    actions = []
    for exe, name in NODES:
        arguments = ["--nocan"] if exe == "daemon" and nocan else []
        parameters = [params]
        if world and exe in WORLD_NODES:
            arguments += ["--world", os.path.abspath(world)]
            parameters.append({"world": os.path.abspath(world)})  # after the file: wins over it
        actions.append(Node(package="mds_ach", executable=exe, name=name, namespace=namespace, arguments=arguments,
                            parameters=parameters, output="screen"))
    return actions


def _after_channels(event, context):
    if event.returncode != 0:
        return [LogInfo(msg=f"mds-ach make failed ({event.returncode}): no node started"), Shutdown()]
    return [OpaqueFunction(function=_nodes)]


def generate_launch_description():
    share = get_package_share_directory("mds_ach")
    make = ExecuteProcess(cmd=[os.path.join(get_package_prefix("mds_ach"), "lib", "mds_ach", "mds-ach"), "make"],
                          output="screen")
    return LaunchDescription([
        DeclareLaunchArgument("nocan", default_value="false", description="the simulated bus (mds-ach run nocan)"),
        DeclareLaunchArgument("world", default_value="", description="world objects file for collision and ik"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="ROS namespace of every node (mds-ach start --namespace)"),
        DeclareLaunchArgument("params", default_value=os.path.join(share, "config", "params.yaml"),
                              description="ROS 2 params file for every node"),
        make,
        RegisterEventHandler(OnProcessExit(target_action=make, on_exit=_after_channels)),
    ])
