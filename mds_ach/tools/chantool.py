"""``mds-ach make | rm | dump``: create, remove and inspect the MDS Ach channels from a shell.

Exit codes a script can rely on: 0 success, 1 a runtime failure (message on stderr naming the channel and the
problem), 2 a usage error (argparse).
"""

from __future__ import annotations

import argparse
import ctypes
import sys
from collections.abc import Callable
from typing import Any

import mds_ach as mds
from mds_ach import ach
from mds_ach.argtypes import seconds
from mds_ach.robot import contracts
from mds_ach.robot.channels import make_channels
from mds_ach.robot.joints import BY_ADDRESS
from mds_ach.robot.msgs import (
    MDS_CMD,
    MDS_COLLIDE,
    MDS_DAEMON_STATUS,
    MDS_IK,
    MDS_IK_STATUS,
    MDS_JOINT_COUNT,
    MDS_JOINT_PARAM,
    MDS_MUX_STATE,
    MDS_REF,
    MDS_STATE,
    get_name,
    ik_status,
)
from mds_ach.robot.msgs import daemon_status as ds

PROG = "mds-ach"


def _err(verb: str, message: str) -> None:
    print(f"{PROG} {verb}: {message}", file=sys.stderr)


# --- make -------------------------------------------------------------------------------------------


def _octal_mode(text: str) -> int:
    """A file mode in octal, 0..0777 (whether it is allowed is ``check_configured_mode``'s: a clear message)."""
    try:
        mode = int(text, 8)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text[:20]!r} is not an octal mode such as 0660") from None
    if not 0 <= mode <= 0o777:
        raise argparse.ArgumentTypeError(f"{text[:20]} is out of range: give an octal mode 0..0777, such as 0660")
    return mode


def add_make_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (f"Create every MDS channel ({', '.join(mds.ALL_CHANNELS)}) with {mds.CHANNEL_FRAME_COUNT} "
                     f"frames x {mds.CHANNEL_FRAME_SIZE} B, mode 0660 (the stack's user and the channels' group "
                     f"read-write), {mds.MDS_CHAN_DAEMON_INPUT_NAME} 0640 (only the stack writes what the daemon "
                     "executes). Channels that already exist are checked, never clobbered: one owned by another "
                     "user (not you, not root), with a looser mode or another group than configured is refused "
                     "(exit 1; 'mds-ach repair --recreate NAME' replaces it); one of yours that is too open (the "
                     "original's 'ach mk' and 'chmod 777') gets the mode in place unless another process has it "
                     "open. See docs/operator.md, 'Users and permissions'.")
    p.add_argument("--group", metavar="GROUP", help="give the new channels to this group (name or gid) so its "
                                                    "members (operators) can run clients; existing channels must "
                                                    "belong to it")
    p.add_argument("--mode", type=_octal_mode, default=0o660, metavar="OCTAL",
                   help="file mode of new channels (default 0660; it may only restrict 0660, e.g. 0600)")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")


def run_make(args: argparse.Namespace) -> int:
    try:
        reports = make_channels(mode=args.mode, group=args.group)
    except ValueError as exc:
        _err("make", str(exc))
        return 1
    failed = 0
    for r in reports:
        if not r.ok:
            failed += 1
            _err("make", f"channel '{r.name}': {r.detail}")
        elif not args.quiet:
            print(f"{r.name:<20} {r.action:<8} {r.detail}")
    return 1 if failed else 0


# --- rm ---------------------------------------------------------------------------------------------


def add_rm_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Remove Ach channels (default: every MDS channel). Processes that have a channel open keep "
                     "working on the orphaned memory; restart them after re-creating the channels.")
    p.add_argument("names", nargs="*", metavar="NAME", help="channels to remove (default: all MDS channels)")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")


def run_rm(args: argparse.Namespace) -> int:
    names = args.names or list(mds.ALL_CHANNELS)
    explicit = bool(args.names)
    status = 0
    for name in names:
        try:
            ach.unlink(name)
        except ach.AchException as exc:
            if exc.status == ach.ACH_ENOENT and not explicit:
                continue  # removing "everything" is idempotent
            _err("rm", str(exc))
            status = 1
            continue
        if not args.quiet:
            print(f"removed {name}")
    return status


# --- dump -------------------------------------------------------------------------------------------

def kind_of(struct: type[ctypes.Structure]) -> str:
    """The ``--type`` name of a wire struct: ``MDS_JOINT_PARAM`` -> ``param``, ``MDS_MUX_STATE`` -> ``mux-state``."""
    return struct.__name__.removeprefix("MDS_").removeprefix("JOINT_").lower().replace("_", "-")


# Every struct a registered channel carries, by --type name (derived from mds_ach.robot.contracts).
DECODERS: dict[str, type[ctypes.Structure]] = {kind_of(c.struct): c.struct for c in contracts.CHANNELS}


def decoder_for(channel: str) -> str:
    """The ``--type`` a channel's frames are decoded as by default: its contract's struct, else ``hex``."""
    found = contracts.lookup(channel)
    return kind_of(found.struct) if found is not None else "hex"


def add_dump_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Print the newest frame of a channel, decoded by the struct its contract names (mds-state: "
                     "joint table, mds-ref*: references, mds-mux-state: joint owners, mds-daemon-status, "
                     "mds-ik-state, mds-param, mds-ik, mds-collide, mds-cmd). Other channels, or frames of an "
                     "unexpected size, are shown as a hex dump with the channel's header counters.")
    p.add_argument("channel", help="channel name, e.g. mds-state")
    p.add_argument("--type", choices=[*DECODERS, "hex"], help="decode as this type regardless of the channel name")
    p.add_argument("-a", "--all", action="store_true", help="list every known joint, not only enabled/named ones")
    p.add_argument("--fields", action="store_true",
                   help="print every field of the struct by its C name (nested structs and arrays expanded)")
    p.add_argument("--wait", type=seconds(zero=True), metavar="SECONDS",
                   help="if the channel is empty, wait up to SECONDS for a first frame")


def run_dump(args: argparse.Namespace) -> int:
    try:
        ch = ach.Channel(args.channel, create=False)
    except ach.AchException as exc:
        _err("dump", str(exc))
        return 1
    with ch:
        buf = bytearray(ch.data_size)
        try:
            status, size = ch.get(buf, last=True)
            if status == ach.ACH_STALE_FRAMES and args.wait:
                status, size = ch.get(buf, wait=True, last=True, timeout=args.wait)
            info = ch.snapshot()
        except ach.AchException as exc:
            _err("dump", str(exc))
            return 1
    counters = (f"seq {info.last_seq}, {info.index_cnt} x {info.frame_size} B, data_head {info.data_head}, "
                f"data_free {info.data_free}, index_head {info.index_head}, index_free {info.index_free}")
    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
        print(f"{args.channel}: empty, no frame written yet ({counters})")
        return 0
    frame = bytes(buf[:size])
    kind = args.type or decoder_for(args.channel)
    ctype = DECODERS.get(kind)
    if ctype is not None and ctypes.sizeof(ctype) != size:
        _err("dump", f"channel '{args.channel}': newest frame is {size} B but {ctype.__name__} is "
                     f"{ctypes.sizeof(ctype)} B; showing it as hex")
        ctype = None
    print(f"{args.channel}: {kind if ctype else 'raw'} frame, {size} B ({counters})")
    if ctype is None:
        print(hexdump(frame))
    elif args.fields:
        print_fields(ctype.from_buffer_copy(frame), args.all)
    else:
        _PRINTERS.get(kind, print_fields)(ctype.from_buffer_copy(frame), args.all)
    return 0


def hexdump(data: bytes, width: int = 16) -> str:
    """Classic offset / hex / ASCII dump."""
    lines = []
    for off in range(0, len(data), width):
        chunk = data[off:off + width]
        text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
        lines.append(f"{off:08x}  {chunk.hex(' '):<{3 * width - 1}}  {text}")
    return "\n".join(lines)


def _joint_label(addr: int, name: bytes = b"", short: bytes = b"") -> tuple[str, str]:
    known = BY_ADDRESS.get(addr)
    s = get_name(short) or (known.short if known else "")
    n = get_name(name) or (known.name if known else "")
    return s, n


def _print_state(st: MDS_STATE, show_all: bool) -> None:
    print(f"time {st.time:.6f} s   refWait {st.refWait}")
    print(f"{'short':<6} {'name':<22} {'addr':>6} {'en':>3} {'hom':>3} {'ref_r':>10} {'ref':>10} "
          f"{'ref_c_send':>10} {'pos':>10} {'vel':>10} {'cur':>10}")
    for addr, j in enumerate(st.joint):
        short, name = _joint_label(addr, j.name, j.nameshort)
        if not (j.enabled or get_name(j.name) or get_name(j.nameshort) or (show_all and addr in BY_ADDRESS)):
            continue
        print(f"{short:<6} {name:<22} {addr:#06x} {j.enabled:>3} {j.homed:>3} {j.ref_r:>10.5f} {j.ref:>10.5f} "
              f"{j.ref_c_send:>10.5f} {j.pos:>10.5f} {j.vel:>10.5f} {j.cur:>10.5f}")
    c = st.collide
    hits = [mds.COLLIDE_PART_NAMES[i] for i in range(len(mds.COLLIDE_PART_NAMES)) if c.joint[i].isCollide]
    print(f"collide: {'True' if c.isCollide else 'False'}  dt {c.time_dt:.7f}  parts: {', '.join(hits) or '-'}")
    print(f"power: {st.power.voltage:.2f} V  {st.power.current:.2f} A  {st.power.power:.2f} W")


def _print_ref(ref: MDS_REF, show_all: bool) -> None:
    print(f"{'short':<6} {'name':<22} {'addr':>6} {'ref':>10} {'mode':>4}")
    for addr, j in enumerate(ref.joint):
        if not (j.ref or j.mode or (show_all and addr in BY_ADDRESS)):
            continue
        short, name = _joint_label(addr)
        print(f"{short:<6} {name:<22} {addr:#06x} {j.ref:>10.5f} {j.mode:>4}")


def _print_param(par: MDS_JOINT_PARAM, show_all: bool) -> None:
    print(f"{'short':<6} {'name':<22} {'addr':>6} {'en':>3} {'rom':>9} {'offset':>9} {'dir':>4} {'gear':>9} "
          f"{'enc_res':>9} {'home':<10}")
    for addr, j in enumerate(par.joint):
        short, name = _joint_label(addr, j.name, j.nameshort)
        if not (j.enabled or get_name(j.name) or get_name(j.nameshort) or (show_all and addr in BY_ADDRESS)):
            continue
        print(f"{short:<6} {name:<22} {addr:#06x} {j.enabled:>3} {j.rom:>9.4f} {j.offset:>9.4f} {j.direction:>4.0f} "
              f"{j.gearratio:>9.3f} {j.encoderresolution:>9.1f} {get_name(j.HomeType):<10}")


def _print_ik(ik: MDS_IK, show_all: bool) -> None:
    arms = {mds.RIGHT: "right", mds.LEFT: "left"}
    print(f"move: {ik.move} ({arms.get(ik.move, 'invalid')})")
    print(f"{'arm':<6} {'t_x':>9} {'t_y':>9} {'t_z':>9} {'r_x':>9} {'r_y':>9} {'r_z':>9} {'dof':>4}")
    for i, a in enumerate(ik.arm):
        print(f"{arms[i]:<6} {a.t_x:>9.4f} {a.t_y:>9.4f} {a.t_z:>9.4f} {a.r_x:>9.4f} {a.r_y:>9.4f} {a.r_z:>9.4f} "
              f"{a.ik_method:>4}")


def _print_collide(c: MDS_COLLIDE, show_all: bool) -> None:
    print(f"isCollide {c.isCollide}  time {c.time:.6f}  dt {c.time_dt:.7f}")
    print(f"{'part':<12} {'count':>6} {'isCollide':>9} {'time':>14} {'dt':>10}")
    for i, name in enumerate(mds.COLLIDE_PART_NAMES):
        j = c.joint[i]
        print(f"{name:<12} {j.collision:>6} {j.isCollide:>9} {j.time:>14.6f} {j.time_dt:>10.7f}")


_CMD_NAMES = {getattr(mds, n): n for n in dir(mds) if n.startswith("MDS_CMD_")}


def _print_cmd(cmd: MDS_CMD, show_all: bool) -> None:
    target = "all enabled joints" if cmd.address == 0 else "/".join(filter(None, _joint_label(cmd.address))) or "?"
    print(f"seq {cmd.seq}  cmd {cmd.cmd} ({_CMD_NAMES.get(cmd.cmd, 'unknown')})  address {cmd.address:#06x} "
          f"({target})  value {cmd.value:g}")


def _print_mux_state(st: MDS_MUX_STATE, show_all: bool) -> None:
    names = st.controller_names()
    count = len(names)
    print(f"seq {st.seq}  time {st.time:.6f}  controllers {st.count}")
    print(f"{'controller':<12} {'priority':>8} {'stale':>5} {'age':>9} {'change_age':>10}")
    for i, name in enumerate(names):
        age = "never" if st.age[i] < 0 else f"{st.age[i]:.3f}"
        change = "never" if st.change_age[i] < 0 else f"{st.change_age[i]:.3f}"
        print(f"{name:<12} {st.priority[i]:>8} {st.stale[i]:>5} {age:>9} {change:>10}")
    print(f"{'short':<6} {'name':<22} {'addr':>6} owner")
    for addr in range(MDS_JOINT_COUNT):
        owner = int(st.owner[addr])
        if owner < 0 and not (show_all and addr in BY_ADDRESS):
            continue
        short, name = _joint_label(addr)
        who = names[owner] if 0 <= owner < count else ("-" if owner < 0 else f"#{owner}?")
        print(f"{short:<6} {name:<22} {addr:#06x} {who}")


def _print_ik_status(st: MDS_IK_STATUS, show_all: bool) -> None:
    print(f"status {st.status} ({ik_status.STATUS_NAMES.get(st.status, 'unknown')}): {ik_status.get_message(st)}")
    print_fields(st, show_all)


def _print_daemon_status(st: MDS_DAEMON_STATUS, show_all: bool) -> None:
    print(ds.summary_line(st))
    print_fields(st, show_all)


def _scalar_text(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.9g}"
    if isinstance(value, bytes):
        return repr(get_name(value))
    return str(value)


def print_fields(obj: ctypes.Structure, show_all: bool = False, prefix: str = "") -> None:
    """Every field of ``obj`` by name, one line each (``joint[0x5f].pos 0.25``). Arrays indexed by CAN address
    (length ``MDS_JOINT_COUNT``) list their non-zero entries, and with ``show_all`` every known joint's."""
    for name, ftype, *_ in obj._fields_:
        _print_value(f"{prefix}{name}", ftype, getattr(obj, name), show_all)


def _print_value(label: str, ftype: type, value: object, show_all: bool) -> None:
    if isinstance(value, ctypes.Structure):
        print_fields(value, show_all, f"{label}.")
    elif isinstance(value, ctypes.Array):
        items = list(value)
        if ftype._type_ is ctypes.c_char:  # type: ignore[attr-defined]
            print(f"{label} {_scalar_text(bytes(value))}")
            return
        per_joint = len(items) == MDS_JOINT_COUNT
        if not per_joint and not isinstance(value[0], ctypes.Structure | ctypes.Array):  # short: one line
            print(f"{label} " + " ".join(_scalar_text(item) for item in items))
            return
        for i, item in enumerate(items):
            if per_joint and not (_nonzero(item) or (show_all and i in BY_ADDRESS)):
                continue
            index = f"{i:#04x}" if per_joint else str(i)
            _print_value(f"{label}[{index}]", ftype._type_, item, show_all)  # type: ignore[attr-defined]
    else:
        print(f"{label} {_scalar_text(value)}")


def _nonzero(value: object) -> bool:
    if isinstance(value, ctypes.Structure | ctypes.Array):
        return any(bytes(value))
    return bool(value)


_PRINTERS: dict[str, Callable[[Any, bool], None]] = {
    "state": _print_state,
    "ref": _print_ref,
    "param": _print_param,
    "ik": _print_ik,
    "collide": _print_collide,
    "cmd": _print_cmd,
    "mux-state": _print_mux_state,
    "ik-status": _print_ik_status,
    "daemon-status": _print_daemon_status,
}
