"""``MDS_DAEMON_STATUS``: the daemon's health on channel ``mds-daemon-status`` (new; not in the original).

Published once per cycle next to ``mds-state`` so monitors (``read``, ``mds-ach status``) can tell a
healthy loop from a late one, a quiet node from a live one, and a loaded bus from a faulty one without
ROS. Packed little-endian like every MDS struct; per-joint arrays are indexed by CAN address.

Version 2 adds what the daemon did to keep every sent target inside the motion bounds (``mds_ach.robot.motion``):
targets it had to limit, position replies it refused, its own stalls, and ``joint_reseed``, the counters the
pipeline nodes (mux, filter, collision gate) watch to restart a joint's reference where the joint is.

Version 3 appends how the control loop thread is scheduled (``loop_policy``, ``loop_priority``, ``memory_locked``):
whether it runs real-time (SCHED_FIFO/SCHED_RR, it then keeps its period under CPU load) or at normal priority
(it may stall for seconds on a loaded machine; the bus stays safe). The layout of versions 1-2 is unchanged.

Version 4 appends the collaborative mode (``collaborative``, its Cartesian bound and what it took to keep it,
``mds_ach.kinematics.cartesian``) and the e-stop (``estop``: ESTOP_*; latched across restarts).
"""

from __future__ import annotations

import ctypes

from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, _Packed

DAEMON_STATUS_VERSION = 4  # 2: motion bounds, stalls, limited targets, bad replies, re-seeds, lock_timeouts
# 3: the loop thread's scheduling (loop_policy, loop_priority, memory_locked)
# 4: collaborative mode and e-stop

# ``estop``: the category-1 e-stop's state.
ESTOP_OFF = 0
ESTOP_STOPPING = 1  # latched: every joint brakes at the bounds, then the drives get DISABLE
ESTOP_STOPPED = 2  # latched: the drives were sent DISABLE; nothing moves until `mds-ach estop reset`, then enable
ESTOP_NAMES = {ESTOP_OFF: "off", ESTOP_STOPPING: "STOPPING", ESTOP_STOPPED: "STOPPED"}

# ``loop_policy``: Linux's policy numbers (os.SCHED_*).
LOOP_POLICY_NAMES = {0: "SCHED_OTHER", 1: "SCHED_FIFO", 2: "SCHED_RR", 3: "SCHED_BATCH", 5: "SCHED_IDLE"}
REALTIME_POLICIES = (1, 2)  # SCHED_FIFO, SCHED_RR

BUS_STATE_ACTIVE = 0  # error-active: all fine
BUS_STATE_PASSIVE = 1  # error-passive / warning level: frames get through, errors seen
BUS_STATE_BUS_OFF = 2  # nothing gets through until the bus is reset (mds-ach resetbus)
BUS_STATE_NAMES = {BUS_STATE_ACTIVE: "active", BUS_STATE_PASSIVE: "error-passive", BUS_STATE_BUS_OFF: "bus-off"}

# Joint flags (``joint_flags[address]``, a bit set).
JOINT_CONFIGURED = 0x01  # in the joint table
JOINT_ENABLED = 0x02  # commands are sent to it
JOINT_FRESH = 0x04  # answered recently enough: state.pos is current
JOINT_STALE = 0x08  # no answer for longer than the staleness limit (or never)
JOINT_CLAMPED = 0x10  # the last reference was outside the joint limits and was clamped
JOINT_REFUSED = 0x20  # the last reference was NaN/Inf and was refused (previous one held)
JOINT_MOVING = 0x40  # a new target was sent this cycle
JOINT_LIMITED = 0x80  # this cycle's target was limited to the motion bounds (it differs from the reference)
JOINT_BAD_REPLY = 0x100  # position replies are implausible (out of range, impossible jump): pos holds the last good
JOINT_UNREFERENCED = 0x200  # its count restarted (ZERO_ENCODER, RESET, HOME timed out): no target, pos NaN until HOME
JOINT_FOLLOW_FAULT = 0x400  # mode 2/3: replies and the motion disagree (a reply fed back): held until ENABLE or HOME
JOINT_SLOWED = 0x800  # collaborative mode: this cycle's step was slowed to keep the hands/elbows within the bound

# Command results (``cmd_result``), echoed with ``cmd_seq`` of the last mds-cmd / service command handled.
CMD_OK = 0
CMD_REFUSED = 1  # bad command code, unknown joint, or not allowed
CMD_FAILED = 2  # accepted, but the bus refused the frames


class MDS_DAEMON_STATUS(_Packed):  # noqa: N801 - MDS struct naming
    """Loop timing, bus load and faults, per-joint freshness (all times in seconds, CLOCK_MONOTONIC)."""

    _fields_ = [
        ("version", ctypes.c_uint16),
        ("pid", ctypes.c_int32),
        ("time", ctypes.c_double),  # publish time
        ("start_time", ctypes.c_double),
        ("cycle", ctypes.c_uint64),
        ("rate_hz", ctypes.c_double),  # configured
        ("measured_rate_hz", ctypes.c_double),  # over the statistics window
        ("period_error", ctypes.c_double),  # this cycle: actual period - nominal
        ("period_error_p50", ctypes.c_double),  # |period error| over the window
        ("period_error_p99", ctypes.c_double),
        ("period_error_max", ctypes.c_double),
        ("wake_latency_max", ctypes.c_double),  # worst wake-up after the deadline in the window
        ("cycle_time", ctypes.c_double),  # work time of the last cycle (wall)
        ("cycle_time_max", ctypes.c_double),
        ("cpu_per_cycle", ctypes.c_double),  # thread CPU time per cycle, window mean
        ("overruns", ctypes.c_uint32),  # cycles that missed their deadline (work > period)
        ("bus_load", ctypes.c_double),  # percent of the bitrate, last cycle (worst-case stuffing)
        ("bus_load_avg", ctypes.c_double),  # percent, window mean
        ("bitrate", ctypes.c_uint32),
        ("bus_state", ctypes.c_uint8),
        ("nocan", ctypes.c_uint8),
        ("tx_frames", ctypes.c_uint64),
        ("rx_frames", ctypes.c_uint64),
        ("tx_errors", ctypes.c_uint32),
        ("rx_errors", ctypes.c_uint32),
        ("error_frames", ctypes.c_uint32),
        ("bus_off_count", ctypes.c_uint32),
        ("bus_resets", ctypes.c_uint32),
        ("unknown_node_frames", ctypes.c_uint32),
        ("malformed_frames", ctypes.c_uint32),
        ("node_errors", ctypes.c_uint32),  # ERROR replies from nodes (WARNINGs other than "move done" too)
        ("acks_missing", ctypes.c_uint32),  # MOVETOs not ACKed in time (the target is sent again)
        ("refs_received", ctypes.c_uint64),
        ("refs_refused", ctypes.c_uint32),  # joint refs that were NaN/Inf
        ("refs_clamped", ctypes.c_uint32),  # joint refs outside the limits
        ("collision_holds", ctypes.c_uint32),  # cycles with sending held by mds-collide
        ("stale_count", ctypes.c_uint16),  # enabled joints currently stale
        ("replies_expected", ctypes.c_uint16),  # nodes waited for this cycle
        ("replies_received", ctypes.c_uint16),
        ("stale_after", ctypes.c_double),  # s without a reply before a joint counts as stale
        ("filter_length", ctypes.c_double),  # L of the mode-0 filter at this rate
        ("cmd_seq", ctypes.c_uint32),
        ("cmd_result", ctypes.c_uint8),
        ("joint_flags", ctypes.c_uint16 * MDS_JOINT_COUNT),  # JOINT_* bits (uint8 in version 1)
        ("joint_age", ctypes.c_float * MDS_JOINT_COUNT),  # s since the last position reply; -1 never
        ("channel_errors", ctypes.c_uint32),  # Ach channel reads/writes that failed (e.g. a corrupt mds-ref)
        # --- version 2: the motion bounds and what it took to keep them
        ("max_velocity", ctypes.c_double),  # rad/s, bound on every sent target (joint table `motion:`)
        ("max_acceleration", ctypes.c_double),  # rad/s^2
        ("max_interval", ctypes.c_double),  # s, the longest interval a step may count on (motion.MAX_INTERVAL)
        ("stalls", ctypes.c_uint32),  # cycles that started more than 2 periods after the previous one
        ("stall_max", ctypes.c_double),  # s, the longest gap between two cycle starts
        ("targets_limited", ctypes.c_uint32),  # targets the daemon had to limit (all joints)
        ("bad_replies", ctypes.c_uint32),  # position replies refused as implausible (all joints)
        ("joint_limited", ctypes.c_uint32 * MDS_JOINT_COUNT),  # per joint
        ("joint_bad_replies", ctypes.c_uint32 * MDS_JOINT_COUNT),  # per joint
        # Incremented when the joint's reference must restart where the joint is (after HOME, RESET, ZERO_ENCODER,
        # ENABLE, resetbus), once its position is known: the pipeline nodes then set their output for the joint to
        # mds-state joint[].pos of that cycle (mds_ach.nodes.pipeline.ReseedWatch).
        ("joint_reseed", ctypes.c_uint32 * MDS_JOINT_COUNT),
        ("lock_timeouts", ctypes.c_uint32),  # channel reads/writes skipped: the lock was held longer than allowed
        # --- version 3: how the control loop thread runs (set once when the loop starts)
        ("loop_policy", ctypes.c_uint8),  # its scheduling policy: 1 SCHED_FIFO, 2 SCHED_RR (real-time), 0 normal
        ("loop_priority", ctypes.c_uint8),  # its real-time priority (1-99), 0 at normal scheduling
        ("memory_locked", ctypes.c_uint8),  # 1: the daemon's memory is locked (mlockall), no page faults to disk
        # --- version 4: collaborative mode, e-stop
        ("collaborative", ctypes.c_uint8),  # 1: hands and elbows within collaborative_speed (Cartesian, sent targets)
        ("collaborative_speed", ctypes.c_double),  # m/s, the bound in collaborative mode
        ("cartesian_speed", ctypes.c_double),  # m/s, the fastest hand/elbow of the last cycle's targets (collab. mode)
        ("cartesian_speed_max", ctypes.c_double),  # m/s, the fastest in collaborative mode since it was switched on
        ("cartesian_slowed", ctypes.c_uint32),  # cycles whose steps were slowed for the bound
        ("cartesian_braking", ctypes.c_uint32),  # cycles over the bound while braking into it (after a switch)
        ("estop", ctypes.c_uint8),  # ESTOP_*
        ("estop_time", ctypes.c_double),  # CLOCK_MONOTONIC when this daemon latched it (or found it latched)
    ]


def flags_text(flags: int) -> str:
    """Short human form of a joint's flags, e.g. 'en fresh'."""
    names = ((JOINT_ENABLED, "en"), (JOINT_FRESH, "fresh"), (JOINT_STALE, "STALE"), (JOINT_CLAMPED, "clamped"),
             (JOINT_REFUSED, "REFUSED"), (JOINT_MOVING, "moving"), (JOINT_LIMITED, "limited"),
             (JOINT_BAD_REPLY, "BAD-REPLY"), (JOINT_UNREFERENCED, "UNREFERENCED"),
             (JOINT_FOLLOW_FAULT, "FOLLOW-FAULT"), (JOINT_SLOWED, "slowed"))
    return " ".join(n for bit, n in names if flags & bit) or "-"


def loop_scheduling_text(st: MDS_DAEMON_STATUS) -> str:
    """How the loop thread runs, for people: 'real-time (SCHED_FIFO 50, memory locked)' or 'not real-time'."""
    if st.loop_policy not in REALTIME_POLICIES:
        return "not real-time"
    name = LOOP_POLICY_NAMES.get(st.loop_policy, str(st.loop_policy))
    return f"real-time ({name} {st.loop_priority}{', memory locked' if st.memory_locked else ''})"


def summary_line(st: MDS_DAEMON_STATUS) -> str:
    """One line for monitors: rate, timing, bus load and state, staleness, faults."""
    faults = []
    for name, value in (("tx-err", st.tx_errors), ("err-frames", st.error_frames), ("bus-off", st.bus_off_count),
                        ("unknown", st.unknown_node_frames), ("malformed", st.malformed_frames),
                        ("refused", st.refs_refused), ("clamped", st.refs_clamped), ("no-ack", st.acks_missing),
                        ("channel-err", st.channel_errors), ("limited", st.targets_limited),
                        ("bad-reply", st.bad_replies), ("stalls", st.stalls),
                        ("lock-timeouts", st.lock_timeouts),
                        ("unreferenced", sum(1 for f in st.joint_flags if f & JOINT_UNREFERENCED)),
                        ("follow-fault", sum(1 for f in st.joint_flags if f & JOINT_FOLLOW_FAULT))):
        if value:
            faults.append(f"{name} {value}" + (f" (longest {st.stall_max:.2f} s)" if name == "stalls" else ""))
    return (f"{st.measured_rate_hz:.1f}/{st.rate_hz:g} Hz, period err p99 {st.period_error_p99 * 1e3:.2f} ms, "
            f"overruns {st.overruns}, loop {loop_scheduling_text(st)}, "
            f"bus {BUS_STATE_NAMES.get(st.bus_state, '?')} {st.bus_load_avg:.0f}%"
            f"{' (nocan)' if st.nocan else ''}, stale {st.stale_count}, {safety_text(st)}"
            + (", " + ", ".join(faults) if faults else ""))


def safety_text(st: MDS_DAEMON_STATUS) -> str:
    """The e-stop and the mode, for people: 'E-STOP STOPPED, collaborative <= 250 mm/s (slowed 12)'."""
    parts = []
    if st.estop != ESTOP_OFF:
        parts.append(f"E-STOP {ESTOP_NAMES.get(st.estop, '?')}")
    if st.collaborative:
        mode = f"collaborative <= {st.collaborative_speed * 1e3:.0f} mm/s (max {st.cartesian_speed_max * 1e3:.0f}"
        parts.append(mode + (f", slowed {st.cartesian_slowed})" if st.cartesian_slowed else ")"))
    else:
        parts.append("normal mode")
    return ", ".join(parts)
