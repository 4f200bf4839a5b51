"""``mds-ach plot``: commanded vs measured, per joint, from a recording (or a CAN log), as a figure people read.

Per joint one panel: the command as each stage saw it -- the controller inputs (``mds-ref``, ``mds-ref-filter``,
``mds-ref-ik``, ``mds-ref-ros``, extra ``mds-ref-*``), the mux's output (``mds-ref-mux``), the filter's
(``mds-ref-smooth``), the collision gate's (``mds-ref-gated``) and what the daemon sent (``mds-state`` ``ref``) --
the measured position (``mds-state`` ``pos``), the effective limits (``mds-limits``), shaded intervals where the
collision gate held the joint's arm (``mds-collide``) or a hold or cancel applied (``mds-mux-state`` ``held``), and
the ``check-log`` findings of the recording's CAN frames on the time axis. A CAN log gives the targets sent, the
joint table's limits and the findings.

:func:`plot_data` computes everything drawn (tested against the recording); :func:`draw` only draws it.
matplotlib with the Agg backend (no display needed): PNG, SVG, PDF, or HTML (the SVG in a standalone page).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import mds_ach as mds
from mds_ach.record import canlog
from mds_ach.record import schema as wire
from mds_ach.record.recording import Recording, RecordingError, is_recording, load
from mds_ach.robot import contracts
from mds_ach.robot.joints import BY_ADDRESS, LEFT_ARM, RIGHT_ARM, lookup
from mds_ach.robot.msgs import get_name
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_HELD

PROG = "mds-ach plot"
MAX_DEFAULT_JOINTS = 6
MOVED = 1e-4  # rad: a joint whose command changed less than this is not plotted by default
INPUTS = (contracts.MDS_CHAN_REF_NAME, contracts.MDS_CHAN_REF_FILTER_NAME, contracts.MDS_CHAN_REF_IK_NAME,
          contracts.MDS_CHAN_REF_ROS_NAME)
STAGES = (("mux", contracts.MDS_CHAN_REF_MUX_NAME), ("filter", contracts.MDS_CHAN_REF_SMOOTH_NAME),
          ("gate", contracts.MDS_CHAN_REF_GATED_NAME))
# The parts of mds-collide that hold each arm (the daemon's rule: mds_ach.nodes.daemon_loop._collision_held)
_LEFT_PARTS = (mds.COLLIDE_L_HAND, mds.COLLIDE_L_SHOULDER, mds.COLLIDE_L_FOREARM, mds.COLLIDE_L_ELBOW,
               mds.COLLIDE_L_WRIST)
_RIGHT_PARTS = (mds.COLLIDE_R_HAND, mds.COLLIDE_R_SHOULDER, mds.COLLIDE_R_FOREARM, mds.COLLIDE_R_ELBOW,
                mds.COLLIDE_R_WRIST)
SUFFIXES = (".png", ".svg", ".pdf", ".html")

Series = tuple[np.ndarray, np.ndarray]
"""(t s since the start, value rad)."""


@dataclass
class Interval:
    start: float
    end: float
    kind: str  # "hold", "cancel", "gate"


@dataclass
class FindingMark:
    time: float
    kind: str
    text: str


@dataclass
class JointPlot:
    """Everything drawn in one joint's panel."""

    joint: str
    address: int
    commands: dict[str, Series] = field(default_factory=dict)  # label -> series, in stage order
    measured: Series | None = None
    limits: tuple[float, float] | None = None
    intervals: list[Interval] = field(default_factory=list)
    findings: list[FindingMark] = field(default_factory=list)


@dataclass
class PlotData:
    title: str
    source: str  # "recording" or "CAN log"
    joints: list[JointPlot]
    notes: list[str] = field(default_factory=list)


def _series(times: list[float], values: list[float]) -> Series:
    return np.asarray(times, dtype=float), np.asarray(values, dtype=float)


def intervals(times: Sequence[float], kinds: Sequence[str], end: float) -> list[Interval]:
    """Runs of equal non-empty ``kinds`` as intervals; a run lasts until the next sample that differs (the last
    one until ``end``)."""
    out: list[Interval] = []
    start, current = 0.0, ""
    for t, k in zip(times, kinds, strict=True):
        if k != current:
            if current:
                out.append(Interval(start, t, current))
            start, current = t, k
    if current:
        out.append(Interval(start, max(end, start), current))
    return out


def _arm_parts(address: int) -> tuple[int, ...] | None:
    short = BY_ADDRESS[address].short if address in BY_ADDRESS else ""
    if short in LEFT_ARM:
        return _LEFT_PARTS
    if short in RIGHT_ARM:
        return _RIGHT_PARTS
    return None


def _gate_holds(collide: Any, address: int) -> bool:
    """The daemon withholds this joint's targets under this ``mds-collide`` frame (``_collision_held``)."""
    if collide.isCollide != 1:
        return False
    flagged = [i for i in range(len(collide.joint)) if collide.joint[i].isCollide]
    if not flagged:
        return True  # a report that flags no part holds every joint
    parts = _arm_parts(address)
    return parts is not None and any(i in parts for i in flagged)


def _choose(rec: Recording, t0: int, wanted: list[str] | None) -> list[tuple[str, int]]:
    if wanted:
        return [(lookup(j).short, lookup(j).address) for j in wanted]
    moved: list[tuple[float, str, int]] = []
    gated = [f for _, f in rec.frames(contracts.MDS_CHAN_REF_GATED_NAME)]
    states = [f for _, f in rec.frames(contracts.MDS_CHAN_STATE_NAME)]
    for a, j in sorted(BY_ADDRESS.items()):
        values = [g.joint[a].ref for g in gated] + [s.joint[a].ref for s in states]
        finite = [v for v in values if math.isfinite(v)]
        if finite and max(finite) - min(finite) > MOVED:
            moved.append((max(finite) - min(finite), j.short, a))
    moved.sort(reverse=True)
    return [(s, a) for _, s, a in moved[:MAX_DEFAULT_JOINTS]]


def plot_data(rec: Recording, joints: list[str] | None = None, table: Any = None) -> PlotData:
    """What the figure of recording ``rec`` shows (``joints``: short names; default the joints whose command moved
    most, at most six). Times are seconds since the recording's first message."""
    t0 = rec.start_ns or 0
    end = ((rec.end_ns or t0) - t0) / 1e9

    def sec(ns: int) -> float:
        return (ns - t0) / 1e9

    chosen = _choose(rec, t0, joints)
    robot = ""
    limits = [f for _, f in rec.frames(contracts.MDS_CHAN_LIMITS_NAME)]
    if limits:
        robot = get_name(bytes(limits[-1].robot))
    robot = robot or rec.metadata.get("mds_ach", {}).get("robot", "")
    title = f"{rec.path.name}" + (f" -- robot {robot}" if robot else "")
    data = PlotData(title, "recording", [])
    if rec.cut:
        data.notes.append(rec.cut)
    inputs = list(INPUTS) + sorted(
        ch for t in rec.messages if (ch := wire.channel_of(t)) and ch.startswith(contracts.REF_INPUT_PREFIX)
        and ch not in INPUTS and ch not in dict(STAGES).values())
    frames = {name: list(rec.frames(name)) for name in [*inputs, *dict(STAGES).values()]}
    states = list(rec.frames(contracts.MDS_CHAN_STATE_NAME))
    mux_states = list(rec.frames(contracts.MDS_CHAN_MUX_STATE_NAME))
    collides = list(rec.frames(contracts.MDS_CHAN_COLLIDE_NAME))
    findings = _recording_findings(rec, table, data.notes)
    for short, a in chosen:
        jp = JointPlot(short, a)
        for name in inputs:
            fs = frames[name]
            values = [f.joint[a].ref for _, f in fs]
            if fs and any(v != values[0] or v != 0.0 for v in values):
                jp.commands[f"input {name}"] = _series([sec(t) for t, _ in fs], values)
        for label, name in STAGES:
            if frames[name]:
                jp.commands[f"{label} ({name})"] = _series([sec(t) for t, _ in frames[name]],
                                                           [f.joint[a].ref for _, f in frames[name]])
        if states:
            ts = [sec(t) for t, _ in states]
            jp.commands[f"sent (daemon, {contracts.MDS_CHAN_STATE_NAME} ref)"] = _series(
                ts, [s.joint[a].ref for _, s in states])
            jp.measured = _series(ts, [s.joint[a].pos for _, s in states])
        if limits and limits[-1].valid[a]:
            jp.limits = (limits[-1].lower[a], limits[-1].upper[a])
        jp.intervals += intervals([sec(t) for t, _ in mux_states],
                                  [{MUX_HELD: "hold", MUX_CANCELLED: "cancel"}.get(int(m.held[a]), "")
                                   for _, m in mux_states], end)
        jp.intervals += intervals([sec(t) for t, _ in collides],
                                  ["gate" if _gate_holds(c, a) else "" for _, c in collides], end)
        jp.findings = [FindingMark((f_t - t0) / 1e9, f.kind, f.line()) for f_t, f in findings if f.joint == short]
        data.joints.append(jp)
    return data


def _recording_findings(rec: Recording, table: Any, notes: list[str]) -> list[tuple[int, Any]]:
    """check-log's findings on the recording's CAN frames, each with its time (ns, the recording's clock)."""
    from mds_ach.tools import checklog

    msgs = [canlog.from_message(r.message, r.log_ns) for r in rec.messages.get(canlog.CAN_TOPIC, [])]
    if not msgs:
        notes.append("no CAN frames in the recording (record with --can-log): no check-log findings")
        return []
    table = table or _table()
    report = checklog.audit_frames(((m.timestamp, m) for m in msgs), table, table.motion_bounds(),
                                   checklog.STALE_AFTER)
    start = report.start_stamp
    return [(int(round((start + f.time) * 1e9)), f) for f in report.findings]


def _table() -> Any:
    from mds_ach.robot import config

    return config.load(None, None)


def can_log_data(path: Path, joints: list[str] | None, table: Any = None) -> PlotData:
    """What the figure of a CAN log shows: per joint the targets sent (rad), the joint table's limits, findings."""
    from mds_ach.bus import canio
    from mds_ach.tools import checklog

    table = table or _table()
    torn: list[str] = []
    try:
        frames = [(m.timestamp, m) for m in checklog._read(path, torn)]
    except canio.LogReadError as exc:
        raise RecordingError(str(exc)) from None
    if not frames:
        raise RecordingError(f"{path}: no CAN frames in the file")
    report = checklog.audit_frames(frames, table, table.motion_bounds(), checklog.STALE_AFTER, record_targets=True)
    sent = {j: v for j, v in report.sent.items() if v}
    names = [lookup(j).short for j in joints] if joints else sorted(
        sent, key=lambda j: -(max(q for _, q in sent[j]) - min(q for _, q in sent[j])))[:MAX_DEFAULT_JOINTS]
    data = PlotData(f"{path.name} -- joint table {table.robot}", "CAN log", [])
    if torn:
        data.notes.append(torn[0])
    for short in names:
        cfg = next((j for j in table if j.short == short), None)
        jp = JointPlot(short, lookup(short).address)
        pts = sent.get(short, [])
        if pts:
            jp.commands["sent (CAN targets)"] = _series([t for t, _ in pts], [q for _, q in pts])
        if cfg is not None:
            jp.limits = (cfg.lower, cfg.upper)
        jp.findings = [FindingMark(f.time, f.kind, f.line()) for f in report.findings if f.joint == short]
        data.joints.append(jp)
    return data


# ------------------------------------------------------------------------------------------------ drawing

_SPAN_COLOURS = {"hold": ("tab:orange", "hold (mux)"), "cancel": ("tab:red", "cancel (mux)"),
                 "gate": ("tab:purple", "collision gate held the arm")}


def draw(data: PlotData) -> Any:
    """The matplotlib figure of ``data`` (Agg: no display)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    n = max(1, len(data.joints))
    fig = Figure(figsize=(12, 2.8 * n + 1.2), layout="constrained")
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    fig.suptitle(f"{data.title}: commanded vs measured ({data.source})")
    for ax, jp in zip(axes, data.joints, strict=False):
        for label, (t, v) in jp.commands.items():
            style = {"linestyle": "--"} if label.startswith("input") else {}
            ax.step(t, v, where="post", label=label, linewidth=1.2, **style)
        if jp.measured is not None:
            ax.plot(jp.measured[0], jp.measured[1], label="measured (mds-state pos)", color="black", linewidth=1.6)
        if jp.limits is not None:
            ax.axhline(jp.limits[0], color="grey", linestyle=":", label="limits (effective)")
            ax.axhline(jp.limits[1], color="grey", linestyle=":")
        seen: set[str] = set()
        for iv in jp.intervals:
            colour, label = _SPAN_COLOURS[iv.kind]
            ax.axvspan(iv.start, iv.end, color=colour, alpha=0.15, label=None if iv.kind in seen else label)
            seen.add(iv.kind)
        for k, fm in enumerate(jp.findings):
            ax.axvline(fm.time, color="red", linewidth=0.8, label="check-log finding" if k == 0 else None)
            ax.annotate(fm.kind, (fm.time, 1.0), xycoords=("data", "axes fraction"), fontsize=7, color="red",
                        rotation=90, va="top")
        ax.set_ylabel(f"{jp.joint} (rad)")
        ax.set_title(f"{jp.joint} (address {jp.address:#04x})", fontsize=9, loc="left")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the panel: never on the data
    axes[-1].set_xlabel("time since the start of the recording (s)")
    if not data.joints:
        axes[0].text(0.5, 0.5, "no joint moved: choose joints with --joints", ha="center", transform=axes[0].transAxes)
    if data.notes:
        fig.text(0.01, 0.0, "\n".join(data.notes), fontsize=7, va="bottom")
    return fig


def save(fig: Any, out: Path) -> None:
    if out.suffix == ".html":
        import io

        buf = io.StringIO()
        fig.savefig(buf, format="svg")
        out.write_text(f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{out.stem}</title></head>"
                       f"<body>{buf.getvalue()}</body></html>\n")
    else:
        fig.savefig(out, dpi=110)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Plot a recording (mds-ach record) or a CAN log: per joint the command as each stage saw it "
                     "(input, mux, filter, gate, sent), the measured position, the effective limits, the intervals "
                     "where the collision gate held the arm or a hold/cancel applied, and the check-log findings.")
    p.add_argument("file", metavar="FILE", help="a recording (.mcap) or a CAN log (daemon --can-log, candump -l, ...)")
    p.add_argument("--joints", metavar="J,J", help="joints by short name, e.g. RSP,REP (default: the joints whose "
                                                   f"command moved most, at most {MAX_DEFAULT_JOINTS})")
    p.add_argument("-o", "--output", metavar="OUT", help="image to write: .png, .svg, .pdf or .html "
                                                         "(default: FILE with .png)")


def run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    out = Path(args.output) if args.output else path.with_suffix(".png")
    if out.suffix not in SUFFIXES:
        print(f"{PROG}: -o {out}: give a .png, .svg, .pdf or .html file", file=sys.stderr)
        return 2
    joints = [j.strip() for j in args.joints.split(",") if j.strip()] if args.joints else None
    try:
        for j in joints or []:
            lookup(j)
    except KeyError as exc:
        print(f"{PROG}: {exc.args[0]}", file=sys.stderr)
        return 2
    if not path.exists():
        print(f"{PROG}: {path}: no such file", file=sys.stderr)
        return 1
    t = time.monotonic()
    try:
        data = plot_data(load(path), joints) if is_recording(path) else can_log_data(path, joints)
    except RecordingError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    try:
        save(draw(data), out)
    except OSError as exc:
        print(f"{PROG}: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    for note in data.notes:
        print(f"{PROG}: note: {note}", file=sys.stderr)
    print(f"{out}: {len(data.joints)} joint(s) ({', '.join(j.joint for j in data.joints) or 'none'}) in "
          f"{time.monotonic() - t:.1f} s")
    return 0
