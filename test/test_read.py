"""The read monitor, through a pseudo-terminal and as --once snapshots, fed with known frames.

The monitor only reads channels, so the tests publish the frames themselves (exact values to look for)
instead of starting the whole system; test_launcher.py covers it against the running system.
"""

from __future__ import annotations

import os
import re
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import VENV_BIN, remove_mds_channels, wait_for
from support.pty_session import PtySession

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot.channels import StructChannel, make_channels
from mds_ach.robot.config import load
from mds_ach.robot.joints import published_short
from mds_ach.robot.msgs.daemon_status import (
    JOINT_CONFIGURED,
    JOINT_ENABLED,
    JOINT_FRESH,
    JOINT_STALE,
    MDS_DAEMON_STATUS,
)
from mds_ach.tools.read import ALT_OFF, ALT_ON, CURSOR_ON

READ = str(VENV_BIN / "mds-ach-read")


class Publisher:
    """Publishes a state (home pose, LSP at a chosen value), daemon status and collide frames at 20 Hz."""

    def __init__(self) -> None:
        make_channels()
        self.table = load()
        self.state = mds.MDS_STATE()
        self.table.fill_state(self.state)
        for j in self.table:
            self.state.joint[j.address].ref = j.home
            self.state.joint[j.address].pos = j.home + 0.001
        self.state.joint[mds.LSP].ref = -0.123
        self.state.joint[mds.LSP].pos = -0.12
        self.status = MDS_DAEMON_STATUS(rate_hz=10.0, measured_rate_hz=9.96, bus_load_avg=12.0, nocan=1)
        for j in self.table:
            self.status.joint_flags[j.address] = JOINT_CONFIGURED | (JOINT_ENABLED | JOINT_FRESH if j.enabled else 0)
        self.status.joint_flags[mds.REP] = JOINT_CONFIGURED | JOINT_ENABLED | JOINT_STALE
        self.collide = mds.MDS_COLLIDE()
        self.collide.joint[mds.COLLIDE_L_HAND].isCollide = 1
        self.collide.isCollide = 1
        self.collide.time_dt = 0.0123456
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.channels = {
            "state": StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE),
            "status": StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS),
            "collide": StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE),
        }

    def put(self) -> None:
        with self.lock:
            self.state.time += 0.05
            self.channels["state"].put(self.state)
            self.channels["status"].put(self.status)
            self.channels["collide"].put(self.collide)

    def set_pos(self, short: str, value: float) -> None:
        with self.lock:
            self.state.joint[mds.BY_SHORT[short].address].pos = value

    def start(self) -> Publisher:
        def loop() -> None:
            while not self._stop.wait(0.05):
                self.put()

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join()
        for ch in self.channels.values():
            ch.close()


@pytest.fixture
def publisher(clean_shm: None) -> Iterator[Publisher]:
    pub = Publisher()
    pub.put()
    yield pub
    pub.close()


def read_once(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([READ, *args, "--once"], capture_output=True, text=True, timeout=60)


def test_once_prints_the_original_columns_for_enabled_joints(publisher: Publisher) -> None:
    publisher.start()
    proc = read_once()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert re.search(r"Joint\s+Enabled\s+address\s+Commanded Pos\s+Actual Pos\s+Fresh", out)
    row = re.search(r"^LSP\s+LeftShoulderExt\s+1\s+0x005f\s+(-?\d+\.\d{5})\s+(-?\d+\.\d{5})\s+yes", out, re.M)
    assert row, out
    assert (float(row.group(1)), float(row.group(2))) == (-0.123, -0.12)
    assert re.search(r"^REP\s+RightElbowFlex\s+1\s+0x0048\s+\S+\s+\S+\s+STALE", out, re.M), out
    enabled = [j.short for j in publisher.table if j.enabled]
    rows = re.findall(r"^(\w+)\s+\w+\s+[01]\s+0x00[0-9a-f]{2}\s", out, re.M)
    assert rows == enabled, "read shows exactly the enabled joints, in table order"
    assert "10.0/10 Hz" in out and "bus active 12%" in out and "(nocan)" in out
    assert "[ Collisions ]" in out
    assert re.search(r"^Right\s+0\s+0\s+0\s+0\s+0$", out, re.M)
    assert re.search(r"^Left\s+1\s+0\s+0\s+0\s+0$", out, re.M)
    assert "Collide: True" in out and "dt = 0.0123456" in out
    assert "collision: BLOCKED: L_HAND" in out


def test_all_shows_every_joint(publisher: Publisher) -> None:
    publisher.start()
    proc = read_once("all")
    assert proc.returncode == 0, proc.stderr
    rows = re.findall(r"^(\w+)\s+\w+\s+([01])\s+0x00[0-9a-f]{2}\s", proc.stdout, re.M)
    assert [r[0] for r in rows] == [published_short(j.address, j.short) for j in mds.JOINTS]  # LYP twice, RYP
    assert ("LF1", "0") in rows


def test_once_fails_when_the_state_is_not_live(publisher: Publisher) -> None:
    proc = read_once()  # one old frame in the channel, nobody publishing
    assert proc.returncode == 1
    assert "waiting for a new frame" in proc.stdout
    assert "LeftShoulderExt" in proc.stdout  # the last known values are still shown


def test_param_dumps_one_joint(publisher: Publisher) -> None:
    with StructChannel(mds.MDS_CHAN_PARAM_NAME, mds.MDS_JOINT_PARAM) as ch:
        ch.put(publisher.table.to_param())
    for which in ("LSP", "0x5f", "95", "leftshoulderext"):
        proc = subprocess.run([READ, "param", which], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        assert "param of address 95 (0x005f)" in proc.stdout
        assert re.search(r"^\s+nameshort\s+LSP$", proc.stdout, re.M)
        assert re.search(r"^\s+offset\s+-0\.45$", proc.stdout, re.M)
        assert re.search(r"^\s+direction\s+-1$", proc.stdout, re.M)
    proc = subprocess.run([READ, "param", "XYZ"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "XYZ" in proc.stderr


def test_without_channels_nothing_is_created(clean_shm: None) -> None:
    proc = read_once()
    assert proc.returncode == 1
    assert "waiting for mds-state (channel mds-state does not exist)" in proc.stdout
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS), "read must never create channels"
    proc = subprocess.run([READ, "param", "LSP"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "nothing on mds-param (channel mds-param does not exist)" in proc.stderr
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)


def test_bad_view_is_a_usage_error() -> None:
    proc = subprocess.run([READ, "everything"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "unknown view" in proc.stderr
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), "read", "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and "param N" in proc.stdout


def _frames(name: str) -> list[tuple[int, bytes]]:
    return ach.parse_image(Path(ach.shm_path(name)).read_bytes()).frames()


def test_live_table_updates_and_q_restores_the_terminal(publisher: Publisher) -> None:
    publisher.start()
    with PtySession([READ], env=dict(os.environ), rows=60, cols=120) as pty:
        pty.expect(ALT_ON, timeout=30)
        pty.expect(re.compile(r"LSP\s+LeftShoulderExt\s+1\s+0x005f\s+-0\.12300\s+-0\.12000"), timeout=15)
        publisher.set_pos("LSP", 0.25)
        pty.expect(re.compile(r"LSP\s+LeftShoulderExt\s+1\s+0x005f\s+-0\.12300\s+0\.25000"), timeout=15)
        pty.expect("[ Collisions ]", timeout=5)
        pty.send("q")
        assert pty.wait(timeout=10) == 0
        tail = pty.buffer[-200:]
        assert CURSOR_ON in tail and ALT_OFF in tail, "the terminal must be restored"


def test_small_terminal_resize_and_ctrl_c(publisher: Publisher) -> None:
    publisher.start()
    with PtySession([READ, "all"], env=dict(os.environ), rows=12, cols=60) as pty:
        pty.expect(re.compile(r"\.\.\. \d+ more joints: enlarge the terminal"), timeout=30)
        screen = pty.buffer[pty.buffer.rfind("\x1b[H"):]
        for line in re.sub(r"\x1b\[[0-9;?]*[a-zA-Z]", "", screen).replace("\r", "").split("\n"):
            assert len(line) < 60, f"line wider than the terminal: {line!r}"
        pty.resize(70, 120)
        pty.expect("[ Collisions ]", timeout=15)
        pty.send("\x03")
        assert pty.wait(timeout=10) == 0
        assert pty.buffer.rstrip().endswith(ALT_OFF)


def test_starts_before_the_system_and_never_disturbs_it(clean_shm: None) -> None:
    """read can start first (waits for the channels), and reading never changes a channel's frames."""
    with PtySession([READ], env=dict(os.environ), rows=50, cols=120) as pty:
        pty.expect("waiting for mds-state (channel mds-state does not exist)", timeout=30)
        pub = Publisher()
        try:
            pub.put()
            before = {n: _frames(n) for n in (mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_COLLIDE_NAME)}
            pty.expect(re.compile(r"LSP\s+LeftShoulderExt\s+1\s+0x005f"), timeout=15)
            pty.expect("STALE", timeout=15)  # nobody publishes: the age shows it
            after = {n: _frames(n) for n in before}
            assert after == before, "read changed a channel"
            listener = StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False)
            listener.flush()
            pub.start()
            assert wait_for(lambda: listener.wait(0.5), timeout=5, what="frames reach another reader")
            listener.close()
        finally:
            pty.terminate()
            assert pty.wait(timeout=10) == 0
            pub.close()
    remove_mds_channels()
