"""IK node (``ros2 run mds_ach ik``): Cartesian requests on ``mds-ik`` -> joint references for one arm.

For every ``MDS_IK`` request (``move``: 0 right, 1 left; ``arm[move].ik_method``: task DOF 1..6 taken in
the order x, y, z, roll, pitch, yaw from ``t_x t_y t_z r_x r_y r_z``; robot frame, m and rad):

1. refuse bad requests (arm not 0/1, DOF not 1..6, NaN/Inf among the used values) with a message;
2. seed from the current reference (``mds-state`` joint[].ref, as the original did; else ``mds-ref-gated``,
   what the daemon executes);
3. solve with ``mds_ach.ik`` inside the effective limits (``mds_ach.kinematics.limits``: URDF & joint table); candidate
   poses and the joint-space path to them are collision-checked (``mds_ach.kinematics.collision``, with the
   world file of ``--world``) against the rest of the robot where it is commanded now AND with the other arm at
   its commanded target (the mux output ``mds-ref-mux``), so a goal the other arm is heading for counts too;
   ``on_collision`` decides what happens when every solution (or its path) collides:
   ``approach`` (default, as in the paper): the nearest solution is sent anyway and the collision gate stops
   the arm where the collision model's parts touch; ``refuse``: nothing moves (unreachable, "N colliding");
4. on success write the arm's six references into the node's output channel: ``mds-ref-ik``, the ik input
   of the mux (``--output mds-ref-filter`` for the legacy set-up without a mux). The frame is the newest one
   on that channel (else the mux output / ``mds-ref-gated`` / ``mds-state``) with only those six joints replaced,
   so other joints are never touched. Never ``mds-ref`` (the mux's ``direct`` input) nor the daemon's input
   ``mds-ref-gated``: the IK controller's priority and joints, the filter and the collision gate stay in the
   path. An unreachable target writes nothing (the arm holds) and says so.
5. after a solution was written, watch ``mds-hold`` until the arm should have arrived: when the gate stops that
   arm at contact (its ``HOLD_CANCEL``, source ``collision``), a second status frame with the same ``seq`` says
   ``IK_STOPPED_AT_CONTACT`` and "stopped at contact: right hand / left hand".

Every request gets an answer on ``mds-ik-state`` (``MDS_IK_STATUS``, see ``mds_ach.robot.msgs.ik_status``) and on the
ROS topic ``mds/ik_status`` (``mds_ach_interfaces/msg/IkStatus``, transient local, made from ``status_to_dict``).
"""

from __future__ import annotations

import argparse
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mds_ach_interfaces.msg import IkStatus
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile

import mds_ach as mds
from mds_ach.kinematics import ik
from mds_ach.kinematics.collision import check_world_file, load_model
from mds_ach.kinematics.limits import current_limits
from mds_ach.nodes.mux import controller_for
from mds_ach.nodes.pipeline import current_reference, make_ref
from mds_ach.nodes.rosnode import Param, declare, find, ros_log, run_node, start_worker
from mds_ach.nodes.status_msgs import ik_status_msg
from mds_ach.robot import contracts
from mds_ach.robot.channels import ChannelGuard, StructChannel
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs.hold import HOLD_CANCEL, MDS_HOLD
from mds_ach.robot.msgs.ik_status import (
    IK_BAD_REQUEST,
    IK_NOT_APPLIED,
    IK_NOT_READY,
    IK_PROBE_MOVE,
    IK_SOLVED,
    IK_STATUS_TOPIC,
    IK_STOPPED_AT_CONTACT,
    IK_UNREACHABLE,
    MDS_IK_STATUS,
    PROBE_ANSWER,
    set_message,
    status_to_dict,
)
from mds_ach.robot.muxverdict import VerdictWatch

ARM_JOINTS: dict[int, tuple[str, ...]] = {mds.RIGHT: RIGHT_ARM, mds.LEFT: LEFT_ARM}
ARM_NAMES: dict[int, str] = {mds.RIGHT: "right", mds.LEFT: "left"}
SafetyFactory = Callable[[np.ndarray, "np.ndarray | None"], ik.SafetyCheck]
ON_COLLISION = ("approach", "refuse")
WATCH_SPEED = 0.5  # rad/s: the slowest an arm is assumed to travel while the node watches for its stop at contact
WATCH_EXTRA = 2.0  # s added to that travel time (filter start-up, gate release)


@dataclass
class IkNodeConfig:
    output: str = mds.MDS_CHAN_REF_IK_NAME
    tolerance: float = ik.DEFAULT_TOLERANCE  # m; angles within ik.DEFAULT_ANGLE_TOLERANCE, checked separately
    max_iterations: int = ik.DEFAULT_ITERATIONS
    timeout: float = 2.0  # s, cap on one solve whatever the iteration count
    collision_check: bool = True
    on_collision: str = "approach"  # what a colliding solution does: approach (sent, stops at contact) | refuse
    seed_sources: tuple[str, ...] = (mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME)
    base_sources: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"tolerance must be > 0, got {self.tolerance}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.on_collision not in ON_COLLISION:
            raise ValueError(f"on_collision must be one of {', '.join(ON_COLLISION)}, got {self.on_collision!r}")
        if self.output in (mds.MDS_CHAN_REF_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME):
            # mds-ref-gated is the daemon's input (only the gate writes it); mds-ref is the mux's 'direct' input for
            # legacy expert clients, whose priority and joints are not the IK controller's.
            raise ValueError(f"the ik node never writes mds-ref directly nor {mds.MDS_CHAN_DAEMON_INPUT_NAME}: "
                             "use mds-ref-ik (mux) or mds-ref-filter")
        if not self.base_sources:
            self.base_sources = (self.output, mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME,
                                 mds.MDS_CHAN_STATE_NAME)


@dataclass
class Outcome:
    """What one request produced: the status frame, and the six (address, value) refs to write if solved."""

    status: MDS_IK_STATUS
    refs: dict[int, float] | None = None
    collides: bool = False  # approach: the solution or its path collides; the gate stops the arm at contact


class IkService:
    """Request -> solution, without channels (the runner and the tests feed it)."""

    def __init__(self, config: IkNodeConfig, limits: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
                 safety: SafetyFactory | None = None) -> None:
        self.config = config
        self.safety = safety
        self.options = ik.IKOptions(tolerance=config.tolerance, max_iterations=config.max_iterations,
                                    timeout=config.timeout)
        self.solvers = {arm: ik.IKSolver(name, self.options, limits=(limits or {}).get(arm))
                        for arm, name in ARM_NAMES.items()}
        self.seq = 0

    def handle(self, request: mds.MDS_IK, current: np.ndarray | None,
               commanded: np.ndarray | None = None) -> Outcome:
        """Solve one request. ``current``: the 100 current refs by address (None = unknown: not ready);
        ``commanded``: the mux output (where the other arm is heading), checked too when given."""
        self.seq += 1
        st = MDS_IK_STATUS()
        st.seq = self.seq
        st.arm = -1
        move = int(request.move)
        if move == IK_PROBE_MOVE:  # someone (the launcher) asks whether this node answers
            return self._refuse(st, IK_BAD_REQUEST, PROBE_ANSWER)
        if move not in ARM_NAMES:
            return self._refuse(st, IK_BAD_REQUEST, f"bad request: move must be 0 (right) or 1 (left), got {move}")
        st.arm = move
        a = request.arm[move]
        values = [a.t_x, a.t_y, a.t_z, a.r_x, a.r_y, a.r_z]
        for i, v in enumerate(values):
            st.target[i] = v
        dof = int(a.ik_method)
        st.dof = dof
        if not 1 <= dof <= 6:
            return self._refuse(st, IK_BAD_REQUEST, f"bad request: ik_method (DOF) must be 1..6, got {dof}")
        used = np.array(values[:dof], dtype=float)
        if not np.all(np.isfinite(used)):
            return self._refuse(st, IK_BAD_REQUEST, f"bad request: NaN/Inf in the target {used.tolist()}")
        if current is None or not np.all(np.isfinite(current)):
            return self._refuse(st, IK_NOT_READY, "no current reference (is the daemon running?); nothing moved")
        addresses = [BY_SHORT[s].address for s in ARM_JOINTS[move]]
        solver = self.solvers[move]
        if commanded is not None and not np.all(np.isfinite(commanded)):
            commanded = None
        solver.is_safe = self.safety(current, commanded) if self.safety is not None else None
        result = solver.solve(used, ik.DOF_ORDERS[dof], current[addresses])
        collides = False
        if not result.success and result.rejected_unsafe and self.config.on_collision == "approach":
            # Every solution (or its path) collides: send the nearest one; the gate stops the arm at contact.
            solver.is_safe = None
            again = solver.solve(used, ik.DOF_ORDERS[dof], current[addresses])
            if again.success:
                again.time += result.time
                result, collides = again, True
        st.iterations = result.iterations
        st.error = result.error
        st.solve_time = result.time
        for i, v in enumerate(result.q):
            st.q[i] = v
        if not result.success:
            st.status = IK_UNREACHABLE
            unsafe = f", {result.rejected_unsafe} colliding" if result.rejected_unsafe else ""
            set_message(st, f"unreachable: best error {result.error:.3g} after {result.iterations} iterations"
                            f"{unsafe}; nothing moved")
            return Outcome(st)
        st.status = IK_SOLVED
        note = "; path collides: stops at contact" if collides else ""
        set_message(st, f"solved in {result.iterations} iterations, error {result.error:.2g}{note}")
        return Outcome(st, dict(zip(addresses, result.q.tolist(), strict=True)), collides)

    @staticmethod
    def _refuse(st: MDS_IK_STATUS, code: int, message: str) -> Outcome:
        st.status = code
        st.error = math.nan
        set_message(st, message)
        return Outcome(st)


def arm_limits(robot: str | None = None) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per-arm (lower, upper): the effective limits (URDF & the active robot's joint table, ``mds-limits`` when
    the daemon published them), so a solution is never one the mux or the gate would refuse."""
    limits = current_limits(robot)
    return {arm: limits.of(names) for arm, names in ARM_JOINTS.items()}


def collision_safety(log: Callable[[str, str], None], world: str | None = None) -> SafetyFactory | None:
    """A factory of ``is_safe`` hooks from the package collision model (and ``world``, a world file; None: the
    package's config/world.yaml), or None (with a warning) if unavailable.

    A candidate is unsafe when the model predicts a collision that involves the solved arm, with the rest of the
    body at the current reference, or with the other arm at its commanded target (``commanded``, the mux
    output: where it is heading; None: not known).
    """
    try:
        model = load_model(world=world)
    except Exception as exc:  # missing fcl, bad config: the gate downstream still checks every reference
        log("warn", f"IK candidates are not collision-checked ({exc}); the collision gate still is")
        return None
    addresses = {name: [BY_SHORT[s].address for s in joints] for name, joints in
                 (("left", LEFT_ARM), ("right", RIGHT_ARM))}

    def factory(current: np.ndarray, commanded: np.ndarray | None = None) -> ik.SafetyCheck:
        base = current.copy()

        def is_safe(q_arm: np.ndarray, arm: str) -> bool:
            ref = base.copy()
            ref[addresses[arm]] = q_arm
            poses = [model.q_from_ref(ref)]
            if commanded is not None:
                other = addresses["right" if arm == "left" else "left"]
                if not np.array_equal(commanded[other], ref[other]):
                    heading = ref.copy()
                    heading[other] = commanded[other]
                    poses.append(model.q_from_ref(heading))
            return not any(arm in r.arms for r in model.check_many(np.array(poses)))

        return is_safe

    return factory


# --------------------------------------------------------------------------------------------- Ach side


@dataclass
class _Watch:
    """A solved request whose arm may still be stopped at contact on its way (see ``IkRunner``)."""

    status: MDS_IK_STATUS  # the answer already published
    addresses: tuple[int, ...]
    since: float  # CLOCK_MONOTONIC when the solution was written
    until: float  # when the arm should have arrived; the watch ends then


def stopped_at_contact(hold: MDS_HOLD, watch: _Watch) -> str | None:
    """The gate's reason when ``hold`` cancels the watched arm's command at contact (else None)."""
    if hold.action != HOLD_CANCEL or hold.time < watch.since:
        return None
    if bytes(hold.source).split(b"\0", 1)[0] != b"collision":
        return None
    if not all(hold.joints[a] for a in watch.addresses):
        return None
    return bytes(hold.reason).split(b"\0", 1)[0].decode("ascii", "replace")


class IkRunner:
    """The request loop: wait on ``mds-ik``, solve, write the output channel and ``mds-ik-state``."""

    def __init__(self, service: IkService, log: Callable[[str, str], None] | None = None,
                 on_status: Callable[[MDS_IK_STATUS], None] | None = None) -> None:
        self.service = service
        self.config = service.config
        self.log = log or (lambda level, msg: print(f"[ik] {level}: {msg}", flush=True))
        self.on_status = on_status
        self._stop = threading.Event()
        self._requests: Any = None
        self._verdicts: VerdictWatch | None = None
        self.ready = threading.Event()
        self.handled = 0
        self.watches: dict[int, _Watch] = {}  # arm -> its newest solved request, until it should have arrived
        self._guard = ChannelGuard(self.log, self._stop)

    def stop(self) -> None:
        self._stop.set()
        if self._requests is not None:
            self._requests.cancel()

    def run(self) -> None:
        requests = StructChannel(mds.MDS_CHAN_IK_NAME, mds.MDS_IK)
        status_ch = StructChannel(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS)
        out = StructChannel(self.config.output, mds.MDS_REF)
        holds = StructChannel(mds.MDS_CHAN_HOLD_NAME, MDS_HOLD)
        self._requests = requests
        self._verdicts = VerdictWatch(controller_for(self.config.output))
        try:
            requests.flush()  # requests from before the start are not commands (the original flushed too)
            holds.flush()
            self.log("info", f"waiting for requests on {mds.MDS_CHAN_IK_NAME}; solutions go to {self.config.output}")
            self.ready.set()
            while not self._stop.is_set():
                # A damaged channel (a writer killed mid-put, a scribbled header) reads as "no request" until
                # `mds-ach repair` fixed it; the guard says so and StructChannel re-opens a re-created file.
                request = self._guard.call(requests.name, requests.wait, timeout=0.05 if self.watches else 0.5)
                self._watch_stops(holds, status_ch)
                if request is None:
                    continue
                try:
                    st = self._handle(request, out, current_reference, make_ref)
                except Exception as exc:  # keep serving: one bad request must not take the node down
                    self.log("error", f"request failed: {exc!r}; nothing moved")
                    st = IkService._refuse(MDS_IK_STATUS(), IK_BAD_REQUEST, f"internal error: {exc!r}"[:79]).status
                    st.arm = -1
                st.stamp = time.monotonic()
                self._guard.put(status_ch, st)
                self.handled += 1
                self._report(st)
        finally:
            requests.close()
            status_ch.close()
            out.close()
            self._verdicts.close()
            holds.close()

    def _watch_stops(self, holds: StructChannel[MDS_HOLD], status_ch: StructChannel[MDS_IK_STATUS]) -> None:
        """Read every new ``mds-hold`` frame; a collision CANCEL of a watched arm gets its request a second
        answer (same seq): IK_STOPPED_AT_CONTACT with the gate's reason. Watches end when the arm should have
        arrived."""
        while (hold := self._guard.call(holds.name, holds.next)) is not None:
            for arm, watch in list(self.watches.items()):
                reason = stopped_at_contact(hold, watch)
                if reason is None:
                    continue
                del self.watches[arm]
                st = MDS_IK_STATUS.from_buffer_copy(watch.status)
                st.status = IK_STOPPED_AT_CONTACT
                set_message(st, reason)
                st.stamp = time.monotonic()
                self._guard.put(status_ch, st)
                self._report(st)
        now = time.monotonic()
        for arm in [a for a, w in self.watches.items() if now > w.until]:
            del self.watches[arm]

    def _handle(self, request: mds.MDS_IK, out: Any, current_reference: Callable[..., Any],
                make_ref: Callable[..., Any]) -> MDS_IK_STATUS:
        found = current_reference(self.config.seed_sources)
        heading = current_reference((mds.MDS_CHAN_REF_MUX_NAME,))  # where the arms are commanded to go
        outcome = self.service.handle(request, None if found is None else found[0],
                                      None if heading is None else heading[0])
        st = outcome.status
        if outcome.refs is not None:
            base = current_reference(self.config.base_sources)
            if base is None:  # cannot happen when a seed was found, but never write a zero frame
                st.status = IK_NOT_READY
                set_message(st, "no reference to modify; nothing moved")
            else:
                ref, mode, _ = base
                travel = max(abs(ref[a] - v) for a, v in outcome.refs.items())
                for address, value in outcome.refs.items():
                    ref[address] = value
                live = self._verdicts is not None and self._verdicts.live()
                sent_at = time.monotonic()
                out.put(make_ref(ref, mode))
                if live and self._verdicts is not None:  # "solved" only once the mux took the whole solution
                    verdict = self._verdicts.wait(sent_at)
                    if not verdict.applied:
                        st.status = IK_NOT_APPLIED
                        set_message(st, verdict.message + "; nothing moved")
                        return st
                now = time.monotonic()
                self.watches[int(st.arm)] = _Watch(MDS_IK_STATUS.from_buffer_copy(st), tuple(outcome.refs), now,
                                                   now + WATCH_EXTRA + travel / WATCH_SPEED)
        return st

    def _report(self, st: MDS_IK_STATUS) -> None:
        doc = status_to_dict(st)
        level = "info" if st.status == IK_SOLVED or doc["message"] == PROBE_ANSWER else "warn"
        self.log(level, f"#{doc['seq']} {doc['arm']} {doc['dof']}-DOF {doc['target'][:max(doc['dof'], 0)]}: "
                        f"{doc['message']} ({st.solve_time * 1e3:.1f} ms)")
        if self.on_status is not None:
            self.on_status(st)


# --------------------------------------------------------------------------------------------- ROS node


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ik",
        description="Inverse kinematics service: solves Cartesian requests from mds-ik (console 'ik left 3 0.3 "
                    "0.2 0', legacy mds_ik_t clients) for one arm and writes the six joint references to the "
                    "mux input mds-ref-ik (through mux, filter and collision gate; never mds-ref or mds-ref-gated). "
                    f"Answers on mds-ik-state and the ROS topic {IK_STATUS_TOPIC} (JSON). Unreachable targets "
                    "move nothing.",
        epilog="Example: ros2 run mds_ach ik --output mds-ref-filter   (legacy set-up without the mux)",
    )
    p.add_argument("--output", default=contracts.base_name(mds.MDS_CHAN_REF_IK_NAME),
                   help="channel for the solutions (default: mds-ref-ik; mds-ref-filter without the mux)")
    p.add_argument("--tolerance",
                   type=find(PARAMETERS, "tolerance").arg_type(), default=ik.DEFAULT_TOLERANCE,
                   help="position tolerance in m (default 0.001); angles must be within 0.01 rad, checked separately")
    p.add_argument("--max-iterations",
                   type=find(PARAMETERS, "max_iterations").arg_type(), default=ik.DEFAULT_ITERATIONS,
                   help="iteration cap per request (default 1000)")
    p.add_argument("--timeout",
                   type=find(PARAMETERS, "timeout").arg_type(), default=2.0, help="cap on one solve in s (default 2)")
    p.add_argument("--no-collision-check", action="store_true",
                   help="do not collision-check IK candidates (the collision gate still checks every reference)")
    p.add_argument("--robot", help="robot whose joint table narrows the limits (default: MDS_ROBOT or 'default')")
    p.add_argument("--on-collision", choices=ON_COLLISION,
                   help="when every solution or its path collides: 'approach' (default, as in the paper: sent "
                        "anyway, the collision gate stops the arm at contact) or 'refuse' (nothing moves)")
    p.add_argument("--world", help="world objects YAML for the collision check (default: the package's "
                                   "config/world.yaml; give the gate the same file)")
    return p


def build_service(args: argparse.Namespace, log: Callable[[str, str], None]) -> IkService:
    """Config, limits and collision hook from the command line (shared by the tests)."""
    config = IkNodeConfig(output=args.output, tolerance=args.tolerance, max_iterations=args.max_iterations,
                          timeout=args.timeout, collision_check=not args.no_collision_check,
                          on_collision=getattr(args, "on_collision", None) or "approach")
    world = getattr(args, "world", None) or None
    safety = collision_safety(log, world) if config.collision_check else None
    return IkService(config, arm_limits(args.robot), safety)


NODE_NAME = "ik"  # the ROS node name (`ros2 param`, the sections of a params file)

PARAMETERS = (
    Param("output", contracts.base_name(mds.MDS_CHAN_REF_IK_NAME),
          "channel for the solutions: mds-ref-ik (the mux's ik input) or mds-ref-filter without a mux; never mds-ref "
          "or mds-ref-gated (option --output)"),
    Param("tolerance", float(ik.DEFAULT_TOLERANCE), "position error (m) below which a request is solved; angles "
                                                    "within 0.01 rad, checked separately (option --tolerance)",
          range=(1e-9, 1.0)),
    Param("max_iterations", int(ik.DEFAULT_ITERATIONS), "iteration cap per request (option --max-iterations)",
          range=(1, 1_000_000)),
    Param("timeout", 2.0, "cap on one solve in s, whatever the iteration count (option --timeout)",
          range=(0.001, 60.0)),
    Param("collision_check", True, "collision-check IK candidates and the path to them; the collision gate "
                                   "checks every reference anyway (option --no-collision-check)"),
    Param("robot", "", "robot variant whose joint table narrows the limits; empty: $MDS_ACH_ROBOT or the saved "
                       "choice (option --robot)"),
    Param("on_collision", "approach", "when every solution or its path collides: approach (sent anyway, the "
                                      "collision gate stops the arm at contact) or refuse (nothing moves) "
                                      "(option --on-collision)"),
    Param("world", "", "world objects YAML for the collision check; empty: the package's config/world.yaml "
                       "(option --world)"),
)


class IkNode(Node):
    """The IK service: ``IkRunner`` on its own thread; every answer also on ``mds/ik_status`` (JSON)."""

    def __init__(self, output: str | None = None, tolerance: float | None = None,
                 max_iterations: int | None = None, timeout: float | None = None,
                 collision_check: bool | None = None, robot: str | None = None, on_collision: str | None = None,
                 world: str | None = None) -> None:
        super().__init__(NODE_NAME)
        log = ros_log(self)
        given = {"output": output, "tolerance": tolerance, "max_iterations": max_iterations, "timeout": timeout,
                 "collision_check": collision_check, "robot": robot, "on_collision": on_collision, "world": world}
        values = {p.name: declare(self, p, given[p.name]) for p in PARAMETERS}
        config = IkNodeConfig(output=contracts.channel_name(values["output"]), tolerance=values["tolerance"],
                              max_iterations=values["max_iterations"], timeout=values["timeout"],
                              collision_check=values["collision_check"], on_collision=values["on_collision"])
        world_path = values["world"] or None
        if world_path is not None:
            check_world_file(world_path)  # a bad file stops the node with its reason (exit 2)
        safety = collision_safety(log, world_path) if config.collision_check else None
        if not config.collision_check:
            log("warn", "IK candidates are not collision-checked (collision_check false); the collision gate "
                        "still is")
        service = IkService(config, arm_limits(values["robot"] or None), safety)
        log("info", f"tolerance {config.tolerance:g}, at most {config.max_iterations} iterations or "
                    f"{config.timeout:g} s per request; on collision: {config.on_collision}"
                    + (f"; world {world_path}" if world_path else ""))
        self.config = config
        self.pub: Any = None
        self.runner = IkRunner(service, log=log, on_status=self._publish)
        self.thread = start_worker(self, self.runner.run, "ik")
        # The status topic appears once requests are being taken: a client that sees it can ask at once.
        self.runner.ready.wait(10.0)
        qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub = self.create_publisher(IkStatus, IK_STATUS_TOPIC, qos)

    def _publish(self, st: MDS_IK_STATUS) -> None:
        if self.pub is not None and self.context.ok():
            doc = status_to_dict(st)
            self.pub.publish(ik_status_msg(doc, self.get_clock().now().to_msg()))

    def shutdown(self) -> None:
        self.runner.stop()
        self.thread.join(timeout=5.0)


def main(argv: Sequence[str] | None = None) -> int:
    def make(args: argparse.Namespace) -> IkNode:
        return IkNode(output=args.output, tolerance=args.tolerance, max_iterations=args.max_iterations,
                      timeout=args.timeout, collision_check=False if args.no_collision_check else None,
                      robot=args.robot, on_collision=args.on_collision, world=args.world)

    return run_node(argv, _build_parser(), make)


if __name__ == "__main__":
    raise SystemExit(main())
