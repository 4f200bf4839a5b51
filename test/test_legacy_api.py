"""The original MDS-Ach Python vocabulary (issue #18 §6): the constants and helpers of the original ``mds_ach.py``
that scripts use, ``import mds_ik as ik`` after installation, and no top-level ``ach`` of ours (the drop-in is
``from mds_ach import ach``, so a real py_ach binding stays importable as ``ach``)."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import distribution

import numpy as np
import pytest

import mds_ach as mds
from mds_ach import ach
from mds_ach.paths import user_label
from mds_ach.robot import legacy_names

# Values straight from the original develop-branch mds_ach.py / mds.h (specs/mds-original.md §a), independent of
# the module under test.
ORIGINAL_VALUES = {
    "COLLISION_L_HAND": 0, "COLLISION_R_HAND": 1, "COLLISION_R_SHOULDER": 2, "COLLISION_L_SHOULDER": 3,
    "COLLISION_R_FOREARM": 4, "COLLISION_L_FOREARM": 5, "COLLISION_R_ELBOW": 6, "COLLISION_L_ELBOW": 7,
    "COLLISION_R_WRIST": 8, "COLLISION_L_WRIST": 9,
    "IK1": 1, "IK2": 2, "IK3": 3, "IK4": 4, "IK5": 5, "IK6": 6, "MAX_EFF": 6, "TRUE": 1, "FALSE": 0,
    "RIGHT": 0, "LEFT": 1, "RIGTH": 0, "MDS_JOINT_COUNT": 100, "MDS_ARM_COUNT": 2, "MDS_COLLIDE_JNT_NUM": 10,
    "MDS_CHAR_PARAM_BUFFER_SIZE": 30, "MDS_REF_MODE_REF_FILTER": 0, "MDS_REF_MODE_REF": 1,
    "MDS_REF_MODE_COMPLIANT": 2, "MDS_REF_MODE_ENC_FILTER": 3,
    "MDS_CHAN_REF_NAME": "mds-ref", "MDS_CHAN_REF_FILTER_NAME": "mds-ref-filter", "MDS_CHAN_IK_NAME": "mds-ik",
    "MDS_CHAN_PARAM_NAME": "mds-param", "MDS_CHAN_STATE_NAME": "mds-state", "MDS_CHAN_COLLLIDE_NAME": "mds-collide",
    "MDS_CHAN_COLLIDE_NAME": "mds-collide", "MDS_CHAN_CAN_DAEMON_NAME": "mds-can-daemon",
    "MDS_CHAN_VIRTUAL_TO_SIM_NAME": "mds-virtual-to-sim", "MDS_CHAN_VIRTUAL_FROM_SIM_NAME": "mds-virtual-from-sim",
}  # fmt: skip

# Hubo-era names of the original mds_ach.py -> the MDS joint they name (by CAN address, like mds.LSP == 0x5f).
HUBO_ERA = {"REB": 0x48, "LEB": 0x4C, "NYH": 0x3A, "NPL": 0x39, "NPH": 0x38, "RFR": 0x53, "LFR": 0x57, "H": 0x30}


@pytest.mark.parametrize(("name", "value"), ORIGINAL_VALUES.items())
def test_original_constants(name: str, value: object) -> None:
    assert getattr(mds, name) == value


@pytest.mark.parametrize(("name", "address"), HUBO_ERA.items())
def test_hubo_era_joint_names_are_the_joints_address(name: str, address: int) -> None:
    assert getattr(mds, name) == address
    assert mds.BY_ADDRESS[address]  # a real node


def test_wrist_pitch_names_the_mds_lacks_reach_no_node() -> None:
    """LWP/RWP (Hubo wrist pitch) keep the original values; no MDS node sits there, so nothing moves."""
    assert (mds.LWP, mds.RWP) == (10, 17)
    assert mds.LWP not in mds.BY_ADDRESS and mds.RWP not in mds.BY_ADDRESS


def test_hubo_joint_names_are_the_original_header_array() -> None:
    names = legacy_names.HUBO_JOINT_NAMES
    assert len(names) == 42
    assert (names[0], names[7], names[14], names[18], names[41]) == ("WST", "LEB", "REB", "N/A", "LF5")


def test_get_address_unknown_is_minus_one_like_the_original() -> None:
    assert mds.getAddress("LSP") == 0x5F
    assert mds.getAddress("LeftElbowFlex", mds.MDS_STATE()) == 0x4C
    assert mds.getAddress("NOPE") == -1
    assert mds.getAddress("NOPE", mds.MDS_STATE()) == -1
    with pytest.raises(KeyError, match="unknown joint"):
        mds.lookup("NOPE")  # the modern call still says what is valid


def test_name_helpers_as_the_original_used_them() -> None:
    state = mds.MDS_STATE()
    for j in (mds.BY_SHORT["LSP"], mds.BY_SHORT["NKY"]):
        state.joint[j.address].name = mds.str2ubytes(j.name)  # space padded, as the original parser wrote
        state.joint[j.address].address = j.address
    state.joint[0x44].name = mds.str2ubytes("Mystery")
    state.joint[0x44].address = 0x44
    rows = mds.getNameAndAddress(state)
    assert len(rows) == mds.MDS_JOINT_COUNT
    assert rows[0x5F] == ["LeftShoulderExt", 0x5F]
    named = mds.getNameShort(rows, state)
    assert named[0x5F] == ["LeftShoulderExt", 0x5F, "LSP"]
    assert named[0x3A] == ["HeadPan", 0x3A, "NKY"]
    assert named[0x44] == ["Mystery", 0x44, "-------"]
    assert mds.getAddressOnly("LSP", named) == 0x5F
    assert mds.getAddressOnly("HeadPan", named) == 0x3A
    assert mds.getAddressOnly("RSP", named) == -1  # not in this state frame
    assert bytes(state.joint[0x5F].name) == b"LeftShoulderExt".ljust(30)
    with pytest.raises(ValueError, match="longer than 30"):
        mds.str2ubytes("x" * 31)


@pytest.mark.parametrize("raw", [b"LSP  \0\0\0", bytearray(b"LSP"), [76, 83, 80, 32, 0, 65], (b"L", b"S", b"P", b"\0")])
def test_ubytes2str_takes_every_form_a_name_field_comes_in(raw: object) -> None:
    assert mds.ubytes2str(raw) == "LSP"


def test_p2f() -> None:
    assert mds.p2f("5%") == pytest.approx(0.05)
    assert mds.p2f("50%") == pytest.approx(0.5)


def test_import_mds_ik_after_install() -> None:
    """`import mds_ik as ik` from outside the checkout (the installed module, not the repo file) is the
    package's IK module with the original functions."""
    code = ("import mds_ik as ik, mds_ach.kinematics.ik as k; assert ik is k; "
            "q, ok = ik.getIK([0, 0.3, 0, -1.0, 0, 0], [0.3, 0.2, 0.0], ['p_x', 'p_y', 'p_z'], 'left'); "
            "A = ik.getFkArm(q, 'left'); print(ok, *ik.getPosCurrentFromOrder(A, ['p_x', 'p_y', 'p_z']))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/", timeout=120)
    assert out.returncode == 0, out.stderr
    ok, *pos = out.stdout.split()
    assert ok == "0"
    np.testing.assert_allclose([float(p) for p in pos], [0.3, 0.2, 0.0], atol=1e-3)


def test_legacy_ik_helpers() -> None:
    import mds_ik as ik

    q = ik.getIK3dof([0, 0.3, 0, -1.0, 0, 0], np.array([0.3, 0.2, 0.0]), "left")
    p = ik.getPosCurrentFromOrder(ik.getFkArm(q, "left"), ["p_x", "p_y", "p_z"])
    assert ik.getDist2End(p, np.array([0.3, 0.2, 0.0])) < 1e-3
    assert ik.getDist2End2([0, 0, 0, 0], [3, 0, 0, 4]) == pytest.approx(5.0)


def test_no_top_level_ach_is_installed() -> None:
    """A real py_ach binding (`import ach`) must never be shadowed by this package."""
    files = {str(f) for f in distribution("mds_ach").files or ()}
    assert not any(f in ("ach.py", "ach/__init__.py") or f.startswith("ach/") for f in files), files
    top = (distribution("mds_ach").read_text("top_level.txt") or "").split()
    assert "ach" not in top


@pytest.mark.parametrize("how", ["symlink", "file"])
def test_a_legacy_write_never_reaches_a_file_another_user_planted(clean_shm: None, other_user: int,
                                                                  how: str) -> None:
    """`import mds_ach as mds` scripts write `mds-ref` with `ach.Channel(...).put(...)`: a symlink another user
    planted at the channel's path to a valid Ach file of theirs, or a channel file they own, is refused at the
    open (issue #25, item 9); their file is unchanged."""
    import os
    from pathlib import Path

    from support import NOBODY, run_as

    from mds_ach import ach

    theirs = Path(ach.shm_path("test-theirs" if how == "symlink" else mds.MDS_CHAN_REF_NAME))

    def plant() -> int:
        ach.create(theirs.name.removeprefix("achshm-"), mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=0o666)
        if how == "symlink":
            os.symlink(theirs, ach.shm_path(mds.MDS_CHAN_REF_NAME))
        return 0

    assert run_as(NOBODY, NOBODY, plant) == 0
    before = theirs.read_bytes()
    with pytest.raises(ach.AchException) as exc:
        ach.Channel(mds.MDS_CHAN_REF_NAME).put(bytes(mds.MDS_REF()))
    assert ("is a symbolic link" if how == "symlink" else f"is owned by {user_label(NOBODY)}") in str(exc.value)
    assert theirs.read_bytes() == before


def test_the_classic_bindings_unopened_channel_open_and_result_string(clean_shm: None) -> None:
    """Issue #29 item 6: golems' binding lets a program make ``ach.Channel()`` and ``open()`` it later, and asks the
    handle for ``result_string(status)``; both were missing (TypeError, AttributeError)."""
    c = ach.Channel()
    assert c.closed
    c.open("test-classic", 4, 64)  # created when missing, as Channel(name) does
    c.put(b"hello")
    buf = bytearray(64)
    assert c.get(buf, wait=False, last=True) == (ach.ACH_OK, 5)
    assert c.result_string(ach.ACH_OVERFLOW) == "ACH_OVERFLOW" and ach.Channel.result_string(0) == "ACH_OK"
    with pytest.raises(ach.AchException) as info:
        c.open("test-classic")
    assert info.value.status == ach.ACH_EINVAL and "close() it first" in str(info.value)
    c.close()
    c.open("test-classic")  # a closed handle opens again
    assert c.get(buf, last=True) == (ach.ACH_OK, 5)
    c.close()
