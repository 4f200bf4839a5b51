"""The IK searches in C (``mds_ach.kinematics._iksearch``) against the Python ones they replace: built where they can
be, the same score and the same steps, every masked task of a fixed seeded sample solved within 1 mm / 0.01 rad by
an independent FK, and the Python path still there (and still solving) when the extension is missing (#20)."""

from __future__ import annotations

import math
import shutil
import sysconfig
from pathlib import Path

import numpy as np
import pytest

from mds_ach import ik
from mds_ach.kinematics import ik as ik_impl
from mds_ach.kinematics import model as kinematics

needs_native = pytest.mark.skipif(not ik.NATIVE_AVAILABLE, reason="mds_ach.kinematics._iksearch not built")
URDF = Path(__file__).resolve().parent.parent / "urdf" / "mds.urdf"
ARM_JOINTS = {"left": ("LSP", "LSR", "LSY", "LEP", "LWY", "LWR"), "right": ("RSP", "RSR", "RSY", "REP", "RWY", "RWR")}


def test_c_searches_are_built_where_they_can_be() -> None:
    """setup.py builds the extension as optional: a failed compile would silently leave the slow path (or a stale
    .so); with a compiler here it must be importable and in use."""
    cc = sysconfig.get_config_var("CC")
    if not (shutil.which(cc.split()[0] if cc else "cc")
            and Path(sysconfig.get_paths().get("include", ""), "Python.h").is_file()):
        pytest.skip("no C compiler or Python headers here: the Python searches are the only ones")
    assert ik.NATIVE_AVAILABLE, "mds_ach.kinematics._iksearch is not importable: run `make setup`"
    assert ik.IKSolver("left")._native is not None
    assert len(ik_impl._iksearch.solve.__doc__ or "") > 0


ORDERS = [ik.DOF_ORDERS[d] for d in range(1, 7)] + [("t-z", "p-x"), ("t-y",), ("t-x", "t-z", "p-y"), ("t-y", "t-z"),
                                                     ("t-x", "t-y", "p-z"), ("t-x", "t-y", "t-z")]


@needs_native
@pytest.mark.parametrize("tolerance", [None, 0.01])
def test_c_score_and_error_equal_the_python_ones(tolerance: float | None) -> None:
    """A search of zero steps reports the score and solver error of its start: those of Task.residual_scalar, for
    every task mode (position, Euler angles, tilt, full pose), both success tests and poses near gimbal lock."""
    solver = ik.IKSolver("left")
    kin = solver.kin
    rng = np.random.default_rng(11)
    steps = solver._native_steps(ik.IKOptions())
    for order in ORDERS:
        q_target = rng.uniform(kin.lower, kin.upper)
        target = ik.getPosCurrentFromOrder(kin.fk_matrix(q_target), order)
        task = ik.Task(target, order, tolerance)
        starts = np.vstack([rng.uniform(kin.lower, kin.upper, size=(20, 6)), q_target + 1e-4,
                            np.clip([-math.pi / 2, 0, 0, 0, 0, 0], kin.lower, kin.upper)])
        for q in starts:
            _, _, err, score = task.residual_scalar(*kin.fk_jacobian_scalar(q.tolist()))
            q_out, c_score, c_err, used, _ = ik_impl._iksearch.search(
                solver._native, task.native_spec(), steps, q.tolist(), q.tolist(), 0, 1.0, 1.0, 10, True)
            assert used == 0 and q_out == q.tolist()
            assert c_score == pytest.approx(score, rel=1e-12, abs=1e-12), order
            assert c_err == pytest.approx(err, rel=1e-12, abs=1e-15), order


@needs_native
@pytest.mark.parametrize("budget", [1, 4, 15])
def test_c_steps_are_the_python_steps(budget: int) -> None:
    """The same trust-region steps (damping, active set at the limits, null-space pull toward the seed) from the
    same start: the joint vectors agree to round-off after 1, 4 and 15 steps."""
    solver = ik.IKSolver("right")
    kin = solver.kin
    opt = ik.IKOptions()
    rng = np.random.default_rng(12)
    compared = 0
    for order in ORDERS:
        for _ in range(4):
            target = ik.getPosCurrentFromOrder(kin.fk_matrix(rng.uniform(kin.lower, kin.upper)), order)
            task = ik.Task(target, order)
            start, seed = rng.uniform(kin.lower, kin.upper), rng.uniform(kin.lower, kin.upper)
            q_py, score_py, _, used_py, _ = solver._fast_search(task, seed, opt, start=start, budget=budget)
            q_c, score_c, _, used_c, _ = ik_impl._iksearch.search(
                solver._native, task.native_spec(), solver._native_steps(opt), start.tolist(), seed.tolist(),
                budget, 1.0, 1.0, min(opt.stall_iterations, 10), True)
            assert used_c == used_py, order
            assert np.allclose(q_c, q_py, atol=1e-9, rtol=0), order
            assert score_c == pytest.approx(score_py, rel=1e-6, abs=1e-9)
            compared += used_py
    assert compared > 2 * len(ORDERS) * budget  # most searches really stepped


def _referee() -> tuple[object, dict[str, tuple[float, float]]]:
    yourdfpy = pytest.importorskip("yourdfpy")
    robot = yourdfpy.URDF.load(str(URDF), load_meshes=False, build_collision_scene_graph=False)
    return robot, {j.name: (j.limit.lower, j.limit.upper) for j in robot.robot.joints if j.limit is not None}


def _solved(robot: object, limits: dict[str, tuple[float, float]], arm: str, q: np.ndarray, dof: int,
            T: np.ndarray) -> bool:
    """Success by yourdfpy's FK (not ours): within the limits, position within 1 mm, angles within 0.01 rad."""
    if not all(limits[n][0] - 1e-9 <= v <= limits[n][1] + 1e-9 for n, v in zip(ARM_JOINTS[arm], q, strict=True)):
        return False
    robot.update_cfg(dict(zip(ARM_JOINTS[arm], (float(v) for v in q), strict=True)))  # type: ignore[attr-defined]
    got = robot.get_transform(f"{arm}_tool", "torso")  # type: ignore[attr-defined]
    n = min(dof, 3)
    if np.linalg.norm(got[:n, 3] - T[:n, 3]) > 1e-3:
        return False
    if dof == 6:
        c = (np.trace(T[:3, :3].T @ got[:3, :3]) - 1) / 2
        return math.acos(max(-1.0, min(1.0, c))) <= 0.01
    want, have = kinematics.euler_zyx(T[:3, :3]), kinematics.euler_zyx(got[:3, :3])
    d = [math.remainder(want[k] - have[k], 2 * math.pi) for k in range(dof - 3)]
    return math.sqrt(sum(x * x for x in d)) <= 0.01


@needs_native
@pytest.mark.parametrize("dof", [1, 2, 3, 4, 5, 6])
def test_every_target_of_a_seeded_sample_is_solved(dof: int) -> None:
    """Both arms, 150 reachable targets per start kind (random seeds and the home pose): all solved within the
    limits at 1 mm / 0.01 rad by an independent FK, with a bounded amount of search."""
    robot, limits = _referee()
    order = ik.DOF_ORDERS[dof]
    rng = np.random.default_rng(2020 + dof)
    steps = []
    for start in ("random", "home"):
        for case in range(150):
            arm = ("left", "right")[case % 2]
            solver = ik.solver(arm)
            T = solver.kin.fk_matrix(rng.uniform(solver.lower, solver.upper))
            q0 = rng.uniform(solver.lower, solver.upper) if start == "random" else np.clip(np.zeros(6), solver.lower,
                                                                                            solver.upper)
            res = solver.solve(ik.getPosCurrentFromOrder(T, order), order, q0)
            assert res.success, (dof, start, case, res.message)
            assert _solved(robot, limits, arm, res.q, dof, T), (dof, start, case)
            steps.append(res.iterations)
    # Every solve stays far inside the step budget (the default 1000 iterations x 8 seeds).
    assert max(steps) < 0.75 * ik.DEFAULT_ITERATIONS * ik.IKOptions().seeds


def test_the_python_searches_remain_the_fallback(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without the extension (no compiler), IKSolver runs the Python searches and still solves every masked task;
    where the seed's own search converges both paths return the same joint vector."""
    monkeypatch.setattr(ik_impl, "_iksearch", None)
    slow = ik.IKSolver("left")
    assert slow._native is None
    monkeypatch.undo()
    fast = ik.IKSolver("left")
    robot, limits = _referee()
    rng = np.random.default_rng(99)
    same = 0
    for dof in range(1, 7):
        order = ik.DOF_ORDERS[dof]
        for _ in range(8):
            T = slow.kin.fk_matrix(rng.uniform(slow.lower, slow.upper))
            q0 = rng.uniform(slow.lower, slow.upper)
            target = ik.getPosCurrentFromOrder(T, order)
            a = slow.solve(target, order, q0)
            assert a.success and _solved(robot, limits, "left", a.q, dof, T), (dof, a.message)
            if fast._native is None:
                continue
            b = fast.solve(target, order, q0)
            assert b.success and _solved(robot, limits, "left", b.q, dof, T), (dof, b.message)
            if slow._fast_search(ik.Task(target, order), np.asarray(q0), ik.IKOptions())[4]:  # the seed's search
                assert np.allclose(a.q, b.q, atol=1e-8), dof
                assert a.error == pytest.approx(b.error, abs=1e-9)
                assert np.allclose(a.achieved, b.achieved, atol=1e-9)
                same += 1
    assert fast._native is None or same >= 15


@needs_native
def test_unreachable_targets_fail_within_the_budget_and_the_timeout() -> None:
    """A target out of reach costs at most the step budget (or the timeout) and reports the best attempt, within
    the limits."""
    solver = ik.IKSolver("left")
    res = solver.solve([2.0, 0.0, 0.0], ["p-x", "p-y", "p-z"], np.zeros(6), ik.IKOptions(max_iterations=50))
    assert not res.success and "no IK solution within 50 iterations" in res.message
    assert res.iterations <= 50 * ik.IKOptions().seeds
    assert solver.kin.within_limits(res.q, tol=0.0)
    assert res.error > 1.0  # the original's m+rad error of the best attempt: over a metre short
    res = solver.solve([2.0, 0.0, 0.0], ["p-x", "p-y", "p-z"], np.zeros(6),
                       ik.IKOptions(max_iterations=10**7, timeout=0.005))
    assert not res.success and "gave up after" in res.message and res.time < 1.0


@needs_native
@pytest.mark.parametrize("arm", ["left", "right"])
def test_c_closed_form_gives_the_python_candidates(arm: str) -> None:
    """Full poses: the C closed form lists the candidates of IKSolver._closed_form (analytic.ArmGeometry.solve,
    moved into the limits by whole turns, the seed first when already there, then nearest the seed, each within
    1e-3 of the tolerance), and the same answer with its error and pose components."""
    from mds_ach.kinematics.analytic import within
    solver = ik.IKSolver(arm)
    kin, geometry = solver.kin, solver.geometry
    assert geometry is not None
    rng = np.random.default_rng(13)
    lower, upper = solver._lower_list, solver._upper_list
    order = ik.DOF_ORDERS[6]
    for k in range(200):
        q_true = rng.uniform(kin.lower, kin.upper)
        task = ik.Task(ik.getPosCurrentFromOrder(kin.fk_matrix(q_true), order), order)
        seed = q_true.copy() if k % 10 == 0 else rng.uniform(kin.lower, kin.upper)
        p = [0.0, 0.0, 0.0]
        for i, v in zip(task.pos_idx, task.pos_target.tolist(), strict=True):
            p[i] = v
        found = [q for q in (within(s, lower, upper) for s in geometry.solve(task._R_target_list, p)) if q is not None]
        found.sort(key=lambda q: max(abs(a - b) for a, b in zip(q, seed.tolist(), strict=True)))
        found.insert(0, seed.tolist())
        want = [q for q in found if task.residual_scalar(*kin.fk_jacobian_scalar(q))[3] <= 1e-3]
        got = ik_impl._iksearch.closed_form(solver._native, task.native_spec(), seed.tolist())
        assert len(got) == len(want) >= 1, k
        for (q, err, pose), q_py in zip(got, want, strict=True):
            assert np.allclose(q, q_py, atol=1e-12, rtol=0), k
            assert err == pytest.approx(float(task.error(*kin.fk(np.array(q)[None]))[0]), abs=1e-12)
            R, pp = kin.fk(np.array(q))
            assert np.allclose(pose, [*pp, *kinematics.euler_zyx(R)], atol=1e-12)
        first, _ = solver._closed_form(task, seed, 0)
        assert first is not None and np.allclose(got[0][0], first, atol=1e-12)


@needs_native
def test_c_searches_refuse_malformed_input_with_a_message() -> None:
    """The extension checks what it is handed (a wrong tuple must not be read as a pose)."""
    solver = ik.IKSolver("left")
    spec = list(ik.Task([0.3, 0.2, 0.0, 0.1, 0.2, 0.3], ik.DOF_ORDERS[6]).native_spec())
    steps = solver._native_steps(ik.IKOptions())
    bad_rotation = tuple(spec[:5] + [[1.0, 0.0, 0.0]] + spec[6:])
    with pytest.raises(ValueError, match="R_target"):
        ik_impl._iksearch.search(solver._native, bad_rotation, steps, [0.0] * 6, [0.0] * 6, 1, 1.0, 1.0, 10, True)
    with pytest.raises(ValueError, match="seed needs 6 numbers"):
        ik_impl._iksearch.solve(solver._native, tuple(spec), steps, [0.0] * 5, True, 20, 60, 100, 0.0, 0, 1)
    with pytest.raises(ValueError, match="closed form needs an arm of the MDS shape|full pose"):
        ik_impl._iksearch.closed_form(solver._native, ik.Task([0.3], ["p-x"]).native_spec(), [0.0] * 6)
    with pytest.raises(ValueError, match="axis must be 0..2"):
        ik_impl._iksearch.arm([5] * 6, [1.0] * 6, [0.0] * 18, [0.0] * 3, [-1.0] * 6, [1.0] * 6)
