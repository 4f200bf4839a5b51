"""Collision-gate benchmark: time to decide whether one reference is safe (full self + world check).

Workload: random joint vectors within the URDF limits (about a third of them collide) with the default
collision config and a table in front of the robot, so every check covers arm-arm, arm-body, arm-head and
arm-world pairs. Measured:

* ``check``: ``CollisionModel.check`` (batched numpy FK of the 17 joint frames, bounding-sphere broad phase,
  python-fcl narrow phase on the close pairs);
* ``gate``: ``Gate.process`` on the same references (validation, speed bound, check, hold logic), i.e. what
  the collision node spends per mds-ref-smooth frame;
* ``gate with the measured pose``: the same, with a measured pose that lags the reference by 4 frames (0.1 s,
  as the robot follows), so every unit differs and all 8 {reference, measured} configurations are checked.

Baseline (same run, same configurations): the straightforward way - yourdfpy scene-graph FK
(``update_cfg`` + ``get_transform`` per collision link) and fresh fcl objects for every primitive, then
``fcl.collide`` on every pair. Both answers are compared on every configuration.

Targets (issue 5): median <= 0.5 ms, p99 <= 2 ms for the full check; one daemon tick is 100 ms. With the
measured pose (issue 15): median <= 2 ms, p99 <= 5 ms, well within one filter period (25 ms).
Run: ``python -m bench --only bench_collision [--quick]`` or ``python -m bench.bench_collision``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from bench.common import Row, median, percentile

TABLE = {"objects": [{"name": "table", "shape": "box", "size": [0.6, 1.4, 0.04], "xyz": [0.6, 0.0, -0.42]}]}


class NaiveChecker:
    """The baseline: yourdfpy FK of the scene graph and new fcl objects on every check, all pairs."""

    def __init__(self, model) -> None:
        import fcl
        import yourdfpy

        from mds_ach.kinematics.collision import _fcl_geometry, inflate
        from mds_ach.paths import urdf_path

        self.fcl = fcl
        self.urdf = yourdfpy.URDF.load(str(urdf_path()), load_meshes=False, build_collision_scene_graph=False)
        self.model = model
        pad = model.margin / 2
        self.geoms = [_fcl_geometry(p.kind, inflate(p.kind, p.size, pad)) for p in model.primitives]

    def check(self, q: np.ndarray) -> frozenset[tuple[str, str]]:
        fcl, model = self.fcl, self.model
        self.urdf.update_cfg(dict(zip(model.joint_names, q, strict=True)))
        objects = []
        for prim, geom in zip(model.primitives, self.geoms, strict=True):
            if prim.group == "world":
                T = prim.offset
            else:
                link = self.urdf.get_transform(prim.link)
                owner_frame_to_link = model.tree.owner(prim.link)[1]
                # prim.offset = (fixed chain from the owning joint frame to the link) @ (collision origin)
                T = link @ np.linalg.inv(owner_frame_to_link) @ prim.offset
            objects.append(fcl.CollisionObject(geom, fcl.Transform(T[:3, :3], T[:3, 3])))
        hits = set()
        for i, j in model.pairs:
            if fcl.collide(objects[i], objects[j]) > 0:
                hits.add((model.primitives[i].name, model.primitives[j].name))
        return frozenset(hits)


def _times(fn, items) -> list[float]:
    out = []
    for item in items:
        t0 = time.perf_counter()
        fn(item)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def run(quick: bool = False) -> list[Row]:
    import mds_ach as mds
    from mds_ach.kinematics.collision import load_model
    from mds_ach.nodes.collision import Gate, GateConfig, Observed, joint_limits

    model = load_model(world=TABLE)
    rng = np.random.default_rng(5)
    n = 300 if quick else 3000
    n_base = 60 if quick else 400
    qs = rng.uniform(model.lower, model.upper, size=(n, len(model.joint_names)))

    for q in qs[:50]:  # warm-up (allocations, fcl first calls)
        model.check(q)
    fast = _times(model.check, qs)
    colliding = sum(model.check(q).collides for q in qs)

    naive = NaiveChecker(model)
    for q in qs[:5]:
        naive.check(q)
    base = _times(naive.check, qs[:n_base])
    mismatches = sum(naive.check(q) != model.check(q).pairs for q in qs[:n_base])
    if mismatches:
        print(f"bench_collision: {mismatches} of {n_base} configurations disagree with the baseline",
              file=sys.stderr)

    # The gate on a realistic stream: the filter's 1.57 rad/s ramps (40 Hz) between random targets inside the
    # gate's limits; some of them collide, so holds and the per-arm re-check are part of the measurement.
    lower, upper = joint_limits(model)
    lo, hi = lower[model.addresses], upper[model.addresses]
    stream: list[np.ndarray] = []
    q = rng.uniform(lo, hi)
    while len(stream) < n:
        goal = rng.uniform(lo, hi)
        steps = max(1, int(np.ceil(np.abs(goal - q).max() / (1.57 / 40))))
        stream.extend(q + (goal - q) * k / steps for k in range(1, steps + 1))
        q = goal
    refs = np.zeros((n, mds.MDS_JOINT_COUNT))
    refs[:, model.addresses] = np.array(stream[:n])
    zero_mode = np.zeros(mds.MDS_JOINT_COUNT, dtype=np.int16)
    gate = Gate(model, GateConfig(), refs[0], zero_mode, 0.0, lower, upper)
    clock = iter(np.arange(1, n + 1) * 0.025)
    gate_ms = _times(lambda r: gate.process(r, zero_mode, next(clock)), refs)
    gate = Gate(model, GateConfig(), refs[0], zero_mode, 0.0, lower, upper)
    outputs = [refs[0]]

    def with_measured(r: np.ndarray) -> None:
        now = len(outputs) * 0.025
        lagging = outputs[max(0, len(outputs) - 5)]  # where the robot is: 4 frames behind its reference
        outputs.append(gate.process(r, zero_mode, now, Observed(lagging, now, now)).ref)

    measured_ms = _times(with_measured, refs)

    group = "collision"
    base_name = f"yourdfpy FK + fcl rebuild, all pairs (n={n_base})"
    return [
        Row(group, f"full check median ({len(model.pairs)} pairs, n={n}, {colliding} hit)", median(fast), "ms",
            base_name, median(base), "<= 0.5 ms", median(fast) <= 0.5),
        Row(group, "full check p99", percentile(fast, 99), "ms", base_name, percentile(base, 99), "<= 2 ms",
            percentile(fast, 99) <= 2.0),
        Row(group, "gate decision per frame median", median(gate_ms), "ms", base_name, median(base),
            "<= 0.5 ms", median(gate_ms) <= 0.5),
        Row(group, "gate decision per frame p99", percentile(gate_ms, 99), "ms", base_name, percentile(base, 99),
            "<= 2 ms", percentile(gate_ms, 99) <= 2.0),
        Row(group, "gate with the measured pose (8 configurations) median", median(measured_ms), "ms", base_name,
            median(base), "<= 2 ms", median(measured_ms) <= 2.0),
        Row(group, "gate with the measured pose p99", percentile(measured_ms, 99), "ms", base_name,
            percentile(base, 99), "<= 5 ms", percentile(measured_ms, 99) <= 5.0),
        Row(group, "answers equal to the baseline", float(n_base - mismatches), f"of {n_base}", "", None,
            f"{n_base} of {n_base}", mismatches == 0, higher_is_better=True),
    ]


if __name__ == "__main__":
    from bench.__main__ import main

    raise SystemExit(main(["--only", "bench_collision", *sys.argv[1:]]))
