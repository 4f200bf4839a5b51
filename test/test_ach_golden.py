"""mds_ach.ach against the files and trace made by the reference C libach (shared/ach-golden).

Bytes inside the pthread mutex/cond record glibc's internal history, so images are compared with those
ranges masked (x86_64 [216,304), aarch64 [216,312)); every other byte must be identical.
"""

from __future__ import annotations

import re
import shutil
import struct
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from mds_ach import ach

pytestmark = pytest.mark.usefixtures("ach_impl")  # every test: C fast path and pure Python

NATIVE = ach.native_layout().arch
ARCHES = ("x86_64", "aarch64")
WRAP_LENGTHS = (20, 20, 20, 10, 30, 5, 64, 3, 65, 12, 12, 12)
SYNC_RANGE = {"x86_64": (216, 304), "aarch64": (216, 312)}


def masked(image: bytes, arch: str) -> bytes:
    lo, hi = SYNC_RANGE[arch]
    return image[:lo] + bytes(hi - lo) + image[hi:]


def wrap_payload(k: int, length: int) -> bytes:
    return bytes(((k << 4) | (i & 0xF)) & 0xFF for i in range(length))


@pytest.fixture
def golden(shared_dir: Path) -> Path:
    path = shared_dir / "ach-golden"
    assert (path / NATIVE / "trace.txt").is_file(), f"golden vectors missing under {path}"
    return path


def read_channel_file(name: str) -> bytes:
    return Path(ach.shm_path(name)).read_bytes()


# --- trace.txt ------------------------------------------------------------------------------------


@dataclass
class Op:
    kind: str  # "put", "get", "flush"
    label: str = ""
    data: bytes = b""
    bufsize: int = 0
    opts: int = 0
    status: int = 0
    frame_size: int = -1
    reader: tuple[int, int] = (0, 0)
    header: dict[str, int] = field(default_factory=dict)
    index: list[tuple[int, int, int]] = field(default_factory=list)


@dataclass
class Section:
    name: str
    length: int
    frame_count: int
    frame_size: int
    initial: dict[str, int]
    ops: list[Op]


_GET = re.compile(r"GET\[(?P<label>.*)\] bufsize=(?P<bufsize>\d+) opts=(?P<opts>0x[0-9a-f]+) -> "
                  r"(?P<name>\w+)\((?P<status>\d+)\) frame_size=(?P<fs>-?\d+)(?: data=(?P<data>[0-9a-f]*))?\s+"
                  r"reader\.seq_num=(?P<seq>\d+) reader\.next_index=(?P<next>\d+)")
_PUT = re.compile(r"PUT len=(?P<len>\d+) bytes=(?P<data>[0-9a-f]*) -> (?P<name>\w+)\((?P<status>\d+)\)")
_FLUSH = re.compile(r"FLUSH (?P<label>.*) -> reader\.seq_num=(?P<seq>\d+) reader\.next_index=(?P<next>\d+)")
_STATE = re.compile(r"\[(initial|after put)\] (.*)")
_ENTRY = re.compile(r"index\[(\d+)\] size=(\d+) offset=(\d+) seq_num=(\d+)")
_SECTION = re.compile(r"== (\w+) \((.*)\) len=(\d+)")


def parse_trace(path: Path) -> list[Section]:
    sections: list[Section] = []
    entries: list[tuple[int, int, int]] | None = None
    for line in path.read_text().splitlines():
        s = line.strip()
        if m := _SECTION.match(s):
            args = m.group(2)
            count, size = (16, 512) if "defaults" in args else map(int, re.findall(r"-[mn] (\d+)", args))
            sections.append(Section(m.group(1), int(m.group(3)), count, size, {}, []))
        elif m := _STATE.match(s):
            values = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", m.group(2))}
            if m.group(1) == "initial":
                sections[-1].initial = values
                entries = []
            else:
                sections[-1].ops[-1].header = values
                entries = sections[-1].ops[-1].index
        elif m := _ENTRY.match(s):
            assert entries is not None
            entries.append((int(m.group(2)), int(m.group(3)), int(m.group(4))))
        elif m := _PUT.match(s):
            sections[-1].ops.append(Op("put", data=bytes.fromhex(m.group("data")), status=int(m.group("status"))))
            assert len(sections[-1].ops[-1].data) == int(m.group("len"))
        elif m := _GET.match(s):
            sections[-1].ops.append(Op(
                "get", label=m.group("label"), bufsize=int(m.group("bufsize")), opts=int(m.group("opts"), 16),
                status=int(m.group("status")), frame_size=int(m.group("fs")),
                data=bytes.fromhex(m.group("data") or ""), reader=(int(m.group("seq")), int(m.group("next")))))
            assert ach.result_string(int(m.group("status"))) == m.group("name")
        elif m := _FLUSH.match(s):
            sections[-1].ops.append(Op("flush", label=m.group("label"),
                                       reader=(int(m.group("seq")), int(m.group("next")))))
        elif s:
            raise AssertionError(f"unparsed trace line: {line!r}")
    return sections


def header_values(img: ach.ChannelImage) -> dict[str, int]:
    return {"index_cnt": img.index_cnt, "data_size": img.data_size, "data_head": img.data_head,
            "data_free": img.data_free, "index_head": img.index_head, "index_free": img.index_free,
            "last_seq": img.last_seq, "dirty": img.dirty}


def index_values(img: ach.ChannelImage) -> list[tuple[int, int, int]]:
    return [(e.size, e.offset, e.seq_num) for e in img.index]


def test_trace_parses_completely(golden: Path) -> None:
    for arch in ARCHES:
        sections = parse_trace(golden / arch / "trace.txt")
        assert [s.name for s in sections] == ["golden_empty", "golden_small", "golden_wrap"]
        lines = (golden / arch / "trace.txt").read_text().splitlines()
        assert sum(op.kind == "get" for s in sections for op in s.ops) == sum(x.startswith("GET[") for x in lines)
        assert sum(op.kind == "put" for s in sections for op in s.ops) == sum(x.startswith("PUT ") for x in lines)
        assert sum(op.kind == "flush" for s in sections for op in s.ops) == 1


# --- creation -------------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "count", "size", "fresh"), [
    ("golden_empty", 0, 0, "golden_empty_fresh.shm"),
    ("golden_small", 4, 16, "golden_small_fresh.shm"),
])
def test_fresh_create_matches_libach(golden: Path, golden_names: None, name: str, count: int, size: int,
                                     fresh: str) -> None:
    ach.create(name, count, size)
    mine = read_channel_file(name)
    reference = (golden / NATIVE / fresh).read_bytes()
    assert len(mine) == len(reference)
    assert masked(mine, NATIVE) == masked(reference, NATIVE)
    # The sync objects themselves: glibc's fresh-init encoding of libach's attributes.
    layout = ach.native_layout()
    kind = struct.unpack_from("<i", mine, layout.mutex + 16)[0]
    wrefs = struct.unpack_from("<I", mine, layout.cond + 36)[0]
    assert kind == 0xB0  # process-shared | priority-inherit | robust
    assert wrefs == 3  # process-shared | CLOCK_MONOTONIC
    assert mine == reference  # nothing has ever locked it, so even the sync bytes agree


def test_create_sizes_and_layout(golden_names: None) -> None:
    ach.create("golden_small", 4, 16)
    img = ach.parse_image(read_channel_file("golden_small"), NATIVE)
    assert img.len == (504 if NATIVE == "x86_64" else 512)
    assert (img.index_cnt, img.data_size, img.frame_size) == (4, 64, 16)
    assert (img.data_head, img.data_free, img.index_head, img.index_free) == (0, 64, 0, 4)
    assert (img.clock, img.dirty, img.last_seq, img.name) == (ach.CLOCK_MONOTONIC, 0, 0, "golden_small")


# --- replaying the put sequences ------------------------------------------------------------------


def test_replay_small_is_byte_identical(golden: Path, golden_names: None) -> None:
    ach.create("golden_small", 4, 16)
    with ach.Channel("golden_small", create=False) as ch:
        for payload in (b"hello", b"world!!", bytes(range(10))):
            ch.put(payload)
    reference = (golden / NATIVE / "golden_small.shm").read_bytes()
    assert masked(read_channel_file("golden_small"), NATIVE) == masked(reference, NATIVE)


def test_replay_wrap_is_byte_identical(golden: Path, golden_names: None) -> None:
    ach.create("golden_wrap", 4, 16)
    with ach.Channel("golden_wrap", create=False) as ch:
        statuses = [ch.put_status(wrap_payload(k, n)) for k, n in enumerate(WRAP_LENGTHS, 1)]
    assert statuses == [ach.ACH_OK] * 8 + [ach.ACH_OVERFLOW] + [ach.ACH_OK] * 3
    mine = read_channel_file("golden_wrap")
    reference = (golden / NATIVE / "golden_wrap.shm").read_bytes()
    assert masked(mine, NATIVE) == masked(reference, NATIVE)
    img = ach.parse_image(mine, NATIVE)
    assert (img.data_head, img.data_free, img.index_head, img.index_free, img.last_seq) == (39, 25, 3, 0, 11)
    assert index_values(img) == [(12, 3, 9), (12, 15, 10), (12, 27, 11), (3, 0, 8)]
    assert bytes(range(0x77, 0x80)) in img.data  # freed data bytes are not cleared


@pytest.mark.parametrize("section_name", ["golden_empty", "golden_small", "golden_wrap"])
def test_trace_replay(golden: Path, golden_names: None, section_name: str) -> None:
    """Every put and get of the C driver, in order: statuses, frame sizes, payloads, reader state, header."""
    section = next(s for s in parse_trace(golden / NATIVE / "trace.txt") if s.name == section_name)
    ach.create(section.name, section.frame_count, section.frame_size)
    writer = ach.Channel(section.name, create=False)
    assert writer.snapshot().len == section.length
    assert header_values(writer.snapshot()) == section.initial
    reader: ach.Channel | None = None
    handles = [writer]
    for op in section.ops:
        if op.kind == "put":
            assert writer.put_status(op.data) == op.status
            img = writer.snapshot()
            assert header_values(img) == op.header
            assert index_values(img) == op.index
            continue
        if reader is None or "fresh" in op.label:
            reader = ach.Channel(section.name, create=False)
            handles.append(reader)
            assert (reader.seq_num, reader.next_index) == (0, 1)  # libach's ach_open: next_index starts at 1
        if op.kind == "flush":
            reader.flush()
        else:
            buf = bytearray(op.bufsize)
            status, size = reader.get_status(buf, op.opts, timeout=0.01)  # the driver's waits were 10 ms
            assert (ach.result_string(status), status) == (ach.result_string(op.status), op.status), op.label
            assert size == (op.frame_size if op.frame_size >= 0 else 0), op.label
            assert bytes(buf[:len(op.data)]) == op.data, op.label
        assert (reader.seq_num, reader.next_index) == op.reader, op.label
    for h in handles:
        h.close()
    # Gets never change a non-sync byte: the final file equals the C driver's.
    golden_file = {"golden_empty": "golden_empty_after_gets.shm"}.get(section.name, section.name + ".shm")
    reference = (golden / NATIVE / golden_file).read_bytes()
    assert masked(read_channel_file(section.name), NATIVE) == masked(reference, NATIVE)


def test_classic_get_on_trace_overflow(golden: Path, golden_names: None) -> None:
    """The classic API raises on OVERFLOW with the needed size and leaves the frame unread."""
    ach.create("golden_small", 4, 16)
    with ach.Channel("golden_small") as w, ach.Channel("golden_small") as r:
        for payload in (b"hello", b"world!!", bytes(range(10))):
            w.put(payload)
        assert r.get(bytearray(256)) == (ach.ACH_OK, 5)
        assert r.get(bytearray(256)) == (ach.ACH_OK, 7)
        with pytest.raises(ach.AchException) as info:
            r.get(bytearray(4))
        assert info.value.status == ach.ACH_OVERFLOW
        assert info.value.frame_size == 10
        assert (r.seq_num, r.next_index) == (2, 2)
        buf = bytearray(10)
        assert r.get(buf) == (ach.ACH_OK, 10)
        assert bytes(buf) == bytes(range(10))


# --- reading the reference files -------------------------------------------------------------------


def install_golden(golden: Path, file: str, name: str) -> None:
    shutil.copyfile(golden / NATIVE / file, ach.shm_path(name))


def test_read_golden_small_file(golden: Path, golden_names: None) -> None:
    """A channel file written by C libach, read with this implementation."""
    install_golden(golden, "golden_small.shm", "golden_small")
    with ach.Channel("golden_small", create=False) as r:
        assert (r.frame_count, r.data_size, r.last_seq) == (4, 64, 3)
        got = []
        buf = bytearray(64)
        while True:
            status, size = r.get(buf)
            if status == ach.ACH_STALE_FRAMES:
                break
            got.append((status, bytes(buf[:size])))
        assert got == [(ach.ACH_OK, b"hello"), (ach.ACH_OK, b"world!!"), (ach.ACH_OK, bytes(range(10)))]
        # ... and written: the C-made mutex is usable, the frame lands after the others.
        r.put(b"python")
    img = ach.parse_image(read_channel_file("golden_small"))
    assert img.frames()[-1] == (4, b"python")
    assert (img.data_head, img.index_head, img.index_free) == (28, 0, 0)


def test_read_golden_wrap_file(golden: Path, golden_names: None) -> None:
    install_golden(golden, "golden_wrap.shm", "golden_wrap")
    with ach.Channel("golden_wrap", create=False) as r:
        buf = bytearray(64)
        assert r.get(buf, last=True) == (ach.ACH_MISSED_FRAME, 12)
        assert bytes(buf[:12]) == wrap_payload(12, 12)
        assert r.get(buf, copy=True) == (ach.ACH_OK, 12)
        assert r.get(buf, wait=True, timeout=0.01) == (ach.ACH_TIMEOUT, 0)


# --- aarch64 (and native) images, parsed without locking ------------------------------------------


@pytest.mark.parametrize("arch", ARCHES)
def test_parse_images(golden: Path, arch: str) -> None:
    layout = ach.LAYOUTS[arch]
    assert layout.header_size == {"x86_64": 320, "aarch64": 328}[arch]
    sections = {s.name: s for s in parse_trace(golden / arch / "trace.txt")}
    for file, section in (("golden_empty_fresh.shm", "golden_empty"), ("golden_small_fresh.shm", "golden_small"),
                          ("golden_empty_after_gets.shm", "golden_empty")):
        img = ach.parse_image((golden / arch / file).read_bytes(), arch)
        assert img.len == sections[section].length
        assert header_values(img) == sections[section].initial
        assert img.frames() == []
    small = ach.parse_image((golden / arch / "golden_small.shm").read_bytes(), arch)
    assert small.name == "golden_small"
    assert header_values(small) == sections["golden_small"].ops[2].header
    assert small.frames() == [(1, b"hello"), (2, b"world!!"), (3, bytes(range(10)))]
    assert small.newest() == bytes(range(10))
    wrap = ach.parse_image((golden / arch / "golden_wrap.shm").read_bytes(), arch)
    last_put = [op for op in sections["golden_wrap"].ops if op.kind == "put"][-1]
    assert header_values(wrap) == last_put.header
    assert index_values(wrap) == last_put.index
    assert wrap.frames() == [(8, wrap_payload(8, 3)), (9, wrap_payload(10, 12)), (10, wrap_payload(11, 12)),
                             (11, wrap_payload(12, 12))]
    # The arch is recognised from the file itself.
    assert ach.detect_layout((golden / arch / "golden_wrap.shm").read_bytes()) is layout


def test_cross_arch_replay_agrees(golden: Path, golden_names: None) -> None:
    """The native replay of golden_wrap decodes to the same header, index and data as the aarch64 C file."""
    ach.create("golden_wrap", 4, 16)
    with ach.Channel("golden_wrap") as ch:
        for k, n in enumerate(WRAP_LENGTHS, 1):
            ch.put_status(wrap_payload(k, n))
    mine = ach.parse_image(read_channel_file("golden_wrap"))
    theirs = ach.parse_image((golden / "aarch64" / "golden_wrap.shm").read_bytes(), "aarch64")
    assert header_values(mine) == header_values(theirs)
    assert index_values(mine) == index_values(theirs)
    assert mine.data == theirs.data
    assert mine.frames() == theirs.frames()


def test_foreign_arch_file_refused_clearly(golden: Path, golden_names: None) -> None:
    """Ach files are not portable: opening the other arch's file gives CORRUPT naming that arch."""
    other = "aarch64" if NATIVE == "x86_64" else "x86_64"
    shutil.copyfile(golden / other / "golden_small.shm", ach.shm_path("golden_small"))
    with pytest.raises(ach.AchException) as info:
        ach.Channel("golden_small", create=False)
    assert info.value.status == ach.ACH_CORRUPT
    assert other in str(info.value)
    with pytest.raises(ach.AchException) as info:
        ach.parse_image((golden / other / "golden_small.shm").read_bytes(), NATIVE)
    assert info.value.status == ach.ACH_CORRUPT


def test_parse_image_rejects_bad_images(golden: Path) -> None:
    image = (golden / "aarch64" / "golden_small.shm").read_bytes()
    with pytest.raises(ach.AchException) as info:
        ach.parse_image(b"\0" * 600)
    assert info.value.status == ach.ACH_BAD_SHM_FILE
    with pytest.raises(ach.AchException) as info:
        ach.parse_image(image[:400], "aarch64")
    assert info.value.status == ach.ACH_CORRUPT
    assert "truncated" in str(info.value)
    broken = bytearray(image)
    broken[328 + 8 + 24 * 4] ^= 0xFF  # index guard
    with pytest.raises(ach.AchException) as info:
        ach.parse_image(bytes(broken), "aarch64")
    assert info.value.status == ach.ACH_CORRUPT
    assert "index guard" in str(info.value)
