"""The colcon workspace build of docs/clients.md, run as a ROS user runs it: the repository under `ws/src/mds_ach`,
the documented `colcon build` command, then `ros2 run mds_ach daemon --nocan`.

The "ROS 2 Jazzy environment" is a prefix of symbolic links to this venv's ROS wheels (rclpy, the message
packages, ament, rosidl, colcon from PyPI) without this project's packages (mds_ach, mds_ach_interfaces, the
control_msgs subset): what `source /opt/ros/jazzy/setup.bash` gives a user who has not built anything of ours, so
every import of ours must come from the workspace. ros2cli is not a wheel: `ros2 run` is done as it resolves
(ament index, then `<prefix>/lib/mds_ach/<exe>`), like test_ros2_run.py.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy
import pytest
from support import REPO, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.ros]

VENV = Path(sys.prefix)
SITE = Path(sysconfig.get_paths()["purelib"])
PYVER = f"python{sys.version_info.major}.{sys.version_info.minor}"
OURS = ("mds_ach_interfaces", "control_msgs", "tf2_msgs")  # the interface packages under interfaces/


def _ours(name: str) -> bool:
    """An installed file or folder of this project (site-packages, lib/, share/, include/ entries)."""
    return (name == "mds_ik.py" or name.startswith(("mds_ach", "__editable__.mds_ach", "__editable___mds_ach"))
            or any(name.startswith((pkg, f"lib{pkg}__")) for pkg in OURS))


def _link_tree(src: Path, dst: Path, depth: int) -> None:
    """dst mirrors src with symbolic links, without our entries; `depth` levels are real folders."""
    dst.mkdir(parents=True, exist_ok=True)
    for entry in sorted(src.iterdir()):
        if _ours(entry.name) or (dst / entry.name).exists():
            continue
        if depth > 0 and entry.is_dir() and not entry.is_symlink():
            _link_tree(entry, dst / entry.name, depth - 1)
        else:
            (dst / entry.name).symlink_to(entry)


def jazzy_environment(root: Path) -> Path:
    """A Python prefix with the venv's ROS wheels and colcon and none of this project's packages."""
    base = Path(getattr(sys, "_base_executable", sys.executable))
    subprocess.run([str(base), "-m", "venv", "--without-pip", str(root)], check=True)
    _link_tree(SITE, root / "lib" / PYVER / "site-packages", 0)
    for top, depth in (("lib", 0), ("include", 0), ("share", 3)):  # share/ament_index/resource_index/<type>/
        _link_tree(VENV / top, root / top, depth)
    colcon = root / "bin" / "colcon"
    colcon.write_text(f"#!{root}/bin/python\nimport sys\nfrom colcon_core.command import main\nsys.exit(main())\n")
    colcon.chmod(0o755)
    return root


def documented_command() -> str:
    """The `colcon build` line of docs/clients.md "Building for `ros2 run`" (the test runs what users read)."""
    text = (REPO / "docs" / "clients.md").read_text()
    section = text.split("## Building for `ros2 run`", 1)[1].split("\n## ", 1)[0]
    lines = [ln.strip() for ln in re.findall(r"```sh\n(.*?)```", section, re.S)[0].splitlines()]
    return next(ln for ln in lines if ln.startswith("colcon build"))


def clone_into(ws: Path, under: str = ".") -> Path:
    """ws/src/mds_ach with the repository's files (tracked and new, as a clone of this work tree would have), all
    of them or those under `under`."""
    src = ws / "src" / "mds_ach"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z", "--", under], cwd=REPO,
                           capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, files):
        if (REPO / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, src / rel)
    return src


def wheel_cmake_args(env_root: Path) -> list[str]:
    """What only the wheel environment needs (interfaces/cmake/wheel_paths.cmake); /opt/ros/jazzy does not."""
    return ["--cmake-args", f"-DCMAKE_PROJECT_INCLUDE={REPO}/interfaces/cmake/wheel_paths.cmake",
            f"-DMDS_PYTHON_INCLUDE={sysconfig.get_paths()['include']}", f"-DMDS_NUMPY_INCLUDE={numpy.get_include()}",
            f"-DPython3_EXECUTABLE={env_root}/bin/python", "-DPython3_FIND_STRATEGY=LOCATION",
            "-DBUILD_TESTING=OFF"]


def user_env(env_root: Path) -> dict[str, str]:
    """The shell of a user who sourced the Jazzy environment (and nothing of this project)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH", "COLCON_PREFIX_PATH",
                        "LD_LIBRARY_PATH", "VIRTUAL_ENV", "_ROS_WHEELS_BOOTSTRAP_COMPLETE")}
    env.update(PATH=f"{env_root}/bin:/usr/local/bin:/usr/bin:/bin", AMENT_PREFIX_PATH=str(env_root),
               CMAKE_PREFIX_PATH=str(env_root), VIRTUAL_ENV=str(env_root))
    return env


def colcon_build(ws: Path, env_root: Path, command: str, extra: list[str]) -> subprocess.CompletedProcess[str]:
    args = " ".join(extra)
    return subprocess.run(["bash", "-c", f"{command} {args}"], cwd=ws, env=user_env(env_root), capture_output=True,
                          text=True, timeout=900)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, subprocess.CompletedProcess[str]]:
    root = tmp_path_factory.mktemp("ws_build")
    env_root = jazzy_environment(root / "jazzy")
    ws = root / "ws"
    clone_into(ws)
    proc = colcon_build(ws, env_root, documented_command(), wheel_cmake_args(env_root))
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return ws, env_root, proc


def sourced(ws: Path, env_root: Path, code: str) -> subprocess.CompletedProcess[str]:
    """Run `code` in bash after `. install/setup.sh` (colcon-core's shell; colcon-bash adds setup.bash)."""
    return subprocess.run(["bash", "-c", f". install/setup.sh && {code}"], cwd=ws, env=user_env(env_root),
                          capture_output=True, text=True, timeout=120)


def test_the_environment_has_none_of_ours(tmp_path: Path) -> None:
    """The premise: without the workspace, the Jazzy environment cannot import our packages (the reported bug)."""
    env_root = jazzy_environment(tmp_path / "jazzy")
    for module in ("rclpy", "colcon_core", "sensor_msgs.msg"):
        subprocess.run([f"{env_root}/bin/python", "-c", f"import {module}"], env=user_env(env_root), check=True,
                       cwd="/", capture_output=True)
    for module in ("mds_ach", "mds_ach_interfaces.msg", "control_msgs.action", "tf2_msgs.msg"):
        proc = subprocess.run([f"{env_root}/bin/python", "-c", f"import {module}"], env=user_env(env_root),
                              cwd="/", capture_output=True, text=True)
        assert proc.returncode != 0 and "No module named" in proc.stderr, module


def test_documented_build_discovers_every_package(workspace: tuple[Path, Path, subprocess.CompletedProcess[str]]
                                                  ) -> None:
    ws, _env_root, proc = workspace
    finished = set(re.findall(r"Finished <<< (\S+)", proc.stdout))
    assert finished == {"mds_ach", *OURS}, proc.stdout
    for pkg in finished:
        assert (ws / "install" / pkg / "share" / "ament_index" / "resource_index" / "packages" / pkg).is_file(), pkg


def test_workspace_imports_resolve_to_the_install(workspace: tuple[Path, Path, subprocess.CompletedProcess[str]]
                                                  ) -> None:
    ws, env_root, _ = workspace
    code = ("import mds_ach, mds_ach_interfaces.msg as m, control_msgs.action as c, tf2_msgs.msg as t; "
            "from mds_ach_interfaces.msg import MuxState; MuxState(); "
            "from control_msgs.action import FollowJointTrajectory; FollowJointTrajectory.Goal(); "
            "t.TFMessage(); print(mds_ach.__file__, m.__file__, c.__file__, t.__file__)")
    proc = sourced(ws, env_root, f"python -c '{code}'")
    assert proc.returncode == 0, proc.stderr
    files = proc.stdout.split()
    for path, pkg in zip(files, ("mds_ach", "mds_ach_interfaces", "control_msgs", "tf2_msgs"), strict=True):
        assert path.startswith(f"{ws}/install/{pkg}/"), (pkg, path)


def test_ros2_run_daemon_nocan_starts(workspace: tuple[Path, Path, subprocess.CompletedProcess[str]]) -> None:
    """`ros2 run mds_ach daemon --nocan`: resolved through the ament index, it runs its loop and its ROS node."""
    ws, env_root, _ = workspace
    where = sourced(ws, env_root, "python -c 'from ament_index_python.packages import get_package_prefix as p; "
                                  "print(p(\"mds_ach\"))'")
    assert where.returncode == 0, where.stderr
    exe = Path(where.stdout.strip()) / "lib" / "mds_ach" / "daemon"
    assert exe == ws / "install" / "mds_ach" / "lib" / "mds_ach" / "daemon"
    daemon = subprocess.Popen(["bash", "-c", f". install/setup.sh && exec {exe} --nocan"], cwd=ws,
                              env=user_env(env_root), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    import rclpy

    rclpy.init()
    node = rclpy.create_node("test_workspace_build")
    try:
        def service_up() -> bool:
            assert daemon.poll() is None, f"daemon exited ({daemon.returncode}):\n{daemon.communicate()[0]}"
            return any(name == "/mds_daemon/command" and types == ["mds_ach_interfaces/srv/Command"]
                       for name, types in node.get_service_names_and_types())
        wait_for(service_up, 90.0, interval=0.2, what="/mds_daemon/command from the workspace's daemon")
    finally:
        node.destroy_node()
        rclpy.shutdown()
        daemon.send_signal(signal.SIGINT)
        out, _ = daemon.communicate(timeout=30)
    assert daemon.returncode == 0, out
    assert "No module named" not in out, out


def test_control_msgs_subset_not_built_over_an_installed_one(tmp_path: Path) -> None:
    """Where the environment has control_msgs (here the venv, with the subset built by make setup: the same
    check as /opt/ros/jazzy with ros-jazzy-control-msgs), the documented command builds the subset's package
    with nothing in it, so the environment's control_msgs stays the one found."""
    ws = tmp_path / "ws"
    clone_into(ws, "interfaces")
    command = documented_command() + " --packages-select control_msgs"
    env = user_env(VENV)
    extra = " ".join(["--event-handlers", "console_direct+", *wheel_cmake_args(VENV)])  # cmake's output on stdout
    proc = subprocess.run(["bash", "-c", f"{command} {extra}"], cwd=ws, env=env, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, f"{proc.stdout}\n{proc.stderr}"
    assert f"control_msgs is already installed in {VENV}: this subset is not built" in proc.stdout, proc.stdout
    prefix = ws / "install" / "control_msgs"
    assert not (prefix / "share" / "ament_index" / "resource_index" / "packages" / "control_msgs").exists()
    assert not list(prefix.rglob("*.so")) and not list(prefix.rglob("*.msg")), "the subset was installed"
