"""Rootless (issue 19, item 6): tools/netns-run, an Ach channel, rclpy and the whole system as a normal user.

We run as root in CI, so the checks run as a dedicated user (``mds-rootless``, created when absent) through
``setpriv``; when the tests themselves already run rootless (user namespace of a normal user), as that user.
The venv's interpreter may live where other users cannot execute it (pyenv under /root): the user then runs the
system's Python of the same version on the venv's packages (``PYTHONPATH``, and the ROS wheels' library path,
which the venv's interpreter sets up itself). Skipped only where the kernel disables user namespaces.
"""

from __future__ import annotations

import json
import os
import pwd
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from support import REPO, in_netns
from support.system import isolated_run

from mds_ach.paths import host_uid

USER = "mds-rootless"
NETNS_RUN = str(REPO / "tools" / "netns-run")


def _sysctl(name: str) -> str | None:
    try:
        return Path("/proc/sys", *name.split(".")).read_text().strip()
    except OSError:
        return None


def _userns_disabled() -> str | None:
    """Why the kernel forbids unprivileged user namespaces here, or None."""
    for name, off in (("user.max_user_namespaces", "0"), ("kernel.unprivileged_userns_clone", "0"),
                      ("kernel.apparmor_restrict_unprivileged_userns", "1")):
        if _sysctl(name) == off:
            return f"the kernel disables unprivileged user namespaces ({name} = {off})"
    return None


@dataclass(frozen=True)
class NormalUser:
    """How to run a command as a normal user: the ``prefix`` (setpriv, or nothing when we are one), its
    environment and a Python interpreter it can execute."""

    prefix: tuple[str, ...]
    env: dict[str, str]
    python: str
    home: Path


def _python_for(uid: int, gid: int, env: dict[str, str]) -> tuple[str, dict[str, str]]:
    """An interpreter that user can run with this venv's packages, and the environment it needs."""
    probe = subprocess.run(["setpriv", f"--reuid={uid}", f"--regid={gid}", "--clear-groups", "env", sys.executable,
                            "-c", "import mds_ach, rclpy"], env=env, capture_output=True)
    if probe.returncode == 0:
        return sys.executable, {}
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    system = shutil.which(version, path="/usr/local/bin:/usr/bin:/bin")
    assert system, (f"the venv's interpreter ({sys.executable}) is not executable by other users and there is no "
                    f"system {version}: build the venv from a Python every user can run")
    site = sysconfig.get_paths()["purelib"]
    return system, {"PYTHONPATH": os.pathsep.join([site, str(REPO)]), "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1",
                    "LD_LIBRARY_PATH": os.environ.get("LD_LIBRARY_PATH", "")}


@pytest.fixture(scope="module")
def user() -> Iterator[NormalUser]:
    assert in_netns(), "run the tests through tools/netns-run"
    reason = _userns_disabled()
    if reason:
        pytest.skip(reason)
    home = Path(tempfile.mkdtemp(prefix="mds-rootless-"))
    base = {"PATH": "/usr/local/bin:/usr/bin:/bin", "HOME": str(home), "LANG": "C.UTF-8",
            "ROS_LOG_DIR": str(home / "ros-log")}
    try:
        if host_uid() != 0:  # the whole test run is already rootless
            yield NormalUser((), base | {"LD_LIBRARY_PATH": os.environ.get("LD_LIBRARY_PATH", "")}, sys.executable,
                             home)
            return
        try:
            pw = pwd.getpwnam(USER)
        except KeyError:
            made = subprocess.run(["useradd", "--system", "--no-create-home", "--home-dir", "/nonexistent",
                                   "--shell", "/usr/sbin/nologin", USER], capture_output=True, text=True)
            assert made.returncode == 0, f"useradd {USER}: {made.stderr}"
            pw = pwd.getpwnam(USER)
        os.chown(home, pw.pw_uid, pw.pw_gid)
        python, extra = _python_for(pw.pw_uid, pw.pw_gid, base)
        prefix = ("setpriv", f"--reuid={pw.pw_uid}", f"--regid={pw.pw_gid}", "--clear-groups")
        yield NormalUser(prefix, base | extra, python, home)
    finally:
        shutil.rmtree(home, ignore_errors=True)


CHECK = r"""
import json, os, socket, sys, time
from mds_ach import ach
from mds_ach.paths import runtime_dir
import rclpy
from std_msgs.msg import String

out = {"uid": os.getuid(), "uid_map": open("/proc/self/uid_map").read().split(),
       "links": [n for _, n in socket.if_nameindex()],
       "shm": sorted(f for f in os.listdir("/dev/shm") if f.startswith("achshm")),
       "runtime_dir": str(runtime_dir())}
with ach.Channel("test-rootless", 4, 16, create=True) as ch:
    ch.put(b"rootless")
    buf = bytearray(16)
    status, n = ch.get(buf, last=True)
    out["channel"] = bytes(buf[:n]).decode()
    out["channel_uid"] = os.stat(ach.shm_path("test-rootless")).st_uid
rclpy.init()
node = rclpy.create_node("rootless_check")
got = []
node.create_subscription(String, "rootless", lambda m: got.append(m.data), 10)
pub = node.create_publisher(String, "rootless", 10)
deadline = time.monotonic() + 30
while not got and time.monotonic() < deadline:
    pub.publish(String(data="hello"))
    rclpy.spin_once(node, timeout_sec=0.1)
out["ros"] = got[:1]
node.destroy_node()
rclpy.shutdown()
print(json.dumps(out))
"""


def test_netns_run_channel_and_rclpy_as_a_normal_user(user: NormalUser) -> None:
    script = user.home / "check.py"
    script.write_text(CHECK)
    os.chmod(script, 0o644)
    env = {k: v for k, v in user.env.items() if k != "MDS_NETNS_ACTIVE"}
    proc = subprocess.run([*user.prefix, NETNS_RUN, user.python, str(script)], env=env, capture_output=True,
                          text=True, timeout=120, cwd=user.home)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    outside = int(out["uid_map"][1])
    assert out["uid"] == 0 and outside != 0, f"a user namespace mapping the user to root inside: {out['uid_map']}"
    assert out["links"] == ["lo"], "DDS must see only loopback"
    assert out["shm"] == [] and not os.path.exists("/dev/shm/achshm-test-rootless"), "a private /dev/shm"
    assert out["channel"] == "rootless" and out["channel_uid"] == 0
    assert out["ros"] == ["hello"]
    assert out["runtime_dir"] == f"/tmp/mds-ach-{outside}", "the same runtime dir as the user's other terminals"


@pytest.mark.ros
@pytest.mark.slow
def test_make_run_and_mds_ach_ros_as_a_normal_user(user: NormalUser) -> None:
    """The whole system, as ``make run`` starts it, as the user; then, as the same user from outside its
    namespaces, an example through ``mds-ach ros`` (joins the user namespace too) and ``mds-ach status``."""
    env = user.env | {"MDS_ACH_RUNTIME_DIR": str(user.home / "run"), "MDS_ACH_CONFIG_DIR": str(user.home / "config")}
    with isolated_run(env, user.prefix, user.python):
        cli = [*user.prefix, user.python, "-m", "mds_ach.tools.cli"]
        proc = subprocess.run([*cli, "ros", user.python, "examples/ros_joint_state_subscriber.py", "--count", "2",
                               "--timeout", "30"], env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert len(re.findall(r"LSP=", proc.stdout)) == 2, proc.stdout
        status = subprocess.run([*cli, "status"], env=env, capture_output=True, text=True, timeout=120, cwd=REPO)
        assert re.search(r"bridge\s+running", status.stdout), status.stdout + status.stderr
