"""The project's libach for C clients (libach/): built and installed by `make setup`, used by C programs exactly as
golems' libach was, on the same channels as the Python nodes.

The C side is test/c/libach_check.c, compiled here with `pkg-config --cflags --libs ach`: it replays the golden
trace written by golems' libach (statuses, frame sizes, data, reader state, header words), and the images it leaves
must equal the golden ones byte for byte (glibc's mutex/condvar bytes masked). Then C <-> Python both ways, the
wake-ups, a C reader killed inside its wait, and the achd server carrying a C writer's frames.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from support import REPO, in_netns, wait_for
from support import libach as lib

from mds_ach import ach
from mds_ach.ach import channel as ach_channel
from mds_ach.net import achd

NAME = "test-libach"
NATIVE = ach.native_layout().arch
SYNC_RANGE = {"x86_64": (216, 304), "aarch64": (216, 312)}


@pytest.fixture(scope="module")
def check(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """test/c/libach_check built against the installed library."""
    return lib.build(REPO / "test" / "c" / "libach_check.c", tmp_path_factory.mktemp("libach") / "libach_check")


def run(check: Path, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(check), *args], capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc


def masked(image: bytes) -> bytes:
    lo, hi = SYNC_RANGE[NATIVE]
    return image[:lo] + bytes(hi - lo) + image[hi:]


def test_installed_where_the_docs_say() -> None:
    """`make setup` puts libach.so, ach.h and ach.pc into the venv; a plain `cc -I -L -lach` builds a client."""
    pfx = lib.prefix()
    for rel in ("lib/libach.so", "lib/libach.so.4", "include/ach.h", "lib/pkgconfig/ach.pc"):
        assert (pfx / rel).exists(), rel
    assert f"prefix={pfx}" in (pfx / "lib/pkgconfig/ach.pc").read_text()


def test_plain_cc_command_builds_and_runs_a_client(tmp_path: Path, clean_shm: None) -> None:
    pfx = lib.prefix()
    demo = tmp_path / "demo.c"
    demo.write_text('#include <ach.h>\n#include <stdio.h>\n#include <string.h>\n'
                    'int main(void) {\n'
                    '    ach_channel_t c; char buf[16]; size_t n = 0;\n'
                    '    if (ach_open(&c, "test-demo", NULL) != ACH_OK) return 1;\n'
                    '    ach_put(&c, "hi", 3);\n'
                    '    enum ach_status r = ach_get(&c, buf, sizeof buf, &n, NULL, ACH_O_LAST);\n'
                    '    printf("%s %s\\n", ach_result_to_string(r), buf);\n'
                    '    return ach_close(&c) != ACH_OK;\n}\n')
    subprocess.run(["cc", str(demo), f"-I{pfx}/include", f"-L{pfx}/lib", "-lach", "-o", str(tmp_path / "demo")],
                   check=True)
    ach.create("test-demo", 4, 64)
    out = subprocess.run([str(tmp_path / "demo")], capture_output=True, text=True, check=True,
                         env={"LD_LIBRARY_PATH": f"{pfx}/lib"}).stdout
    assert out == "ACH_OK hi\n"


def test_golden_trace_replayed_in_c_gives_the_golden_images(check: Path, shared_dir: Path,
                                                            golden_names: None) -> None:
    golden = shared_dir / "ach-golden" / NATIVE
    out = run(check, "trace", str(golden / "trace.txt")).stdout
    assert "0 failures" in out
    for name, image in (("golden_empty", "golden_empty_fresh.shm"), ("golden_small", "golden_small.shm"),
                        ("golden_wrap", "golden_wrap.shm")):
        mine = Path(ach.shm_path(name)).read_bytes()
        assert masked(mine) == masked((golden / image).read_bytes()), name
    fresh = Path(ach.shm_path("golden_empty")).read_bytes()
    lo = SYNC_RANGE[NATIVE][0]
    assert fresh[lo + 16] == 0xB0  # mutex kind: process-shared | priority-inherit | robust, as libach's release build
    cond = lo + ach.native_layout().cond - ach.native_layout().mutex
    assert fresh[cond + 36] == 3  # condvar: process-shared, CLOCK_MONOTONIC


def test_rest_of_the_api(check: Path, clean_shm: None) -> None:
    assert "0 failures" in run(check, "api", NAME).stdout


def test_c_put_python_get(check: Path, clean_shm: None) -> None:
    ach.create(NAME, 32, 64)
    with ach.Channel(NAME, create=False) as r:
        run(check, "put", NAME, "20", "0")
        buf = bytearray(64)
        got = []
        while (res := r.get(buf))[0] == ach.ACH_OK:
            got.append(bytes(buf[:res[1]]).decode())
        assert got == [f"c-frame-{i}" for i in range(20)]


def test_python_put_c_get(check: Path, clean_shm: None) -> None:
    ach.create(NAME, 16, 64)
    with ach.Channel(NAME, create=False) as w:
        proc = subprocess.Popen([str(check), "get", NAME, "10"], stdout=subprocess.PIPE, text=True)
        for i in range(10):
            w.put(f"py-frame-{i}".encode())
            time.sleep(0.005)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert out.split("\n")[:10] == [f"frame py-frame-{i}" for i in range(10)]


def test_c_writer_wakes_a_python_reader_at_once(check: Path, clean_shm: None,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The library's put wakes the futex Python readers sleep on: with 60 s slices only that wake-up can end the
    wait in time (golems' libach only broadcasts the condvar, which those readers do not wait in)."""
    monkeypatch.setattr(ach_channel, "POLL_SLICE", 60.0)
    monkeypatch.setattr(ach_channel, "IDLE_SLICE", 60.0)
    ach.create(NAME, 16, 64)
    with ach.Channel(NAME, create=False) as r:
        got: list[tuple[int, int]] = []
        t = threading.Thread(target=lambda: got.append(r.get(bytearray(64), wait=True, timeout=120)))
        t.start()
        time.sleep(0.1)  # inside the wait
        t0 = time.monotonic()
        run(check, "put", NAME, "1", "0")
        t.join(timeout=30)
        assert got and got[0][0] == ach.ACH_OK
        assert time.monotonic() - t0 < 5


def test_c_reader_killed_inside_its_wait_does_not_wedge_the_writers(check: Path, clean_shm: None) -> None:
    """ach_get(ACH_O_WAIT) of this library sleeps on the futex, not in the condvar: a reader SIGKILLed there leaves
    nothing behind, and every later put (C or Python) returns. With golems' libach the next broadcast would hang."""
    ach.create(NAME, 4, 64)
    writer_py = f"from mds_ach import ach; ach.Channel({NAME!r}, create=False).put(b'after')"
    for trial in range(10):
        waiter = subprocess.Popen([str(check), "wait", NAME], stdout=subprocess.PIPE, text=True)
        assert waiter.stdout is not None
        assert waiter.stdout.readline().strip() == "waiting"
        time.sleep(0.05)  # inside the wait
        waiter.kill()
        waiter.wait(10)
        waiter.stdout.close()
        for cmd in ([str(check), "put", NAME, "1", "0"], [sys.executable, "-c", writer_py]):
            try:
                proc = subprocess.run(cmd, capture_output=True, timeout=10)
            except subprocess.TimeoutExpired:
                raise AssertionError(f"trial {trial}: {cmd[0]} hangs in put() after a C reader was killed while "
                                     "waiting") from None
            assert proc.returncode == 0, proc.stderr


def test_achd_server_delivers_every_frame_of_a_c_writer(check: Path, clean_shm: None) -> None:
    """A C writer at 100 Hz into a channel the achd server serves: the pulling client gets every frame, in order
    (its put wakes the server's reader at once, so nothing is overwritten on the ring first)."""
    assert in_netns(), "run inside tools/netns-run (make test does)"
    ach.create("test-src", 16, 64)
    ach.create("test-dst", 16, 64)
    srv = achd.Server(("127.0.0.1",), 0, policy=achd.AccessPolicy(writable=()), dead_after_s=5.0).start()
    pull = achd.Link("pull", "127.0.0.1", "test-dst", remote_channel="test-src", port=srv.ports[0],
                     get_last=False).start()
    count = 300
    try:
        assert pull.connected.wait(10)
        wait_for(lambda: srv.stats, 5, what="the server's session")
        with ach.Channel("test-dst", create=False) as dst:
            dst.flush()
            writer = subprocess.Popen([str(check), "put", "test-src", str(count), "100"])
            buf = bytearray(64)
            got = []
            deadline = time.monotonic() + 60
            while len(got) < count and time.monotonic() < deadline:
                status, size = dst.get(buf, wait=True, timeout=5)
                if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                    got.append(bytes(buf[:size]).decode())
            assert writer.wait(30) == 0
        assert got == [f"c-frame-{i}" for i in range(count)]
    finally:
        pull.stop()
        pull.join(5)
        srv.stop()
        srv.join()
