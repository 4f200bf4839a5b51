"""Nodes keep running through a corrupt channel (a client died inside a put) and resume once it is repaired."""

from __future__ import annotations

import mmap
import os
import threading

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
