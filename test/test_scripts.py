"""scripts/start_nodes.sh and stop_nodes.sh: the whole system node by node, without launch files."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from support import REPO, VENV_BIN, in_netns, remove_mds_channels, wait_for
from support.channels import newest
from support.system import joint_pos, mds_ach, system_env

import mds_ach as mds
from mds_ach.robot.msgs import MDS_MUX_STATE
from mds_ach.tools.launcher import NODES, read_pid

READY = [(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE), (mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE),
         (mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)]
START = REPO / "scripts" / "start_nodes.sh"
STOP = REPO / "scripts" / "stop_nodes.sh"


def test_scripts_have_help_and_refuse_bad_arguments() -> None:
    for script in (START, STOP):
        proc = subprocess.run([str(script), "--help"], capture_output=True, text=True, timeout=30)
        assert proc.returncode == 0 and "Usage:" in proc.stdout, proc.stdout
        proc = subprocess.run([str(script), "--bogus"], capture_output=True, text=True, timeout=30)
        assert proc.returncode == 2 and "usage:" in proc.stderr


@pytest.mark.slow
def test_start_nodes_runs_the_system_and_stop_nodes_ends_it(clean_shm: None, tmp_path: Path) -> None:
    assert in_netns()
    env = system_env(tmp_path)
    env.pop("MDS_ACH_BIN", None)
    try:
        proc = subprocess.run([str(START), "--nocan"], env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        for name in NODES:
            assert re.search(rf"^\s+{name} started \(pid \d+", proc.stdout, re.M), proc.stdout
        pids = {n: read_pid(n, tmp_path) for n in NODES}
        assert all(pids.values()), f"every node runs and its pid file names it: {pids}"
        # the launcher's tools understand what the script started
        status = mds_ach("status", "--window", "0.5", env=env)
        assert status.returncode == 0, status.stdout + status.stderr
        # the pipeline works end to end once the nodes are up (the script does not wait for them)
        wait_for(lambda: all(newest(n, t) is not None for n, t in READY), timeout=120, what="pipeline up")
        move = subprocess.run([str(VENV_BIN / "mds-ach-console"), "-c", "goto RSP -0.2 wait"], env=env,
                              capture_output=True, text=True, timeout=120)
        assert move.returncode == 0, move.stdout + move.stderr
        assert abs(joint_pos("RSP") + 0.2) < 0.011

        proc = subprocess.run([str(STOP)], env=env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        lines = re.findall(r"^\s+(\w+): SIGTERM", proc.stdout, re.M)
        assert set(lines) == set(NODES) and lines[-1] == "daemon", "the daemon stops last"
        assert not any(Path(f"/proc/{p}").exists() and _alive(p) for p in pids.values())
        assert not list(tmp_path.glob("*.pid"))
        again = subprocess.run([str(STOP)], env=env, capture_output=True, text=True, timeout=60)
        assert again.returncode == 0 and "SIGTERM" not in again.stdout
    finally:
        subprocess.run([str(STOP), "1"], env=env, capture_output=True, timeout=60)
        mds_ach("killall", env=env)
        remove_mds_channels()


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2] != "Z"
