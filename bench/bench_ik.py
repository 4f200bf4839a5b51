"""IK benchmark: success rate and time per solve for 3-6 DOF tasks, against the original algorithm.

Targets are reachable by construction: the tool pose of a random joint vector within the URDF limits.
Each solve starts from another random joint vector (the "current pose"). Both solvers get the same
targets and seeds; the baseline runs on a subset because it can take 1000 slow iterations per failure.

Baseline = the original ``mds_ik.getIK`` algorithm re-implemented: forward-difference Jacobian
(dθ = 0.01) of the Z-Y-X components, ``numpy.linalg.pinv``, a fixed task-space step of 0.01 toward
the target, the original clamps, success at ||e|| <= 0.01, at most 1000 iterations. Its FK is our
batched numpy FK (7 poses per Jacobian in one call), so it is faster than the 2015 code was.

Run: ``python -m bench --only bench_ik [--quick]`` or ``python -m bench.bench_ik [--quick]``.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from bench.common import Row, median, percentile
from mds_ach import ik
from mds_ach.kinematics import arm_kinematics, euler_zyx

# The original clamps (specs section e.2), [SP, SR, SY, EP, WY, WR]; SR is mirrored for the right arm.
_WR = 0.3 * math.pi / 2
ORIGINAL_CLAMPS = {
    "left": (np.array([-math.pi, 0.0, -math.pi, -2.4, -math.pi, -_WR]),
             np.array([math.pi, math.pi, math.pi, 0.0, math.pi, _WR])),
    "right": (np.array([-math.pi, -math.pi, -math.pi, -2.4, -math.pi, -_WR]),
              np.array([math.pi, 0.0001, math.pi, 0.0, math.pi, _WR])),
}


def original_ik(q0: np.ndarray, target: np.ndarray, dof: int, arm: str, err: tuple[float, float, float] = (0.01,) * 3,
                itr: int = 1000) -> tuple[np.ndarray, int, int]:
    """The original algorithm; returns (q, 0 | -1, iterations)."""
    kin = arm_kinematics(arm)
    lo, hi = ORIGINAL_CLAMPS[arm]
    dtheta, step, tol = err
    perturb = np.vstack([np.zeros(6), np.eye(6) * dtheta])
    q = np.clip(np.asarray(q0, dtype=float), lo, hi)

    def components(qs: np.ndarray) -> np.ndarray:
        R, p = kin.fk(qs)
        return np.concatenate([p, euler_zyx(R)], axis=-1)[..., :dof]

    for i in range(1, itr + 1):
        x = components(q + perturb)  # current pose and the six forward-difference neighbours
        e = target - x[0]
        norm = float(np.linalg.norm(e))
        if norm <= tol:
            return q, 0, i - 1
        J = ((x[1:] - x[0]) / dtheta).T  # dof x 6
        q = np.clip(q + np.linalg.pinv(J) @ (e / norm * step), lo, hi)
    x = components(q[None])[0]
    return q, (0 if np.linalg.norm(target - x) <= tol else -1), itr


def _cases(arm: str, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    kin = arm_kinematics(arm)
    q_target = rng.uniform(kin.lower, kin.upper, size=(n, 6))
    q_seed = rng.uniform(kin.lower, kin.upper, size=(n, 6))
    return q_target, q_seed, kin.fk_matrix(q_target)


def run(quick: bool = False) -> list[Row]:
    n = 100 if quick else 500
    n_base = 12 if quick else 60
    rng = np.random.default_rng(20150101)
    rows: list[Row] = []
    for dof in (3, 4, 5, 6):
        order = ik.DOF_ORDERS[dof]
        times: list[float] = []
        iters: list[int] = []
        ok = 0
        base_times: list[float] = []
        base_ok = 0
        for case in range(n):
            arm = ("left", "right")[case % 2]
            solver = ik.solver(arm)
            _, q_seed, T = _cases(arm, 1, rng)
            target = ik.getPosCurrentFromOrder(T[0], order)
            t0 = time.perf_counter()
            res = solver.solve(target, order, q_seed[0])
            times.append(time.perf_counter() - t0)
            iters.append(res.iterations)
            # Count a success only if it really is one: within the limits and at the target.
            R, p = solver.kin.fk(res.q[None])
            real = float(ik.Task(target, order).error(R, p)[0])
            ok += int(res.success and bool(solver.kin.within_limits(res.q)) and real <= 0.01)
            if case < n_base:
                t0 = time.perf_counter()
                _, status, _ = original_ik(q_seed[0], target, dof, arm)
                base_times.append(time.perf_counter() - t0)
                base_ok += int(status == 0)
        rate = 100.0 * ok / n
        base_rate = 100.0 * base_ok / n_base
        base_name = f"original algorithm ({n_base} targets)"
        ms = [t * 1e3 for t in times]
        base_ms = [t * 1e3 for t in base_times]
        rows += [
            Row("ik", f"{dof}-DOF success ({n} targets)", rate, "%", base_name, base_rate, ">= 99.5 %",
                rate >= 99.5, higher_is_better=True),
            Row("ik", f"{dof}-DOF median time per solve", median(ms), "ms", base_name, median(base_ms), "<= 2 ms",
                median(ms) <= 2.0),
            Row("ik", f"{dof}-DOF p99 time per solve", percentile(ms, 99), "ms", base_name, percentile(base_ms, 99),
                "<= 20 ms", percentile(ms, 99) <= 20.0),
            Row("ik", f"{dof}-DOF median iterations", float(median([float(i) for i in iters])), "it"),
        ]
    return rows


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        base = "" if row.baseline_value is None else f"  (baseline {row.baseline_value:.3g} {row.unit})"
        verdict = "" if row.passed is None else ("  ok" if row.passed else "  MISSED")
        print(f"{row.name:<36} {row.value:10.3f} {row.unit}{base}  {row.target}{verdict}")
