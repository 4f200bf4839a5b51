"""`mds-ach sim`: the robot in 3-D in a web browser, live from the shared-memory channels.

The original showed the robot in Gazebo; this viewer needs no simulator: viser serves its own web client, the
robot comes from urdf/mds.urdf posed by the numpy FK of :mod:`mds_ach.kinematics.model`, and the collision
primitives are exactly the collision gate's (:mod:`mds_ach.kinematics.collision`: URDF shapes plus the extra ones from
config/collision.yaml). The viewer only *reads* channels (mds-state, mds-collide, mds-ik, mds-ik-state) and
never creates one, so starting and stopping it does not disturb a running system. The one exception is the
optional joint-slider panel (off by default): it writes goto-style references to ``mds-ref-filter``, the
default mux input, so they pass the mux, the filter and the collision gate like every other client's.

Shown: the measured pose (``joint[].pos``) as the solid robot, the commanded reference (``joint[].ref``) as a
translucent ghost, the collision primitives (toggle), the world objects of config/world.yaml, colliding parts
in magenta (from ``mds-collide``) and the last IK target as a marker.

``python -m mds_ach.tools.viewer`` runs it in the foreground; ``mds-ach sim`` / ``mds-ach sim kill`` run it in the
background (pid file, URL and log in :func:`mds_ach.paths.runtime_dir`), and the launcher's stops end it with the
system. The page and its websocket need the token in the URL (:mod:`mds_ach.tools.viewer_door`); the sliders write
with the rights of the user who started the viewer.
"""

from __future__ import annotations

import argparse
import asyncio
import ctypes
import ipaddress
import math
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

import mds_ach as mds
from mds_ach import ach, paths
from mds_ach import procs as background
from mds_ach.ach.watch import Latest
from mds_ach.argtypes import bounded, count
from mds_ach.kinematics import model as kin
from mds_ach.kinematics.collision import CollisionModel, WorldObject, load_model
from mds_ach.kinematics.collision import load_world as _load_world
from mds_ach.kinematics.limits import current_limits
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.robot.joints import MODEL_JOINTS, lookup
from mds_ach.robot.msgs.ik_status import IK_SOLVED, IK_UNREACHABLE, MDS_IK_STATUS, STATUS_NAMES
from mds_ach.tools.refwriter import RefWriteError, RefWriter
from mds_ach.tools.viewer_door import Door, guarded, new_token
from mds_ach.tools.viewer_plot import LivePlot

if TYPE_CHECKING:  # heavy imports stay out of `import mds_ach.tools.viewer` (the `mds-ach sim` start-up path)
    import trimesh
    import viser


DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
DEFAULT_RATE_HZ = 30.0
RETRY_S = 1.0  # how often a missing (or replaced) channel is looked for again
STALE_S = 2.0  # a state older than this is reported as stale
GHOST_TOLERANCE = 0.002  # a ghost link shows when its pose differs from the solid one's by more (m / rotation)

SOLID_PATH = "/robot"
GHOST_PATH = "/ghost"
COLLISION_PATH = "/collision"
WORLD_PATH = "/world"

CAMERA_POSITION = (1.6, 0.8, 1.4)
CAMERA_LOOK_AT = (0.0, 0.0, 0.9)
VISER_DEFAULT_CAMERA = (3.0, 3.0, 3.0)  # where a viser page starts (looking at the origin) with +z up

GHOST_RGB = (90, 170, 255)
GHOST_OPACITY = 0.35
COLLISION_RGB = (255, 190, 40)
COLLISION_OPACITY = 0.35
HIGHLIGHT_RGB = (255, 0, 255)  # magenta: no URDF material, world object or marker uses it
HIGHLIGHT_OPACITY = 0.85
WORLD_RGB = (150, 120, 90)
WORLD_OPACITY = 0.6
IK_RGB = (30, 200, 90)  # solved
IK_REQUEST_RGB = (230, 200, 0)  # asked for, no answer yet
IK_FAILED_RGB = (230, 80, 20)  # unreachable
IK_OTHER_RGB = (140, 140, 140)  # refused / not ready

SIM_PID = "sim.pid"
SIM_LOG = "sim.log"
SIM_URL = "sim.url"

# --------------------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------------------


def primitive_mesh(kind: str, size: Sequence[float]) -> trimesh.Trimesh:
    """Triangle mesh of a primitive: box (x, y, z), cylinder (radius, length) along z, sphere (radius,)."""
    import trimesh  # lazy: ~0.5 s; `import mds_ach.tools.viewer` (the `mds-ach sim` start-up path) must not pay it

    if kind == "box":
        return trimesh.creation.box(extents=[float(s) for s in size])
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=float(size[0]), height=float(size[1]), sections=32)
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=float(size[0]))
    raise ValueError(f"unknown primitive {kind!r}")


def geometry_mesh(geom: kin.Geometry, urdf_dir: Path) -> trimesh.Trimesh | None:
    """Mesh of a URDF visual: a primitive, or a mesh file resolved like ROS does (package://, file://,
    relative to the URDF) through yourdfpy. An unreadable file is reported and skipped, not fatal."""
    if geom.kind != "mesh":
        return primitive_mesh(geom.kind, geom.size)
    import trimesh  # lazy, as in primitive_mesh
    import yourdfpy  # lazy: ~0.8 s (measured, -X importtime), only a running viewer needs it

    path = yourdfpy.filename_handler_magic(geom.filename, dir=str(urdf_dir))
    try:
        mesh = cast("trimesh.Trimesh", trimesh.load(path, force="mesh"))  # force="mesh": one Trimesh
    except Exception as exc:  # trimesh raises many types; any of them only costs this one shape
        print(f"viewer: skipping mesh {geom.filename}: {exc}", file=sys.stderr)
        return None
    mesh.apply_scale(geom.size)
    return mesh


def _rgb(rgba: Sequence[float] | None) -> tuple[int, int, int]:
    if rgba is None:
        return (160, 160, 160)
    r, g, b = (int(round(255 * min(max(float(c), 0.0), 1.0))) for c in rgba[:3])
    return (r, g, b)


def _wxyz_position(matrix: np.ndarray) -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
    x, y, z = matrix[:3, 3].tolist()
    return kin.quaternion_wxyz(matrix), (x, y, z)


def _add_mesh(
    server: viser.ViserServer,
    path: str,
    mesh: trimesh.Trimesh,
    rgb: tuple[int, int, int],
    opacity: float | None,
    pose: np.ndarray,
    visible: bool = True,
    wireframe: bool = False,
) -> Any:
    wxyz, pos = _wxyz_position(pose)
    return server.scene.add_mesh_simple(
        path,
        mesh.vertices,
        mesh.faces,
        color=rgb,
        opacity=opacity,
        wireframe=wireframe,
        wxyz=wxyz,
        position=pos,
        visible=visible,
        cast_shadow=False,
        receive_shadow=False,
    )


# --------------------------------------------------------------------------------------------------
# Scene parts
# --------------------------------------------------------------------------------------------------


class RobotScene:
    """The robot's visuals under ``root``: one frame per link, posed by the numpy FK (link_poses).

    Only frames whose pose changed are sent, so a still robot costs nothing and a moving arm a few small
    messages. ``color``/``opacity`` override the URDF materials (the reference ghost).
    """

    def __init__(
        self,
        server: viser.ViserServer,
        model: kin.RobotModel,
        root: str,
        *,
        color: tuple[int, int, int] | None = None,
        opacity: float | None = None,
    ) -> None:
        self.model = model
        self.root = root
        self.q: dict[str, float] = {name: 0.0 for name in model.actuated_joints}
        self._poses = model.link_poses(self.q)
        self._frames: dict[str, Any] = {}
        self.root_frame = server.scene.add_frame(root, show_axes=False)
        urdf_dir = Path(model.source).parent if model.source else Path(".")
        for name, link in model.links.items():
            path = self.link_path(name)
            wxyz, pos = _wxyz_position(self._poses[name])
            self._frames[name] = server.scene.add_frame(path, show_axes=False, wxyz=wxyz, position=pos)
            for i, geom in enumerate(link.visuals):
                mesh = geometry_mesh(geom, urdf_dir)
                if mesh is not None:
                    _add_mesh(server, f"{path}/visual{i}", mesh, color or _rgb(geom.rgba), opacity, geom.origin)

    def link_path(self, link: str) -> str:
        """Scene path of a link's frame (things added below it move with the link)."""
        return f"{self.root}/{link}"

    def frame(self, link: str) -> Any:
        """The viser frame handle of a link (its pose and visibility as sent to the browser)."""
        return self._frames[link]

    def set_joints(self, q: Mapping[str, float]) -> int:
        """Pose the robot for these joint values (the others keep theirs); returns how many links moved."""
        changed = {name: value for name, value in q.items() if name in self.q and self.q[name] != value}
        if not changed:
            return 0
        self.q.update(changed)
        moved = 0
        for name, pose in self.model.link_poses(self.q).items():
            frame = self._frames.get(name)
            if frame is None or np.array_equal(pose, self._poses[name]):
                continue
            frame.wxyz, frame.position = _wxyz_position(pose)
            self._poses[name] = pose
            moved += 1
        return moved

    def set_visible(self, visible: bool) -> None:
        self.root_frame.visible = visible

    def show_only_where_apart(self, other: RobotScene, tolerance: float = GHOST_TOLERANCE) -> None:
        """Show only the links whose pose differs from ``other``'s (the ghost where reference and measurement
        disagree): a ghost drawn over the identical solid robot would only wash it out."""
        for name, frame in self._frames.items():
            apart = bool(np.abs(self._poses[name] - other._poses[name]).max() > tolerance)
            if frame.visible != apart:
                frame.visible = apart


class CollisionScene:
    """The collision gate's robot primitives, posed like the solid robot; hidden unless toggled on, except the
    primitives of parts flagged in mds-collide, which turn magenta and show even when toggled off."""

    def __init__(self, server: viser.ViserServer, model: CollisionModel) -> None:
        self.model = model
        self._robot = [k for k, p in enumerate(model.primitives) if p.group != "world"]
        self._q = np.zeros(len(model.joint_names))
        poses = model.primitive_poses(self._q)
        self._poses = {k: poses[k] for k in self._robot}
        self.handles: dict[int, Any] = {}
        for k in self._robot:
            p = model.primitives[k]
            mesh = primitive_mesh(p.kind, p.size)
            path = f"{COLLISION_PATH}/{_node_name(p.name)}"
            self.handles[k] = _add_mesh(server, path, mesh, COLLISION_RGB, COLLISION_OPACITY, poses[k], visible=False)
        self._show = False
        self.highlighted_parts: set[int] = set()

    def set_joints(self, q: Mapping[str, float]) -> None:
        vector = np.array([q.get(name, old) for name, old in zip(self.model.joint_names, self._q, strict=True)])
        if np.array_equal(vector, self._q):
            return
        self._q = vector
        poses = self.model.primitive_poses(vector)
        for k in self._robot:
            if not np.array_equal(poses[k], self._poses[k]):
                self.handles[k].wxyz, self.handles[k].position = _wxyz_position(poses[k])
                self._poses[k] = poses[k]

    def show(self, visible: bool) -> None:
        self._show = visible
        self._restyle()

    def highlight(self, parts: set[int]) -> None:
        """Flag the legacy COLLIDE_* parts in ``parts`` (all their primitives), un-flag the others."""
        if parts != self.highlighted_parts:
            self.highlighted_parts = set(parts)
            self._restyle()

    def _is_hot(self, k: int) -> bool:
        return self.model.primitives[k].part in self.highlighted_parts

    def _restyle(self) -> None:
        for k, handle in self.handles.items():
            hot = self._is_hot(k)
            handle.color = HIGHLIGHT_RGB if hot else COLLISION_RGB
            handle.opacity = HIGHLIGHT_OPACITY if hot else COLLISION_OPACITY
            handle.visible = hot or self._show


def load_world(path: Path, robot_zero: np.ndarray) -> list[WorldObject]:
    """World objects from config/world.yaml, parsed as the collision gate parses them (a missing file: none).

    ``robot_zero`` is the torso pose at WST = 0, the ``robot`` frame. Bad entries raise ValueError naming them.
    """
    return _load_world(path, robot_zero)


# --------------------------------------------------------------------------------------------------
# Channels: read-only, opened when they appear
# --------------------------------------------------------------------------------------------------


def ChannelWatch(name: str, ctype: type[ctypes.Structure], retry: float = RETRY_S) -> Latest:  # noqa: N802
    """The viewer's channel reader: the shared read-only watcher, re-checking a quiet channel every ``retry`` s."""
    return Latest(name, ctype, retry=retry)


def joint_values(state: Any, attr: str, names: Sequence[str]) -> tuple[dict[str, float], list[str]]:
    """``state.joint[addr].<attr>`` of the named joints; non-finite values are left out and listed."""
    values: dict[str, float] = {}
    bad: list[str] = []
    for name in names:
        value = float(getattr(state.joint[lookup(name).address], attr))
        if math.isfinite(value):
            values[name] = value
        else:
            bad.append(name)
    return values, bad


def collided_parts(collide: Any) -> set[int]:
    """Legacy COLLIDE_* indices flagged in an MDS_COLLIDE (``joint[part].isCollide``)."""
    return {i for i in range(mds.MDS_COLLIDE_JNT_NUM) if collide.joint[i].isCollide}


@dataclass
class IkTarget:
    """What the IK marker shows: the tool position asked for (robot frame), a caption and a colour."""

    position: np.ndarray
    text: str
    rgb: tuple[int, int, int]


def _arm_name(arm: int) -> str:
    return "left" if arm == mds.LEFT else "right"


def ik_request_target(ik: Any) -> IkTarget | None:
    """The target of an MDS_IK request (``mds-ik``), or None if it names no arm or holds NaN/Inf."""
    arm = int(ik.move)
    if arm not in (mds.RIGHT, mds.LEFT):
        return None
    a = ik.arm[arm]
    position = np.array([a.t_x, a.t_y, a.t_z], dtype=float)
    if not np.all(np.isfinite(position)):
        return None
    return IkTarget(position, f"IK {_arm_name(arm)}: requested ({int(a.ik_method)} DOF)", IK_REQUEST_RGB)


def ik_status_target(status: Any) -> IkTarget | None:
    """The target of the IK node's answer (``mds-ik-state``), captioned with the outcome."""
    arm = int(status.arm)
    position = np.array(status.target[:3], dtype=float)
    if arm not in (mds.RIGHT, mds.LEFT) or not np.all(np.isfinite(position)):
        return None
    outcome = STATUS_NAMES.get(int(status.status), f"status {int(status.status)}")
    text = f"IK {_arm_name(arm)}: {outcome} ({int(status.dof)} DOF)"
    if int(status.status) == IK_SOLVED and math.isfinite(status.error):
        text += f", error {status.error:.2g}"
    rgb = {IK_SOLVED: IK_RGB, IK_UNREACHABLE: IK_FAILED_RGB}.get(int(status.status), IK_OTHER_RGB)
    return IkTarget(position, text, rgb)


# --------------------------------------------------------------------------------------------------
# The viewer
# --------------------------------------------------------------------------------------------------


@dataclass
class ViewerOptions:
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    rate_hz: float = DEFAULT_RATE_HZ
    urdf: Path | None = None
    world: Path | None = None
    sliders: bool = True  # offer the slider panel at all (its toggle is still off by default)
    url_file: Path | None = None


class Viewer:
    """The viser server, the scene and the GUI; :meth:`tick` brings them up to date with the channels."""

    def __init__(self, options: ViewerOptions) -> None:
        import viser  # lazy: ~0.4 s (measured, -X importtime), only a running viewer needs it

        self.options = options
        self.model = kin.load_model(options.urdf)  # None: the package's urdf/mds.urdf
        _use_shipped_client()
        self.door = Door(new_token(), options.host)  # the page and its websocket need the token (viewer_door)
        with guarded(self.door):
            self.server = viser.ViserServer(host=options.host, port=options.port, label="MDS", verbose=False)
        if not self.door.installed:  # fail closed: never serve a page that moves the robot without the token
            self.server.stop()
            raise OSError("this viser does not serve through websockets.asyncio.server.serve: the token check "
                          "cannot be installed; refusing to serve")
        # viser opens a public tunnel when a page asks for a share link: never from this viewer.
        self.server.request_share_url = _refuse_share  # type: ignore[method-assign]
        self.server.gui.configure_theme(control_layout="fixed", show_share_button=False, brand_color=(40, 90, 160))
        self.server.scene.set_up_direction("+z")
        # No HDRI environment: viser would fetch it from the server's hdri/ folder, which lacks the default one
        # (the page then renders without it anyway); the default lights are enough for primitives.
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.add_grid("/grid", width=4.0, height=4.0, cell_size=0.25, plane="xy")
        self.server.on_client_connect(self._on_connect)

        self.solid = RobotScene(self.server, self.model, SOLID_PATH)
        self.ghost = RobotScene(self.server, self.model, GHOST_PATH, color=GHOST_RGB, opacity=GHOST_OPACITY)
        self.ghost.show_only_where_apart(self.solid)
        self.names = [n for n in MODEL_JOINTS if n in self.model.joints]
        effective = current_limits()  # the one limit authority: what the mux, the gate and the daemon accept
        self.limits = {n: _slider_range(self.model.joints[n], effective.range(n)) for n in self.names}
        self.problems: list[str] = []  # shown under the status line
        self.collision = self._collision_scene()
        self.world_frame = self.server.scene.add_frame(WORLD_PATH, show_axes=False)
        self.world_path = options.world or system_world() or paths.config_path("world.yaml")
        self._add_world(self.world_path)
        self.ik_marker = self.server.scene.add_icosphere(
            f"{self.solid.link_path('torso')}/ik_target", radius=0.03, color=IK_RGB, visible=False, cast_shadow=False
        )
        self.ik_label = self.server.scene.add_label(f"{self.solid.link_path('torso')}/ik_label", "", visible=False)

        self.state = ChannelWatch(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        self.collide = ChannelWatch(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
        self.ik = ChannelWatch(mds.MDS_CHAN_IK_NAME, mds.MDS_IK)
        self.ik_state = ChannelWatch(mds.MDS_CHAN_IK_STATE_NAME, _ik_status_type())
        self.ik_shown: IkTarget | None = None
        self.last_state: Any = None
        self._last_state_at = 0.0
        self.state_frames = 0  # mds-state frames applied (status line, bench)
        self._rate_window = (time.monotonic(), 0)
        self._state_rate = 0.0
        self._bad_values: list[str] = []
        self._ref_lock = threading.Lock()
        self._refs: RefWriter | None = None  # set while the sliders are on
        self._build_gui()
        self.plot = LivePlot(self.server.gui)  # commanded vs measured, last N s (viewer_plot)

    # ---- scene setup -------------------------------------------------------------------------------

    def _collision_scene(self) -> CollisionScene | None:
        try:
            return CollisionScene(self.server, load_model(self.options.urdf))
        except (ImportError, OSError, ValueError) as exc:
            self.problems.append(f"collision model not shown: {exc}")
            print(f"viewer: {self.problems[-1]}", file=sys.stderr)
            return None

    def _add_world(self, path: Path) -> None:
        """Draw the world objects: the enabled ones translucent, disabled ones as wireframes."""
        try:
            objects = load_world(path, self.model.link_poses()["torso"])
        except (OSError, ValueError) as exc:
            self.problems.append(f"world objects not shown: {exc}")
            print(f"viewer: {self.problems[-1]}", file=sys.stderr)
            return
        for obj in objects:
            mesh = primitive_mesh(obj.kind, obj.size)
            path_ = f"{WORLD_PATH}/{_node_name(obj.name)}"
            _add_mesh(self.server, path_, mesh, WORLD_RGB, WORLD_OPACITY, obj.pose, wireframe=not obj.enabled)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        """Start a page looking at the robot from the front-left, at chest height, unless it asked for a view
        itself (viser's ``?initialCameraPosition=...`` URL parameters)."""
        if np.allclose(client.camera.position, VISER_DEFAULT_CAMERA) and np.allclose(client.camera.look_at, 0.0):
            client.camera.position = CAMERA_POSITION
            client.camera.look_at = CAMERA_LOOK_AT

    def _build_gui(self) -> None:
        gui = self.server.gui
        self.status = gui.add_markdown(f"**waiting for {mds.MDS_CHAN_STATE_NAME}**")
        with gui.add_folder("Show"):
            self.show_ghost = gui.add_checkbox("Reference ghost", True, hint="joint[].ref, translucent")
            self.show_collision = gui.add_checkbox("Collision primitives", False, hint="the collision gate's model")
            self.show_world = gui.add_checkbox("World objects", True)
            self.show_ik = gui.add_checkbox("IK target", True)
        self.show_ghost.on_update(lambda _: self.ghost.set_visible(self.show_ghost.value))
        self.show_collision.on_update(lambda _: self._show_collision_changed())
        self.show_world.on_update(lambda _: setattr(self.world_frame, "visible", self.show_world.value))
        self.show_ik.on_update(lambda _: self._show_ik_changed())
        self.sliders: dict[str, Any] = {}
        self.sliders_on: Any = None
        if not self.options.sliders:
            return
        with gui.add_folder("Joint sliders", expand_by_default=False):
            self.sliders_on = gui.add_checkbox(
                "Send references",
                False,
                hint=f"write goto-style references to {mds.MDS_CHAN_REF_FILTER_NAME} (mux, filter and collision "
                "gate apply)",
            )
            self.slider_status = gui.add_markdown("off: the sliders follow the reference")
            for name in self.names:
                lower, upper = self.limits[name]
                slider = gui.add_slider(name, min=lower, max=upper, step=0.01, initial_value=_clamp(0.0, lower, upper))
                slider.disabled = True
                slider.on_update(self._slider_callback(name))
                self.sliders[name] = slider
        self.sliders_on.on_update(lambda _: self._sliders_toggled())

    def _show_collision_changed(self) -> None:
        if self.collision:
            self.collision.show(self.show_collision.value)

    def _show_ik_changed(self) -> None:
        visible = bool(self.show_ik.value) and self.ik_shown is not None
        self.ik_marker.visible = self.ik_label.visible = visible

    def _show_ik_target(self, target: IkTarget) -> None:
        self.ik_shown = target
        self.ik_marker.position = target.position
        self.ik_marker.color = target.rgb
        self.ik_label.position = target.position + np.array([0.0, 0.0, 0.06])
        self.ik_label.text = target.text
        self._show_ik_changed()

    # ---- sliders: goto-style references into the safe pipeline -------------------------------------

    def _sliders_toggled(self) -> None:
        on = bool(self.sliders_on.value)
        with self._ref_lock:
            if self._refs is not None:
                self._refs.close()
                self._refs = None
            error = self._open_ref_channel() if on else ""
        if error:
            self.sliders_on.value = False  # calls us again, with on = False
            self.slider_status.content = f"**not sending:** {error}"
            return
        for slider in self.sliders.values():
            slider.disabled = not on
        if on:
            self.slider_status.content = f"**on:** moving a slider writes `{mds.MDS_CHAN_REF_FILTER_NAME}`"
        else:
            self.slider_status.content = "off: the sliders follow the reference"

    def _open_ref_channel(self) -> str:
        """Open mds-ref-filter for writing (never create it: no running system, no references). The viewer writes
        with its own process's rights: a viewer started by a user who may not write the channel stays read-only,
        whoever opens its page."""
        if self.last_state is None:
            return f"no `{mds.MDS_CHAN_STATE_NAME}` frame yet"
        path = ach.shm_path(mds.MDS_CHAN_REF_FILTER_NAME)
        if os.path.exists(path) and not os.access(path, os.R_OK | os.W_OK):
            return (f"read-only: this viewer runs as {_user_name()}, who may not write `{mds.MDS_CHAN_REF_FILTER_NAME}`"
                    " (only users who may write the reference channels move the robot from the viewer)")
        refs = RefWriter(mds.MDS_CHAN_REF_FILTER_NAME)
        try:
            refs.open()
        except RefWriteError as exc:
            return str(exc)
        self._refs = refs
        return ""

    def _slider_callback(self, name: str) -> Callable[[Any], None]:
        def on_update(event: Any) -> None:
            if event.client is None:  # set by the viewer itself (following the reference)
                return
            self.send_goto(name, float(self.sliders[name].value))

        return on_update

    def send_goto(self, name: str, value: float) -> bool:
        """Write one reference frame to mds-ref-filter: its newest frame (or, if it has none, the references the
        daemon holds now) with joint ``name`` set to ``value``, so other joints keep their targets.

        Refuses non-finite or out-of-limit values; does nothing while the slider toggle is off.
        """
        lower, upper = self.limits[name]
        if not (math.isfinite(value) and lower <= value <= upper):
            self.slider_status.content = f"**refused** {name} = {value!r}: outside [{lower:.3f}, {upper:.3f}]"
            return False
        with self._ref_lock:
            if self._refs is None or self.last_state is None:
                return False
            try:
                self._refs.put({lookup(name).address: value}, self.last_state)
            except RefWriteError as exc:
                self.slider_status.content = f"**not sent:** {exc}"
                return False
        self.slider_status.content = f"**sent** {name} = {value:+.3f} rad to `{mds.MDS_CHAN_REF_FILTER_NAME}`"
        return True

    # ---- the update loop ---------------------------------------------------------------------------

    def tick(self) -> bool:
        """Read the channels and update the scene; returns True if the robot moved or a highlight changed."""
        changed = False
        now = time.monotonic()
        with self.server.atomic():
            state = self.state.read_new()
            if state is not None:
                changed |= self._apply_state(state, now)
            collide = self.collide.read_new()
            if self.collision is not None:
                parts = None
                if collide is not None:
                    parts = collided_parts(collide)
                elif state is not None and not self.collide.available:
                    parts = collided_parts(state.collide)  # no mds-collide channel: the daemon's copy
                if parts is not None and parts != self.collision.highlighted_parts:
                    self.collision.highlight(parts)
                    changed = True
            request, answer = self.ik.read_new(), self.ik_state.read_new()
            for target in (request and ik_request_target(request), answer and ik_status_target(answer)):
                if target is not None:  # the answer, read second, wins over its request
                    self._show_ik_target(target)
        self.plot.refresh(now)
        self._update_status(now)
        return changed

    def _apply_state(self, state: Any, now: float) -> bool:
        measured, bad_pos = joint_values(state, "pos", self.names)
        reference, bad_ref = joint_values(state, "ref", self.names)
        self._bad_values = [f"{n}.pos" for n in bad_pos] + [f"{n}.ref" for n in bad_ref]
        moved = self.solid.set_joints(measured) + self.ghost.set_joints(reference)
        if moved:
            self.ghost.show_only_where_apart(self.solid)
        if self.collision is not None:
            self.collision.set_joints(measured)
        self.last_state = state
        self._last_state_at = now
        self.state_frames += 1
        self.plot.add(now, state)
        if self.sliders_on is not None and not self.sliders_on.value:
            for name, value in reference.items():
                slider = self.sliders[name]
                if abs(slider.value - value) > 0.005:
                    slider.value = _clamp(value, *self.limits[name])
        return moved > 0

    def _update_status(self, now: float) -> None:
        start, frames = self._rate_window
        if now - start >= 1.0:
            self._state_rate = (self.state_frames - frames) / (now - start)
            self._rate_window = (now, self.state_frames)
        name = mds.MDS_CHAN_STATE_NAME
        if self.last_state is None:
            why = "no frame yet" if self.state.available else (
                "channel missing; retrying" if not ach.exists(name) else f"{self.state.error}; retrying")
            text = f"**waiting for {name}** ({why})"
        elif now - self._last_state_at > STALE_S:
            text = f"**{name} stale**: last frame {now - self._last_state_at:.0f} s ago"
        else:
            text = f"**{name} live**, {self._state_rate:.0f} frames/s"
        if self._bad_values:
            text += f"  \nnon-finite values skipped: {', '.join(self._bad_values)}"
        if self.collision is not None and self.collision.highlighted_parts:
            names = ", ".join(mds.COLLIDE_PART_NAMES[p] for p in sorted(self.collision.highlighted_parts))
            text += f"  \n**collision:** {names}"
        for problem in self.problems:
            text += f"  \n{problem}"
        if self.status.content != text:
            self.status.content = text

    def url(self) -> str:
        """The page's URL, with the token: the only way in (viewer_door)."""
        host = self.server.get_host()
        return f"http://{f'[{host}]' if ':' in host else host}:{self.server.get_port()}/{self.door.token}/"

    def run(self, stop: threading.Event) -> None:
        """Tick at ``rate_hz`` on an absolute schedule until ``stop`` is set."""
        period = 1.0 / self.options.rate_hz
        next_t = time.monotonic()
        while not stop.is_set():
            self.tick()
            next_t += period
            delay = next_t - time.monotonic()
            if delay < -period:  # fell behind (machine busy): skip ticks instead of bursting
                next_t = time.monotonic()
                delay = 0.0
            stop.wait(max(delay, 0.0))

    def close(self, timeout: float = 5.0) -> None:
        """Stop writing, then stop the server and wait (up to ``timeout`` s) until its event loop has ended: the
        port is closed when this returns."""
        for watch in (self.state, self.collide, self.ik, self.ik_state):
            watch.close()
        with self._ref_lock:
            if self._refs is not None:
                self._refs.close()
                self._refs = None
        loop = self.server.get_event_loop()
        loop.set_exception_handler(_quiet_teardown)
        self.server.stop()
        deadline = time.monotonic() + timeout
        while loop.is_running() and time.monotonic() < deadline:
            time.sleep(0.02)


def _quiet_teardown(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
    """The server's event-loop error handler once the viewer closes. viser 1.0 ends a connection's message tasks
    sloppily when the server stops with pages open: a producer raises StopAsyncIteration nobody retrieves and
    waiting tasks are dropped pending, which asyncio reports at exit as "Task exception was never retrieved" /
    "Task was destroyed but it is pending!". Those two, for these causes, are the normal end of a page's
    connection, not errors; anything else is still reported."""
    import websockets.exceptions

    exc = context.get("exception")
    message = str(context.get("message", ""))
    if message.startswith("Task was destroyed but it is pending") or (
        message.startswith("Task exception was never retrieved")
        and isinstance(exc, StopAsyncIteration | websockets.exceptions.ConnectionClosed)
    ):
        return
    loop.default_exception_handler(context)


def _use_shipped_client() -> None:
    """Serve the web client that ships in the viser wheel, never rebuild it.

    viser's start-up check scans every process on the machine (psutil; it crashes when one exits meanwhile)
    and rebuilds the client with node/yarn, downloaded from the network, whenever its sources look newer than
    the build. Neither belongs in a robot's viewer: check that the build is there and use it.
    """
    from viser import _client_autobuild  # lazy: viser, as in Viewer.__init__

    def check() -> None:
        if not (_client_autobuild.build_dir / "index.html").is_file():
            raise FileNotFoundError(f"viser's web client is missing ({_client_autobuild.build_dir}); reinstall viser")

    _client_autobuild.ensure_client_is_built = check


def _user_name() -> str:
    import pwd

    uid = os.geteuid()
    try:
        return f"{pwd.getpwuid(uid).pw_name} (uid {uid})"
    except KeyError:
        return f"uid {uid}"


def write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` readable by this user only (0600, atomic): the URL file carries the token."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    tmp.replace(path)


def _ik_status_type() -> type[ctypes.Structure]:
    return MDS_IK_STATUS


def _refuse_share(*_args: object, **_kwargs: object) -> None:
    print("viewer: share links are disabled", file=sys.stderr)


def _slider_range(joint: kin.Joint, effective: tuple[float, float] | None = None) -> tuple[float, float]:
    """The URDF limits (continuous joints get one turn each way), narrowed to the ``effective`` limits
    (``mds_ach.kinematics.limits``), so a slider never offers a value the pipeline refuses."""
    lower = joint.lower if math.isfinite(joint.lower) else -math.pi
    upper = joint.upper if math.isfinite(joint.upper) else math.pi
    if effective is not None:
        lower, upper = max(lower, effective[0]), min(upper, effective[1])
    return lower, upper


def _clamp(value: float, lower: float, upper: float) -> float:
    return min(max(value, lower), upper)


def _node_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name) or "object"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def free_port(host: str) -> int:
    """A port the OS reports free on ``host`` (for --port 0; viser itself would report 0 as its port)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


# --------------------------------------------------------------------------------------------------
# Command line: the foreground process and the `mds-ach sim` verb
# --------------------------------------------------------------------------------------------------


def add_server_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=DEFAULT_HOST, help=f"address to serve on (default {DEFAULT_HOST}, loopback)")
    parser.add_argument(
        "--port",
        type=count(0, 65535),
        default=DEFAULT_PORT,
        help=f"port (default {DEFAULT_PORT}; the next free one if taken; 0 picks any free port)",
    )
    parser.add_argument(
        "--rate", type=bounded(0.0, 1000.0, above=True, unit="Hz"), default=DEFAULT_RATE_HZ,
        help=f"scene updates per second (default {DEFAULT_RATE_HZ:g})",
    )
    parser.add_argument("--urdf", type=Path, default=None, help="robot model (default: the package's urdf/mds.urdf)")
    parser.add_argument("--world", type=Path, default=None,
                        help="world objects YAML (default: the running system's, the one its collision gate started "
                             "with, else config/world.yaml)")
    parser.add_argument(
        "--sliders",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="offer the joint-slider panel (its toggle is off by default). Default: on for a loopback --host, "
        "off otherwise, since anyone who can open the page could move the robot",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m mds_ach.tools.viewer",
        description="3-D view of the MDS robot in the browser, live from the Ach channels: measured pose (solid), "
        "reference (ghost), collision primitives, world objects, collisions (magenta) and the IK target. "
        "Read-only, except the optional slider panel that writes mds-ref-filter (with this user's rights). The URL "
        "it prints carries an access token: without it the page is refused. Ctrl-C stops it. "
        "`mds-ach sim` runs it in the background.",
    )
    add_server_arguments(parser)
    parser.add_argument("--url-file", type=Path, default=None, help="write the URL here once serving (mds-ach sim)")
    return parser


def options_from_args(args: argparse.Namespace) -> ViewerOptions:
    """Validated options; bad values end the program with a clear message (exit 2)."""
    if not (math.isfinite(args.rate) and 1.0 <= args.rate <= 120.0):
        raise SystemExit(f"error: --rate must be between 1 and 120 updates per second, got {args.rate}")
    if not 0 <= args.port <= 65535:
        raise SystemExit(f"error: --port must be 0..65535, got {args.port}")
    for what, path in (("--urdf", args.urdf), ("--world", args.world)):
        if path is not None and not path.is_file():
            raise SystemExit(f"error: {what} {path}: no such file")
    return ViewerOptions(
        host=args.host,
        port=args.port,
        rate_hz=args.rate,
        urdf=args.urdf,
        world=args.world,
        sliders=args.sliders if args.sliders is not None else is_loopback(args.host),
        url_file=getattr(args, "url_file", None),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run the viewer in the foreground until Ctrl-C or SIGTERM (exit 0)."""
    args = build_parser().parse_args(strip_ros_args(sys.argv[1:] if argv is None else argv))
    options = options_from_args(args)
    if options.port == 0:
        options.port = free_port(options.host)
    if not is_loopback(options.host):
        print(f"viewer: serving on {options.host}: anyone who can reach it sees the robot", file=sys.stderr)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        viewer = Viewer(options)
    except (OSError, ValueError) as exc:
        print(f"viewer: cannot start: {exc}", file=sys.stderr)
        return 1
    url = viewer.url()
    if options.url_file is None:
        print(f"mds-ach viewer: {url}  (the URL carries its access token: keep it to yourself)", flush=True)
    else:  # the background viewer's log may be readable by others: the token goes only to the 0600 URL file
        print(f"mds-ach viewer: serving on {url.rsplit('/', 2)[0]}/ (URL with the token in {options.url_file})",
              flush=True)
        write_private(options.url_file, url + "\n")
    try:
        viewer.run(stop)
    finally:
        viewer.close()
        if options.url_file is not None:
            options.url_file.unlink(missing_ok=True)
    return 0


def system_world(run_dir: Path | None = None) -> Path | None:
    """The world file the running system's collision gate started with (recorded by the launcher in the runtime
    dir), so the viewer draws the objects the gate checks; None when no start recorded one."""
    from mds_ach.tools.launcher import WORLD_RECORD  # lazy, as the launcher imports this module lazily too

    try:
        text = ((run_dir or paths.runtime_dir()) / WORLD_RECORD).read_text().strip()
    except OSError:
        return None
    return Path(text) if text and Path(text).is_file() else None


def _is_viewer(argv: list[str]) -> bool:
    return "mds_ach.tools.viewer" in argv


def running_viewer(run_dir: Path | None = None) -> int | None:
    """The background viewer's pid, if its pid file names a live viewer (never a recycled pid, a zombie or a
    dead task)."""
    return background.running_pid((run_dir or paths.runtime_dir()) / SIM_PID, _is_viewer)


def start_background(argv: Sequence[str], timeout: float = 60.0) -> int:
    """Start ``python -m mds_ach.tools.viewer ARGV`` detached, wait until it serves, print its URL."""
    run_dir = paths.runtime_dir()
    run_dir.mkdir(parents=True, exist_ok=True)
    pid_file, log_file, url_file = run_dir / SIM_PID, run_dir / SIM_LOG, run_dir / SIM_URL
    pid = running_viewer()
    if pid is not None:
        url = url_file.read_text().strip() if url_file.is_file() else "(starting)"
        print(f"viewer already running (pid {pid}): {url}")
        return 0
    url_file.unlink(missing_ok=True)
    cmd = [sys.executable, "-m", "mds_ach.tools.viewer", *argv, "--url-file", str(url_file)]
    proc = background.spawn_detached(cmd, log_file)
    background.write_pid_file(pid_file, proc.pid)
    deadline = time.monotonic() + timeout
    try:
        while not url_file.is_file():
            if proc.poll() is not None:
                background.remove_pid_file(pid_file)
                print(f"viewer failed to start (exit {proc.returncode}); last lines of {log_file}:", file=sys.stderr)
                print("\n".join(background.log_tail(log_file, 15)), file=sys.stderr)
                return 1
            if time.monotonic() > deadline:
                print(f"viewer did not start within {timeout:.0f} s (pid {proc.pid}); see {log_file}",
                      file=sys.stderr)
                return 1
            time.sleep(0.1)
    except BaseException:  # Ctrl-C while waiting: never leave a half-started viewer behind
        background.stop_pid(proc.pid, reap=proc.poll)
        background.remove_pid_file(pid_file)
        raise
    print(f"viewer running (pid {proc.pid}): {url_file.read_text().strip()}")
    print(LIFETIME_NOTE.format(url_file=url_file))
    return 0


LIFETIME_NOTE = (
    "The URL carries the viewer's access token (also in {url_file}, readable only by you): without it the page and "
    "its websocket are refused. The viewer stops with the system: Ctrl-C of `mds-ach run` / `make run`, "
    "`mds-ach stop`, `kill`, `killall`; `mds-ach sim kill` stops it alone."
)


def stop_viewer(run_dir: Path | None = None, timeout: float = 10.0) -> int | None:
    """Stop the background viewer of ``run_dir`` (SIGTERM, SIGKILL after ``timeout`` s) and remove its pid and URL
    files; returns the pid it stopped, None if none ran. Used by `sim kill` and by the launcher's stops."""
    run_dir = run_dir or paths.runtime_dir()
    pid = running_viewer(run_dir)
    if pid is not None:
        background.stop_pid(pid, timeout)
    background.remove_pid_file(run_dir / SIM_PID)
    (run_dir / SIM_URL).unlink(missing_ok=True)
    return pid


def stop_background(timeout: float = 10.0) -> int:
    """`mds-ach sim kill`."""
    pid = stop_viewer(timeout=timeout)
    print("viewer not running" if pid is None else f"viewer stopped (pid {pid})")
    return 0


def add_sim_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of the `mds-ach sim` verb."""
    parser.description = (
        "Start the 3-D viewer in the browser in the background and print its URL, which carries an access token "
        "(without it the page is refused). It only reads the channels, except the optional sliders (written with "
        "the rights of the user who starts it), so it can be started and stopped while the system runs. It stops "
        "with the system (Ctrl-C of `mds-ach run`, `mds-ach stop`); `mds-ach sim kill` stops it alone."
    )
    parser.add_argument("action", nargs="?", choices=["start", "kill"], default="start", help="default: start")
    add_server_arguments(parser)


def run_sim(args: argparse.Namespace) -> int:
    """Handler of the `mds-ach sim` verb."""
    if args.action == "kill":
        return stop_background()
    options_from_args(args)  # clear messages here, before anything is started
    forwarded = ["--host", args.host, "--port", str(args.port), "--rate", str(args.rate)]
    if args.urdf is not None:
        forwarded += ["--urdf", str(args.urdf.resolve())]
    if args.world is not None:
        forwarded += ["--world", str(args.world.resolve())]
    if args.sliders is not None:
        forwarded.append("--sliders" if args.sliders else "--no-sliders")
    return start_background(forwarded)


if __name__ == "__main__":
    sys.exit(main())
