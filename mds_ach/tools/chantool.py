"""``mds-ach make | rm | dump``: create, remove and inspect the MDS Ach channels from a shell.

Exit codes a script can rely on: 0 success, 1 a runtime failure (message on stderr naming the channel and the
problem), 2 a usage error (argparse).
"""

from __future__ import annotations

import argparse
import ctypes
import sys
from collections.abc import Callable

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot.joints import BY_ADDRESS
from mds_ach.robot.msgs import MDS_CMD, MDS_COLLIDE, MDS_IK, MDS_JOINT_PARAM, MDS_REF, MDS_STATE, get_name

PROG = "mds-ach"


def _err(verb: str, message: str) -> None:
    print(f"{PROG} {verb}: {message}", file=sys.stderr)


# --- make -------------------------------------------------------------------------------------------


def add_make_arguments(p: argparse.ArgumentParser) -> None:
    p.description = (f"Create every MDS channel ({', '.join(mds.ALL_CHANNELS)}) with {mds.CHANNEL_FRAME_COUNT} "
                     f"frames x {mds.CHANNEL_FRAME_SIZE} B, mode 0660 (the stack's user and the channels' group "
                     f"read-write), {mds.MDS_CHAN_DAEMON_INPUT_NAME} 0640 (only the stack writes what the daemon "
                     "executes). Channels that already exist are checked, never clobbered: one owned by another "
                     "user (not you, not root), with a looser mode or another group than configured is refused "
                     "(exit 1; 'mds-ach repair --recreate NAME' replaces it). See docs/operator.md, 'Users and "
                     "permissions'.")
    p.add_argument("--group", metavar="GROUP", help="give the new channels to this group (name or gid) so its "
                                                    "members (operators) can run clients; existing channels must "
                                                    "belong to it")
    p.add_argument("--mode", type=lambda s: int(s, 8), default=0o660, metavar="OCTAL",
                   help="file mode of new channels (default 0660; it may only restrict 0660, e.g. 0600)")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing on success")


def run_make(args: argparse.Namespace) -> int:
    from mds_ach.robot.channels import make_channels

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

DECODERS: dict[str, type[ctypes.Structure]] = {
    "state": MDS_STATE,
    "ref": MDS_REF,
    "param": MDS_JOINT_PARAM,
    "ik": MDS_IK,
    "collide": MDS_COLLIDE,
    "cmd": MDS_CMD,
}
CHANNEL_TYPES: dict[str, str] = {
    mds.MDS_CHAN_STATE_NAME: "state",
    mds.MDS_CHAN_REF_NAME: "ref",
    mds.MDS_CHAN_REF_FILTER_NAME: "ref",
    mds.MDS_CHAN_REF_IK_NAME: "ref",
    mds.MDS_CHAN_REF_ROS_NAME: "ref",
    mds.MDS_CHAN_REF_MUX_NAME: "ref",
    mds.MDS_CHAN_REF_SMOOTH_NAME: "ref",
    mds.MDS_CHAN_PARAM_NAME: "param",
    mds.MDS_CHAN_IK_NAME: "ik",
    mds.MDS_CHAN_COLLIDE_NAME: "collide",
    mds.MDS_CHAN_BOARD_CMD_NAME: "cmd",
}


def add_dump_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Print the newest frame of a channel, decoded by the channel's type (mds-state: joint table, "
                     "mds-ref*: references, mds-param, mds-ik, mds-collide, mds-cmd). Other channels, or frames "
                     "of an unexpected size, are shown as a hex dump with the channel's header counters.")
    p.add_argument("channel", help="channel name, e.g. mds-state")
    p.add_argument("--type", choices=[*DECODERS, "hex"], help="decode as this type regardless of the channel name")
    p.add_argument("-a", "--all", action="store_true", help="list every known joint, not only enabled/named ones")
    p.add_argument("--wait", type=float, metavar="SECONDS",
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
    kind = args.type or CHANNEL_TYPES.get(args.channel, "hex")
    ctype = DECODERS.get(kind)
    if ctype is not None and ctypes.sizeof(ctype) != size:
        _err("dump", f"channel '{args.channel}': newest frame is {size} B but {ctype.__name__} is "
                     f"{ctypes.sizeof(ctype)} B; showing it as hex")
        ctype = None
    print(f"{args.channel}: {kind if ctype else 'raw'} frame, {size} B ({counters})")
    if ctype is None:
        print(hexdump(frame))
    else:
        _PRINTERS[kind](ctype.from_buffer_copy(frame), args.all)
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


_PRINTERS: dict[str, Callable[[ctypes.Structure, bool], None]] = {
    "state": _print_state,
    "ref": _print_ref,
    "param": _print_param,
    "ik": _print_ik,
    "collide": _print_collide,
    "cmd": _print_cmd,
}
