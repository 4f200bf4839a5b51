"""include/mds.h against the Python layouts: compiled with gcc/g++, every sizeof/offsetof compared.

The header is generated from mds_ach.robot.contracts and mds_ach.robot.msgs, so these tests check what
generation cannot promise by itself: that a C compiler lays the structs out byte for byte like ctypes
(packing, field types), that the bytes a C program writes decode correctly in Python, that the constants
agree, and that the committed file is the generated one. mds.h includes <ach.h> like the original, so the
project's libach headers are on the include path; the C examples and an original-style client are linked and
run in test_examples.py.
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from pathlib import Path

import pytest
from support import libach

import mds_ach as mds
from mds_ach.robot import contracts, joints, msgs
from mds_ach.robot.msgs import daemon_status, ik_status, mux_state
from mds_ach.tools import cheader

INCLUDE = cheader.HEADER_PATH.parent


def include_flags() -> list[str]:
    """mds.h includes <ach.h> like the original: the project's libach headers (installed by make setup)."""
    return [f"-I{INCLUDE}", f"-I{libach.prefix() / 'include'}"]

# Sizes from the original develop-branch mds.h (specs/mds-original.md §a.5), independent of msgs.py.
SPEC_SIZES = {
    "mds_joint_ref_t": 10,
    "mds_ref_t": 1000,
    "mds_joint_state_t": 138,
    "mds_jnt_collide_t": 20,
    "mds_collide_t": 218,
    "mds_power_t": 24,
    "mds_state_t": 14051,
    "mds_jnt_param_t": 290,
    "mds_joint_param_t": 29000,
    "mds_ik_arm_t": 50,
    "mds_ik_t": 102,
}
# The new structs (this stack's own channels); test_msgs_layout checks their offsets.
NEW_SIZES = {"mds_cmd_t": 16, "mds_ik_status_t": 214, "mds_mux_state_t": 920, "mds_daemon_status_t": 2132}


def _compile_and_run(tmp_path: Path, source: str, compiler: str = "gcc", std: str = "c11", extra: tuple = ()) -> str:
    """Build ``source`` against include/mds.h with warnings as errors, run it, return stdout."""
    exe = shutil.which(compiler)
    assert exe, f"{compiler} is needed to check include/mds.h"
    suffix = ".cpp" if compiler in ("g++", "c++") else ".c"
    src = tmp_path / f"prog{suffix}"
    src.write_text(source)
    binary = tmp_path / "prog"
    cmd = [exe, f"-std={std}", "-Wall", "-Wextra", "-Werror", *include_flags(), *extra, str(src), "-o", str(binary)]
    build = subprocess.run(cmd, capture_output=True, text=True)
    assert build.returncode == 0, f"{' '.join(cmd)} failed:\n{build.stderr}"
    run = subprocess.run([str(binary)], capture_output=True, text=True, timeout=30)
    assert run.returncode == 0, run.stderr
    return run.stdout


def _layout_program() -> str:
    lines = ["#include <stddef.h>", "#include <stdio.h>", '#include "mds.h"', "int main(void) {"]
    for cls in cheader.STRUCTS:
        c = cheader.c_type_name(cls)
        lines.append(f'    printf("{c} - %zu %zu\\n", (size_t)0, sizeof({c}));')
        for name, _ in cls._fields_:
            lines.append(f'    printf("{c} {name} %zu %zu\\n", offsetof({c}, {name}), sizeof((({c} *)0)->{name}));')
    lines += ["    return 0;", "}"]
    return "\n".join(lines) + "\n"


def _python_layout() -> set[tuple[str, str, int, int]]:
    rows = set()
    for cls in cheader.STRUCTS:
        c = cheader.c_type_name(cls)
        rows.add((c, "-", 0, ctypes.sizeof(cls)))
        for name, _ in cls._fields_:
            field = getattr(cls, name)
            rows.add((c, name, field.offset, field.size))
    return rows


def _parse_layout(out: str) -> set[tuple[str, str, int, int]]:
    rows = set()
    for line in out.splitlines():
        struct, field, off, size = line.split()
        rows.add((struct, field, int(off), int(size)))
    return rows


def test_committed_header_is_generated_text() -> None:
    committed = cheader.HEADER_PATH.read_text()
    assert committed == cheader.generate(), \
        "include/mds.h is stale: run `python -m mds_ach.tools.cheader` and commit it"
    assert cheader.main(["--check"]) == 0


def test_gcc_layout_equals_ctypes(tmp_path: Path) -> None:
    c_rows = _parse_layout(_compile_and_run(tmp_path, _layout_program()))
    py_rows = _python_layout()
    assert c_rows == py_rows, f"only in C: {sorted(c_rows - py_rows)}; only in ctypes: {sorted(py_rows - c_rows)}"
    sizes = {s: size for s, f, _, size in c_rows if f == "-"}
    for name, size in SPEC_SIZES.items():
        assert sizes[name] == size, f"{name}: gcc says {sizes[name]} B, the original mds.h had {size} B"
    for name, size in NEW_SIZES.items():
        assert sizes[name] == size, f"{name}: gcc says {sizes[name]} B, expected {size} B"


def test_header_has_every_channel_struct() -> None:
    """Every struct a registered channel carries (and every struct nested in one) is in the header."""
    for c in contracts.CHANNELS:
        assert c.struct in cheader.STRUCTS, f"{c.name}: {c.struct.__name__} missing from include/mds.h"
    text = cheader.HEADER_PATH.read_text()
    for cls in cheader.STRUCTS:
        assert f"}} {cheader.c_type_name(cls)};" in text


def test_new_structs_written_in_c_decode_in_python(tmp_path: Path) -> None:
    """Mux state, IK status and daemon status filled by a C program read back field by field in Python."""
    prog = r"""
#include <stdio.h>
#include <string.h>
#include "mds.h"
int main(void) {
    mds_mux_state_t m;
    mds_ik_status_t k;
    mds_daemon_status_t d;
    memset(&m, 0, sizeof m);
    memset(&k, 0, sizeof k);
    memset(&d, 0, sizeof d);
    for (int a = 0; a < MDS_JOINT_COUNT; a++) m.owner[a] = MDS_MUX_NO_OWNER;
    m.owner[MDS_JOINT_LSP] = 1;
    m.count = 2;
    m.priority[1] = 10;
    m.age[1] = 0.5;
    strcpy(m.name[1], "default");
    m.seq = 9;
    k.seq = 3;
    k.status = MDS_IK_UNREACHABLE;
    k.arm = MDS_LEFT;
    k.q[5] = -0.25;
    strcpy(k.message, "no solution");
    d.version = MDS_DAEMON_STATUS_VERSION;
    d.bus_state = MDS_DAEMON_BUS_STATE_BUS_OFF;
    d.cmd_result = MDS_DAEMON_CMD_REFUSED;
    d.joint_flags[MDS_JOINT_LEP] = MDS_DAEMON_JOINT_ENABLED | MDS_DAEMON_JOINT_STALE;
    d.joint_reseed[MDS_JOINT_LEP] = 4;
    d.lock_timeouts = 77;
    d.loop_policy = 1;
    d.loop_priority = 50;
    fwrite(&m, sizeof m, 1, stdout);
    fwrite(&k, sizeof k, 1, stdout);
    fwrite(&d, sizeof d, 1, stdout);
    return 0;
}
"""
    exe = tmp_path / "writer"
    src = tmp_path / "writer.c"
    src.write_text(prog)
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Werror", *include_flags(), str(src), "-o", str(exe)], check=True)
    raw = subprocess.run([str(exe)], capture_output=True, check=True).stdout
    n_m, n_k = ctypes.sizeof(msgs.MDS_MUX_STATE), ctypes.sizeof(msgs.MDS_IK_STATUS)
    assert len(raw) == n_m + n_k + ctypes.sizeof(msgs.MDS_DAEMON_STATUS)
    m = msgs.MDS_MUX_STATE.from_bytes(raw[:n_m])
    k = msgs.MDS_IK_STATUS.from_bytes(raw[n_m:n_m + n_k])
    d = msgs.MDS_DAEMON_STATUS.from_bytes(raw[n_m + n_k:])
    assert (m.owner[mds.LSP], m.owner[mds.LEP], m.count, m.priority[1], m.age[1], m.seq) == (1, -1, 2, 10, 0.5, 9)
    assert msgs.get_name(bytes(m.name[1])) == "default"
    assert (k.seq, k.status, k.arm, k.q[5]) == (3, ik_status.IK_UNREACHABLE, mds.LEFT, -0.25)
    assert ik_status.get_message(k) == "no solution"
    assert (d.version, d.bus_state, d.cmd_result) == (daemon_status.DAEMON_STATUS_VERSION,
                                                      daemon_status.BUS_STATE_BUS_OFF, daemon_status.CMD_REFUSED)
    assert d.joint_flags[mds.LEP] == daemon_status.JOINT_ENABLED | daemon_status.JOINT_STALE
    assert (d.joint_reseed[mds.LEP], d.lock_timeouts, d.loop_policy, d.loop_priority) == (4, 77, 1, 50)


def test_gxx_layout_equals_ctypes(tmp_path: Path) -> None:
    """C++ controllers include the same header; the layout must not change under g++."""
    out = _compile_and_run(tmp_path, _layout_program(), compiler="g++", std="c++11")
    assert _parse_layout(out) == _python_layout()


def test_header_compiles_as_c99_pedantic(tmp_path: Path) -> None:
    """The C99 fallback of MDS_STATIC_ASSERT must still build (old controllers use -std=c99). mds.h's own text
    is pedantic C99; libach's ach.h is not (anonymous unions, as in golems' libach), so it is left out here and
    built in C99 without -pedantic below."""
    prog = '#define MDS_NO_ACH\n#include "mds.h"\nint main(void) { mds_state_t s = {0}; return (int)s.refWait; }\n'
    _compile_and_run(tmp_path, prog, std="c99", extra=("-pedantic",))
    prog = ('#include "mds.h"\n'
            "int main(void) { mds_state_t s = {0}; ach_channel_t c; (void)c; return (int)s.refWait; }\n")
    _compile_and_run(tmp_path, prog, std="c99")


# The original develop-branch mds.h's own names and values (specs/mds-original.md §a; read from the original
# header), written out here independently of the generator.
ORIGINAL_INTS = {
    "MDS_CAN_CHAN_NUM": 4, "MDS_JOINT_COUNT": 100, "MDS_COLLIDE_JNT_NUM": 10, "MDS_ARM_COUNT": 2,
    "MDS_REF_FILTER_LENGTH": 40, "MDS_CAN_BUFFER_CLEAR_I": 1000, "MDS_CHAR_PARAM_BUFFER_SIZE": 30,
    "MAX_SAFE_STACK": 1024 * 1024, "FALSE": 0, "TRUE": 1, "IK1": 1, "IK2": 2, "IK3": 3, "IK4": 4, "IK5": 5, "IK6": 6,
    "MDS_REF_MODE_REF_FILTER": 0, "MDS_REF_MODE_REF": 1, "MDS_REF_MODE_COMPLIANT": 2, "MDS_REF_MODE_ENC_FILTER": 3,
    "RIGHT": 0, "LEFT": 1, "COLLISION_L_HAND": 0, "COLLISION_R_HAND": 1, "COLLISION_R_SHOULDER": 2,
    "COLLISION_L_SHOULDER": 3, "COLLISION_R_FOREARM": 4, "COLLISION_L_FOREARM": 5, "COLLISION_R_ELBOW": 6,
    "COLLISION_L_ELBOW": 7, "COLLISION_R_WRIST": 8, "COLLISION_L_WRIST": 9,
    "REP": 0x48, "RSY": 0x49, "RSR": 0x4B, "LEP": 0x4C, "LSY": 0x4D, "LSR": 0x4F, "RWR": 0x50, "RWY": 0x52,
    "LWR": 0x54, "LWY": 0x56, "RSP": 0x5B, "WST": 0x5C, "LSP": 0x5F, "RightElbowFlex": 0x48,
    "RightUpperArmRoll": 0x49, "RightShoulderAbd": 0x4B, "LeftElbowFlex": 0x4C, "LeftUpperArmRoll": 0x4D,
    "LeftShoulderAbd": 0x4F, "RightWristFlex": 0x50, "RightWristRoll": 0x52, "LeftWristFlex": 0x54,
    "LeftWristRoll": 0x56, "RightShoulderExt": 0x5B, "TorsoPan": 0x5C, "LeftShoulderExt": 0x5F,
}  # fmt: skip
ORIGINAL_DOUBLES = {"MDS_CAN_TIMEOUT_DEFAULT": 0.00018, "MDS_LOOP_PERIOD": 0.1, "MDS_STARTUP_SEND_REF_DELAY": 0.8}
ORIGINAL_CHANNELS = {
    "MDS_CHAN_REF_NAME": "mds-ref", "MDS_CHAN_BOARD_CMD_NAME": "mds-cmd", "MDS_CHAN_PARAM_NAME": "mds-param",
    "MDS_CHAN_IK_NAME": "mds-ik", "MDS_CHAN_COLLIDE_NAME": "mds-collide", "MDS_CHAN_CAN_DAEMON_NAME": "mds-can-daemon",
    "MDS_CHAN_STATE_NAME": "mds-state", "MDS_CHAN_REF_FILTER_NAME": "mds-ref-filter",
    "MDS_CHAN_VIRTUAL_TO_SIM_NAME": "mds-virtual-to-sim", "MDS_CHAN_VIRTUAL_FROM_SIM_NAME": "mds-virtual-from-sim",
}  # fmt: skip
ORIGINAL_JOINT_NAMES = ["WST", "NKY", "NK1", "NK2", "LSP", "LSR", "LSY", "LEB", "LWY", "LWR", "LWP", "RSP", "RSR",
                        "RSY", "REB", "RWY", "RWR", "RWP", "N/A", "LHY", "LHR", "LHP", "LKN", "LAP", "LAR", "N/A",
                        "RHY", "RHR", "RHP", "RKN", "RAP", "RAR", "RF1", "RF2", "RF3", "RF4", "RF5", "LF1", "LF2",
                        "LF3", "LF4", "LF5"]


@pytest.mark.parametrize(("compiler", "std"), [("gcc", "gnu99"), ("gcc", "c11"), ("g++", "c++11")])
def test_every_name_of_the_original_header_with_its_value(tmp_path: Path, compiler: str, std: str) -> None:
    """Issue #18 §3: what the original mds.h gave its clients is here under the same names with the same values:
    the guard, <ach.h> and the libc headers (used below without including them), the constants, the channel
    names, jointNames[], the ref-mode enum, the typedefs and the struct tags."""
    body = ["#ifndef MDS_PRIMARY_H", "#error MDS_PRIMARY_H", "#endif"]
    body += ["int main(void) {"]
    body += [f'    printf("{k} %ld\\n", (long)({k}));' for k in ORIGINAL_INTS]
    body += [f'    printf("{k} %.17g\\n", (double)({k}));' for k in ORIGINAL_DOUBLES]
    body += [f'    printf("{k} %s\\n", {k});' for k in ORIGINAL_CHANNELS]
    body += ['    for (int i = 0; i < MDS_JOINT_COUNT; i++) printf("jointNames %d %s\\n", i, jointNames[i] ? '
             'jointNames[i] : "(null)");']
    # libc and libach through mds.h alone, as the original's clients used them
    body += ["    ach_channel_t chan; memset(&chan, 0, sizeof chan); (void)chan;",
             "    (void)sizeof(&ach_open); (void)sizeof(&ach_get); (void)sizeof(&ach_put); /* declared, not linked */",
             "    enum ach_status st0 = ACH_OK; (void)st0;",
             "    struct mds_ref ref; mds_ref_t *r = &ref; r->joint[LEP].ref = -0.2; (void)r;",
             "    struct mds_state st; struct mds_joint_state *js = &st.joint[LSP]; (void)js;",
             "    struct mds_ik ik; struct mds_ik_arm *arm = &ik.arm[LEFT]; arm->ik_method = IK3; (void)arm;",
             "    struct mds_joint_param p; struct mds_jnt_param *jp = &p.joint[RSP]; (void)jp;",
             "    struct mds_collide c; struct mds_jnt_collide *jc = &c.joint[COLLISION_L_HAND]; (void)jc;",
             "    struct mds_power pw; (void)pw; bool ok = TRUE; assert(ok); (void)isdigit('1'); (void)getpid();",
             "    int mode = MDS_REF_MODE_REF; (void)mode; (void)sqrt(2.0); (void)strlen(\"x\"); (void)errno;",
             '    printf("%" PRId16 "\\n", (int16_t)0);',
             "    return 0;", "}"]
    prog = "#include <stdio.h>\n#include \"mds.h\"\n" + "\n".join(body) + "\n"
    out = _compile_and_run(tmp_path, prog, compiler=compiler, std=std).splitlines()
    values = dict(line.split(" ", 1) for line in out if not line.startswith("jointNames") and " " in line)
    assert {k: int(values[k]) for k in ORIGINAL_INTS} == ORIGINAL_INTS
    assert {k: float(values[k]) for k in ORIGINAL_DOUBLES} == ORIGINAL_DOUBLES
    assert {k: values[k] for k in ORIGINAL_CHANNELS} == ORIGINAL_CHANNELS
    names = [line.split(" ", 2)[2] for line in out if line.startswith("jointNames")]
    assert names == ORIGINAL_JOINT_NAMES + ["(null)"] * (100 - len(ORIGINAL_JOINT_NAMES))


def test_bytes_written_in_c_decode_in_python(tmp_path: Path) -> None:
    """A C program fills a state and an IK request; Python must read the same values from the bytes."""
    prog = r"""
#include <stdio.h>
#include <string.h>
#include "mds.h"
int main(void) {
    mds_state_t s;
    mds_ik_t ik;
    memset(&s, 0, sizeof s);
    memset(&ik, 0, sizeof ik);
    s.joint[MDS_JOINT_LSP].pos = 0.25;
    s.joint[MDS_JOINT_LSP].ref_c_send = -1.5;
    s.joint[MDS_JOINT_LSP].address = MDS_JOINT_LSP;
    strcpy(s.joint[MDS_JOINT_LSP].nameshort, "LSP");
    s.joint[MDS_JOINT_NKR].homed = 1;
    s.collide.joint[MDS_COLLIDE_R_WRIST].isCollide = 1;
    s.collide.time_dt = 0.125;
    s.power.voltage = 24.0;
    s.time = 1234.5;
    s.refWait = 7;
    ik.arm[MDS_LEFT].t_x = 0.3;
    ik.arm[MDS_LEFT].r_z = -0.5;
    ik.arm[MDS_LEFT].ik_method = 3;
    ik.move = MDS_LEFT;
    fwrite(&s, sizeof s, 1, stdout);
    fwrite(&ik, sizeof ik, 1, stdout);
    return 0;
}
"""
    exe = tmp_path / "writer"
    src = tmp_path / "writer.c"
    src.write_text(prog)
    subprocess.run(["gcc", "-std=c11", "-Wall", "-Werror", *include_flags(), str(src), "-o", str(exe)], check=True)
    raw = subprocess.run([str(exe)], capture_output=True, check=True).stdout
    n_state = ctypes.sizeof(msgs.MDS_STATE)
    assert len(raw) == n_state + ctypes.sizeof(msgs.MDS_IK)
    state = msgs.MDS_STATE.from_bytes(raw[:n_state])
    ik = msgs.MDS_IK.from_bytes(raw[n_state:])
    lsp = state.joint[mds.LSP]
    assert (lsp.pos, lsp.ref_c_send, lsp.address) == (0.25, -1.5, 0x5F)
    assert msgs.get_name(lsp.nameshort) == "LSP"
    assert state.joint[joints.BY_SHORT["NKR"].address].homed == 1
    assert state.collide.joint[mds.COLLIDE_R_WRIST].isCollide == 1
    assert (state.collide.time_dt, state.power.voltage, state.time, state.refWait) == (0.125, 24.0, 1234.5, 7)
    arm = ik.arm[mds.LEFT]
    assert (arm.t_x, arm.r_z, arm.ik_method, ik.move) == (0.3, -0.5, 3, mds.LEFT)


def test_constants_agree_with_python(tmp_path: Path) -> None:
    channels = [k for k, v in vars(mds).items() if k.startswith("MDS_CHAN_") and k.endswith("_NAME")]
    assert set(mds.ALL_CHANNELS) <= {getattr(mds, k) for k in channels}
    ints = {
        "MDS_JOINT_COUNT": mds.MDS_JOINT_COUNT,
        "MDS_ARM_COUNT": mds.MDS_ARM_COUNT,
        "MDS_COLLIDE_JNT_NUM": mds.MDS_COLLIDE_JNT_NUM,
        "MDS_CHAR_PARAM_BUFFER_SIZE": mds.MDS_CHAR_PARAM_BUFFER_SIZE,
        "MDS_REF_FILTER_LENGTH": mds.MDS_REF_FILTER_LENGTH,
        "MDS_CHANNEL_FRAME_COUNT": mds.CHANNEL_FRAME_COUNT,
        "MDS_CHANNEL_FRAME_SIZE": mds.CHANNEL_FRAME_SIZE,
        "MDS_RIGHT": mds.RIGHT,
        "MDS_LEFT": mds.LEFT,
        "RIGHT": mds.RIGHT,
        "LEFT": mds.LEFT,
        "MDS_NODE_COUNT": len(joints.JOINTS),
        "MDS_MODEL_JOINTS_COUNT": len(joints.MODEL_JOINTS),
    }
    for prefix in ("MDS_REF_MODE_", "MDS_CMD_"):
        ints.update({k: v for k, v in vars(mds).items() if k.startswith(prefix) and type(v) is int})
    ints.update({"MDS_MUX_MAX_CONTROLLERS": mux_state.MUX_MAX_CONTROLLERS, "MDS_MUX_NO_OWNER": mux_state.MUX_NO_OWNER,
                 "MDS_IK_MESSAGE_SIZE": ik_status.IK_MESSAGE_SIZE})
    ints.update({"MDS_" + k: v for k in ("IK_SOLVED", "IK_UNREACHABLE", "IK_BAD_REQUEST", "IK_NOT_READY")
                 for v in (getattr(ik_status, k),)})
    ints.update({"MDS_DAEMON_" + k: v for k, v in vars(daemon_status).items()
                 if k.startswith(("BUS_STATE_", "CMD_", "JOINT_")) and type(v) is int})
    ints.update({"MDS_" + k: v for k, v in vars(mds).items() if k.startswith("COLLIDE_") and type(v) is int})
    for j in joints.JOINTS:
        ints[f"MDS_JOINT_{j.short}"] = j.address
        ints[f"MDS_JOINT_{cheader.snake_upper(j.name)}"] = j.address
    for short in cheader.LEGACY_BARE_JOINTS:  # the original's bare macros, short and long
        ints[short] = getattr(mds, short)
        ints[joints.BY_SHORT[short].name] = getattr(mds, short)
    body = [f'    printf("{k} %s\\n", {k});' for k in channels]
    body += [f'    printf("{k} %ld\\n", (long)({k}));' for k in ints]
    body.append('#define ROW(addr, s, l) printf("table %d %s %s\\n", addr, #s, #l);')
    body.append("    MDS_JOINT_TABLE(ROW)")
    body.append("    { int model[] = MDS_MODEL_JOINTS; for (int i = 0; i < MDS_MODEL_JOINTS_COUNT; i++)")
    body.append('        printf("model %d %d\\n", i, model[i]); }')
    body.append("    { int arm[] = MDS_LEFT_ARM_JOINTS; for (int i = 0; i < MDS_LEFT_ARM_JOINTS_COUNT; i++)")
    body.append('        printf("left %d %d\\n", i, arm[i]); }')
    prog = "#include <stdio.h>\n#include \"mds.h\"\nint main(void) {\n" + "\n".join(body) + "\n    return 0;\n}\n"
    out = _compile_and_run(tmp_path, prog).splitlines()
    got_text = dict(line.split(" ", 1) for line in out if line.startswith("MDS_CHAN_"))
    assert got_text == {k: getattr(mds, k) for k in channels}
    assert {got_text[c.macro] for c in contracts.CHANNELS} == set(contracts.ALL_CHANNELS)
    assert all(got_text[c.macro] == c.name for c in contracts.CHANNELS)
    got_int = {k: int(v) for k, v in (line.split(" ", 1) for line in out) if k in ints}
    assert got_int == ints
    table = [tuple(line.split()[1:]) for line in out if line.startswith("table ")]
    assert table == [(str(j.address), j.short, j.name) for j in joints.JOINTS]
    model = [int(line.split()[2]) for line in out if line.startswith("model ")]
    assert model == [joints.BY_SHORT[s].address for s in joints.MODEL_JOINTS]
    left = [int(line.split()[2]) for line in out if line.startswith("left ")]
    assert left == [joints.BY_SHORT[s].address for s in joints.LEFT_ARM]


def test_legacy_macro_clash_is_a_compile_error(tmp_path: Path) -> None:
    src = tmp_path / "clash.c"
    src.write_text('#define LSP 4\n#include "mds.h"\nint main(void) { return 0; }\n')
    res = subprocess.run(["gcc", "-std=c11", *include_flags(), "-fsyntax-only", str(src)], capture_output=True,
                         text=True)
    assert res.returncode != 0
    assert "LSP is already a macro" in res.stderr and "MDS_NO_LEGACY_MACROS" in res.stderr


def test_legacy_macros_can_be_left_out(tmp_path: Path) -> None:
    prog = (
        "#define LSP 4\n#define MDS_NO_LEGACY_MACROS\n#include <stdio.h>\n#include \"mds.h\"\n"
        "#ifdef LEFT\n#error LEFT must not be defined\n#endif\n"
        'int main(void) { printf("%d %d\\n", LSP, MDS_JOINT_LSP); return 0; }\n'
    )
    assert _compile_and_run(tmp_path, prog).split() == ["4", str(mds.LSP)]


def test_generator_refuses_platform_sized_fields() -> None:
    """A pointer-sized field (different on 32/64-bit) has no place in a wire struct."""

    class Bad(ctypes.LittleEndianStructure):
        _pack_ = 1
        _fields_ = [("x", ctypes.c_void_p)]

    with pytest.raises(TypeError, match="fixed-width"):
        cheader._struct(Bad)
