"""The console: parser, bad input (fuzzed), and every command against the running simulated system."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import VENV_BIN, remove_mds_channels, wait_for
from support.channels import newest
from support.pty_session import PtySession
from support.system import arm_pos, arm_refs, chain_fk, joint_pos, joint_ref, mds_ach, running_system

import mds_ach as mds
from mds_ach import ach
from mds_ach.kinematics.limits import current_limits
from mds_ach.robot.config import load
from mds_ach.robot.joints import JOINTS
from mds_ach.robot.msgs.mux_state import MUX_HELD
from mds_ach.tools import console
from mds_ach.tools.console import CommandError, Get, GetFk, Goto, Ik, Simple, parse

# --------------------------------------------------------------------------------------------- parser


@pytest.mark.parametrize(("line", "expected"), [
    ("goto LSP -0.3", Goto(mds.BY_SHORT["LSP"], -0.3)),
    ("GOTO lsp -0.3 wait", Goto(mds.BY_SHORT["LSP"], -0.3, wait=True)),
    ("goto LeftShoulderExt 0.1", Goto(mds.BY_SHORT["LSP"], 0.1)),
    ("goto filter LEP -0.2", Goto(mds.BY_SHORT["LEP"], -0.2)),
    ("goto 0x5f 0", Goto(mds.BY_SHORT["LSP"], 0.0)),
    ("get REP", Get(mds.BY_SHORT["REP"])),
    ("get rightelbowflex", Get(mds.BY_SHORT["REP"])),
    ("get fk left", GetFk("left")),
    ("get FK Right", GetFk("right")),
    ("ik left 3 0.3 0.2 0.0", Ik("left", 3, (0.3, 0.2, 0.0))),
    ("ik right 6 0.3 -0.2 0 0 0 1.57 wait", Ik("right", 6, (0.3, -0.2, 0.0, 0.0, 0.0, 1.57), wait=True)),
    ("help", Simple("help")),
    ("?", Simple("help")),
    ("exit", Simple("exit")),
    ("quit", Simple("exit")),
    ("zeroall", Simple("zeroall")),
    ("goto LSP -0.3 step", Goto(mds.BY_SHORT["LSP"], -0.3, step=True)),
    ("goto LSP -0.3 wait STEP", Goto(mds.BY_SHORT["LSP"], -0.3, wait=True, step=True)),
    ("ik3 left 0.3 0.2 0", Ik("left", 3, (0.3, 0.2, 0.0), send=False)),
    ("ik3 right 0.3 -0.2 0 set", Ik("right", 3, (0.3, -0.2, 0.0))),
    ("ik3 left 0.3 0.2 0 set wait", Ik("left", 3, (0.3, 0.2, 0.0), wait=True)),
    ("ik5 left 0.3 0.2 0 0 0", Ik("left", 5, (0.3, 0.2, 0.0, 0.0, 0.0), send=False)),
    ("ik5 left 0.3 0.2 0 0 0.1 filter set", Ik("left", 5, (0.3, 0.2, 0.0, 0.0, 0.1))),
    ("", Simple("empty")),
    ("   # a comment", Simple("empty")),
])
def test_parse_valid(line: str, expected: object) -> None:
    assert parse(line) == expected


@pytest.mark.parametrize(("line", "message"), [
    ("fly", "unknown command 'fly'"),
    ("goto", "usage: goto <joint> <rad>"),
    ("goto LSP", "usage: goto <joint> <rad>"),
    ("goto XYZ 0.1", "unknown joint 'XYZ'"),
    ("goto LSP abc", "must be a number, got 'abc'"),
    ("goto LSP nan", "must be finite"),
    ("goto LSP inf", "must be finite"),
    ("goto LSP -1e999", "must be finite"),
    ("get", "usage: get <joint>"),
    ("get fk", "usage: get <joint>"),
    ("get fk middle", "arm must be 'left' or 'right'"),
    ("get LSP REP", "usage: get <joint>"),
    ("ik", "usage: ik <left|right>"),
    ("ik up 3 0 0 0", "arm must be 'left' or 'right'"),
    ("ik left three 0 0 0", "dof must be an integer"),
    ("ik left 7 0 0 0 0 0 0 0", "dof must be 1..6"),
    ("ik left 0", "dof must be 1..6"),
    ("ik left 3 0.3 0.2", "needs 3 value(s) (x y z), got 2"),
    ("ik left 2 0.3 0.2 0.1", "needs 2 value(s) (x y), got 3"),
    ("ik left 3 0.3 nan 0", "y must be finite"),
    ("help me", "'help' takes no arguments"),
    ("goto LSP step", "usage: goto <joint> <rad> [step] [wait]"),
    ("ik3 left 0.3 0.2", "usage: ik3 <left|right> <x> <y> <z> [set] [wait]"),
    ("ik3 left 0.3 0.2 0 filter", "usage: ik3"),
    ("ik3 left 0.3 0.2 0 wait", "'wait' needs 'set'"),
    ("ik5 left 0.3 0.2 0 0", "usage: ik5 <left|right> <x> <y> <z> <rx> <ry> [filter] [set] [wait]"),
    ("ik5 up 0.3 0.2 0 0 0", "arm must be 'left' or 'right'"),
    ("ik3 left 0.3 nan 0", "y must be finite"),
])
def test_parse_errors_say_what_is_wrong(line: str, message: str) -> None:
    with pytest.raises(CommandError) as info:
        parse(line)
    assert message in str(info.value)


@settings(max_examples=400, deadline=None)
@given(st.text(max_size=80))
def test_parse_never_raises_anything_but_command_error(line: str) -> None:
    try:
        parse(line)
    except CommandError as exc:
        assert str(exc)


# --------------------------------------------------------------------------------------------- fuzz against channels

TOKENS = ["goto", "get", "fk", "ik", "ik3", "ik5", "set", "step", "left", "right", "wait", "filter", "help", "zeroall",
          "exit", "LSP", "lsp",
          "LeftElbowFlex", "RSR", "NKY", "LF1", "0x5f", "0x00", "3", "6", "0", "-0.3", "0.2", "1e308", "-1e308",
          "nan", "inf", "-inf", "1e-320", "x", "", "#", "\x00", "é", "--", "-c"]
LINES = st.one_of(
    st.text(max_size=60),
    st.lists(st.sampled_from(TOKENS) | st.floats(allow_nan=True).map(repr) | st.integers().map(str),
             max_size=9).map(" ".join),
)


@pytest.fixture
def fake_system() -> Iterator[None]:
    """Channels holding one state frame at the home pose, and nothing running: the console must cope."""
    from mds_ach.robot.channels import StructChannel, make_channels
    from mds_ach.robot.config import load

    remove_mds_channels()
    make_channels()
    table = load()
    st_frame = mds.MDS_STATE()
    table.fill_state(st_frame)
    for j in table:
        st_frame.joint[j.address].ref = st_frame.joint[j.address].pos = j.home
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE) as ch:
        ch.put(st_frame)
    yield
    remove_mds_channels()


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(LINES)
def test_console_never_crashes_on_random_lines(fake_system: None, line: str) -> None:
    out: list[str] = []
    con = console.Console(out=out.append, err=out.append, progress=lambda: None)
    with mock.patch.object(console, "IK_TIMEOUT", 0.05), mock.patch.object(console, "GOTO_TIMEOUT", 0.05), \
            mock.patch.object(console, "STATE_WAIT", 0.01):
        try:
            ok = con.run_line(line)
        finally:
            con.close()
    assert ok in (True, False)
    if not ok:
        assert out and out[0].strip(), "a failure must say what was wrong"


def test_a_goto_to_the_value_the_channel_holds_is_a_command_after_another_controller_moved_it(
        fake_system: None) -> None:
    """Every put on mds-ref-filter is a command (issue 26): a goto to the value mds-ref-filter already holds, after
    another controller moved the joint, sends it back (as the original did) and is reported applied; a joint held
    by 'hold' stays held and the console says so. Then ``zeroall``: all or nothing, naming the joints that block."""
    import threading

    from mds_ach.nodes.mux import MuxRunner, load_config
    from mds_ach.nodes.pipeline import make_ref, ref_arrays
    from mds_ach.robot.channels import StructChannel

    cfg = load_config()
    logs: list[str] = []
    runner = MuxRunner(cfg["controllers"], cfg["state_rate"], log=lambda level, msg: logs.append(msg))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    out: list[str] = []
    con = console.Console(out=out.append, err=out.append, progress=lambda: None)
    try:
        assert runner.ready.wait(10), logs
        lsp = mds.BY_SHORT["LSP"].address
        assert con.run_line("goto LSP -0.3"), out
        assert re.fullmatch(r"\.+done", out[-1]), out  # the original's dots and 'done'
        with StructChannel(mds.MDS_CHAN_REF_IK_NAME, mds.MDS_REF) as ik:  # the IK controller moves LSP
            ref, mode = ref_arrays(_newest_mux_output())
            ref[lsp] = -0.1
            ik.put(make_ref(ref, mode))
        wait_for(lambda: _newest_mux_output().joint[lsp].ref == -0.1, 5, what="the IK frame applied")
        ik_index = [c.name for c in cfg["controllers"]].index("ik")
        wait_for(lambda: runner.core.stale(ik_index, time.monotonic()) and runner.core.owner[lsp] != ik_index, 10,
                 what="the IK controller stale, LSP released")
        out.clear()
        assert con.run_line("goto LSP -0.3"), out
        wait_for(lambda: _newest_mux_output().joint[lsp].ref == -0.3, 5, what="LSP back at -0.3")
        # the IK controller moves LSP again; zeroall after it is applied to every joint (not "some")
        with StructChannel(mds.MDS_CHAN_REF_IK_NAME, mds.MDS_REF) as ik:
            ref, mode = ref_arrays(_newest_mux_output())
            ref[lsp] = -0.15  # a change for 'ik' (it keeps "changed values only")
            ik.put(make_ref(ref, mode))
        wait_for(lambda: _newest_mux_output().joint[lsp].ref == -0.15, 5, what="the IK frame applied")
        wait_for(lambda: runner.core.stale(ik_index, time.monotonic()), 10, what="the IK controller stale")
        out.clear()
        assert con.run_line("zeroall"), out
        limits = current_limits()
        mux = _newest_mux_output()
        for j in JOINTS:
            rng = limits.range(j.address)
            if rng is not None:
                assert mux.joint[j.address].ref == min(max(0.0, rng[0]), rng[1]), j.short
        # a held joint that would have to move: zeroall sends nothing and names it
        assert con.run_line("goto LSP -0.2"), out
        assert con.run_line("hold LSP"), out
        before = ref_arrays(_newest_mux_output())[0]
        out.clear()
        assert not con.run_line("zeroall")
        assert "not sent: LSP (held)" in out[0], out
        assert np.array_equal(ref_arrays(_newest_mux_output())[0], before), "nothing moved"
        assert runner.core.held[lsp] == MUX_HELD
    finally:
        con.close()
        runner.stop()
        thread.join(5)


def _newest_mux_output() -> mds.MDS_REF:
    frame = newest(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
    assert frame is not None
    return frame


def test_without_a_system_commands_fail_with_a_clear_message() -> None:
    remove_mds_channels()
    out: list[str] = []
    con = console.Console(out=out.append, err=out.append, progress=lambda: None)
    with mock.patch.object(console, "STATE_WAIT", 0.01):
        assert not con.run_line("get LSP")
        assert not con.run_line("goto LSP 0.1")
    con.close()
    assert "is MDS-Ach running?" in out[0]
    assert not any(os.path.exists(f"/dev/shm/achshm-{n}") for n in mds.ALL_CHANNELS), "the console created channels"


@pytest.mark.parametrize(("value", "printed"), [(0.244, "0.244"), (-0.5, "-0.5"), (0.0, "0.0"), (-0.0, "-0.0"),
                                               (1e-05, "1e-05"), (0.24551, "0.24551"), (-0.65881, "-0.65881"),
                                               (3.0, "3.0"), (123456.12345, "123456.12345")])
def test_floats_print_as_python_2_printed_them(value: float, printed: str) -> None:
    """The original console was Python 2: `print 'x = ', round(v, 5)` wrote str(v) -- 12 significant digits, '.0'
    on a whole number -- not a fixed 5 decimals (issue #29 item 4)."""
    assert console.py2_str(value) == printed


def test_get_fk_and_ik_lines_have_the_original_spacing() -> None:
    """Python 2's print put a space between items: two spaces after each '=', the header's 'for  left  arm';
    ik3 and ik5 both said 'N-3'."""
    assert console.format_fk("left", (0.244, 0.24551, -0.6588125), (0.0, -0.0, 1.5707963)) == [
        "6DOF FK - for  left  arm", "pos:\tx =  0.244 \ty =  0.24551 \tz =  -0.65881",
        "rot:\tx =  0.0 \ty =  -0.0 \tz =  1.5708"]
    assert console.format_ik("right", (0.3, -0.2, 0.0, 0.0, 0.1), (0.3000042, -0.19999, 1e-06)) == [
        "N-3 DOF IK Solution - for  right  arm", "des:\tx =  0.3 \ty =  -0.2 \tz =  0.0",
        "ret:\tx =  0.3 \ty =  -0.19999 \tz =  0.0", "dif:\tx =  -0.0 \ty =  -1e-05 \tz =  -0.0"]


@pytest.mark.parametrize(("start", "target", "dots"), [(0.0, 0.25, 3), (0.0, 0.0, 1), (0.0, -0.05, 1),
                                                       (-1.0, -1.2, 2), (0.5, 0.15, 4)])
def test_goto_prints_a_dot_per_step_of_the_original(start: float, target: float, dots: int) -> None:
    assert console.original_steps(start, target) == dots


def test_the_original_verbs_print_what_the_original_printed(fake_system: None) -> None:
    """stdout of get, get fk and ik3/ik5 (solve only) is the original's lines and nothing else; notes go to stderr;
    an unknown verb is ignored (one line on stderr, not a failure) as the original ignored it."""
    out: list[str] = []
    err: list[str] = []
    con = console.Console(out=out.append, err=err.append, progress=lambda: None)
    try:
        assert con.run_line("get LSP")
        ref = f"{next(j.home for j in load() if j.short == 'LSP'):.5f}"
        assert out == [f"LeftShoulderExt  State =  {ref}  rad", f"LeftShoulderExt  Ref   =  {ref}  rad"], out
        out.clear()
        assert con.run_line("get fk left")
        assert len(out) == 3 and out[0] == "6DOF FK - for  left  arm"
        assert all(re.fullmatch(r"(pos|rot):\tx =  \S+ \ty =  \S+ \tz =  \S+", line) for line in out[1:]), out
        out.clear()
        for line in ("ik3 left 0.3 0.2 0", "ik5 left 0.3 0.2 0.0 1.2 -0.3"):
            assert con.run_line(line), err
        assert [x.split(":")[0] for x in out] == ["N-3 DOF IK Solution - for  left  arm", "des", "ret", "dif"] * 2
        out.clear()
        err.clear()
        assert con.run_line("fly")
        assert out == [] and err == ["  unknown command 'fly': ignored, as the original console did ('help' lists "
                                     "the commands)"]
        assert console.run_commands(con, ["fly", "get LSP"]) == 0
        assert out[-1].startswith("LeftShoulderExt  Ref   =")
    finally:
        con.close()


# --------------------------------------------------------------------------------------------- the real system


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    with running_system(tmp_path_factory.mktemp("console")) as env:
        yield env


def run_console(env: dict[str, str], *commands: str, timeout: float = 60.0,
                verbose: bool = False) -> subprocess.CompletedProcess:
    args = [str(VENV_BIN / "mds-ach"), "console"] + (["--verbose"] if verbose else [])
    for c in commands:
        args += ["-c", c]
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=timeout)


FK_RE = re.compile(r"6DOF FK - for  (left|right)  arm\npos:\tx =  (\S+) \ty =  (\S+) \tz =  (\S+)\n"
                   r"rot:\tx =  (\S+) \ty =  (\S+) \tz =  (\S+)")


def parse_fk(text: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for m in FK_RE.finditer(text):
        values = [float(v) for v in m.groups()[1:]]
        for v in m.groups()[1:]:  # Python 2's print of round(v, 5): 0.244, -0.5, 0.0, 1e-05
            assert v == console.py2_str(round(float(v), 5)), f"not as the original printed it: {v}"
        out[m.group(1)] = (np.array(values[:3]), np.array(values[3:]))
    return out


@pytest.mark.slow
def test_get_fk_prints_the_pose_of_the_current_references(system: dict[str, str]) -> None:
    proc = run_console(system, "get fk left", "get fk right")
    assert proc.returncode == 0, proc.stderr
    poses = parse_fk(proc.stdout)
    assert set(poses) == {"left", "right"}, proc.stdout
    for arm in ("left", "right"):
        p, euler = chain_fk(arm_refs(arm), arm)
        np.testing.assert_allclose(poses[arm][0], p, atol=2e-5)
        np.testing.assert_allclose(poses[arm][1], euler, atol=2e-5)


@pytest.mark.slow
def test_goto_moves_the_joint_through_the_pipeline(system: dict[str, str]) -> None:
    proc = run_console(system, "goto LSP -0.3 wait", "get LSP", verbose=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "LSP -> -0.30000 rad (sent to mds-ref-filter)" in proc.stdout  # --verbose
    assert re.search(r"^\.+done$", proc.stdout, re.M), proc.stdout
    assert abs(joint_pos("LSP") + 0.3) < 0.011
    # the original printed the joint's long (anatomy) name
    m = re.search(r"^LeftShoulderExt  State =  (-?\d+\.\d{5})  rad\nLeftShoulderExt  Ref   =  (-?\d+\.\d{5})  rad$",
                  proc.stdout, re.M)
    assert m, proc.stdout
    assert abs(float(m.group(1)) + 0.3) < 0.011 and abs(float(m.group(2)) + 0.3) < 0.011
    # the motion went through the mux: the default controller owns LSP now
    from support.channels import newest

    from mds_ach.robot.msgs import MDS_MUX_STATE

    mux_state = newest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
    owner = mux_state.owner[mds.LSP]
    assert mds.msgs.get_name(bytes(mux_state.name[owner])) == "default"


@pytest.mark.slow
def test_goto_with_a_long_name_and_get_shows_state_and_ref(system: dict[str, str]) -> None:
    proc = run_console(system, "goto LeftElbowFlex -0.4 wait")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert abs(joint_pos("LEP") + 0.4) < 0.011


@pytest.mark.slow
def test_goto_refuses_out_of_range_and_disabled_joints(system: dict[str, str]) -> None:
    before = joint_ref("RSP")
    proc = run_console(system, "goto RSP 5.0")
    assert proc.returncode == 1
    assert "outside RSP's range" in proc.stderr
    proc = run_console(system, "goto LF1 0.1")
    assert proc.returncode == 1
    assert "disabled" in proc.stderr
    time.sleep(0.3)  # a bad command must not move anything: give a wrong one time to show
    assert joint_ref("RSP") == pytest.approx(before, abs=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize(("short", "value"), [("LSR", -0.15), ("RSR", 0.15), ("LEP", -2.45), ("REP", -2.45),
                                              ("LWR", -1.0), ("RWR", 1.0)])
def test_goto_refuses_what_the_urdf_refuses_at_once(system: dict[str, str], short: str, value: float) -> None:
    """Issue #17: the joint table allows these, the URDF does not. `goto LSR -0.15` was accepted and stopped at
    0.023 ("did not arrive ... collision gate: clear"); now it is refused before anything is sent, naming the
    limits the daemon published."""
    before = joint_ref(short)
    proc = run_console(system, f"goto {short} {value} wait")
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"refused, nothing sent: {value:.5f} rad is outside {short}'s range" in proc.stderr
    assert "effective limits: URDF & joint table, robot" in proc.stderr
    time.sleep(0.3)  # a refused command must not move anything: give a wrong one time to show
    assert joint_ref(short) == pytest.approx(before, abs=1e-9)


@pytest.mark.slow
def test_bad_input_prints_the_problem_and_the_usage(system: dict[str, str]) -> None:
    proc = run_console(system, "get LSP", "goto LSP", "get LSP")
    assert proc.returncode == 1
    assert proc.stdout.count("State =") == 1, "commands after a failure must not run in -c mode"
    assert proc.stdout.endswith("rad\n  Invalid input... \n"), "the original's line for a bad goto"
    assert "usage: goto <joint> <rad>" in proc.stderr and "commands (joint names" in proc.stderr


@pytest.mark.slow
def test_ik_moves_the_arm_to_the_target_and_reports_the_fk(system: dict[str, str]) -> None:
    proc = run_console(system, "ik left 3 0.3 0.2 0.0 wait", timeout=90, verbose=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "solved" in proc.stdout and "done" in proc.stdout
    reported = parse_fk(proc.stdout)["left"][0]
    np.testing.assert_allclose(reported, [0.3, 0.2, 0.0], atol=0.011)
    reached, _ = chain_fk(arm_pos("left"), "left")
    np.testing.assert_allclose(reached, [0.3, 0.2, 0.0], atol=0.03)


@pytest.mark.slow
def test_goto_waits_while_a_higher_priority_controller_holds_the_joint(system: dict[str, str]) -> None:
    proc = run_console(system, "ik left 3 0.32 0.22 0.0", "goto LWY 0.3 wait", timeout=90)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "waiting for the mux to release LWY (held by 'ik')" in proc.stderr
    assert abs(joint_pos("LWY") - 0.3) < 0.011, "the goto is applied once the IK controller lets go"


@pytest.mark.slow
def test_ik_unreachable_moves_nothing(system: dict[str, str]) -> None:
    before = arm_refs("right")
    proc = run_console(system, "ik right 3 2.0 0.0 0.0", timeout=90)
    assert proc.returncode == 1
    assert "unreachable" in proc.stderr and proc.stdout == "", "the original's ik printed nothing"
    time.sleep(0.3)
    np.testing.assert_allclose(arm_refs("right"), before, atol=1e-9)


@pytest.mark.slow
def test_interactive_prompt_history_and_exit(system: dict[str, str], tmp_path: Path) -> None:
    env = dict(system, MDS_ACH_HISTORY=str(tmp_path / "history"))
    with PtySession([str(VENV_BIN / "mds-ach"), "console"], env=env) as pty:
        pty.expect(console.PROMPT, timeout=30)
        pty.send("get LSP\r")
        pty.expect(re.compile(r"LeftShoulderExt  Ref   =  -?\d+\.\d{5}  rad"), timeout=10)
        pty.expect(console.PROMPT, timeout=10)
        pty.send("goto nowhere 1\r")
        pty.expect("unknown joint 'nowhere'", timeout=10)
        pty.expect(console.PROMPT, timeout=10)
        pty.send("get LS")
        pty.expect("get LS", timeout=10)  # echoed: readline is reading the line
        pty.send("\x03")  # Ctrl-C abandons the line, the console stays
        pty.expect(console.PROMPT, timeout=10)
        pty.send("exit\r")
        assert pty.wait(timeout=10) == 0
    history = (tmp_path / "history").read_text()
    assert "get LSP" in history and "exit" in history


@pytest.mark.slow
def test_ctrl_d_and_sigterm_end_the_console_cleanly(system: dict[str, str]) -> None:
    with PtySession([str(VENV_BIN / "mds-ach"), "console"], env=system) as pty:
        pty.expect(console.PROMPT, timeout=30)
        pty.send("\x04")
        assert pty.wait(timeout=10) == 0
    with PtySession([str(VENV_BIN / "mds-ach-console")], env=system) as pty:
        pty.expect(console.PROMPT, timeout=30)
        pty.terminate()
        assert pty.wait(timeout=10) == 0


@pytest.mark.slow
def test_ctrl_c_and_sigterm_right_after_a_key_are_not_lost(system: dict[str, str]) -> None:
    """A Ctrl-C or SIGTERM that lands while readline is still handling the previous key was lost until the next key
    (the prompt slept in select(); 7 of 20 rounds on main before the fix): every one is taken at once now."""
    for _ in range(10):
        with PtySession([str(VENV_BIN / "mds-ach-console")], env=system) as pty:
            pty.expect(console.PROMPT, timeout=30)
            pty.send("get L")
            pty.expect("get L", timeout=10)
            pty.send("S")
            pty.send("\x03")
            pty.expect(console.PROMPT, timeout=10)
            pty.send("get LS")
            pty.terminate()
            assert pty.wait(timeout=10) == 0


@pytest.mark.slow
def test_console_reads_commands_from_a_pipe(system: dict[str, str]) -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach-console")], input="get fk left\nget LEP\n", env=system,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "6DOF FK - for  left  arm" in proc.stdout and "LeftElbowFlex  State =" in proc.stdout


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rfind(")") + 2] != "Z"


@pytest.mark.slow
def test_commands_are_not_applied_while_the_mux_is_down(system: dict[str, str]) -> None:
    """The adversarial run: 80 console commands "succeeded" with the mux dead, and not one MOVETO was sent."""
    mux_pid = int((Path(system["MDS_ACH_RUNTIME_DIR"]) / "mux.pid").read_text())
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
        sent_before = chan.last_seq
    before = [joint_ref(s) for s in ("LSP", "LEP", "RSP")]
    os.kill(mux_pid, signal.SIGKILL)
    try:
        wait_for(lambda: not _alive(mux_pid), 10, what="mux gone")
        for command in ("goto LSP -0.2", "ik left 3 0.3 0.2 0.0", "goto LSP -0.2 wait"):
            proc = run_console(system, command, timeout=90)
            assert proc.returncode == 1, f"{command}: {proc.stdout} {proc.stderr}"
            assert "not applied: mux not running (no new frame on mds-mux-state within 1 s); start it: " \
                   "mds-ach start --only mux; nothing sent" in proc.stderr, proc.stderr
            assert "done" not in proc.stdout and "solved" not in proc.stdout, proc.stdout
        with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
            assert chan.last_seq == sent_before, "nothing was written for the mux to find later"
        assert [joint_ref(s) for s in ("LSP", "LEP", "RSP")] == before, "nothing moved"
    finally:
        restart = mds_ach("start", "--only", "mux", "--timeout", "120", env=system, timeout=200)
        assert restart.returncode == 0, restart.stdout + restart.stderr
    proc = run_console(system, "goto LSP -0.2 wait")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.endswith("done\n") and abs(joint_pos("LSP") + 0.2) < 0.011


@pytest.mark.slow
def test_goto_step_ramps_like_the_original(system: dict[str, str]) -> None:
    """`goto <joint> <rad> step`: 0.1 rad every 0.1 s from the current reference, one dot per step, each step a
    frame on mds-ref-filter, the last one on the target."""
    proc = run_console(system, "goto LEP -0.1 wait")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    start = joint_ref("LEP")
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
        seq0 = chan.last_seq
        t0 = time.monotonic()
        proc = run_console(system, "goto LEP -0.75 step wait", "get LEP", verbose=True)
        elapsed = time.monotonic() - t0
        written = chan.last_seq - seq0
    assert proc.returncode == 0, proc.stdout + proc.stderr
    m = re.search(r"^(\.+)done\nLEP -> -0\.75000 rad in (\d+) steps of 0\.1 rad every 0\.1 s "
                  r"\(sent to mds-ref-filter\)$", proc.stdout, re.M)
    assert m, proc.stdout
    steps = int(m.group(2))
    assert len(m.group(1)) == steps
    assert abs(start + 0.75) / 0.1 <= steps <= abs(start + 0.75) / 0.1 + 1, (start, steps)
    assert steps >= 6 and written >= steps and elapsed >= (steps - 1) * 0.1
    assert "done" in proc.stdout and abs(joint_pos("LEP") + 0.75) < 0.011
    assert "LeftElbowFlex  Ref   =  -0.75000  rad" in proc.stdout


@pytest.mark.slow
def test_ik3_without_set_solves_and_prints_only(system: dict[str, str]) -> None:
    """The original's ik3/ik5 only printed the solution unless told 'set': nothing may move."""
    before = arm_refs("left")
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan, \
            ach.Channel(mds.MDS_CHAN_IK_NAME, create=False) as ikch:
        seqs = (chan.last_seq, ikch.last_seq)
        proc = run_console(system, "ik3 left 0.3 0.2 0.0", "ik5 left 0.3 0.2 0.0 1.2 -0.3")
        assert (chan.last_seq, ikch.last_seq) == seqs, "nothing was sent"
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("N-3 DOF IK Solution - for  left  arm\ndes:\tx =  0.3 \ty =  0.2 \tz =  0.0\n") == 2, \
        proc.stdout  # the original said N-3 for ik5 too
    m = re.search(r"^ret:\tx =  (\S+) \ty =  (\S+) \tz =  (\S+)$", proc.stdout, re.M)
    assert m, proc.stdout
    np.testing.assert_allclose([float(v) for v in m.groups()], [0.3, 0.2, 0.0], atol=1e-3)
    assert len(proc.stdout.splitlines()) == 8, "the original's four lines each, nothing more"
    time.sleep(0.3)  # give a wrong motion time to show
    np.testing.assert_allclose(arm_refs("left"), before, atol=1e-9)


@pytest.mark.slow
def test_ik3_set_moves_the_arm_through_the_ik_node(system: dict[str, str]) -> None:
    proc = run_console(system, "ik3 left 0.35 0.25 -0.05 set wait", timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("N-3 DOF IK Solution - for  left  arm\ndes:\tx =  0.35 \ty =  0.25 \tz =  -0.05\n")
    assert proc.stdout.endswith("done\n") and "solved:" not in proc.stdout
    np.testing.assert_allclose(chain_fk(arm_pos("left"), "left")[0], [0.35, 0.25, -0.05], atol=0.02)


@pytest.mark.slow
def test_zeroall_goes_to_the_nearest_in_range_value_and_says_so(system: dict[str, str]) -> None:
    """0 rad is outside both elbows' effective limits: each goes to its nearest in-range value instead of the whole
    command being refused, and the console names them. Last of the system tests (the fake-system tests after it
    replace the channels): the arms end down at the body."""
    from mds_ach.kinematics.limits import current_limits
    from mds_ach.robot.config import load

    limits = current_limits()
    expected = {}
    for j in load():
        if j.enabled and (rng := limits.range(j.address)) is not None:
            expected[j.short] = min(max(0.0, rng[0]), rng[1])
    clamped = {s: v for s, v in expected.items() if v != 0.0}
    assert {"LEP", "REP"} <= set(clamped), clamped  # otherwise this test shows nothing
    proc = run_console(system, "zeroall", timeout=120, verbose=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{len(expected)} enabled joints -> 0 rad (sent to mds-ref-filter)" in proc.stdout  # --verbose
    line = next(x for x in proc.stderr.splitlines() if x.startswith("0 rad is outside the limits"))
    for short, value in clamped.items():
        assert f"{short} {value:.5f} (range [" in line, line
    assert f"of {len(clamped)}; nearest in range" in line
    out = newest(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
    for short, value in expected.items():
        assert out.joint[mds.BY_SHORT[short].address].ref == value, short


def test_console_does_not_import_torch(fake_system: None) -> None:
    code = ("import sys; from mds_ach.tools.console import main; rc = main(['-c', 'get fk left']); "
            "assert 'torch' not in sys.modules, 'console imported torch'; sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "6DOF FK - for  left  arm" in proc.stdout


def test_help_exits_zero() -> None:
    for args in (["mds-ach-console", "--help"], ["mds-ach", "console", "--help"]):
        proc = subprocess.run([str(VENV_BIN / args[0]), *args[1:]], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0 and "usage" in proc.stdout.lower()
        assert "goto <joint> <rad>" in proc.stdout


@pytest.mark.parametrize(("word", "hint"), [("XYZ", ""), ("LSX", "did you mean LSY, LSR, LSP? ")])
def test_an_unknown_joint_is_one_line(word: str, hint: str) -> None:
    """Issue 28: an unknown joint printed the whole help (and 43 names)."""
    with pytest.raises(CommandError) as info:
        parse(f"goto {word} 0.1")
    assert str(info.value) == f"unknown joint {word!r} ({hint}'mds-ach read all' lists every joint)"
    assert not info.value.show_usage
    proc = mds_ach("console", "-c", f"goto {word} 0.1")
    assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


@pytest.mark.parametrize("verb", ["read", "console"])
def test_help_descriptions_are_wrapped(verb: str) -> None:
    proc = subprocess.run([str(VENV_BIN / "mds-ach"), verb, "--help"], capture_output=True, text=True, timeout=60,
                          env={**os.environ, "COLUMNS": "100"})
    assert proc.returncode == 0
    description = proc.stdout.split("\n\n")[1]
    assert len(description.splitlines()) > 1 and max(len(line) for line in description.splitlines()) <= 98, \
        description


def test_a_reader_that_stops_reading_ends_the_console_quietly() -> None:
    """Issue #29 item 6: `mds-ach console -c ... | head -1` ended in a BrokenPipeError traceback. Now it stops as a
    tool killed by SIGPIPE does: no traceback, status 141, no later command run."""
    for argv in ([str(VENV_BIN / "mds-ach"), "console"], [str(VENV_BIN / "mds-ach-console")]):
        proc = subprocess.Popen([*argv, *["-c", "help"] * 200], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert proc.stdout is not None and proc.stderr is not None
        first = proc.stdout.readline()  # `head -1`
        proc.stdout.close()
        err = proc.stderr.read().decode()
        assert proc.wait(60) == 141 and first.startswith(b"commands"), err
        assert err == "", err
