"""IK benchmark: success rate and time per solve for 3-6 DOF tasks, against the original algorithm.

Targets are reachable by construction: the tool pose of a random joint vector within the URDF limits.
Each solve starts from another random joint vector (the "current pose"). Both solvers get the same
targets and seeds; the baseline runs on a subset because it can take 1000 slow iterations per failure.
The measurement runs in a fresh child process at nice -20 when allowed (as the robot's IK node would
run); on a shared, loaded machine the wall-clock times are still noisier.

Baseline = the original ``mds_ik.getIK`` algorithm re-implemented: forward-difference Jacobian
(dθ = 0.01) of the Z-Y-X components, ``numpy.linalg.pinv``, a fixed task-space step of 0.01 toward
the target, the original clamps, success at ||e|| <= 0.01, at most 1000 iterations. Its FK is our
batched numpy FK (7 poses per Jacobian in one call), so it is faster than the 2015 code was.

Run: ``python -m bench --only bench_ik [--quick]`` or ``python -m bench.bench_ik [--quick]``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import Row, median, percentile
from mds_ach import ik
from mds_ach.kinematics.model import arm_kinematics, euler_zyx

REPO = Path(__file__).resolve().parent.parent

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


def measure(dof: int, n: int, n_base: int, seed: int) -> dict[str, list[float]]:
    """Solve ``n`` targets (the first ``n_base`` also with the original algorithm); times in ms."""
    rng = np.random.default_rng(seed)
    order = ik.DOF_ORDERS[dof]
    out: dict[str, list[float]] = {"ms": [], "cpu_ms": [], "iterations": [], "ok": [], "base_ms": [], "base_ok": []}
    for case in range(n):
        arm = ("left", "right")[case % 2]
        solver = ik.solver(arm)
        _, q_seed, T = _cases(arm, 1, rng)
        target = ik.getPosCurrentFromOrder(T[0], order)
        t0, c0 = time.perf_counter(), time.thread_time()
        res = solver.solve(target, order, q_seed[0])
        out["ms"].append((time.perf_counter() - t0) * 1e3)
        out["cpu_ms"].append((time.thread_time() - c0) * 1e3)
        out["iterations"].append(res.iterations)
        # Count a success only if it really is one: within the limits and at the target.
        R, p = solver.kin.fk(res.q[None])
        real = float(ik.Task(target, order).error(R, p)[0])
        out["ok"].append(float(res.success and bool(solver.kin.within_limits(res.q)) and real <= 0.01))
        if case < n_base:
            t0 = time.perf_counter()
            _, status, _ = original_ik(q_seed[0], target, dof, arm)
            out["base_ms"].append((time.perf_counter() - t0) * 1e3)
            out["base_ok"].append(float(status == 0))
    return out


def _child(quick: bool) -> None:
    """Measure in this (fresh) process at raised priority and print JSON: what a robot's process would get."""
    try:
        os.nice(-20)
    except OSError:
        pass
    n, n_base = (100, 12) if quick else (500, 60)
    ik.solver("left").solve([0.3, 0.2, 0.0], ik.DOF_ORDERS[3])  # warm-up: first-call imports and caches
    print(json.dumps({dof: measure(dof, n, n_base, 20150101 + dof) for dof in (3, 4, 5, 6)}))


def run(quick: bool = False) -> list[Row]:
    print(f"[bench_ik] load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cpus "
          "(times on a shared, loaded machine are noisier)", file=sys.stderr)
    cmd = [sys.executable, "-m", "bench.bench_ik", "--child"] + (["--quick"] if quick else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, cwd=REPO, check=True)
    data = json.loads(proc.stdout)
    rows: list[Row] = []
    for dof in (3, 4, 5, 6):
        d = data[str(dof)]
        n, n_base = len(d["ms"]), len(d["base_ms"])
        rate = 100.0 * sum(d["ok"]) / n
        base_rate = 100.0 * sum(d["base_ok"]) / n_base
        base_name = f"original algorithm ({n_base} targets)"
        ms, base_ms = d["ms"], d["base_ms"]
        rows += [
            Row("ik", f"{dof}-DOF success ({n} targets)", rate, "%", base_name, base_rate, ">= 99.5 %",
                rate >= 99.5, higher_is_better=True),
            Row("ik", f"{dof}-DOF median time per solve", median(ms), "ms", base_name, median(base_ms), "<= 2 ms",
                median(ms) <= 2.0),
            Row("ik", f"{dof}-DOF p99 time per solve", percentile(ms, 99), "ms", base_name, percentile(base_ms, 99),
                "<= 20 ms", percentile(ms, 99) <= 20.0),
            Row("ik", f"{dof}-DOF median CPU time per solve", median(d["cpu_ms"]), "ms"),  # less load-dependent
            Row("ik", f"{dof}-DOF median iterations", float(median(d["iterations"])), "it"),
        ]
    return rows


if __name__ == "__main__":
    if "--child" in sys.argv:
        _child("--quick" in sys.argv)
    else:
        for row in run(quick="--quick" in sys.argv):
            base = "" if row.baseline_value is None else f"  (baseline {row.baseline_value:.3g} {row.unit})"
            verdict = "" if row.passed is None else ("  ok" if row.passed else "  MISSED")
            print(f"{row.name:<36} {row.value:10.3f} {row.unit}{base}  {row.target}{verdict}")
