"""``mds-ach console``: the operator's command line (prompt ``>> mds-ach-console$ ``), as in the original.

Commands keep the original's names and output formats; motion goes through the safety pipeline: ``goto``
read-modify-writes ``mds-ref-filter`` (the mux's default controller input, then filter and collision gate),
``ik`` asks the IK node on ``mds-ik``. A motion command is reported applied only once the mux acknowledged it
(``mds-mux-state``) and its output (``mds-ref-mux``) has the targets; with the mux down nothing is sent and the
console says "not applied: mux not running". Bad input prints what was wrong plus the usage and never ends the
console. ``-c "cmd"`` (repeatable) runs commands non-interactively; the exit status says whether they worked.

Only numpy forward kinematics is used (``get fk``), so the console starts without torch.
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import signal
import sys
import termios
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mds_ach as mds
from mds_ach.kinematics.limits import current_limits
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.robot import lifecycle
from mds_ach.robot.joints import BY_SHORT, JOINTS, LEFT_ARM, RIGHT_ARM, Joint, lookup
from mds_ach.robot.msgs import MDS_MUX_STATE, get_name
from mds_ach.robot.msgs.mux_state import MUX_FREE, MUX_HELD
from mds_ach.tools.cli import help_paragraph, stdout_closed
from mds_ach.tools.holdcmd import enabled_joints, held_summary
from mds_ach.tools.monitor import Latest, collision_summary
from mds_ach.tools.refwriter import RefWriteError, RefWriter

if TYPE_CHECKING:  # imported lazily at run time (numpy)
    from mds_ach.nodes.ik_client import IkClient, IkReply

PROMPT = ">> mds-ach-console$ "
ARMS = {"left": (mds.LEFT, LEFT_ARM), "right": (mds.RIGHT, RIGHT_ARM)}
IK_COMPONENTS = ("x", "y", "z", "rx", "ry", "rz")
GOTO_TOLERANCE = 0.01  # rad, "arrived" for goto ... wait
GOTO_TIMEOUT = 20.0  # s
GOTO_STEP = 0.1  # rad per step of 'goto ... step' (the original console's ramp)
GOTO_STEP_PERIOD = 0.1  # s between those steps
IK_TIMEOUT = 10.0  # s for the IK node's answer
IK_MOTION_TIMEOUT = 20.0  # s for the arm to arrive (ik ... wait)
STATE_WAIT = 1.0  # s to wait for a first state frame
RELEASE_TIMEOUT = 10.0  # s to wait for a higher-priority mux controller to release a joint
MUX_TIMEOUT = 1.0  # s for a new mds-mux-state frame (the mux publishes at 10 Hz, config/mux.yaml state_rate)
APPLIED_TOLERANCE = 1e-9  # rad: the mux copies references, it does not compute them
NOT_RUNNING = (f"not applied: mux not running (no new frame on {mds.MDS_CHAN_MUX_STATE_NAME} within {MUX_TIMEOUT:g} s)"
               "; start it: mds-ach start --only mux")

USAGE = f"""\
commands (joint names: short or long, e.g. LSP or LeftShoulderExt, any case):
  goto <joint> <rad> [step] [wait]   move one joint through the mux, smoothing filter and collision gate
                                     (writes {mds.MDS_CHAN_REF_FILTER_NAME}); 'step': ramp there like the original
                                     console, {GOTO_STEP:g} rad every {GOTO_STEP_PERIOD:g} s with a dot per step;
                                     'wait': until it arrives
  get <joint>                        measured state and reference of one joint (by its long name)
  get fk <left|right>                6-DOF pose of the arm's tool point from the current references
  ik <left|right> <dof> <p1> ... <pN> [wait]
                                     move the tool point through the IK node; dof 1..6 takes the first N
                                     of x y z (m) rx ry rz (rad, Z-Y-X angles), robot frame: x forward,
                                     y left, z up, origin midway between the shoulders
  ik3 <left|right> <x> <y> <z> [set] [wait]
  ik5 <left|right> <x> <y> <z> <rx> <ry> [filter] [set] [wait]
                                     the original shorthands (3-DOF position, 5-DOF): without 'set' only
                                     solve and print (nothing moves); with 'set' as 'ik <arm> 3|5 ...'
  zeroall                            every enabled joint to 0 rad through the smoothing path, or to the
                                     value nearest 0 within its limits (it says which)
  hold [<joints>|left|right|arms|all]
                                     stop the joints where the pipeline has them (braking within the
                                     filter's bounds); nothing moves until 'resume' or a new command
                                     for them (default: all)
  resume [<joints>|left|right|arms|all]
                                     held joints go on to their controllers' targets (default: all)
  help                               this text
  exit                               quit (also 'quit' or Ctrl-D)"""


class CommandError(Exception):
    """Bad input or an unmet precondition; the message says what was wrong (and the usage follows)."""

    def __init__(self, message: str, usage: bool = True) -> None:
        super().__init__(message)
        self.show_usage = usage


class UnknownCommandError(CommandError):
    """A first word that is no command: the original console ignored such a line, and so does this one (one
    line on stderr, no usage, not a failure)."""


ORIGINAL_INVALID = "  Invalid input... "
"""What the original printed (stdout) when ``goto``, ``ik3`` or ``ik5`` failed; printed for them here too, the
reason following on stderr."""
ORIGINAL_INVALID_VERBS = ("goto", "ik3", "ik5")


def report_error(console: Console, line: str, exc: CommandError) -> bool:
    """Print why ``line`` failed: the original's stdout line for its verbs, the reason (and usage) on stderr.
    Returns whether it counts as a failure (an unknown command does not: the original ignored it)."""
    if isinstance(exc, UnknownCommandError):
        console.err(f"  {exc}: ignored, as the original console did ('help' lists the commands)")
        return False
    words = line.split()
    if words and words[0].lower() in ORIGINAL_INVALID_VERBS:
        console.out(ORIGINAL_INVALID)
    console.err(f"  {exc}")
    if exc.show_usage:
        console.err(USAGE)
    return True


def py2_str(value: float) -> str:
    """``value`` as the original's Python 2 ``print`` wrote a float: ``str()``, i.e. 12 significant digits and
    ``.0`` on a whole number (``0.244``, ``-0.5``, ``0.0``, ``1e-05``)."""
    text = format(value, ".12g")
    return text if any(c in text for c in ".en") else text + ".0"  # 'n': nan and inf stay as they are


def py2_xyz(label: str, v: Sequence[float]) -> str:
    """The original's ``print 'pos:\tx = ', round(x,5), '\ty = ', ...`` line: Python 2's print put a space
    between the items, so two spaces after each ``=`` and one before each tab."""
    x, y, z = (py2_str(round(float(c), 5)) for c in v[:3])
    return f"{label}:\tx =  {x} \ty =  {y} \tz =  {z}"


def original_steps(start: float, target: float) -> int:
    """How many steps (dots) the original console's ``goto`` took from ``start`` to ``target``: GOTO_STEP
    toward it while further than that, then the target itself."""
    steps, pos = 0, start
    while True:
        steps += 1
        delta = target - pos
        if abs(delta) <= GOTO_STEP:
            return steps
        pos += math.copysign(GOTO_STEP, delta)


# --------------------------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class Goto:
    joint: Joint
    value: float
    wait: bool = False
    step: bool = False  # ramp like the original console (GOTO_STEP every GOTO_STEP_PERIOD)
    filter: bool = field(default=False, compare=False)  # the original's 'goto filter ...': it printed nothing


@dataclass(frozen=True)
class Get:
    joint: Joint


@dataclass(frozen=True)
class GetFk:
    arm: str


@dataclass(frozen=True)
class Ik:
    arm: str
    dof: int
    values: tuple[float, ...]
    wait: bool = False
    send: bool = True  # False: the original ik3/ik5 without 'set' (solve and print only)
    shorthand: bool = field(default=False, compare=False)  # ik3/ik5: prints the original's 'N-3 DOF' lines


@dataclass(frozen=True)
class Hold:
    action: int  # lifecycle.HOLD_HOLD or HOLD_RESUME
    addresses: tuple[int, ...]  # empty: every joint
    what: str


@dataclass(frozen=True)
class Simple:
    name: str  # help, exit, zeroall, empty


Command = Goto | Get | GetFk | Ik | Hold | Simple


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise CommandError(f"{what} must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise CommandError(f"{what} must be finite, got {text!r}")
    return value


def _joint(text: str) -> Joint:
    try:
        return lookup(text)
    except KeyError:
        close = difflib.get_close_matches(text.upper(), [j.short for j in JOINTS], n=3, cutoff=0.5)
        hint = f"did you mean {', '.join(close)}? " if close else ""
        raise CommandError(f"unknown joint {text!r} ({hint}'mds-ach read all' lists every joint)",
                           usage=False) from None


def _arm(text: str) -> str:
    arm = text.lower()
    if arm not in ARMS:
        raise CommandError(f"arm must be 'left' or 'right', got {text!r}")
    return arm


def _hold(verb: str, args: list[str]) -> Hold:
    """``hold``/``resume`` [joints | left | right | arms | all]: the joints a lifecycle request names."""
    action = lifecycle.HOLD_HOLD if verb == "hold" else lifecycle.HOLD_RESUME
    if not args or [a.lower() for a in args] == ["all"]:
        return Hold(action, (), "all joints")
    addresses: list[int] = []
    for word in args:
        key = word.lower()
        if key in ("left", "right", "arms"):
            for arm in (("left", "right") if key == "arms" else (key,)):
                addresses += [BY_SHORT[s].address for s in ARMS[arm][1]]
        else:
            addresses.append(_joint(word).address)
    return Hold(action, tuple(dict.fromkeys(addresses)), " ".join(args))


def _trailing_flags(args: list[str], allowed: Sequence[str]) -> tuple[set[str], list[str]]:
    """Split trailing option words (any order, any case) off ``args``: (flags found, the rest)."""
    flags: set[str] = set()
    while args and args[-1].lower() in allowed and args[-1].lower() not in flags:
        flags.add(args[-1].lower())
        args = args[:-1]
    return flags, args


def _ik_shorthand(dof: int, args: list[str]) -> Ik:
    """The original ``ik3 <arm> x y z [set]`` / ``ik5 <arm> x y z rx ry [filter] [set]``: without ``set`` the
    original only solved and printed, so nothing is sent; ``filter`` chose the original's smoothed channel,
    which every command here goes through anyway."""
    names = " ".join(f"<{c}>" for c in IK_COMPONENTS[:dof])
    usage = f"usage: ik{dof} <left|right> {names} {'[filter] ' if dof == 5 else ''}[set] [wait]"
    flags, args = _trailing_flags(args, ("set", "wait", "filter") if dof == 5 else ("set", "wait"))
    if len(args) != dof + 1:
        raise CommandError(usage)
    if "wait" in flags and "set" not in flags:
        raise CommandError(f"'wait' needs 'set' (without it ik{dof} only solves and prints); {usage}")
    arm = _arm(args[0])
    values = tuple(_number(v, IK_COMPONENTS[i]) for i, v in enumerate(args[1:]))
    return Ik(arm, dof, values, wait="wait" in flags, send="set" in flags, shorthand=True)


def parse(line: str) -> Command:
    """One console line -> a command; CommandError says what is wrong with it."""
    words = line.split()
    if not words or words[0].startswith("#"):
        return Simple("empty")
    verb, args = words[0].lower(), words[1:]
    if verb in ("help", "h", "?", "exit", "quit", "zeroall"):
        if args:
            raise CommandError(f"'{verb}' takes no arguments")
        return Simple({"h": "help", "?": "help", "quit": "exit"}.get(verb, verb))
    if verb == "goto":
        filtered = bool(args) and args[0].lower() == "filter"  # the original's 'goto filter <JNT> <rad>'
        if filtered:
            args = args[1:]
        flags, args = _trailing_flags(args, ("wait", "step"))
        if len(args) != 2:
            raise CommandError("usage: goto <joint> <rad> [step] [wait]")
        return Goto(_joint(args[0]), _number(args[1], "the position"), "wait" in flags, "step" in flags,
                    filter=filtered)
    if verb in ("hold", "resume"):
        return _hold(verb, args)
    if verb == "get":
        if len(args) == 2 and args[0].lower() == "fk":
            return GetFk(_arm(args[1]))
        if len(args) == 1 and args[0].lower() != "fk":
            return Get(_joint(args[0]))
        raise CommandError("usage: get <joint> | get fk <left|right>")
    if verb in ("ik3", "ik5"):
        return _ik_shorthand(int(verb[2]), args)
    if verb == "ik":
        wait = bool(args) and args[-1].lower() == "wait"
        if wait:
            args = args[:-1]
        if len(args) < 2:
            raise CommandError("usage: ik <left|right> <dof> <p1> ... <pN> [wait]")
        arm = _arm(args[0])
        try:
            dof = int(args[1])
        except ValueError:
            raise CommandError(f"dof must be an integer 1..6, got {args[1]!r}") from None
        if not 1 <= dof <= 6:
            raise CommandError(f"dof must be 1..6, got {dof}")
        if len(args) - 2 != dof:
            names = " ".join(IK_COMPONENTS[:dof])
            raise CommandError(f"ik {arm} {dof} needs {dof} value(s) ({names}), got {len(args) - 2}")
        values = tuple(_number(v, IK_COMPONENTS[i]) for i, v in enumerate(args[2:]))
        return Ik(arm, dof, values, wait)
    raise UnknownCommandError(f"unknown command {words[0]!r}", usage=False)


# --------------------------------------------------------------------------------------------- the console


def fk_pose(q: Sequence[float], arm: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(position, Z-Y-X rotation) of the arm's tool point for q = [SP, SR, SY, EP, WY, WR] (numpy, no torch)."""
    from mds_ach.kinematics.model import euler_zyx, fk_matrix  # lazy: numpy, ~90 ms of a ~120 ms console start

    T = fk_matrix(list(q), arm)
    rot = euler_zyx(T[:3, :3])
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), (float(rot[0]), float(rot[1]), float(rot[2]))


def format_fk(arm: str, pos: Sequence[float], rot: Sequence[float]) -> list[str]:
    """The original's ``get fk`` lines, as its Python 2 ``print`` wrote them (values rounded to 5 decimals)."""
    return [f"6DOF FK - for  {arm}  arm", py2_xyz("pos", pos), py2_xyz("rot", rot)]


def format_ik(arm: str, des: Sequence[float], ret: Sequence[float]) -> list[str]:
    """The original's ``ik3``/``ik5`` lines: the header says ``N-3`` for both, then the desired, reached and
    difference positions (x, y, z)."""
    dif = [d - r for d, r in zip(des[:3], ret[:3], strict=True)]
    return [f"N-3 DOF IK Solution - for  {arm}  arm", py2_xyz("des", des), py2_xyz("ret", ret),
            py2_xyz("dif", dif)]


class Console:
    """Executes parsed commands against the running system. ``out``/``err`` print one line each, ``progress``
    one dot while a ``wait`` is pending.

    The original's commands print exactly what the original printed on stdout (scripts parse it); what this
    console adds (where a command went, the IK solution, notes) goes to stdout only with ``verbose``, warnings to
    stderr."""

    def __init__(self, out: Callable[[str], None] | None = None, err: Callable[[str], None] | None = None,
                 progress: Callable[[], None] | None = None, verbose: bool = False) -> None:
        self.verbose = verbose
        self.out = out or _default_out
        self.err = err or (lambda s: print(s, file=sys.stderr, flush=True))
        self.progress = progress or (lambda: print(".", end="", flush=True))
        self.state = Latest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)

    def close(self) -> None:
        self.state.close()

    def say(self, text: str) -> None:
        """A line the original did not print: on stdout with ``verbose`` only."""
        if self.verbose:
            self.out(text)

    # -- helpers ----------------------------------------------------------------------------------

    def _state(self) -> mds.MDS_STATE:
        state = self.state.read()
        if state is None:
            state = self.state.wait_new(STATE_WAIT)
        if state is None:
            raise CommandError(f"no robot state ({self.state.error or 'no frames on ' + self.state.name}); "
                               "is MDS-Ach running? (mds-ach start)", usage=False)
        return state

    def _check_target(self, joint: Joint, value: float, state: mds.MDS_STATE) -> None:
        """Refuse what the daemon would refuse, with a message: disabled joints, targets beyond the limits."""
        if not state.joint[joint.address].enabled:
            raise CommandError(f"{joint.short} ({joint.name}) is disabled in the joint table; it cannot move",
                               usage=False)
        problem = current_limits().problem(joint.address, value)  # what the mux, gate and daemon accept
        if problem is not None:
            raise CommandError(f"refused, nothing sent: {problem}", usage=False)

    def _put_refs(self, targets: dict[int, float], state: mds.MDS_STATE) -> None:
        """Read-modify-write ``mds-ref-filter``: the mux takes only the joints that changed as commands."""
        refs = RefWriter(mds.MDS_CHAN_REF_FILTER_NAME)
        try:
            refs.put(targets, state)
        except RefWriteError as exc:
            raise CommandError(str(exc), usage=False) from None
        finally:
            refs.close()

    @staticmethod
    def _mux_holders(st: MDS_MUX_STATE, addresses: list[int],
                     channel: str = mds.MDS_CHAN_REF_FILTER_NAME) -> dict[int, str]:
        """Joints of ``addresses`` owned by a higher-priority mux controller than ours (the one reading
        ``channel``)."""
        mine = _controller_for(channel)
        names = st.controller_names()
        if mine not in names:
            return {}
        my_priority = st.priority[names.index(mine)]
        return {a: names[st.owner[a]] for a in addresses
                if 0 <= st.owner[a] < len(names) and names[st.owner[a]] != mine
                and st.priority[st.owner[a]] > my_priority}

    @staticmethod
    def _mux_state(newer_than: float, chan: Latest,
                   accept: Callable[[MDS_MUX_STATE], bool] = lambda st: True) -> MDS_MUX_STATE | None:
        """The first mux state published after ``newer_than`` (CLOCK_MONOTONIC) that ``accept`` takes, waiting up
        to ``MUX_TIMEOUT`` s; None without a live mux (its last frame stays in the channel when it dies)."""
        deadline = time.monotonic() + MUX_TIMEOUT
        st = chan.read()
        while True:
            if st is not None and st.time > newer_than and accept(st):
                return st
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            st = chan.wait_new(min(0.1, remaining)) or st

    def _require_mux(self) -> None:
        """CommandError unless the mux published a new state just now: a command it cannot take is not sent."""
        chan = Latest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        try:
            if self._mux_state(time.monotonic(), chan) is None:
                raise CommandError(NOT_RUNNING + "; nothing sent", usage=False)
        finally:
            chan.close()

    def _wait_until_free(self, addresses: list[int]) -> None:
        """Wait (up to ``RELEASE_TIMEOUT`` s) while a higher-priority mux controller owns one of the joints.

        Why: the mux applies a frame only to joints its controller may write *now*; a goto sent while the IK
        node (or ROS) still owns the joint is absorbed without effect and is not replayed after the release.
        A mux state published after this call started is awaited first, so a move the IK node answered a
        moment ago is already visible.
        """
        chan = Latest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        try:
            st = self._mux_state(time.monotonic(), chan)
            if st is None:  # nothing would take the command: do not leave it in the channel either
                raise CommandError(NOT_RUNNING + "; nothing sent", usage=False)
            deadline = time.monotonic() + RELEASE_TIMEOUT
            said = False
            while True:
                held = self._mux_holders(st, addresses)
                if not held:
                    return
                text = ", ".join(f"{mds.BY_ADDRESS[a].short} (held by '{n}')" for a, n in held.items())
                if time.monotonic() > deadline:
                    raise CommandError(f"{text}: a higher-priority controller still commands it after "
                                       f"{RELEASE_TIMEOUT:g} s; nothing sent (see 'mds-ach dump mds-mux-state')",
                                       usage=False)
                if not said:
                    self.err(f"waiting for the mux to release {text} ...")
                    said = True
                st = chan.wait_new(0.2) or st
        finally:
            chan.close()

    def _confirm_applied(self, targets: dict[int, float], sent_at: float,
                         channel: str = mds.MDS_CHAN_REF_FILTER_NAME) -> None:
        """Report success only once the command reached the pipeline: the mux acknowledged a frame from
        ``channel``'s controller that arrived after ``sent_at`` (in ``mds-mux-state``), no higher-priority
        controller holds the joints, and the mux output (``mds-ref-mux``) has every target. CommandError
        ("not applied: ...") otherwise: a dead mux, or one that ignored the frame, moves nothing."""
        mine = _controller_for(channel)
        chan = Latest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        out = Latest(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
        try:
            st = self._mux_state(sent_at, chan, lambda st: _took_frame_since(st, mine, sent_at))
            if st is None:
                latest = chan.read()
                if latest is not None and latest.time > sent_at and mine not in latest.controller_names():
                    raise CommandError(f"not applied: the mux has no controller reading {channel} "
                                       "(config/mux.yaml)", usage=False)
                raise CommandError(NOT_RUNNING, usage=False)
            held = self._mux_holders(st, list(targets), channel)
            output = out.read()
        finally:
            chan.close()
            out.close()
        if held:
            text = ", ".join(f"{mds.BY_ADDRESS[a].short} (held by '{n}')" for a, n in held.items())
            raise CommandError(f"not applied: {text} took the joint first; send the command again once it is free",
                               usage=False)
        if output is None:
            raise CommandError(f"not applied: nothing on {mds.MDS_CHAN_REF_MUX_NAME} (is the mux running?)",
                               usage=False)
        off = {a: v for a, v in targets.items() if not abs(output.joint[a].ref - v) <= APPLIED_TOLERANCE}
        if off:
            text = ", ".join(f"{mds.BY_ADDRESS[a].short} at {output.joint[a].ref:.5f} (target {v:.5f})"
                             for a, v in off.items())
            raise CommandError(f"not applied: the mux output ({mds.MDS_CHAN_REF_MUX_NAME}) keeps {text} (held, "
                               f"cancelled or taken by another controller: see 'mds-ach dump mds-mux-state')",
                               usage=False)

    def _wait_arrival(self, targets: dict[int, float], timeout: float,
                      gave_up: Callable[[], bool] = lambda: False, show: bool = True) -> bool:
        """Print a dot per half second (``show``) until every target joint's measured position is within
        tolerance (False after ``timeout`` s, or as soon as ``gave_up()``)."""
        deadline = time.monotonic() + timeout
        next_dot = time.monotonic() + 0.5
        dots = False
        while time.monotonic() < deadline and not gave_up():
            state = self.state.wait_new(0.2) or self.state.read()
            if state is not None and all(abs(state.joint[a].pos - v) <= GOTO_TOLERANCE for a, v in targets.items()):
                if dots:
                    self.out("")
                return True
            if show and time.monotonic() >= next_dot:
                self.progress()
                dots = True
                next_dot += 0.5
        if dots:
            self.out("")
        return False

    def _not_arrived(self, targets: dict[int, float]) -> str:
        state = self.state.read()
        parts = []
        for a, v in targets.items():
            j = mds.BY_ADDRESS[a]
            if state is not None:
                parts.append(f"{j.short} target {v:.5f}, ref {state.joint[a].ref:.5f}, pos {state.joint[a].pos:.5f}")
        collide = Latest(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
        try:
            summary = collision_summary(collide.read())
        finally:
            collide.close()
        return "; ".join(parts) + f"; collision gate: {summary}"

    # -- commands ---------------------------------------------------------------------------------

    def execute(self, cmd: Command) -> None:
        """Run one parsed command; CommandError on failure."""
        if isinstance(cmd, Goto):
            self.goto(cmd)
        elif isinstance(cmd, Get):
            self.get(cmd.joint)
        elif isinstance(cmd, GetFk):
            self.get_fk(cmd.arm)
        elif isinstance(cmd, Ik):
            self.ik(cmd)
        elif isinstance(cmd, Hold):
            self.hold(cmd)
        elif cmd.name == "help":
            self.out(USAGE)
        elif cmd.name == "zeroall":
            self.zeroall()

    def goto(self, cmd: Goto) -> None:
        state = self._state()
        self._check_target(cmd.joint, cmd.value, state)
        self._wait_until_free([cmd.joint.address])
        sent_at = time.monotonic()
        steps = 0
        if cmd.step:
            steps, sent_at = self._ramp(cmd.joint.address, cmd.value, state)
        else:
            self._put_refs({cmd.joint.address: cmd.value}, state)
        self._confirm_applied({cmd.joint.address: cmd.value}, sent_at)
        if cmd.wait:
            if not self._wait_arrival({cmd.joint.address: cmd.value}, GOTO_TIMEOUT, show=False):
                why = self._not_arrived({cmd.joint.address: cmd.value})
                raise CommandError(f"{cmd.joint.short} did not arrive within {GOTO_TIMEOUT:g} s: {why}; "
                                   + self._cancel([cmd.joint.address], "goto timed out"), usage=False)
        if not cmd.filter:  # the original: a dot per 0.1 rad step, then 'done'; 'goto filter' printed nothing
            dots = "" if cmd.step else "." * original_steps(float(state.joint[cmd.joint.address].ref), cmd.value)
            self.out(dots + "done")
        how = f" in {steps} steps of {GOTO_STEP:g} rad every {GOTO_STEP_PERIOD:g} s" if cmd.step else ""
        self.say(f"{cmd.joint.short} -> {cmd.value:.5f} rad{how} (sent to {mds.MDS_CHAN_REF_FILTER_NAME})")

    def _ramp(self, address: int, target: float, state: mds.MDS_STATE) -> tuple[int, float]:
        """The original console's goto: from the joint's current reference toward ``target`` in ``GOTO_STEP``
        steps every ``GOTO_STEP_PERIOD`` s (absolute schedule), a dot per step, the last step exactly on the
        target. Every intermediate value lies between two in-range values, so it is in range too. Returns the
        number of steps written and when the last (the target) was sent, for ``_confirm_applied``."""
        pos = float(state.joint[address].ref)
        steps = 0
        next_at = time.monotonic()
        while True:
            delta = target - pos
            pos = target if abs(delta) <= GOTO_STEP else pos + math.copysign(GOTO_STEP, delta)
            sent_at = time.monotonic()
            self._put_refs({address: pos}, state)
            steps += 1
            self.progress()
            if pos == target:
                break
            next_at += GOTO_STEP_PERIOD
            time.sleep(max(0.0, next_at - time.monotonic()))
        return steps, sent_at

    def _cancel(self, addresses: list[int], reason: str) -> str:
        """A command that timed out stops being a target: CANCEL it where the reference is (the mux drops it
        for good, so the arm does not move on to it later, e.g. when the collision gate clears)."""
        ack = lifecycle.request(lifecycle.HOLD_CANCEL, addresses, source="console", reason=reason)
        if ack.ok:
            return "cancelled: the joints hold where they are"
        return f"could not cancel the target ({ack.message}): use 'hold'"

    def hold(self, cmd: Hold) -> None:
        ack = lifecycle.request(cmd.action, cmd.addresses, source="console",
                                reason=f"console {'hold' if cmd.action == lifecycle.HOLD_HOLD else 'resume'}")
        if not ack.ok:
            raise CommandError(ack.message, usage=False)
        verb = "held" if cmd.action == lifecycle.HOLD_HOLD else "resumed"
        summary = held_summary(ack.state, enabled_joints(self.state.read()), resume="resume")
        self.out(f"{verb}: {cmd.what}; held now: {summary}")

    def zeroall(self) -> None:
        """Every enabled joint to 0 rad, or to the value nearest 0 inside its effective limits (the original
        wrote 0 everywhere, unchecked; refusing all of them for one joint whose range excludes 0 helped nobody).

        All or nothing: nothing is sent while a joint that would move is owned by a higher-priority controller
        (after ``RELEASE_TIMEOUT`` s) or held/cancelled (``hold``: a re-put does not release it), and the error
        names those joints; the mux applies the frame whole (every put on mds-ref-filter is a command)."""
        state = self._state()
        limits = current_limits()
        targets: dict[int, float] = {}
        nearest: list[str] = []
        for j in JOINTS:
            if not state.joint[j.address].enabled:
                continue
            rng = limits.range(j.address)
            if rng is None:  # no limits: nothing may be commanded (what _check_target says)
                self._check_target(j, 0.0, state)
                continue
            value = min(max(0.0, rng[0]), rng[1])
            targets[j.address] = value
            if value != 0.0:
                nearest.append(f"{j.short} {value:.5f} (range [{rng[0]:.5f}, {rng[1]:.5f}])")
        for a, v in targets.items():
            self._check_target(mds.BY_ADDRESS[a], v, state)
        self._wait_until_free(list(targets))
        self._refuse_held(targets)
        sent_at = time.monotonic()
        self._put_refs(targets, state)
        self._confirm_applied(targets, sent_at)
        self.say(f"{len(targets)} enabled joints -> 0 rad (sent to {mds.MDS_CHAN_REF_FILTER_NAME})")
        if nearest:  # the original printed nothing: a note, on stderr
            self.err(f"0 rad is outside the limits ({limits.describe()}) of {len(nearest)}; nearest in range: "
                     + ", ".join(nearest))

    def _refuse_held(self, targets: dict[int, float]) -> None:
        """CommandError naming the joints of ``targets`` that are held or cancelled (mds-mux-state ``held``) and
        would have to move (the mux output is elsewhere): the mux would leave them, so nothing is sent."""
        chan = Latest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
        out = Latest(mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_REF)
        try:
            st = self._mux_state(time.monotonic(), chan)
            output = out.read()
        finally:
            chan.close()
            out.close()
        if st is None or output is None:
            raise CommandError(NOT_RUNNING + "; nothing sent", usage=False)
        stuck = {a: st.held[a] for a, v in targets.items()
                 if st.held[a] != MUX_FREE and not abs(output.joint[a].ref - v) <= APPLIED_TOLERANCE}
        if stuck:
            text = ", ".join(f"{mds.BY_ADDRESS[a].short} ({'held' if h == MUX_HELD else 'cancelled'})"
                             for a, h in stuck.items())
            raise CommandError(f"not sent: {text}; 'resume' releases held joints, 'goto' a cancelled one; "
                               "nothing moved", usage=False)

    def get(self, joint: Joint) -> None:
        """The original's two lines, under the joint's long (anatomy) name as the original printed it."""
        state = self._state()
        js = state.joint[joint.address]
        name = get_name(bytes(js.name)) or joint.name
        self.out(f"{name}  State =  {js.pos:.5f}  rad")
        self.out(f"{name}  Ref   =  {js.ref:.5f}  rad")
        age = self.state.age()
        if age is not None and age > 1.0:
            self.err(f"(state is {age:.1f} s old: is the daemon running?)")

    def get_fk(self, arm: str) -> None:
        state = self._state()
        q = [state.joint[BY_SHORT[s].address].ref for s in ARMS[arm][1]]
        for line in format_fk(arm, *fk_pose(q, arm)):
            self.out(line)

    def ik(self, cmd: Ik) -> None:
        from mds_ach.nodes.ik_client import IkClient, IkTimeout  # lazy: numpy (kinematics), ~90 ms of console start

        if not cmd.send:
            self._ik_preview(cmd)
            return
        self._state()  # a clear message when the system is not running
        self._require_mux()
        values = list(cmd.values) + [0.0] * (6 - cmd.dof)
        sent_at = time.monotonic()
        with IkClient() as client:
            try:
                reply = client.request(cmd.arm, cmd.dof, values, timeout=IK_TIMEOUT)
            except IkTimeout as exc:
                raise CommandError(str(exc), usage=False) from None
            self._ik_result(cmd, reply, sent_at, client)

    def _ik_preview(self, cmd: Ik) -> None:
        """ik3/ik5 without 'set': solve from the current references with the IK library (within the effective
        limits) and print the original's lines; nothing is sent."""
        from mds_ach.kinematics.ik import getFkArm, getPosCurrentFromOrder, order_for_dof, solve  # lazy: numpy

        state = self._state()
        shorts = ARMS[cmd.arm][1]
        q0 = [state.joint[BY_SHORT[s].address].ref for s in shorts]
        order = order_for_dof(cmd.dof)
        result = solve(list(cmd.values), order, cmd.arm, q0)
        got = getPosCurrentFromOrder(getFkArm(result.q, cmd.arm), order)
        for line in format_ik(cmd.arm, list(cmd.values), [float(g) for g in got]):
            self.out(line)
        joints = ", ".join(f"{s} {v:.5f}" for s, v in zip(shorts, result.q, strict=True))
        if not result.success:
            self.err(f"no solution within {result.iterations} iterations (closest: {joints}); nothing sent")
            raise CommandError(f"ik{cmd.dof} {cmd.arm}: target not reachable", usage=False)
        self.say(f"joints: {joints}")
        self.say(f"not sent: add 'set' to move the arm (ik{cmd.dof} {cmd.arm} ... set)")

    def _ik_result(self, cmd: Ik, reply: IkReply, sent_at: float, client: IkClient) -> None:
        """Print the answer; with ``wait``, follow the arm until it arrives or the gate stops it at contact."""
        if not reply.success:
            self.err(reply.message or "unreachable; nothing moved")
            raise CommandError(f"ik {cmd.arm} {cmd.dof}: target not reachable", usage=False)
        if cmd.shorthand:  # ik3/ik5 ... set: the original printed its solution lines, then put it
            from mds_ach.kinematics.ik import getFkArm, getPosCurrentFromOrder, order_for_dof  # lazy: numpy

            got = getPosCurrentFromOrder(getFkArm(list(reply.q), cmd.arm), order_for_dof(cmd.dof))
            for line in format_ik(cmd.arm, list(cmd.values), [float(g) for g in got]):
                self.out(line)
        self.say(f"solved: error {reply.error:.5f} in {reply.iterations} iterations ({reply.time * 1000:.1f} ms)")
        for line in format_fk(cmd.arm, *fk_pose(reply.q, cmd.arm)):
            self.say(line)
        targets = {BY_SHORT[s].address: float(v) for s, v in zip(ARMS[cmd.arm][1], reply.q, strict=True)}
        self._confirm_applied(targets, sent_at, mds.MDS_CHAN_REF_IK_NAME)  # the IK node's output, a mux input
        if cmd.wait:
            stop: list[str] = []

            def stopped() -> bool:
                if not stop and (msg := client.stopped(reply)) is not None:
                    stop.append(msg)
                return bool(stop)

            if not self._wait_arrival(targets, IK_MOTION_TIMEOUT, stopped):
                if stop:  # the collision gate stopped the arm at contact; its command is cancelled
                    raise CommandError(f"the {cmd.arm} arm {stop[0]}", usage=False)
                why = self._not_arrived(targets)
                raise CommandError(f"the {cmd.arm} arm did not arrive within {IK_MOTION_TIMEOUT:g} s: {why}; "
                                   + self._cancel(list(targets), "ik timed out"), usage=False)
            self.out("done")

    def run_line(self, line: str) -> bool:
        """Parse and execute one line, printing errors; True on success. Never raises for bad input."""
        try:
            self.execute(parse(line))
            return True
        except CommandError as exc:
            return not report_error(self, line, exc)


_DEFAULT_CONTROLLERS = {mds.MDS_CHAN_REF_FILTER_NAME: "default", mds.MDS_CHAN_REF_IK_NAME: "ik"}


@lru_cache(maxsize=4)
def _controller_for(channel: str) -> str:
    """The mux controller fed by ``channel`` (config/mux.yaml): 'default' for mds-ref-filter, 'ik' for
    mds-ref-ik unless configured otherwise."""
    try:
        from mds_ach.nodes.mux import load_config  # lazy: the mux node module loads rclpy+numpy, ~190 ms

        for c in load_config()["controllers"]:
            if c.channel == channel:
                return c.name
    except (ValueError, OSError):
        pass
    return _DEFAULT_CONTROLLERS.get(channel, channel)


def _took_frame_since(st: MDS_MUX_STATE, controller: str, since: float) -> bool:
    """Did the mux receive a frame from ``controller`` at or after ``since`` (CLOCK_MONOTONIC)?
    ``age`` is the time from that frame's arrival to ``st.time``, so the arrival is ``st.time - age``."""
    names = st.controller_names()
    if controller not in names:
        return False
    i = names.index(controller)
    return st.age[i] >= 0 and st.time - st.age[i] >= since


def _default_out(text: str) -> None:
    print(text, flush=True)


# --------------------------------------------------------------------------------------------- interactive


def history_path() -> Path:
    """$MDS_ACH_HISTORY, else $XDG_STATE_HOME/mds-ach/console_history (~/.local/state/...)."""
    env = os.environ.get("MDS_ACH_HISTORY")
    if env:
        return Path(env)
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "mds-ach" / "console_history"


def _completer(text: str, index: int) -> str | None:
    import readline  # already loaded by _setup_readline; see there why not at module top

    words = readline.get_line_buffer()[: readline.get_begidx()].split()
    if not words:
        options = ["goto", "get", "ik", "ik3", "ik5", "hold", "resume", "zeroall", "help", "exit"]
    elif words[0] == "get" and len(words) == 1:
        options = ["fk"] + [j.short for j in JOINTS]
    elif (words[0] in ("ik", "ik3", "ik5") and len(words) == 1) or (words[:2] == ["get", "fk"] and len(words) == 2):
        options = list(ARMS)
    elif words[0] == "goto" and len(words) == 1:
        options = [j.short for j in JOINTS]
    else:
        options = []
    matches = [o + " " for o in options if o.lower().startswith(text.lower())]
    return matches[index] if index < len(matches) else None


def _setup_readline() -> Callable[[], None]:
    """Line editing, history and tab completion; returns the function that saves the history."""
    try:  # not at module top: importing readline changes input() in every importer, only the console wants it
        import readline
    except ImportError:  # pragma: no cover - readline is part of CPython on Linux
        return lambda: None
    path = history_path()
    try:
        readline.read_history_file(path)
    except (OSError, UnicodeDecodeError):
        pass
    readline.set_history_length(1000)
    readline.set_completer(_completer)
    readline.set_completer_delims(" \t")
    readline.parse_and_bind("tab: complete")

    def save() -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            readline.write_history_file(path)
        except OSError:
            pass

    return save


def _wake_readline_on_signals() -> Callable[[], None]:
    """Make Ctrl-C and SIGTERM reach a prompt at once; returns the function that undoes it.

    CPython's readline loop runs signal handlers only when its ``select()`` on the terminal is interrupted. A
    signal that lands while it is processing keys (echoing them) only sets the handler's flag, and the prompt then
    sleeps in ``select()`` until the next key: Ctrl-C seemed ignored and SIGTERM never ended the console (measured:
    6 of 15 Ctrl-C on a loaded machine, seen with strace). A thread with every signal blocked (the kernel never
    delivers one to it) reads Python's signal wakeup fd and, until the handler has run, interrupts the main thread
    every 20 ms with SIGUSR1 (a no-op handler): its EINTR makes readline run the pending handler. And the terminal
    gets NOFLSH: Ctrl-C flushing the typed-ahead input could take the key readline had just been told was there,
    and readline then waits for another key inside its own read loop, where no handler runs (1 in 5 Ctrl-C typed
    right after a key)."""
    main = threading.main_thread().ident
    tty_before = termios.tcgetattr(sys.stdin.fileno())
    tty = termios.tcgetattr(sys.stdin.fileno())
    tty[3] |= termios.NOFLSH
    termios.tcsetattr(sys.stdin.fileno(), termios.TCSANOW, tty)
    counts = [0, 0]  # signals seen on the wakeup fd, handler runs
    previous: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        inner = signal.getsignal(sig)
        if callable(inner):
            def handler(signum: int, frame: Any, inner: Callable[[int, Any], Any] = inner) -> None:
                counts[1] += 1
                inner(signum, frame)

            previous[sig] = signal.signal(sig, handler)
    r, w = os.pipe()
    os.set_blocking(w, False)
    previous[signal.SIGUSR1] = signal.signal(signal.SIGUSR1, lambda signum, frame: None)
    previous_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def watch() -> None:
        while data := os.read(r, 64):
            counts[0] += sum(1 for b in data if b in previous and b != signal.SIGUSR1)
            deadline = time.monotonic() + 2.0
            while counts[1] < counts[0] and time.monotonic() < deadline and main is not None:
                signal.pthread_kill(main, signal.SIGUSR1)
                time.sleep(0.02)
            counts[0] = min(counts[0], counts[1])  # several signals may run one handler: never kick forever

    mask = signal.pthread_sigmask(signal.SIG_BLOCK, signal.valid_signals())  # inherited by the thread
    try:
        threading.Thread(target=watch, name="console-signal-wake", daemon=True).start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)

    def undo() -> None:
        try:
            termios.tcsetattr(sys.stdin.fileno(), termios.TCSANOW, tty_before)
        except termios.error:
            pass  # the terminal is gone
        signal.set_wakeup_fd(previous_fd)
        for sig, old in previous.items():
            signal.signal(sig, old)
        os.close(w)  # the thread's read returns b"" and it ends

    return undo


def interactive(console: Console) -> int:
    """The prompt loop: Ctrl-C abandons the current line or command, Ctrl-D or 'exit' quits."""
    save = _setup_readline() if sys.stdin.isatty() else (lambda: None)
    unwake = _wake_readline_on_signals() if sys.stdin.isatty() else (lambda: None)
    if sys.stdin.isatty():
        console.out("MDS-Ach console. Type 'help' for the commands, 'exit' to quit.")
    status = 0
    try:
        while True:
            try:
                line = input(PROMPT) if sys.stdin.isatty() else sys.stdin.readline()
                if not sys.stdin.isatty():
                    if not line:
                        break
                    print(PROMPT + line.rstrip("\n"), flush=True)
            except EOFError:
                console.out("")
                break
            except KeyboardInterrupt:
                console.out("")
                continue
            try:
                cmd = parse(line)
            except CommandError as exc:
                status = 1 if report_error(console, line, exc) else status
                continue
            if isinstance(cmd, Simple) and cmd.name == "exit":
                break
            try:
                console.execute(cmd)
            except CommandError as exc:
                status = 1 if report_error(console, line, exc) else status
            except KeyboardInterrupt:
                console.out("\n  interrupted")
    finally:
        unwake()
        save()
    return status if not sys.stdin.isatty() else 0


def run_commands(console: Console, commands: Sequence[str]) -> int:
    """``-c`` mode: run each command in order, stop at the first failure (exit 1), 'exit' stops with 0."""
    for line in commands:
        try:
            cmd = parse(line)
        except CommandError as exc:
            if report_error(console, line, exc):
                return 1
            continue
        if isinstance(cmd, Simple) and cmd.name == "exit":
            return 0
        try:
            console.execute(cmd)
        except CommandError as exc:
            if report_error(console, line, exc):
                return 1
    return 0


# --------------------------------------------------------------------------------------------- entry points


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = help_paragraph(
        "The MDS-Ach console: move joints (goto), read them (get, get fk) and send Cartesian targets (ik), through "
        "the mux, smoothing filter and collision gate. Without -c it is interactive (line editing, history, tab "
        "completion); commands are read from stdin when it is not a terminal.")
    p.epilog = USAGE + "\n\nexamples:\n  mds-ach console -c 'get fk left'\n  mds-ach console -c 'goto LSP -0.3 wait' " \
                       "-c 'get LSP'"
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("-c", "--command", action="append", default=[], metavar="CMD",
                   help="run CMD and exit (repeatable; stops at the first failure, exit status 1)")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="also print what the original console did not: where a command went, the IK solution "
                        "and its pose, how many joints zeroall moved")
    p.add_argument("legacy", nargs="?", choices=["read"], help=argparse.SUPPRESS)  # 'mds_console.py read'


def run(args: argparse.Namespace) -> int:
    console = Console(verbose=args.verbose)
    previous = signal.signal(signal.SIGTERM, _sigterm)
    try:
        if args.command:
            return run_commands(console, args.command)
        return interactive(console)
    except _TerminatedError:
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
        console.close()


class _TerminatedError(Exception):
    pass


def _sigterm(signum: int, frame: object) -> None:
    raise _TerminatedError


def main(argv: list[str] | None = None) -> int:
    argv = strip_ros_args(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="console")
    add_arguments(parser)
    try:
        return run(parser.parse_args(argv))
    except BrokenPipeError:  # `mds-ach-console -c ... | head -1`
        return stdout_closed()


if __name__ == "__main__":
    raise SystemExit(main())
