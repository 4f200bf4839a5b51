"""achd-compatible networking: our server and links on loopback, then two simulated hosts over a veth pair.

The fast tests run a :class:`mds_ach.net.achd.Server` and :class:`mds_ach.net.achd.Link` in this process on
loopback. The slow ones build a robot host (its own network and /dev/shm) joined to this namespace (the
operator station) by a veth pair; the robot runs the simulated system (``daemon --nocan``, mux, filter and
collision gate) and ``mds-ach remote serve``; the operator
runs ``mds-ach remote``. References written here move the robot, and its state comes back; the same
through an SSH tunnel to a real sshd on the robot; a cut link recovers without losing the newest reference.
"""

from __future__ import annotations

import ctypes
import ipaddress
import json
import logging
import math
import os
import select
import signal
import socket
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import pytest
from support import VENV_BIN, golems, in_netns, run_as, wait_for
from support.netsim import Host, Sshd, Veth, reachable
from support.pty_session import PtySession
from support.rig import DaemonRig

import mds_ach as mds
from mds_ach import ach
from mds_ach.net import achd
from mds_ach.net import protocol as ap
from mds_ach.nodes import daemon_loop
from mds_ach.robot import msgs

OP_IP = "10.77.0.1"
ROBOT_IP = "10.77.0.2"
LOOPBACK_ONLY_PORT = 8077  # a second robot server that listens on the robot's loopback only (for --ssh)


def _need_netns() -> None:
    assert in_netns(), "run inside tools/netns-run (make test does): these tests bind sockets and build namespaces"


# --------------------------------------------------------------------------------------------------
# Fast: one process, loopback
# --------------------------------------------------------------------------------------------------


@pytest.fixture
def server(clean_shm):
    _need_netns()
    for name in ("mds-ref-filter", "mds-ref", "mds-state", "test-state", "test-src", "test-dst"):
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("127.0.0.1",), 0, policy=achd.AccessPolicy(writable=("mds-ref-filter", "test-dst")),
                      dead_after_s=2.0).start()
    yield srv
    srv.stop()
    srv.join()


def _raw_session(port: int, request: bytes) -> tuple[socket.socket, ap.Headers]:
    """A bare client: send ``request``, read the response headers."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=5)
    sock.sendall(request)
    headers, rest = achd._read_headers(sock, 5.0)
    assert rest == b""
    return sock, headers


def _ref(value: float, address: int = mds.LSP) -> msgs.MDS_REF:
    ref = msgs.MDS_REF()
    ref.joint[address].ref = value
    return ref


def _frames(name: str) -> list[bytes]:
    """Every frame currently in a channel, oldest first."""
    return [f for _, f in ach.Channel(name, create=False).snapshot().frames()]


def test_server_writes_only_valid_frames(server):
    sock, headers = _raw_session(server.ports[0], ap.encode_request("mds-ref-filter", "tcp", "pull"))
    assert headers.status == ap.ACH_OK
    assert (headers.frame_count, headers.frame_size) == (mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    nan_ref = _ref(0.0)
    nan_ref.joint[mds.RSP].ref = math.nan
    bad_mode = _ref(0.1)
    bad_mode.joint[mds.LEP].mode = 7
    for payload in (bytes(_ref(-0.25)), bytes(nan_ref), b"\0" * 999, bytes(_ref(50.0)), bytes(bad_mode),
                    bytes(_ref(0.5))):
        sock.sendall(ap.encode_frame(payload))
    stats = wait_for(lambda: next(iter(server.stats.values()), None), 5, what="server stats")
    wait_for(lambda: stats.written + stats.dropped_size + stats.dropped_invalid == 6, 5, what="all six frames")
    sock.close()
    assert (stats.written, stats.dropped_size, stats.dropped_invalid) == (2, 1, 3)
    written = [msgs.MDS_REF.from_bytes(f).joint[mds.LSP].ref for f in _frames("mds-ref-filter")]
    assert written == [-0.25, 0.5]


def test_a_flood_of_refused_frames_is_counted_but_logged_a_few_times(server, caplog):
    """Every out-of-limit frame a peer pushes is dropped and counted, but the log gets one line for the first and
    repeats are summarized (issue #25, item 9: 1 kHz of refused frames wrote megabytes a second)."""
    caplog.set_level(logging.WARNING, logger="mds_ach.net.achd")
    sock, headers = _raw_session(server.ports[0], ap.encode_request("mds-ref-filter", "tcp", "pull"))
    assert headers.status == ap.ACH_OK
    n = 3000
    # Non-finite values: refused at the door on every input (an out-of-limit one the mux clamps on this legacy input)
    frames = [bytes(_ref(-0.25))] + [bytes(_ref(math.nan if i % 2 else math.inf)) for i in range(n)]
    sock.sendall(b"".join(ap.encode_frame(f) for f in frames))
    stats = wait_for(lambda: next(iter(server.stats.values()), None), 5, what="server stats")
    wait_for(lambda: stats.dropped_invalid == n, 30, what="every frame dropped")
    sock.close()
    lines = [r for r in caplog.records if "received frame dropped" in r.getMessage()]
    assert 1 <= len(lines) <= 3, [r.getMessage() for r in lines]
    assert "non-finite reference" in lines[0].getMessage() and stats.written == 1


@pytest.mark.parametrize(
    "request_bytes, status, fragment",
    [
        (ap.encode_request("mds-ref", "tcp", "pull"), ap.ACH_EACCES, "may not be written"),
        (ap.encode_request("mds-nothing", "tcp", "push"), ap.ACH_ENOENT, "mds-nothing"),
        (b"channel-name: ../../etc/passwd\ntransport: tcp\ndirection: push\n.\n", ap.ACH_INVALID_NAME, "invalid"),
        (b"channel-name: mds-state\ntransport: tcp\ndirection: push\nflavour: x\n.\n", ap.ACH_BAD_HEADER, "flavour"),
        (b"channel-name: mds-state\ntransport: udp\ndirection: push\n.\n", ap.ACH_BAD_HEADER, "remote-port"),
    ],
)
def test_server_refuses_with_achd_error_headers(server, request_bytes, status, fragment):
    sock, headers = _raw_session(server.ports[0], request_bytes)
    assert headers.status == status
    assert fragment in headers.message
    assert sock.recv(100) == b""  # and closes
    sock.close()


@pytest.mark.parametrize("name", [mds.MDS_CHAN_BOARD_CMD_NAME, mds.MDS_CHAN_DAEMON_INPUT_NAME])
def test_a_refused_write_says_why_in_words_golems_achd_prints_whole(clean_shm, name):
    """Issue #29 item 2: `achd push mds-cmd` (the original `mds-ach remote`) is refused with the reason and what to
    do instead; golems' achd prints the message (its header parser ends a value at ':' or '=', so none)."""
    _need_netns()
    ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("127.0.0.1",), 0).start()
    try:
        sock, headers = _raw_session(srv.ports[0], ap.encode_request(name, "tcp", "pull"))
        sock.close()
    finally:
        srv.stop()
        srv.join()
    assert headers.status == ap.ACH_EACCES
    assert headers.message.startswith(f"channel {name} may not be written from the network -- ")
    assert ":" not in headers.message and "=" not in headers.message
    assert ("mds-ach enable|home|zero|reset JOINT" if name == mds.MDS_CHAN_BOARD_CMD_NAME
            else "write mds-ref-filter or mds-ref") in headers.message


def test_the_original_remote_script_with_golems_achd(clean_shm, tmp_path: Path):
    """Issue #29 item 2: the original `mds-ach remote` runs four golems `achd -r` links to the robot. Three work;
    `push mds-cmd` is refused on purpose (setup commands are not levels a reconnect may replay, and pass no safety
    stage; the original never read mds-cmd): golems' achd prints the reason and that link alone exits, at once
    although `-r` (a refused request is not a lost connection)."""
    _need_netns()
    achd_bin = golems.tool("achd")
    for name in (mds.MDS_CHAN_REF_NAME, mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_PARAM_NAME, "test-station-ref"):
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    ach.create(mds.MDS_CHAN_BOARD_CMD_NAME, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)  # the station's
    srv = achd.Server(("127.0.0.1",), 0, dead_after_s=2.0).start()  # the default write rules of `remote serve`
    port = str(srv.ports[0])
    # One /dev/shm here: the station's channels get other names (-z names the robot's), as on two hosts.
    links = [("push", "test-station-ref", mds.MDS_CHAN_REF_NAME),
             ("pull", "test-station-state", mds.MDS_CHAN_STATE_NAME),
             ("pull", "test-station-param", mds.MDS_CHAN_PARAM_NAME)]
    procs = [subprocess.Popen([str(achd_bin), "-r", "-p", port, "-z", robot, verb, "127.0.0.1", local],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for verb, local, robot in links]
    try:
        with PtySession([str(achd_bin), "-r", "-p", port, "push", "127.0.0.1", mds.MDS_CHAN_BOARD_CMD_NAME]) as cmd:
            cmd.expect("status: ACH_EACCES", timeout=20)
            cmd.expect("Server error: channel mds-cmd may not be written from the network -- its setup commands "
                       "(enable, disable, home, zero, reset) pass no safety stage", timeout=5)
            cmd.expect("never read mds-cmd, so this link carried nothing; the other links work\r\n")
            assert cmd.wait(10) == 1
        assert "mds-cmd" not in str(srv.stats)  # never served
        wait_for(lambda: len(srv.stats) == 3, 20, what="the three other links served")
        with ach.Channel("test-station-ref", create=False) as ref, \
                ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as state, \
                ach.Channel(mds.MDS_CHAN_PARAM_NAME, create=False) as param:
            def arrived(name: str) -> bool:
                if not ach.exists(name):
                    return False
                with ach.Channel(name, create=False) as ch:
                    return ch.last_seq > 0

            def flowing() -> bool:  # frames put after the links connected (golems' achd flushes at connect)
                ref.put(_ref(-0.2))
                state.put(msgs.MDS_STATE())
                param.put(msgs.MDS_JOINT_PARAM())
                return all(arrived(n) for n in targets)

            targets = (mds.MDS_CHAN_REF_NAME, "test-station-state", "test-station-param")
            try:
                wait_for(flowing, 20, what="frames over the three links")
            except AssertionError:
                raise AssertionError({n: arrived(n) for n in targets}, srv.stats, [p.poll() for p in procs]) from None
        assert all(p.poll() is None for p in procs), [p.stderr.read() for p in procs if p.poll() is not None]
        assert msgs.MDS_REF.from_bytes(_frames(mds.MDS_CHAN_REF_NAME)[-1]).joint[mds.LSP].ref == -0.2
    finally:
        for p in procs:
            p.terminate()
            p.wait(10)
        srv.stop()
        srv.join()


def _first_frames_of_a_pull(port: int, name: str, written_before: bytes, written_after: list[bytes]) -> list[bytes]:
    """What a pulling link (ours, with achd's get-last) delivers when ``written_before`` was put before it
    connected and ``written_after`` once it runs (one by one, each waited for)."""
    with ach.Channel(name, create=False) as src:
        src.put(written_before)
        link = achd.Link("pull", "127.0.0.1", f"test-got-{name}", remote_channel=name, port=port,
                         reconnect=False).start()
        try:
            assert link.connected.wait(10), link.stats.last_error
            got: list[bytes] = []
            with ach.Channel(f"test-got-{name}", create=False) as dst:
                buf = bytearray(dst.data_size)
                def delivered(frame: bytes, n: int) -> bool:
                    src.put(frame)  # again until it arrives: the serving side may still be flushing
                    status, size = dst.get(buf, wait=True, timeout=0.2)
                    while status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                        got.append(bytes(buf[:size]))
                        status, size = dst.get(buf)
                    return len(got) > n and got[-1] == frame

                for frame in written_after:
                    wait_for(partial(delivered, frame, len(got)), 10, what=f"{frame!r} over the link")
            return list(dict.fromkeys(got))  # a frame put twice while waiting counts once
        finally:
            link.stop()
            link.join(5)


@pytest.mark.parametrize("server_kind", ["ours", "ours --newest-on-connect", "golems achd serve"])
def test_a_pull_starts_with_the_first_frame_written_after_the_client_connected(clean_shm, server_kind):
    """Issue #29 item 3: golems' achd flushes the channel when a client connects; our server does the same by
    default (a pull never starts with a frame written before the client connected), and with
    ``send_latest_on_connect`` (``--newest-on-connect``) starts with the newest frame instead."""
    _need_netns()
    ach.create("test-state", 10, 64)
    if server_kind == "golems achd serve":
        with golems.Inetd(golems.tool("achd")) as inetd:
            got = _first_frames_of_a_pull(inetd.port, "test-state", b"before", [b"after-1", b"after-2"])
    else:
        newest = server_kind.endswith("--newest-on-connect")
        srv = achd.Server(("127.0.0.1",), 0, **({"send_latest_on_connect": True} if newest else {})).start()
        try:
            got = _first_frames_of_a_pull(srv.ports[0], "test-state", b"before", [b"after-1", b"after-2"])
        finally:
            srv.stop()
            srv.join()
        if newest:
            assert got == [b"before", b"after-1", b"after-2"]
            return
    assert got == [b"after-1", b"after-2"]


@pytest.mark.parametrize("server_kind", ["ours", "golems achd serve"])
def test_a_station_connecting_after_the_daemon_started_gets_mds_param(clean_shm, server_kind):
    """Issue #29 item 3: a station's link to golems' `achd serve` (and to ours: the same first-frame rule) never
    gets a frame written before it connected, whatever it asks (get-last picks the newest of the frames that
    arrive afterwards) -- and the daemon puts mds-param once at start. So the daemon puts it again every second
    (``PARAM_PERIOD``): a station that connects later has the joint names within a second of robot time."""
    _need_netns()
    rig = DaemonRig()
    rig.loop.start_up()  # mds-param, once, before any station connected
    inetd = golems.Inetd(golems.tool("achd")) if server_kind == "golems achd serve" else None
    srv = achd.Server(("127.0.0.1",), 0).start() if inetd is None else None
    port = inetd.port if inetd is not None else srv.ports[0]
    link = achd.Link("pull", "127.0.0.1", "test-station-param", remote_channel=mds.MDS_CHAN_PARAM_NAME,
                     port=port).start()
    try:
        assert link.connected.wait(10), link.stats.last_error
        param = msgs.MDS_JOINT_PARAM()

        def names() -> bool:
            with ach.Channel("test-station-param", create=False) as station:
                return station.get(param, last=True)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME)

        rig.step(2)
        assert not names(), "the frame put before the station connected is not sent (achd's rule)"
        rig.step(round(daemon_loop.PARAM_PERIOD / rig.loop.period))  # one period of robot time
        wait_for(names, 10, what="mds-param at the station")
        assert msgs.get_name(param.joint[mds.LSP].nameshort) == "LSP"
    finally:
        link.stop()
        link.join(5)
        if inetd is not None:
            inetd.close()
        if srv is not None:
            srv.stop()
            srv.join()
        rig.close()


def test_a_udp_receiver_that_was_not_scheduled_loses_no_datagram(clean_shm):
    """Issue #29 item 3: under load our UDP links lost frames where golems' achd lost none. One cause: a receiver
    that is not scheduled for a while finds the kernel dropped what did not fit its socket buffer (the default
    held 7 mds-state datagrams; RcvbufErrors in /proc/net/snmp). Stopped for the time 60 frames take at 1 kHz,
    the receiving client now gets every one of them."""
    _need_netns()
    n, size = 60, ctypes.sizeof(msgs.MDS_STATE)
    ach.create("test-src", 2 * n, size)
    ach.create("test-dst", 2 * n, size)
    srv = achd.Server(("127.0.0.1",), 0).start()
    client = subprocess.Popen([sys.executable, "-m", "mds_ach.net.achd", "-t", "udp", "-p", str(srv.ports[0]),
                               "-z", "test-src", "pull", "127.0.0.1", "test-dst"])
    try:
        with ach.Channel("test-src", create=False) as src, ach.Channel("test-dst", create=False) as dst:
            frame = bytearray(size)
            buf = bytearray(size)

            def linked() -> bool:  # a frame put now arrives (the server flushed at connect, the client too)
                src.put(frame)
                return dst.get(buf, wait=True, timeout=0.2)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME)

            wait_for(linked, 20, what="the UDP link")
            wait_for(lambda: next(iter(srv.stats.values())).sent >= 1, 5, what="server stats")
            stats = next(iter(srv.stats.values()))
            dst.flush()
            os.kill(client.pid, signal.SIGSTOP)
            try:
                sent = stats.sent
                for i in range(n):
                    frame[0:4] = i.to_bytes(4, "little")
                    src.put(frame)
                    time.sleep(0.001)
                wait_for(lambda: stats.sent == sent + n, 10, what="the server sent every frame")
            finally:
                os.kill(client.pid, signal.SIGCONT)
            got: set[int] = set()

            def all_arrived() -> bool:
                while True:
                    status, got_size = dst.get(buf)
                    if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                        return len(got) == n
                    got.add(int.from_bytes(buf[0:4], "little"))

            wait_for(all_arrived, 10, what=f"all {n} frames")
    finally:
        client.terminate()
        client.wait(10)
        srv.stop()
        srv.join()


def test_link_refused_reports_the_server_message(server):
    link = achd.Link("push", "127.0.0.1", "mds-ref", port=server.ports[0], reconnect=False).start()
    assert link.finished.wait(10)
    assert "ACH_EACCES" in link.stats.last_error and "mds-ref" in link.stats.last_error
    assert link.stats.sent == 0


def test_server_refuses_a_cancel_the_mux_would_refuse_and_the_client_sees_why(clean_shm):
    """Issue 25 item 2: a CANCEL pushed over the network got ACH_OK and moved LEP from -1.20 to the edge of its
    range. The server applies the mux's check (``check_cancel``): the frame is not written, the connection is
    answered with the reason and closed; our client reports it and does not re-send that frame; a CANCEL without
    target still goes through."""
    from mds_ach.nodes.pipeline import make_ref
    from mds_ach.robot import lifecycle
    from mds_ach.robot.channels import StructChannel

    _need_netns()
    pose = [0.0] * mds.MDS_JOINT_COUNT
    pose[mds.LEP], pose[mds.LSP] = -1.2, -0.2
    with StructChannel.of(mds.MDS_CHAN_REF_GATED_NAME) as gated:  # where the pipeline has the joints
        gated.put(make_ref(pose, [0] * mds.MDS_JOINT_COUNT))
    StructChannel.of(mds.MDS_CHAN_HOLD_NAME).close()
    ach.create("test-hold", mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("127.0.0.1",), 0, dead_after_s=2.0).start()  # the default write rules: mds-hold allowed
    port = srv.ports[0]
    link = achd.Link("push", "127.0.0.1", "test-hold", remote_channel=mds.MDS_CHAN_HOLD_NAME, port=port)
    try:
        for targets, fragment in (({mds.LEP: 1.0}, "outside LEP's range"),
                                  ({mds.LSP: 0.3}, "a CANCEL never moves a joint")):
            sock, headers = _raw_session(port, ap.encode_request(mds.MDS_CHAN_HOLD_NAME, "tcp", "pull"))
            assert headers.status == ap.ACH_OK
            sock.sendall(ap.encode_frame(bytes(lifecycle.make(lifecycle.HOLD_CANCEL, targets=targets))))
            reply, _ = achd._read_headers(sock, 5.0)
            assert reply.status == ap.ACH_EINVAL and fragment in reply.message, reply.message
            assert sock.recv(100) == b""  # and closes
            sock.close()
        assert _frames(mds.MDS_CHAN_HOLD_NAME) == []  # nothing reached the mux
        assert srv.refused_frames == 2
        # our client: the reason in its status, the refused frame never re-sent after it reconnects
        link.start()
        assert link.connected.wait(5), link.stats.last_error
        with ach.Channel("test-hold", create=False) as local:
            local.put(bytes(lifecycle.make(lifecycle.HOLD_CANCEL, targets={mds.LEP: 1.0})))
            wait_for(lambda: "ACH_EINVAL" in link.stats.last_error, 5, what="the refusal at the client")
            assert "outside LEP's range" in link.stats.last_error
            wait_for(link.connected.is_set, 10, what="the client back")
            stop = lifecycle.make(lifecycle.HOLD_CANCEL, [mds.LEP])  # no target: where the reference is
            local.put(bytes(stop))
            wait_for(lambda: _frames(mds.MDS_CHAN_HOLD_NAME) != [], 5, what="the CANCEL without target written")
        assert [msgs.MDS_HOLD.from_bytes(f).seq for f in _frames(mds.MDS_CHAN_HOLD_NAME)] == [stop.seq]
        assert srv.refused_frames == 3  # the client's refused frame once: not re-sent when it reconnected
    finally:
        link.stop()
        link.join(5)
        srv.stop()
        srv.join()


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_pull_and_push_links(server, transport):
    port = server.ports[0]
    pull = achd.Link("pull", "127.0.0.1", "test-state", remote_channel="mds-state", port=port,
                     transport=transport).start()
    push = achd.Link("push", "127.0.0.1", "test-src", remote_channel="test-dst", port=port,
                     transport=transport, get_last=False).start()
    try:
        assert pull.connected.wait(5) and push.connected.wait(5)
        state_w = ach.Channel("mds-state")
        state_r = ach.Channel("test-state")
        state_r.flush()
        got = msgs.MDS_STATE()
        for i in range(5):
            st = msgs.MDS_STATE()
            st.time = i + 1.0
            state_w.put(st)
            status, size = state_r.get(got, wait=True, timeout=5)
            assert (status, size, got.time) == (ach.ACH_OK, ctypes.sizeof(got), i + 1.0)
        state_w.put(b"runt")  # wrong size for mds-state: never sent
        src = ach.Channel("test-src")
        dst = ach.Channel("test-dst")
        dst.flush()
        for word in (b"one", b"two", b"three"):
            src.put(word)
        buf = bytearray(64)
        seen = []
        while len(seen) < 3:
            status, size = dst.get(buf, wait=True, timeout=5)
            assert status == ach.ACH_OK
            seen.append(bytes(buf[:size]))
        assert seen == [b"one", b"two", b"three"]  # without get-last every frame, in order
        served = {k: v for k, v in server.stats.items() if "mds-state" in k}
        wait_for(lambda: sum(s.dropped_size for s in served.values()) == 1, 5, what="runt counted")
    finally:
        for link in (pull, push):
            link.stop()
            link.join(5)


def test_udp_ignores_stray_datagrams(server):
    link = achd.Link("pull", "127.0.0.1", "test-state", remote_channel="mds-state", port=server.ports[0],
                     transport="udp").start()
    try:
        assert link.connected.wait(5)
        udp_port = link.udp_port
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
            spoof = msgs.MDS_STATE()
            spoof.time = 666.0
            intruder.sendto(bytes(spoof), ("127.0.0.1", udp_port))
        wait_for(lambda: link.stats.stray_datagrams == 1, 5, what="stray counted")
        assert link.stats.written == 0
    finally:
        link.stop()
        link.join(5)


def test_reconnect_delivers_the_newest_frame(clean_shm):
    """Server gone, frames written meanwhile, server back: the newest one arrives; the older are not resent."""
    _need_netns()
    for name in ("test-src", "test-dst"):
        ach.create(name, 10, 64)
    policy = achd.AccessPolicy(writable=("test-dst",))
    srv = achd.Server(("127.0.0.1",), 0, policy=policy, dead_after_s=1.0).start()
    port = srv.ports[0]
    link = achd.Link("push", "127.0.0.1", "test-src", remote_channel="test-dst", port=port, dead_after_s=1.0).start()
    src = ach.Channel("test-src")
    dst = ach.Channel("test-dst")
    buf = bytearray(64)
    try:
        assert link.connected.wait(5)
        dst.flush()
        src.put(b"before")
        assert dst.get(buf, wait=True, timeout=5) == (ach.ACH_OK, 6)
        srv.stop()
        srv.join()
        wait_for(lambda: not link.connected.is_set(), 10, what="link notices the server is gone")
        for word in (b"old-1", b"old-2", b"newest"):
            src.put(word)
        srv = achd.Server(("127.0.0.1",), port, policy=policy, dead_after_s=1.0).start()
        wait_for(link.connected.is_set, 10, what="reconnect")
        status, size = dst.get(buf, wait=True, last=True, timeout=5)
        assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and bytes(buf[:size]) == b"newest"
        assert link.stats.connects >= 2
    finally:
        link.stop()
        link.join(5)
        srv.stop()
        srv.join()


def test_recreated_channel_is_followed(server):
    """The robot's stack restarts (channel removed and made again): the link finds the new channel."""
    link = achd.Link("pull", "127.0.0.1", "test-state", remote_channel="mds-state", port=server.ports[0],
                     dead_after_s=2.0).start()
    try:
        assert link.connected.wait(5)
        ach.unlink("mds-state")
        ach.create("mds-state", mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
        wait_for(lambda: link.stats.connects >= 2 and link.connected.is_set(), 15, what="reconnect to the new one")
        writer = ach.Channel("mds-state", create=False)
        reader = ach.Channel("test-state", create=False)
        reader.flush()
        st = msgs.MDS_STATE()
        st.time = 42.0
        writer.put(st)
        got = msgs.MDS_STATE()
        assert reader.get(got, wait=True, timeout=5)[0] == ach.ACH_OK and got.time == 42.0
    finally:
        link.stop()
        link.join(5)


def test_period_limits_rate_and_newest_wins(server):
    """With period-ns the server sends at most one frame per period, always the newest."""
    link = achd.Link("pull", "127.0.0.1", "test-state", remote_channel="mds-state", port=server.ports[0],
                     period_ns=300_000_000).start()
    try:
        assert link.connected.wait(5)
        writer = ach.Channel("mds-state")
        st = msgs.MDS_STATE()
        for i in range(40):
            st.time = float(i)
            writer.put(st)
        reader = ach.Channel("test-state", create=False)
        got = msgs.MDS_STATE()
        wait_for(lambda: reader.get(got, last=True, copy=True)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME)
                 and got.time == 39.0, 10, what="newest frame")
        assert link.stats.written < 40
    finally:
        link.stop()
        link.join(5)


# --------------------------------------------------------------------------------------------------
# Admission limits and idle connections (addresses on this namespace's loopback device)
# --------------------------------------------------------------------------------------------------

SERVER_IP, ATTACKER_IP, OTHER_IP = "10.78.0.1", "10.78.0.2", "10.78.0.3"  # not loopback addresses


@pytest.fixture
def lan_addresses(clean_shm):
    """Three non-loopback addresses on ``lo`` (private namespace), so one test process can be several peers."""
    _need_netns()
    for address in (SERVER_IP, ATTACKER_IP, OTHER_IP):
        subprocess.run(["ip", "addr", "add", f"{address}/32", "dev", "lo"], check=True, capture_output=True)
    yield
    for address in (SERVER_IP, ATTACKER_IP, OTHER_IP):
        subprocess.run(["ip", "addr", "del", f"{address}/32", "dev", "lo"], capture_output=True)


def _session_from(source: str, host: str, port: int, request: bytes) -> tuple[socket.socket, ap.Headers]:
    """A bare client connecting from ``source``: send ``request``, read the response headers."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.settimeout(5)
    sock.bind((source, 0))
    sock.connect((host, port))
    sock.sendall(request)
    headers, _ = achd._read_headers(sock, 5.0)
    return sock, headers


def _closed_by_server(sock: socket.socket) -> bool:
    readable, _, _ = select.select([sock], [], [], 0)
    return bool(readable) and sock.recv(4096) == b""


def test_idle_connections_from_one_peer_lock_out_neither_another_peer_nor_the_operator(lan_addresses):
    for name in ("test-idle", "mds-ref-filter", "test-state"):
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("0.0.0.0",), 0, policy=achd.AccessPolicy(writable=("mds-ref-filter",))).start()
    port = srv.ports[0]
    held, refused = [], 0
    operator = achd.Link("pull", "127.0.0.1", "test-state", remote_channel="test-idle", port=port)
    try:
        for _ in range(1000):  # each asks to pull a channel nobody writes, then sits idle
            sock, headers = _session_from(ATTACKER_IP, SERVER_IP, port, ap.encode_request("test-idle", "tcp", "push"))
            if headers.status == ap.ACH_OK:
                held.append(sock)
                continue
            assert headers.status == ap.ACH_EAGAIN and f"too many connections from {ATTACKER_IP}" in headers.message
            refused += 1
            sock.close()
        assert (len(held), refused) == (achd.MAX_PER_PEER, 1000 - achd.MAX_PER_PEER)
        # another peer still gets in, and its reference is written
        other, headers = _session_from(OTHER_IP, SERVER_IP, port, ap.encode_request("mds-ref-filter", "tcp", "pull"))
        assert headers.status == ap.ACH_OK, headers.message
        other.sendall(ap.encode_frame(bytes(_ref(-0.25))))
        wait_for(lambda: [msgs.MDS_REF.from_bytes(f).joint[mds.LSP].ref for f in _frames("mds-ref-filter")]
                 == [-0.25], 5, what="the other peer's reference written")
        # and so does the operator on loopback (local tools, SSH tunnels)
        operator.start()
        assert operator.connected.wait(5), operator.stats.last_error
        assert srv.connections() == {"local": 1, "remote": achd.MAX_PER_PEER + 1, ATTACKER_IP: achd.MAX_PER_PEER,
                                     OTHER_IP: 1}
        other.close()
    finally:
        operator.stop()
        operator.join(5)
        for sock in held:
            sock.close()
        srv.stop()
        srv.join()


def test_idle_connections_are_closed_and_busy_ones_kept(lan_addresses):
    for name in ("test-idle", "mds-ref-filter"):
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("0.0.0.0",), 0, policy=achd.AccessPolicy(writable=("mds-ref-filter",)),
                      idle_timeout_s=1.0).start()
    port = srv.ports[0]
    idle = [_session_from(ATTACKER_IP, SERVER_IP, port, ap.encode_request("test-idle", "tcp", "push"))[0]
            for _ in range(achd.MAX_PER_PEER)]
    busy, headers = _session_from(OTHER_IP, SERVER_IP, port, ap.encode_request("mds-ref-filter", "tcp", "pull"))
    assert headers.status == ap.ACH_OK
    try:
        value = 0.0

        def idle_closed_while_busy() -> bool:
            nonlocal value
            value += 0.01  # the busy peer keeps sending while we wait
            busy.sendall(ap.encode_frame(bytes(_ref(value))))
            return srv.idle_closed == achd.MAX_PER_PEER

        wait_for(idle_closed_while_busy, 10, interval=0.2, what="the idle connections closed by the server")
        wait_for(lambda: all(_closed_by_server(s) for s in idle), 5, what="EOF on every idle connection")
        assert srv.connections() == {"local": 0, "remote": 1, OTHER_IP: 1}, "the busy connection stays"
        busy.sendall(ap.encode_frame(bytes(_ref(-0.5))))
        wait_for(lambda: msgs.MDS_REF.from_bytes(_frames("mds-ref-filter")[-1]).joint[mds.LSP].ref == -0.5, 5,
                 what="the busy peer's newest reference")
        again, headers = _session_from(ATTACKER_IP, SERVER_IP, port, ap.encode_request("test-idle", "tcp", "push"))
        assert headers.status == ap.ACH_OK, "closed idle connections free their slots"
        again.close()
    finally:
        busy.close()
        for sock in idle:
            sock.close()
        srv.stop()
        srv.join()


@pytest.mark.parametrize("family, host", [(socket.AF_INET, "127.0.0.1"), (socket.AF_INET6, "::1")])
def test_peer_uid_names_the_user_at_the_other_end_of_a_loopback_connection(family, host):
    """The connected socket at the accepted peer's address whose other end is the server: sock_diag's exact lookup,
    and the ``/proc/net/tcp{,6}`` fallback, agree."""
    from mds_ach.net import peeruid
    from mds_ach.net.peeruid import parse_address, peer_uid

    _need_netns()
    assert parse_address("0100007F:1F90") == (ipaddress.ip_address("127.0.0.1"), 8080)
    assert parse_address("00000000000000000000000001000000:0050") == (ipaddress.ip_address("::1"), 80)
    assert parse_address("0000000000000000FFFF00000100007F:0050") == (ipaddress.ip_address("127.0.0.1"), 80)
    with socket.socket(family, socket.SOCK_STREAM) as listener:
        listener.bind((host, 0))
        listener.listen(1)
        client = socket.create_connection(listener.getsockname()[:2], timeout=5)
        accepted, peer = listener.accept()
        with accepted:
            assert peer_uid(peer, accepted.getsockname()) == os.getuid()
            ends = [(ipaddress.ip_address(a[0]), a[1]) for a in (peer, accepted.getsockname())]
            assert peeruid._diag_uid(*ends[0], *ends[1]) == peeruid._table_uid(*ends) == os.getuid()
            assert peeruid._diag_uid(*ends[0], *ends[0]) is None  # no such connection
            assert peer_uid(accepted.getsockname(), peer) == os.getuid()  # the server's own socket: also ours
            client.close()
            wait_for(lambda: peer_uid(peer, accepted.getsockname()) is None, 5, what="a closed peer: no longer listed")


def _pull_one_state_frame(port: int) -> int:
    """The SSH-tunnelled operator (runs as another user, in a forked child): pull ``mds-state`` through loopback;
    0 once a whole state frame arrived, else the reason on stdout and 1."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(ap.encode_request("mds-state", "tcp", "push"))
        headers, rest = achd._read_headers(sock, 5.0)
        if headers.status != ap.ACH_OK:
            print(f"operator refused: {ap.status_name(headers.status or 0)}: {headers.message}", flush=True)
            return 1
        decoder = ap.FrameDecoder()
        frames = decoder.feed(rest)
        while not frames:
            data = sock.recv(65536)
            if not data:
                print("operator: closed before a state frame", flush=True)
                return 1
            frames = decoder.feed(data)
    return 0 if len(frames[0]) == ctypes.sizeof(msgs.MDS_STATE) else 1


def test_a_local_user_flooding_the_loopback_pool_does_not_lock_out_the_operator(clean_shm, other_user):
    """Issue 25 item 8: 32 loopback connections pulling ``mds-state`` (never idle) refused the SSH-tunnelled
    operator ("too many local connections (32)") for as long as they stayed. Each local user (the uid owning the
    peer's socket: sshd's forwarding child runs as the operator's user) now has a pool of its own: the flooding
    user's 33rd connection is refused, another user's is served."""
    import threading

    _need_netns()
    for name in ("mds-state", "test-state"):
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
    srv = achd.Server(("127.0.0.1",), 0).start()
    port = srv.ports[0]
    stop = threading.Event()

    def publish() -> None:  # the daemon's state stream: the pullers are never idle
        with ach.Channel("mds-state", create=False) as chan:
            while not stop.wait(0.05):
                chan.put(bytes(msgs.MDS_STATE()))

    writer = threading.Thread(target=publish, daemon=True)
    writer.start()
    flood = [achd.Link("pull", "127.0.0.1", "test-state", remote_channel="mds-state", port=port,
                       period_ns=100_000_000) for _ in range(achd.MAX_LOCAL_CLIENTS)]
    try:
        for link in flood:
            link.start()
        wait_for(lambda: all(link.connected.is_set() and link.stats.written > 0 for link in flood), 20,
                 what="every puller connected and receiving")
        assert run_as(other_user, other_user, lambda: _pull_one_state_frame(port)) == 0, "the operator locked out"
        wait_for(lambda: srv.local_users() == {os.getuid(): achd.MAX_LOCAL_CLIENTS}, 5,
                 what="the flooding user's pool full, the operator's connection released")
        sock, headers = _raw_session(port, ap.encode_request("mds-state", "tcp", "push"))  # the flooder's 33rd
        sock.close()
        assert headers.status == ap.ACH_EAGAIN
        assert headers.message == f"too many local connections from uid {os.getuid()} ({achd.MAX_LOCAL_CLIENTS}); " \
                                  f"close some first"
        assert all(link.connected.is_set() for link in flood)
    finally:
        stop.set()
        for link in flood:
            link.stop()
        for link in flood:
            link.join(5)
        writer.join(5)
        srv.stop()
        srv.join()
    assert srv.local_users() == {} and srv.connections()["local"] == 0  # every slot released


def test_an_idle_close_does_not_replay_an_old_reference(clean_shm):
    """The server closes a quiet pushing link as idle; the client reconnects and must not re-send its last
    frame (certainly delivered long ago) over a newer one written on the robot meanwhile."""
    _need_netns()
    for name in ("test-src", "test-dst"):
        ach.create(name, 10, 64)
    srv = achd.Server(("127.0.0.1",), 0, policy=achd.AccessPolicy(writable=("test-dst",)), idle_timeout_s=2.0).start()
    link = achd.Link("push", "127.0.0.1", "test-src", remote_channel="test-dst", port=srv.ports[0],
                     dead_after_s=1.0).start()
    src, dst = ach.Channel("test-src"), ach.Channel("test-dst")
    try:
        assert link.connected.wait(5)
        src.put(b"operator-old")
        wait_for(lambda: _frames("test-dst")[-1:] == [b"operator-old"], 5, what="the operator's frame")
        dst.put(b"robot-newer")  # e.g. the robot's own console, on the same mux input
        wait_for(lambda: srv.idle_closed >= 1 and link.stats.connects >= 2 and link.connected.is_set(), 15,
                 what="idle close and reconnect")
        src.put(b"operator-next")
        wait_for(lambda: _frames("test-dst")[-1:] == [b"operator-next"], 5, what="the next frame")
        frames = _frames("test-dst")
        assert frames[frames.index(b"robot-newer"):] == [b"robot-newer", b"operator-next"], frames
    finally:
        link.stop()
        link.join(5)
        srv.stop()
        srv.join()
        src.close()
        dst.close()


# --------------------------------------------------------------------------------------------------
# Slow: robot and operator on two simulated hosts
# --------------------------------------------------------------------------------------------------


class Robot:
    def __init__(self, host, veth, env: dict[str, str], rt: Path) -> None:
        self.host, self.veth, self.env, self.rt = host, veth, env, rt


def _exe(name: str) -> str:
    return str(VENV_BIN / name)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    _need_netns()
    assert os.geteuid() == 0, "the network tests need root (namespaces and veth pairs)"
    rt = tmp_path_factory.mktemp("robot-rt")
    env = dict(os.environ, MDS_ACH_RUNTIME_DIR=str(rt))
    host = Host("robot")
    veth = Veth("mdsn", host, OP_IP, ROBOT_IP)
    procs: list[subprocess.Popen] = []
    try:
        start = host.run([_exe("mds-ach"), "start", "nocan", "--only", "daemon", "mux", "filter", "collision",
                          "--timeout", "120"], env=env, capture_output=True, text=True, timeout=180)
        assert start.returncode == 0, f"robot system did not start:\n{start.stdout}\n{start.stderr}"
        # one server on the veth address (plain mode), one on the robot's loopback only (for --ssh)
        for extra, out in ((["--bind", ROBOT_IP], "serve.out"), (["--port", str(LOOPBACK_ONLY_PORT)], "serve-lo.out")):
            with open(rt / out, "wb") as log:
                procs.append(host.popen([_exe("mds-ach"), "remote", "serve", *extra, "--dead-after", "2"], env=env,
                                        stdout=log, stderr=subprocess.STDOUT))
        wait_for(lambda: reachable(ROBOT_IP, ap.ACHD_PORT), 20, what="robot achd server")
        yield Robot(host, veth, env, rt)
    finally:
        for proc in procs:
            proc.terminate()
        host.run([_exe("mds-ach"), "stop"], env=env, capture_output=True, timeout=60)
        for proc in procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
        veth.close()
        host.close()


@pytest.fixture
def operator(robot, tmp_path, monkeypatch, clean_shm):
    """This namespace as the operator station; ``mds-ach remote kill`` afterwards."""
    monkeypatch.setenv("MDS_ACH_RUNTIME_DIR", str(tmp_path / "operator-rt"))
    yield tmp_path / "operator-rt"
    subprocess.run([_exe("mds-ach"), "remote", "kill"], capture_output=True, timeout=30)


def _remote(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([_exe("mds-ach"), "remote", *args], capture_output=True, text=True, timeout=timeout)


def _session_status(rt: Path) -> dict:
    try:
        return json.loads((rt / "remote.status.json").read_text())
    except (OSError, ValueError):
        return {}


def _state() -> msgs.MDS_STATE | None:
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as chan:
        st = msgs.MDS_STATE()
        status, size = chan.get(st, last=True, copy=True)
        return st if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(st) else None


def _command(address: int, value: float) -> float:
    """Read-modify-write of the local mds-ref-filter, as console ``goto`` does; returns the target."""
    st = wait_for(_state, 20, what="state from the robot")
    ref = msgs.MDS_REF()
    for i in range(mds.MDS_JOINT_COUNT):
        ref.joint[i].ref = st.joint[i].ref
    ref.joint[address].ref = value
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
        chan.put(ref)
    return value


def _arrives(address: int, target: float, timeout: float = 40.0) -> None:
    wait_for(lambda: (st := _state()) is not None and abs(st.joint[address].pos - target) < 0.02, timeout,
             what=f"joint {address:#x} at {target} in the state that came back")


def _check_state_and_param() -> None:
    st = wait_for(_state, 20, what="mds-state from the robot")
    assert msgs.get_name(st.joint[mds.LSP].nameshort) == "LSP"
    with ach.Channel(mds.MDS_CHAN_PARAM_NAME, create=False) as chan:
        param = msgs.MDS_JOINT_PARAM()
        wait_for(lambda: chan.get(param, last=True, copy=True)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME), 10,
                 what="mds-param (published once, before we connected)")
        assert msgs.get_name(param.joint[mds.LSP].nameshort) == "LSP"


@pytest.mark.slow
def test_remote_over_veth_moves_robot_and_recovers_a_cut_link(robot, operator):
    result = _remote(ROBOT_IP, "--dead-after", "2")
    assert result.returncode == 0, result.stderr
    assert "mds-state" in result.stdout and "(udp)" in result.stdout
    _check_state_and_param()
    start = _state().joint[mds.LSP].pos
    _arrives(mds.LSP, _command(mds.LSP, start - 0.2))
    # a NaN reference written locally is never sent, and the robot stays where it is
    bad = msgs.MDS_REF()
    bad.joint[mds.LSP].ref = math.nan
    with ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False) as chan:
        chan.put(bad)
    wait_for(lambda: any(link["dropped_invalid"] for link in _session_status(operator).get("links", [])), 10,
             what="NaN reference counted")
    # cut the cable long enough for every connection to be declared dead
    robot.veth.down()
    try:
        wait_for(lambda: (s := _session_status(operator)).get("links")
                 and not any(link["connected"] for link in s["links"]), 30, what="links notice the cut")
        target = _command(mds.LSP, start - 0.4)  # written while the link is down
    finally:
        robot.veth.up()
    _arrives(mds.LSP, target)  # the newest reference was not lost, and state flows again
    wait_for(lambda: all(link["connected"] and link["connects"] >= 2 for link in _session_status(operator)["links"]),
             10, what="every link reconnected")
    killed = _remote("kill")
    assert killed.returncode == 0 and "stopped" in killed.stdout


@pytest.fixture(scope="module")
def sshd(robot, tmp_path_factory):
    """A real OpenSSH server on the robot, key-only, whose key may only forward to the loopback server."""
    reason = Sshd.missing_ids()
    if reason:
        pytest.skip(f"sshd: {reason}")
    server = Sshd(robot.host, ROBOT_IP, tmp_path_factory.mktemp("ssh"), f"127.0.0.1:{LOOPBACK_ONLY_PORT}")
    yield server
    server.close()


@pytest.mark.slow
def test_remote_through_ssh_tunnel(robot, sshd, operator):
    # the loopback-only server cannot be reached from the operator: everything must go through ssh
    assert not reachable(ROBOT_IP, LOOPBACK_ONLY_PORT)
    args = ["--ssh", f"root@{ROBOT_IP}", "--port", str(LOOPBACK_ONLY_PORT), "--ssh-identity", str(sshd.identity),
            "--ssh-known-hosts", str(sshd.known_hosts), "--dead-after", "2"]
    result = _remote(*args)
    assert result.returncode == 0, result.stderr + sshd.log.read_text()[-2000:]
    assert "(udp)" not in result.stdout  # UDP cannot pass the tunnel: the state stream uses TCP
    _check_state_and_param()
    start = _state().joint[mds.LSP].pos
    _arrives(mds.LSP, _command(mds.LSP, start - 0.15))
    status = _session_status(operator)
    assert status["ssh"] and status["tunnel"]["running"]
    assert _remote("kill").returncode == 0


@pytest.mark.slow
def test_ssh_refuses_an_unknown_host_key(robot, sshd, operator, tmp_path):
    (tmp_path / "empty_known_hosts").write_text("")
    result = _remote("--ssh", f"root@{ROBOT_IP}", "--port", str(LOOPBACK_ONLY_PORT), "--ssh-identity",
                     str(sshd.identity), "--ssh-known-hosts", str(tmp_path / "empty_known_hosts"),
                     "--wait", "8")
    assert result.returncode == 1
    assert "Host key verification failed" in result.stderr


def test_remote_refuses_to_bridge_this_machine_into_itself(tmp_path, monkeypatch):
    monkeypatch.setenv("MDS_ACH_RUNTIME_DIR", str(tmp_path))
    result = _remote("127.0.0.1")
    assert result.returncode == 2
    assert "is this machine" in result.stderr
    assert not (tmp_path / "remote.pid").exists()
