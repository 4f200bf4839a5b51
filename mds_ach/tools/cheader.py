"""Generate ``include/mds.h`` for C/C++ clients from the Python definitions (the one source of truth).

The channels (names, structs, writers and readers) come from the contracts registry
(:mod:`mds_ach.robot.contracts`), the packed structs from the ctypes layouts in :mod:`mds_ach.robot.msgs`
(every struct a channel carries, nested ones first), the constants from :mod:`mds_ach` and the message modules,
and the joint table from :mod:`mds_ach.robot.joints`, so the C header cannot drift from what the Python nodes
put on the channels. ``python -m mds_ach.tools.cheader`` rewrites the committed header;
``--check`` exits 1 if it is out of date; test/test_cheader.py compiles it and compares every
``sizeof``/``offsetof`` with ctypes.
"""

from __future__ import annotations

import argparse
import ctypes
import re
import sys
import textwrap
from pathlib import Path
from typing import Any

import mds_ach as mds
from mds_ach.robot import contracts, joints, legacy_names, msgs
from mds_ach.robot.msgs import daemon_status, hold, ik_status, legacy, limits, mux_state

HEADER_PATH = Path(__file__).resolve().parents[2] / "include" / "mds.h"

# Every struct a registered channel carries, in dependency order (nested ones first), as C needs them.
STRUCTS: tuple[type[ctypes.Structure], ...] = contracts.wire_structs()

# Fixed-width C spelling of every ctypes scalar the structs use (float and double: IEEE 754 binary32/64 on every
# platform MDS runs on). Anything else (pointers, long double, bools) is refused. ctypes aliases c_int/c_long to
# these on Linux, so they come out fixed-width too.
_SCALARS: dict[type, str] = {
    ctypes.c_double: "double",
    ctypes.c_float: "float",
    ctypes.c_int8: "int8_t",
    ctypes.c_uint8: "uint8_t",
    ctypes.c_int16: "int16_t",
    ctypes.c_uint16: "uint16_t",
    ctypes.c_int32: "int32_t",
    ctypes.c_uint32: "uint32_t",
    ctypes.c_int64: "int64_t",
    ctypes.c_uint64: "uint64_t",
    ctypes.c_char: "char",
}

# Array lengths are written with their mds.h macro so C code reads like the original header.
_LENGTH_MACROS: dict[int, str] = {
    msgs.MDS_JOINT_COUNT: "MDS_JOINT_COUNT",
    msgs.MDS_COLLIDE_JNT_NUM: "MDS_COLLIDE_JNT_NUM",
    msgs.MDS_ARM_COUNT: "MDS_ARM_COUNT",
    msgs.MDS_CHAR_PARAM_BUFFER_SIZE: "MDS_CHAR_PARAM_BUFFER_SIZE",
    mux_state.MUX_MAX_CONTROLLERS: "MDS_MUX_MAX_CONTROLLERS",
    ik_status.IK_MESSAGE_SIZE: "MDS_IK_MESSAGE_SIZE",
    hold.HOLD_REASON_SIZE: "MDS_HOLD_REASON_SIZE",
    mux_state.MUX_HOLD_REASON_SIZE: "MDS_MUX_HOLD_REASON_SIZE",
    limits.LIMITS_SOURCE_SIZE: "MDS_LIMITS_SOURCE_SIZE",
}

# The 13 joints the original mds.h named with bare macros (``#define LSP 0x005f`` and the long name).
LEGACY_BARE_JOINTS: tuple[str, ...] = (
    "REP", "RSY", "RSR", "LEP", "LSY", "LSR", "RWR", "RWY", "LWR", "LWY", "RSP", "WST", "LSP",
)  # fmt: skip


# What the original mds.h included before <ach.h>, in its order (its clients call libc through it).
ORIGINAL_LIBC_HEADERS: tuple[str, ...] = (
    "stdint.h", "time.h", "string.h", "pthread.h", "sys/stat.h", "sys/types.h", "errno.h", "fcntl.h", "assert.h",
    "unistd.h", "ctype.h", "stdbool.h", "math.h", "inttypes.h",
)  # fmt: skip


def c_type_name(cls: type[ctypes.Structure]) -> str:
    """``MDS_JOINT_STATE`` -> ``mds_joint_state_t`` (the original C typedef names)."""
    return cls.__name__.lower() + "_t"


def snake_upper(name: str) -> str:
    """``LeftShoulderExt`` -> ``LEFT_SHOULDER_EXT`` for the prefixed long-name macros."""
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", name).upper()


def _c_field(name: str, ctype: Any) -> str:
    """One struct member declaration; arrays keep their macro length."""
    dims: list[str] = []
    while issubclass(ctype, ctypes.Array):
        dims.append(_LENGTH_MACROS.get(ctype._length_, str(ctype._length_)))
        ctype = ctype._type_
    if issubclass(ctype, ctypes.Structure):
        base = c_type_name(ctype)
    elif ctype in _SCALARS:
        base = _SCALARS[ctype]
    else:
        raise TypeError(f"field {name!r}: {ctype.__name__} has no fixed-width C type; use c_int16 etc.")
    return f"{base} {name}" + "".join(f"[{d}]" for d in dims) + ";"


_FIELD_DOC = re.compile(r"^\s*(\w+)(?:\[[^\]]*\])?\s{2,}(\S.*)$")


def _field_docs(cls: type) -> dict[str, str]:
    """Field descriptions from a docstring's table (``name[i]    what it is`` lines after the summary)."""
    _summary, _, rest = (cls.__doc__ or "").partition("\n\n")
    found = (_FIELD_DOC.match(line) for line in rest.splitlines())
    return {m.group(1): m.group(2).replace("``", "").strip() for m in found if m}


def _doc(cls: type) -> list[str]:
    """The docstring's summary (its first paragraph) as a C comment, without reST markup, wrapped to 100
    columns; a field table after it goes to the members (``_field_docs``)."""
    summary = (cls.__doc__ or "").partition("\n\n")[0]
    text = " ".join(summary.replace("``", "").split())
    wrapped = textwrap.wrap(text, 96)
    if not wrapped:
        return []
    if len(wrapped) == 1:
        return [f"/* {wrapped[0]} */"]
    return ["/* " + wrapped[0], *(f"   {w}" for w in wrapped[1:-1]), f"   {wrapped[-1]} */"]


def _struct(cls: type[ctypes.Structure]) -> list[str]:
    tag = cls.__name__.lower()
    size = ctypes.sizeof(cls)
    lines = [*_doc(cls), f"typedef struct MDS_PACKED {tag} {{"]
    docs = _field_docs(cls)
    for name, ctype, *_ in cls._fields_:
        offset = getattr(cls, name).offset
        what = f" {docs[name]}" if name in docs else ""
        lines.append(f"    {_c_field(name, ctype):<52} /* @{offset}{what} */")
    lines.append(f"}} {c_type_name(cls)};")
    lines.append(f'MDS_STATIC_ASSERT(sizeof({c_type_name(cls)}) == {size}, "{c_type_name(cls)} must be {size} bytes");')
    return lines


def _module_constants(prefix: str, suffix: str = "", kind: type = int, module: object = mds) -> list[tuple[str, Any]]:
    """Public constants of ``module`` (default ``mds_ach``) named ``prefix...suffix`` of the given type, in
    definition order."""
    return [
        (k, v)
        for k, v in vars(module).items()
        if k.startswith(prefix) and k.endswith(suffix) and type(v) is kind
    ]


def _channel_section() -> list[str]:
    """One macro per registered channel, with its struct, writers and readers (the contracts registry)."""
    out = [
        "/* ---- Ach channels (all made with MDS_CHANNEL_FRAME_COUNT frames of MDS_CHANNEL_FRAME_SIZE bytes) ---- */",
        f"#define MDS_CHANNEL_FRAME_COUNT {contracts.CHANNEL_FRAME_COUNT}",
        f"#define MDS_CHANNEL_FRAME_SIZE {contracts.CHANNEL_FRAME_SIZE}",
    ]
    for c in contracts.CHANNELS:
        if (c.frame_count, c.frame_size) != (contracts.CHANNEL_FRAME_COUNT, contracts.CHANNEL_FRAME_SIZE):
            raise ValueError(f"{c.name}: channels of their own geometry need a macro pair here")
        origin = "" if c.legacy else ", new"
        only = ", stack only" if c.stack_only else ""
        out.append(f"/* {c_type_name(c.struct)}{origin}{only}: {c.purpose}. */")
        out.append(f"/*   written by {', '.join(c.writers)}; read by {', '.join(c.readers)} */")
        out.append(f'#define {c.macro} "{contracts.base_name(c.name)}"')
    daemon_input = contracts.BY_NAME[contracts.MDS_CHAN_DAEMON_INPUT_NAME].macro
    out.append("/* What the daemon executes: the collision gate's output, only the stack's user writes it.")
    out.append("   Legacy clients write MDS_CHAN_REF_NAME (\"mds-ref\"): the mux's 'direct' input, limit-checked")
    out.append("   and collision-gated. */")
    out.append(f"#define MDS_CHAN_DAEMON_INPUT_NAME {daemon_input}")
    out.append("/* Names the original header declared for channels nothing made or used (kept for its clients; no")
    out.append("   channel of that name exists), and the original mds_ach.py's spelling of MDS_CHAN_COLLIDE_NAME. */")
    for name in ("MDS_CHAN_CAN_DAEMON_NAME", "MDS_CHAN_VIRTUAL_TO_SIM_NAME", "MDS_CHAN_VIRTUAL_FROM_SIM_NAME",
                 "MDS_CHAN_COLLLIDE_NAME"):
        out.append(f'#define {name} "{contracts.base_name(getattr(legacy_names, name))}"')
    return out


def _enum(tag: str, doc: str, items: list[tuple[str, int]]) -> list[str]:
    body = [f"    {name} = {value}," for name, value in items]
    return [f"/* {doc} */", f"typedef enum {tag} {{", *body, f"}} {tag}_t;"]


def _joint_section() -> list[str]:
    out = [
        "/* ---- joints: the array index of every struct is the CAN node address ---- */",
        f"/* MDS_JOINT_<short> and MDS_JOINT_<LONG_NAME>: the address of each of the {len(joints.JOINTS)} nodes. */",
        "typedef enum mds_joint_address {",
    ]
    names: set[str] = set()
    for j in joints.JOINTS:
        short, long = f"MDS_JOINT_{j.short}", f"MDS_JOINT_{snake_upper(j.name)}"
        if short in names or long in names or short == long:
            raise ValueError(f"joint macro {short} or {long} would be defined twice")
        names.update((short, long))
        out.append(f"    {short:<16} = 0x{j.address:02x},  {long} = 0x{j.address:02x},")
    out.append("} mds_joint_address_t;")
    out.append(f"#define MDS_NODE_COUNT {len(joints.JOINTS)}")
    out.append("")
    out.append("/* X-macro over the node table: X(address, short, LongName), e.g. to build a name lookup.")
    out.append("   Use the names with # or ## in X: the legacy bare macros below would expand them otherwise. */")
    rows = [f"    X(0x{j.address:02x}, {j.short}, {j.name})" for j in joints.JOINTS]
    out.append("#define MDS_JOINT_TABLE(X) \\")
    out.append(" \\\n".join(rows))
    out.append("")
    out.append("/* Joint groups as initialiser lists of addresses; MDS_MODEL_JOINTS is the URDF and")
    out.append("   /joint_states order, the arms are in IK order (SP, SR, SY, EP, WY, WR). */")
    for macro, group in (
        ("MDS_MODEL_JOINTS", joints.MODEL_JOINTS),
        ("MDS_LEFT_ARM_JOINTS", joints.LEFT_ARM),
        ("MDS_RIGHT_ARM_JOINTS", joints.RIGHT_ARM),
        ("MDS_NECK_JOINTS", joints.NECK),
    ):
        out.append(f"#define {macro}_COUNT {len(group)}")
        items = ", ".join(f"MDS_JOINT_{s}" for s in group)
        out.append(f"#define {macro} {{ \\\n    {items} }}" if len(items) > 90 else f"#define {macro} {{ {items} }}")
    return out


def _legacy_macros() -> list[str]:
    """The original header's bare names, last in the file so they cannot touch anything above."""
    out = [
        "/* ---- legacy bare names of the original mds.h: RIGHT/LEFT, the 13 arm and torso joints by short and",
        "   long name (#define LSP 0x005f), IK1..IK6 (the original wrote them malformed, `#define IK1 = 1`),",
        "   COLLISION_*, TRUE/FALSE, MAX_SAFE_STACK and jointNames[]. They are common words, so define",
        "   MDS_NO_LEGACY_MACROS before including mds.h to leave them out; a clash with an existing",
        "   macro is a compile error rather than a silent redefinition. ---- */",
        "#ifndef MDS_NO_LEGACY_MACROS",
    ]
    bare: list[tuple[str, str, str]] = [("RIGHT", str(mds.RIGHT), "MDS_RIGHT"), ("LEFT", str(mds.LEFT), "MDS_LEFT")]
    for short in LEGACY_BARE_JOINTS:
        j = joints.BY_SHORT[short]
        bare += [(name, f"0x{j.address:04x}", f"MDS_JOINT_{j.short}") for name in (j.short, j.name)]
    bare += [(f"IK{n}", str(getattr(legacy_names, f"IK{n}")), f"the number {n}") for n in range(1, 7)]
    bare += [(k, str(v), "MDS_" + k.replace("COLLISION_", "COLLIDE_"))
             for k, v in _module_constants("COLLISION_", module=legacy_names)]
    for name, value, modern in bare:
        out += [
            f"#ifdef {name}",
            f'#error "mds.h: {name} is already a macro; define MDS_NO_LEGACY_MACROS and use {modern}"',
            "#endif",
            f"#define {name} {value}",
        ]
    out.append("/* Generic names other headers define too (glib's TRUE, the RT examples' MAX_SAFE_STACK): theirs")
    out.append("   win. */")
    generic: tuple[tuple[str, int], ...] = (("TRUE", legacy_names.TRUE), ("FALSE", legacy_names.FALSE),
                                            ("MAX_SAFE_STACK", legacy_names.MAX_SAFE_STACK))
    for generic_name, generic_value in generic:
        out += [f"#ifndef {generic_name}", f"#define {generic_name} {generic_value}", "#endif"]
    out.append("/* The original's jointNames[]: a Hubo leftover, 42 names indexed 0..41 (NOT by CAN address; use")
    out.append("   MDS_JOINT_TABLE for the MDS names). */")
    names = legacy_names.HUBO_JOINT_NAMES
    rows = [", ".join(f'"{n}"' for n in names[i:i + 11]) for i in range(0, len(names), 11)]
    out.append("static const char *jointNames[MDS_JOINT_COUNT] MDS_UNUSED = {")
    out += [f"    {r}," if i < len(rows) - 1 else f"    {r}}};" for i, r in enumerate(rows)]
    out.append("#endif /* MDS_NO_LEGACY_MACROS */")
    return out


def generate() -> str:
    """The complete text of include/mds.h."""
    out: list[str] = [
        "/* mds.h -- C/C++ interface to the MDS-Ach channels (packed structs, channel names, joints).",
        " *",
        " * GENERATED by `python -m mds_ach.tools.cheader` from mds_ach/robot/contracts.py (channels),",
        " * mds_ach/robot/msgs/ (structs), mds_ach/__init__.py and mds_ach/robot/joints.py. Do not edit by hand:",
        " * change the Python definitions and regenerate (test/test_cheader.py fails while this file is out of date).",
        " *",
        " * Layouts are byte-packed, little-endian (x86-64 / aarch64), identical to the original",
        " * MDS-Ach develop-branch mds.h. Arrays of joints are indexed by CAN node address.",
        " * Link your program with -lach and ach_put()/ach_get() these structs on the named channels.",
        " *",
        " * Like the original it includes <ach.h> (the project's libach: `pkg-config --cflags --libs ach`) and the",
        " * libc headers the original included, so the original clients build unchanged; define MDS_NO_ACH",
        " * before including it to leave <ach.h> out (e.g. to decode recorded frames without libach).",
        " */",
        "#ifndef MDS_PRIMARY_H /* the original header's guard */",
        "#define MDS_PRIMARY_H",
        "#define MDS_H",
        "",
        *[f"#include <{h}>" for h in ORIGINAL_LIBC_HEADERS],
        "#ifndef MDS_NO_ACH",
        "#include <ach.h>",
        "#endif",
        "",
        "#if defined(__GNUC__) || defined(__clang__)",
        "#define MDS_PACKED __attribute__((packed))",
        "#define MDS_UNUSED __attribute__((unused))",
        "#else",
        '#error "mds.h needs __attribute__((packed)) (gcc or clang)"',
        "#endif",
        "#if defined(__cplusplus)",
        "#define MDS_STATIC_ASSERT(cond, msg) static_assert(cond, msg)",
        "#elif defined(__STDC_VERSION__) && __STDC_VERSION__ >= 201112L",
        "#define MDS_STATIC_ASSERT(cond, msg) _Static_assert(cond, msg)",
        "#else /* C99: a negative array size fails the build just the same */",
        "#define MDS_STATIC_ASSERT(cond, msg) extern char mds_static_assert_[(cond) ? 1 : -1]",
        "#endif",
        "",
        "/* ---- sizes and timing ---- */",
        f"#define MDS_JOINT_COUNT {msgs.MDS_JOINT_COUNT}  /* array length = highest CAN address + 1 */",
        f"#define MDS_ARM_COUNT {msgs.MDS_ARM_COUNT}",
        f"#define MDS_COLLIDE_JNT_NUM {msgs.MDS_COLLIDE_JNT_NUM}",
        f"#define MDS_CHAR_PARAM_BUFFER_SIZE {msgs.MDS_CHAR_PARAM_BUFFER_SIZE}",
        f"#define MDS_MUX_MAX_CONTROLLERS {mux_state.MUX_MAX_CONTROLLERS}  /* mds_mux_state_t per-controller arrays */",
        f"#define MDS_IK_MESSAGE_SIZE {ik_status.IK_MESSAGE_SIZE}  /* mds_ik_status_t.message, NUL included */",
        f"#define MDS_HOLD_REASON_SIZE {hold.HOLD_REASON_SIZE}  /* mds_hold_t.reason, NUL included */",
        f"#define MDS_MUX_HOLD_REASON_SIZE {mux_state.MUX_HOLD_REASON_SIZE}  /* mds_mux_state_t.hold_reason, NUL "
        f"included */",
        f"#define MDS_LIMITS_SOURCE_SIZE {limits.LIMITS_SOURCE_SIZE}  /* mds_limits_t.source, NUL included */",
        f"#define MDS_LOOP_PERIOD {mds.MDS_LOOP_PERIOD!r}  /* s, default daemon period */",
        f"#define MDS_REF_FILTER_LENGTH {mds.MDS_REF_FILTER_LENGTH}",
        "/* Declared by the original header and used by nothing (kept for its clients). */",
        f"#define MDS_CAN_CHAN_NUM {legacy_names.MDS_CAN_CHAN_NUM}",
        f"#define MDS_CAN_TIMEOUT_DEFAULT {legacy_names.MDS_CAN_TIMEOUT_DEFAULT!r}  /* s */",
        f"#define MDS_CAN_BUFFER_CLEAR_I {legacy_names.MDS_CAN_BUFFER_CLEAR_I}",
        f"#define MDS_STARTUP_SEND_REF_DELAY {legacy_names.MDS_STARTUP_SEND_REF_DELAY!r}  /* s */",
        "#ifdef __cplusplus",
        'extern "C" {',
        "#endif",
        "extern int mds_debug; /* declared by the original header; define it if you use it */",
        "#ifdef __cplusplus",
        "}",
        "#endif",
        "",
    ]
    out += _channel_section()
    out.append("")
    out += _enum("mds_arm", "Arm index of mds_ik_t.arm[] and mds_ik_t.move.", [
        ("MDS_RIGHT", mds.RIGHT), ("MDS_LEFT", mds.LEFT),
    ])  # fmt: skip
    out.append("")
    out += _enum("mds_ref_mode", "mds_joint_ref_t.mode (the field itself is int16_t).",
                 _module_constants("MDS_REF_MODE_", module=legacy))  # fmt: skip
    out.append("")
    out += _enum("mds_collide_part", "Index into mds_collide_t.joint[].",
                 [("MDS_" + k, v) for k, v in _module_constants("COLLIDE_")])  # fmt: skip
    out.append("")
    out += _enum("mds_cmd_code", "mds_cmd_t.cmd on MDS_CHAN_BOARD_CMD_NAME (address 0 = every enabled joint).",
                 _module_constants("MDS_CMD_"))  # fmt: skip
    out.append("")
    out += _joint_section()
    out.append("")
    out.append("/* ---- mds_daemon_status_t (MDS_CHAN_DAEMON_STATUS_NAME): version and joint_flags[] bits ---- */")
    out.append(f"#define MDS_DAEMON_STATUS_VERSION {daemon_status.DAEMON_STATUS_VERSION}")
    out += [f"#define MDS_DAEMON_{k} 0x{v:04x}" for k, v in vars(daemon_status).items()
            if k.startswith("JOINT_") and type(v) is int]
    out += _enum("mds_daemon_bus_state", "mds_daemon_status_t.bus_state.",
                 [("MDS_DAEMON_" + k, v) for k, v in _module_constants("BUS_STATE_", module=daemon_status)])
    out += _enum("mds_daemon_cmd_result", "mds_daemon_status_t.cmd_result (for the command cmd_seq names).",
                 [("MDS_DAEMON_" + k, v) for k, v in _module_constants("CMD_", module=daemon_status)])
    out.append("")
    out.append("/* ---- mds_ik_status_t (MDS_CHAN_IK_STATE_NAME): one answer per mds-ik request ---- */")
    out += _enum("mds_ik_status_code", "mds_ik_status_t.status.",
                 [("MDS_" + k, v) for k, v in _module_constants("IK_", module=ik_status)
                  if k not in ("IK_MESSAGE_SIZE",)])
    out.append("")
    out.append("/* ---- mds_mux_state_t (MDS_CHAN_MUX_STATE_NAME) ---- */")
    out.append(f"#define MDS_MUX_NO_OWNER ({mux_state.MUX_NO_OWNER})  /* owner[] of a joint nobody owns */")
    out += _enum("mds_mux_held", "mds_mux_state_t.held[].",
                 [("MDS_" + k, v) for k, v in _module_constants("MUX_", module=mux_state)
                  if k in ("MUX_FREE", "MUX_HELD", "MUX_CANCELLED")])
    out += _enum("mds_mux_verdict", "mds_mux_state_t.verdict[]: what the mux did with a controller's newest frame.",
                 [("MDS_MUX_" + k, v) for k, v in _module_constants("VERDICT_", module=mux_state)
                  if k != "VERDICT_NAMES"])
    out += _enum("mds_mux_hold_status", "mds_mux_state_t.hold_status.",
                 [("MDS_" + k, v) for k, v in _module_constants("MUX_HOLD_", module=mux_state)
                  if k != "MUX_HOLD_REASON_SIZE"])
    out.append("")
    out.append("/* ---- mds_hold_t (MDS_CHAN_HOLD_NAME): hold / resume / cancel requests to the mux ---- */")
    out += _enum("mds_hold_action", "mds_hold_t.action.",
                 [("MDS_" + k, v) for k, v in _module_constants("HOLD_", module=hold)
                  if k not in ("HOLD_REASON_SIZE", "HOLD_ACTIONS")])
    out.append("")
    out.append("/* ---- packed wire structs (byte offsets in the comments) ---- */")
    for cls in STRUCTS:
        out += _struct(cls)
        out.append("")
    out += _legacy_macros()
    out.append("")
    out.append("#endif /* MDS_PRIMARY_H */")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m mds_ach.tools.cheader",
        description="Write include/mds.h (C structs, channel names, joints) from the Python definitions.",
    )
    ap.add_argument("-o", "--output", type=Path, default=HEADER_PATH, help="where to write (default: %(default)s)")
    ap.add_argument("--check", action="store_true", help="do not write; exit 1 if the file differs")
    ap.add_argument("--stdout", action="store_true", help="print the header instead of writing it")
    args = ap.parse_args(argv)
    text = generate()
    if args.stdout:
        sys.stdout.write(text)
        return 0
    if args.check:
        current = args.output.read_text() if args.output.exists() else ""
        if current != text:
            print(f"{args.output} is out of date; run: python -m mds_ach.tools.cheader", file=sys.stderr)
            return 1
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
