"""urdf/mds.urdf: loads in yourdfpy and pytorch-kinematics, matches the original IK chain and the SDF geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.reference_chain import L1, L2, L3, L4, original_chain

from mds_ach.kinematics import model as kinematics
from mds_ach.paths import urdf_path
from mds_ach.robot.joints import LEFT_ARM, MODEL_JOINTS, RIGHT_ARM

SHOULDER_HEIGHT = 1.2065
ARMS = {"left": (LEFT_ARM, 1.0), "right": (RIGHT_ARM, -1.0)}


@pytest.fixture(scope="module")
def robot():
    import yourdfpy

    return yourdfpy.URDF.load(str(urdf_path()), build_collision_scene_graph=False, load_meshes=False)


def random_joints(n: int, seed: int = 7) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-math.pi, math.pi, size=(n, 6))


# --------------------------------------------------------------------------------------------- structure


def test_urdf_validates_and_names_the_model_joints(robot) -> None:
    assert robot.validate()
    assert set(robot.actuated_joint_names) == set(MODEL_JOINTS)
    for name in MODEL_JOINTS:
        assert robot.joint_map[name].type == "revolute"
    for frame in ("base_link", "torso", "left_tool", "right_tool", "left_hand_link", "right_hand_link"):
        assert frame in robot.link_map


def test_heights_waist_and_torso_frame(robot) -> None:
    robot.update_cfg(np.zeros(len(robot.actuated_joint_names)))
    torso = robot.get_transform("torso", "base_link")
    assert np.allclose(torso[:3, :3], np.eye(3)) and np.allclose(torso[:3, 3], [0, 0, SHOULDER_HEIGHT], atol=1e-12)
    waist = robot.get_transform("chest_link", "base_link")
    assert waist[2, 3] == pytest.approx(SHOULDER_HEIGHT - 0.4954, abs=1e-12)  # 0.7111 m, the SDF's TSY pose
    assert tuple(robot.joint_map["WST"].axis) == (0, 0, 1)


@pytest.mark.parametrize("arm", ["left", "right"])
def test_arm_joints_have_the_ik_chain_origins_and_axes(robot, arm: str) -> None:
    names, m = ARMS[arm]
    expected = [((0, m * L1, 0), (0, 1, 0)), ((0, 0, 0), (1, 0, 0)), ((0, 0, 0), (0, 0, 1)),
                ((0, 0, -L2), (0, 1, 0)), ((0, 0, -L3), (0, 0, 1)), ((0, 0, 0), (1, 0, 0))]
    parent = "torso"
    for name, (xyz, axis) in zip(names, expected, strict=True):
        j = robot.joint_map[name]
        assert j.parent == parent, name
        assert np.allclose(j.origin[:3, 3], xyz, atol=1e-12) and np.allclose(j.origin[:3, :3], np.eye(3)), name
        assert tuple(j.axis) == axis, name
        parent = j.child


def test_limits_are_inside_the_ik_clamps_and_the_joint_table(robot) -> None:
    from mds_ach.robot import config

    table = {j.short: j for j in config.load("default")}
    for name in MODEL_JOINTS:
        lim = robot.joint_map[name].limit
        assert lim.lower < lim.upper, name
        assert table[name].lower - 1e-9 <= lim.lower and lim.upper <= table[name].upper + 1e-9, name
    clamps = {"SR": {"left": (0.0, math.pi), "right": (-math.pi, 0.0001)}, "EP": (-2.4, 0.0),
              "WR": (-0.3 * math.pi / 2, 0.3 * math.pi / 2)}
    for arm, (names, _) in ARMS.items():
        for name in names:
            clamp = clamps.get(name[1:], (-math.pi, math.pi))
            lo, hi = clamp[arm] if isinstance(clamp, dict) else clamp
            lim = robot.joint_map[name].limit
            assert lo - 1e-9 <= lim.lower and lim.upper <= hi + 1e-9, name
    # SR is one-sided toward the body and mirrored: positive abducts the left arm, negative the right.
    assert robot.joint_map["LSR"].limit.lower == 0.0 and robot.joint_map["RSR"].limit.upper == 0.0


# --------------------------------------------------------------------------------------------- collision geometry

PARTS = {  # link: (kind, size, offset in the link frame) -- the develop SDF numbers (specs section f.2)
    "shoulder_link": ("cylinder", (0.051, 0.04551), (0, 0, -0.0412875)),
    "elbow_link": ("sphere", (0.075,), (0, 0, 0)),
    "forearm_link": ("cylinder", (0.051, 0.1527375), (0, 0, 0)),
    "wrist_link": ("cylinder", (0.06, 0.01), (0, 0, 0)),
    "hand_link": ("sphere", (0.1,), (0.02, 0, -0.025)),
}


@pytest.mark.parametrize("arm", ["left", "right"])
def test_arm_collision_parts_sit_where_the_sdf_puts_them(arm: str) -> None:
    model = kinematics.load_model()
    m = ARMS[arm][1]
    poses = model.link_poses(root="torso")
    # Model-frame centres at zero pose (specs f.2; y mirrors for the right arm).
    centres = {"shoulder_link": (0, 0.24551, -0.0412875), "elbow_link": (0, 0.24551, -0.282575),
               "forearm_link": (0, 0.24551, -0.43894375), "wrist_link": (0, 0.24551, -0.5953125),
               "hand_link": (0.02, 0.24551, -0.725)}
    for suffix, (kind, size, offset) in PARTS.items():
        link = model.links[f"{arm}_{suffix}"]
        assert len(link.collisions) == 1, link.name
        g = link.collisions[0]
        assert (g.kind, g.size) == (kind, size), link.name
        assert np.allclose(g.origin[:3, 3], offset) and np.allclose(g.origin[:3, :3], np.eye(3)), link.name
        centre = (poses[link.name] @ g.origin)[:3, 3]
        cx, cy, cz = centres[suffix]
        assert np.allclose(centre, (cx, m * cy, cz), atol=1e-6), link.name


def test_body_and_head_primitives() -> None:
    model = kinematics.load_model()
    poses = model.link_poses()

    def one(link: str):
        (g,) = model.links[link].collisions
        return g, (poses[link] @ g.origin)

    g, T = one("head_link")
    assert (g.kind, g.size) == ("sphere", (0.21,))
    assert np.allclose(T[:3, 3] - [0, 0, SHOULDER_HEIGHT], (-0.0017, 0.0012, 0.3091), atol=1e-4)
    g, T = one("wheels_link")
    assert (g.kind, g.size) == ("cylinder", (0.254, 0.6604)) and np.allclose(T[:3, 2], [0, -1, 0], atol=1e-6)
    assert T[2, 3] == pytest.approx(0.254)
    boxes = {"box1_link": ((0.4191, 0.508, 0.5842), 0.2921), "box2_link": ((0.2413, 0.508, 0.1398), 0.6541),
             "chest_link": ((0.1651, 0.2286, 0.4064), 0.9271), "torso": ((0.1651, 0.26035, 0.1524), 1.2065)}
    for link, (size, z) in boxes.items():
        g, T = one(link)
        assert (g.kind, g.size) == ("box", size) and T[2, 3] == pytest.approx(z, abs=1e-9), link
    g, T = one("backpack_link")
    assert g.size == (0.09625, 0.50815, 0.6242)
    assert np.allclose(T[:3, 3], (-0.17145, 0, SHOULDER_HEIGHT - 0.13335))
    assert math.atan2(-T[2, 0], T[0, 0]) == pytest.approx(-0.163526619)
    assert not model.links["base_link"].collisions  # the SDF's 1000 m ground plate is out of the arms' reach


# --------------------------------------------------------------------------------------------- FK vs the original


@pytest.mark.parametrize("arm", ["left", "right"])
def test_yourdfpy_fk_equals_the_original_chain(robot, arm: str) -> None:
    names, m = ARMS[arm]
    order = robot.actuated_joint_names
    for q in random_joints(50):
        cfg = np.zeros(len(order))
        for name, v in zip(names, q, strict=True):
            cfg[order.index(name)] = v
        robot.update_cfg(cfg)
        got = robot.get_transform(f"{arm}_tool", "torso")
        assert np.abs(got - original_chain(q, m)).max() < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("arm", ["left", "right"])
def test_pytorch_kinematics_fk_equals_the_original_chain(arm: str) -> None:
    # Imported here, not at the top: torch costs ~3 s of import (measured) that collecting this module must not pay.
    import pytorch_kinematics as pk
    import torch
    from support.torch_kinematics import torch_chain

    names, m = ARMS[arm]
    q = random_joints(64, seed=11)
    chain = torch_chain(arm)  # float64 chain built from the URDF
    assert chain.get_joint_parameter_names() == list(names)
    T = chain.forward_kinematics(torch.as_tensor(q)).get_matrix().numpy()
    expected = np.array([original_chain(x, m) for x in q])
    assert np.abs(T - expected).max() < 1e-9
    # pytorch-kinematics' own URDF loader reads the same file (it parses origins in float32).
    own = pk.build_serial_chain_from_urdf(urdf_path().read_bytes(), f"{arm}_tool", "torso").to(dtype=torch.float64)
    assert own.get_joint_parameter_names() == list(names)
    assert np.abs(own.forward_kinematics(torch.as_tensor(q)).get_matrix().numpy() - expected).max() < 1e-6
    full = pk.build_chain_from_urdf(urdf_path().read_bytes())
    assert set(full.get_joint_parameter_names()) == set(MODEL_JOINTS)


@pytest.mark.parametrize(
    "q, printed, exact",
    [  # specs e.1 prints these rounded; the exact values follow from the link lengths
        ((0, 0, 0, 0, 0, 0), (0.0, 0.24551, -0.6588125), (0.0, L1, -(L2 + L3 + L4))),
        ((0, 0, 0, -math.pi / 2, 0, 0), (0.376, 0.2455, -0.2826), (L3 + L4, L1, -L2)),  # elbow flexes forward
        ((-math.pi / 2, 0, 0, 0, 0, 0), (0.6588, 0.2455, 0.0), (L2 + L3 + L4, L1, 0.0)),  # SP raises it forward
    ],
)
def test_spot_checks_from_the_original(robot, q: tuple[float, ...], printed: tuple[float, ...],
                                       exact: tuple[float, ...]) -> None:
    order = robot.actuated_joint_names
    cfg = np.zeros(len(order))
    for name, v in zip(LEFT_ARM, q, strict=True):
        cfg[order.index(name)] = v
    robot.update_cfg(cfg)
    got = robot.get_transform("left_tool", "torso")[:3, 3]
    assert np.allclose(got, exact, atol=1e-12)
    assert np.allclose(got, printed, atol=5e-4)
    # Mirror: the right arm at the same joint values is the left one with y -> -y.
    for name, v in zip(RIGHT_ARM, q, strict=True):
        cfg[order.index(name)] = v
    robot.update_cfg(cfg)
    right = robot.get_transform("right_tool", "torso")[:3, 3]
    assert np.allclose(right, got * [1, -1, 1], atol=1e-12)


def test_positive_sr_abducts_the_left_arm_and_negative_the_right(robot) -> None:
    left = original_chain(np.array([0, 0.5, 0, 0, 0, 0]), 1.0)[:3, 3]
    right = original_chain(np.array([0, -0.5, 0, 0, 0, 0]), -1.0)[:3, 3]
    assert left[1] > L1 and right[1] < -L1
