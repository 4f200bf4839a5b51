"""The packed struct layouts are a wire contract with C clients: every size and offset from mds-original.md §a.5."""

from __future__ import annotations

import ctypes

import pytest

import mds_ach as mds
from mds_ach.robot import msgs


def offsets(ctype: type[ctypes.Structure]) -> dict[str, int]:
    return {name: getattr(ctype, name).offset for name, *_ in ctype._fields_}


def field_type(ctype: type[ctypes.Structure], name: str) -> type:
    return dict((n, t) for n, t, *_ in ctype._fields_)[name]


@pytest.mark.parametrize(
    ("ctype", "size"),
    [
        (msgs.MDS_JOINT_REF, 10),
        (msgs.MDS_REF, 1000),
        (msgs.MDS_JOINT_STATE, 138),
        (msgs.MDS_POWER, 24),
        (msgs.MDS_JNT_COLLIDE, 20),
        (msgs.MDS_COLLIDE, 218),
        (msgs.MDS_STATE, 14051),
        (msgs.MDS_JNT_PARAM, 290),
        (msgs.MDS_JOINT_PARAM, 29000),
        (msgs.MDS_IK_ARM, 50),
        (msgs.MDS_IK, 102),
    ],
)
def test_sizes(ctype: type[ctypes.Structure], size: int) -> None:
    assert ctypes.sizeof(ctype) == size


def test_joint_ref_offsets() -> None:
    assert offsets(msgs.MDS_JOINT_REF) == {"ref": 0, "mode": 8}
    assert field_type(msgs.MDS_JOINT_REF, "mode") is ctypes.c_int16
    assert offsets(msgs.MDS_REF) == {"joint": 0}
    assert msgs.MDS_REF.joint.size == 1000


def test_joint_state_offsets() -> None:
    assert offsets(msgs.MDS_JOINT_STATE) == {
        "ref_r": 0,
        "ref": 8,
        "ref_c_send": 16,
        "ref_c": 24,
        "pos": 32,
        "cur": 40,
        "vel": 48,
        "offset": 56,
        "direction": 64,
        "enabled": 72,
        "address": 74,
        "active": 76,
        "homed": 77,
        "name": 78,
        "nameshort": 108,
    }
    assert msgs.MDS_JOINT_STATE.name.size == 30
    assert msgs.MDS_JOINT_STATE.nameshort.size == 30
    assert field_type(msgs.MDS_JOINT_STATE, "enabled") is ctypes.c_int16
    assert field_type(msgs.MDS_JOINT_STATE, "active") is ctypes.c_uint8


def test_state_offsets() -> None:
    assert offsets(msgs.MDS_STATE) == {"joint": 0, "collide": 13800, "power": 14018, "time": 14042, "refWait": 14050}
    assert field_type(msgs.MDS_STATE, "refWait") is ctypes.c_uint8  # uint8 as in C, not the old c_int16
    assert field_type(msgs.MDS_STATE, "time") is ctypes.c_double
    assert offsets(msgs.MDS_POWER) == {"voltage": 0, "current": 8, "power": 16}


def test_collide_offsets() -> None:
    assert offsets(msgs.MDS_JNT_COLLIDE) == {"collision": 0, "isCollide": 2, "time": 4, "time_dt": 12}
    assert offsets(msgs.MDS_COLLIDE) == {"joint": 0, "isCollide": 200, "time": 202, "time_dt": 210}
    assert msgs.MDS_COLLIDE.joint.size == 200


def test_jnt_param_offsets() -> None:
    doubles = ["rom", "encoderresolution", "gearratio", "HomeAcceleration", "HomeVelocity", "HomeError",
               "HomeBuffer", "HomeTimeout", "MCB_KP", "MCB_KI", "MCB_KD", "MCB_KM", "safetymargin",
               "encoderconfig_tickspercount", "rom_margin", "offset", "direction"]
    expected = {name: 8 * i for i, name in enumerate(doubles)}
    expected.update({"enabled": 136, "address": 138, "coordsys": 140, "HomeType": 170, "HomeTarget": 200,
                     "name": 230, "nameshort": 260})
    assert offsets(msgs.MDS_JNT_PARAM) == expected
    assert field_type(msgs.MDS_JNT_PARAM, "address") is ctypes.c_uint16
    assert offsets(msgs.MDS_JOINT_PARAM) == {"joint": 0}


def test_ik_offsets() -> None:
    assert offsets(msgs.MDS_IK_ARM) == {"t_x": 0, "t_y": 8, "t_z": 16, "r_x": 24, "r_y": 32, "r_z": 40,
                                        "ik_method": 48}
    assert offsets(msgs.MDS_IK) == {"arm": 0, "move": 100}


def test_array_element_positions() -> None:
    """Arrays are indexed by CAN address: joint[0x5F] of MDS_STATE starts at 0x5F * 138."""
    st = msgs.MDS_STATE()
    st.joint[mds.LSP].pos = 1.25
    raw = bytes(st)
    assert raw[0x5F * 138 + 32:0x5F * 138 + 40] == bytes(ctypes.c_double(1.25))
    ik = msgs.MDS_IK()
    ik.arm[mds.LEFT].ik_method = 6
    assert bytes(ik)[50 + 48:50 + 50] == b"\x06\x00"


def test_little_endian_packed() -> None:
    ref = msgs.MDS_REF()
    ref.joint[1].mode = 0x0102
    assert bytes(ref)[18:20] == b"\x02\x01"


def test_constants() -> None:
    assert mds.MDS_CHAN_REF_NAME == "mds-ref"
    assert mds.MDS_CHAN_REF_FILTER_NAME == "mds-ref-filter"
    assert mds.MDS_CHAN_STATE_NAME == "mds-state"
    assert mds.MDS_CHAN_PARAM_NAME == "mds-param"
    assert mds.MDS_CHAN_IK_NAME == "mds-ik"
    assert mds.MDS_CHAN_COLLIDE_NAME == "mds-collide"
    assert mds.LEFT == 1
    assert mds.RIGHT == 0
    assert (mds.MDS_REF_MODE_REF_FILTER, mds.MDS_REF_MODE_REF, mds.MDS_REF_MODE_COMPLIANT,
            mds.MDS_REF_MODE_ENC_FILTER) == (0, 1, 2, 3)
    assert mds.getAddress("LSP") == 0x5F
    assert mds.getAddress("LSP", msgs.MDS_STATE()) == 0x5F
    assert mds.LSP == 0x5F
    assert len(mds.JOINTS) == 43
    assert len({j.address for j in mds.JOINTS}) == 43
    assert mds.CHANNEL_FRAME_COUNT == 10
    assert mds.CHANNEL_FRAME_SIZE == 3000


@pytest.mark.parametrize(
    ("short", "name", "address"),
    [("REP", "RightElbowFlex", 0x48), ("RSY", "RightUpperArmRoll", 0x49), ("RSR", "RightShoulderAbd", 0x4B),
     ("LEP", "LeftElbowFlex", 0x4C), ("LSY", "LeftUpperArmRoll", 0x4D), ("LSR", "LeftShoulderAbd", 0x4F),
     ("RWR", "RightWristFlex", 0x50), ("RWY", "RightWristRoll", 0x52), ("LWR", "LeftWristFlex", 0x54),
     ("LWY", "LeftWristRoll", 0x56), ("RSP", "RightShoulderExt", 0x5B), ("WST", "TorsoPan", 0x5C),
     ("LSP", "LeftShoulderExt", 0x5F)],
)
def test_mds_h_joint_constants(short: str, name: str, address: int) -> None:
    """The 13 arm/torso constants of mds.h, each under its short and long name (§a.3)."""
    assert getattr(mds, short) == address
    assert getattr(mds, name) == address
    assert mds.getAddress(short) == address
    assert mds.getAddress(name) == address


# --- the new structs (not in the original mds.h): their layouts are contracts with C clients just the same ---


def test_new_struct_sizes() -> None:
    assert ctypes.sizeof(msgs.MDS_CMD) == 16
    assert ctypes.sizeof(msgs.MDS_IK_STATUS) == 214
    assert ctypes.sizeof(msgs.MDS_MUX_STATE) == 920
    assert ctypes.sizeof(msgs.MDS_DAEMON_STATUS) == 2132


def test_cmd_offsets() -> None:
    assert offsets(msgs.MDS_CMD) == {"seq": 0, "cmd": 4, "address": 6, "value": 8}


def test_ik_status_offsets() -> None:
    assert offsets(msgs.MDS_IK_STATUS) == {"seq": 0, "status": 4, "arm": 6, "dof": 8, "iterations": 10, "error": 14,
                                           "solve_time": 22, "target": 30, "q": 78, "stamp": 126, "message": 134}
    assert field_type(msgs.MDS_IK_STATUS, "iterations") is ctypes.c_int32


def test_mux_state_offsets() -> None:
    assert offsets(msgs.MDS_MUX_STATE) == {"owner": 0, "count": 100, "priority": 102, "stale": 118, "age": 126,
                                           "change_age": 190, "name": 254, "time": 494, "seq": 502,
                                           # appended with the command lifecycle (issue 17)
                                           "held": 506, "hold_seq": 606, "hold_action": 610, "hold_status": 612,
                                           "hold_source": 614, "verdict": 644, "blocker": 652, "blocked_joint": 660,
                                           "refused": 668,
                                           # appended with issue 25
                                           "hold_reason": 700,
                                           # appended with issue 26
                                           "clamped": 820}
    assert msgs.MDS_MUX_STATE.name.size == 8 * 30


def test_daemon_status_offsets() -> None:
    got = offsets(msgs.MDS_DAEMON_STATUS)
    assert {k: got[k] for k in ("version", "pid", "time", "cycle", "bus_state", "cmd_result", "joint_flags",
                                "joint_age", "channel_errors", "joint_limited", "joint_reseed", "lock_timeouts",
                                "loop_policy", "loop_priority", "memory_locked")} == {
        "version": 0, "pid": 2, "time": 6, "cycle": 22, "bus_state": 134, "cmd_result": 234, "joint_flags": 235,
        "joint_age": 435, "channel_errors": 835, "joint_limited": 883, "joint_reseed": 1683, "lock_timeouts": 2083,
        # appended in version 3 (the loop thread's scheduling, issue 25)
        "loop_policy": 2087, "loop_priority": 2088, "memory_locked": 2089}


def test_every_struct_is_packed_little_endian() -> None:
    """One base for all of them: byte-packed, little-endian, exact-size decoding."""
    for cls in (msgs.MDS_REF, msgs.MDS_STATE, msgs.MDS_JOINT_PARAM, msgs.MDS_IK, msgs.MDS_COLLIDE, msgs.MDS_CMD,
                msgs.MDS_IK_STATUS, msgs.MDS_MUX_STATE, msgs.MDS_DAEMON_STATUS):
        assert issubclass(cls, msgs.Packed) and cls._pack_ == 1
        assert cls.from_bytes(bytes(ctypes.sizeof(cls))).to_bytes() == bytes(ctypes.sizeof(cls))
        with pytest.raises(ValueError, match=cls.__name__):
            cls.from_bytes(b"\0")
