"""MoveIt configuration (config/moveit/, config/joint_limits.yaml, config/moveit_controllers.yaml) and the launch
file for `ros2 launch` users, checked against MoveIt's and the launcher's own definitions by reading them (no MoveIt
or ros2 launch here)."""

from __future__ import annotations

import ast
import xml.etree.ElementTree as ET

import yaml
from support import REPO

from mds_ach.kinematics import srdf
from mds_ach.kinematics.collision import load_yaml
from mds_ach.kinematics.model import load_model
from mds_ach.paths import config_path
from mds_ach.tools import launcher, params

MOVEIT = REPO / "config" / "moveit"
REASONS = {"Adjacent", "Never", "Default", "Always", "User"}  # MoveIt Setup Assistant's disable reasons


def test_srdf_is_generated_from_the_urdf_and_the_gate_model() -> None:
    assert (MOVEIT / "mds.srdf").read_text() == srdf.render(), \
        "config/moveit/mds.srdf is out of date: python -m mds_ach.kinematics.srdf --write"


def test_srdf_follows_the_format_and_names_only_urdf_things() -> None:
    """SRDF (srdfdom): <robot name> = the URDF's, <group> of <joint name>, <virtual_joint>, <disable_collisions
    link1 link2 reason>; the groups are the controllers' joints, adjacency and the gate's ignored pairs disabled."""
    model = load_model()
    root = ET.parse(MOVEIT / "mds.srdf").getroot()
    assert root.tag == "robot" and root.get("name") == model.name
    assert {child.tag for child in root} <= {"group", "group_state", "end_effector", "virtual_joint",
                                             "passive_joint", "disable_collisions", "disable_default_collisions"}
    groups = {g.get("name"): [j.get("name") for j in g.findall("joint")] for g in root.findall("group")}
    controllers = yaml.safe_load((REPO / "config" / "moveit_controllers.yaml").read_text())
    manager = controllers["moveit_simple_controller_manager"]
    assert {f"{g}_controller": js for g, js in groups.items()} == \
        {name: manager[name]["joints"] for name in manager["controller_names"]}
    assert set(groups) == {"left_arm", "right_arm", "head"}
    assert all(j in model.actuated_joints for js in groups.values() for j in js)
    (virtual,) = root.findall("virtual_joint")
    assert virtual.get("child_link") == model.root and virtual.get("type") == "fixed"
    disabled = {}
    for el in root.findall("disable_collisions"):
        a, b, reason = el.get("link1"), el.get("link2"), el.get("reason")
        assert a in model.links and b in model.links and reason in REASONS, (a, b, reason)
        disabled[tuple(sorted((a, b)))] = reason
    adjacent = srdf.adjacent_pairs(model)
    assert ("left_elbow_link", "left_shoulder_link") in adjacent and len(adjacent) >= 14
    assert adjacent <= set(disabled) and all(disabled[p] == "Adjacent" for p in adjacent)
    ignored = srdf.ignored_pairs(model, load_yaml(config_path("collision.yaml")))
    assert ("left_shoulder_link", "torso") in ignored and ignored <= set(disabled)
    assert set(disabled) == adjacent | ignored, "a disabled pair the gate checks"


def test_kinematics_and_joint_limits_name_the_srdf_groups_and_urdf_joints() -> None:
    model = load_model()
    kin = yaml.safe_load((MOVEIT / "kinematics.yaml").read_text())
    assert set(kin) == {"left_arm", "right_arm"}
    for solver in kin.values():
        assert solver["kinematics_solver"] == "kdl_kinematics_plugin/KDLKinematicsPlugin"
        assert solver["kinematics_solver_timeout"] > 0 and solver["kinematics_solver_search_resolution"] > 0
    limits = yaml.safe_load((REPO / "config" / "joint_limits.yaml").read_text())  # one source: mds-ach limits
    assert set(limits["joint_limits"]) == set(model.actuated_joints)
    assert not (MOVEIT / "joint_limits.yaml").exists() and not (MOVEIT / "moveit_controllers.yaml").exists()


def _launch_constants() -> tuple[dict[str, object], set[str]]:
    """Module-level literal assignments of the launch file, and every string constant in it."""
    tree = ast.parse((REPO / "launch" / "mds.launch.py").read_text())
    values = {t.id: ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
              for t in node.targets if isinstance(t, ast.Name)}
    strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    return values, strings


def test_launch_file_starts_what_mds_ach_run_starts() -> None:
    """The same nodes in the same order, with their ROS node names, the shipped params file, --nocan for the
    daemon, --world (and the world parameter) for the launcher's world nodes, the channels made first."""
    values, strings = _launch_constants()
    names = {n.name: n.ros_name for n in params.nodes()}
    assert values["NODES"] == [(n, names[n]) for n in launcher.NODES]
    assert tuple(values["WORLD_NODES"]) == launcher.WORLD_NODES  # type: ignore[arg-type]
    assert launcher.node_args("daemon", nocan=True) == ["--nocan"]
    assert {"--nocan", "--world", "world", "params.yaml", "config", "mds_ach", "mds-ach", "make", "nocan",
            "params"} <= strings
    assert (REPO / "config" / "params.yaml").is_file()
    setup = (REPO / "setup.py").read_text()
    assert '*tree("launch")' in setup and '*tree("config")' in setup  # share/mds_ach/launch, config/moveit
