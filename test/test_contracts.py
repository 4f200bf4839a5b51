"""The contracts registry (mds_ach.robot.contracts) and what is derived from it: channel names, achd's write rules,
the daemon's channel set, the launcher's readiness checks, file modes, ``mds-ach dump``."""

from __future__ import annotations

import ctypes
import math
import signal
from collections.abc import Callable, Iterator

import pytest

import mds_ach as mds
from mds_ach import ach
from mds_ach.net import achd, remote
from mds_ach.nodes.daemon_loop import DAEMON_ROLES
from mds_ach.robot import access, contracts, msgs
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import daemon_status, ik_status
from mds_ach.tools import chantool, cli, launcher

PROCESSES = {contracts.DAEMON, contracts.MUX, contracts.FILTER, contracts.COLLISION, contracts.IK, contracts.BRIDGE,
             contracts.CONSOLE, contracts.READ, contracts.VIEWER, contracts.CLI, contracts.REMOTE, contracts.CLIENTS}

Run = Callable[..., tuple[int, str, str]]


# --- the registry itself --------------------------------------------------------------------------------------


def test_every_channel_is_declared_once() -> None:
    names = [c.name for c in contracts.CHANNELS]
    macros = [c.macro for c in contracts.CHANNELS]
    assert len(set(names)) == len(names) and len(set(macros)) == len(macros)
    assert tuple(names) == mds.ALL_CHANNELS == mds.LEGACY_CHANNELS + mds.PIPELINE_CHANNELS
    assert mds.LEGACY_CHANNELS == ("mds-ref", "mds-ref-filter", "mds-state", "mds-param", "mds-ik", "mds-collide",
                                   "mds-cmd")
    for c in contracts.CHANNELS:
        assert getattr(mds, c.macro) == c.name, f"mds.{c.macro}"
        assert c.writers and c.readers and set(c.writers + c.readers) <= PROCESSES, c.name
        assert issubclass(c.struct, msgs.Packed)
        assert c.size <= c.frame_count * c.frame_size, f"{c.name}: {c.struct.__name__} does not fit the channel"
        assert contracts.lookup(c.name) is c and contracts.struct_of(c.name) is c.struct


def test_structs_of_the_channels() -> None:
    expected = {"mds-ref": msgs.MDS_REF, "mds-ref-filter": msgs.MDS_REF, "mds-state": msgs.MDS_STATE,
                "mds-param": msgs.MDS_JOINT_PARAM, "mds-ik": msgs.MDS_IK, "mds-collide": msgs.MDS_COLLIDE,
                "mds-cmd": msgs.MDS_CMD, "mds-ref-ik": msgs.MDS_REF, "mds-ref-ros": msgs.MDS_REF,
                "mds-ref-mux": msgs.MDS_REF, "mds-ref-smooth": msgs.MDS_REF, "mds-ref-gated": msgs.MDS_REF,
                "mds-ik-state": msgs.MDS_IK_STATUS,
                "mds-mux-state": msgs.MDS_MUX_STATE, "mds-daemon-status": msgs.MDS_DAEMON_STATUS,
                "mds-hold": msgs.MDS_HOLD, "mds-limits": msgs.MDS_LIMITS}
    assert {c.name: c.struct for c in contracts.CHANNELS} == expected


def test_unregistered_channels() -> None:
    """Extra mux inputs (config/mux.yaml) are reference channels; anything else is not an MDS channel."""
    extra = contracts.lookup("mds-ref-joystick")
    assert extra is not None and extra.struct is msgs.MDS_REF and extra.validator is contracts.check_ref
    assert contracts.lookup("test-raw") is None
    with pytest.raises(KeyError, match="test-raw"):
        contracts.struct_of("test-raw")


def test_wire_structs_nested_first() -> None:
    order = contracts.wire_structs()
    assert len(set(order)) == len(order)
    assert {c.struct for c in contracts.CHANNELS} <= set(order)
    for i, cls in enumerate(order):
        for _name, ftype, *_ in cls._fields_:
            while issubclass(ftype, ctypes.Array):
                ftype = ftype._type_
            if issubclass(ftype, ctypes.Structure):
                assert order.index(ftype) < i, f"{ftype.__name__} must come before {cls.__name__}"


# --- validators --------------------------------------------------------------------------------------------


def _ref(address: int = mds.LSP, value: float = 0.5, mode: int = mds.MDS_REF_MODE_REF) -> msgs.MDS_REF:
    ref = msgs.MDS_REF()
    ref.joint[address].ref = value
    ref.joint[address].mode = mode
    return ref


def test_validators() -> None:
    assert contracts.check_ref(_ref()) is None
    assert "non-finite" in (contracts.check_ref(_ref(value=math.nan)) or "")
    assert "beyond one turn" in (contracts.check_ref(_ref(value=7.0)) or "")
    assert "ref mode 4" in (contracts.check_ref(_ref(mode=4)) or "")
    assert contracts.check_ik(msgs.MDS_IK(move=mds.LEFT)) is None
    assert "neither arm" in (contracts.check_ik(msgs.MDS_IK(move=2)) or "")
    bad = msgs.MDS_IK(move=mds.RIGHT)
    bad.arm[mds.RIGHT].t_z = math.inf
    assert "non-finite" in (contracts.check_ik(bad) or "")
    bad = msgs.MDS_IK(move=mds.RIGHT)
    bad.arm[mds.LEFT].ik_method = 7
    assert "outside 0..6" in (contracts.check_ik(bad) or "")
    assert contracts.check_cmd(msgs.MDS_CMD(cmd=mds.MDS_CMD_HOME)) is None
    assert "non-finite" in (contracts.check_cmd(msgs.MDS_CMD(value=math.nan)) or "")


def test_problem_checks_size_then_content() -> None:
    c = contracts.BY_NAME[mds.MDS_CHAN_REF_FILTER_NAME]
    assert c.problem(bytes(_ref())) is None
    assert c.problem(b"\0" * 999) == ("size", "999 bytes, MDS_REF has 1000")
    kind, reason = c.problem(bytes(_ref(value=math.nan))) or ("", "")
    assert kind == "invalid" and "non-finite" in reason
    assert contracts.BY_NAME[mds.MDS_CHAN_STATE_NAME].problem(bytes(msgs.MDS_STATE())) is None


# --- what is derived from it -------------------------------------------------------------------------------


def test_achd_rules_follow_the_contracts() -> None:
    for c in contracts.CHANNELS:
        rule = achd.rule_for(c.name)
        assert rule.ctype is c.struct
        assert rule.problem(b"") == ("size", "empty frame")
        assert rule.problem(bytes(c.struct())) == c.problem(bytes(c.struct()))
    assert achd.rule_for("mds-ref-joystick").ctype is msgs.MDS_REF
    assert achd.rule_for("mds-ref-joystick").problem(bytes(_ref(mode=9)))[0] == "invalid"
    assert achd.rule_for("test-raw").ctype is None and achd.rule_for("test-raw").problem(b"x") is None


def test_network_defaults_never_reach_the_daemon() -> None:
    # mds-ref is the mux's 'direct' input (issue #18): a remote `achd push mds-ref` passes the pipeline like the rest
    assert achd.SAFE_WRITABLE == remote.ROBOT_WRITABLE == ("mds-ref", "mds-ref-filter", "mds-ik", "mds-hold")
    assert mds.MDS_CHAN_DAEMON_INPUT_NAME == "mds-ref-gated" != mds.MDS_CHAN_REF_NAME
    assert mds.MDS_CHAN_DAEMON_INPUT_NAME not in achd.SAFE_WRITABLE
    assert mds.MDS_CHAN_BOARD_CMD_NAME not in achd.SAFE_WRITABLE
    assert set(remote.ROBOT_READABLE) == {"mds-state", "mds-param", "mds-collide", "mds-daemon-status",
                                          "mds-mux-state", "mds-ik-state", "mds-limits"}


def test_stack_only_is_the_daemon_input() -> None:
    # mds-limits too: the limit authority every entry point checks against is the daemon's alone (issue #17)
    assert contracts.STACK_ONLY == access.STACK_ONLY == frozenset({mds.MDS_CHAN_DAEMON_INPUT_NAME,
                                                                   mds.MDS_CHAN_LIMITS_NAME})
    assert contracts.BY_NAME[mds.MDS_CHAN_LIMITS_NAME].writers == (contracts.DAEMON,)
    assert access.channel_mode(mds.MDS_CHAN_LIMITS_NAME) == 0o640
    assert contracts.BY_NAME[mds.MDS_CHAN_DAEMON_INPUT_NAME].writers == (contracts.COLLISION,)
    assert access.channel_mode(mds.MDS_CHAN_DAEMON_INPUT_NAME) == 0o640
    assert access.channel_mode(mds.MDS_CHAN_REF_FILTER_NAME) == 0o660
    assert access.channel_mode(mds.MDS_CHAN_REF_NAME) == 0o660  # legacy clients (operators) write mds-ref


def test_daemon_channel_set() -> None:
    assert set(DAEMON_ROLES.values()) == {c.name for c in contracts.used_by(contracts.DAEMON)}


def test_launcher_readiness() -> None:
    """Every node the launcher starts shows it is up on a channel it writes, except the bridge (ROS output)."""
    assert set(launcher.READY_CHANNELS) == set(launcher.NODES) - {"bridge"}
    for node, channel in launcher.READY_CHANNELS.items():
        assert contracts.BY_NAME[channel].writers[0] == node
    assert launcher.READY_CHANNELS["daemon"] == mds.MDS_CHAN_STATE_NAME
    assert launcher.READINESS["ik"] == (mds.MDS_CHAN_IK_STATE_NAME, "answer")


def test_struct_channel_of(clean_shm: None) -> None:
    with StructChannel.of(mds.MDS_CHAN_MUX_STATE_NAME) as ch:
        assert ch.ctype is msgs.MDS_MUX_STATE
        assert (ch.channel.frame_count, ch.channel.frame_size) == (mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    with pytest.raises(KeyError):
        StructChannel.of("test-raw")


# --- mds-ach dump decodes every registered struct ----------------------------------------------------------------


@pytest.fixture
def run(clean_shm: None, capsys: pytest.CaptureFixture[str]) -> Iterator[Run]:
    """Run ``mds-ach ARGS`` in-process; returns (exit code, stdout, stderr)."""
    old_term = signal.getsignal(signal.SIGTERM)

    def invoke(*args: str) -> tuple[int, str, str]:
        try:
            rc = cli.main(list(args))
        except SystemExit as exc:
            rc = int(exc.code or 0)
        out, err = capsys.readouterr()
        return rc, out, err

    yield invoke
    signal.signal(signal.SIGTERM, old_term)


def _put(name: str, frame: ctypes.Structure) -> None:
    with ach.Channel(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE) as ch:
        ch.put(frame)


@pytest.mark.parametrize("name", mds.ALL_CHANNELS)
def test_dump_decodes_every_registered_channel_by_field_name(run: Run, name: str) -> None:
    c = contracts.BY_NAME[name]
    _put(name, c.struct())
    rc, out, err = run("dump", name)
    assert (rc, err) == (0, "")
    assert out.startswith(f"{name}: {chantool.kind_of(c.struct)} frame, {c.size} B")
    rc, out, err = run("dump", "--fields", "--all", name)
    assert (rc, err) == (0, "")
    labels = {line.split(" ", 1)[0].split("[", 1)[0].split(".", 1)[0] for line in out.splitlines()[1:]}
    assert labels == {f for f, *_ in c.struct._fields_}, "every field by name, nothing else"


def test_dump_mux_state_shows_owners(run: Run) -> None:
    """docs/operator.md: `mds-ach dump mds-mux-state` shows who owns each joint."""
    st = msgs.MDS_MUX_STATE(count=2, seq=5)
    for a in range(mds.MDS_JOINT_COUNT):
        st.owner[a] = -1
    st.owner[mds.LEP] = 1
    st.name[0].value, st.name[1].value = b"ros", b"default"
    st.priority[0], st.priority[1] = 30, 10
    st.age[0], st.age[1] = -1.0, 0.25
    _put(mds.MDS_CHAN_MUX_STATE_NAME, st)
    rc, out, _ = run("dump", "mds-mux-state")
    assert rc == 0 and "seq 5" in out
    assert [x.split() for x in out.splitlines() if x.startswith(("ros ", "default "))] == [
        ["ros", "30", "0", "never", "0.000"], ["default", "10", "0", "0.250", "0.000"]]
    assert [x.split() for x in out.splitlines() if x.startswith("LEP")] == [
        ["LEP", "LeftElbowFlex", "0x004c", "default"]]
    assert "LSP " not in out  # owned by nobody: shown only with --all
    rc, out, _ = run("dump", "--all", "mds-mux-state")
    assert [x.split()[-1] for x in out.splitlines() if x.startswith("LSP ")] == ["-"]


def test_dump_ik_and_daemon_status(run: Run) -> None:
    answer = msgs.MDS_IK_STATUS(seq=2, status=ik_status.IK_UNREACHABLE, arm=mds.LEFT)
    ik_status.set_message(answer, "no solution within 200 iterations")
    _put(mds.MDS_CHAN_IK_STATE_NAME, answer)
    rc, out, _ = run("dump", "mds-ik-state")
    assert rc == 0 and "status 1 (unreachable): no solution within 200 iterations" in out
    assert "seq 2" in out.splitlines() and "arm 1" in out.splitlines()
    st = msgs.MDS_DAEMON_STATUS(version=daemon_status.DAEMON_STATUS_VERSION, rate_hz=10, overruns=3)
    st.joint_flags[mds.LEP] = daemon_status.JOINT_ENABLED | daemon_status.JOINT_FRESH
    _put(mds.MDS_CHAN_DAEMON_STATUS_NAME, st)
    rc, out, _ = run("dump", "mds-daemon-status")
    assert rc == 0 and "overruns 3" in out and "/10 Hz" in out.splitlines()[1]
    assert f"joint_flags[{mds.LEP:#04x}] 6" in out.splitlines()
    assert not any(x.startswith(f"joint_flags[{mds.LSP:#04x}]") for x in out.splitlines())  # zero: hidden
