"""Several robots on one ROS graph (issue #27 item 3): every topic, service and action of every node is relative,
so ``mds-ach start --namespace NAME`` moves all of them under ``/NAME``; a params file's ``/**/NODE`` and
``/NAME/NODE`` sections reach the namespaced nodes; two whole systems (each with its own ``/dev/shm``, or on one
``/dev/shm`` with a channel-name prefix) run side by side on one graph and each follows only its own commands."""

from __future__ import annotations

import math
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
from support import VENV_BIN
from support.spin import Spinner
from support.system import START_TIMEOUT, mds_ach, running_system, system_env

import mds_ach as mds
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import daemon_status as ds

NODE_NAMES = {"mds_daemon", "mux", "filter", "collision", "ik", "mds_bridge"}
RCL_GLOBAL = {"/rosout", "/parameter_events"}  # rcl's own, absolute by design in every node
LSP = "LSP"  # joint_states and mds/joint_command name joints by their short names (MODEL_JOINTS)


class Probe(Spinner):
    """A probe node on the tests' graph (same network namespace and ROS_DOMAIN_ID as the systems)."""

    def __init__(self) -> None:
        self.open_node("namespace_probe")

    def nodes_in(self, namespace: str) -> set[str]:
        return {name for name, ns in self.node.get_node_names_and_namespaces() if ns == namespace}

    def names_of(self, name: str, namespace: str) -> set[str]:
        """Every topic, service and action the node ``namespace/name`` publishes, subscribes, serves or calls."""
        from rclpy.action import get_action_server_names_and_types_by_node

        n = self.node
        found: set[str] = set()
        for query in (n.get_publisher_names_and_types_by_node, n.get_subscriber_names_and_types_by_node,
                      n.get_service_names_and_types_by_node, n.get_client_names_and_types_by_node):
            found |= {topic for topic, _types in query(name, namespace)}
        found |= {action for action, _types in get_action_server_names_and_types_by_node(n, name, namespace)}
        return found


@pytest.fixture
def probe() -> Iterator[Probe]:
    p = Probe()
    try:
        yield p
    finally:
        p.close_node()


def test_every_name_of_every_node_is_under_the_namespace_and_the_params_sections_reach_it(
        clean_shm: None, tmp_path: Path, probe: Probe) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({
        "/**/filter": {"ros__parameters": {"rate": 20.0}},
        "/robot1/mds_daemon": {"ros__parameters": {"rate": 20.0}},
        "/robot2/mds_daemon": {"ros__parameters": {"rate": 40.0}},  # another robot's: checked, not applied here
    }))
    with running_system(tmp_path, extra=("--namespace", "robot1", "--params", str(params))) as env:
        probe.spin_until(lambda: NODE_NAMES <= probe.nodes_in("/robot1"), 60.0, "the six nodes in /robot1")
        assert not NODE_NAMES & probe.nodes_in("/")
        # a node's graph entries appear after the node itself: wait for the bridge's last ones
        last = {"/robot1/tf", "/robot1/joint_states", "/robot1/left_arm_controller/follow_joint_trajectory"}
        probe.spin_until(lambda: last <= probe.names_of("mds_bridge", "/robot1"), 30.0, f"the bridge's {last}")
        names = {node: probe.names_of(node, "/robot1") for node in NODE_NAMES}
        outside = {node: sorted(n for n in found if not n.startswith("/robot1/") and n not in RCL_GLOBAL)
                   for node, found in names.items()}
        assert outside == {node: [] for node in NODE_NAMES}, outside
        assert {"/robot1/mds/mux_state"} <= names["mux"]
        assert {"/robot1/mds/collision", "/robot1/mds/collision/override"} <= names["collision"]
        assert {"/robot1/mds/daemon_status", "/robot1/diagnostics", "/robot1/mds_daemon/command"} <= \
            names["mds_daemon"]
        assert "/robot1/mds/ik_status" in names["ik"]
        with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS, create=False) as chan:
            st = chan.latest()
        assert st is not None and st.rate_hz == pytest.approx(20.0)  # the /robot1/mds_daemon section
        status = mds_ach("status", env=env)
        assert "namespace  /robot1" in status.stdout, status.stdout
        echo = mds_ach("ros", "echo", "joint_states", "-n", "1", env=env)  # relative: the system's namespace
        assert echo.returncode == 0 and "frame_id: base_link" in echo.stdout, echo.stdout + echo.stderr


def test_no_json_alias_and_no_borrowed_text_service_is_left(clean_shm: None, tmp_path: Path, probe: Probe) -> None:
    """Issue #27 item 6: after their release of deprecation the ``<topic>/json`` String aliases and the daemon's text
    command on the borrowed ``diagnostic_msgs/srv/AddDiagnostics`` are gone; every status is typed."""
    with running_system(tmp_path):
        probe.spin_until(lambda: NODE_NAMES <= probe.nodes_in("/"), 60.0, "the six nodes")
        last = {"/tf", "/joint_states", "/left_arm_controller/follow_joint_trajectory"}
        probe.spin_until(lambda: last <= probe.names_of("mds_bridge", "/"), 30.0, f"the bridge's {last}")
        topics = dict(probe.node.get_topic_names_and_types())
        services = dict(probe.node.get_service_names_and_types())
        assert [t for t in topics if t.endswith("/json")] == []
        assert [s for s, types in services.items() if "diagnostic_msgs/srv/AddDiagnostics" in types] == []
        assert "/mds_daemon/command_text" not in services
        typed = {"/mds/mux_state": "mds_ach_interfaces/msg/MuxState",
                 "/mds/collision": "mds_ach_interfaces/msg/CollisionState",
                 "/mds/ik_status": "mds_ach_interfaces/msg/IkStatus",
                 "/mds/daemon_status": "mds_ach_interfaces/msg/DaemonStatus"}
        assert {name: topics.get(name) for name in typed} == {name: [kind] for name, kind in typed.items()}


def test_a_params_section_outside_the_namespace_is_refused_before_anything_starts(clean_shm: None,
                                                                                  tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"mds_daemon": {"ros__parameters": {"rate": 25.0}}}))
    env = system_env(tmp_path)
    proc = mds_ach("start", "nocan", "--namespace", "robot1", "--params", str(params), env=env, timeout=120)
    assert proc.returncode == 1
    assert ("mds_daemon: this section is for mds_daemon outside any namespace, but the nodes start in /robot1: write "
            "/**/mds_daemon: (any namespace) or /robot1/mds_daemon:") in proc.stderr, proc.stderr
    assert "started" not in proc.stdout
    bad = mds_ach("start", "nocan", "--namespace", "1robot", env=env)
    assert bad.returncode == 2 and "'1robot' is not a ROS namespace" in bad.stderr, bad.stderr


# ----- two robots, one graph


@contextmanager
def second_system(tmp_path: Path, how: str) -> Iterator[dict[str, str]]:
    """Robot 2 (``--namespace robot2``, its own runtime dir) on the tests' ROS graph: in a mount namespace of its
    own with a fresh ``/dev/shm`` (``own-shm``), or on this ``/dev/shm`` with its channels prefixed ``r2-``."""
    env = system_env(tmp_path / "robot2")
    argv = [str(VENV_BIN / "mds-ach"), "start", "nocan", "--namespace", "robot2", "--timeout", str(START_TIMEOUT)]
    if how == "own-shm":
        # Fast DDS delivers between processes of one host through files in /dev/shm: across two /dev/shm only its
        # UDP transport carries the data, and rmw_fastrtps's LOCALHOST range sets its own transports (shared memory
        # included), so robot 2 takes the SUBNET range; this network namespace has loopback only all the same
        # (docs/architecture.md, several robots)
        env.update(FASTDDS_BUILTIN_TRANSPORTS="UDPv4", ROS_AUTOMATIC_DISCOVERY_RANGE="SUBNET")
        argv = ["unshare", "-m", "--propagation", "private", "sh", "-c",
                'mount -t tmpfs -o mode=1777 tmpfs /dev/shm && exec "$@"', "sh", *argv]
    else:
        env["MDS_ACH_CHANNEL_PREFIX"] = "r2-"
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=START_TIMEOUT + 60)
    assert proc.returncode == 0, f"robot2 did not start:\n{proc.stdout}\n{proc.stderr}"
    try:
        yield env
    finally:
        mds_ach("stop", env=env, timeout=60)
        if how == "prefix":
            mds_ach("killall", env=env, timeout=60)  # its own channels only (r2-mds-*)


@pytest.mark.parametrize("how", ["own-shm", "prefix"])
def test_two_robots_on_one_graph_each_follow_only_their_own_commands(clean_shm: None, tmp_path: Path, probe: Probe,
                                                                     how: str) -> None:
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    with running_system(tmp_path / "robot1", extra=("--namespace", "robot1")), second_system(tmp_path, how):
        latest: dict[str, JointState] = {}
        for ns in ("robot1", "robot2"):
            probe.node.create_subscription(JointState, f"/{ns}/joint_states",
                                           lambda m, ns=ns: latest.__setitem__(ns, m), qos_profile_sensor_data)
        commands = {ns: probe.node.create_publisher(JointState, f"/{ns}/mds/joint_command", 10)
                    for ns in ("robot1", "robot2")}
        for pub in commands.values():
            probe.spin_until(lambda p=pub: p.get_subscription_count() == 1, 60.0, f"the bridge on {pub.topic_name}")
        probe.spin_until(lambda: len(latest) == 2, 60.0, "joint_states of both robots")
        shm = sorted(os.listdir("/dev/shm"))
        if how == "prefix":
            assert "achshm-r2-mds-state" in shm and "achshm-mds-state" in shm, shm
        else:
            assert not any("r2-" in name for name in shm), shm  # robot 2's channels are in its own /dev/shm

        def lsp(ns: str) -> float:
            msg = latest[ns]
            return msg.position[list(msg.name).index(LSP)]

        targets = {"robot1": 0.2, "robot2": -0.3}
        for ns, value in targets.items():
            commands[ns].publish(JointState(name=[LSP], position=[value]))
        probe.spin_until(lambda: all(abs(lsp(ns) - v) < 0.02 for ns, v in targets.items()), 60.0,
                         f"LSP at {targets} on each robot's joint_states")
        probe.spin_for(1.0)  # and they stay there: neither follows the other's command
        assert {ns: round(lsp(ns), 2) for ns in targets} == targets
        # this /dev/shm's unprefixed channels are robot 1's: the C clients' robot
        with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as chan:
            state = chan.latest()
        assert state is not None
        assert math.isclose(state.joint[mds.BY_SHORT["LSP"].address].pos, 0.2, abs_tol=0.02)


def test_a_channel_prefix_renames_every_channel_and_nothing_else(tmp_path: Path) -> None:
    """$MDS_ACH_CHANNEL_PREFIX: every channel of the registry (and the mux's configured inputs) carries it, the runtime
    dir is the second system's own, include/mds.h keeps the original names; without it the original names."""
    script = ("import json, mds_ach as mds; from mds_ach.paths import runtime_dir; from mds_ach.tools import cheader; "
              "from mds_ach.nodes.mux import load_config; "
              "print(json.dumps([list(mds.ALL_CHANNELS), str(runtime_dir()), cheader.generate(), "
              "sorted(c.channel for c in load_config()['controllers'])]))")
    env = {k: v for k, v in os.environ.items() if k not in ("MDS_ACH_RUNTIME_DIR", "XDG_RUNTIME_DIR")}

    def names(prefix: str | None) -> list:
        run_env = env if prefix is None else {**env, "MDS_ACH_CHANNEL_PREFIX": prefix}
        proc = subprocess.run([str(VENV_BIN / "python"), "-c", script], env=run_env, capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 0, proc.stderr
        import json
        return json.loads(proc.stdout)

    plain, prefixed = names(None), names("r2-")
    assert "mds-state" in plain[0] and all(not n.startswith("r2-") for n in plain[0])
    assert prefixed[0] == ["r2-" + n for n in plain[0]]
    assert prefixed[1] == plain[1] + "-r2" and prefixed[2] == plain[2]
    assert prefixed[3] == ["r2-" + n for n in plain[3]] and "mds-ref-ros" in plain[3]
    bad = subprocess.run([str(VENV_BIN / "mds-ach"), "status"], env={**env, "MDS_ACH_CHANNEL_PREFIX": "../x"},
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and bad.stdout == ""
    assert bad.stderr == ("mds_ach: MDS_ACH_CHANNEL_PREFIX='../x' is not a channel-name prefix: give 1..24 lower-case "
                          "letters, digits, '.', '_' or '-', starting with a letter or digit (e.g. r2-)\n")
