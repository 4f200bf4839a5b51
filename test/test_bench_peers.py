"""`make bench` measures ours against the field's peers, and they never leak into the runtime.

The peers (Pinocchio + coal, iceoryx2, ...) come from bench/requirements.txt, which only `make bench` installs; the
collision peer must answer on exactly our primitives and pairs (else the comparison is not like for like).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bench import bench_collision  # noqa: E402  (bench/ is not an installed package)


def _names(path: Path) -> list[str]:
    out = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(re.split(r"[=<>!~\[; ]", line, maxsplit=1)[0].lower())
    return out


def test_bench_peers_are_pinned_sorted_and_not_runtime_dependencies() -> None:
    bench = _names(REPO / "bench/requirements.txt")
    assert {"pin", "coal", "iceoryx2"} <= set(bench)
    assert bench == sorted(bench), "keep bench/requirements.txt sorted (several engineers add peers)"
    assert all("==" in line for line in (REPO / "bench/requirements.txt").read_text().splitlines()
               if line.strip() and not line.startswith("#"))
    runtime = set(_names(REPO / "requirements.txt"))
    assert not runtime & set(bench), "a benchmark peer must not be a runtime dependency"
    makefile = (REPO / "Makefile").read_text()
    assert "-r bench/requirements.txt" in makefile
    assert re.search(r"^bench: \$\(BENCH_STAMP\)", makefile, re.M)


def test_bench_scenes_exercise_contacts() -> None:
    from mds_ach.kinematics.collision import load_model

    model = load_model(world=bench_collision.TABLE)
    for scene in (bench_collision.hands_together, bench_collision.hand_over_table):
        qs = scene(model, 100)
        assert np.all((qs >= model.lower) & (qs <= model.upper))
        hits = sum(model.check(q).collides for q in qs)
        assert 10 < hits < 100


def test_pinocchio_coal_peer_answers_on_our_primitives_and_pairs() -> None:
    pytest.importorskip("pinocchio", reason="Pinocchio + coal come with `make bench` (bench/requirements.txt)")
    from mds_ach.kinematics.collision import load_model

    model = load_model(world=bench_collision.TABLE)
    peer = bench_collision.PinocchioCoal(model)
    rng = np.random.default_rng(2)
    qs = np.vstack([rng.uniform(model.lower, model.upper, size=(100, len(model.lower))),
                    bench_collision.hands_together(model, 50), bench_collision.hand_over_table(model, 50)])
    for q in qs:
        ours = model.check(q)
        peer.pair_list(q)
        assert peer.pairs() == ours.pairs
        assert peer.collides(q) == model.collides(q) == ours.collides
