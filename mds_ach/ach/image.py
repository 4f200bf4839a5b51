"""Read-only decoding of a whole channel file, any architecture, no locking: for inspection tools, foreign-arch
files, golden-file tests and the geometry check every open performs.

Imports: :mod:`mds_ach.ach.status` and :mod:`mds_ach.ach.layout`.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass, field

from mds_ach.ach.layout import (
    COUNTERS,
    GEOMETRY,
    GUARD_DATA,
    GUARD_HEADER,
    GUARD_INDEX,
    INDEX_ENTRY,
    LAYOUTS,
    MAGIC,
    NAME_FIELD,
    OFF_CLOCK,
    OFF_DATA_HEAD,
    OFF_INDEX_CNT,
    OFF_LEN,
    OFF_MAGIC,
    OFF_NAME,
    Layout,
)
from mds_ach.ach.status import ACH_BAD_SHM_FILE, ACH_CORRUPT, AchException


@dataclass(frozen=True)
class IndexEntry:
    size: int
    offset: int
    seq_num: int


@dataclass
class ChannelImage:
    """A decoded channel file. Parsing takes no lock: use it for inspection, foreign-arch files and tests."""

    layout: Layout
    len: int
    name: str
    index_cnt: int
    data_size: int
    data_head: int
    data_free: int
    index_head: int
    index_free: int
    clock: int
    dirty: int
    last_seq: int
    index: list[IndexEntry]
    data: bytes = field(repr=False)

    @property
    def frame_size(self) -> int:
        """Nominal frame size, as achd reports it."""
        return self.data_size // self.index_cnt

    def frames(self) -> list[tuple[int, bytes]]:
        """Live frames as ``(seq_num, payload)``, oldest first."""
        live = [e for e in self.index if e.seq_num]
        return [(e.seq_num, self.data[e.offset:e.offset + e.size]) for e in sorted(live, key=lambda e: e.seq_num)]

    def newest(self) -> bytes | None:
        frames = self.frames()
        return frames[-1][1] if frames else None


def detect_layout(image: bytes) -> Layout:
    """Pick the arch whose size formula matches the file (magic and guard H decide)."""
    for layout in LAYOUTS.values():
        h = layout.header_size
        if len(image) >= h + 8 and struct.unpack_from("<Q", image, h)[0] == GUARD_HEADER:
            return layout
    raise AchException(ACH_BAD_SHM_FILE, "no header guard where x86_64 or aarch64 libach puts it")


def parse_image(image: bytes | bytearray | memoryview, arch: str | None = None) -> ChannelImage:
    """Decode a whole channel file. Bad magic -> ACH_BAD_SHM_FILE; wrong length or guards -> ACH_CORRUPT."""
    data = bytes(image)
    if len(data) < 4 or struct.unpack_from("<I", data, OFF_MAGIC)[0] != MAGIC:
        raise AchException(ACH_BAD_SHM_FILE, "bad magic number")
    layout = LAYOUTS[arch] if arch else detect_layout(data)
    cnt, dsize = check_geometry(data, layout)
    fields = COUNTERS.unpack_from(data, OFF_DATA_HEAD)
    index = [IndexEntry(*INDEX_ENTRY.unpack_from(data, layout.index_offset() + 24 * i)) for i in range(cnt)]
    d0 = layout.data_offset(cnt)
    return ChannelImage(
        layout=layout,
        len=struct.unpack_from("<Q", data, OFF_LEN)[0],
        name=data[OFF_NAME:OFF_NAME + NAME_FIELD].split(b"\0", 1)[0].decode("ascii", "replace"),
        index_cnt=cnt,
        data_size=dsize,
        data_head=fields[0],
        data_free=fields[1],
        index_head=fields[2],
        index_free=fields[3],
        clock=struct.unpack_from("<i", data, OFF_CLOCK)[0],
        dirty=struct.unpack_from("<i", data, layout.dirty)[0],
        last_seq=struct.unpack_from("<Q", data, layout.last_seq)[0],
        index=index,
        data=data[d0:d0 + dsize],
    )


def check_geometry(data: bytes | memoryview | mmap.mmap, layout: Layout) -> tuple[int, int]:
    """Header length fields, file length and the three guards; raises AchException with the reason. Returns the
    (index_cnt, data_size) it checked: use those, never a second read of the header, which may change meanwhile."""
    h = layout.header_size
    size = len(data)
    if size < h + 24:
        raise AchException(ACH_BAD_SHM_FILE, f"truncated: {size} bytes, an Ach header alone needs {h + 24}")
    length, = struct.unpack_from("<Q", data, OFF_LEN)
    cnt, dsize = GEOMETRY.unpack_from(data, OFF_INDEX_CNT)
    if length != size:
        raise AchException(ACH_CORRUPT, f"header says {length} bytes but the file has {size} (truncated?)")
    expected = layout.file_size(cnt, dsize)
    if cnt == 0 or dsize == 0 or expected != length:
        other = [a.arch for a in LAYOUTS.values() if a is not layout and cnt and a.file_size(cnt, dsize) == length]
        hint = f"; it looks like a {other[0]} file (Ach files are not portable across architectures)" if other else ""
        raise AchException(ACH_CORRUPT, f"inconsistent header: index_cnt={cnt} data_size={dsize} len={length}, "
                                        f"{layout.arch} expects {expected}{hint}")
    guards = (
        (h, GUARD_HEADER, "header"),
        (layout.guard_index_offset(cnt), GUARD_INDEX, "index"),
        (layout.guard_data_offset(cnt, dsize), GUARD_DATA, "data"),
    )
    for offset, value, what in guards:
        if struct.unpack_from("<Q", data, offset)[0] != value:
            raise AchException(ACH_CORRUPT, f"bad {what} guard at offset {offset}")
    return cnt, dsize

