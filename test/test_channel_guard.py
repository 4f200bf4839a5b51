"""Nodes keep running through a corrupt or re-created channel (a client died inside a put, a scribbled header, a
truncated file) and resume once it is repaired."""

from __future__ import annotations

import mmap
import os
import threading

import pytest

from mds_ach import ach
from mds_ach.nodes.pipeline import ChannelGuard
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_REF


def _set_dirty(name: str, value: int) -> None:
    """What libach leaves behind when a writer dies mid-put: the dirty word set."""
    with ach.Channel(name, create=False) as ch:
        offset = ch.layout.dirty
    fd = os.open(ach.shm_path(name), os.O_RDWR)
    try:
        with mmap.mmap(fd, 0) as mm:
            mm[offset:offset + 4] = value.to_bytes(4, "little")
    finally:
        os.close(fd)


def test_guard_holds_through_corruption_and_resumes_after_repair(clean_shm) -> None:
    ach.create("mds-ref-mux", 10, 3000)
    writer = StructChannel("mds-ref-mux", MDS_REF)
    reader = StructChannel("mds-ref-mux", MDS_REF)
    logged: list[tuple[str, str]] = []
    guard = ChannelGuard(lambda level, msg: logged.append((level, msg)), threading.Event())
    try:
        writer.put(MDS_REF())
        assert guard.call(reader.name, reader.latest) is not None
        _set_dirty("mds-ref-mux", 1)
        for _ in range(3):
            assert guard.call(reader.name, reader.latest, default="held") == "held"
        assert guard.errors == 3
        assert len(logged) == 1 and logged[0][0] == "error"  # rate-limited, names the remedy
        assert "mds-ach repair mds-ref-mux" in logged[0][1] and "ACH_CORRUPT" in logged[0][1]
        _set_dirty("mds-ref-mux", 0)  # what `mds-ach repair` does for a frame-consistent channel
        ref = MDS_REF()
        ref.joint[0x5F].ref = -0.25
        writer.put(ref)
        got = guard.call(reader.name, reader.latest)
        assert got is not None and got.joint[0x5F].ref == -0.25
    finally:
        writer.close()
        reader.close()


def scribble_header(name: str, offset: int = 16, count: int = 80) -> None:
    """What issue 25 did to a channel an operator may write: bytes over the header (name and frame count), which
    no handle can use and `mds-ach repair` cannot fix in place (it re-creates the file)."""
    fd = os.open(ach.shm_path(name), os.O_RDWR)
    try:
        os.pwrite(fd, b"X" * count, offset)
    finally:
        os.close(fd)


@pytest.mark.parametrize("damage", ["scribbled header", "truncated"])
def test_a_re_created_channel_is_re_opened_and_the_guard_says_it_works_again(clean_shm, damage: str) -> None:
    from mds_ach.tools import repair

    ach.create("mds-ref-mux", 10, 3000)
    writer = StructChannel("mds-ref-mux", MDS_REF)
    reader = StructChannel("mds-ref-mux", MDS_REF)
    logged: list[tuple[str, str]] = []
    guard = ChannelGuard(lambda level, msg: logged.append((level, msg)), threading.Event())
    try:
        writer.put(MDS_REF())
        if damage == "truncated":
            os.truncate(ach.shm_path("mds-ref-mux"), 4096)
        else:
            scribble_header("mds-ref-mux")
        assert guard.call(reader.name, reader.latest, default="held") == "held"
        assert not guard.put(writer, MDS_REF())
        assert guard.failing("mds-ref-mux")
        assert [lvl for lvl, _ in logged] == ["error"] and "mds-ach repair mds-ref-mux" in logged[0][1]
        fixed = repair.repair("mds-ref-mux")
        assert fixed.action == "re-created", fixed.line()
        ref = MDS_REF()
        ref.joint[0x5F].ref = -0.25
        assert guard.put(writer, ref)  # the writer re-opens the new file by itself
        got = guard.call(reader.name, reader.latest)  # and so does the reader
        assert got is not None and got.joint[0x5F].ref == -0.25
        assert (writer.reopened, reader.reopened) == (1, 1)
        assert not guard.failing("mds-ref-mux")
        assert logged[-1][0] == "info" and "mds-ref-mux works again" in logged[-1][1]
    finally:
        writer.close()
        reader.close()


def test_a_removed_channel_is_not_a_replacement(clean_shm) -> None:
    """An unlinked file is not re-created: the open handle is all there is and keeps working."""
    ach.create("mds-ref-mux", 10, 3000)
    with StructChannel("mds-ref-mux", MDS_REF) as ch:
        ach.unlink("mds-ref-mux")
        assert not ch.replaced()
        ch.put(MDS_REF())
        assert ch.latest() is not None and ch.reopened == 0
