"""``mds-ach ros topics|echo|hz``: list the graph's topics, print one's messages, measure its rate, on rclpy alone.

Why: a pip-installed ROS (this venv's wheels) has rclpy but no ``ros2`` command line, so the docs could not say
``ros2 topic echo``. These three cover what an operator checks; ``mds-ach ros`` runs them inside the running
system's graph (namespaces, ``ROS_DOMAIN_ID``), as ``python -m mds_ach.tools.rostopic VERB ...``.

A relative topic name (``joint_states``) is resolved in the running system's ROS namespace (``mds-ach start
--namespace``; ``--namespace`` here), an absolute one (``/robot2/joint_states``) is taken as is. The subscription's
QoS follows the topic's publishers (best effort if one of them is, transient local when all are, so the latched
``robot_description`` arrives), as ``ros2 topic echo`` does.
"""

from __future__ import annotations

import argparse
import importlib
import math
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from mds_ach.argtypes import bounded, ros_namespace, seconds

DISCOVERY = 2.0  # s to let discovery settle before listing or resolving a type (graph updates every ~0.25 s)


class TopicError(RuntimeError):
    """A topic that cannot be echoed or measured; the message says why."""


def message_class(type_name: str) -> Any:
    """The Python class of ``pkg/msg/Type`` (what the graph reports), imported from the package's ``msg`` module."""
    package, kind, name = type_name.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError) as exc:
        raise TopicError(f"type {type_name} is not installed here ({exc})") from None


def to_plain(value: Any) -> Any:
    """A message (or a field of one) as plain lists, dicts and numbers, for YAML."""
    if hasattr(value, "get_fields_and_field_types"):
        return {field: to_plain(getattr(value, field)) for field in value.get_fields_and_field_types()}
    if isinstance(value, str | bytes | bool | int | float) or value is None:
        return value
    try:
        items = list(value)  # sequences, array.array, numpy arrays
    except TypeError:
        return str(value)
    return [x.item() if hasattr(x, "item") else to_plain(x) for x in items]


def render(msg: Any) -> str:
    """One message as YAML, the way ``ros2 topic echo`` prints it, ending in ``---``."""
    import yaml

    return yaml.safe_dump(to_plain(msg), sort_keys=False, default_flow_style=None, width=100) + "---"


class Graph:
    """A probe node in its own context, in the system's namespace (so relative names resolve as the nodes')."""

    def __init__(self, namespace: str) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context, args=[])
        self.node = rclpy.create_node("mds_ach_ros_probe", namespace=namespace, context=self.context,
                                      start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()

    def spin_for(self, duration: float, until: Callable[[], bool] = lambda: False) -> None:
        end = time.monotonic() + duration
        while time.monotonic() < end and not until():
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def resolve(self, topic: str) -> str:
        return self.node.resolve_topic_name(topic)

    def topics(self) -> dict[str, list[str]]:
        return {name: types for name, types in self.node.get_topic_names_and_types()}

    def wait_type(self, topic: str, timeout: float) -> str:
        """The type of ``topic`` once a publisher of it is known; TopicError after ``timeout`` s."""
        self.spin_for(timeout, lambda: bool(self.node.get_publishers_info_by_topic(topic)))
        infos = self.node.get_publishers_info_by_topic(topic)
        if not infos:
            known = sorted(self.topics())
            raise TopicError(f"no publisher of {topic} within {timeout:g} s; topics now: {', '.join(known) or 'none'}"
                             " ('mds-ach ros topics')")
        return str(infos[0].topic_type)

    def subscribe(self, topic: str, type_name: str, callback: Callable[[Any], None]) -> None:
        """A subscription whose QoS every publisher of ``topic`` is compatible with."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        infos = self.node.get_publishers_info_by_topic(topic)
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        qos = QoSProfile(depth=100,
                         reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        self.node.create_subscription(message_class(type_name), topic, callback, qos)


def hidden(name: str) -> bool:
    """ROS's hidden names (a token starting with ``_``: actions' ``_action/feedback``...), left out of a listing
    unless asked for, as ``ros2 topic list`` does."""
    return any(token.startswith("_") for token in name.split("/"))


def run_topics(graph: Graph, args: argparse.Namespace, out: Callable[[str], None]) -> int:
    graph.spin_for(args.wait)
    topics = {name: types for name, types in graph.topics().items() if args.all or not hidden(name)}
    if not topics:
        out("(no topics: is the system running? 'mds-ach status')")
        return 1
    width = max(len(name) for name in topics)
    for name, types in sorted(topics.items()):
        pubs, subs = graph.node.count_publishers(name), graph.node.count_subscribers(name)
        out(f"{name:<{width}}  {', '.join(types)}  ({pubs} pub, {subs} sub)")
    return 0


def run_echo(graph: Graph, args: argparse.Namespace, out: Callable[[str], None]) -> int:
    topic = graph.resolve(args.topic)
    type_name = graph.wait_type(topic, args.wait)
    got: list[Any] = []

    def on_message(msg: Any) -> None:
        if args.count is None or len(got) < args.count:  # one spin may deliver several: never more than asked
            got.append(msg)
            out(render(msg))

    graph.subscribe(topic, type_name, on_message)
    deadline = math.inf if args.timeout is None else time.monotonic() + args.timeout
    while (args.count is None or len(got) < args.count) and time.monotonic() < deadline:
        graph.spin_for(0.2, lambda: args.count is not None and len(got) >= args.count)
    if args.count is not None and len(got) < args.count:
        raise TopicError(f"{len(got)} of {args.count} message(s) on {topic} within {args.timeout:g} s")
    return 0


def rate_line(stamps: Sequence[float]) -> str:
    """``ros2 topic hz``'s summary of receipt times: average rate and the periods' min, max and std dev."""
    periods = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    mean = statistics.fmean(periods)
    std = statistics.pstdev(periods)
    return (f"average rate: {1.0 / mean:.3f} Hz  min {min(periods):.4f} s  max {max(periods):.4f} s  "
            f"std dev {std:.5f} s  window {len(stamps)}")


def run_hz(graph: Graph, args: argparse.Namespace, out: Callable[[str], None]) -> int:
    topic = graph.resolve(args.topic)
    type_name = graph.wait_type(topic, args.wait)
    stamps: list[float] = []
    graph.subscribe(topic, type_name, lambda _msg: stamps.append(time.monotonic()))
    start = time.monotonic()
    end = math.inf if args.duration is None else start + args.duration
    next_report = start + 1.0
    while time.monotonic() < end:
        graph.spin_for(min(0.2, max(0.0, end - time.monotonic())))
        if time.monotonic() >= next_report:
            next_report += 1.0
            window = stamps[-args.window:]
            out(rate_line(window) if len(window) >= 2 else f"no new messages on {topic}" if not stamps else
                f"1 message on {topic} so far")
    if len(stamps) < 2:
        raise TopicError(f"fewer than 2 messages on {topic} in {args.duration:g} s: no rate")
    return 0


VERBS: dict[str, Callable[[Graph, argparse.Namespace, Callable[[str], None]], int]] = {
    "topics": run_topics, "echo": run_echo, "hz": run_hz}


def _namespace(text: str) -> str:
    """A ROS namespace, ``/`` (none) included."""
    return "/" if text == "/" else ros_namespace(text)


def build_parser(prog: str = "mds-ach ros") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="The running system's ROS topics without a ros2 command "
                                                            "line (rclpy only).")
    parser.add_argument("--namespace", type=_namespace, default="/",
                        help="resolve relative topic names here (default: the running system's namespace)")
    sub = parser.add_subparsers(dest="verb", required=True)
    topics = sub.add_parser("topics", help="every topic of the graph with its type and publisher/subscriber counts")
    topics.add_argument("--wait", type=seconds(60.0), default=DISCOVERY,
                        help=f"seconds of discovery before listing (default {DISCOVERY:g})")
    topics.add_argument("--all", "-a", action="store_true",
                        help="also the hidden topics (actions' _action/feedback and _action/status)")
    echo = sub.add_parser("echo", help="print a topic's messages as YAML (Ctrl-C stops)")
    echo.add_argument("topic", help="e.g. joint_states, mds/command_status, /robot2/joint_states")
    echo.add_argument("--count", "-n", type=bounded(1, 1_000_000, integer=True), default=None,
                      help="stop after this many messages (exit 1 if fewer arrive within --timeout)")
    echo.add_argument("--timeout", type=seconds(), default=None, help="stop after this many seconds")
    echo.add_argument("--wait", type=seconds(60.0), default=10.0,
                      help="seconds to wait for a publisher of the topic (default 10)")
    hz = sub.add_parser("hz", help="the topic's rate, once a second (Ctrl-C stops)")
    hz.add_argument("topic", help="e.g. joint_states")
    hz.add_argument("--window", type=bounded(2, 100_000, integer=True), default=100,
                    help="messages the rate is computed over (default 100)")
    hz.add_argument("--duration", type=seconds(), default=None, help="stop after this many seconds")
    hz.add_argument("--wait", type=seconds(60.0), default=10.0,
                    help="seconds to wait for a publisher of the topic (default 10)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verb == "echo" and args.count is not None and args.timeout is None:
        args.timeout = 30.0

    def out(text: str) -> None:
        print(text, flush=True)

    graph = Graph(args.namespace)
    try:
        return VERBS[args.verb](graph, args, out)
    except TopicError as exc:
        print(f"mds-ach ros {args.verb}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        graph.close()


if __name__ == "__main__":
    raise SystemExit(main())
