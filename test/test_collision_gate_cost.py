"""The collision gate's own cost per frame (issue 26 item 5): the braking look-ahead and the approach bisection check
their poses a few per call into the C screen, with the previous output's configurations made once a frame, and
decide exactly as checking every pose on its own did.

``OnePoseAtATime`` restates the gate's checks as they were before (every configuration built and checked on its
own, one call per pose of a braking path): the reference the decisions must equal and the cost must beat, measured
in the same run, frame by frame in lockstep, on the bench's paper scenes (``bench/bench_collision.py``)."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import mds_ach as mds
from mds_ach.kinematics.collision import load_model
from mds_ach.nodes import gate as gate_module
from mds_ach.nodes.gate import Decision, Gate, GateConfig, Observed, joint_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.bench_collision import (  # noqa: E402  (bench/: no package)
    TABLE,
    hand_over_table,
    hands_together,
    random_stream,
    scene_stream,
)

ZERO_MODE = np.zeros(mds.MDS_JOINT_COUNT, dtype=np.int16)
LAG = 4  # frames the measured pose is behind the output, as in the bench


class OnePoseAtATime(Gate):
    """The gate's checks as they were before they were batched: configurations built one candidate at a time, the
    braking path judged pose by pose with one ``check_many`` call each, the baseline rebuilt at every comparison."""

    def _configs(self, x: np.ndarray, pos: np.ndarray | None,
                 choices: Iterable[gate_module.Choice] | None = None) -> dict[gate_module.Choice, np.ndarray]:
        q_ref = np.asarray(x, dtype=float).take(self.model.addresses)
        if pos is None:
            return {(False, False, False): q_ref}
        measured = pos.take(self.model.addresses)
        q_pos = np.where(np.isnan(measured), q_ref, measured)
        if choices is None:
            apart = tuple((gate_module._UNIT_COLUMNS & (np.abs(q_pos - q_ref) > gate_module.SAME_POSE))
                          .any(axis=1).tolist())
            choices = gate_module._CHOICES_FOR[apart]
        return {c: np.where(gate_module._CHOICE_MASK[gate_module._CHOICES.index(c)], q_pos, q_ref) for c in choices}

    def _analyze(self, x: np.ndarray, pos: np.ndarray | None,
                 new_only: bool = False) -> tuple[dict[gate_module.Choice, Any], list[tuple[gate_module.Choice, Any]]]:
        cfg = self._configs(x, pos)
        res = dict(zip(cfg, self._check(list(cfg.values())), strict=True))
        hit = [c for c, r in res.items() if r.collides]
        if not hit:
            return res, []
        base = self._configs(self.ref, pos, hit)
        changed = [c for c in hit if not np.array_equal(cfg[c], base[c])]
        before = dict(zip(changed, self._check([base[c] for c in changed]), strict=True))
        blocking = []
        for c in changed:
            old = {(k.a, k.b): k.clearance for k in before[c].contacts}
            new = [k for k in res[c].contacts if (k.a, k.b) not in old]
            kept = [k for k in res[c].contacts if (k.a, k.b) in old]
            closer = sum(k.clearance - old[(k.a, k.b)] for k in kept) < -gate_module.CLOSER
            blocking += [(c, k) for k in new]
            if closer and not new_only:
                blocking += [(c, k) for k in kept if k.clearance < old[(k.a, k.b)]]
        return res, blocking

    def _check(self, qs: Any) -> list[Any]:
        keys = [q.tobytes() for q in qs]
        todo = {k: q for k, q in zip(keys, qs, strict=True) if k not in self._cache}
        if todo:
            self._cache.update(zip(todo, self.model.check_many(np.array(list(todo.values()))), strict=True))
        return [self._cache[k] for k in keys]

    def _blocks(self, x: np.ndarray, pos: np.ndarray | None, arms: Iterable[str],
                dt: float) -> list[tuple[gate_module.Choice, Any]]:
        blocking = self._analyze(x, pos)[1]
        if blocking:
            return blocking
        h = min(dt, self.config.input_period)
        ext = []
        reach = 0.0
        for arm in arms if h > 0 else ():
            idx = gate_module.UNIT_ADDRESSES[arm]
            d = x[idx] - self.ref[idx]
            fastest = float(np.abs(d).max())
            if fastest > 0:
                k = fastest / (2.0 * self.config.brake_accel * h * h)
                ext.append((idx, d * k))
                reach = max(reach, fastest * k)
        n = math.ceil(reach / gate_module.AHEAD_STEP) if ext else 0
        for step in range(1, n + 1):
            y = x.copy()
            for idx, e in ext:
                y[idx] = np.minimum(np.maximum(x[idx] + e * (step / n), self.lower[idx]), self.upper[idx])
            blocking = self._analyze(y, pos, new_only=True)[1]
            if blocking:
                return blocking
        return []


def same_decision(a: Decision, b: Decision) -> bool:
    def contacts(r: Any) -> list[tuple[Any, ...]]:
        return [(c.a, c.b, c.group_a, c.group_b, c.part_a, c.part_b, c.clearance) for c in r.contacts]

    return (np.array_equal(a.ref, b.ref) and np.array_equal(a.mode, b.mode)
            and contacts(a.result) == contacts(b.result) and contacts(a.contacts) == contacts(b.contacts)
            and (a.held, a.refused, a.overridden, a.releasing, a.escaping, a.measured, a.stopped)
            == (b.held, b.refused, b.overridden, b.releasing, b.escaping, b.measured, b.stopped))


def lockstep(refs: np.ndarray, measured: bool = True, passes: int = 1) -> dict[str, Any]:
    """Both gates on the same stream, frame by frame (the measured pose ``LAG`` frames behind the output): every
    decision and report compared; per frame the thread CPU time of each (the smallest of ``passes``) and the calls
    into the C screen."""
    out: dict[str, Any] = {"cpu": {}, "calls": {}, "rows": {}}
    for _ in range(passes):
        gates: dict[str, Gate] = {}
        counts: dict[str, list[int]] = {}
        for name, cls in (("gate", Gate), ("reference", OnePoseAtATime)):
            model = load_model(world=TABLE)
            lower, upper = joint_limits(model)
            inner, calls = model.check_many, counts.setdefault(name, [0, 0])

            def counted(qs: np.ndarray, inner: Any = inner, calls: list[int] = calls) -> list[Any]:
                calls[0] += 1
                calls[1] += len(qs)
                return inner(qs)

            model.check_many = counted  # type: ignore[method-assign]
            gates[name] = cls(model, GateConfig(), refs[0], ZERO_MODE, 0.0, lower, upper)
        cpu: dict[str, list[float]] = {name: [] for name in gates}
        frame_calls: dict[str, list[int]] = {name: [] for name in gates}
        frame_rows: dict[str, list[int]] = {name: [] for name in gates}
        outputs = [refs[0]]
        for frame, ref in enumerate(refs):
            now = len(outputs) * 0.025
            seen = Observed(outputs[max(0, len(outputs) - 1 - LAG)], now, now) if measured else None
            decided = {}
            for name, gate in gates.items():
                before = list(counts[name])
                t0 = time.thread_time()
                decided[name] = gate.process(ref, ZERO_MODE, now, seen)
                cpu[name].append(time.thread_time() - t0)
                frame_calls[name].append(counts[name][0] - before[0])
                frame_rows[name].append(counts[name][1] - before[1])
            assert same_decision(decided["gate"], decided["reference"]), f"frame {frame}: decisions differ"
            assert bytes(gates["gate"].report(now)) == bytes(gates["reference"].report(now)), f"frame {frame}: report"
            outputs.append(decided["gate"].ref)
        for name in gates:
            t = np.array(cpu[name])
            out["cpu"][name] = t if name not in out["cpu"] else np.minimum(out["cpu"][name], t)
            out["calls"][name], out["rows"][name] = np.array(frame_calls[name]), np.array(frame_rows[name])
    return out


@pytest.fixture(scope="module")
def scenes() -> dict[str, np.ndarray]:
    model = load_model(world=TABLE)
    lower, upper = joint_limits(model)
    return {"hands together": scene_stream(model, hands_together(model, 300), lower, upper, 2000),
            "hand over table": scene_stream(model, hand_over_table(model, 300), lower, upper, 2000)}


@pytest.mark.parametrize("scene", ["hands together", "hand over table"])
def test_batched_checks_decide_as_one_pose_at_a_time(scenes: dict[str, np.ndarray], scene: str) -> None:
    run = lockstep(scenes[scene][:800])
    calls = run["calls"]
    # the approach frames: one call per pose before, a few poses per call now
    assert calls["gate"].max() < calls["reference"].max()
    assert calls["gate"].sum() < calls["reference"].sum()


@pytest.mark.parametrize("measured", [True, False])
def test_batched_checks_decide_as_one_pose_at_a_time_on_random_ramps(measured: bool) -> None:
    model = load_model(world=TABLE)
    lockstep(random_stream(model, *joint_limits(model), 600, np.random.default_rng(5)), measured=measured)


def test_hands_together_costs_far_less_cpu_per_frame_than_one_pose_at_a_time(scenes: dict[str, np.ndarray]) -> None:
    """The bench's hands-together stream (2000 frames, approach frames at its p99): the gate's thread CPU time per
    frame at p99 against the one-pose-at-a-time reference's on the same frames, in the same run (interleaved frame
    by frame, the smallest of 3 passes per frame: a busy machine slows both alike, so the ratio holds where an
    absolute bound would not). Measured 0.6-0.7x; the same checks one pose at a time are 1.0x by construction. The
    deterministic part: at p99 a frame makes at most half the calls into the C screen, for at most 10 % more
    configurations (the poses of a braking path checked past the one that blocks, in the same call)."""
    run = lockstep(scenes["hands together"], passes=3)
    cpu, calls, rows = run["cpu"], run["calls"], run["rows"]
    assert np.percentile(calls["gate"], 99) <= 0.5 * np.percentile(calls["reference"], 99)
    assert rows["gate"].sum() <= 1.1 * rows["reference"].sum()
    ratio = np.percentile(cpu["gate"], 99) / np.percentile(cpu["reference"], 99)
    assert ratio < 0.85, (f"gate p99 {np.percentile(cpu['gate'], 99) * 1e3:.3f} ms CPU, one pose at a time "
                          f"{np.percentile(cpu['reference'], 99) * 1e3:.3f} ms")
