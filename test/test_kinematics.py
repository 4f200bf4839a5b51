"""mds_ach.kinematics.model: numpy FK/Jacobian of the arms and the whole tree, light imports
(the pytorch-kinematics cross-check is in test/support/torch_kinematics.py)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from support.reference_chain import original_chain

from mds_ach.kinematics import model as kinematics
from mds_ach.robot.joints import LEFT_ARM, MODEL_JOINTS, RIGHT_ARM

SIGN = {"left": 1.0, "right": -1.0}


def _q(n: int, seed: int = 3) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-math.pi, math.pi, size=(n, 6))


@pytest.mark.parametrize("arm", ["left", "right"])
def test_numpy_fk_equals_the_original_chain(arm: str) -> None:
    q = _q(200)
    T = kinematics.fk_matrix(q, arm)
    assert T.shape == (200, 4, 4)
    expected = np.array([original_chain(x, SIGN[arm]) for x in q])
    assert np.abs(T - expected).max() < 1e-12
    # Any leading batch shape, and a single vector.
    assert np.allclose(kinematics.fk_matrix(q.reshape(10, 20, 6), arm).reshape(200, 4, 4), T, atol=0)
    assert np.allclose(kinematics.fk_matrix(q[5], arm), expected[5], atol=1e-12)


@pytest.mark.parametrize("arm", ["left", "right"])
def test_geometric_jacobian_matches_finite_differences(arm: str) -> None:
    kin = kinematics.arm_kinematics(arm)
    q = _q(30, seed=5)
    R, p, J = kin.fk_jacobian(q)
    R0, p0 = kin.fk(q)
    assert np.allclose(R, R0, atol=0) and np.allclose(p, p0, atol=0)
    h = 1e-6
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        Rp, pp = kin.fk(q + dq)
        Rm, pm = kin.fk(q - dq)
        v = (pp - pm) / (2 * h)
        W = (Rp - Rm) / (2 * h) @ np.swapaxes(R, -1, -2)  # [w]x
        w = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
        assert np.abs(J[:, :3, i] - v).max() < 1e-8
        assert np.abs(J[:, 3:, i] - w).max() < 1e-8


def test_arm_chain_is_read_from_the_urdf() -> None:
    left, right = kinematics.arm_kinematics("left"), kinematics.arm_kinematics(0)  # legacy RIGHT = 0
    assert left.joint_names == LEFT_ARM and right.joint_names == RIGHT_ARM and right.arm == "right"
    assert kinematics.arm_kinematics(1) is left and kinematics.arm_kinematics("L") is left
    assert np.all(left.lower < left.upper)
    with pytest.raises(ValueError, match="unknown arm"):
        kinematics.arm_name("middle")
    with pytest.raises(ValueError, match="unknown arm"):
        kinematics.arm_name(2)


def test_joint_points_are_the_skeleton() -> None:
    kin = kinematics.arm_kinematics("left")
    pts = kin.joint_points(np.zeros(6))
    assert np.allclose(pts["shoulder"], [0, 0.24551, 0])
    assert np.allclose(pts["elbow"], [0, 0.24551, -0.282575])
    assert np.allclose(pts["wrist"], [0, 0.24551, -0.5953125])
    assert np.allclose(pts["tool"], [0, 0.24551, -0.6588125])


def test_link_poses_of_the_whole_tree_agree_with_the_arm_fk() -> None:
    model = kinematics.load_model()
    q = dict(zip(MODEL_JOINTS, np.random.default_rng(1).uniform(-0.3, 0.3, len(MODEL_JOINTS)), strict=True))
    poses = model.link_poses(q)
    assert set(poses) == set(model.links)
    torso = poses["torso"]
    for arm, names in (("left", LEFT_ARM), ("right", RIGHT_ARM)):
        tool = np.linalg.inv(torso) @ poses[f"{arm}_tool"]
        assert np.allclose(tool, kinematics.fk_matrix([q[n] for n in names], arm), atol=1e-12)
    # WST turns the whole upper body about z; the head follows the neck joints.
    turned = model.link_poses({"WST": 0.3})
    assert np.allclose(turned["torso"][:3, :3], kinematics.axis_angle(np.array([0.0, 0, 1]), 0.3))
    in_torso = model.link_poses({"NKY": 0.4}, root="torso")
    assert np.allclose(in_torso["torso"], np.eye(4))
    head = in_torso["head_link"]
    assert np.allclose(head[:3, :3], kinematics.axis_angle(np.array([0.0, 0, 1]), 0.4))


def test_euler_zyx_is_the_original_getrot_and_inverts_rotation_zyx() -> None:
    rng = np.random.default_rng(2)
    rpy = np.column_stack([rng.uniform(-math.pi, math.pi, 100), rng.uniform(-1.5, 1.5, 100),
                           rng.uniform(-math.pi, math.pi, 100)])
    R = kinematics.rotation_zyx(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    assert np.allclose(kinematics.euler_zyx(R), rpy, atol=1e-12)
    assert np.allclose(R, np.array([kinematics.rpy_matrix(*x) for x in rpy]), atol=1e-12)  # = URDF rpy
    r = R[0]
    assert kinematics.euler_zyx(r)[0] == math.atan2(r[2, 1], r[2, 2])
    assert kinematics.euler_zyx(r)[1] == math.atan2(-r[2, 0], math.sqrt(r[2, 1] ** 2 + r[2, 2] ** 2))
    assert kinematics.euler_zyx(r)[2] == math.atan2(r[1, 0], r[0, 0])


@pytest.mark.slow
@pytest.mark.parametrize("arm", ["left", "right"])
def test_torch_fk_and_jacobian_equal_numpy(arm: str) -> None:
    # Imported here, not at the top: torch costs ~3 s of import (measured) that collecting this module must not pay.
    from support.torch_kinematics import torch_chain, torch_fk, torch_jacobian

    q = _q(64, seed=9)
    kin = kinematics.arm_kinematics(arm)
    _, _, J = kin.fk_jacobian(q)
    assert np.abs(torch_fk(q, arm).numpy() - kin.fk_matrix(q)).max() < 1e-12
    assert np.abs(torch_jacobian(q, arm).numpy() - J).max() < 1e-12
    whole = torch_chain()
    assert set(whole.get_joint_parameter_names()) == set(MODEL_JOINTS)


def test_kinematics_and_ik_import_without_torch() -> None:
    code = ("import sys, mds_ach.kinematics.model, mds_ach.ik, mds_ach.nodes.ik_client, mds_ach.robot.msgs.ik_status; "
            "print(sorted(m for m in ('torch', 'pytorch_kinematics', 'yourdfpy', 'rclpy', 'fcl') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "[]"


def test_a_urdf_with_another_arm_geometry_is_followed(tmp_path) -> None:
    """The numpy chain is built from the file, not from constants: a longer forearm moves the tool."""
    from mds_ach.paths import urdf_path

    text = urdf_path().read_text().replace('xyz="0 0 -0.3127375"', 'xyz="0 0 -0.4"')
    path = tmp_path / "long.urdf"
    path.write_text(text)
    kin = kinematics.ArmKinematics(kinematics.load_model(path), "left")
    assert np.allclose(kin.fk_matrix(np.zeros(6))[:3, 3], [0, 0.24551, -(0.282575 + 0.4 + 0.0635)])


@pytest.mark.parametrize("arm", ["left", "right"])
def test_scalar_fk_jacobian_equals_numpy(arm: str) -> None:
    kin = kinematics.arm_kinematics(arm)
    assert kin.scalar_chain is not None  # the MDS arms turn about principal axes only
    q = _q(40, seed=12)
    R, p, J = kin.fk_jacobian(q)
    for k in range(len(q)):
        r, pos, cols = kin.fk_jacobian_scalar(q[k].tolist())
        assert np.abs(np.reshape(r, (3, 3)) - R[k]).max() < 1e-14
        assert np.abs(np.array(pos) - p[k]).max() < 1e-14
        assert np.abs(np.array(cols).T - J[k]).max() < 1e-14


def test_skewed_joint_axes_use_the_numpy_path(tmp_path) -> None:
    """A joint axis off x/y/z has no plain-float chain; FK still works through numpy (and IK with it)."""
    from mds_ach import ik
    from mds_ach.paths import urdf_path

    text = urdf_path().read_text()
    marker = '<joint name="LSY" type="revolute">'
    head, tail = text.split(marker)
    tail = tail.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0.6 0.8"/>', 1)
    path = tmp_path / "skew.urdf"
    path.write_text(head + marker + tail)
    kin = kinematics.ArmKinematics(kinematics.load_model(path), "left")
    assert kin.scalar_chain is None
    with pytest.raises(ValueError, match="principal axes"):
        kin.fk_jacobian_scalar([0.0] * 6)
    q = np.array([0.1, 0.2, 0.7, -0.5, 0.3, 0.2])
    R, p = kin.fk(q)
    axes = [np.array(a, dtype=float) for a in ((0, 1, 0), (1, 0, 0), (0, 0.6, 0.8), (0, 1, 0), (0, 0, 1), (1, 0, 0))]
    steps = [(0, 0.24551, 0), (0, 0, 0), (0, 0, 0), (0, 0, -0.282575), (0, 0, -0.3127375), (0, 0, 0)]
    T = np.eye(4)
    for axis, t, angle in zip(axes, steps, q, strict=True):
        A = np.eye(4)
        A[:3, :3] = kinematics.axis_angle(axis, angle)
        A[:3, 3] = t
        T = T @ A
    assert np.allclose(R, T[:3, :3], atol=1e-12) and np.allclose(p, T[:3, :3] @ [0, 0, -0.0635] + T[:3, 3])
    solver = ik.IKSolver("left")
    solver.kin = kin  # the solver uses whatever chain it is given
    res = solver.solve(p, ["p-x", "p-y", "p-z"], np.zeros(6))
    assert res.success and np.linalg.norm(kin.fk(res.q)[1] - p) <= 0.01
