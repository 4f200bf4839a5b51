"""The ROS side shared by all six nodes (daemon, mux, filter, collision, ik and the bridge).

* ``Param``: one declared parameter (type from its default, description, inclusive range, read-only or not).
  Each node lists its parameters in a module-level ``PARAMETERS`` tuple; docs/parameters.md's table is rendered
  from them (``parameter_table``), so the documentation cannot drift from what is declared.
* ``declare``: declare one ``Param`` on a node and return its value (a command-line option may supply the
  default); an out-of-range or wrongly typed ``--ros-args -p`` value raises ``ParameterException``, which
  ``run_node`` turns into one line on stderr and exit status 2.
* ``run_node``: the common ``main()``: parse the command line (ROS arguments removed), start rclpy, build
  the node, spin until SIGINT/SIGTERM, shut down cleanly (exit 0; 2 for bad parameters or configuration;
  1 when the node's real-time loop died).
* ``ros_log`` / ``start_worker``: the Ach-side loops log into the node's logger and run on their own thread.

rclpy is imported inside ``run_node`` and ``Param.descriptor``, not at module top: ``<node> --help`` and usage
errors answer without loading rclpy (measured: ~120 ms of a ~300 ms start), and the bridge's ``--help`` must not
import it at all (test_bridge).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from mds_ach import logformat
from mds_ach.argtypes import bounded
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.robot import access as channel_access

if TYPE_CHECKING:
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.node import Node

ParamValue = bool | int | float | str


@dataclass(frozen=True)
class Param:
    """One ROS parameter of a node: what ``ros2 param describe`` shows and what docs/parameters.md lists."""

    name: str
    default: ParamValue
    description: str
    range: tuple[float, float] | None = None  # inclusive [from, to]; int or float like the default
    read_only: bool = True  # read once at start (changing it later would silently do nothing)
    default_doc: str | None = None  # docs default column when the real default comes from a config file

    @property
    def type_name(self) -> str:
        """The ROS parameter type (``bool``, ``integer``, ``double``, ``string``)."""
        if isinstance(self.default, bool):
            return "bool"
        if isinstance(self.default, int):
            return "integer"
        if isinstance(self.default, float):
            return "double"
        return "string"

    def descriptor(self) -> ParameterDescriptor:
        """The rcl ``ParameterDescriptor`` with the description and the range (checked by rclpy itself)."""
        from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor  # lazy: module docstring

        desc = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.range is not None:
            lo, hi = self.range
            if self.type_name == "integer":
                desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
            else:
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        return desc

    def arg_type(self) -> Callable[[str], float]:
        """The argparse ``type`` of the option that sets this parameter: the same range (mds_ach.argtypes), so a
        value ROS would refuse is a usage error on the command line too (not a traceback, not a silent nan)."""
        assert self.range is not None and self.type_name in ("integer", "double"), self.name
        return bounded(*self.range, integer=self.type_name == "integer")

    def doc_default(self) -> str:
        if self.default_doc is not None:
            return self.default_doc
        if isinstance(self.default, str):
            return f"`{self.default}`" if self.default else "`''`"
        return f"`{str(self.default).lower() if isinstance(self.default, bool) else self.default}`"

    def doc_range(self) -> str:
        if self.range is None:
            return ""
        lo, hi = self.range
        if self.type_name == "integer":
            return f"{int(lo)} … {int(hi)}"
        return f"{lo:g} … {hi:g}"


def declare(node: Node, param: Param, default: ParamValue | None = None) -> Any:
    """Declare ``param`` on ``node`` and return its value: ``--ros-args -p`` wins, then ``default`` (a command-line
    option), then ``param.default``. A float default given as an int (``--rate 50``) is converted."""
    from rclpy.exceptions import InvalidParameterTypeException  # rclpy is loaded by now (a node exists)

    value: ParamValue = param.default if default is None else default
    if isinstance(param.default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    try:
        return node.declare_parameter(param.name, value, param.descriptor()).value
    except InvalidParameterTypeException as exc:
        if param.type_name != "double":
            raise
        wrong_type = exc
    # `-p rate:=20` is an integer to ROS: accept it for a double parameter (then range-checked as usual).
    from rcl_interfaces.msg import ParameterDescriptor  # lazy: see the module docstring

    loose = ParameterDescriptor(dynamic_typing=True)  # only to read the given value; then declared properly
    given = node.declare_parameter(param.name, value, loose).value
    node.undeclare_parameter(param.name)
    if isinstance(given, bool) or not isinstance(given, int | float):
        raise wrong_type
    return node.declare_parameter(param.name, float(given), param.descriptor(), ignore_override=True).value


def find(params: Iterable[Param], name: str) -> Param:
    """The ``Param`` called ``name`` (KeyError if none)."""
    for p in params:
        if p.name == name:
            return p
    raise KeyError(name)


def parameter_table(nodes: Sequence[tuple[str, Sequence[Param]]]) -> str:
    """docs/parameters.md's parameter table (Markdown) for ``[(node name, PARAMETERS), ...]``."""
    lines = ["| node | parameter | type | default | range | meaning |", "|---|---|---|---|---|---|"]
    for node, params in nodes:
        for p in params:
            meaning = p.description if p.read_only else f"{p.description} (can be changed while running)"
            lines.append(f"| `{node}` | `{p.name}` | {p.type_name} | {p.doc_default()} | {p.doc_range()} | "
                         f"{meaning} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------- node helpers


def ros_log(node: Node) -> Callable[[str, str], None]:
    """``log(level, msg)`` for the Ach-side runners, backed by the node's logger.

    One call site per severity: rclpy's logger refuses a call site whose severity changes between calls.
    """
    logger = node.get_logger()

    def log(level: str, msg: str) -> None:
        if level == "error":
            logger.error(msg)
        elif level == "warn":
            logger.warning(msg)
        else:
            logger.info(msg)

    return log


def start_worker(node: Any, target: Callable[[], None], name: str) -> threading.Thread:
    """Run the node's real-time loop on its own thread. If it raises, the error is logged with its traceback
    and the node shuts down (``run_node`` then exits 1): a dead real-time loop must not look like a live node."""

    def body() -> None:
        try:
            target()
        except Exception as exc:  # report and stop: never limp on without the loop
            node.worker_error = exc
            node.get_logger().fatal(f"{name} loop failed: {exc!r}\n{traceback.format_exc()}")
            node.context.try_shutdown()

    node.worker_error = None
    thread = threading.Thread(target=body, name=name, daemon=True)
    thread.start()
    return thread


class StoppableNode(Protocol):
    """What ``run_node`` needs of a node: rclpy's Node plus ``shutdown()`` stopping its own threads."""

    def shutdown(self) -> None: ...

    def destroy_node(self) -> None: ...

    def get_logger(self) -> Any: ...


def run_node(argv: Sequence[str] | None, parser: argparse.ArgumentParser,
             make_node: Callable[[argparse.Namespace], StoppableNode], rt_priority: int = 0) -> int:
    """Parse the command line (ROS args removed), start rclpy, build the node, spin until SIGINT/SIGTERM; exit 0.

    ``argv`` includes the program name (``sys.argv`` when None). ``make_node(args)`` returns the node. A
    ``ValueError``, ``OSError`` or rclpy ``ParameterException`` while building it (bad configuration, a
    parameter out of range or of the wrong type) is printed as one line with exit status 2; a real-time loop
    that died (``start_worker``) gives exit status 1.

    Signals: our own SIGINT/SIGTERM handlers set a flag that the ``spin_once`` loop checks. rclpy's handlers are
    not used: a signal that arrives while the node is still being built could be lost there and leave the
    executor spinning forever. The executor waits for work (``SPIN_TIMEOUT``), not a polling period: a signal
    wakes it at once through ``signal.set_wakeup_fd`` and a guard condition (``_SignalWake``), so an idle node
    costs nothing between its callbacks.

    ``rt_priority`` > 0: once the node is built, the executor thread (this one) and the DDS reception threads
    (``realtime_dds_reception``) run SCHED_FIFO at it, for a node whose subscription callbacks are a hand-off
    (the bridge's commands, #26 item 5); refused (no privilege): logged once, normal priority.
    """
    argv = list(sys.argv if argv is None else argv)
    args = parser.parse_args(strip_ros_args(argv)[1:])

    import rclpy  # after parsing: see the module docstring
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    channel_access.enforce_in_this_process()  # a node: refuse channel files another user planted
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    wake = _SignalWake(stop)
    logformat.use_ros_console_format()  # every line of the node's log with its time (rcutils reads it at init)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node: StoppableNode | None = None
    status = 0
    try:
        if not stop.is_set():
            node = make_node(args)
            executor = SingleThreadedExecutor()
            executor.add_node(node)  # type: ignore[arg-type]  # an rclpy Node (the Protocol names what we call)
            wake.attach(node)
            if rt_priority > 0:
                _realtime_callbacks(node, rt_priority)
            while not stop.is_set() and rclpy.ok():
                executor.spin_once(timeout_sec=SPIN_TIMEOUT)
    except ExternalShutdownException:
        pass
    except (ValueError, OSError, ParameterException) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            node.shutdown()
            if getattr(node, "worker_error", None) is not None:
                status = 1
            node.destroy_node()
        rclpy.try_shutdown()
        wake.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return status


DDS_RECEPTION_THREAD = re.compile(r"dds\.(shm|udp|tcp)[a-z0-9]*\.\d+")
"""Fast DDS's names (2.13+) of its transports' reception threads: ``dds.shm.<port>``, ``dds.udp.<port>`` (not the
shared-memory watchdog ``dds.shm.wdog``, the event thread ``dds.ev.N`` or the asynchronous writers ``dds.asyn.N``)."""


def realtime_dds_reception(rt_priority: int) -> tuple[list[str], list[str]]:
    """Put this process's DDS reception threads at SCHED_FIFO ``rt_priority`` (with SCHED_RESET_ON_FORK): (the
    threads changed, what failed). Why: a message waits in the reception thread before any callback runs; at normal
    priority on a busy 2-core machine that was 24 ms p99 of a ROS command's way to the daemon (docs/reliability.md E).
    Each thread does bounded work per datagram (deserialise, queue, notify the executor). Done in the process, not
    in the Fast DDS profile's thread settings, so that only the node that asks for it (the bridge) gets it, and a
    user's own profile file does not lose it."""
    changed: list[str] = []
    problems: list[str] = []
    for entry in sorted(os.listdir("/proc/self/task")):
        name = f"thread {entry}"
        try:
            with open(f"/proc/self/task/{entry}/comm") as f:
                name = f.read().strip()
            if DDS_RECEPTION_THREAD.fullmatch(name):
                os.sched_setscheduler(int(entry), os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(rt_priority))
                changed.append(name)
        except FileNotFoundError:  # the thread ended meanwhile
            continue
        except OSError as exc:
            problems.append(f"{name}: SCHED_FIFO {rt_priority} refused ({exc.strerror or exc})")
    return changed, problems


def _realtime_callbacks(node: StoppableNode, rt_priority: int) -> None:
    """The executor thread (the caller) and the DDS reception threads at SCHED_FIFO ``rt_priority`` (``run_node``);
    refused or no reception thread found: one warning, and the node runs at normal priority. The node's other
    threads go to the daemon's nice value for its other threads: they share Python's interpreter lock with the
    executor, and one preempted while it holds the lock stops the executor too (measured: 39 ms once in 300)."""
    from mds_ach.ach.glibc import renice_other_threads, tune_thread
    from mds_ach.nodes.daemon_loop import OTHER_THREADS_NICE

    problems = [p for p in tune_thread(rt_priority) if "SCHED_FIFO" in p]
    if not problems:  # refused for the executor: refused for the others too, said once
        changed, problems = realtime_dds_reception(rt_priority)
        if not changed:
            problems.append("no DDS reception thread found (not Fast DDS 2.13+?)")
        if (reniced := renice_other_threads(OTHER_THREADS_NICE)) is not None:
            problems.append(f"the other threads at their nice value ({reniced})")
    for problem in problems:
        node.get_logger().warning(f"real-time callbacks: {problem}: a command may wait for a CPU on a busy machine "
                                  "(docs/reliability.md E)")


SPIN_TIMEOUT = 2.0
"""s: the longest the executor waits without work; a signal or a shutdown wakes it earlier (``_SignalWake``)."""


class _SignalWake:
    """Wakes the executor when SIGINT/SIGTERM arrives: the interpreter runs a Python signal handler only when the
    main thread gets back from C, and the executor's wait is C. The C-level handler writes the signal number to a
    pipe (``signal.set_wakeup_fd``); a thread blocked on it sets ``stop`` and triggers a guard condition in the
    executor's wait set."""

    def __init__(self, stop: threading.Event) -> None:
        self._stop = stop
        self._guard: Any = None
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self._previous = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._watch, name="signal-wake", daemon=True)
        self._thread.start()

    def attach(self, node: Any) -> None:
        self._guard = node.create_guard_condition(lambda: None)
        if self._stop.is_set():
            self._guard.trigger()

    def _watch(self) -> None:
        while True:
            try:
                data = os.read(self._read, 64)
            except OSError:
                return
            if not data:
                return
            if {signal.SIGINT, signal.SIGTERM} & set(data):
                self._stop.set()
                guard = self._guard
                if guard is not None:
                    try:
                        guard.trigger()
                    except Exception:  # noqa: BLE001 - destroyed at shutdown: the loop sees stop anyway
                        pass

    def close(self) -> None:
        signal.set_wakeup_fd(self._previous)
        os.close(self._write)  # the watcher reads EOF and ends
        self._thread.join(timeout=1.0)
        os.close(self._read)
