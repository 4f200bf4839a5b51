"""``mds-ach make | rm | dump`` and the channel-set helpers: files, modes, decoding, exit codes, messages."""

from __future__ import annotations

import grp
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import NOBODY, VENV_BIN, other_ids_missing, run_as

import mds_ach as mds
from mds_ach import ach
from mds_ach.paths import user_label
from mds_ach.robot import access as channel_access
from mds_ach.robot.channels import make_channels, remove_channels
from mds_ach.robot.msgs import MDS_CMD, MDS_COLLIDE, MDS_IK, MDS_JOINT_PARAM, MDS_REF, MDS_STATE, set_name
from mds_ach.tools import cli


@pytest.fixture
def run(clean_shm: None, capsys: pytest.CaptureFixture[str]) -> Iterator:
    """Run ``mds-ach ARGS`` in-process; returns (exit code, stdout, stderr)."""
    old_term = signal.getsignal(signal.SIGTERM)

    def invoke(*args: str) -> tuple[int, str, str]:
        try:
            rc = cli.main(list(args))
        except SystemExit as exc:  # argparse: --help (0) and usage errors (2)
            rc = int(exc.code or 0)
        out, err = capsys.readouterr()
        return rc, out, err

    yield invoke
    signal.signal(signal.SIGTERM, old_term)


def mode_of(name: str) -> int:
    return os.stat(ach.shm_path(name)).st_mode & 0o777


# --- make -------------------------------------------------------------------------------------------


def test_make_creates_every_channel(run) -> None:
    rc, out, err = run("make")
    assert (rc, err) == (0, "")
    for name in mds.ALL_CHANNELS:
        assert mode_of(name) == (0o640 if name in channel_access.STACK_ONLY else 0o660)
        with ach.Channel(name, create=False) as ch:
            assert (ch.frame_count, ch.frame_size) == (10, 3000)
        assert f"{name} " in out
    assert out.count("created") == len(mds.ALL_CHANNELS)


def test_make_keeps_existing_channels(run) -> None:
    assert run("make", "-q")[0] == 0
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as ch:
        ch.put(MDS_STATE())
    rc, out, err = run("make")
    assert (rc, err) == (0, "")
    assert out.count("exists") == len(mds.ALL_CHANNELS)
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as ch:
        assert ch.last_seq == 1  # not clobbered


def test_make_reports_wrong_geometry(run) -> None:
    ach.create(mds.MDS_CHAN_REF_NAME, 16, 512, mode=0o640)
    rc, out, err = run("make")
    assert rc == 1
    assert "mds-ref" in err and "16 x 512" in err and "mds-ach rm mds-ref" in err
    assert all(ach.exists(n) for n in mds.ALL_CHANNELS)  # the others were still made
    with ach.Channel(mds.MDS_CHAN_REF_NAME, create=False) as ch:
        assert ch.frame_count == 16  # and the odd one left alone


def test_make_reports_non_ach_file(run) -> None:
    Path(ach.shm_path(mds.MDS_CHAN_IK_NAME)).write_bytes(b"not a channel")
    os.chmod(ach.shm_path(mds.MDS_CHAN_IK_NAME), 0o660)  # ours, not too open: only its content is wrong
    rc, _, err = run("make")
    assert rc == 1
    assert "mds-ik" in err and "ACH_BAD_SHM_FILE" in err
    assert Path(ach.shm_path(mds.MDS_CHAN_IK_NAME)).read_bytes() == b"not a channel"


def other_group() -> grp.struct_group:
    return next(g for g in grp.getgrall() if g.gr_gid != os.getgid())


def test_make_group_and_mode(run) -> None:
    group = other_group()
    reason = other_ids_missing(uids=(), gids=(group.gr_gid,))
    if reason:
        pytest.skip(reason)
    rc, out, _ = run("make", "--group", group.gr_name, "--mode", "640")
    assert rc == 0
    for name in mds.ALL_CHANNELS:
        st = os.stat(ach.shm_path(name))
        assert (st.st_gid, st.st_mode & 0o777) == (group.gr_gid, 0o640)
    assert f"group {group.gr_name}" in out


def test_make_refuses_world_writable_and_unknown_group(run) -> None:
    rc, _, err = run("make", "--mode", "666")
    assert rc == 1 and "world-writable" in err
    rc, _, err = run("make", "--group", "no-such-group-here")
    assert rc == 1 and "no such group" in err
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)
    assert run("make", "--mode", "8")[0] == 2  # not octal: usage error


def plant_channels(mode: int = 0o666, names: tuple[str, ...] = mds.ALL_CHANNELS) -> None:
    """What the adversarial run did: user nobody creates the stack's channels first, world-writable."""
    def plant() -> int:
        for name in names:
            ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=mode)
        return 0

    assert run_as(NOBODY, NOBODY, plant) == 0
    assert all(os.stat(ach.shm_path(n)).st_uid == NOBODY for n in names)


def test_make_and_repair_refuse_channels_another_user_planted(run, other_user: int) -> None:
    plant_channels()
    rc, out, err = run("make")
    assert rc == 1
    for name in mds.ALL_CHANNELS:
        assert f"channel '{name}': /dev/shm/achshm-{name} is owned by {user_label(NOBODY)}, not by the stack's " \
               f"user ({user_label(0)}) or root" in err
        assert f"mds-ach repair --recreate {name} (as root if another user owns the file" in err
    rc, out, err = run("repair", "--check")
    assert rc == 1 and "ok " not in out
    assert all(f"{name:<20} unsafe" in err for name in mds.ALL_CHANNELS), err
    rc, out, err = run("repair", "--recreate", *mds.ALL_CHANNELS)
    assert rc == 0, err
    for name in mds.ALL_CHANNELS:
        st = os.stat(ach.shm_path(name))
        assert (st.st_uid, st.st_mode & 0o777) == (0, channel_access.channel_mode(name)), name
    assert run("make")[0] == 0 and run("repair", "--check")[0] == 0


def test_make_tightens_channels_the_stacks_user_made_too_open(run) -> None:
    """Issue #29 item 1: the original made its channels with `ach -1 mk NAME -m 10 -n 3000` (mode 0644 under the
    usual umask) and then `chmod 777 /dev/shm/achshm-mds*`. Made by the stack's own user and open in no process,
    they are tightened in place (frames kept), one line each; a daemon input left 0660 gets 0640."""
    ach.create(mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o660)
    ach.create(mds.MDS_CHAN_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o644)
    ach.create(mds.MDS_CHAN_REF_FILTER_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o644)
    os.chmod(ach.shm_path(mds.MDS_CHAN_REF_FILTER_NAME), 0o777)
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as ch:
        ch.put(MDS_STATE())
    inode = os.stat(ach.shm_path(mds.MDS_CHAN_STATE_NAME)).st_ino
    rc, out, err = run("make")
    assert (rc, err) == (0, "")
    assert (mode_of(mds.MDS_CHAN_DAEMON_INPUT_NAME), mode_of(mds.MDS_CHAN_STATE_NAME),
            mode_of(mds.MDS_CHAN_REF_FILTER_NAME)) == (0o640, 0o660, 0o660)
    assert f"{mds.MDS_CHAN_STATE_NAME:<20} tightened 10 x 3000 B, mode 0644 -> 0660" in out
    assert f"{mds.MDS_CHAN_REF_FILTER_NAME:<20} tightened 10 x 3000 B, mode 0777 -> 0660" in out
    assert f"{mds.MDS_CHAN_DAEMON_INPUT_NAME:<20} tightened 10 x 3000 B, mode 0660 -> 0640" in out
    assert out.count("tightened") == 3
    assert os.stat(ach.shm_path(mds.MDS_CHAN_STATE_NAME)).st_ino == inode  # in place
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as ch:
        assert ch.last_seq == 1  # frames kept
    rc, out, _ = run("make")
    assert rc == 0 and "tightened" not in out  # once


def test_make_refuses_a_too_open_channel_that_another_process_has_open(run) -> None:
    """A process that opened the channel while it was world-writable keeps write access after a chmod: the
    stack then refuses as before (nothing changed) and says why."""
    ach.create(mds.MDS_CHAN_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o666)
    code = (f"import sys; from mds_ach import ach; c = ach.Channel({mds.MDS_CHAN_STATE_NAME!r}, create=False); "
            "print('open', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "open\n"
        rc, _, err = run("make")
        assert rc == 1
        assert f"{ach.shm_path(mds.MDS_CHAN_STATE_NAME)} has mode 0666 and is open in another process" in err
        assert mode_of(mds.MDS_CHAN_STATE_NAME) == 0o666
    finally:
        holder.communicate("")
    rc, out, _ = run("make")
    assert rc == 0 and "mode 0666 -> 0660" in out


def test_make_still_refuses_a_channel_of_another_group(run) -> None:
    """Only the mode of the stack's own files is adopted: a configured group must still match."""
    ach.create(mds.MDS_CHAN_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o660)
    rc, _, err = run("make", "--group", other_group().gr_name)
    assert rc == 1 and f"not to the configured group {other_group().gr_gid}" in err


def test_operators_can_write_controller_inputs_but_not_the_daemon_input(run, other_user: int) -> None:
    assert run("make", "-q")[0] == 0
    group = os.stat(ach.shm_path(mds.MDS_CHAN_REF_FILTER_NAME)).st_gid

    def operator() -> int:  # a member of the channels' group, not the stack's user
        for name in (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_IK_NAME, mds.MDS_CHAN_BOARD_CMD_NAME,
                     mds.MDS_CHAN_STATE_NAME):
            ach.Channel(name, create=False).close()
        try:
            ach.Channel(mds.MDS_CHAN_DAEMON_INPUT_NAME, create=False)
        except ach.AchException as exc:
            return 0 if exc.status == ach.ACH_EACCES else 3
        return 4  # opened (read-write) the daemon's input

    assert run_as(NOBODY, NOBODY, operator, groups=(group,)) == 0
    assert run_as(NOBODY, NOBODY, lambda: 0 if not os.access(ach.shm_path(mds.MDS_CHAN_STATE_NAME), os.W_OK) else 5) \
        == 0, "other users get nothing"


def test_make_channels_api(clean_shm: None) -> None:
    reports = make_channels(names=["test-a", "test-b"], mode=0o600)
    assert [(r.name, r.action, r.ok) for r in reports] == [("test-a", "created", True), ("test-b", "created", True)]
    assert mode_of("test-a") == 0o600
    reports = make_channels(names=["test-a"])
    assert (reports[0].action, reports[0].ok) == ("exists", True)
    with pytest.raises(ValueError, match="world-writable"):
        make_channels(names=["test-c"], mode=0o666)
    assert remove_channels(["test-a", "test-b", "test-c"]) == ["test-a", "test-b"]


# --- rm -----------------------------------------------------------------------------------------------


def test_rm_all_and_named(run) -> None:
    run("make", "-q")
    ach.create("test-keep", 1, 8)
    rc, out, err = run("rm", mds.MDS_CHAN_STATE_NAME)
    assert (rc, out.strip(), err) == (0, "removed mds-state", "")
    assert not ach.exists(mds.MDS_CHAN_STATE_NAME)
    rc, out, _ = run("rm")
    assert rc == 0
    assert out.count("removed") == len(mds.ALL_CHANNELS) - 1
    assert not any(ach.exists(n) for n in mds.ALL_CHANNELS)
    assert ach.exists("test-keep")  # only MDS channels by default
    assert run("rm")[0] == 0  # nothing left: still fine


def test_rm_missing_or_invalid(run) -> None:
    rc, _, err = run("rm", "mds-nothing")
    assert rc == 1 and "mds-nothing" in err and "does not exist" in err
    rc, _, err = run("rm", "bad/name")
    assert rc == 1 and "ACH_INVALID_NAME" in err


# --- dump ---------------------------------------------------------------------------------------------


def put(name: str, obj: object) -> None:
    with ach.Channel(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE) as ch:
        ch.put(obj)


def test_dump_state(run) -> None:
    st = MDS_STATE()
    st.time = 42.5
    j = st.joint[mds.LSP]
    j.enabled, j.address, j.pos, j.ref = 1, mds.LSP, -0.25, 0.5
    set_name(j, "name", "LeftShoulderExt")
    set_name(j, "nameshort", "LSP")
    st.collide.isCollide = 1
    st.collide.joint[mds.COLLIDE_L_HAND].isCollide = 1
    put(mds.MDS_CHAN_STATE_NAME, MDS_STATE())  # older frame: dump shows the newest
    put(mds.MDS_CHAN_STATE_NAME, st)
    rc, out, err = run("dump", "mds-state")
    assert (rc, err) == (0, "")
    assert "state frame, 14051 B" in out and "seq 2" in out
    assert "time 42.500000" in out
    lines = [x for x in out.splitlines() if x.startswith("LSP ")]
    assert len(lines) == 1
    assert "LeftShoulderExt" in lines[0] and "0x005f" in lines[0] and "-0.25000" in lines[0] and "0.50000" in lines[0]
    assert "LEP " not in out  # not enabled, not named: hidden ...
    rc, out, _ = run("dump", "--all", "mds-state")
    assert "LEP " in out  # ... unless --all
    assert "collide: True" in out and "L_HAND" in out


def test_dump_ref_ik_collide_param_cmd(run) -> None:
    ref = MDS_REF()
    ref.joint[mds.LEP].ref = 1.25
    ref.joint[mds.LEP].mode = 1
    put(mds.MDS_CHAN_REF_FILTER_NAME, ref)
    rc, out, _ = run("dump", "mds-ref-filter")
    assert rc == 0
    assert [x.split() for x in out.splitlines() if x.startswith("LEP")] == [
        ["LEP", "LeftElbowFlex", "0x004c", "1.25000", "1"]]

    ik = MDS_IK(move=mds.LEFT)
    ik.arm[mds.LEFT].t_y = 0.2
    ik.arm[mds.LEFT].ik_method = 3
    put(mds.MDS_CHAN_IK_NAME, ik)
    rc, out, _ = run("dump", "mds-ik")
    assert rc == 0 and "move: 1 (left)" in out
    assert [x.split() for x in out.splitlines() if x.startswith("left")] == [
        ["left", "0.0000", "0.2000", "0.0000", "0.0000", "0.0000", "0.0000", "3"]]

    col = MDS_COLLIDE(isCollide=1)
    col.joint[mds.COLLIDE_R_ELBOW].collision = 4
    put(mds.MDS_CHAN_COLLIDE_NAME, col)
    rc, out, _ = run("dump", "mds-collide")
    assert rc == 0 and "isCollide 1" in out
    assert [x.split()[:3] for x in out.splitlines() if x.startswith("R_ELBOW")] == [["R_ELBOW", "4", "0"]]

    par = MDS_JOINT_PARAM()
    p = par.joint[mds.RSP]
    p.enabled, p.rom, p.direction = 1, 3.1, -1
    set_name(p, "nameshort", "RSP")
    set_name(p, "HomeType", "limit")
    put(mds.MDS_CHAN_PARAM_NAME, par)
    rc, out, _ = run("dump", "mds-param")
    assert rc == 0
    row = next(x for x in out.splitlines() if x.startswith("RSP"))
    assert "RightShoulderExt" in row and "3.1000" in row and "limit" in row

    put(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD(seq=7, cmd=mds.MDS_CMD_HOME, address=mds.LSP, value=0.5))
    rc, out, _ = run("dump", "mds-cmd")
    assert rc == 0 and "seq 7" in out and "MDS_CMD_HOME" in out and "LSP" in out


def test_dump_unknown_channel_as_hex(run) -> None:
    put("test-raw", b"Hello, Ach!\x00\x01")
    rc, out, err = run("dump", "test-raw")
    assert (rc, err) == (0, "")
    assert "raw frame, 13 B" in out and "seq 1" in out and "data_head 13" in out
    assert "48 65 6c 6c 6f 2c 20 41 63 68 21 00 01" in out and "Hello, Ach!.." in out


def test_dump_wrong_size_frame_falls_back_to_hex(run) -> None:
    put(mds.MDS_CHAN_STATE_NAME, b"short")
    rc, out, err = run("dump", "mds-state")
    assert rc == 0
    assert "5 B but MDS_STATE is 14051 B" in err and "mds-state" in err
    assert "73 68 6f 72 74" in out


def test_dump_type_override_and_empty(run) -> None:
    ref = MDS_REF()
    ref.joint[mds.WST].ref = 0.75
    put("test-myref", ref)
    rc, out, _ = run("dump", "--type", "ref", "test-myref")
    assert rc == 0 and "0.75000" in out and "WST" in out
    rc, out, _ = run("dump", "--type", "hex", "test-myref")
    assert rc == 0 and "00000000  " in out
    ach.create("test-empty", 2, 8)
    rc, out, _ = run("dump", "test-empty")
    assert rc == 0 and "empty" in out and "seq 0" in out


def test_dump_wait_for_first_frame(run) -> None:
    ach.create("test-late", 2, 16)
    t = threading.Timer(0.05, lambda: put("test-late", b"late frame"))
    t.start()
    rc, out, _ = run("dump", "--wait", "10", "test-late")
    t.join()
    assert rc == 0 and "late frame" in out


def test_dump_errors(run) -> None:
    rc, out, err = run("dump", "mds-nope")
    assert (rc, out) == (1, "")
    assert err.startswith("mds-ach dump: ") and "mds-nope" in err and "does not exist" in err
    rc, _, err = run("dump", ".bad")
    assert rc == 1 and "ACH_INVALID_NAME" in err
    Path(ach.shm_path("test-junk")).write_bytes(b"\0" * 1000)
    rc, _, err = run("dump", "test-junk")
    assert rc == 1 and "test-junk" in err and "ACH_BAD_SHM_FILE" in err
    assert run("dump")[0] == 2
    assert run("dump", "--type", "nonsense", "mds-state")[0] == 2


# --- front-end ------------------------------------------------------------------------------------------


def test_help_and_usage_errors(run) -> None:
    rc, out, _ = run("--help")
    assert rc == 0 and all(v in out for v in ("make", "rm", "dump"))
    for verb in ("make", "rm", "dump", "mk"):
        rc, out, _ = run(verb, "--help")
        assert rc == 0 and "usage: mds-ach" in out
    assert run()[0] == 2
    rc, _, err = run("frobnicate")
    assert rc == 2 and "invalid choice" in err


def test_ros_args_are_ignored(run) -> None:
    assert cli.strip_ros_args(["rm", "--ros-args", "-r", "__node:=x", "--", "-q"]) == ["rm", "-q"]
    assert cli.strip_ros_args(["make", "--ros-args", "-p", "a:=1"]) == ["make"]
    rc, out, _ = run("make", "-q", "--ros-args", "-r", "__node:=chantool")
    assert (rc, out) == (0, "")


def test_console_script_and_light_startup(clean_shm: None) -> None:
    exe = VENV_BIN / "mds-ach"
    result = subprocess.run([str(exe), "dump", "mds-nope"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 1 and "mds-nope" in result.stderr
    result = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "dump" in result.stdout
    code = ("import sys\nfrom mds_ach.tools import cli\n"
            "rc = cli.main(['make', '-q'])\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'torch', 'fcl', 'yourdfpy', 'pytorch_kinematics'))\n"
            "print(rc, heavy)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.stdout.strip() == "0 []", result.stderr


# --- clients and channel files they must not use (issue #25, item 9) ----------------------------------------


def _plant_as_nobody(how: str, names: tuple[str, ...]) -> Path | None:
    """User nobody plants the clients' channels: a symlink to a valid Ach file of theirs, or the file itself."""
    theirs = Path(ach.shm_path("test-theirs"))

    def plant() -> int:
        if how == "symlink":
            ach.create("test-theirs", mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o666)
        for name in names:
            if how == "symlink":
                os.symlink(theirs, ach.shm_path(name))
            else:
                ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o666)
        return 0

    assert run_as(NOBODY, NOBODY, plant) == 0
    return theirs if how == "symlink" else None


CLIENTS = [(("read", "--once"), mds.MDS_CHAN_STATE_NAME), (("dump", mds.MDS_CHAN_STATE_NAME), mds.MDS_CHAN_STATE_NAME),
           (("hold", "--timeout", "2"), mds.MDS_CHAN_HOLD_NAME)]


@pytest.mark.parametrize("how", ["symlink", "file"])
@pytest.mark.parametrize(("argv", "channel"), CLIENTS, ids=[a[0] for a, _ in CLIENTS])
def test_clients_refuse_channels_another_user_planted(run, other_user: int, how: str, argv: tuple[str, ...],
                                                     channel: str) -> None:
    """`read --once`, `dump` and `hold` neither follow a planted symlink nor use a file another user owns: a clear
    message, exit 1, and that user's file is untouched (nothing was read from or written into it)."""
    ach.create(mds.MDS_CHAN_MUX_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    theirs = _plant_as_nobody(how, (mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_HOLD_NAME))
    target = theirs or Path(ach.shm_path(channel))
    before = target.read_bytes()
    rc, out, err = run(*argv)
    assert rc == 1, (out, err)
    assert "Traceback" not in out + err
    want = "is a symbolic link" if how == "symlink" else f"is owned by {user_label(NOBODY)}, neither you"
    assert want in out + err and f"mds-ach repair --recreate {channel}" in out + err
    assert target.read_bytes() == before


@pytest.mark.parametrize("kind", ["fifo", "directory"])
@pytest.mark.parametrize(("argv", "channel"), CLIENTS, ids=[a[0] for a, _ in CLIENTS])
def test_clients_on_a_fifo_or_directory_say_so_without_blocking(run, kind: str, argv: tuple[str, ...],
                                                                channel: str) -> None:
    ach.create(mds.MDS_CHAN_MUX_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    path = ach.shm_path(channel)
    os.mkfifo(path) if kind == "fifo" else os.mkdir(path)
    try:
        rc, out, err = run(*argv)
    finally:
        os.rmdir(path) if kind == "directory" else os.unlink(path)
    assert rc == 1 and "Traceback" not in out + err, (out, err)
    assert f"{path} is a {'FIFO' if kind == 'fifo' else 'directory'}, not a channel file" in out + err


def test_a_client_trusts_the_stack_users_channels(clean_shm: None, other_user: int) -> None:
    """The stack's user, for a client, is the owner of the daemon's input with the daemon input's mode: a client
    running as another user (here root, the stack being nobody's) uses that user's channels, and nobody else's."""
    ach.create(mds.MDS_CHAN_STATE_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o660)
    os.chown(ach.shm_path(mds.MDS_CHAN_STATE_NAME), NOBODY, NOBODY)
    with pytest.raises(ach.AchException, match="neither you .* root nor the stack's user \\(unknown"):
        ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    gated = mds.MDS_CHAN_DAEMON_INPUT_NAME
    ach.create(gated, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o660)  # group-writable: not the stack's
    os.chown(ach.shm_path(gated), NOBODY, NOBODY)
    assert channel_access.stack_owner() is None
    with pytest.raises(ach.AchException, match="ACH_EACCES"):
        ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False)
    os.chmod(ach.shm_path(gated), 0o640)
    assert channel_access.stack_owner() == NOBODY
    ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False).close()


def test_rm_of_a_directory_at_the_channel_path_is_a_clear_error(run) -> None:
    path = ach.shm_path(mds.MDS_CHAN_STATE_NAME)
    os.mkdir(path)
    try:
        rc, out, err = run("rm", mds.MDS_CHAN_STATE_NAME)
    finally:
        os.rmdir(path)
    assert rc == 1 and "Traceback" not in out + err
    assert f"{path} is a directory, not a channel file" in err
