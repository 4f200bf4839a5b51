"""The closed-form 6-DOF IK (mds_ach.kinematics.analytic): exact, every solution, the nearest one chosen."""

from __future__ import annotations

import numpy as np
import pytest

from mds_ach import ik
from mds_ach.kinematics import model as kinematics
from mds_ach.kinematics.analytic import ArmGeometry, within


@pytest.mark.parametrize("arm", ["left", "right"])
def test_every_solution_is_exact_and_the_generating_one_is_among_them(arm: str) -> None:
    kin = kinematics.arm_kinematics(arm)
    geometry = ArmGeometry.of(kin)
    assert geometry is not None
    assert geometry.upper == pytest.approx(0.282575) and geometry.tool == pytest.approx(0.0635)
    rng = np.random.default_rng(7)
    for q in rng.uniform(kin.lower, kin.upper, size=(300, 6)):
        R, p, _ = kin.fk_jacobian_scalar(q.tolist())
        solutions = geometry.solve(R, p)
        assert 1 <= len(solutions) <= 8
        assert min(np.abs(np.array(s) - q).max() for s in solutions) < 1e-7
        for s in solutions:
            R2, p2, _ = kin.fk_jacobian_scalar(s)
            assert np.abs(np.array(R2) - R).max() < 1e-9 and np.abs(np.array(p2) - p).max() < 1e-9


def test_out_of_reach_has_no_solution_and_within_wraps_whole_turns() -> None:
    geometry = ArmGeometry.of(kinematics.arm_kinematics("left"))
    assert geometry is not None
    assert geometry.solve([1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [2.0, 0.0, 0.0]) == []
    lower, upper = [-1.0] * 6, [1.0] * 6
    wrapped = within([0.5 + 2 * np.pi, 0, 0, 0, 0, -0.5 - 4 * np.pi], lower, upper)
    assert wrapped == pytest.approx([0.5, 0, 0, 0, 0, -0.5])
    assert within([2.0, 0, 0, 0, 0, 0], lower, upper) is None


def test_full_pose_is_solved_in_closed_form_nearest_the_seed_and_safe() -> None:
    kin = kinematics.arm_kinematics("left")
    q_true = np.array([-0.4, 0.9, 0.2, -1.0, 0.5, 0.3])
    target = ik.getPosCurrentFromOrder(ik.getFkArm(q_true, "left"), ik.DOF_ORDERS[6])
    res = ik.solve(target, ik.DOF_ORDERS[6], "left", q_true + 0.05)
    assert res.success and res.iterations == 0 and np.abs(res.q - q_true).max() < 1e-9
    assert res.error < 1e-9 and kin.within_limits(res.q)
    # A collision hook that rejects that answer: another exact one (or the search), never the rejected one.
    def not_near_q_true(q: np.ndarray, arm: str) -> bool:
        return bool(np.abs(q - q_true).max() > 1e-3)
    res2 = ik.solve(target, ik.DOF_ORDERS[6], "left", q_true + 0.05, is_safe=not_near_q_true,
                    options=ik.IKOptions(max_iterations=200))
    assert not_near_q_true(res2.q, "left")
    assert res2.success or "no IK solution" in res2.message
    # The searches alone still solve it (closed_form=False), to the same tolerance.
    res3 = ik.solve(target, ik.DOF_ORDERS[6], "left", q_true + 0.05, options=ik.IKOptions(closed_form=False))
    assert res3.success and res3.iterations >= 1
