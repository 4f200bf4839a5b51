"""Randomized adversarial safety test: the whole stack, a seeded random sequence of commands and faults, and
``mds-ach check-log`` on everything the daemon sent (``bench/adversary.py`` has the scenario).

The seed is fresh each run and printed (``MDS_AUDIT_SEED=N`` repeats a sequence; the processes' timing still
varies); ``MDS_AUDIT_SECONDS`` sets the scenario length (60 s here, many minutes in ``make soak``). Also here:
the test-only fault control the scenario uses to reach the daemon's simulated bus.
"""

from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import can
import pytest
from support import REPO, VENV_BIN, in_netns, remove_mds_channels

from mds_ach.bus import mcb
from mds_ach.bus.simbus import FaultControl, ManualClock, SimNetwork, send_fault
from mds_ach.robot import config
from mds_ach.tools import checklog

if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
from bench import adversary  # noqa: E402  (bench/ is not an installed package)

TABLE = config.load("default")
SECONDS = float(os.environ.get("MDS_AUDIT_SECONDS", "60"))


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_random_commands_and_faults_never_break_the_safety_invariants(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    assert in_netns(), "run through tools/netns-run (private /dev/shm and network namespace)"
    seed = int(os.environ.get("MDS_AUDIT_SEED") or random.SystemRandom().randrange(2**32))
    print(f"\nadversarial scenario seed {seed} (MDS_AUDIT_SEED={seed} repeats it)")
    monkeypatch.setenv("MDS_ACH_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setenv("MDS_ACH_CONFIG_DIR", str(tmp_path / "config"))
    monkeypatch.delenv("MDS_ACH_ROBOT", raising=False)
    remove_mds_channels()
    try:
        result = adversary.run(seed, SECONDS, tmp_path)
    finally:
        remove_mds_channels()
    report = adversary.audit(result, collisions=True)
    text = checklog.format_report(report, TABLE, max_listed=60)
    print(text)
    assert not result.problems, f"seed {seed}: the stack misbehaved: {result.problems}"
    # The scenario really exercised the system: motion went out, and most kinds of attack happened.
    assert sum(sum(r.targets.values()) for r in report.files) > 50, text
    assert len(result.counts) >= 5 and sum(result.counts.values()) >= 15, result.counts
    # Every daemon log with targets had its commanded poses checked (a run killed before the first goto has none).
    assert all(r.poses_checked for r in report.files if not r.error and sum(r.targets.values())), text
    assert report.exit_code == 0, f"seed {seed} (MDS_AUDIT_SEED={seed} repeats it):\n" + "\n".join(
        result.actions) + "\n" + text


# --------------------------------------------------------------------------------------------- fault control


def test_fault_control_reaches_the_simulated_bus(tmp_path: Path) -> None:
    clock = ManualClock()
    net = SimNetwork.from_table(TABLE, clock=clock, bitrate=None)
    path = tmp_path / "faults.sock"
    control = FaultControl(path, net)
    try:
        assert path.stat().st_mode & 0o777 == 0o600
        lsp = TABLE["LSP"].address
        send_fault(path, "bogus_positions", address=lsp, counts=1000.0, replies=2)
        replies = []
        for _ in range(3):
            net.host_send(can.Message(arbitration_id=mcb.BROADCAST_SID, data=mcb.encode_query_positions().data,
                                      is_extended_id=False))
            clock.advance(0.01)
            while (m := net.host_recv(0)) is not None:
                pos = mcb.decode_position(m.data)
                if pos and pos[0] == lsp:
                    replies.append(pos[1])
        assert replies == [1000.0, 1000.0, 0.0]  # two bogus readings, then the truth; the node never moved
        assert float(send_fault(path, "position", address=lsp).split()[1]) == 0.0
        send_fault(path, "offline", address=lsp, on=True)
        assert net.faults[lsp].offline
        send_fault(path, "bus_off")
        assert net.bus_off_active
        with pytest.raises(RuntimeError, match="unknown op"):
            send_fault(path, "explode")
        with pytest.raises(RuntimeError, match="KeyError"):
            send_fault(path, "offline")
    finally:
        control.close()
    assert not path.exists()


def test_fault_control_exists_only_on_the_simulated_bus(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAN_")} | {"HOME": str(tmp_path)}
    out = subprocess.run([str(VENV_BIN / "mds-ach-daemon"), "--no-ros", "--sim-faults", str(tmp_path / "s")],
                         capture_output=True, text=True, timeout=60, env=env, cwd=tmp_path)
    assert out.returncode == 2 and "--sim-faults needs --nocan" in out.stderr, out.stderr
