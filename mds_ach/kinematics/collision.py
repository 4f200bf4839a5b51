"""Geometric collision model of the MDS: URDF collision primitives + world objects, checked with python-fcl.

Why this shape:
* The primitives come from the URDF's ``<collision>`` elements (read once with yourdfpy at start-up), plus
  optional extra primitives and world objects from ``config/collision.yaml`` / ``config/world.yaml``.
* Every primitive is attached to the *last actuated joint* above its link with a precomputed fixed offset, so
  a check needs only the 17 joint frames. They are computed with a batched numpy FK (one matrix product per
  tree level), not with yourdfpy's scene graph, which is ~10x slower.
* A screen keeps python-fcl calls to the few pairs that are actually close; the narrow phase is
  ``fcl.collide`` per pair on our own object list, so each result is tied to a known pair. The screen is the C
  extension ``_collfast`` when it was built (FK, poses and per-pair tests in ~2 us: exact for sphere-sphere,
  sphere-box, sphere-cylinder and box-box, bounding boxes / capsules otherwise; pairs it proves overlapping skip
  ``fcl.collide``), else a numpy bounding-sphere broad phase. Both give python-fcl's answers: the screen only
  decides pairs apart or overlapping by more than ``SCREEN_EPS`` (1 um) and leaves the rest to fcl.
  (python-fcl swallows exceptions raised in collision-manager callbacks and hands back new wrapper objects,
  so a manager-based check could silently drop a collision.)
* The minimum clearance margin is applied by inflating every primitive by half the margin: two objects are
  "in collision" when they come closer than ``margin`` (exact for spheres, conservative for boxes/cylinders).

Groups: ``left``/``right`` (links below LSP/RSP), ``head`` (below the neck joints), ``body`` (everything else
on the robot) and ``world``. Only pairs with at least one arm primitive are checked: arm-arm, arm-body,
arm-head, arm-world, and same-arm pairs separated by enough joints.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

import mds_ach as mds
from mds_ach.paths import config_path, urdf_path
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, MODEL_JOINTS, NECK, RIGHT_ARM

_collfast: Any
try:  # the optional C screen (setup.py builds it when a compiler is there)
    from mds_ach.kinematics import _collfast  # type: ignore[attr-defined, no-redef]
except ImportError:  # pragma: no cover - depends on the build
    _collfast = None

FAST_AVAILABLE = _collfast is not None
SCREEN_EPS = 1e-6  # m: the C screen leaves pairs this close to touching to fcl (rounding differs between them)
SHAPES = ("sphere", "box", "cylinder")
GROUPS = ("left", "right", "body", "head", "world")
ARM_GROUPS = ("left", "right")
_ARM_OF_JOINT = {**{n: "left" for n in LEFT_ARM}, **{n: "right" for n in RIGHT_ARM}, **{n: "head" for n in NECK}}


# --------------------------------------------------------------------------------------------- data


@dataclass(frozen=True)
class Primitive:
    """One collision shape. ``size``: (r,) sphere, (x, y, z) box, (r, length) cylinder along local z."""

    name: str
    link: str
    kind: str
    size: tuple[float, ...]
    offset: np.ndarray = field(repr=False)  # 4x4 pose in the frame of ``link`` (or the base for world objects)
    group: str = "body"
    part: int = -1  # legacy COLLIDE_* index, -1 when the part has none


@dataclass(frozen=True)
class Contact:
    """A predicted collision between two primitives (names as in ``CollisionModel.primitives``)."""

    a: str
    b: str
    group_a: str
    group_b: str
    part_a: int
    part_b: int
    # Signed distance (m) between the two *un-inflated* shapes: > 0 a gap (still inside the margin), < 0 the
    # overlap depth. Tells "moving out of contact" from "pushing further in" (the gate's escape rule).
    clearance: float = 0.0

    @property
    def arms(self) -> set[str]:
        return {g for g in (self.group_a, self.group_b) if g in ARM_GROUPS}


@dataclass(frozen=True)
class CheckResult:
    contacts: tuple[Contact, ...] = ()

    @property
    def collides(self) -> bool:
        return bool(self.contacts)

    @property
    def arms(self) -> set[str]:
        """Arms ('left'/'right') that take part in at least one predicted collision."""
        out: set[str] = set()
        for c in self.contacts:
            out |= c.arms
        return out

    @property
    def parts(self) -> set[int]:
        """Legacy ``COLLIDE_*`` part indices involved."""
        return {p for c in self.contacts for p in (c.part_a, c.part_b) if p >= 0}

    @property
    def pairs(self) -> frozenset[tuple[str, str]]:
        return frozenset((c.a, c.b) for c in self.contacts)


_FREE = CheckResult()

# --------------------------------------------------------------------------------------------- helpers


def pose_matrix(xyz: Sequence[float] = (0.0, 0.0, 0.0), rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 from a URDF-style xyz + fixed-axis roll/pitch/yaw."""
    r, p, y = (float(v) for v in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    T = np.eye(4)
    T[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    T[:3, 3] = [float(v) for v in xyz]
    return T


def _skew4(axis: np.ndarray) -> np.ndarray:
    K = np.zeros((4, 4))
    x, y, z = axis
    K[:3, :3] = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]]
    return K


def inflate(kind: str, size: Sequence[float], pad: float) -> tuple[float, ...]:
    """Grow a primitive by ``pad`` on every side (radius + pad, lengths + 2 pad)."""
    if kind == "sphere":
        return (size[0] + pad,)
    if kind == "cylinder":
        return (size[0] + pad, size[1] + 2 * pad)
    if kind == "box":
        return tuple(s + 2 * pad for s in size)
    raise ValueError(f"unknown shape {kind!r}")


def bounding_radius(kind: str, size: Sequence[float]) -> float:
    """Radius of the sphere around the primitive's centre that contains it."""
    if kind == "sphere":
        return float(size[0])
    if kind == "cylinder":
        return math.hypot(size[0], size[1] / 2)
    return 0.5 * math.sqrt(sum(s * s for s in size))


def _fcl_geometry(kind: str, size: Sequence[float]) -> Any:
    import fcl  # lazy, as in CollisionModel.__init__

    if kind == "sphere":
        return fcl.Sphere(float(size[0]))
    if kind == "cylinder":
        return fcl.Cylinder(float(size[0]), float(size[1]))
    return fcl.Box(*(float(s) for s in size))


def part_index(name: str | int) -> int:
    """Legacy part index from 'L_HAND' / 'COLLIDE_L_HAND' / 0..9."""
    if isinstance(name, int):
        if 0 <= name < len(mds.COLLIDE_PART_NAMES):
            return name
        raise ValueError(f"collide part index {name} out of range 0..{len(mds.COLLIDE_PART_NAMES) - 1}")
    key = str(name).strip().upper().removeprefix("COLLIDE_")
    if key not in mds.COLLIDE_PART_NAMES:
        raise ValueError(f"unknown collide part {name!r}; use one of {', '.join(mds.COLLIDE_PART_NAMES)}")
    return mds.COLLIDE_PART_NAMES.index(key)


def shape_from_config(entry: Mapping[str, Any], where: str) -> tuple[str, tuple[float, ...]]:
    """(kind, size) from a YAML entry: ``shape: box, size: [x, y, z]`` / ``sphere, radius`` / ``cylinder,
    radius, length``; every dimension must be a positive finite number."""
    kind = str(entry.get("shape", "")).lower()
    try:
        if kind == "box":
            size = tuple(float(v) for v in entry["size"])
            if len(size) != 3:
                raise ValueError("box size needs 3 numbers [x, y, z]")
        elif kind == "sphere":
            size = (float(entry["radius"]),)
        elif kind == "cylinder":
            size = (float(entry["radius"]), float(entry["length"]))
        else:
            raise ValueError(f"shape must be one of {', '.join(SHAPES)}, got {entry.get('shape')!r}")
    except KeyError as exc:
        raise ValueError(f"{where}: {kind} needs {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None
    if not all(math.isfinite(s) and s > 0 for s in size):
        raise ValueError(f"{where}: dimensions must be positive finite numbers, got {list(size)}")
    return kind, size


def _pose_from_config(entry: Mapping[str, Any], where: str) -> np.ndarray:
    try:
        xyz = [float(v) for v in entry.get("xyz", (0, 0, 0))]
        rpy = [float(v) for v in entry.get("rpy", (0, 0, 0))]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: xyz/rpy must be lists of 3 numbers ({exc})") from None
    if len(xyz) != 3 or len(rpy) != 3 or not all(math.isfinite(v) for v in xyz + rpy):
        raise ValueError(f"{where}: xyz and rpy need 3 finite numbers each")
    return pose_matrix(xyz, rpy)


@dataclass
class WorldObject:
    """A configured world object, posed in the base frame (on the floor)."""

    name: str
    kind: str
    size: tuple[float, ...]
    pose: np.ndarray
    enabled: bool
    padding: float = 0.0  # m the collision gate grows it by (the viewer shows it as configured)


def parse_world(world: Mapping[str, Any], robot_zero: np.ndarray, source: str = "") -> list[WorldObject]:
    """The objects of a ``config/world.yaml`` mapping: the one parser, for the collision gate and the viewer.

    Poses are in ``frame``: ``robot`` (the torso frame at WST = 0, ``robot_zero``: origin between the shoulders,
    x forward, y left, z up) or ``base`` (base_link, on the floor). Bad entries raise ValueError naming them
    (and ``source``, the file, when given)."""
    prefix = f"{source}: " if source else ""
    default_frame = str(world.get("frame", "robot"))
    objects = []
    for k, obj in enumerate(world.get("objects") or []):
        if not isinstance(obj, Mapping):
            raise ValueError(f"{prefix}world objects[{k}] must be a mapping")
        name = str(obj.get("name", k))
        where = f"{prefix}world object {name!r}"
        kind, size = shape_from_config(obj, where)
        frame = str(obj.get("frame", default_frame))
        if frame not in ("robot", "base"):
            raise ValueError(f"{where}: frame must be 'robot' or 'base', got {frame!r}")
        pose = _pose_from_config(obj, where)
        if frame == "robot":
            pose = robot_zero @ pose
        try:
            padding = float(obj.get("padding", 0.0))
        except (TypeError, ValueError):
            padding = math.nan
        if not (math.isfinite(padding) and padding >= 0):
            raise ValueError(f"{where}: padding must be >= 0")
        objects.append(WorldObject(name, kind, size, pose, bool(obj.get("enabled", True)), padding))
    return objects


def load_world(path: str | Path, robot_zero: np.ndarray) -> list[WorldObject]:
    """:func:`parse_world` of a file; a missing file means no objects."""
    path = Path(path)
    return parse_world(load_yaml(path), robot_zero, path.name) if path.is_file() else []


def check_world_file(path: str | Path) -> int:
    """Validate a world file before a node or the launcher uses it: ValueError naming the file and the problem
    (missing, not YAML, a bad object); returns how many objects are enabled."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"world file {path} not found")
    try:
        data = load_yaml(path)
    except yaml.YAMLError as exc:
        raise ValueError(f"world file {path} is not valid YAML: {exc}") from None
    return sum(obj.enabled for obj in parse_world(data, np.eye(4), str(path)))


def load_yaml(path: str | Path) -> dict[str, Any]:
    with open(path, encoding="utf-8") as fh:
        data = yaml.safe_load(fh) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    return data


# --------------------------------------------------------------------------------------------- kinematic tree


class TreeFK:
    """Batched FK of the actuated joint frames of a URDF tree (joint frame = child link frame of the joint).

    Built from yourdfpy's parsed joints. ``joint_frames(q)`` returns (n + 1, 4, 4): the n actuated joints
    in ``joint_names`` order, then the identity for the root (index n == index -1 semantics for "static").
    """

    def __init__(self, robot: Any, joint_names: Sequence[str]) -> None:
        joints = {j.name: j for j in robot.joints}
        parent_joint = {j.child: j for j in robot.joints}
        self.root = next(link.name for link in robot.links if link.name not in parent_joint)
        self.joint_names = tuple(joint_names)
        actuated = {j.name for j in robot.joints if j.type in ("revolute", "continuous")}
        if set(self.joint_names) != actuated:
            raise ValueError(f"URDF actuated joints {sorted(actuated)} differ from the model joints "
                             f"{sorted(self.joint_names)}")
        self.index = {n: i for i, n in enumerate(self.joint_names)}
        n = len(self.joint_names)
        # Walk each link up to its nearest actuated ancestor: owner joint index and fixed offset.
        self._owner: dict[str, tuple[int, np.ndarray]] = {}

        def owner_of(link: str) -> tuple[int, np.ndarray]:
            if link in self._owner:
                return self._owner[link]
            j = parent_joint.get(link)
            if j is None:
                res = (n, np.eye(4))
            elif j.name in self.index:
                res = (self.index[j.name], np.eye(4))
            else:
                up, off = owner_of(j.parent)
                res = (up, off @ _origin(j))
            self._owner[link] = res
            return res

        for link in robot.links:
            owner_of(link.name)
        parent = np.empty(n, dtype=int)
        A0, A1, A2 = (np.empty((n, 4, 4)) for _ in range(3))
        depth = np.zeros(n, dtype=int)
        for name, i in self.index.items():
            j = joints[name]
            up, off = owner_of(j.parent)
            parent[i] = up
            C = off @ _origin(j)
            axis = np.asarray(j.axis if j.axis is not None else (1.0, 0.0, 0.0), dtype=float)
            K = _skew4(axis / np.linalg.norm(axis))
            A0[i], A1[i], A2[i] = C, C @ K, C @ K @ K
        for i in range(n):  # depth = number of actuated ancestors
            k, d = parent[i], 0
            while k != n:
                k, d = parent[k], d + 1
            depth[i] = d
        self.parent = parent
        self._A0, self._A1, self._A2 = A0, A1, A2
        self._levels = [(np.flatnonzero(depth == d), parent[depth == d]) for d in range(int(depth.max()) + 1)]
        self.lower = np.array([_limit(joints[nm], "lower") for nm in self.joint_names])
        self.upper = np.array([_limit(joints[nm], "upper") for nm in self.joint_names])

    def owner(self, link: str) -> tuple[int, np.ndarray]:
        """(index of the actuated joint that moves ``link``, or n for the root; fixed offset from its frame)."""
        return self._owner[link]

    def joint_frames(self, q: np.ndarray) -> np.ndarray:
        """(n + 1, 4, 4) for one configuration, or (K, n + 1, 4, 4) for a batch ``q`` of shape (K, n): the gate
        checks several configurations per reference, and one batched pass costs about as much as one."""
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            return self.joint_frames(q[None])[0]
        s = np.sin(q)[..., None, None]
        c1 = 1.0 - np.cos(q)[..., None, None]
        local = self._A0 + s * self._A1 + c1 * self._A2
        T = np.empty((q.shape[0], q.shape[1] + 1, 4, 4))
        T[:, -1] = np.eye(4)
        for idx, par in self._levels:
            T[:, idx] = T[:, par] @ local[:, idx]
        return T

    def link_pose(self, link: str, q: np.ndarray) -> np.ndarray:
        i, off = self.owner(link)
        return self.joint_frames(q)[i] @ off


def _origin(joint: Any) -> np.ndarray:
    return np.eye(4) if joint.origin is None else np.asarray(joint.origin, dtype=float)


def _limit(joint: Any, which: str) -> float:
    if joint.type == "continuous" or joint.limit is None:
        return -math.inf if which == "lower" else math.inf
    value = getattr(joint.limit, which)
    return float(value) if value is not None else (-math.inf if which == "lower" else math.inf)


# --------------------------------------------------------------------------------------------- model


class CollisionModel:
    """Self- and world-collision checker for one configuration of the 17 model joints.

    ``q`` vectors are in ``joint_names`` order (= ``mds_ach.robot.joints.MODEL_JOINTS``); ``q_from_ref`` converts a
    100-entry ref array indexed by CAN address.
    """

    def __init__(self, urdf: str | Path, config: Mapping[str, Any] | None = None,
                 world: Mapping[str, Any] | None = None) -> None:
        # Lazy: fcl ~0.12 s, yourdfpy ~0.8 s (-X importtime); this module's world/config parsers serve the viewer,
        # check-log and the IK node, which must start without them.
        import fcl
        import yourdfpy

        config = dict(config or {})
        robot = yourdfpy.URDF.load(str(urdf), build_scene_graph=False, load_meshes=False,
                                   build_collision_scene_graph=False).robot
        self.urdf = str(urdf)
        self.joint_names: tuple[str, ...] = MODEL_JOINTS
        self.addresses = np.array([BY_SHORT[n].address for n in self.joint_names])
        self.tree = TreeFK(robot, self.joint_names)
        self.lower, self.upper = self.tree.lower, self.tree.upper
        self.margin = float(config.get("margin", 0.02))
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"collision margin must be a finite number >= 0 m, got {self.margin}")
        n = len(self.joint_names)

        groups = {link.name: self._group_of(robot, link.name) for link in robot.links}
        parts_cfg = {str(k): part_index(v) for k, v in (config.get("parts") or {}).items()}
        prims: list[Primitive] = []
        owners: list[int] = []
        for link in robot.links:
            owner, off = self.tree.owner(link.name)
            for k, col in enumerate(link.collisions):
                kind, size = _urdf_shape(col.geometry, link.name)
                name = link.name if len(link.collisions) == 1 else f"{link.name}#{k}"
                origin = np.eye(4) if col.origin is None else np.asarray(col.origin, dtype=float)
                prims.append(Primitive(name, link.name, kind, size, off @ origin, groups[link.name],
                                       parts_cfg.get(link.name, -1)))
                owners.append(owner)
        for k, extra in enumerate(config.get("extra_primitives") or []):
            where = f"collision config extra_primitives[{k}]"
            link = str(extra.get("link", ""))
            if link not in groups:
                raise ValueError(f"{where}: unknown link {link!r}")
            kind, size = shape_from_config(extra, where)
            owner, off = self.tree.owner(link)
            part = part_index(extra["part"]) if extra.get("part") is not None else parts_cfg.get(link, -1)
            prims.append(Primitive(str(extra.get("name") or f"{link}#extra{k}"), link, kind, size,
                                   off @ _pose_from_config(extra, where), groups[link], part))
            owners.append(owner)
        for prim, owner in self._world_primitives(world or {}):
            prims.append(prim)
            owners.append(owner)
        names = [p.name for p in prims]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate collision primitive names: {sorted({x for x in names if names.count(x) > 1})}")
        self.primitives: tuple[Primitive, ...] = tuple(prims)
        self._index = {p.name: k for k, p in enumerate(prims)}
        self._owner = np.array(owners, dtype=int)
        self._offset = np.array([p.offset for p in prims])
        self._moving = self._owner != n
        pad = self.margin / 2
        self._radius = np.array([bounding_radius(p.kind, inflate(p.kind, p.size, pad)) for p in prims])
        self._objects = [fcl.CollisionObject(_fcl_geometry(p.kind, inflate(p.kind, p.size, pad)), fcl.Transform())
                         for p in prims]
        self._raw_objects = [fcl.CollisionObject(_fcl_geometry(p.kind, p.size), fcl.Transform()) for p in prims]
        static = self._offset[~self._moving]
        for fixed, T in zip(np.flatnonzero(~self._moving), static, strict=True):
            for obj in (self._objects[fixed], self._raw_objects[fixed]):
                obj.setRotation(T[:3, :3])
                obj.setTranslation(T[:3, 3])
        pairs = self._pairs(config)
        self.pairs: tuple[tuple[int, int], ...] = tuple(pairs)
        self._I = np.array([p[0] for p in pairs], dtype=int)
        self._J = np.array([p[1] for p in pairs], dtype=int)
        self._rsum = self._radius[self._I] + self._radius[self._J]
        self._pair_info = [(prims[i].name, prims[j].name, prims[i].group, prims[j].group, prims[i].part,
                            prims[j].part) for i, j in pairs]
        self._contact_fields = tuple(Contact(*info).__dict__ for info in self._pair_info)
        self._request = fcl.CollisionRequest()
        self._signed = fcl.DistanceRequest(enable_signed_distance=True)
        self._plain = fcl.DistanceRequest()
        self._fcl = fcl
        self._fast: Any = self._build_screen(pad) if FAST_AVAILABLE else None
        if self._fast is not None:  # check's answers: CheckResult((Contact(*pair_info[k], clearance), ...)), in C
            _collfast.contacts(self._fast, Contact, self._contact_fields, CheckResult, _FREE)
        self._pose_buffer = np.zeros((len(prims), 4, 4))

    def _build_screen(self, pad: float) -> Any:
        """The C screen's copy of the model: joint chain, primitives (inflated, as half extents), pairs."""
        assert _collfast is not None
        tree, n = self.tree, len(self.joint_names)
        A = np.stack([tree._A0[:, :3], tree._A1[:, :3], tree._A2[:, :3]], axis=1)  # (n, 3, 3, 4)
        order = np.concatenate([idx for idx, _ in tree._levels]).astype(np.int64)
        kinds = {"sphere": 0, "box": 1, "cylinder": 2}
        dims, raw = np.zeros((len(self.primitives), 3)), np.zeros((len(self.primitives), 3))
        for k, p in enumerate(self.primitives):
            for out, size in ((dims, inflate(p.kind, p.size, pad)), (raw, p.size)):
                if p.kind == "sphere":
                    out[k, 0] = size[0]
                elif p.kind == "box":
                    out[k] = np.asarray(size) / 2
                else:
                    out[k, :2] = size[0], size[1] / 2
        return _collfast.build(
            n, len(self.primitives), len(self.pairs), SCREEN_EPS, np.ascontiguousarray(A),
            tree.parent.astype(np.int64), order, self._owner.astype(np.int64),
            np.ascontiguousarray(self._offset[:, :3]), np.array([kinds[p.kind] for p in self.primitives], np.int64),
            dims, raw, np.ascontiguousarray(self._radius), self._I.astype(np.int64), self._J.astype(np.int64))

    # ----- construction helpers

    @staticmethod
    def _group_of(robot: Any, link: str) -> str:
        parent_joint = {j.child: j for j in robot.joints}
        while link in parent_joint:
            j = parent_joint[link]
            if j.name in _ARM_OF_JOINT:
                return _ARM_OF_JOINT[j.name]
            link = j.parent
        return "body"

    def _world_primitives(self, world: Mapping[str, Any]) -> Iterable[tuple[Primitive, int]]:
        """The enabled world objects (:func:`parse_world`), grown by their ``padding``, fixed to the floor."""
        n = len(self.joint_names)
        for obj in parse_world(world, self.tree.link_pose("torso", np.zeros(n))):
            if not obj.enabled:
                continue
            size = inflate(obj.kind, obj.size, obj.padding) if obj.padding else obj.size
            yield Primitive(f"world:{obj.name}", "world", obj.kind, size, obj.pose, "world", -1), n

    def _pairs(self, config: Mapping[str, Any]) -> list[tuple[int, int]]:
        """Arm-arm, arm-body, arm-head, arm-world and listed same-arm pairs, minus ``ignore_pairs``."""
        check = {"arm_arm": True, "arm_body": True, "arm_world": True, "same_arm": True, **(config.get("check") or {})}
        ignore = _pattern_pairs(config.get("ignore_pairs"), "ignore_pairs")
        same_arm = _pattern_pairs(config.get("same_arm_pairs"), "same_arm_pairs")
        out = []
        P = self.primitives
        for i in range(len(P)):
            for j in range(i + 1, len(P)):
                a, b = P[i], P[j]
                if a.group not in ARM_GROUPS and b.group not in ARM_GROUPS:
                    continue
                if a.group in ARM_GROUPS and b.group in ARM_GROUPS:
                    if a.group != b.group:
                        wanted = check["arm_arm"]
                    else:
                        wanted = check["same_arm"] and _matches(a, b, same_arm)
                elif "world" in (a.group, b.group):
                    wanted = check["arm_world"]
                else:
                    wanted = check["arm_body"]
                if wanted and not _matches(a, b, ignore):
                    out.append((i, j))
        return out

    # ----- run time

    def q_from_ref(self, ref: np.ndarray) -> np.ndarray:
        """The model joint vector from a 100-entry array indexed by CAN address."""
        return np.asarray(ref, dtype=float)[self.addresses]

    def primitive_poses(self, q: np.ndarray) -> np.ndarray:
        """(P, 4, 4) poses of all primitives in the base frame; (K, P, 4, 4) for a batch of K configurations."""
        T = self.tree.joint_frames(np.asarray(q, dtype=float))
        return T[..., self._owner, :, :] @ self._offset

    def check(self, q: np.ndarray) -> CheckResult:
        """Predicted collisions (clearance below ``margin``) for one configuration."""
        if self._fast is not None:
            found = _collfast.check_one(self._fast, q)  # NotImplemented: not a contiguous float64 vector
            if found is NotImplemented:
                q = self._vector(q)
                found = _collfast.check_one(self._fast, q)
            if found is not False:
                return found
            return self._check_screened(np.asarray(q, dtype=float))
        return self.check_many(self._vector(q)[None])[0]

    def _vector(self, q: Any) -> np.ndarray:
        """q as a contiguous float64 vector of the model's joints; ValueError naming the shape otherwise."""
        q = np.ascontiguousarray(q, dtype=float)
        if q.shape != (len(self.joint_names),):
            raise ValueError(f"a configuration needs {len(self.joint_names)} joint values, got shape {q.shape}")
        return q

    def check_many(self, qs: np.ndarray) -> list[CheckResult]:
        """``check`` for each row of ``qs`` (K, 17): the C screen per row, else one batched numpy FK and broad
        phase."""
        if not (type(qs) is np.ndarray and qs.ndim == 2 and qs.dtype == np.float64 and qs.flags.c_contiguous):
            qs = np.ascontiguousarray(np.atleast_2d(np.asarray(qs, dtype=float)))  # (the gate's rows already are)
        if self._fast is not None:
            found = _collfast.check_many(self._fast, qs)
            return [self._check_screened(qs[k]) if f is False else f for k, f in enumerate(found)]
        poses = self.primitive_poses(qs)
        centres = poses[..., :3, 3]
        gap = np.linalg.norm(centres[:, self._I] - centres[:, self._J], axis=2) - self._rsum
        return [self._narrow(p, np.flatnonzero(g < 0.0)) for p, g in zip(poses, gap, strict=True)]

    def _check_screened(self, q: np.ndarray) -> CheckResult:
        """The fcl way for a configuration the C code could not settle (``_collfast.check_many`` answered False: an
        undecided pair or a clearance it could not certify): the same screen, fcl on the pairs it did not prove
        apart; the same answer."""
        poses = self._pose_buffer
        candidates = _collfast.screen(self._fast, np.ascontiguousarray(q, dtype=float), poses)
        return self._narrow(poses, candidates) if candidates else _FREE

    def collides(self, q: np.ndarray) -> bool:
        """Whether ``check(q)`` would report a collision, without the pair list and clearances: stops at the first
        colliding pair (the yes/no question, cheaper than ``check`` on colliding configurations)."""
        if self._fast is None:
            return self.check(q).collides
        poses = self._pose_buffer
        candidates = _collfast.screen(self._fast, np.ascontiguousarray(q, dtype=float), poses, True)
        if candidates and candidates[-1] < 0:
            return True
        fcl, objs = self._fcl, self._objects
        for k in candidates:
            i, j = int(self._I[k]), int(self._J[k])
            for m in (i, j):
                if self._moving[m]:
                    objs[m].setRotation(poses[m, :3, :3])
                    objs[m].setTranslation(poses[m, :3, 3])
            if fcl.collide(objs[i], objs[j], self._request, fcl.CollisionResult()) > 0:
                return True
        return False

    def check_exhaustive(self, q: np.ndarray) -> CheckResult:
        """Same answer as ``check`` without the broad phase: fcl on every pair (for tests and as a baseline)."""
        return self._narrow(self.primitive_poses(q), range(len(self.pairs)))

    def _narrow(self, poses: np.ndarray, candidates: Iterable[int]) -> CheckResult:
        """fcl on the candidate pairs (``-1 - k``: pair k proven overlapping by the screen, no ``fcl.collide``);
        the signed distance of the un-inflated shapes for each colliding pair."""
        fcl, objs, prims = self._fcl, self._objects, self.primitives
        placed = np.zeros(len(prims), dtype=bool)
        contacts = []
        for k in candidates:
            sure = k < 0
            k = -1 - k if sure else k
            i, j = int(self._I[k]), int(self._J[k])
            if not sure:
                for m in (i, j):
                    if self._moving[m] and not placed[m]:
                        objs[m].setRotation(poses[m, :3, :3])
                        objs[m].setTranslation(poses[m, :3, 3])
                        placed[m] = True
            if sure or fcl.collide(objs[i], objs[j], self._request, fcl.CollisionResult()) > 0:
                clearance = self._signed_distance(poses, i, j)
                a, b = prims[i], prims[j]
                contacts.append(Contact(a.name, b.name, a.group, b.group, a.part, b.part, clearance))
        return CheckResult(tuple(contacts))

    def _signed_distance(self, poses: np.ndarray, i: int, j: int) -> float:
        """Signed distance (m) of primitives ``i``, ``j`` (un-inflated) at ``poses``: the C code's exact closed
        forms and certified GJK distances where it has them (every pair with a sphere, every pair apart), else
        fcl's signed distance (overlapping or touching boxes and cylinders). fcl's signed mode is only used
        for overlaps: on shapes apart it is up to a millimetre off, its plain distance is exact there."""
        if self._fast is not None:
            d = _collfast.distance(self._fast, poses, i, j)
            if d == d:  # not NaN
                return float(d)
        return self.fcl_signed_distance(poses, i, j)

    def fcl_signed_distance(self, poses: np.ndarray, i: int, j: int) -> float:
        """python-fcl's signed distance of primitives ``i``, ``j`` (un-inflated) at ``poses``: ``fcl.distance``
        when ``fcl.collide`` finds them apart (exact there, where its signed mode is up to a millimetre off), its
        signed mode (EPA, within 1e-6 m) when they overlap. The fallback where the C code has no answer. (fcl's
        collide misses some sub-millimetre sphere overlaps: then this gives ~0 for a small negative distance.)"""
        fcl, raw = self._fcl, self._raw_objects
        for m in (i, j):
            if self._moving[m]:
                raw[m].setRotation(poses[m, :3, :3])
                raw[m].setTranslation(poses[m, :3, 3])
        if fcl.collide(raw[i], raw[j], self._request, fcl.CollisionResult()) == 0:
            return float(fcl.distance(raw[i], raw[j], self._plain, fcl.DistanceResult()))
        return float(fcl.distance(raw[i], raw[j], self._signed, fcl.DistanceResult()))

    def distances(self, q: np.ndarray) -> dict[tuple[str, str], float]:
        """Clearance (m) of every checked pair on the un-inflated shapes; 0.0 when they overlap. For reports and
        tests, not for the real-time path."""
        fcl = self._fcl
        poses = self.primitive_poses(q)
        for m in np.flatnonzero(self._moving):
            self._raw_objects[m].setRotation(poses[m, :3, :3])
            self._raw_objects[m].setTranslation(poses[m, :3, 3])
        out = {}
        for i, j in self.pairs:
            a, b = self._raw_objects[i], self._raw_objects[j]
            if fcl.collide(a, b) > 0:
                d = 0.0
            else:
                d = max(0.0, float(fcl.distance(a, b)))
            out[(self.primitives[i].name, self.primitives[j].name)] = d
        return out

    def clearance(self, q: np.ndarray, a: str, b: str) -> float:
        """Clearance (m) of the one pair of primitives ``a``, ``b`` on the un-inflated shapes; 0.0 when they
        overlap. Cheap enough for the gate to follow one contact per frame (an arm resting where it stopped)."""
        i, j = self._index[a], self._index[b]
        if self._fast is not None:
            poses = self._pose_buffer
            _collfast.poses(self._fast, np.ascontiguousarray(q, dtype=float), poses)
            return max(0.0, self._signed_distance(poses, i, j))
        fcl = self._fcl
        poses = self.primitive_poses(q)
        for m in (i, j):
            if self._moving[m]:
                self._raw_objects[m].setRotation(poses[m, :3, :3])
                self._raw_objects[m].setTranslation(poses[m, :3, 3])
        oa, ob = self._raw_objects[i], self._raw_objects[j]
        if fcl.collide(oa, ob) > 0:
            return 0.0
        return max(0.0, float(fcl.distance(oa, ob)))

    def within_limits(self, q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        return (q >= self.lower) & (q <= self.upper)


def _pattern_pairs(entries: Any, key: str) -> list[tuple[str, str]]:
    out = []
    for pair in entries or []:
        if not isinstance(pair, list | tuple) or len(pair) != 2:
            raise ValueError(f"collision config {key}: entries need two name patterns, got {pair!r}")
        out.append((str(pair[0]), str(pair[1])))
    return out


def _matches(a: Primitive, b: Primitive, patterns: Sequence[tuple[str, str]]) -> bool:
    """True when (a, b) or (b, a) matches one [pattern, pattern] entry (on primitive or link names)."""

    def hit(p: Primitive, pattern: str) -> bool:
        return fnmatch.fnmatchcase(p.name, pattern) or fnmatch.fnmatchcase(p.link, pattern)

    return any((hit(a, pa) and hit(b, pb)) or (hit(b, pa) and hit(a, pb)) for pa, pb in patterns)


def _urdf_shape(geometry: Any, link: str) -> tuple[str, tuple[float, ...]]:
    if geometry.sphere is not None:
        return "sphere", (float(geometry.sphere.radius),)
    if geometry.cylinder is not None:
        return "cylinder", (float(geometry.cylinder.radius), float(geometry.cylinder.length))
    if geometry.box is not None:
        return "box", tuple(float(s) for s in geometry.box.size)
    raise ValueError(f"link {link!r}: only box/sphere/cylinder collision geometry is supported (no meshes)")


def load_model(urdf: str | Path | None = None, config: str | Path | Mapping[str, Any] | None = None,
               world: str | Path | Mapping[str, Any] | None = None) -> CollisionModel:
    """The package's model: ``urdf/mds.urdf`` + ``config/collision.yaml`` + ``config/world.yaml`` by default.

    ``config``/``world`` may be paths or already-loaded mappings.
    """
    def as_map(value: str | Path | Mapping[str, Any] | None, default: str) -> Mapping[str, Any]:
        if value is None:
            path = config_path(default)
            return load_yaml(path) if path.exists() else {}
        if isinstance(value, Mapping):
            return value
        return load_yaml(value)

    cfg = as_map(config, "collision.yaml")
    return CollisionModel(urdf or urdf_path(), cfg, as_map(world, "world.yaml"))
