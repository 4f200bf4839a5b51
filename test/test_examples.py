"""Every example in examples/ against the running simulated system, checking that the motion really happened
(measured positions on mds-state, not the examples' own output)."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from support import REPO, libach, wait_for
from support.system import arm_pos, chain_fk, joint_pos, running_system

import mds_ach as mds

EXAMPLES = REPO / "examples"


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    with running_system(tmp_path_factory.mktemp("examples")) as env:
        yield env


def run_example(env: dict[str, str], name: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(EXAMPLES / name), *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


def left_hand() -> np.ndarray:
    return chain_fk(arm_pos("left"), "left")[0]


def test_examples_have_help() -> None:
    for path in sorted(EXAMPLES.glob("*.py")):
        proc = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0 and "usage" in proc.stdout, f"{path.name}: {proc.stderr}"


@pytest.mark.slow
def test_c_examples_build_and_move_the_robot(system: dict[str, str], tmp_path: Path) -> None:
    """examples/c builds with its Makefile against the project's libach (make setup) and drives the robot."""
    out = tmp_path / "c"
    proc = subprocess.run(["make", "-C", str(EXAMPLES / "c"), f"BUILD={out}", f"ACH_PREFIX={libach.prefix()}"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    proc = subprocess.run([str(out / "mds_controller"), "-0.25", "0.15"], env=system, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    wait_for(lambda: abs(joint_pos("LEP") + 0.25) < 0.006 and abs(joint_pos("LSP") - 0.15) < 0.006, timeout=30,
             what="LEP at -0.25 and LSP at 0.15")
    proc = subprocess.run([str(out / "mds_ik_request"), "left", "0.3", "0.2", "0.0"], env=system,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    wait_for(lambda: np.linalg.norm(left_hand() - [0.3, 0.2, 0.0]) < 0.03, timeout=30,
             what="left hand at (0.3, 0.2, 0.0)")


@pytest.mark.slow
def test_one_joint(system: dict[str, str]) -> None:
    proc = run_example(system, "one_joint.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert abs(joint_pos("LSP") + 0.123) < 0.006


@pytest.mark.slow
def test_two_joints(system: dict[str, str]) -> None:
    proc = run_example(system, "two_joints.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert abs(joint_pos("LEP") + 0.2) < 0.006
    assert abs(joint_pos("RSP") - 0.1) < 0.006


@pytest.mark.slow
def test_local_ik_solver(system: dict[str, str]) -> None:
    proc = run_example(system, "ik_solver_local.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    wait_for(lambda: np.linalg.norm(left_hand() - [0.3, 0.2, 0.0]) < 0.02, timeout=20,
             what="left hand at (0.3, 0.2, 0.0)")


@pytest.mark.slow
def test_ik_box_one_round(system: dict[str, str]) -> None:
    proc = run_example(system, "ik_box.py", "--cycles", "1", "--period", "4", timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("arrived after") == 5, proc.stdout
    np.testing.assert_allclose(left_hand(), [0.4, 0.45, -0.25], atol=0.03)  # the last corner


@pytest.mark.slow
def test_ik_point(system: dict[str, str]) -> None:
    proc = run_example(system, "ik_point.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert re.search(r"IK solved in \d+ iterations", proc.stdout)
    np.testing.assert_allclose(left_hand(), [0.3, 0.2, 0.0], atol=0.03)


@pytest.mark.slow
def test_ros_joint_state_subscriber(system: dict[str, str]) -> None:
    proc = run_example(system, "ros_joint_state_subscriber.py", "--count", "3")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 3
    values = dict(re.findall(r"(\w+)=([+-]\d+\.\d+)", lines[-1]))
    assert list(values) == list(mds.joints.MODEL_JOINTS)
    for name in ("LSP", "LEP", "RSP", "WST"):
        assert abs(float(values[name]) - joint_pos(name)) < 0.002, name


@pytest.mark.slow
def test_ros_trajectory_publisher(system: dict[str, str]) -> None:
    start = joint_pos("LEP")
    proc = run_example(system, "ros_trajectory_publisher.py")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lowest_lep = start
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # follow the motion: through the first point, to the last
        lowest_lep = min(lowest_lep, joint_pos("LEP"))
        if abs(joint_pos("LSP") + 0.2) < 0.006 and abs(joint_pos("LEP") + 0.3) < 0.006 and lowest_lep < -0.5:
            break
        time.sleep(0.05)
    assert lowest_lep < -0.5, f"LEP never came near the via point (-0.6): from {start} lowest {lowest_lep}"
    assert abs(joint_pos("LSP") + 0.2) < 0.006 and abs(joint_pos("LEP") + 0.3) < 0.006
