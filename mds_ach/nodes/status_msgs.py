"""Typed ROS status topics (``mds_ach_interfaces``) built from the nodes' status documents.

Each node already builds one document per report (``mux.state_to_dict``, ``collision.decision_to_dict``,
``ik_status.status_to_dict``: also what ``mds-ach`` tools print); the typed message is made from that same document,
so the topic and the tools can never disagree. Types and fields: interfaces/mds_ach_interfaces/msg/. (The JSON
``<topic>/json`` aliases and the daemon's text command service were removed after their release of deprecation.)
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from builtin_interfaces.msg import Time
from mds_ach_interfaces.msg import (
    CollisionPair,
    CollisionState,
    CollisionUnit,
    CommandStatus,
    DaemonStatus,
    IkStatus,
    MuxController,
    MuxState,
)

from mds_ach.robot.msgs import daemon_status as ds
from mds_ach.robot.msgs.ik_status import IK_STATUS_TOPIC

__all__ = ["COLLISION_TOPIC", "DAEMON_STATUS_TOPIC", "DIAGNOSTICS_TOPIC", "IK_STATUS_TOPIC", "MUX_STATE_TOPIC",
           "collision_state_msg", "command_status_msg", "daemon_status_msg", "ik_status_msg", "mux_state_msg"]

COLLISION_TOPIC = "mds/collision"  # relative, like every name of every node: a namespace moves them all
MUX_STATE_TOPIC = "mds/mux_state"
DAEMON_STATUS_TOPIC = "mds/daemon_status"
DIAGNOSTICS_TOPIC = "diagnostics"  # /diagnostics outside a namespace, where diagnostic_aggregator listens
COLLISION_UNITS = ("left", "right", "body")  # the gate's units: both arms, waist + neck
_HELD = {"held": MuxState.HELD, "cancelled": MuxState.CANCELLED}


def _num(value: float | None) -> float:
    """JSON had null where the value was NaN/Inf or absent; the typed field carries NaN."""
    return math.nan if value is None else float(value)


def _age(value: float | None) -> float:
    return -1.0 if value is None else float(value)


def _stamped(msg: Any, stamp: Time | None) -> Any:
    if stamp is not None:
        msg.header.stamp = stamp
    return msg


def mux_state_msg(doc: Mapping[str, Any], joints: Sequence[str], stamp: Time | None = None) -> MuxState:
    """``mds/mux_state`` from ``mux.state_to_dict``: every joint of ``joints`` with its owner ("" = none) and
    hold state, every controller."""
    msg = MuxState(time=float(doc["time"]))
    msg.controllers = [
        MuxController(name=c["name"], priority=int(c["priority"]), stale=bool(c["stale"]), age=_age(c["age"]),
                      change_age=_age(c["change_age"]), verdict=c["verdict"], refused=int(c["refused"]),
                      blocker=c.get("blocker", ""), blocked_joint=c.get("blocked_joint", ""),
                      clamped=list(c.get("clamped", [])))
        for c in doc["controllers"]]
    msg.joint_names = list(joints)
    msg.owner = [doc["owners"].get(j, "") for j in joints]
    msg.held = [_HELD.get(doc["held"].get(j, ""), MuxState.FREE) for j in joints]
    hold = doc["hold"]
    msg.hold_seq, msg.hold_action = int(hold["seq"]), hold["action"]
    msg.hold_source, msg.hold_status = hold["source"], hold["status"]
    msg.hold_reason = hold["reason"]
    return _stamped(msg, stamp)


def _pairs(pairs: Iterable[Sequence[str]]) -> list[CollisionPair]:
    return [CollisionPair(a=a, b=b) for a, b in pairs]


def collision_state_msg(doc: Mapping[str, Any], stamp: Time | None = None) -> CollisionState:
    """``mds/collision`` from ``collision.decision_to_dict``: the lists of held / releasing / escaping / stopped
    units become one ``CollisionUnit`` per unit (left, right, body), always all three."""
    held = set(doc["held"])
    units = []
    for name in COLLISION_UNITS:
        state = (CollisionUnit.HELD if name in held or "all" in held
                 else CollisionUnit.RELEASING if name in doc["releasing"] else CollisionUnit.FREE)
        reason = doc["stopped"].get(name, "")
        units.append(CollisionUnit(unit=name, state=state, escaping=name in doc["escaping"], stopped=bool(reason),
                                   stopped_reason=reason))
    msg = CollisionState(time=float(doc["time"]), collision=bool(doc["collision"]), pairs=_pairs(doc["pairs"]),
                         parts=list(doc["parts"]), contact=_pairs(doc["contact"]), units=units,
                         measured=bool(doc["measured"]), refused=list(doc["refused"]),
                         refused_count=int(doc["refused_count"]), overridden=bool(doc["overridden"]),
                         override_remaining=float(doc["override_remaining"]), margin=float(doc["margin"]))
    return _stamped(msg, stamp)


def ik_status_msg(doc: Mapping[str, Any], stamp: Time | None = None) -> IkStatus:
    """``mds/ik_status`` from ``ik_status.status_to_dict`` (null numbers become NaN)."""
    msg = IkStatus(seq=int(doc["seq"]), status=int(doc["status"]), status_name=doc["status_name"], arm=doc["arm"],
                   dof=int(doc["dof"]), iterations=int(doc["iterations"]), error=_num(doc["error"]),
                   solve_time=_num(doc["solve_time"]), target=[_num(v) for v in doc["target"]],
                   q=[_num(v) for v in doc["q"]], stamp=float(doc["stamp"]), message=doc["message"])
    return _stamped(msg, stamp)


def daemon_status_msg(st: ds.MDS_DAEMON_STATUS, running: bool, stale: Sequence[str], bad_replies: Sequence[str],
                      stamp: Time | None = None) -> DaemonStatus:
    """``mds/daemon_status``: the summary of an ``mds-daemon-status`` frame (names of stale / untrusted joints
    resolved by the caller, which knows the joint table)."""
    msg = DaemonStatus(
        time=float(st.time), running=bool(running), cycle=int(st.cycle), rate_hz=float(st.rate_hz),
        measured_rate_hz=float(st.measured_rate_hz), period_error_p99=float(st.period_error_p99),
        period_error_max=float(st.period_error_max), cycle_time_max=float(st.cycle_time_max),
        overruns=int(st.overruns), stalls=int(st.stalls), bus_load=float(st.bus_load),
        bus_load_avg=float(st.bus_load_avg), bus_state=int(st.bus_state),
        bus_state_name=ds.BUS_STATE_NAMES.get(int(st.bus_state), str(int(st.bus_state))), nocan=bool(st.nocan),
        tx_errors=int(st.tx_errors), rx_errors=int(st.rx_errors), bus_off_count=int(st.bus_off_count),
        node_errors=int(st.node_errors), refs_refused=int(st.refs_refused), refs_clamped=int(st.refs_clamped),
        targets_limited=int(st.targets_limited), bad_replies=int(st.bad_replies),
        channel_errors=int(st.channel_errors), stale_joints=list(stale), bad_reply_joints=list(bad_replies),
        cmd_seq=int(st.cmd_seq), cmd_result=int(st.cmd_result))
    return _stamped(msg, stamp)


def command_status_msg(doc: Mapping[str, Any], stamp: Time | None = None) -> CommandStatus:
    """The bridge's ``mds/command_status`` from one of its event documents (``event``, ``command``, ``message``;
    ``owner`` and ``frames`` for a mux refusal, ``code`` for a goal's end)."""
    msg = CommandStatus(event=str(doc["event"]), command=str(doc.get("command", "")),
                        message=str(doc.get("message", "")), owner=str(doc.get("owner", "")),
                        frames=int(doc.get("frames", 0)), code=str(doc.get("code", "")))
    return _stamped(msg, stamp)
