"""Start and stop the whole simulated system for a test module (``mds-ach start nocan`` ... ``killall``).

Why a helper module instead of a conftest fixture: only the operator-tool tests need a full system, and each
of their modules starts it once (module scope) to keep the suite fast.
"""

from __future__ import annotations

import ctypes
import math
import os
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from conftest import VENV_BIN, in_netns, remove_mds_channels

import mds_ach as mds
from mds_ach import ach

START_TIMEOUT = 150.0  # s: cold start imports torch, fcl and rclpy on a shared 2-core machine


def system_env(runtime: Path) -> dict[str, str]:
    """Environment for the system and its clients: private runtime and config dirs, the default robot."""
    env = dict(os.environ)
    env["MDS_ACH_RUNTIME_DIR"] = str(runtime)
    env["MDS_ACH_CONFIG_DIR"] = str(runtime / "config")
    env["MDS_ACH_HISTORY"] = str(runtime / "console_history")
    env.pop("MDS_ACH_ROBOT", None)
    return env


def mds_ach(*args: str, env: dict[str, str], timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([str(VENV_BIN / "mds-ach"), *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


@contextmanager
def running_system(runtime: Path, robot: str | None = None) -> Iterator[dict[str, str]]:
    """``mds-ach start nocan`` in a clean /dev/shm (after ``changerobot robot`` if given); yields the
    environment; ``mds-ach stop`` and ``killall`` afterwards."""
    assert in_netns(), "run the tests through tools/netns-run (private /dev/shm and network namespace)"
    remove_mds_channels()
    env = system_env(runtime)
    if robot:
        proc = mds_ach("changerobot", robot, env=env)
        assert proc.returncode == 0, proc.stderr
    proc = mds_ach("start", "nocan", "--timeout", str(START_TIMEOUT), env=env, timeout=START_TIMEOUT + 60)
    assert proc.returncode == 0, f"mds-ach start nocan failed:\n{proc.stdout}\n{proc.stderr}"
    try:
        yield env
    finally:
        mds_ach("stop", env=env, timeout=60)
        mds_ach("killall", env=env, timeout=60)
        remove_mds_channels()


def newest(name: str, ctype: type[ctypes.Structure]) -> ctypes.Structure | None:
    """The newest frame of a channel (read-only, even if seen before)."""
    obj = ctype()
    with ach.Channel(name, create=False) as chan:
        status, size = chan.get(obj, last=True, copy=True)
    return obj if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(ctype) else None


def state() -> mds.MDS_STATE:
    st = newest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
    assert st is not None, "no frame on mds-state"
    return st


def joint_pos(short: str) -> float:
    return float(state().joint[mds.BY_SHORT[short].address].pos)


def joint_ref(short: str) -> float:
    return float(state().joint[mds.BY_SHORT[short].address].ref)


def arm_refs(arm: str) -> list[float]:
    names = mds.joints.LEFT_ARM if arm == "left" else mds.joints.RIGHT_ARM
    return [joint_ref(n) for n in names]


def arm_pos(arm: str) -> list[float]:
    names = mds.joints.LEFT_ARM if arm == "left" else mds.joints.RIGHT_ARM
    return [joint_pos(n) for n in names]


def chain_fk(q: list[float], arm: str) -> tuple[np.ndarray, np.ndarray]:
    """The original IK chain (mds-original.md section e.1), written out independently of mds_ach.kinematics.model."""
    l1, l2, l3, l4 = 0.24551, 0.282575, 0.3127375, 0.0635
    m = 1.0 if arm == "left" else -1.0

    def rot(axis: str, a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
                "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
                "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]

    steps = [((0, m * l1, 0), "y"), ((0, 0, 0), "x"), ((0, 0, 0), "z"), ((0, 0, -l2), "y"), ((0, 0, -l3), "z"),
             ((0, 0, 0), "x")]
    R, p = np.eye(3), np.zeros(3)
    for (offset, axis), angle in zip(steps, q, strict=True):
        p = p + R @ np.array(offset, dtype=float)
        R = R @ rot(axis, angle)
    p = p + R @ np.array([0.0, 0.0, -l4])
    euler = np.array([math.atan2(R[2, 1], R[2, 2]), math.atan2(-R[2, 0], math.hypot(R[2, 1], R[2, 2])),
                      math.atan2(R[1, 0], R[0, 0])])
    return p, euler
