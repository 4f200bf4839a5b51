"""A reachable ROS 2 graph (issue 19, item 5): ``make run`` prints its ROS_DOMAIN_ID and how to get in, and
``mds-ach ros CMD`` / ``mds-ach ros-shell`` run inside the system's namespaces with its domain, from a shell
that is neither in its network namespace nor on its domain."""

from __future__ import annotations

import os
import pwd
import re
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from support import REPO, VENV_BIN
from support.system import isolated_run, system_env

from mds_ach.paths import host_uid
from mds_ach.tools import rosgraph


def _ros(env: dict[str, str], *argv: str, stdin: str | None = None, verb: str = "ros",
         timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(VENV_BIN / "mds-ach"), verb, *argv], env=env, input=stdin, capture_output=True,
                          text=True, timeout=timeout, cwd=REPO)


@pytest.fixture(scope="module")
def graph(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[dict[str, str], str]]:
    """The system as ``make run`` starts it (own network and mount namespace), on another ROS domain than ours;
    yields our environment (its runtime dir) and what ``mds-ach run`` printed."""
    env = system_env(tmp_path_factory.mktemp("rosgraph"))
    ours = int(os.environ.get("ROS_DOMAIN_ID", "0"))
    with isolated_run(env | {"ROS_DOMAIN_ID": str(ours % 100 + 101)}) as (_proc, printed):
        yield env, printed


@pytest.mark.ros
@pytest.mark.slow
def test_make_run_prints_its_domain_and_the_way_in(graph: tuple[dict[str, str], str]) -> None:
    env, printed = graph
    domain = re.search(r"ROS_DOMAIN_ID=(\d+)", printed)
    assert domain and domain.group(1) != os.environ.get("ROS_DOMAIN_ID"), printed
    assert "mds-ach ros-shell" in printed and "mds-ach ros python examples/ros_joint_state_subscriber.py" in printed


@pytest.mark.ros
@pytest.mark.slow
def test_the_example_subscriber_gets_joint_states_through_mds_ach_ros(graph: tuple[dict[str, str], str]) -> None:
    env, _ = graph
    found = rosgraph.find_graph(Path(env["MDS_ACH_RUNTIME_DIR"]))
    assert "net" in found.join, "the system must run in a network namespace of its own (else this proves nothing)"
    proc = _ros(env, "python", "examples/ros_joint_state_subscriber.py", "--count", "3", "--timeout", "30")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = [line for line in proc.stdout.splitlines() if "LSP=" in line]
    assert len(rows) == 3, proc.stdout


@pytest.mark.ros
@pytest.mark.slow
def test_mds_ach_ros_has_the_systems_environment_and_keeps_ros_args(graph: tuple[dict[str, str], str]) -> None:
    env, printed = graph
    domain = re.search(r"ROS_DOMAIN_ID=(\d+)", printed).group(1)  # type: ignore[union-attr]
    code = ("import os, socket, sys; print(os.environ['ROS_DOMAIN_ID'], os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'], "
            "[n for _, n in socket.if_nameindex()], sys.prefix, sys.argv[1:])")
    proc = _ros(env, "python", "-c", code, "--ros-args", "-r", "__node:=x")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split(maxsplit=2)[:2] == [domain, "LOCALHOST"], proc.stdout
    assert "['lo']" in proc.stdout, "only loopback inside the system's namespace"
    assert str(VENV_BIN.parent) in proc.stdout and "['--ros-args', '-r', '__node:=x']" in proc.stdout, proc.stdout


@pytest.mark.ros
@pytest.mark.slow
def test_ros_shell_is_a_shell_in_the_graph(graph: tuple[dict[str, str], str]) -> None:
    env, printed = graph
    domain = re.search(r"ROS_DOMAIN_ID=(\d+)", printed).group(1)  # type: ignore[union-attr]
    proc = _ros(env, "--shell", "/bin/sh", verb="ros-shell", stdin='echo "domain=$ROS_DOMAIN_ID"; exit 3\n')
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert f"domain={domain}" in proc.stdout, proc.stdout
    assert f"ROS_DOMAIN_ID={domain}" in proc.stderr and "'exit' leaves it" in proc.stderr, proc.stderr


@pytest.mark.ros
@pytest.mark.slow
def test_ros_shell_keeps_the_venv_and_the_graph_whatever_bashrc_does(graph: tuple[dict[str, str], str],
                                                                      tmp_path: Path) -> None:
    """A ~/.bashrc that puts another Python first and sets another domain (the README tour's step 4 broke on
    `No module named 'rclpy'`): the shell still runs this venv's python, with rclpy, in the system's graph."""
    env, printed = graph
    domain = re.search(r"ROS_DOMAIN_ID=(\d+)", printed).group(1)  # type: ignore[union-attr]
    other = tmp_path / "otherbin"
    other.mkdir()
    (other / "python").symlink_to("/usr/bin/false")
    (tmp_path / ".bashrc").write_text(f'export PATH="{other}:$PATH"\nexport ROS_DOMAIN_ID=99\necho bashrc-read\n')
    script = ('echo "python=$(command -v python) domain=$ROS_DOMAIN_ID"; '
              "python -c 'import rclpy; print(\"rclpy-ok\")'; exit 3\n")
    proc = _ros({**env, "HOME": str(tmp_path)}, "--shell", "/bin/bash", verb="ros-shell", stdin=script)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    assert "bashrc-read" in proc.stdout, "the user's ~/.bashrc is still read"
    assert f"python={VENV_BIN}/python domain={domain}" in proc.stdout, proc.stdout
    assert "rclpy-ok" in proc.stdout, proc.stdout + proc.stderr


@pytest.mark.ros
@pytest.mark.slow
def test_topics_echo_and_hz_need_no_ros2_command_line(graph: tuple[dict[str, str], str]) -> None:
    """Issue #27 item 6: a pip-only user (no `ros2`) lists the topics, echoes one and measures its rate with
    `mds-ach ros topics|echo|hz`, built on rclpy, inside the system's graph."""
    env, _ = graph
    topics = _ros(env, "topics")
    assert topics.returncode == 0, topics.stderr
    rows = {line.split()[0]: line for line in topics.stdout.splitlines()}
    assert "sensor_msgs/msg/JointState  (1 pub" in rows["/joint_states"], topics.stdout
    assert "mds_ach_interfaces/msg/CommandStatus" in rows["/mds/command_status"], topics.stdout
    assert not [name for name in rows if "/_action/" in name], "hidden topics only with --all, as ros2 topic list"
    every = _ros(env, "topics", "--all")
    assert "/left_arm_controller/follow_joint_trajectory/_action/status" in every.stdout, every.stdout
    echo = _ros(env, "echo", "joint_states", "-n", "2")
    assert echo.returncode == 0, echo.stderr
    docs = [yaml.safe_load(part) for part in echo.stdout.split("---") if part.strip()]
    assert len(docs) == 2 and docs[0]["name"][0] == "LSP" and len(docs[0]["position"]) == len(docs[0]["name"])
    assert docs[0]["header"]["frame_id"] == "base_link"
    latched = _ros(env, "echo", "robot_description", "-n", "1")  # transient local: arrives to a late subscriber
    assert latched.returncode == 0 and "<robot" in latched.stdout, latched.stderr
    hz = _ros(env, "hz", "joint_states", "--duration", "4")
    assert hz.returncode == 0, hz.stderr
    rates = [float(m.group(1)) for m in re.finditer(r"average rate: ([\d.]+) Hz", hz.stdout)]
    assert rates and 7.0 < rates[-1] < 13.0, hz.stdout  # the daemon's 10 Hz
    missing = _ros(env, "echo", "nope", "--wait", "1")
    assert missing.returncode == 1 and missing.stdout == ""
    assert missing.stderr.startswith("mds-ach ros echo: no publisher of /nope within 1 s;"), missing.stderr
    assert len(missing.stderr.splitlines()) == 1, missing.stderr


@pytest.mark.ros
@pytest.mark.slow
def test_ros_shell_prompt_says_what_it_is_and_who_the_user_really_is(graph: tuple[dict[str, str], str],
                                                                    tmp_path: Path) -> None:
    """Issue 28: inside a rootless system's user namespace the user is uid 0, and the prompt said `root@...`; now
    `(mds-ach ros) USER@HOST:DIR$ ` with the real user, in bash after ~/.bashrc (which may set its own) and in sh."""
    env, _ = graph
    user, host = pwd.getpwuid(host_uid()).pw_name, socket.gethostname().split(".")[0]
    sign = "#" if host_uid() == 0 else "$"
    (tmp_path / ".bashrc").write_text("PS1='mine> '\n")
    bash = _ros({**env, "HOME": str(tmp_path)}, "--shell", "/bin/bash", verb="ros-shell",
                stdin='echo "prompt=[$PS1] uid=$(id -u)"; exit 3\n')
    assert bash.returncode == 3, bash.stdout + bash.stderr
    assert f"prompt=[(mds-ach ros) {user}@{host}:\\w{sign} ]" in bash.stdout, bash.stdout
    sh = _ros(env, "--shell", "/bin/sh", verb="ros-shell", stdin='echo "prompt=[$PS1]"; exit 3\n')
    assert f"prompt=[(mds-ach ros) {user}@{host}{sign} ]" in sh.stdout, sh.stdout + sh.stderr


def test_ros_without_a_running_system_says_how_to_start_one(tmp_path: Path) -> None:
    proc = _ros(system_env(tmp_path), "true")
    assert proc.returncode == 1
    assert "no running MDS-Ach node" in proc.stderr and "make run" in proc.stderr, proc.stderr
    usage = _ros(system_env(tmp_path))
    assert usage.returncode == 2 and "give a command" in usage.stderr, usage.stderr


def test_summary_without_isolation_tells_the_domain() -> None:
    text = rosgraph.summary({"ROS_DOMAIN_ID": "42"})
    assert "ROS_DOMAIN_ID=42 on this machine's network" in text and "export ROS_DOMAIN_ID=42" in text
    assert "private network namespace" in rosgraph.summary({"ROS_DOMAIN_ID": "7", "MDS_NETNS_ACTIVE": "1"})
