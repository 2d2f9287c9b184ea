"""Serial framing and transport over real ports: loop://, a pseudo-terminal pair, a TCP socket.

No mocked Serial: every SerialLink test goes through pyserial to a real transport.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import msgpack
import pytest
from cobs import cobs  # type: ignore[import-untyped]
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from telesurg.shared.errors import DeviceConnectionError, MessageError, TelesurgError
from telesurg.shared.serial_link import (
    FRAME_VERSION,
    MAX_FRAME_BYTES,
    Frame,
    FrameError,
    FrameReader,
    SerialLink,
    crc16_ccitt_false,
    decode_frame,
    encode_frame,
    seq_delta,
)

pytestmark = pytest.mark.timeout(20)

JOINTS6 = {
    "position": [0.1, -0.2, 0.3, -0.4, 0.5, -0.6],
    "velocity": [0.01, 0.02, 0.03, 0.04, 0.05, 0.06],
    "effort": [1.5, -2.5, 3.5, -4.5, 5.5, -6.5],
    "faults": 0,
}


def raw_frame(content: bytes, crc: int | None = None) -> bytes:
    """Raw (unstuffed) frame: content + CRC (the right one unless ``crc`` is given)."""
    return content + struct.pack("<H", crc16_ccitt_false(content) if crc is None else crc)


def wire(raw: bytes) -> bytes:
    """COBS-encode a raw frame and terminate it, as a sender would."""
    return bytes(cobs.encode(raw)) + b"\x00"


def content(kind: int, seq: int, body: Any, version: int = FRAME_VERSION) -> bytes:
    packed: bytes = msgpack.packb(body, use_bin_type=True)
    return struct.pack("<BBH", version, kind, seq) + packed


def flip_bit(data: bytes, bit: int) -> bytes:
    b = bytearray(data)
    b[bit // 8] ^= 1 << (bit % 8)
    return bytes(b)


# --------------------------------------------------------------------------- format


def test_crc_is_ccitt_false_standard_check_value() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1


def test_wire_layout_matches_the_documented_diagram() -> None:
    data = encode_frame(0x42, 0x1234, {"q": [1.0]})
    assert data.endswith(b"\x00") and data.count(0) == 1
    raw = cobs.decode(data[:-1])
    assert raw[:4] == bytes([FRAME_VERSION, 0x42, 0x34, 0x12])  # version, kind, seq LE
    assert msgpack.unpackb(raw[4:-2]) == {"q": [1.0]}
    assert raw[-2:] == struct.pack("<H", crc16_ccitt_false(raw[:-2]))  # CRC LE over the rest


leaves = (
    st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=False)
    | st.text(max_size=8)
    | st.booleans()
    | st.none()
)
values = st.recursive(leaves, lambda c: st.lists(c, max_size=6), max_leaves=16)
bodies = st.dictionaries(st.text(max_size=8), values, max_size=6)


@settings(max_examples=150, deadline=None, database=None)
@given(kind=st.integers(0, 255), seq=st.integers(0, 0xFFFF), body=bodies)
def test_encode_decode_round_trip(kind: int, seq: int, body: dict[str, Any]) -> None:
    data = encode_frame(kind, seq, body)
    assert data.index(0) == len(data) - 1  # the only 0x00 is the delimiter
    assert decode_frame(data) == Frame(kind, seq, body)
    assert decode_frame(data[:-1]) == Frame(kind, seq, body)  # delimiter optional


def test_frame_error_is_a_message_error() -> None:
    assert issubclass(FrameError, MessageError)
    assert issubclass(FrameError, TelesurgError)
    assert issubclass(FrameError, ValueError)


# --------------------------------------------------------------------------- decode errors


@pytest.mark.parametrize(
    ("data", "reason", "match"),
    [
        (b"\x01" * (MAX_FRAME_BYTES + 1), "oversize", f"frame is {MAX_FRAME_BYTES + 1} bytes encoded, limit"),
        (b"\x05ab", "cobs", "bad COBS encoding"),
        (b"\x02a\x00\x02b", "cobs", "bad COBS encoding"),  # 0x00 inside a frame
        (b"", "short", "short frame: 0 bytes after COBS decoding, need at least 6"),
        (wire(b"\x01\x02\x03\x04\x05"), "short", "short frame: 5 bytes"),
        (wire(raw_frame(content(1, 2, {"a": 1}, version=2))), "version", "unknown frame version 2, expected"),
        (wire(raw_frame(content(1, 2, {}, version=0))), "version", "unknown frame version 0, expected 1"),
        (wire(raw_frame(content(1, 2, [1, 2]))), "body", "must be a MessagePack map, got list"),
        (wire(raw_frame(content(1, 2, 7))), "body", "must be a MessagePack map, got int"),
        (wire(raw_frame(struct.pack("<BBH", 1, 1, 2))), "body", "body is empty"),
        (wire(raw_frame(content(1, 2, {"a": 1}) + b"\xc0")), "body", "ExtraData"),  # trailing byte
        (wire(raw_frame(content(1, 2, {"a": 1})[:-1])), "body", "not valid MessagePack"),  # truncated
        (wire(raw_frame(content(1, 2, {1: 2}))), "body", "not valid MessagePack"),  # int key
        (wire(raw_frame(content(1, 2, {b"k": 2}))), "body", "keys must be strings"),  # bytes key
        (wire(raw_frame(content(1, 2, {"a": 1}) + b"\xa1a\x02")), "body", "ExtraData"),
        (wire(raw_frame(b"\x01\x01\x02\x00\x82\xa1a\x01\xa1a\x02")), "body", "duplicate keys"),
    ],
)
def test_decode_errors_name_the_problem(data: bytes, reason: str, match: str) -> None:
    with pytest.raises(FrameError, match=match) as info:
        decode_frame(data)
    assert info.value.reason == reason


def test_crc_mismatch_reports_expected_and_received() -> None:
    body_bytes = content(3, 9, {"q": 1})
    good = crc16_ccitt_false(body_bytes)
    bad = good ^ 0x0101
    with pytest.raises(FrameError, match=f"CRC mismatch: expected 0x{good:04X}, got 0x{bad:04X}") as info:
        decode_frame(wire(raw_frame(body_bytes, crc=bad)))
    assert info.value.reason == "crc"


def test_every_single_bit_flip_is_a_crc_error() -> None:
    raw = cobs.decode(encode_frame(7, 513, JOINTS6)[:-1])
    for bit in range(len(raw) * 8):  # every bit: header, body and the CRC itself
        with pytest.raises(FrameError, match="CRC mismatch") as info:
            decode_frame(wire(flip_bit(raw, bit)))
        assert info.value.reason == "crc", bit


def test_every_single_bit_flip_on_the_wire_is_rejected() -> None:
    data = encode_frame(7, 513, JOINTS6)[:-1]
    for bit in range(len(data) * 8):  # flips in COBS code bytes shift data around, or make a 0x00
        with pytest.raises(FrameError):
            decode_frame(flip_bit(data, bit))


# --------------------------------------------------------------------------- encode errors


def test_encode_rejects_bad_kind_seq_and_bodies() -> None:
    for kind in (-1, 256, True, 1.0):
        with pytest.raises(ValueError, match="kind must be an integer in"):
            encode_frame(kind, 0, {})  # type: ignore[arg-type]
    for seq in (-1, 0x10000):
        with pytest.raises(ValueError, match="seq must be an integer in"):
            encode_frame(0, seq, {})
    with pytest.raises(FrameError, match="body must be a dict, got list"):
        encode_frame(0, 0, [1])  # type: ignore[arg-type]
    with pytest.raises(FrameError, match="body keys must be strings, got 1"):
        encode_frame(0, 0, {1: 2})  # type: ignore[dict-item]
    with pytest.raises(FrameError, match=r"body\['a'\]\[0\] keys must be strings"):
        encode_frame(0, 0, {"a": [{2: 3}]})
    with pytest.raises(FrameError, match="cannot be packed") as info:
        encode_frame(0, 0, {"a": object()})
    assert info.value.reason == "body"


def test_encode_rejects_oversized_frames_and_accepts_the_largest() -> None:
    with pytest.raises(FrameError, match=f"limit {MAX_FRAME_BYTES}") as info:
        encode_frame(0, 0, {"blob": "x" * MAX_FRAME_BYTES})
    assert info.value.reason == "oversize"
    n = MAX_FRAME_BYTES  # find the longest string body that still fits: it must round-trip
    while True:
        try:
            data = encode_frame(0, 0, {"blob": "x" * n})
            break
        except FrameError:
            n -= 1
    assert len(data) == MAX_FRAME_BYTES + 1
    assert decode_frame(data).body == {"blob": "x" * n}


# --------------------------------------------------------------------------- sequence numbers


@pytest.mark.parametrize(
    ("a", "b", "d"),
    [(0, 1, 1), (65535, 0, 1), (65530, 4, 10), (0, 65535, -1), (5, 5, 0), (10, 3, -7), (0, 32767, 32767)],
)
def test_seq_delta_cases(a: int, b: int, d: int) -> None:
    assert seq_delta(a, b) == d


@given(a=st.integers(0, 0xFFFF), d=st.integers(-0x8000, 0x7FFF))
def test_seq_delta_inverts_modular_addition(a: int, d: int) -> None:
    assert seq_delta(a, (a + d) % 0x10000) == d


# --------------------------------------------------------------------------- FrameReader


def chunked(data: bytes, cuts: list[int]) -> Iterator[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts})
    start = 0
    for p in [*points, len(data)]:
        yield data[start:p]
        start = p


items = st.one_of(
    st.tuples(st.just("ok"), st.integers(0, 255), bodies),
    st.tuples(st.just("damaged"), st.integers(0, 255), st.integers(0, 10_000)),
    st.tuples(st.just("garbage"), st.binary(min_size=1, max_size=40)),
)


@settings(max_examples=100, deadline=None, database=None)
@given(stream=st.lists(items, max_size=25), cuts=st.lists(st.integers(0, 10**6), max_size=40))
def test_reader_recovers_every_intact_frame_and_counts_damage_exactly(
    stream: list[tuple[Any, ...]], cuts: list[int]
) -> None:
    data = bytearray()
    expected: list[Frame] = []
    damaged = garbage_segments = dropped = 0
    for seq, item in enumerate(stream):
        if item[0] == "ok":
            _, kind, body = item
            data += encode_frame(kind, seq, body)
            expected.append(Frame(kind, seq, body))
        elif item[0] == "damaged":  # one flipped bit in the raw frame: the CRC must catch it
            _, kind, bit = item
            raw = cobs.decode(encode_frame(kind, seq, {"q": [seq, 0.5]})[:-1])
            bad = wire(flip_bit(raw, bit % (len(raw) * 8)))
            data += bad
            damaged += 1
            dropped += len(bad) - 1
        else:  # line noise, ended by a 0x00 (a sender's idle fill, or a zero in the noise)
            noise = item[1] + b"\x00"
            for seg in noise.split(b"\x00"):
                if seg:
                    with contextlib.suppress(FrameError):
                        decode_frame(seg)
                        assume(False)  # random noise that is a valid frame: astronomically rare
                    garbage_segments += 1
                    dropped += len(seg)
            data += noise

    reader = FrameReader()
    got: list[Frame] = []
    for chunk in chunked(bytes(data), cuts):
        got += reader.feed(chunk)
        assert reader.buffered <= MAX_FRAME_BYTES

    assert got == expected
    assert reader.frames == len(expected)
    assert reader.errors["crc"] >= damaged
    assert reader.error_count == damaged + garbage_segments
    assert reader.dropped_bytes == dropped
    assert reader.buffered == 0


def test_noise_without_a_delimiter_costs_exactly_the_next_frame() -> None:
    a, b, c = (encode_frame(1, i, {"i": i}) for i in range(3))
    reader = FrameReader()
    frames = reader.feed(a + b"\x13\x37noise" + b + c)
    assert [f.seq for f in frames] == [0, 2]  # b was glued to the noise; c resynchronised
    assert reader.error_count == 1
    assert reader.dropped_bytes == len(b"\x13\x37noise") + len(b) - 1


def test_idle_delimiters_are_not_errors() -> None:
    reader = FrameReader()
    frames = reader.feed(b"\x00\x00" + encode_frame(1, 0, {}) + b"\x00\x00\x00")
    assert len(frames) == 1 and reader.error_count == 0 and reader.dropped_bytes == 0


def test_reader_bounds_its_buffer_and_counts_an_overlong_run_once() -> None:
    reader = FrameReader()
    for _ in range(30):
        assert reader.feed(b"\x01" * 100) == []
        assert reader.buffered <= MAX_FRAME_BYTES
    frames = reader.feed(b"\x01" * 5 + b"\x00" + encode_frame(2, 9, {"ok": True}))
    assert frames == [Frame(2, 9, {"ok": True})]
    assert reader.errors == {"oversize": 1}
    assert reader.dropped_bytes == 3005
    assert reader.buffered == 0


def test_reader_accepts_a_frame_of_exactly_the_limit_split_anywhere() -> None:
    body = {"blob": "x" * (MAX_FRAME_BYTES - 20)}
    data = encode_frame(0, 0, body)
    assert len(data) <= MAX_FRAME_BYTES + 1
    reader = FrameReader()
    out = [f for i in range(0, len(data), 3) for f in reader.feed(data[i : i + 3])]
    assert out == [Frame(0, 0, body)]


@settings(max_examples=300, deadline=None, database=None)
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 10**6), max_size=20))
def test_reader_never_raises_on_arbitrary_bytes(data: bytes, cuts: list[int]) -> None:
    reader = FrameReader()
    for chunk in chunked(data, cuts):
        reader.feed(chunk)
        assert reader.buffered <= MAX_FRAME_BYTES
    reader.feed(b"\x00")
    assert reader.buffered == 0
    assert reader.dropped_bytes <= len(data) - data.count(0)


# --------------------------------------------------------------------------- SerialLink: loop://


def test_loop_round_trip() -> None:
    with SerialLink("loop://") as link:
        seqs = [link.send(5, {"i": i, **JOINTS6}) for i in range(3)]
        assert seqs == [0, 1, 2] and link.next_seq == 3 and link.sent == 3
        for i in range(3):  # loop:// delivers at once, so no waiting is needed
            assert link.receive(timeout=0.0) == Frame(5, i, {"i": i, **JOINTS6})
        assert link.receive(timeout=0.0) is None
        t0 = time.monotonic()
        assert link.receive(timeout=0.05) is None
        assert time.monotonic() - t0 >= 0.05
        assert link.reader.frames == 3 and link.reader.error_count == 0  # opening 0x00 is idle fill


def test_loop_poll_returns_everything_waiting_in_order() -> None:
    with SerialLink("loop://") as link:
        for i in range(5):
            link.send(1, {"i": i})
        deadline = time.monotonic() + 2.0
        got: list[Frame] = []
        while len(got) < 5 and time.monotonic() < deadline:
            got += link.poll()
        assert [f.body["i"] for f in got] == [0, 1, 2, 3, 4]
        assert link.poll() == []


def test_send_seq_wraps_and_a_failed_encode_uses_no_seq() -> None:
    with SerialLink("loop://") as link:
        link._seq = 0xFFFF  # skip 65535 sends
        with pytest.raises(FrameError):
            link.send(1, {"blob": "x" * 2000})
        assert link.send(1, {}) == 0xFFFF
        assert link.send(1, {}) == 0
        a, b = link.receive(1.0), link.receive(1.0)
        assert a is not None and b is not None and seq_delta(a.seq, b.seq) == 1


def test_concurrent_senders_never_interleave_frames() -> None:
    n_threads, per_thread = 4, 40
    pad = "x" * 300  # long writes (loop:// queues byte by byte) and fast thread switches invite races
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        _run_concurrent_senders(n_threads, per_thread, pad)
    finally:
        sys.setswitchinterval(interval)


def _run_concurrent_senders(n_threads: int, per_thread: int, pad: str) -> None:
    with SerialLink("loop://") as link:

        def sender(t: int) -> None:
            for i in range(per_thread):
                link.send(t, {"t": t, "i": i, "pad": pad})

        threads = [threading.Thread(target=sender, args=(t,)) for t in range(n_threads)]
        for th in threads:
            th.start()
        got: list[Frame] = []
        deadline = time.monotonic() + 10.0
        while len(got) < n_threads * per_thread and time.monotonic() < deadline:
            f = link.receive(timeout=0.1)
            if f is not None:
                got.append(f)
        for th in threads:
            th.join(timeout=5.0)
        assert len(got) == n_threads * per_thread
        assert sorted(f.seq for f in got) == list(range(n_threads * per_thread))
        assert link.reader.error_count == 0
        for t in range(n_threads):
            assert [f.body["i"] for f in got if f.kind == t] == list(range(per_thread))


def test_close_is_idempotent_and_later_use_names_the_port() -> None:
    link = SerialLink("loop://")
    link.close()
    link.close()
    assert link.closed
    with pytest.raises(DeviceConnectionError, match="'loop://' is closed"):
        link.send(1, {})
    with pytest.raises(DeviceConnectionError, match="'loop://' is closed"):
        link.receive(0.1)
    with pytest.raises(DeviceConnectionError, match="'loop://' is closed"):
        link.poll()


# --------------------------------------------------------------------------- SerialLink: a pty pair


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(controller-side fd, device name) of a real pseudo-terminal pair."""
    master_fd, slave_fd = os.openpty()
    try:
        yield master_fd, os.ttyname(slave_fd)
    finally:
        for fd in (master_fd, slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)


def read_frames(fd: int, reader: FrameReader, want: int, timeout: float = 2.0) -> list[Frame]:
    out: list[Frame] = []
    deadline = time.monotonic() + timeout
    while len(out) < want and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.05)
        if ready:
            out += reader.feed(os.read(fd, 4096))
    return out


def test_pty_peer_writing_small_chunks(pty_pair: tuple[int, str]) -> None:
    peer_fd, name = pty_pair
    n = 60
    with SerialLink(name) as link:  # opened (raw mode) before the peer writes
        stream = bytearray()
        for i in range(n):
            stream += encode_frame(0x10, i, {"enc": [i, -i, i * 3, 0, 1, 2], "t_us": i * 1000})
            if i == n // 2:
                stream += b"\xde\xad\xbe\xef\x00"  # a noise burst between frames

        def peer() -> None:
            for k in range(0, len(stream), 7):
                os.write(peer_fd, stream[k : k + 7])
                time.sleep(0.0002)

        th = threading.Thread(target=peer)
        th.start()
        got: list[Frame] = []
        deadline = time.monotonic() + 5.0
        while len(got) < n and time.monotonic() < deadline:
            f = link.receive(timeout=0.2)
            if f is not None:
                got.append(f)
        th.join(timeout=5.0)
        assert [f.seq for f in got] == list(range(n))
        assert got[7].body == {"enc": [7, -7, 21, 0, 1, 2], "t_us": 7000}
        assert link.reader.error_count == 1  # the noise burst, nothing else

        # and back: what the link sends arrives intact at the peer
        link.send(0x20, {"enable": True})
        back = read_frames(peer_fd, FrameReader(), 1)
        assert back == [Frame(0x20, 0, {"enable": True})]


def test_pty_peer_hangup_is_a_device_connection_error(pty_pair: tuple[int, str]) -> None:
    peer_fd, name = pty_pair
    with SerialLink(name) as link:
        os.close(peer_fd)  # the device went away
        with pytest.raises(DeviceConnectionError, match=name):
            for _ in range(10):
                link.receive(timeout=0.05)
                link.send(1, {})


# --------------------------------------------------------------------------- SerialLink: socket://


def test_socket_url_round_trip_through_an_echo_peer() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def echo() -> None:
        conn, _ = server.accept()
        with conn:
            while data := conn.recv(4096):
                conn.sendall(data)

    th = threading.Thread(target=echo, daemon=True)
    th.start()
    try:
        with SerialLink(f"socket://127.0.0.1:{port}") as link:
            link.send(3, JOINTS6)
            assert link.receive(timeout=2.0) == Frame(3, 0, JOINTS6)
    finally:
        server.close()
        th.join(timeout=2.0)


# --------------------------------------------------------------------------- open failures


def test_nonexistent_port_names_itself() -> None:
    name = "/dev/ttyTELESURG_DOES_NOT_EXIST"
    with pytest.raises(DeviceConnectionError, match=f"cannot open serial port '{name}'") as info:
        SerialLink(name)
    assert isinstance(info.value, ConnectionError)


def test_refused_socket_and_unknown_scheme_name_the_port() -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    url = f"socket://127.0.0.1:{port}"
    with pytest.raises(DeviceConnectionError, match=f"cannot open serial port '{url}'"):
        SerialLink(url)
    with pytest.raises(DeviceConnectionError, match="cannot open serial port 'nope://x'"):
        SerialLink("nope://x")


# --------------------------------------------------------------------------- benchmark (printed)


def test_benchmark_encode_decode_six_joints(capsys: pytest.CaptureFixture[str]) -> None:
    n = 20_000
    t0 = time.perf_counter()
    for i in range(n):
        f = decode_frame(encode_frame(0x11, i & 0xFFFF, JOINTS6))
    us = (time.perf_counter() - t0) / n * 1e6
    assert f.body == JOINTS6
    with capsys.disabled():
        size = len(encode_frame(0x11, 0, JOINTS6))
        print(f"\nserial frame, 6 joints (pos/vel/effort, {size} B on the wire): {us:.1f} µs encode+decode")
