"""The package builds with colcon and every executable resolves exactly as `ros2 run mds_ach <exe>` would.

ros2cli is not available as a wheel, so the test does what `ros2 run` does: ask the ament index for the
package prefix, execute `<prefix>/lib/mds_ach/<exe>`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from importlib.metadata import distribution
from pathlib import Path

import pytest
from support import REPO, VENV_BIN

EXECUTABLES = ["daemon", "filter", "mux", "ik", "collision", "bridge", "console", "read", "mds-ach"]
SOURCES = ["package.xml", "setup.py", "setup.cfg", "resource", "mds_ach", "mds_ach_bridge", "urdf", "config",
           "include", "launch", "mds_ik.py"]


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build a copy of the package with colcon into a temporary install prefix (isolated layout)."""
    root = tmp_path_factory.mktemp("colcon")
    src = root / "src" / "mds_ach"
    src.mkdir(parents=True)
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so"))
        else:
            shutil.copy2(path, src / name)
    colcon = Path(sys.executable).parent / "colcon"
    proc = subprocess.run(
        [str(colcon), "--log-base", str(root / "log"), "build", "--base-paths", str(root / "src"),
         "--build-base", str(root / "build"), "--install-base", str(root / "install")],
        cwd=root, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout}\n{proc.stderr}"
    return root / "install"


def _env(install: Path) -> dict[str, str]:
    prefix = install / "mds_ach"
    env = dict(os.environ)
    venv = Path(sys.executable).parent.parent
    env["AMENT_PREFIX_PATH"] = f"{prefix}:{venv}"
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = str(site)
    return env


def test_colcon_builds_the_ach_fast_path(colcon_install: Path) -> None:
    """The installed package imports from the prefix and has the C fast path wherever the dev install has it."""
    from mds_ach import ach

    code = "from mds_ach import ach; print(ach.__file__); print(ach.FAST_AVAILABLE)"
    out = subprocess.run([sys.executable, "-c", code], env=_env(colcon_install), capture_output=True, text=True,
                         check=True, cwd="/")
    where, fast = out.stdout.split()
    assert where.startswith(str(colcon_install))
    assert fast == str(ach.FAST_AVAILABLE)


def test_colcon_installs_the_original_mds_ik_module(colcon_install: Path) -> None:
    """`import mds_ik as ik` (the original module name) works from the install prefix and is the package's IK."""
    code = ("import mds_ik, mds_ach.kinematics.ik as k; assert mds_ik is k; import mds_ik as ik; "
            "print(ik.getFkArm([0] * 6, 'left')[2, 3])")
    out = subprocess.run([sys.executable, "-c", code], env=_env(colcon_install), capture_output=True, text=True,
                         cwd="/")
    assert out.returncode == 0, out.stderr
    assert abs(float(out.stdout) + 0.6588125) < 1e-6  # the zero-pose tool point (specs/mds-original.md §e.1)
    site = next((colcon_install / "mds_ach" / "lib").glob("python3*/site-packages"))
    assert (site / "mds_ik.py").is_file()
    assert not (site / "ach").exists() and not (site / "ach.py").exists(), "a top-level ach would shadow py_ach"


def _resolve(install: Path, exe: str) -> Path:
    """`ros2 run` resolution: package prefix from the ament index, then lib/<pkg>/<exe>."""
    code = (
        "from ament_index_python.packages import get_package_prefix;"
        "print(get_package_prefix('mds_ach'))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=_env(install), capture_output=True, text=True,
                         check=True, cwd="/")
    return Path(out.stdout.strip()) / "lib" / "mds_ach" / exe


def test_share_files_installed(colcon_install: Path) -> None:
    code = (
        "from ament_index_python.packages import get_package_share_directory as d;"
        "print(d('mds_ach'))"
    )
    out = subprocess.run([sys.executable, "-c", code], env=_env(colcon_install), capture_output=True, text=True,
                         check=True, cwd="/")
    share = Path(out.stdout.strip())
    assert share == colcon_install / "mds_ach" / "share" / "mds_ach"
    for rel in ["package.xml", "urdf/mds.urdf", "config/joints.yaml", "include/mds.h", "launch/mds.launch.py",
                "config/moveit/mds.srdf", "config/moveit/kinematics.yaml", "config/mds.rviz"]:
        assert (share / rel).is_file(), f"{rel} not installed to share/mds_ach"


@pytest.mark.parametrize("exe", EXECUTABLES)
def test_ros2_run_help(colcon_install: Path, exe: str) -> None:
    path = _resolve(colcon_install, exe)
    assert path == colcon_install / "mds_ach" / "lib" / "mds_ach" / exe
    assert os.access(path, os.X_OK), f"{path} is not executable"
    proc = subprocess.run([str(path), "--help"], env=_env(colcon_install), capture_output=True, text=True,
                          timeout=60, cwd="/")
    assert proc.returncode == 0, f"{exe} --help failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    assert "usage" in proc.stdout.lower(), proc.stdout


def test_ros2_run_names_only_in_lib(colcon_install: Path) -> None:
    """lib/mds_ach/ holds the ros2 run names and nothing else (no mds-ach-daemon next to daemon)."""
    lib = colcon_install / "mds_ach" / "lib" / "mds_ach"
    assert sorted(p.name for p in lib.iterdir() if p.is_file()) == sorted(EXECUTABLES)


def test_bin_names_shadow_no_builtin_or_command() -> None:
    """The venv's bin/ (on PATH after `source .venv/bin/activate`) gets only mds-ach and mds-ach-<node>: a `read`
    there is hidden by the shell builtin, a `daemon` or `filter` hides or is hidden by a system command."""
    scripts = sorted(ep.name for ep in distribution("mds_ach").entry_points if ep.group == "console_scripts")
    assert scripts == sorted(f"mds-ach-{e}" if e != "mds-ach" else e for e in EXECUTABLES)
    builtins = subprocess.run(["bash", "-c", "compgen -b; compgen -k"], capture_output=True, text=True,
                              check=True).stdout.split()
    for name in scripts:
        assert (VENV_BIN / name).is_file(), f"{name} not installed in {VENV_BIN}"
        assert name not in builtins and shutil.which(name, path="/usr/local/bin:/usr/bin:/bin") is None, name
    for exe in EXECUTABLES:
        if exe != "mds-ach":
            assert not (VENV_BIN / exe).exists(), f"{VENV_BIN / exe} shadows or is shadowed by a common command"
