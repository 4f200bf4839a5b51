"""mds_ach.ik: the legacy API (getFkArm, getIK, getPosCurrentFromOrder, getRot) and the modern solver."""

from __future__ import annotations

import math

import numpy as np
import pytest
from support.reference_chain import original_chain

from mds_ach import ik
from mds_ach.kinematics import model as kinematics

ARMS = ("left", "right")


def reachable(arm: str, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(joint vectors within the limits, their tool poses)."""
    kin = kinematics.arm_kinematics(arm)
    q = np.random.default_rng(seed).uniform(kin.lower, kin.upper, size=(n, 6))
    return q, kin.fk_matrix(q)


def task_error(q: np.ndarray, arm: str, target: np.ndarray, order: list[str]) -> float:
    """Independent check: components of the pose at q vs the target (angles wrapped)."""
    got = ik.getPosCurrentFromOrder(ik.getFkArm(q, arm), order)
    diff = np.asarray(target, dtype=float) - got
    angles = [i for i, c in enumerate(order) if c.replace("_", "-").startswith("t")]
    diff[angles] = (diff[angles] + math.pi) % (2 * math.pi) - math.pi
    return float(np.linalg.norm(diff))


# --------------------------------------------------------------------------------------------- legacy API


@pytest.mark.parametrize("arm", ARMS)
def test_getfkarm_is_the_original_chain(arm: str) -> None:
    q = np.random.default_rng(0).uniform(-3, 3, 6)
    A = ik.getFkArm(q, arm)
    assert isinstance(A, np.ndarray) and A.shape == (4, 4)
    assert np.abs(A - original_chain(q, 1.0 if arm == "left" else -1.0)).max() < 1e-12
    assert np.allclose(ik.getFkArm(list(q), arm), A)
    with pytest.raises(ValueError, match="unknown arm"):
        ik.getFkArm(q, "both")
    with pytest.raises(ValueError, match="6 joint values"):
        ik.getFkArm(q[:5], arm)


def test_getposcurrentfromorder_and_getrot_pick_components() -> None:
    A = ik.getFkArm([-0.4, 0.3, 0.2, -1.0, 0.5, 0.3], "left")
    rpy = kinematics.euler_zyx(A[:3, :3])
    got = ik.getPosCurrentFromOrder(A, ["p_x", "p_y", "p_z", "t_x", "t_y", "t_z"])
    assert np.allclose(got, [*A[:3, 3], *rpy], atol=0)
    assert np.allclose(ik.getPosCurrentFromOrder(A, ["t-z", "p-y"]), [rpy[2], A[1, 3]], atol=0)
    assert [ik.getRot(A, a) for a in ("x", "y", "z")] == pytest.approx(list(rpy), abs=0)
    assert ik.getRot(A, "t_y") == pytest.approx(rpy[1], abs=0)
    with pytest.raises(ValueError, match="unknown task component"):
        ik.getPosCurrentFromOrder(A, ["p_w"])
    with pytest.raises(ValueError, match="unknown rotation axis"):
        ik.getRot(A, "w")


def test_task_jacobian_matches_finite_differences() -> None:
    q = np.array([-0.5, 0.4, 0.3, -1.1, 0.2, 0.2])
    order = ["p_x", "t_z", "p_z", "t_x", "t_y", "p_y"]
    J = ik.getJacobian(q, order, 0.01, "right")
    h = 1e-6
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        num = (ik.getPosCurrentFromOrder(ik.getFkArm(q + dq, "right"), order)
               - ik.getPosCurrentFromOrder(ik.getFkArm(q - dq, "right"), order)) / (2 * h)
        assert np.allclose(J[:, i], num, atol=1e-7)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 5, 6])
@pytest.mark.parametrize("arm", ARMS)
def test_getik_solves_reachable_targets(arm: str, dof: int) -> None:
    order = [c.replace("-", "_") for c in ik.DOF_ORDERS[dof]]  # the original's spelling
    q_true, T = reachable(arm, 15, seed=dof)
    seeds = np.random.default_rng(100 + dof).uniform(-1, 1, size=(15, 6))
    kin = kinematics.arm_kinematics(arm)
    for k in range(15):
        target = ik.getPosCurrentFromOrder(T[k], order)
        q, status = ik.getIK(seeds[k], target, order, arm)
        assert status == 0
        assert kin.within_limits(q)
        assert task_error(q, arm, target, order) <= 0.01


def test_getik_itr_none_means_the_default_cap_not_instant_failure() -> None:
    """The original returned failure after one step when itr was None (Python 2 comparison bug)."""
    target = [0.3, 0.2, 0.0]
    q, status = ik.getIK(np.zeros(6), target, ["p_x", "p_y", "p_z"], "left", err=None, itr=None)
    assert status == 0 and task_error(q, "left", np.array(target), ["p_x", "p_y", "p_z"]) <= 0.01


def test_getik_unreachable_returns_the_last_attempt_and_minus_one() -> None:
    q, status = ik.getIK(np.zeros(6), [2.0, 0.2, 0.0], ["p_x", "p_y", "p_z"], "left", itr=50)
    assert status == -1
    assert q.shape == (6,) and np.all(np.isfinite(q)) and kinematics.arm_kinematics("left").within_limits(q)
    # The best attempt reaches toward the target: the arm is stretched forward.
    assert ik.getFkArm(q, "left")[0, 3] > 0.5


def test_getik_tolerance_is_err_2() -> None:
    order = ["p_x", "p_y", "p_z"]
    target = [0.35, 0.3, -0.1]
    for tol in (0.05, 1e-4):
        q, status = ik.getIK(np.zeros(6), target, order, "left", err=[0.01, 0.01, tol])
        assert status == 0 and task_error(q, "left", np.array(target), order) <= tol
    with pytest.raises(ValueError, match="err must be"):
        ik.getIK(np.zeros(6), target, order, "left", err=[0.01, 0.01])


def test_original_examples_from_the_demo() -> None:
    """mds-demo.sh: `ik left 3 0.3 0.2 0` and the box demo corners are reachable."""
    for target in ([0.3, 0.2, 0.0], [0.4, 0.45, 0.25], [0.4, -0.05, 0.25], [0.4, -0.05, -0.25], [0.4, 0.45, -0.25]):
        q, status = ik.getIK(np.zeros(6), target, ["p_x", "p_y", "p_z"], "left")
        assert status == 0, target
        assert task_error(q, "left", np.array(target), ["p_x", "p_y", "p_z"]) <= 0.01


@pytest.mark.parametrize("arm, target", [
    ("left", [0.3, 0.2, 0.0, 1.57, 0.0, -1.57]),  # `ik left 6 0.3 0.2 0.0 1.57 0.0 -1.57`
    ("right", [0.3, -0.2, 0.0, 0.0, 0.0, 1.57]),  # `ikach right 6 0.3 -0.2 0 0 0 1.57`
])
def test_demo_6dof_poses_beyond_the_wrist_range_are_reported_unreachable(arm: str, target: list[float]) -> None:
    """Both need the forearm nearly along the tool z axis, but WR bends at most 0.3*pi/2: the elbow would
    have to sit farther from (or closer to) the shoulder than the upper arm's length. Say so, move nothing."""
    res = ik.solve(target, ik.DOF_ORDERS[6], arm, np.zeros(6), options=ik.IKOptions(max_iterations=150))
    assert not res.success and res.error > 0.01
    assert "no IK solution" in res.message
    assert kinematics.arm_kinematics(arm).within_limits(res.q)


# --------------------------------------------------------------------------------------------- modern API


def test_any_component_order_and_spelling() -> None:
    q_true, T = reachable("left", 5, seed=42)
    for order in (["t-z", "p-x"], ["p_y", "t_x", "p_z"], ["t-y"], ["p-z", "t-z", "t-x", "p-x"]):
        for k in range(5):
            target = ik.getPosCurrentFromOrder(T[k], order)
            res = ik.solve(target, order, "left", np.zeros(6))
            assert res.success, (order, res.message)
            assert res.order == tuple(c.replace("_", "-") for c in order)
            assert task_error(res.q, "left", target, order) <= 0.01
            assert np.allclose(res.achieved, ik.getPosCurrentFromOrder(ik.getFkArm(res.q, "left"), order))


def test_result_reports_error_iterations_and_time() -> None:
    res = ik.solve([0.3, 0.2, 0.0], ["p-x", "p-y", "p-z"], "left", np.zeros(6))
    assert res.success and res.message == "solved"
    assert 0 <= res.error <= 0.01 and res.iterations >= 1 and res.time > 0
    assert res.arm == "left" and np.allclose(res.target, [0.3, 0.2, 0.0])


def test_joint_limits_are_never_left() -> None:
    kin = kinematics.arm_kinematics("right")
    rng = np.random.default_rng(8)
    for _ in range(40):
        target = rng.uniform([-0.8, -1.0, -0.8], [0.8, 0.6, 0.8])  # many unreachable
        res = ik.solve(target, ["p-x", "p-y", "p-z"], "right", rng.uniform(-3, 3, 6),
                       options=ik.IKOptions(max_iterations=60))
        assert kin.within_limits(res.q, tol=0.0)


def test_narrower_limits_are_respected() -> None:
    solver = ik.IKSolver("left", limits=(np.full(6, -0.3), np.full(6, 0.3)))
    assert np.all(solver.lower >= -0.3) and np.all(solver.upper <= 0.3)
    assert solver.lower[1] == 0.0  # LSR's URDF bound is tighter than -0.3
    res = solver.solve([0.2, 0.3, -0.55], ["p-x", "p-y", "p-z"], np.zeros(6))
    assert np.all(res.q >= solver.lower) and np.all(res.q <= solver.upper)
    with pytest.raises(ValueError, match="empty joint range"):
        ik.IKSolver("left", limits=(np.full(6, 3.0), np.full(6, 3.5)))


def test_null_space_keeps_the_free_dof_at_the_seed() -> None:
    """A position-only task leaves three DOF free; they stay where they were instead of drifting."""
    kin = kinematics.arm_kinematics("left")
    seed = np.array([-0.6, 0.4, 0.3, -1.2, 0.5, 0.2])
    target = kin.fk(seed)[1] + [0.02, -0.01, 0.015]  # a small move
    res = ik.solve(target, ["p-x", "p-y", "p-z"], "left", seed)
    assert res.success
    assert np.max(np.abs(res.q - seed)) < 0.15
    # Already there: nothing moves.
    res = ik.solve(kin.fk(seed)[1], ["p-x", "p-y", "p-z"], "left", seed)
    assert res.success and res.iterations == 0 and np.array_equal(res.q, seed)


def test_fixed_step_limits_without_adaptation() -> None:
    seed = np.zeros(6)
    opts = ik.IKOptions(adaptive=False, joint_step=0.01, task_step=0.01, max_iterations=10, seeds=1)
    res = ik.solve([0.3, 0.2, 0.0], ["p-x", "p-y", "p-z"], "left", seed, options=opts)
    assert not res.success and res.iterations == 10
    assert np.max(np.abs(res.q - np.clip(seed, *_limits("left")))) <= 10 * 0.01 + 1e-12


def _limits(arm: str) -> tuple[np.ndarray, np.ndarray]:
    kin = kinematics.arm_kinematics(arm)
    return kin.lower, kin.upper


def test_gimbal_lock_and_non_canonical_angles() -> None:
    kin = kinematics.arm_kinematics("left")
    q_fwd = np.array([-math.pi / 2, 0.0, 0.0, 0.0, 0.0, 0.0])  # arm raised forward: pitch -90 deg exactly
    A = kin.fk_matrix(np.clip(q_fwd, kin.lower, kin.upper))
    target = ik.getPosCurrentFromOrder(A, ik.DOF_ORDERS[6])
    res = ik.solve(target, ik.DOF_ORDERS[6], "left", np.zeros(6))
    assert res.success and np.allclose(kin.fk_matrix(res.q)[:3, :3], A[:3, :3], atol=0.02)
    # Roll/pitch given outside the canonical range describe the same orientation: still solved.
    A = kin.fk_matrix(np.array([-0.3, 0.2, 0.1, -1.0, 0.3, 0.2]))
    r, p, y = kinematics.euler_zyx(A[:3, :3])
    alt = [r + math.pi, math.pi - p, y + math.pi]  # the other Z-Y-X triple of the same rotation
    res = ik.solve([*A[:3, 3], *alt], ik.DOF_ORDERS[6], "left", np.zeros(6))
    assert res.success and np.allclose(res.target[3:], [r, p, y], atol=1e-9)


def test_collision_hook_rejects_candidates_and_paths() -> None:
    calls: list[np.ndarray] = []

    def no_positive_shoulder_yaw(q: np.ndarray, arm: str) -> bool:
        assert arm == "left"
        calls.append(q.copy())
        return q[2] <= 0.0

    solver = ik.IKSolver("left", is_safe=no_positive_shoulder_yaw)
    q_true, T = reachable("left", 10, seed=77)
    for k in range(10):
        target = T[k][:3, 3]
        res = solver.solve(target, ["p-x", "p-y", "p-z"], np.zeros(6))
        assert res.success and res.q[2] <= 0.0
    # The path from the seed is sampled too: points strictly between seed and candidate were checked.
    assert any(0 < np.linalg.norm(c) for c in calls)

    def never(q: np.ndarray, arm: str) -> bool:
        return False

    res = ik.IKSolver("left", ik.IKOptions(max_iterations=40), is_safe=never).solve([0.3, 0.2, 0.0],
                                                                                     ["p-x", "p-y", "p-z"])
    assert not res.success and res.rejected_unsafe > 0 and "collision" in res.message


@pytest.mark.parametrize(
    "target, order, message",
    [
        ([0.3, math.nan, 0.0], ["p-x", "p-y", "p-z"], "NaN or Inf"),
        ([0.3, 0.2], ["p-x", "p-y", "p-z"], "has 2 values"),
        ([0.3, 0.2], ["p-x", "p-x"], "given twice"),
        ([0.3], ["q-x"], "unknown task component"),
        ([], [], "empty task order"),
    ],
)
def test_bad_requests_are_refused_with_a_message(target: list[float], order: list[str], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ik.solve(target, order, "left")


def test_bad_seed_and_dof_are_refused() -> None:
    with pytest.raises(ValueError, match="finite joint values"):
        ik.solve([0.3], ["p-x"], "left", [0, 0, math.inf, 0, 0, 0])
    with pytest.raises(ValueError, match="bad IK dof"):
        ik.order_for_dof(7)
    assert ik.order_for_dof(4) == ("p-x", "p-y", "p-z", "t-x")


def test_rotation_vectors_including_half_turns() -> None:
    rng = np.random.default_rng(4)
    R = kinematics.rotation_zyx(*rng.uniform(-3, 3, (3, 50)))
    half = kinematics.axis_angle(np.array([1.0, 2.0, -2.0]) / 3.0, math.pi)
    R = np.concatenate([R, np.eye(3)[None], half[None]])
    rv, theta = ik._rotvec(R)
    assert np.allclose(np.linalg.norm(rv, axis=1), theta) and np.all(theta <= math.pi + 1e-12)
    for k in range(len(R)):
        axis = rv[k] / theta[k] if theta[k] > 0 else np.array([1.0, 0, 0])
        assert np.allclose(kinematics.axis_angle(axis, theta[k]), R[k], atol=1e-9)


@pytest.mark.parametrize("dof", [3, 4, 5, 6])
def test_batched_searches_alone_solve_reachable_targets(dof: int) -> None:
    """The restarts path (numpy-batched searches), without the one-search fast path in front of it."""
    order = ik.DOF_ORDERS[dof]
    opts = ik.IKOptions(fast_iterations=0)
    _, T = reachable("right", 12, seed=30 + dof)
    seeds = np.random.default_rng(dof).uniform(-1, 1, size=(12, 6))
    for k in range(12):
        target = ik.getPosCurrentFromOrder(T[k], order)
        res = ik.solve(target, order, "right", seeds[k], options=opts)
        assert res.success, res.message
        assert task_error(res.q, "right", target, list(order)) <= 0.01


def test_plain_float_residual_equals_the_batched_one() -> None:
    kin = kinematics.arm_kinematics("left")
    rng = np.random.default_rng(6)
    orders = [ik.DOF_ORDERS[d] for d in range(1, 7)] + [("t-z", "p-x"), ("t-y",), ("t-x", "t-z", "p-y"),
                                                         ("t-y", "t-z"), ("t-x", "t-y", "p-z")]
    for order in orders:
        target = ik.getPosCurrentFromOrder(kin.fk_matrix(rng.uniform(kin.lower, kin.upper)), order)
        for tolerance in (None, 0.01):
            task = ik.Task(target, order, tolerance)
            for q in rng.uniform(kin.lower, kin.upper, size=(10, 6)):
                batched = task.residual(*kin.fk_jacobian(q[None]))
                scalar = task.residual_scalar(*kin.fk_jacobian_scalar(q.tolist()))
                assert np.allclose(batched[0][0], scalar[0], atol=1e-12)
                assert np.allclose(batched[1][0], np.array(scalar[1]), atol=1e-12)
                assert batched[2][0] == pytest.approx(scalar[2], abs=1e-12)
                assert batched[3][0] == pytest.approx(scalar[3], abs=1e-12)
