"""The channel file layout of libach 2.0 (glibc, 64-bit): the one place that knows where each byte lives.

Every reader of the file -- the Python path (:mod:`mds_ach.ach.channel`), read-only parsing
(:mod:`mds_ach.ach.image`), creation (:mod:`mds_ach.ach.files`) and ``mds-ach repair`` -- takes its offsets from
here, so a layout change (or a mistake in one) cannot leave the others reading different bytes.

``struct ach_header`` (alignment 8; offsets in bytes)::

    0    u32   magic            MAGIC
    8    u64   len              total file length (Layout.file_size)
    16   char  name[65]         NUL-terminated, rest zero
    88   u64   index_cnt        frame count
    96   u64   data_size        bytes in the data ring
    104  u64   data_head        where the next frame is written
    112  u64   data_free        free contiguous bytes from data_head
    120  u64   index_head       index slot of the next put
    128  u64   index_free       unused index slots
    136  i32   clock            clock id of the condvar (1 = CLOCK_MONOTONIC)
    216  pthread_mutex_t        M bytes: 40 on x86_64, 48 on aarch64 (why files are not portable)
    216+M  pthread_cond_t       48 bytes
    264+M  int dirty            1 while a writer is mid-update
    272+M  u64 last_seq         newest frame's sequence number (0: none yet)
    280+M  = H, the header size

Then guard H (u64 at H), the index (``index_cnt`` entries of 24 bytes: size, offset, seq_num) from H + 8,
guard I, the data ring from H + 16 + 24 * index_cnt, guard D.

Imports: only :mod:`mds_ach.ach.status` (the layout is leaf knowledge of the ``ach`` package).
"""

from __future__ import annotations

import ctypes
import platform
import struct
from dataclasses import dataclass

from mds_ach.ach.status import ACH_ENOTSUP, AchException

MAGIC = 0xB07511F3
GUARD_HEADER = 0x1A2A3A4A5A6A7A8A
GUARD_INDEX = 0x1B2B3B4B5B6B7B8B
GUARD_DATA = 0x1C2C3C4C5C6C7C8C
NAME_MAX = 64  # libach: strlen(name) < 64
NAME_FIELD = 65  # bytes of the header's name field

# Header fields: byte offsets (any reader) and u64 word indices (for a "<Q"-cast memoryview of the mapping).
OFF_MAGIC = 0
OFF_LEN = 8
OFF_NAME = 16
OFF_INDEX_CNT = 88
OFF_DATA_SIZE = 96
OFF_DATA_HEAD = 104
OFF_DATA_FREE = 112
OFF_INDEX_HEAD = 120
OFF_INDEX_FREE = 128
OFF_CLOCK = 136
Q_LEN = OFF_LEN // 8
Q_INDEX_CNT = OFF_INDEX_CNT // 8
Q_DATA_SIZE = OFF_DATA_SIZE // 8
Q_DATA_HEAD = OFF_DATA_HEAD // 8
Q_DATA_FREE = OFF_DATA_FREE // 8
Q_INDEX_HEAD = OFF_INDEX_HEAD // 8
Q_INDEX_FREE = OFF_INDEX_FREE // 8

INDEX_ENTRY = struct.Struct("<QQQ")  # size, offset, seq_num
GEOMETRY = struct.Struct("<QQ")  # index_cnt, data_size at OFF_INDEX_CNT
COUNTERS = struct.Struct("<QQQQ")  # data_head, data_free, index_head, index_free at OFF_DATA_HEAD
_SYNC = 216  # where the pthread objects start, on every architecture


@dataclass(frozen=True)
class Layout:
    """Byte offsets of one architecture's channel file; only the mutex size differs between arches."""

    arch: str
    mutex_size: int

    @property
    def mutex(self) -> int:
        return _SYNC

    @property
    def cond(self) -> int:
        return _SYNC + self.mutex_size

    @property
    def dirty(self) -> int:
        return _SYNC + 48 + self.mutex_size

    @property
    def last_seq(self) -> int:
        return _SYNC + 56 + self.mutex_size

    @property
    def header_size(self) -> int:
        return _SYNC + 64 + self.mutex_size

    def file_size(self, index_cnt: int, data_size: int) -> int:
        """``sizeof(header) + guard + 24*cnt + guard + data_size + guard``."""
        return self.header_size + 24 * index_cnt + data_size + 24

    def index_offset(self) -> int:
        return self.header_size + 8

    def guard_index_offset(self, index_cnt: int) -> int:
        return self.header_size + 8 + 24 * index_cnt

    def data_offset(self, index_cnt: int) -> int:
        return self.header_size + 16 + 24 * index_cnt

    def guard_data_offset(self, index_cnt: int, data_size: int) -> int:
        return self.data_offset(index_cnt) + data_size


LAYOUT_X86_64 = Layout("x86_64", 40)
LAYOUT_AARCH64 = Layout("aarch64", 48)
LAYOUTS = {"x86_64": LAYOUT_X86_64, "aarch64": LAYOUT_AARCH64}
_MACHINE_ALIASES = {"amd64": "x86_64", "x86_64": "x86_64", "aarch64": "aarch64", "arm64": "aarch64"}


def entry_ok(size: int, offset: int, seq: int, data_size: int, last_seq: int) -> bool:
    """An index entry that may be used: a non-empty frame inside the data ring, written at or before ``last_seq``.

    The one definition of a sane entry for the put/get paths and ``mds-ach repair`` (the C twin in ``_achfast.c``
    checks the same). Anything else reads as ACH_CORRUPT: offsets from the file are never used unchecked."""
    return 0 < size <= data_size - offset and offset < data_size and 0 < seq <= last_seq


def native_arch() -> str | None:
    """``x86_64`` or ``aarch64`` for this machine (64-bit glibc), else None."""
    arch = _MACHINE_ALIASES.get(platform.machine().lower())
    return arch if arch is not None and ctypes.sizeof(ctypes.c_void_p) == 8 else None


def native_layout() -> Layout:
    """The layout for this machine (glibc on 64-bit x86 or ARM); other platforms are refused."""
    arch = native_arch()
    if arch is None:
        raise AchException(ACH_ENOTSUP, f"no known Ach layout for {platform.machine()} "
                                        f"({8 * ctypes.sizeof(ctypes.c_void_p)}-bit); only x86_64 and aarch64")
    return LAYOUTS[arch]
