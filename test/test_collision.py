"""Collision model: primitives from the URDF, FK against independent implementations, broad phase vs exhaustive
fcl, margins, world objects, and a known colliding pair that must always be reported."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import mds_ach as mds
from mds_ach.kinematics import collision
from mds_ach.kinematics.model import load_model as load_kinematics
from mds_ach.paths import config_path, urdf_path
from mds_ach.robot.joints import MODEL_JOINTS

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from bench.bench_collision import half_dims, project_onto  # noqa: E402  (bench/ is not an installed package)

HOME = {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2, "LEP": -1.25,
        "LSY": -0.25, "LWR": -0.28}


@pytest.fixture(scope="module")
def model() -> collision.CollisionModel:
    return collision.load_model()


def q_of(**joints: float) -> np.ndarray:
    q = np.zeros(len(MODEL_JOINTS))
    for name, value in joints.items():
        q[MODEL_JOINTS.index(name)] = value
    return q


def random_configs(model: collision.CollisionModel, n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(model.lower, model.upper, size=(n, len(model.lower)))


def index(model: collision.CollisionModel, name: str) -> int:
    return [p.name for p in model.primitives].index(name)


# --------------------------------------------------------------------------------------------- primitives


def test_every_urdf_collision_element_becomes_a_primitive(model: collision.CollisionModel) -> None:
    kin = load_kinematics(urdf_path())  # independent stdlib parse of the same file
    expected = {(name, g.kind, tuple(round(s, 9) for s in g.size))
                for name, link in kin.links.items() for g in link.collisions}
    ours = {(p.link, p.kind, tuple(round(s, 9) for s in p.size)) for p in model.primitives
            if p.group != "world" and not p.name.endswith(("upper_arm", "lower_arm"))}
    assert ours == expected
    assert len(expected) >= 16


def test_parts_and_groups(model: collision.CollisionModel) -> None:
    by_name = {p.name: p for p in model.primitives}
    for side, prefix in (("left", "L"), ("right", "R")):
        for link, part in (("hand", "HAND"), ("wrist", "WRIST"), ("forearm", "FOREARM"), ("elbow", "ELBOW"),
                           ("shoulder", "SHOULDER")):
            p = by_name[f"{side}_{link}_link"]
            assert p.group == side
            assert p.part == getattr(mds, f"COLLIDE_{prefix}_{part}")
    assert by_name["left_upper_arm"].part == mds.COLLIDE_L_SHOULDER
    assert by_name["right_lower_arm"].part == mds.COLLIDE_R_FOREARM
    assert by_name["head_link"].group == "head" and by_name["backpack_link"].group == "body"


def test_pairs_cover_arm_arm_body_and_head_but_not_neighbours(model: collision.CollisionModel) -> None:
    names = {tuple(sorted((model.primitives[i].name, model.primitives[j].name))) for i, j in model.pairs}
    assert ("left_hand_link", "right_hand_link") in names
    assert ("head_link", "left_hand_link") in names
    assert ("backpack_link", "right_elbow_link") in names
    assert ("left_hand_link", "left_shoulder_link") in names  # same arm, listed in same_arm_pairs
    assert ("left_hand_link", "left_wrist_link") not in names  # neighbours touch by construction
    assert ("left_shoulder_link", "torso") not in names  # ignore_pairs
    assert not any(model.primitives[i].group not in ("left", "right") and model.primitives[j].group not in (
        "left", "right") for i, j in model.pairs)


# --------------------------------------------------------------------------------------------- kinematics


def test_primitive_poses_match_the_kinematics_module(model: collision.CollisionModel) -> None:
    kin = load_kinematics(urdf_path())
    for q in random_configs(model, 25):
        poses = model.primitive_poses(q)
        links = kin.link_poses(dict(zip(MODEL_JOINTS, q, strict=True)))
        for k, p in enumerate(model.primitives):
            if p.group == "world" or p.name.endswith(("upper_arm", "lower_arm")):
                continue
            expected = links[p.link] @ kin.links[p.link].collisions[0].origin
            np.testing.assert_allclose(poses[k], expected, atol=1e-12)


def test_primitive_poses_match_yourdfpy(model: collision.CollisionModel) -> None:
    import yourdfpy

    urdf = yourdfpy.URDF.load(str(urdf_path()), load_meshes=False, build_collision_scene_graph=False)
    for q in random_configs(model, 5, seed=7):
        urdf.update_cfg(dict(zip(MODEL_JOINTS, q, strict=True)))
        poses = model.primitive_poses(q)
        for k, p in enumerate(model.primitives):
            if p.group == "world" or p.name.endswith(("upper_arm", "lower_arm")):
                continue
            link = urdf.link_map[p.link]
            expected = urdf.get_transform(p.link) @ link.collisions[0].origin
            np.testing.assert_allclose(poses[k], expected, atol=1e-9)


def test_hand_follows_the_original_ik_chain(model: collision.CollisionModel) -> None:
    """Spec e.1: LSP = -pi/2 raises the left arm forward; the hand frame is 0.1046875 below the wrist."""
    poses = model.primitive_poses(q_of(LSP=-np.pi / 2))
    torso = model.tree.link_pose("torso", np.zeros(len(MODEL_JOINTS)))
    hand = np.linalg.inv(torso) @ poses[index(model, "left_hand_link")]
    reach = 0.282575 + 0.3127375 + 0.1046875 + 0.025
    np.testing.assert_allclose(hand[:3, 3], [reach, 0.24551, 0.02], atol=1e-9)  # local +x offset turns up


# --------------------------------------------------------------------------------------------- checking


def test_home_pose_is_free_and_hanging_arms_hit_the_lower_body(model: collision.CollisionModel) -> None:
    assert not model.check(q_of(**HOME)).collides
    hanging = model.check(np.zeros(len(MODEL_JOINTS)))
    assert ("box1_link", "left_hand_link") in hanging.pairs and hanging.arms == {"left", "right"}


def test_broad_phase_never_drops_a_collision(model: collision.CollisionModel) -> None:
    configs = random_configs(model, 400, seed=3)
    colliding = 0
    for q in configs:
        fast, full = model.check(q), model.check_exhaustive(q)
        assert fast.pairs == full.pairs
        colliding += fast.collides
    assert 40 < colliding < 400  # the sample exercises both outcomes


def test_batched_check_answers_like_single_checks(model: collision.CollisionModel) -> None:
    """``check_many`` (one batched FK and broad phase for the gate's several configurations per reference) gives
    each configuration exactly the answer of ``check``, clearances included."""
    configs = random_configs(model, 200, seed=7)
    batched = model.check_many(configs)
    assert len(batched) == len(configs) and sum(r.collides for r in batched) > 20
    for q, many in zip(configs, batched, strict=True):
        assert many == model.check(q)


def test_contact_clearance_is_the_signed_distance_of_the_shapes() -> None:
    """A world ball at a known gap from the left hand sphere: a contact's clearance is the gap between the real
    (un-inflated) surfaces, negative when they overlap (how far one is pushed into the other)."""
    base = collision.load_model(world={})
    q = q_of(**HOME)
    hand = base.primitive_poses(q)[index(base, "left_hand_link"), :3, 3]
    torso = base.tree.link_pose("torso", np.zeros(len(MODEL_JOINTS)))
    for gap in (0.015, 0.0, -0.03):
        local = np.linalg.inv(torso) @ np.append(hand + np.array([0.0, 0.0, 0.15 + gap]), 1.0)
        m = collision.load_model(world={"objects": [{"name": "ball", "shape": "sphere", "radius": 0.05,
                                                     "xyz": local[:3].tolist()}]})
        (contact,) = [c for c in m.check(q).contacts if {c.a, c.b} == {"left_hand_link", "world:ball"}]
        assert contact.clearance == pytest.approx(gap, abs=1e-6)


def test_known_colliding_pair_is_always_reported(model: collision.CollisionModel) -> None:
    """Hand spheres (r 0.1 each): reported exactly when the centres are closer than 0.2 m + margin.

    The reference answer is computed here from the sphere centres, independently of fcl; configurations are
    sampled with both hands in front of the chest so that many of them touch.
    """
    rng = np.random.default_rng(11)
    li, ri = index(model, "left_hand_link"), index(model, "right_hand_link")
    hits = 0
    for _ in range(1500):
        q = q_of(**HOME)
        for side, sign in (("L", 1.0), ("R", -1.0)):
            q[MODEL_JOINTS.index(f"{side}SP")] = rng.uniform(-1.6, -0.6)
            q[MODEL_JOINTS.index(f"{side}SR")] = sign * rng.uniform(0.0, 0.4)
            q[MODEL_JOINTS.index(f"{side}SY")] = -sign * rng.uniform(0.3, 1.0)
            q[MODEL_JOINTS.index(f"{side}EP")] = rng.uniform(-2.0, -1.0)
        poses = model.primitive_poses(q)
        dist = np.linalg.norm(poses[li, :3, 3] - poses[ri, :3, 3])
        reported = ("left_hand_link", "right_hand_link") in model.check(q).pairs
        if abs(dist - (0.2 + model.margin)) < 1e-6:
            continue  # exactly on the boundary: either answer is fine
        assert reported == (dist < 0.2 + model.margin), (q, dist)
        hits += reported
    assert hits > 100


def test_margin_is_the_clearance_between_surfaces() -> None:
    """A world ball placed at a known gap from the left hand sphere (exact geometry: sphere vs sphere)."""
    base = collision.load_model(config=config_path("collision.yaml"), world={})
    q = q_of(**HOME)
    hand = base.primitive_poses(q)[index(base, "left_hand_link"), :3, 3]
    torso = base.tree.link_pose("torso", np.zeros(len(MODEL_JOINTS)))
    for gap, expected in ((0.015, True), (0.025, False), (-0.01, True)):
        centre = hand + np.array([0.0, 0.0, 0.1 + 0.05 + gap])  # above the hand: r_hand 0.1 + r_ball 0.05
        local = np.linalg.inv(torso) @ np.append(centre, 1.0)
        world = {"objects": [{"name": "ball", "shape": "sphere", "radius": 0.05, "xyz": local[:3].tolist()}]}
        m = collision.load_model(world=world)
        assert m.margin == 0.02
        assert (("left_hand_link", "world:ball") in {tuple(sorted(p)) for p in m.check(q).pairs}) == expected, gap
        d = m.distances(q)[("left_hand_link", "world:ball")]
        assert d == pytest.approx(max(gap, 0.0), abs=1e-6)


def test_world_objects_from_config_and_frames() -> None:
    table = {"shape": "box", "size": [0.6, 1.4, 0.04], "xyz": [0.6, 0.0, -0.42]}
    robot_frame = collision.load_model(world={"objects": [{"name": "t", **table}]})
    base_frame = collision.load_model(world={"frame": "base", "objects": [
        {"name": "t", **table, "xyz": [0.6, 0.0, -0.42 + 1.2065]}]})
    k = index(robot_frame, "world:t")
    np.testing.assert_allclose(robot_frame.primitive_poses(np.zeros(17))[k],
                               base_frame.primitive_poses(np.zeros(17))[k], atol=1e-12)
    disabled = collision.load_model(world={"objects": [{"name": "t", "enabled": False, **table}]})
    assert not any(p.group == "world" for p in disabled.primitives)
    # the hand pushed down through the table top collides with it, the home pose does not
    assert not robot_frame.check(q_of(**HOME)).collides
    reach_down = robot_frame.check(q_of(**{**HOME, "LSP": -0.9, "LSR": 0.3, "LEP": -0.4}))
    assert ("left_hand_link", "world:t") in reach_down.pairs


@pytest.mark.parametrize(
    "obj, message",
    [
        ({"name": "a", "shape": "cone", "radius": 1}, "shape must be one of"),
        ({"name": "a", "shape": "box", "size": [1, 1]}, "3 numbers"),
        ({"name": "a", "shape": "sphere"}, "needs 'radius'"),
        ({"name": "a", "shape": "sphere", "radius": -0.1}, "positive"),
        ({"name": "a", "shape": "sphere", "radius": 0.1, "xyz": [0, 0]}, "xyz and rpy"),
        ({"name": "a", "shape": "sphere", "radius": 0.1, "frame": "moon"}, "frame"),
    ],
)
def test_bad_world_objects_are_refused(obj: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        collision.load_model(world={"objects": [obj]})


def test_bad_collision_config_is_refused() -> None:
    with pytest.raises(ValueError, match="margin"):
        collision.load_model(config={"margin": -0.1})
    with pytest.raises(ValueError, match="unknown collide part"):
        collision.load_model(config={"parts": {"left_hand_link": "L_FOOT"}})
    with pytest.raises(ValueError, match="unknown link"):
        collision.load_model(config={"extra_primitives": [{"link": "tail", "shape": "sphere", "radius": 0.1}]})


def test_ignore_pairs_removes_pairs() -> None:
    m = collision.load_model(config={"ignore_pairs": [["left_hand_link", "right_hand_link"]]})
    names = {(m.primitives[i].name, m.primitives[j].name) for i, j in m.pairs}
    assert ("left_hand_link", "right_hand_link") not in names
    assert ("left_hand_link", "right_wrist_link") in names


def test_check_result_summaries(model: collision.CollisionModel) -> None:
    res = model.check(np.zeros(17))
    assert res.collides and res.arms == {"left", "right"}
    assert mds.COLLIDE_L_HAND in res.parts and mds.COLLIDE_R_HAND in res.parts
    assert all(c.part_a == -1 or c.part_b >= 0 for c in res.contacts)


# --------------------------------------------------------------------------------------------- C screen

TABLE = {"objects": [{"name": "table", "shape": "box", "size": [0.6, 1.4, 0.04], "xyz": [0.6, 0.0, -0.42]}]}


def hands_together(model: collision.CollisionModel, n: int, seed: int = 11) -> np.ndarray:
    """Both hands in front of the chest, often touching (the hands-together scene)."""
    rng = np.random.default_rng(seed)
    out = np.tile(q_of(**HOME), (n, 1))
    for side, sign in (("L", 1.0), ("R", -1.0)):
        out[:, MODEL_JOINTS.index(f"{side}SP")] = rng.uniform(-1.6, -0.6, n)
        out[:, MODEL_JOINTS.index(f"{side}SR")] = sign * rng.uniform(0.0, 0.4, n)
        out[:, MODEL_JOINTS.index(f"{side}SY")] = -sign * rng.uniform(0.3, 1.0, n)
        out[:, MODEL_JOINTS.index(f"{side}EP")] = rng.uniform(-2.0, -1.0, n)
    return np.clip(out, model.lower, model.upper)


def hand_over_table(model: collision.CollisionModel, n: int, seed: int = 12) -> np.ndarray:
    """Arms reaching forward and down over a table (the hand-over-table scene): hands, wrists and forearms
    graze, touch or go into the table top."""
    rng = np.random.default_rng(seed)
    out = np.tile(q_of(**HOME), (n, 1))
    for side, sign in (("L", 1.0), ("R", -1.0)):
        out[:, MODEL_JOINTS.index(f"{side}SP")] = rng.uniform(-1.4, -0.2, n)
        out[:, MODEL_JOINTS.index(f"{side}SR")] = sign * rng.uniform(0.0, 0.5, n)
        out[:, MODEL_JOINTS.index(f"{side}SY")] = rng.uniform(-0.6, 0.6, n)
        out[:, MODEL_JOINTS.index(f"{side}EP")] = rng.uniform(-1.6, 0.0, n)
        out[:, MODEL_JOINTS.index(f"{side}WY")] = rng.uniform(-1.0, 1.0, n)
        out[:, MODEL_JOINTS.index(f"{side}WR")] = rng.uniform(-0.8, 0.8, n)
    out[:, MODEL_JOINTS.index("WST")] = rng.uniform(-0.5, 0.5, n)
    return np.clip(out, model.lower, model.upper)


def test_collision_screen_is_built_where_it_can_be() -> None:
    """With a C compiler `make setup` builds the collision screen (the gate's ~50x faster path); a silent
    fallback would hide it."""
    import shutil
    import sysconfig
    from pathlib import Path

    cc = sysconfig.get_config_var("CC")
    if not (shutil.which(cc.split()[0] if cc else "cc")
            and Path(sysconfig.get_paths().get("include", ""), "Python.h").is_file()):
        pytest.skip("no C compiler or Python headers here: the numpy path is the only one")
    assert collision.FAST_AVAILABLE, "mds_ach.kinematics._collfast is not importable: run `make setup`"
    assert collision.load_model()._fast is not None


@pytest.mark.skipif(not collision.FAST_AVAILABLE, reason="mds_ach.kinematics._collfast not built")
@pytest.mark.parametrize("scene", ["random", "hands_together", "hand_over_table"])
def test_c_screen_gives_the_numpy_and_exhaustive_answers(scene: str) -> None:
    """The C screen (exact sphere/box tests, conservative cylinder bounds, pairs proven overlapping skip fcl) and
    the yes/no ``collides`` answer exactly like the numpy broad phase and like fcl on every pair: same pairs in
    the same order, same clearances (within fcl's distance tolerance: the FKs round differently), on 400 random
    configurations with a table and on the hands-together and hand-over-table scenes."""
    fast = collision.load_model(world=TABLE)
    slow = collision.load_model(world=TABLE)
    slow._fast = None
    configs = {"random": lambda: random_configs(fast, 400, seed=5), "hands_together": lambda: hands_together(fast, 300),
               "hand_over_table": lambda: hand_over_table(fast, 300)}[scene]()
    hits = 0
    for q in configs:
        a, b, full = fast.check(q), slow.check(q), slow.check_exhaustive(q)
        assert [(c.a, c.b) for c in a.contacts] == [(c.a, c.b) for c in b.contacts] == \
            [(c.a, c.b) for c in full.contacts], q
        for x, y in zip(a.contacts, b.contacts, strict=True):
            # The numpy path's clearances are python-fcl's, which is off by up to ~0.2 mm near touching (its
            # collide misses small overlaps) and on cylinders; the C path's are exact (see the test below).
            assert x.clearance == pytest.approx(y.clearance, abs=5e-4)
        assert fast.collides(q) == slow.collides(q) == b.collides
        hits += b.collides
    assert 0.1 * len(configs) < hits < len(configs)  # both outcomes are exercised
    if scene == "hand_over_table":
        table_hits = sum(any("world:table" in p for p in fast.check(q).pairs) for q in configs)
        assert table_hits > 20


def _sphere_overlap(poses: np.ndarray, kinds: np.ndarray, dims: np.ndarray, i: int, j: int) -> float | None:
    """Signed distance of a sphere and a solid that overlap it, in numpy: the centre's signed distance to the
    solid (inside: minus the distance to its nearest face) minus the radius. None without a sphere."""
    if kinds[j] == 0:
        i, j = j, i
    if kinds[i] != 0:
        return None
    p = poses[j, :3, :3].T @ (poses[i, :3, 3] - poses[j, :3, 3])
    h = dims[j]
    if kinds[j] == 0:
        inside = float(np.linalg.norm(p)) - h[0]
    elif kinds[j] == 1:
        out = np.maximum(np.abs(p) - h, 0.0)
        inside = float(np.linalg.norm(out)) if out.any() else float((np.abs(p) - h).max())
    else:
        e = np.array([math.hypot(p[0], p[1]) - h[0], abs(p[2]) - h[1]])
        inside = float(np.linalg.norm(np.maximum(e, 0.0))) if (e > 0).any() else float(e.max())
    return inside - dims[i][0]


@pytest.mark.skipif(not collision.FAST_AVAILABLE, reason="mds_ach.kinematics._collfast not built")
def test_c_clearances_equal_an_independent_reference() -> None:
    """The C code's signed distances (closed forms with a sphere, GJK/EPA otherwise), which the gate's clearances
    and escape rule use, equal an independent reference within 1e-6 m on every checked pair of 300 random
    configurations and the two paper scenes: apart shapes, the distance of the closest pair found by
    alternating projections onto the two solids in numpy (never below the C distance, which is certified, and
    at most 1e-6 above it); overlapping boxes and cylinders, python-fcl's penetration depth (its EPA, within
    1e-6 m).
    python-fcl's own distance is not the reference where shapes are apart: on cylinders it is off by up to
    millimetres, and its signed mode by up to a millimetre on spheres (measured with coal, bench_collision);
    overlaps with a sphere are checked against the closed form in numpy (python-fcl's collide misses some)."""
    model = collision.load_model(world=TABLE)
    configs = np.concatenate([random_configs(model, 300, seed=9), hands_together(model, 100, seed=3),
                              hand_over_table(model, 100, seed=4)])
    kind_code = {"sphere": 0, "box": 1, "cylinder": 2}
    kinds = np.array([kind_code[p.kind] for p in model.primitives])
    dims = np.array([half_dims(p) for p in model.primitives])
    apart: list[tuple[np.ndarray, np.ndarray, int, int, float]] = []
    overlapping = checked = 0
    for q in configs:
        poses = model.primitive_poses(q)
        for i, j in model.pairs:
            d = model._signed_distance(poses, i, j)
            checked += 1
            if d < 0:
                overlapping += 1
                reference = _sphere_overlap(poses, kinds, dims, i, j)
                if reference is None:  # boxes and cylinders: python-fcl's EPA
                    reference = model.fcl_signed_distance(poses, i, j)
                assert d == pytest.approx(reference, abs=1e-6), (q, i, j)
            else:
                apart.append((poses[i], poses[j], i, j, d))
    assert overlapping > 300 and len(apart) > 10000, (overlapping, len(apart))
    # every pair apart by less than 5 cm (contacts are within the 2 cm margin) and every 20th of the others
    apart = [a for k, a in enumerate(apart) if a[4] < 0.05 or k % 20 == 0]
    Pi = np.array([a[0] for a in apart])
    Pj = np.array([a[1] for a in apart])
    first, second = np.array([a[2] for a in apart]), np.array([a[3] for a in apart])
    ours = np.array([a[4] for a in apart])
    x = Pj[:, :3, 3].copy()
    for _ in range(5000):  # alternating projections: converge to a closest pair of two disjoint convex solids
        a = project_onto(x, Pi, kinds[first], dims[first])
        step = project_onto(a, Pj, kinds[second], dims[second])
        moved = np.abs(step - x).max()
        x = step
        if moved < 1e-13:
            break
    reference = np.linalg.norm(a - x, axis=1)
    assert np.all(reference >= ours - 1e-9), "a pair of points closer than the C code's certified distance"
    worst = int(np.argmax(reference - ours))
    assert reference[worst] - ours[worst] <= 1e-6, (model.primitives[first[worst]], model.primitives[second[worst]],
                                                    reference[worst], ours[worst])
    assert checked == len(configs) * len(model.pairs)


@pytest.mark.skipif(not collision.FAST_AVAILABLE, reason="mds_ach.kinematics._collfast not built")
def test_c_answers_are_fcls_on_every_pair_where_pairs_barely_touch() -> None:
    """The C path decides a pair itself when it is apart or overlapping by more than SCREEN_EPS (closed forms,
    GJK, and for pairs with a cylinder the un-inflated clearance first: apart beyond sqrt(3) (pad_i + pad_j),
    overlapping within pad_i + pad_j - 2 eps) and leaves the pairs closer to touching to python-fcl, so that both
    round alike. Its pair lists must be those of fcl on every pair also there: where one pair starts to collide
    along the segment between a configuration where fcl finds it apart and one where it finds it colliding
    (bisection to 1e-12 of the segment), and 1e-9 to 1e-5 of the segment either side, where that pair is within
    nanometres to tens of micrometres of touching. The pairs: every box-cylinder and cylinder-cylinder pair that
    collides somewhere in the pool (their decisions go through GJK and the clearance-first rules), and the pairs
    that collide first along random segments (mostly the hands' spheres). fcl judges every pair at the poses of
    the C code's FK: at a boundary itself, fcl's answer flips with the last bit of a pose (the numpy FK's), and
    even between points 1e-9 apart (its GJK stops within ~1e-7 m)."""
    model = collision.load_model(world=TABLE)
    slow = collision.load_model(world=TABLE)
    slow._fast = None
    rng = np.random.default_rng(23)
    pool = np.concatenate([random_configs(model, 150, seed=29), hands_together(model, 60, seed=31),
                           hand_over_table(model, 90, seed=37)])
    kinds = [(model.primitives[i].kind, model.primitives[j].kind) for i, j in model.pairs]

    def hits(q: np.ndarray, pair: int | None) -> bool:
        if pair is None:
            return slow.check(q).collides
        return bool(slow._narrow(slow.primitive_poses(q), [pair]).contacts)

    pool_hits = np.array([[c.a, c.b] for q in pool for c in slow.check(q).contacts])
    segments: list[tuple[np.ndarray, np.ndarray, int | None]] = []
    for k, (i, j) in enumerate(model.pairs):
        if "sphere" in kinds[k] or "cylinder" not in kinds[k]:
            continue
        names = [model.primitives[i].name, model.primitives[j].name]
        if not ((pool_hits[:, 0] == names[0]) & (pool_hits[:, 1] == names[1])).any():
            continue
        verdict = np.array([hits(q, k) for q in pool])
        segments.append((pool[rng.choice(np.flatnonzero(~verdict))], pool[rng.choice(np.flatnonzero(verdict))], k))
    assert len(segments) >= 10, len(segments)
    any_hit = np.array([hits(q, None) for q in pool])
    segments += [(pool[rng.choice(np.flatnonzero(~any_hit))], pool[rng.choice(np.flatnonzero(any_hit))], None)
                 for _ in range(30)]
    compared = decided_by_c = 0
    poses = np.zeros((len(model.primitives), 4, 4))
    for a, b, pair in segments:
        lo, hi = 0.0, 1.0  # a + t (b - a): apart at lo, colliding at hi
        while hi - lo > 1e-12:
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if hits(a + mid * (b - a), pair) else (mid, hi)
        for t in (lo, hi, *(hi + s * d for d in (1e-9, 1e-7, 1e-5) for s in (-1, 1))):
            q = np.ascontiguousarray(a + t * (b - a))
            collision._collfast.poses(model._fast, q, poses)
            ours, full = model.check(q), model._narrow(poses, range(len(model.pairs)))
            assert ours.pairs == full.pairs, (pair, t, ours.pairs ^ full.pairs)
            assert model.collides(q) == full.collides
            compared += 1
            decided_by_c += _collfast_decides(model, q)
    assert decided_by_c > compared // 6, decided_by_c  # the C decisions near touching are exercised, not only fcl's


def _collfast_decides(model: collision.CollisionModel, q: np.ndarray) -> bool:
    """Whether the C code answered configuration q without python-fcl."""
    return collision._collfast.check_one(model._fast, np.ascontiguousarray(q, dtype=float)) is not False


@pytest.mark.skipif(not collision.FAST_AVAILABLE, reason="mds_ach.kinematics._collfast not built")
def test_clearance_first_rule_keeps_fcls_answer_at_its_threshold() -> None:
    """The C path proves a pair with a cylinder overlapping when its un-inflated shapes are closer than
    pad_i + pad_j - 2 eps (each inflated shape contains its un-inflated one grown by pad). That threshold is met
    where the inflated shapes are exactly the grown ones: a box face-on to a cylinder's side. World boxes face-on
    to the left forearm's cylinder at un-inflated gaps of 2 pad + delta, delta from -20 to +20 um: every answer
    (all pairs, fcl on every pair at the same poses) and the box-forearm pair in the list exactly when fcl finds
    the inflated gap delta closed."""
    base = collision.load_model()
    q = q_of(**{**HOME, "LEP": -0.6})
    poses = base.primitive_poses(q)
    cyl = base.primitives[index(base, "left_forearm_link")]
    T = poses[index(base, "left_forearm_link")]
    a, c, r = T[:3, 2], T[:3, 3], cyl.size[0]
    pad = base.margin / 2
    deltas = (-2e-5, -5e-6, -2.5e-6, -2.01e-6, -1.99e-6, -1e-6, -5e-7, 0.0, 5e-7, 1e-6, 1.5e-6, 5e-6, 2e-5)
    objects = []
    for k, delta in enumerate(deltas):  # around the forearm, one box per gap, each face-on to its side
        angle = 2 * math.pi * k / len(deltas)
        u = np.cross(a, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        n = math.cos(angle) * u + math.sin(angle) * np.cross(a, u)
        R = np.column_stack([a, np.cross(n, a), n])  # the box's -z face looks at the forearm
        centre = c + n * (r + 2 * pad + delta + 0.02)
        rpy = [math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0]), math.atan2(R[1, 0], R[0, 0])]
        objects.append({"name": f"gap{k}", "shape": "box", "size": [0.4, 0.03, 0.04], "frame": "base",
                        "xyz": centre.tolist(), "rpy": rpy})
    model = collision.load_model(world={"objects": objects})
    qc = np.ascontiguousarray(q)
    c_poses = np.zeros((len(model.primitives), 4, 4))
    collision._collfast.poses(model._fast, qc, c_poses)
    ours, full = model.check(qc), model._narrow(c_poses, range(len(model.pairs)))
    assert ours.pairs == full.pairs
    touching = {p[0].removeprefix("world:") for p in ours.pairs if p[1] == "left_forearm_link"} | \
        {p[1].removeprefix("world:") for p in ours.pairs if p[0] == "left_forearm_link"}
    assert {f"gap{k}" for k, d in enumerate(deltas) if d <= -2e-6} <= touching
    assert not touching & {f"gap{k}" for k, d in enumerate(deltas) if d >= 1e-6}


def test_check_takes_any_vector_of_the_joints_and_refuses_a_wrong_length() -> None:
    """``check`` hands a contiguous float64 vector to the C code as it is and converts anything else (a list,
    float32, a strided view) first: the same answer; a vector of the wrong length is refused with its shape."""
    model = collision.load_model(world=TABLE)
    for q in random_configs(model, 40, seed=41):
        answer = model.check(q)
        assert model.check(list(q)) == answer
        assert model.check(np.stack([q, q], axis=1)[:, 0]) == answer  # not contiguous
        assert model.check(q.astype(np.float32)).pairs == model.check(q.astype(np.float32).astype(float)).pairs
    with pytest.raises(ValueError, match="17 joint values"):
        model.check(np.zeros(16))
