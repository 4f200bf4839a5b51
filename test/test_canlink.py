"""Issue #18 §4: a real start without CAN settings uses SocketCAN can0 at 1 Mbit/s and brings the link up like the
original (or says which `ip link` commands to run); `resetbus` restarts the link.

The kernel here has no SocketCAN: a fake `ip` first on $PATH answers `ip -json -details link show` from a state file
and records every call. No real interface is ever touched."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
from pathlib import Path

import pytest
from support.system import mds_ach, system_env

import mds_ach as mds
from mds_ach import ach
from mds_ach.tools import canlink

FAKE_IP = r"""#!/bin/sh
# Fake iproute2 `ip` for the tests: records its arguments, keeps one CAN link's state in $FAKE_IP_DIR/state.
echo "$*" >> "$FAKE_IP_DIR/calls"
state="$FAKE_IP_DIR/state"
case "$*" in
  "-json -details link show dev "*)
    [ -f "$state" ] || { echo "Device \"$6\" does not exist." >&2; exit 1; }
    read up bitrate < "$state"
    flags='"NOARP","ECHO"'; [ "$up" = 1 ] && flags='"NOARP","UP","LOWER_UP","ECHO"'
    data="{\"state\":\"ERROR-ACTIVE\",\"bittiming\":{\"bitrate\":$bitrate}}"
    echo "[{\"ifname\":\"$6\",\"flags\":[$flags],\"linkinfo\":{\"info_kind\":\"can\",\"info_data\":$data}}]"
    ;;
  "link set "*)
    [ -n "$FAKE_IP_EPERM" ] && { echo "RTNETLINK answers: Operation not permitted" >&2; exit 2; }
    read up bitrate < "$state"
    case "$*" in
      *" down") up=0 ;;
      *" up") up=1 ;;
      *" bitrate "*) [ "$up" = 1 ] && { echo "RTNETLINK answers: Device or resource busy" >&2; exit 2; }
                     bitrate=$(echo "$*" | sed 's/.* bitrate \([0-9]*\).*/\1/') ;;
    esac
    echo "$up $bitrate" > "$state"
    ;;
  *) echo "fake ip: unexpected: $*" >&2; exit 3 ;;
esac
"""

CONFIGURE = ["link set can0 type can bitrate 1000000 sample-point 0.5 restart-ms 100", "link set can0 up"]


@pytest.fixture
def fake_ip(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fake `ip` first on PATH (this process and its children); returns its directory (calls, state)."""
    d = tmp_path / "fake-ip"
    (d / "bin").mkdir(parents=True)
    script = d / "bin" / "ip"
    script.write_text(FAKE_IP)
    script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{d / 'bin'}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_IP_DIR", str(d))
    return d


def _link(d: Path, up: bool, bitrate: int) -> None:
    (d / "state").write_text(f"{int(up)} {bitrate}\n")


def _sets(d: Path) -> list[str]:
    calls = (d / "calls").read_text().splitlines() if (d / "calls").exists() else []
    return [c for c in calls if c.startswith("link set")]


def test_link_down_is_brought_up_like_the_original(fake_ip: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(canlink, "may_configure", lambda: True)
    _link(fake_ip, up=False, bitrate=0)
    assert canlink.ensure_up().startswith("can0 configured: ip link set can0 type can bitrate 1000000")
    assert _sets(fake_ip) == CONFIGURE
    assert canlink.link_state("can0") == canlink.LinkState(True, 1_000_000, "ERROR-ACTIVE")
    # already up at 1 Mbit/s: nothing to do
    (fake_ip / "calls").unlink()
    assert canlink.ensure_up().startswith("can0 is up (1000000 bit/s, ERROR-ACTIVE)")
    assert _sets(fake_ip) == []
    # up at another bitrate: down, configure, up
    _link(fake_ip, up=True, bitrate=500_000)
    canlink.ensure_up()
    assert _sets(fake_ip) == ["link set can0 down", *CONFIGURE]


def test_not_permitted_says_exactly_what_to_run(fake_ip: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _link(fake_ip, up=False, bitrate=0)
    monkeypatch.setattr(canlink, "may_configure", lambda: False)
    with pytest.raises(canlink.CanLinkError) as err:
        canlink.ensure_up()
    expected = " && ".join(f"sudo ip {c}" for c in CONFIGURE)
    assert "can0 is down" in str(err.value) and expected in str(err.value)
    assert _sets(fake_ip) == []  # nothing tried
    # permitted by capabilities but refused by the kernel: the same commands
    monkeypatch.setattr(canlink, "may_configure", lambda: True)
    monkeypatch.setenv("FAKE_IP_EPERM", "1")
    with pytest.raises(canlink.CanLinkError, match="Operation not permitted") as err:
        canlink.ensure_up()
    assert expected in str(err.value)
    # no such interface
    (fake_ip / "state").unlink()
    with pytest.raises(canlink.CanLinkError, match=r"CAN interface can0 not found .*the simulated robot \('nocan'\)"):
        canlink.ensure_up()


@pytest.mark.parametrize("verb", ["start", "run"])
def test_no_can_interface_names_the_verb_that_was_run(tmp_path: Path, fake_ip: Path, clean_shm: None,
                                                      verb: str) -> None:
    """Issue 28: `mds-ach run` without a CAN interface suggested 'mds-ach start nocan'."""
    env = _real_start_env(tmp_path, fake_ip)  # no link at all: `ip link show` fails
    proc = mds_ach(verb, "--timeout", "30", env=env, timeout=120)
    assert proc.returncode == 1
    assert "CAN interface can0 not found" in proc.stderr and f"'mds-ach {verb} nocan'" in proc.stderr, proc.stderr
    other = "run" if verb == "start" else "start"
    assert f"mds-ach {other} nocan" not in proc.stderr


def _real_start_env(tmp_path: Path, fake_ip: Path) -> dict[str, str]:
    """No CAN settings at all: no CAN_* variables, a HOME without ~/.canrc, run where no can.ini is."""
    env = {k: v for k, v in system_env(tmp_path / "rt").items() if not k.startswith("CAN_")}
    return env | {"HOME": str(tmp_path), "PATH": os.environ["PATH"], "FAKE_IP_DIR": str(fake_ip)}


def test_start_without_can_settings_brings_can0_up(tmp_path: Path, fake_ip: Path, clean_shm: None) -> None:
    """`mds-ach start` (real robot) configures can0 at 1 Mbit/s and starts the daemon on SocketCAN can0 (which
    then fails here: the kernel has no can0; before, start refused with 'no CAN interface configured')."""
    _link(fake_ip, up=False, bitrate=0)
    env = _real_start_env(tmp_path, fake_ip)
    proc = mds_ach("start", "--timeout", "60", env=env, timeout=240)
    assert _sets(fake_ip) == CONFIGURE, proc.stdout + proc.stderr
    assert "CAN link can0 configured: ip link set can0 type can bitrate 1000000" in proc.stdout
    assert "no CAN interface configured" not in proc.stderr
    daemon_log = (tmp_path / "rt" / "daemon.log").read_text()
    # the daemon opened SocketCAN can0 (and failed: no SocketCAN in this kernel), and says which interface
    assert "cannot open CAN interface socketcan can0" in daemon_log, daemon_log
    assert proc.returncode == 1
    assert not list((tmp_path / "rt").glob("*.pid"))


def test_start_not_permitted_prints_the_commands_and_starts_nothing(tmp_path: Path, fake_ip: Path,
                                                                   clean_shm: None) -> None:
    _link(fake_ip, up=False, bitrate=0)
    env = _real_start_env(tmp_path, fake_ip) | {"FAKE_IP_EPERM": "1"}
    proc = mds_ach("start", env=env, timeout=120)
    assert proc.returncode == 1
    assert " && ".join(f"sudo ip {c}" for c in CONFIGURE) in proc.stderr, proc.stderr
    assert "started" not in proc.stdout and not list((tmp_path / "rt").glob("*.pid"))
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)


def test_resetbus_restarts_the_link_of_the_start(tmp_path: Path, fake_ip: Path, clean_shm: None) -> None:
    _link(fake_ip, up=True, bitrate=1_000_000)
    env = _real_start_env(tmp_path, fake_ip)
    rt = tmp_path / "rt"
    rt.mkdir()
    canlink.save_link(rt, "can0", 1_000_000)  # what `mds-ach start` records for a SocketCAN start
    proc = mds_ach("resetbus", "--timeout", "0.5", env=env)
    assert _sets(fake_ip) == ["link set can0 down", *CONFIGURE], proc.stdout + proc.stderr
    assert "can0 restarted" in proc.stdout
    assert proc.returncode == 1 and "is the system started?" in proc.stderr  # then the daemon's part: none here
    # not permitted: the commands, nothing sent
    (fake_ip / "calls").unlink()
    proc = mds_ach("resetbus", env=env | {"FAKE_IP_EPERM": "1"})
    assert proc.returncode == 1 and shlex.join(["sudo", "ip", "link", "set", "can0", "down"]) in proc.stderr
    # a simulated start records no link: resetbus never runs ip
    canlink.clear_link(rt)
    (fake_ip / "calls").unlink()
    mds_ach("resetbus", "--timeout", "0.5", env=env)
    assert not (fake_ip / "calls").exists()


def test_fake_ip_json_is_what_iproute2_prints(fake_ip: Path) -> None:
    """The fake's answer has the fields of real `ip -json -details link show` output that canlink reads."""
    _link(fake_ip, up=True, bitrate=1_000_000)
    out = subprocess.run(["ip", "-json", "-details", "link", "show", "dev", "can0"], capture_output=True, text=True,
                         check=True).stdout
    info = json.loads(out)[0]
    assert info["linkinfo"]["info_data"]["bittiming"]["bitrate"] == 1_000_000 and "UP" in info["flags"]
