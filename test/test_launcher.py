"""``mds-ach start/stop/kill/killall/status/resetbus/changerobot/run``: the process manager, end to end."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import (
    NOBODY,
    REPO,
    VENV_BIN,
    in_netns,
    may_use_sched_fifo,
    realtime_threads,
    remove_mds_channels,
    run_as,
    wait_for,
)
from support.channels import newest
from support.system import mds_ach, running_system, system_env

import mds_ach as mds
from mds_ach import ach
from mds_ach.nodes.pipeline import HANDOFF_RT_PRIORITY
from mds_ach.paths import user_label
from mds_ach.robot import access as channel_access
from mds_ach.robot.config import load
from mds_ach.robot.msgs import get_name
from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS
from mds_ach.tools import repair
from mds_ach.tools.launcher import NODES, node_command

VERBS = ["start", "run", "stop", "kill", "killall", "status", "resetbus", "changerobot", "console", "read", "ros-shell",
         "ros"]


@pytest.mark.parametrize("verb", VERBS)
def test_every_verb_has_help(verb: str) -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), verb, "--help"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"usage: mds-ach {verb}")


def test_node_commands_are_this_packages_scripts() -> None:
    for name in NODES:
        cmd = node_command(name)
        assert Path(cmd[0]).name == f"mds-ach-{name}" and "mds_ach" in Path(cmd[0]).read_text(errors="replace"), cmd


def _pid_alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2] != "Z"


def _processes_of(runtime: Path) -> list[int]:
    """Live processes started with this runtime dir (other tests on the machine have their own)."""
    marker = f"MDS_ACH_RUNTIME_DIR={runtime}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            try:
                if marker in (entry / "environ").read_bytes().split(b"\0") and _pid_alive(int(entry.name)):
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


def test_a_stale_pid_file_never_kills_an_unrelated_process(tmp_path: Path) -> None:
    env = system_env(tmp_path)
    tmp_path.mkdir(exist_ok=True)
    bystander = subprocess.Popen(["sleep", "60"])
    try:
        for name in NODES:
            (tmp_path / f"{name}.pid").write_text(f"{bystander.pid}\n")
        proc = mds_ach("status", "--window", "0.1", env=env)
        assert proc.returncode == 3
        assert re.search(r"daemon\s+stopped\s+\(stale pid file\)", proc.stdout), proc.stdout
        assert mds_ach("stop", env=env).returncode == 0
        assert mds_ach("kill", env=env).returncode == 0
        subprocess.run([str(REPO / "scripts" / "stop_nodes.sh"), "1"], env=env, capture_output=True, timeout=60)
        assert bystander.poll() is None, "a process that is not an MDS node was signalled"
        assert not list(tmp_path.glob("*.pid")), "stale pid files are cleaned up"
    finally:
        bystander.kill()
        bystander.wait()


def test_changerobot_saves_the_variant_and_refuses_unknown_ones(tmp_path: Path) -> None:
    env = system_env(tmp_path)
    proc = mds_ach("changerobot", "octavia", env=env)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "config" / "robot").read_text().strip() == "octavia"
    status = mds_ach("status", "--window", "0.1", env=env)
    assert re.search(rf"robot\s+octavia \({re.escape(str(tmp_path / 'config' / 'robot'))}\)", status.stdout)
    env_override = dict(env, MDS_ACH_ROBOT="lucas")
    status = mds_ach("status", "--window", "0.1", env=env_override)
    assert re.search(r"robot\s+lucas \(\$MDS_ACH_ROBOT\)", status.stdout), status.stdout
    bad = mds_ach("changerobot", "marvin", env=env)
    assert bad.returncode == 2 and bad.stdout.strip() == "-- No Change to Robot --" and "'marvin'" in bad.stderr
    assert (tmp_path / "config" / "robot").read_text().strip() == "octavia"


def test_resetbus_without_a_system_fails_clearly(clean_shm: None, tmp_path: Path) -> None:
    proc = mds_ach("resetbus", env=system_env(tmp_path))
    assert proc.returncode == 1 and "is the system started?" in proc.stderr
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)


def _plant(names: tuple[str, ...] = mds.ALL_CHANNELS) -> None:
    """User nobody creates channels of the stack before it starts, world-writable (the adversarial run)."""
    def plant() -> int:
        for name in names:
            ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o666)
        return 0

    assert run_as(NOBODY, NOBODY, plant) == 0


def test_start_refuses_channels_another_user_planted(clean_shm: None, tmp_path: Path, other_user: int) -> None:
    _plant()
    proc = mds_ach("start", "nocan", env=system_env(tmp_path), timeout=120)
    assert proc.returncode == 1
    assert "refusing to start, channel problems:" in proc.stderr
    for name in mds.ALL_CHANNELS:
        assert f"{name}: /dev/shm/achshm-{name} is owned by {user_label(NOBODY)}" in proc.stderr
        assert f"mds-ach repair --recreate {name}" in proc.stderr
    assert "started" not in proc.stdout, "no node was started"
    assert not list(tmp_path.glob("*.pid")) and _processes_of(tmp_path) == []


@pytest.mark.slow
def test_start_tightens_channels_made_the_original_way(clean_shm: None, tmp_path: Path) -> None:
    """Issue #29 item 1: the original's `ach -1 mk NAME -m 10 -n 3000` (0644) and `chmod 777`, by the stack's own
    user: `start` gives them the stack's modes in place, one line each, and starts."""
    for name in mds.ALL_CHANNELS:
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o644)
    os.chmod(ach.shm_path(mds.MDS_CHAN_REF_NAME), 0o777)
    env = system_env(tmp_path)
    proc = mds_ach("start", "nocan", "--only", "daemon", env=env, timeout=200)
    try:
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert f"  channel {mds.MDS_CHAN_REF_NAME}: 10 x 3000 B, mode 0777 -> 0660" in proc.stdout
        assert f"  channel {mds.MDS_CHAN_DAEMON_INPUT_NAME}: 10 x 3000 B, mode 0644 -> 0640" in proc.stdout
        assert proc.stdout.count(" -> 06") == len(mds.ALL_CHANNELS)
        for name in mds.ALL_CHANNELS:
            assert os.stat(ach.shm_path(name)).st_mode & 0o777 == channel_access.channel_mode(name), name
    finally:
        mds_ach("stop", env=env, timeout=60)


def test_another_users_system_channels_are_explained_in_one_line(clean_shm: None, tmp_path: Path,
                                                                   other_user: int) -> None:
    """Issue 28 item 2: after another user's system (`sudo make run`, then `make run` as a normal user: the same
    /dev/shm) every channel was listed with a fix that cannot work; now one line names both users and the command."""
    from mds_ach.robot.channels import make_channels

    def their_system() -> int:
        return 0 if all(r.ok for r in make_channels()) else 1

    assert run_as(NOBODY, NOBODY, their_system) == 0
    proc = mds_ach("start", "nocan", env=system_env(tmp_path), timeout=120)
    assert proc.returncode == 1
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert f"belong to {user_label(NOBODY)}, not to you ({user_label(0)})" in lines[0], lines[0]
    assert "killall' (it also stops that user's nodes), then start again" in lines[0], lines[0]
    assert "repair --recreate" not in lines[0]
    assert "started" not in proc.stdout


def test_nodes_refuse_a_planted_channel(clean_shm: None, tmp_path: Path, other_user: int) -> None:
    """Started by hand (not through 'mds-ach start', which checks first), a node still refuses the file."""
    _plant((mds.MDS_CHAN_DAEMON_INPUT_NAME,))
    env = system_env(tmp_path)
    daemon = subprocess.run([str(VENV_BIN / "mds-ach-daemon"), "--nocan", "--no-ros", "--duration", "30"], env=env,
                            capture_output=True, text=True, timeout=120)
    assert daemon.returncode == 2, daemon.stderr
    assert f"refusing channel 'mds-ref-gated': /dev/shm/achshm-mds-ref-gated is owned by {user_label(NOBODY)}" in \
        daemon.stderr
    assert "mds-ach repair --recreate mds-ref-gated" in daemon.stderr
    mux = subprocess.run([str(VENV_BIN / "mds-ach-mux")], env=env, capture_output=True, text=True, timeout=120)
    assert mux.returncode == 1, mux.stdout + mux.stderr  # the mux reads mds-ref-gated for its start reference
    assert "refusing channel 'mds-ref-gated'" in mux.stdout + mux.stderr
    assert os.stat(ach.shm_path(mds.MDS_CHAN_DAEMON_INPUT_NAME)).st_uid == NOBODY, "the file was left alone"


def _damage(how: str) -> None:
    path = Path(ach.shm_path(mds.MDS_CHAN_STATE_NAME))
    if how == "corrupt":  # a writer died inside a put: the dirty flag stays set
        m = repair._Mapped(mds.MDS_CHAN_STATE_NAME)
        m.dirty = 1
        m.close()
    elif how == "truncated":
        os.truncate(path, 20000)
    elif how == "not an Ach file":
        path.write_bytes(b"\0" * 100)
    elif how == "wrong size":
        path.unlink()
        ach.create(mds.MDS_CHAN_STATE_NAME, 16, 512)


@pytest.mark.parametrize(("how", "expected"), [
    ("corrupt", "mds-state: corrupt: a writer died inside a put .*; repair it in place: mds-ach repair mds-state$"),
    ("truncated", "mds-state: broken: .*truncated.*; mds-ach repair mds-state re-creates it; the stack's nodes "
                  "re-open it by themselves, restart any other process that uses it$"),
    ("not an Ach file", "mds-state: broken: ACH_BAD_SHM_FILE.*; mds-ach repair mds-state re-creates it"),
    ("wrong size", r"mds-state: exists as 16 x 512 B, expected 10 x 3000 B; remove it \(mds-ach rm mds-state\)"),
], ids=["corrupt", "truncated", "not-ach", "wrong-size"])
def test_status_reports_a_damaged_state_channel_with_the_fix(clean_shm: None, tmp_path: Path, how: str,
                                                             expected: str) -> None:
    env = system_env(tmp_path)
    assert mds_ach("make", "-q", env=env).returncode == 0
    _damage(how)
    proc = mds_ach("status", "--window", "0.2", env=env)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert re.search(r"^channel\s+" + expected, proc.stdout, re.M), proc.stdout
    assert re.search(r"^state\s+unreadable", proc.stdout, re.M), proc.stdout
    assert re.search(r"^\s+daemon\s+stopped$", proc.stdout, re.M), "the rest of the report is still there"


def test_status_after_a_stop_says_not_running_and_shows_the_last_frames_as_history(clean_shm: None,
                                                                                    tmp_path: Path) -> None:
    """Issue 28 item 4: the daemon's last rate and a 'collision BLOCKED' left in the channels are not the robot now."""
    from mds_ach.robot.channels import StructChannel

    env = system_env(tmp_path)
    assert mds_ach("make", "-q", env=env).returncode == 0
    status = MDS_DAEMON_STATUS()
    status.time = time.monotonic() - 42.0
    collide = mds.MDS_COLLIDE()
    collide.isCollide, collide.joint[mds.COLLIDE_L_HAND].isCollide = 1, 1
    with StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS, create=False) as chan:
        chan.put(status)
    with StructChannel(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE, create=False) as chan:
        chan.put(collide)
    proc = mds_ach("status", "--window", "0.1", env=env)
    assert proc.returncode == 3, proc.stdout + proc.stderr
    out = proc.stdout
    assert re.search(r"^MDS-Ach is not running", out, re.M), out
    history = re.search(r"^last seen\s+\(history, not live: .*last daemon frame (\d+) s ago\)$", out, re.M)
    assert history and 41 <= int(history.group(1)) <= 60, out
    assert re.search(r"^  collision\s+BLOCKED", out, re.M), "the old verdict is shown indented, under the history"
    assert not re.search(r"^(daemon|collision|held|limits) ", out, re.M), "nothing of it reads as a live line"
    assert "STALE" not in out


def test_every_exit_code_is_in_the_top_level_help() -> None:
    out = mds_ach("--help").stdout
    for code, what in (("0", "ok"), ("1", "failure"), ("2", "usage error"), ("3", "status: a node is not running"),
                       ("130", "start: interrupted"), ("127", "not found")):
        assert re.search(rf"^\s+{code}\s+{re.escape(what)}", out, re.M) or f"{code} it" in out, (code, out)


def test_status_of_sound_channels_and_a_foreign_one(clean_shm: None, tmp_path: Path, other_user: int) -> None:
    env = system_env(tmp_path)
    assert mds_ach("make", "-q", env=env).returncode == 0
    proc = mds_ach("status", "--window", "0.1", env=env)
    sound = rf"^channels\s+ok \({len(mds.ALL_CHANNELS)}\)$"
    assert proc.returncode == 3 and re.search(sound, proc.stdout, re.M), proc.stdout
    ach.unlink(mds.MDS_CHAN_BOARD_CMD_NAME)
    _plant((mds.MDS_CHAN_BOARD_CMD_NAME,))
    proc = mds_ach("status", "--window", "0.1", env=env)
    assert proc.returncode == 1
    owner = re.escape(user_label(NOBODY))
    assert re.search(rf"^channel\s+mds-cmd: unsafe: /dev/shm/achshm-mds-cmd is owned by {owner}, .*"
                     r"mds-ach repair --recreate mds-cmd", proc.stdout, re.M), proc.stdout


@pytest.mark.slow
def test_a_node_that_fails_is_named_with_its_log_and_nothing_is_left_running(clean_shm: None,
                                                                             tmp_path: Path) -> None:
    env = dict(system_env(tmp_path), MDS_ACH_ROBOT="nosuchrobot")  # the nodes refuse the joint table
    proc = mds_ach("start", "nocan", "--timeout", "120", env=env, timeout=300)
    assert proc.returncode == 1
    failed = re.search(r"(\w+) exited with status \d+ during start-up; last lines of (\S+):", proc.stderr)
    assert failed and failed.group(1) in NODES, proc.stderr
    assert failed.group(2) == str(tmp_path / f"{failed.group(1)}.log")
    assert "unknown robot 'nosuchrobot'" in proc.stderr, "the node's log tail explains why"
    assert not list(tmp_path.glob("*.pid")), "the nodes started before the failure are stopped again"
    assert _processes_of(tmp_path) == [], "the nodes started before the failure are stopped again"


@pytest.mark.slow
def test_a_restarted_node_keeps_the_previous_runs_log(clean_shm: None, tmp_path: Path) -> None:
    """The documented recovery (`start --only NODE`) must not erase what a crashed node wrote (issue #25, item 9):
    each start appends a marker line (time, pid) and the new run's lines; the start's log tail shows the new run
    only."""
    from mds_ach.nodes.pipeline import make_ref
    from mds_ach.procs import START_MARKER
    from mds_ach.robot.channels import StructChannel
    from mds_ach.tools import launcher

    env = system_env(tmp_path)
    assert mds_ach("make", "-q", env=env).returncode == 0
    with StructChannel(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_REF) as ch:  # the mux starts from this reference
        ch.put(make_ref([0.0] * mds.MDS_JOINT_COUNT, [0] * mds.MDS_JOINT_COUNT))
    log = tmp_path / "mux.log"
    first = launcher.start_node("mux", rt=tmp_path, env=dict(env))
    try:
        wait_for(lambda: "started from" in log.read_text(errors="replace"), 60, what="the first mux's start line")
    finally:
        first.kill()  # a crash: SIGKILL
        first.wait()
    before = log.read_text(errors="replace")
    proc = mds_ach("start", "--only", "mux", "--timeout", "60", env=env, timeout=120)
    try:
        assert proc.returncode == 0, proc.stdout + proc.stderr
        text = log.read_text(errors="replace")
        assert text.startswith(before), "the first run's lines are still there, first"
        markers = [line for line in text.splitlines() if line.startswith(START_MARKER)]
        assert len(markers) == 2 and f" pid {first.pid}: " in markers[0], markers
        second = int((tmp_path / "mux.pid").read_text())
        assert f" pid {second}: " in markers[1] and re.search(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", markers[1])
        assert "started from" in text.split(markers[1], 1)[1], "the second run's lines follow its marker"
        assert launcher.log_tail("mux", rt=tmp_path).count("started from") == 1  # the new run only
    finally:
        assert mds_ach("stop", env=env, timeout=60).returncode == 0


# --------------------------------------------------------------------------------------------- a running system


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    with running_system(tmp_path_factory.mktemp("launcher"), robot="isaac") as env:
        yield env


def _pids(env: dict[str, str]) -> dict[str, int]:
    rt = Path(env["MDS_ACH_RUNTIME_DIR"])
    return {n: int((rt / f"{n}.pid").read_text()) for n in NODES if (rt / f"{n}.pid").exists()}


@pytest.mark.slow
def test_start_runs_each_node_as_its_own_process(system: dict[str, str]) -> None:
    rt = Path(system["MDS_ACH_RUNTIME_DIR"])
    pids = _pids(system)
    assert set(pids) == set(NODES)
    assert len(set(pids.values())) == len(NODES)
    for name, pid in pids.items():
        assert _pid_alive(pid), f"{name} is not running"
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        assert any(Path(a.decode()).name == f"mds-ach-{name}" for a in argv[:3]), argv
        assert os.getsid(pid) == pid, f"{name} runs in its own session"
        assert (rt / f"{name}.log").exists()
        environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        assert b"MDS_ACH_ROBOT=isaac" in environ, "the saved robot choice reaches the nodes"


@pytest.mark.slow
def test_the_daemon_loaded_the_chosen_robot(system: dict[str, str]) -> None:
    param = newest(mds.MDS_CHAN_PARAM_NAME, mds.MDS_JOINT_PARAM)
    assert param is not None
    isaac, default = load("isaac")[mds.LEP], load("default")[mds.LEP]
    assert isaac.rom != default.rom
    assert param.joint[mds.LEP].rom == pytest.approx(isaac.rom)
    assert get_name(param.joint[mds.LEP].nameshort) == "LEP"


@pytest.mark.slow
def test_status_reports_nodes_rate_bus_load_and_collisions(system: dict[str, str]) -> None:
    proc = mds_ach("status", env=system)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for name in NODES:
        assert re.search(rf"^\s+{name}\s+running\s+pid \d+$", proc.stdout, re.M), proc.stdout
    rate = float(re.search(r"^state\s+([\d.]+) frames/s", proc.stdout, re.M).group(1))
    assert 7.0 < rate < 13.0, f"the daemon runs at 10 Hz, measured {rate}"
    assert re.search(r"^daemon\s+[\d.]+/10 Hz, .*bus active \d+% \(nocan\)", proc.stdout, re.M), proc.stdout
    assert re.search(r"^collision\s+clear$", proc.stdout, re.M), proc.stdout
    assert "robot      isaac" in proc.stdout
    # issue #17: where the limits come from (the daemon's, for its robot) and whether the gate refuses anything
    assert re.search(r"^limits\s+URDF & joint table, robot isaac from mds-limits \(the daemon's\); nothing refused$",
                     proc.stdout, re.M), proc.stdout


@pytest.mark.slow
def test_only_the_daemon_loop_and_the_hand_off_threads_run_real_time(system: dict[str, str]) -> None:
    """`mds-ach start` asks nothing of the scheduler itself: the daemon puts its loop thread under SCHED_FIFO 50
    and the reference pipeline its hand-off threads under SCHED_FIFO 40 (``pipeline.HANDOFF_RT_PRIORITY``: the mux's
    readers and loop, the filter's loop, the gate's loop and readers), where the user may; every other thread of
    every node stays at normal priority; `status` says which for the daemon. The bridge's executor thread (its
    main thread, named as the process) and its DDS reception threads (``dds.shm.<port>``, ``dds.udp.<port>``: the
    ports vary, so they are compared without them) hand a ROS command over at the same priority
    (``rosnode.run_node``)."""
    pids = _pids(system)
    threads = {name: sorted({(re.sub(r"^(dds\.\w+)\.\d+$", r"\1.N", t), p) for t, p in realtime_threads(pid)})
               for name, pid in pids.items()}
    status = mds_ach("status", env=system).stdout
    if may_use_sched_fifo():
        bridge_main = Path(f"/proc/{pids['bridge']}/comm").read_text().strip()
        handoff = {"mux": ["mux", "mux-hold", "mux-in default", "mux-in direct", "mux-in ik", "mux-in ros"],
                   "filter": ["filter"], "collision": ["gate", "wake mds-ref-sm", "wake mds-state"],
                   "bridge": sorted([bridge_main, "dds.shm.N", "dds.udp.N"])}
        assert threads == {**{n: [] for n in NODES}, "daemon": [("mds-daemon-loop", 50)],
                           **{n: [(t, HANDOFF_RT_PRIORITY) for t in names] for n, names in handoff.items()}}, threads
        assert re.search(r"^daemon .*, loop real-time \(SCHED_FIFO 50, memory locked\), bus", status, re.M), status
    else:
        assert threads == {n: [] for n in NODES}, threads
        assert re.search(r"^daemon .*, loop not real-time, bus", status, re.M), status


@pytest.mark.slow
def test_start_refuses_a_second_system(system: dict[str, str]) -> None:
    before = _pids(system)
    proc = mds_ach("start", "nocan", env=system)
    assert proc.returncode == 1 and "already running" in proc.stderr
    assert _pids(system) == before


@pytest.mark.slow
def test_resetbus_reaches_the_daemon(system: dict[str, str]) -> None:
    before = newest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS).bus_resets
    proc = mds_ach("resetbus", env=system)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    seq = int(re.search(r"seq (\d+)", proc.stdout).group(1))
    assert "bus reset by the daemon: state active" in proc.stdout
    status = newest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)
    assert status.cmd_seq == seq and status.bus_resets == before + 1
    assert mds_ach("resetbus", env=system).returncode == 0, "a second reset gets the next sequence number"


@pytest.mark.slow
def test_read_once_against_the_running_system(system: dict[str, str]) -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-read"), "--once"], env=system, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = re.findall(r"^(\w+)\s+\w+\s+1\s+0x00[0-9a-f]{2}\s+(\S+)\s+(\S+)\s+(\S+)$", proc.stdout, re.M)
    assert {r[0] for r in rows} >= {"LSP", "LEP", "RSP", "WST", "NKY"}
    assert all(r[3] == "yes" for r in rows), "every enabled simulated node answers"
    assert all(abs(float(r[1]) - float(r[2])) < 0.01 for r in rows), "at rest the joints sit at their reference"


@pytest.mark.slow
def test_an_operator_cannot_open_the_daemon_input_of_a_running_system(system: dict[str, str], other_user: int) -> None:
    group = os.stat(ach.shm_path(mds.MDS_CHAN_REF_FILTER_NAME)).st_gid

    def operator() -> int:  # in the channels' group: may command through the pipeline, not around it
        ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False).close()
        try:
            ach.Channel(mds.MDS_CHAN_DAEMON_INPUT_NAME, create=False)
        except ach.AchException as exc:
            return 0 if exc.status == ach.ACH_EACCES else 3
        return 4

    assert run_as(NOBODY, NOBODY, operator, groups=(group,)) == 0
    assert os.stat(ach.shm_path(mds.MDS_CHAN_DAEMON_INPUT_NAME)).st_mode & 0o777 == 0o640


@pytest.mark.slow
def test_a_killed_node_is_seen_and_restarted_alone(system: dict[str, str]) -> None:
    pids = _pids(system)
    os.kill(pids["filter"], signal.SIGKILL)
    wait_for(lambda: not _pid_alive(pids["filter"]), timeout=10, what="filter gone")
    proc = mds_ach("status", "--window", "0.3", env=system)
    assert proc.returncode == 3 and re.search(r"^\s+filter\s+stopped", proc.stdout, re.M), proc.stdout
    proc = mds_ach("start", "--only", "filter", "--timeout", "120", env=system, timeout=200)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert re.search(r"daemon\s+already running", proc.stdout) is None, "--only starts just that node"
    new = _pids(system)
    assert new["filter"] != pids["filter"] and _pid_alive(new["filter"])
    assert {n: p for n, p in new.items() if n != "filter"} == {n: p for n, p in pids.items() if n != "filter"}
    assert mds_ach("status", "--window", "0.3", env=system).returncode == 0


@pytest.mark.slow
def test_stop_ends_every_node_and_keeps_the_channels(system: dict[str, str]) -> None:
    pids = _pids(system)
    proc = mds_ach("stop", env=system, timeout=120)
    assert proc.returncode == 0, proc.stderr
    order = re.findall(r"^\s+(\w+)\s+stopped", proc.stdout, re.M)
    assert set(order) == set(NODES) and order[-1] == "daemon", "the daemon stops last"
    assert not any(_pid_alive(p) for p in pids.values())
    assert not list(Path(system["MDS_ACH_RUNTIME_DIR"]).glob("*.pid"))
    assert all(ach.exists(n) for n in mds.ALL_CHANNELS)
    assert mds_ach("stop", env=system).stdout.strip() == "nothing was running"
    proc = mds_ach("killall", env=system)
    assert proc.returncode == 0
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)


# --------------------------------------------------------------------------------------------- run (make run)


def _start_run(env: dict[str, str]) -> tuple[subprocess.Popen[str], str]:
    """`mds-ach run --nocan` in the foreground, read until it says everything is up; returns it and its output."""
    proc = subprocess.Popen([str(VENV_BIN / "mds-ach"), "run", "--nocan", "--timeout", "150"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 240
        while not any("Press Ctrl-C to stop everything." in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(lines)
            lines.append(proc.stdout.readline())
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    return proc, "".join(lines)


@pytest.mark.slow
def test_run_in_the_foreground_stops_everything_on_ctrl_c(clean_shm: None, tmp_path: Path) -> None:
    assert in_netns()
    env = system_env(tmp_path)
    proc, text = _start_run(env)
    try:
        assert "mds-ach console" in text and "mds-ach read" in text, "it says what to do next"
        pids = _pids(env)
        assert set(pids) == set(NODES)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, text + rest
    assert "stopping" in rest
    assert not any(_pid_alive(p) for p in pids.values()), "Ctrl-C stops every node"
    assert not list(tmp_path.glob("*.pid"))
    remove_mds_channels()


def _start_viewer(env: dict[str, str]) -> int:
    """`mds-ach sim --port 0` with this runtime dir; returns the viewer's pid (its start said it ends with the
    system, its URL file is the user's only)."""
    from mds_ach.tools import viewer

    proc = mds_ach("sim", "--port", "0", env=env, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "stops with the system" in proc.stdout and "Ctrl-C of `mds-ach run`" in proc.stdout, proc.stdout
    rt = Path(env["MDS_ACH_RUNTIME_DIR"])
    assert (rt / viewer.SIM_URL).stat().st_mode & 0o777 == 0o600, "the URL file carries the token"
    pid = int((rt / viewer.SIM_PID).read_text())
    assert _pid_alive(pid)
    return pid


@pytest.mark.slow
def test_run_ctrl_c_ends_the_viewer_too(clean_shm: None, tmp_path: Path) -> None:
    """Issue 28: the viewer's page can move the robot; it must not outlive `run` (whose help says nothing is left)."""
    env = system_env(tmp_path)
    proc, text = _start_run(env)
    try:
        viewer_pid = _start_viewer(env)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, text + rest
    assert f"viewer     stopped (pid {viewer_pid})" in rest
    assert not _pid_alive(viewer_pid), "Ctrl-C of run ends the viewer"
    assert not list(tmp_path.glob("*.pid")) and not (tmp_path / "sim.url").exists()
    remove_mds_channels()


@pytest.mark.slow
def test_stop_kill_and_killall_end_the_viewer_too(clean_shm: None, tmp_path: Path) -> None:
    env = system_env(tmp_path)
    for verb in ("stop", "kill", "killall"):
        viewer_pid = _start_viewer(env)
        proc = mds_ach(verb, env=env, timeout=60)
        assert proc.returncode == 0, proc.stderr
        wait_for(lambda pid=viewer_pid: not _pid_alive(pid), 10, what=f"the viewer gone after {verb}")  # type: ignore[misc]
        assert not (tmp_path / "sim.url").exists()
    remove_mds_channels()


@pytest.mark.slow
def test_run_reports_a_node_that_dies_and_stops_the_rest(clean_shm: None, tmp_path: Path) -> None:
    env = system_env(tmp_path)
    proc, _ = _start_run(env)
    try:
        pids = _pids(env)
        os.kill(pids["filter"], signal.SIGKILL)
        rest, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 1
    assert "filter was killed by SIGKILL" in rest and "stopping everything" in rest
    assert not any(_pid_alive(p) for p in pids.values())
    remove_mds_channels()


# --------------------------------------------------------------------------------------------- no orphans (#17 item 6)


def _nodes_gone(env: dict[str, str], pids: dict[str, int], what: str) -> None:
    """Every node of ``pids`` exits (SIGTERM, the daemon last) and leaves no pid file; the daemon's log shows no
    crash (it finished its cycle and closed the bus)."""
    rt = Path(env["MDS_ACH_RUNTIME_DIR"])
    assert set(pids) == set(NODES), pids
    wait_for(lambda: not any(_pid_alive(p) for p in pids.values()), 60, what=f"every node to stop ({what})")
    wait_for(lambda: not list(rt.glob("*.pid")), 10, what=f"the pid files to go ({what})")
    assert "Traceback" not in (rt / "daemon.log").read_text(errors="replace"), f"{what}: the daemon crashed"


def _run_again_starts(env: dict[str, str]) -> None:
    """The next `mds-ach run` starts (nothing left running blocks it), and stops on Ctrl-C."""
    proc, _ = _start_run(env)
    proc.send_signal(signal.SIGINT)
    rest, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, rest


@pytest.mark.slow
def test_run_stops_everything_when_its_terminal_is_closed(clean_shm: None, tmp_path: Path) -> None:
    """`make run` in a terminal, then the terminal window is closed: the kernel hangs the terminal up (SIGHUP, and
    every later write to it fails with EIO). Before #17 the launcher died on its "stopping" line and left all six
    nodes running."""
    from support.pty_session import PtySession

    assert in_netns()
    env = system_env(tmp_path)
    session = PtySession([str(VENV_BIN / "mds-ach"), "run", "--nocan", "--timeout", "150"], env=env)
    try:
        session.expect("Press Ctrl-C to stop everything.", timeout=240)
        pids = _pids(env)
        os.close(session.fd)  # the terminal closes: hang-up
        wait_for(lambda: session.poll() is not None, 120, what="the launcher to exit after the hang-up")
        _nodes_gone(env, pids, "terminal closed")
    finally:
        session.close()
    _run_again_starts(env)
    remove_mds_channels()


@pytest.mark.slow
def test_run_piped_into_a_reader_that_dies_still_stops_everything(clean_shm: None, tmp_path: Path) -> None:
    """`make run | tee log` and Ctrl-C: tee dies first, so every print of the launcher fails (EPIPE); it must still
    stop every node."""
    assert in_netns()
    env = system_env(tmp_path)
    proc, _ = _start_run(env)  # stdout is a pipe to this test: the test is the `tee`
    try:
        pids = _pids(env)
        proc.stdout.close()  # the reader dies
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=120)
        _nodes_gone(env, pids, "reader gone, then Ctrl-C")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    _run_again_starts(env)
    remove_mds_channels()


@pytest.mark.slow
def test_run_stops_everything_when_its_parent_dies(clean_shm: None, tmp_path: Path) -> None:
    """The launcher's parent (``make``) is killed outright: the launcher notices it was re-parented and stops
    every node; the next `mds-ach run` starts."""
    assert in_netns()
    env = system_env(tmp_path)
    out = tmp_path / "run.out"
    parent_code = "import subprocess, sys; sys.exit(subprocess.call(sys.argv[1:]))"
    with open(out, "wb") as f:
        parent = subprocess.Popen([sys.executable, "-c", parent_code, str(VENV_BIN / "mds-ach"), "run", "--nocan",
                                   "--timeout", "150"], env=env, stdout=f, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: "Press Ctrl-C to stop everything." in out.read_text(errors="replace")
                 or parent.poll() is not None, 240, interval=0.2, what="the system to start")
        assert parent.poll() is None, out.read_text(errors="replace")
        launcher = int(Path(f"/proc/{parent.pid}/task/{parent.pid}/children").read_text().split()[0])
        pids = _pids(env)
        parent.kill()
        parent.wait()
        wait_for(lambda: not _pid_alive(launcher), 120, what="the launcher to exit after its parent died")
        _nodes_gone(env, pids, "parent killed")
        assert "its parent" in out.read_text(errors="replace")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    _run_again_starts(env)
    remove_mds_channels()
