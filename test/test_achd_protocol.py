"""achd wire protocol: replay the captured C achd session, then achd's header and framing rules."""

from __future__ import annotations

import pytest

from mds_ach.net import protocol as ap

RESP_MARK = b"\n--RESP--\n"
FRAMES_MARK = b"\n--FRAMES--\n"


@pytest.fixture(scope="module")
def capture(shared_dir) -> tuple[bytes, bytes, bytes]:
    """(request, response, frame stream) of the captured `achd serve` session."""
    blob = (shared_dir / "ach-golden" / "achd_pull_tcp_wire.bin").read_bytes()
    request, rest = blob.split(RESP_MARK, 1)
    response, frames = rest.split(FRAMES_MARK, 1)
    return request, response, frames


def test_captured_request_parses_and_reencodes(capture):
    request, _, _ = capture
    headers, rest = ap.parse_headers(request)
    assert rest == b""
    assert headers.channel_name == "wiretest"
    assert headers.transport == "tcp"
    assert headers.get_last is False
    assert headers.direction == "push"  # the client pulls, so the server pushes
    assert headers.period_ns is None and headers.remote_port is None
    headers.check_request()
    assert ap.encode_request("wiretest", "tcp", "push", get_last=False) == request


def test_captured_response_parses_and_reencodes(capture):
    _, response, _ = capture
    headers, rest = ap.parse_headers(response)
    assert rest == b""
    assert (headers.frame_count, headers.frame_size, headers.status) == (4, 32, ap.ACH_OK)
    assert ap.encode_response(4, 32) == response


def test_captured_frames_decode_whole_and_byte_by_byte(capture):
    _, _, stream = capture
    assert ap.FrameDecoder().feed(stream) == [b"hello-wire", b"xyz"]
    decoder = ap.FrameDecoder()
    frames = []
    for i in range(len(stream)):
        frames += decoder.feed(stream[i : i + 1])
    assert frames == [b"hello-wire", b"xyz"]
    assert decoder.pending == 0
    assert ap.encode_frame(b"hello-wire") + ap.encode_frame(b"xyz") == stream
    assert ap.frame_header(10) == stream[:16]


def test_whole_session_as_one_stream(capture):
    """Response headers followed directly by frames (as the client socket sees them), fed in odd chunks."""
    _, response, frames = capture
    stream = response + frames
    parser = ap.HeaderParser()
    decoder = ap.FrameDecoder()
    got = []
    for i in range(0, len(stream), 7):
        chunk = stream[i : i + 7]
        if not parser.done:
            chunk = parser.feed(chunk)
        if parser.done:
            got += decoder.feed(chunk)
    assert parser.headers().frame_size == 32
    assert got == [b"hello-wire", b"xyz"]


def test_header_syntax_rules():
    block = (
        b"# a comment line\r\n"
        b"\n"
        b"   CHANNEL-Name =  mds-state   # trailing comment\r\n"
        b"Transport: UDP\n"
        b"remote-port=4242\n"
        b"get-last: aye\n"
        b"Direction: Pull\n"
        b"period-ns: 100000000\n"
        b" . \n"
        b"achpipe"
    )
    headers, rest = ap.parse_headers(block)
    assert rest == b"achpipe"
    assert headers.channel_name == "mds-state"
    assert headers.transport == "udp"
    assert headers.remote_port == 4242
    assert headers.get_last is True
    assert headers.direction == "pull"
    assert headers.period_ns == 100_000_000
    headers.check_request()


@pytest.mark.parametrize("word", ap.TRUE_WORDS + ("YES", "True", "AYE"))
def test_true_words(word):
    assert ap.parse_bool(word) is True


@pytest.mark.parametrize("word", ap.FALSE_WORDS + ("NO", "Nay", "F"))
def test_false_words(word):
    assert ap.parse_bool(word) is False


@pytest.mark.parametrize(
    "block, fragment",
    [
        (b"get-last: maybe\n.\n", "boolean"),
        (b"colour: blue\n.\n", "invalid header"),
        (b"channel-name mds-state\n.\n", "malformed"),
        (b"message: a: b\n.\n", "malformed"),
        (b": value\n.\n", "malformed"),
        (b"frame-size: 12abc\n.\n", "not an integer"),
        (b"remote-port: 70000\n.\n", "outside"),
        (b"direction: sideways\n.\n", "direction"),
        (b"\xff\xfe: x\n.\n", "not text"),
    ],
)
def test_bad_headers_are_refused(block, fragment):
    with pytest.raises(ap.HeaderError, match=fragment) as err:
        ap.parse_headers(block)
    assert err.value.status == ap.ACH_BAD_HEADER


def test_line_length_limit():
    ok = b"message: " + b"x" * (ap.LINE_LENGTH - 1 - len(b"message: ")) + b"\r\n.\n"
    headers, _ = ap.parse_headers(ok)  # 1023 bytes + CR + LF is still fine: CR is not counted
    assert len(headers.message) == ap.LINE_LENGTH - 1 - len("message: ")
    with pytest.raises(ap.HeaderError, match="longer"):
        ap.parse_headers(b"message: " + b"x" * ap.LINE_LENGTH + b"\n.\n")
    parser = ap.HeaderParser()
    parser.feed(b"message: " + b"x" * 1000)
    with pytest.raises(ap.HeaderError, match="longer"):
        parser.feed(b"x" * 100)  # no newline yet, but already over the limit


def test_unterminated_block():
    parser = ap.HeaderParser()
    assert parser.feed(b"channel-name: a\n") == b""
    assert not parser.done
    with pytest.raises(ap.HeaderError, match="terminated"):
        parser.headers()
    with pytest.raises(ap.HeaderError, match="terminated"):
        ap.parse_headers(b"channel-name: a\n")


@pytest.mark.parametrize(
    "headers, fragment",
    [
        (b"transport: tcp\ndirection: push\n.\n", "no channel-name"),
        (b"channel-name: ../etc/passwd\ntransport: tcp\ndirection: push\n.\n", "invalid channel name"),
        (b"channel-name: .hidden\ntransport: tcp\ndirection: push\n.\n", "invalid channel name"),
        (b"channel-name: a\ndirection: push\n.\n", "no transport"),
        (b"channel-name: a\ntransport: sctp\ndirection: push\n.\n", "not supported"),
        (b"channel-name: a\ntransport: tcp\n.\n", "no direction"),
        (b"channel-name: a\ntransport: udp\ndirection: push\n.\n", "remote-port"),
    ],
)
def test_request_checks(headers, fragment):
    parsed, _ = ap.parse_headers(headers)
    with pytest.raises(ap.HeaderError, match=fragment):
        parsed.check_request()


def test_udp_request_order_matches_achd_client():
    raw = ap.encode_request("mds-state", "udp", "push", get_last=True, period_ns=5_000_000, udp_port=40000)
    assert raw == (
        b"remote-port: 40000\nchannel-name: mds-state\ntransport: udp\nget-last: 1\n"
        b"direction: push\nperiod-ns: 5000000\n.\n"
    )
    headers, _ = ap.parse_headers(raw)
    assert (headers.remote_port, headers.get_last, headers.period_ns) == (40000, True, 5_000_000)
    assert ap.encode_response(10, 300, udp_port=40001).startswith(b"remote-port: 40001\nframe-count: 10\n")


def test_error_response_round_trips_through_achd_rules():
    raw = ap.encode_error(ap.ACH_EACCES, "channel mds-ref: not writable from the network (use mds-ref-filter)")
    headers, _ = ap.parse_headers(raw)
    assert headers.status == ap.ACH_EACCES
    assert raw.startswith(b"status: 15 # ACH_EACCES\n")
    assert "mds-ref" in headers.message and ":" not in headers.message


def test_encoders_refuse_what_achd_could_not_parse():
    with pytest.raises(ap.HeaderError):
        ap.encode_request("bad name", "tcp", "push")
    with pytest.raises(ap.HeaderError):
        ap.encode_request("ok", "sctp", "push")
    with pytest.raises(ap.HeaderError):
        ap.encode_request("ok", "udp", "push")  # no udp port
    with pytest.raises(ap.HeaderError):
        ap.encode_headers([("message", "a=b")])
    assert ap.encode_headers([("frame-count", 3)]) == b"frame-count: 3\n.\n"


def test_frame_decoder_bounds_and_magic():
    decoder = ap.FrameDecoder(max_size=8)
    stream = ap.encode_frame(b"small") + ap.encode_frame(b"x" * 100) + ap.encode_frame(b"after")
    got = []
    for i in range(0, len(stream), 5):
        got += decoder.feed(stream[i : i + 5])
    assert got == [b"small", b"after"]
    assert decoder.oversize == 1
    assert ap.FrameDecoder().feed(ap.encode_frame(b"")) == [b""]
    with pytest.raises(ap.FrameError):
        ap.FrameDecoder().feed(b"HTTP/1.1 200 OK\r\n")
    with pytest.raises(ap.FrameError):
        ap.FrameDecoder().feed(b"achx")  # wrong already within the first bytes


def test_channel_names():
    assert ap.valid_channel_name("mds-ref-filter")
    assert ap.valid_channel_name("a" * 63)
    assert not ap.valid_channel_name("a" * 64)
    assert not ap.valid_channel_name("")
    assert not ap.valid_channel_name(".x")
    assert not ap.valid_channel_name("a/b")
