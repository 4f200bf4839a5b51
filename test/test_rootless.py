"""Rootless (issue 19, item 6): tools/netns-run, an Ach channel, rclpy and the whole system as a normal user.

We run as root in CI, so the checks run as a dedicated user (``mds-rootless``, created when absent) through
``setpriv``; when the tests themselves already run rootless (user namespace of a normal user), as that user.
The venv's interpreter may live where other users cannot execute it (pyenv under /root): the user then runs the
system's Python of the same version on the venv's packages (``PYTHONPATH``, and the ROS wheels' library path,
which the venv's interpreter sets up itself). Skipped only where the kernel disables user namespaces.

The tests that act as other users (channels planted by nobody, the operator's group, chown to another group) need
more than the one uid ``unshare -r`` maps: the user gets a subordinate id range here (/etc/subuid, /etc/subgid;
``make sysdeps`` installs uidmap's newuidmap/newgidmap), which tools/netns-run then maps, and those tests run as
the user.
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
from support import REPO, in_netns, other_ids_missing
from support.system import isolated_run

from mds_ach.paths import host_uid

USER = "mds-rootless"
SUBID_MIN, SUBID_COUNT = 100000, 65536  # Debian's login.defs defaults (SUB_UID_MIN, SUB_UID_COUNT)
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


def _ensure_subids(pw: pwd.struct_passwd) -> None:
    """Give the user a subordinate uid and gid range (what tools/netns-run maps with ``--map-auto``) unless it has
    one: ``useradd --system`` allocates none. The range starts after every range already given out."""
    for kind, path in (("uids", Path("/etc/subuid")), ("gids", Path("/etc/subgid"))):
        entries = [line.split(":") for line in (path.read_text().splitlines() if path.exists() else [])]
        entries = [e for e in entries if len(e) == 3]
        if any(e[0] in (pw.pw_name, str(pw.pw_uid)) for e in entries):
            continue
        start = max([SUBID_MIN, *(int(e[1]) + int(e[2]) for e in entries)])
        made = subprocess.run(["usermod", f"--add-sub{kind}", f"{start}-{start + SUBID_COUNT - 1}", pw.pw_name],
                              capture_output=True, text=True)
        assert made.returncode == 0, f"usermod --add-sub{kind} for {pw.pw_name}: {made.stderr}"


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
        if host_uid() != 0:  # the whole test run is already rootless: the user's name as its netns-run set it
            inherited = {k: os.environ[k] for k in ("LD_LIBRARY_PATH", "LOGNAME", "USER") if k in os.environ}
            yield NormalUser((), base | inherited, sys.executable, home)
            return
        try:
            pw = pwd.getpwnam(USER)
        except KeyError:
            made = subprocess.run(["useradd", "--system", "--no-create-home", "--home-dir", "/nonexistent",
                                   "--shell", "/usr/sbin/nologin", USER], capture_output=True, text=True)
            assert made.returncode == 0, f"useradd {USER}: {made.stderr}"
            pw = pwd.getpwnam(USER)
        _ensure_subids(pw)
        os.chown(home, pw.pw_uid, pw.pw_gid)
        python, extra = _python_for(pw.pw_uid, pw.pw_gid, base)
        prefix = ("setpriv", f"--reuid={pw.pw_uid}", f"--regid={pw.pw_gid}", "--clear-groups")
        yield NormalUser(prefix, base | extra, python, home)
    finally:
        shutil.rmtree(home, ignore_errors=True)


CHECK = r"""
import getpass, json, os, socket, sys, time
from mds_ach import ach
from mds_ach.paths import runtime_dir
import rclpy
from std_msgs.msg import String

out = {"uid": os.getuid(), "uid_map": open("/proc/self/uid_map").read().split(),
       "links": [n for _, n in socket.if_nameindex()],
       "shm": sorted(f for f in os.listdir("/dev/shm") if f.startswith("achshm")),
       "runtime_dir": str(runtime_dir()), "user": getpass.getuser()}
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
    assert out["user"] == pwd.getpwuid(outside).pw_name, "the user's own name inside (pytest-of-<user>, not root's)"


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


def test_root_channels_in_the_shared_shm_name_the_real_users_in_one_line(clean_shm: None, user: NormalUser) -> None:
    """Issue 28 item 2: after `sudo make run` (root's channels stay in the host's /dev/shm) a normal user's `make
    run` shares that /dev/shm from inside its user namespace, where it is uid 0 and root's files show as uid 65534.
    `mds-ach status` and `start` say it in one line, both users as the machine names them, with the command; the
    per-channel lines printed `uid 65534 (nobody)` and `(uid 0 (root))`."""
    if not user.prefix:
        pytest.skip("needs root to leave root's channels for the user")
    made = subprocess.run([sys.executable, "-m", "mds_ach.tools.cli", "make"], capture_output=True, text=True,
                          timeout=60)
    assert made.returncode == 0, made.stderr
    name = pwd.getpwuid(int(user.prefix[1].split("=")[1])).pw_name
    env = {k: v for k, v in user.env.items() if k != "MDS_NETNS_ACTIVE"} | {
        "MDS_NETNS_SHARE_SHM": "1", "MDS_ACH_RUNTIME_DIR": str(user.home / "run")}
    for verb in (["status"], ["start", "nocan"]):
        proc = subprocess.run([*user.prefix, NETNS_RUN, user.python, "-m", "mds_ach.tools.cli", *verb], env=env,
                              capture_output=True, text=True, timeout=120, cwd=user.home)
        out = proc.stdout + proc.stderr
        lines = [line for line in out.splitlines() if "/dev/shm" in line]
        assert len(lines) == 1, out
        assert "root, if the files come from 'sudo make run'" in lines[0] and f"not to you ({name} (uid " in \
            lines[0], lines[0]
        assert "uid 0 (root)" not in out and "(nobody)" not in out and "killall" in lines[0], out
        assert proc.returncode == 1, out


# The tests that act as another user inside the tests' namespace (support.run_as, chown to another group).
OTHER_USER_TESTS = (
    "test/test_chantool.py::test_make_group_and_mode",
    "test/test_chantool.py::test_make_and_repair_refuse_channels_another_user_planted",
    "test/test_chantool.py::test_operators_can_write_controller_inputs_but_not_the_daemon_input",
    "test/test_ach_api.py::test_permission_denied",
)


def test_the_tests_acting_as_other_users_run_as_a_normal_user(user: NormalUser) -> None:
    """``make test`` as a normal user: the ownership tests (channels planted by nobody, an operator in the
    channels' group, chown to another group) run, and pass, in tools/netns-run's namespace of that user."""
    if user.prefix:  # we are root: as the user, through its own tools/netns-run
        missing = [tool for tool in ("newuidmap", "newgidmap") if not shutil.which(tool)]
        assert not missing, f"{' and '.join(missing)} missing: install the Debian package uidmap (make sysdeps)"
        env = {k: v for k, v in user.env.items() if k != "MDS_NETNS_ACTIVE"}
        argv = [*user.prefix, NETNS_RUN, user.python]
    else:  # the whole run is rootless: this namespace is the user's
        reason = other_ids_missing()
        if reason:
            pytest.skip(reason)
        env, argv = dict(os.environ), [sys.executable]
    argv += ["-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "--basetemp", str(user.home / "pytest"),
             *OTHER_USER_TESTS]
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300, cwd=REPO)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    summary = out.strip().splitlines()[-1]
    assert re.fullmatch(r"\d+ passed in .*", summary), f"every one runs and passes (no skip): {summary}\n{out}"
