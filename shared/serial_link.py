"""Serial framing and transport shared by serial masters and serial slave controllers.

Framing and transport only: which ``kind`` values exist and what their bodies hold is the business
of the device protocol built on top (a master's encoder stream, a slave's joint-servo controller).

Frame format, version 1
-----------------------

Before stuffing (the *raw* frame), all integers little-endian::

    byte  0         1        2      3      4 ..... n-1          n       n+1
        +---------+--------+------+------+--------------------+-------+-------+
        | version | kind   | seq (u16 LE)| body: msgpack map  | CRC-16 (u16 LE)|
        | u8 = 1  | u8     | lo   | hi   | (>= 1 byte)        | lo    | hi    |
        +---------+--------+------+------+--------------------+-------+-------+
        \\_______________ covered by the CRC _________________/

On the wire::

    COBS(raw frame) 0x00

* ``version`` :data:`FRAME_VERSION`; a receiver rejects any other value.
* ``kind``    message kind 0..255, defined by the device protocol (not checked here).
* ``seq``     per-sender running counter modulo 2**16; :func:`seq_delta` does the loss/reorder
  arithmetic.
* ``body``    one MessagePack map with string keys (self-describing fields, e.g. ``{"q": [...]}``),
  no trailing bytes, no duplicate keys.
* ``CRC``     CRC-16/CCITT-FALSE (a.k.a. CRC-16/IBM-3740, AUTOSAR): poly 0x1021, init 0xFFFF, not
  reflected, xorout 0x0000; check value ``crc("123456789") == 0x29B1``. It detects every 1-, 2- and
  3-bit error and every burst of up to 16 bits in frames of this size.
* COBS (Consistent Overhead Byte Stuffing, Cheshire & Baker 1999) removes every 0x00 from the raw
  frame at a cost of 1 byte per 254, so 0x00 marks a frame end and a receiver resynchronises on
  the next 0x00 after garbage. An encoded frame (without its 0x00) is at most
  :data:`MAX_FRAME_BYTES` long. An empty frame (two 0x00 in a row) is idle fill and is ignored;
  :class:`SerialLink` writes one 0x00 on open so the peer drops any half-received frame.

Libraries: ``cobs`` (C extension) for COBS, ``fastcrc`` (Rust) for the CRC, ``msgpack`` for bodies,
``pyserial`` for ports. Errors: :class:`FrameError` is a :class:`~telesurg.shared.errors.MessageError` (a
payload failed decoding, like every other strict decoder in telesurg); a port that cannot be
opened, read or written raises :class:`~telesurg.shared.errors.DeviceConnectionError` naming the port.

Example::

    >>> from telesurg.shared.serial_link import SerialLink, decode_frame, encode_frame
    >>> decode_frame(encode_frame(kind=3, seq=7, body={"q": [0.1, 0.2]}))
    Frame(kind=3, seq=7, body={'q': [0.1, 0.2]})
    >>> with SerialLink("loop://") as link:  # or "/dev/ttyUSB0", "/dev/pts/4", "socket://host:port"
    ...     link.send(3, {"q": [0.1, 0.2]})
    ...     link.receive(timeout=1.0)
    0
    Frame(kind=3, seq=0, body={'q': [0.1, 0.2]})
"""

from __future__ import annotations

import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, ClassVar, Generic, Literal, Protocol, Self, TypeVar

import msgpack
import serial
from cobs import cobs  # type: ignore[import-untyped]
from fastcrc import crc16
from telesurg.shared.errors import DeviceConnectionError, MessageError
from telesurg.shared.streams import SeqTracker, seq_distance

#: Version byte of every frame this module writes; frames of other versions are rejected.
FRAME_VERSION = 1
#: Longest COBS-encoded frame, bytes, without its 0x00 delimiter (a raw frame of ~1015 bytes).
MAX_FRAME_BYTES = 1024
#: Header bytes: version, kind, seq.
HEADER_BYTES = 4
#: CRC bytes after the body.
CRC_BYTES = 2
#: Sequence numbers count modulo this.
SEQ_MODULUS = 1 << 16

#: Why a frame was rejected; the keys of :attr:`FrameReader.errors`.
FrameErrorReason = Literal["oversize", "cobs", "short", "crc", "version", "body"]
FRAME_ERROR_REASONS: tuple[FrameErrorReason, ...] = ("oversize", "cobs", "short", "crc", "version", "body")

_HEADER = struct.Struct("<BBH")
_CRC = struct.Struct("<H")
_DELIMITER = b"\x00"


class FrameError(MessageError):
    """A serial frame could not be encoded or decoded.

    Attributes:
        reason: one of :data:`FRAME_ERROR_REASONS`, for counting.
    """

    def __init__(self, reason: FrameErrorReason, message: str) -> None:
        super().__init__(message)
        self.reason: FrameErrorReason = reason


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame.

    Attributes:
        kind: message kind 0..255 (meaning defined by the device protocol).
        seq: sender's sequence number 0..65535.
        body: the MessagePack map, string keys.
    """

    kind: int
    seq: int
    body: dict[str, Any]


def crc16_ccitt_false(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF, no reflection, xorout 0)."""
    return crc16.ibm_3740(data)


def seq_delta(a: int, b: int) -> int:
    """Signed distance from sequence number ``a`` to ``b`` modulo 2**16, in [-32768, 32767].

    With ``a`` the last accepted seq and ``b`` a new one: 1 is in order, ``d > 1`` means ``d - 1``
    frames were lost, ``d <= 0`` goes back. Wraps correctly: ``seq_delta(65535, 0) == 1``. The
    receivers count with :func:`frame_seq_tracker`, which uses the same distance.
    """
    return seq_distance(a, b, SEQ_MODULUS)


def frame_seq_tracker() -> SeqTracker:
    """Sequence bookkeeping of one receiving end of a link (the project's one :class:`SeqTracker`).

    16-bit numbers that wrap; a byte stream delivers in order, so a number going back (or
    repeating) is the sender restarting, and a forward jump is a gap of lost frames. Call
    ``reset()`` when the port is opened again or a new peer says HELLO: its counter may start
    anywhere; the counts carry on."""
    return SeqTracker(modulus=SEQ_MODULUS, reorders=False)


def _no_duplicate_keys(pairs: list[tuple[Any, Any]]) -> dict[Any, Any]:
    d = dict(pairs)
    if len(d) != len(pairs):
        raise ValueError("duplicate keys in a map")
    return d


_LEAF_TYPES = frozenset({int, float, str, bool, bytes, type(None)})


def _non_str_key(value: Any) -> tuple[str, Any] | None:
    """(path, key) of the first map key inside ``value`` that is not a string, else None."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str):
                return "", k
            if type(v) not in _LEAF_TYPES and (found := _non_str_key(v)):
                return f"[{k!r}]{found[0]}", found[1]
    elif isinstance(value, (list, tuple)) and not _LEAF_TYPES.issuperset(map(type, value)):
        for i, v in enumerate(value):
            if type(v) not in _LEAF_TYPES and (found := _non_str_key(v)):
                return f"[{i}]{found[0]}", found[1]
    return None


def encode_frame(kind: int, seq: int, body: dict[str, Any]) -> bytes:
    """Wire bytes of one frame: COBS(version, kind, seq, msgpack(body), CRC) + 0x00.

    Raises:
        ValueError: ``kind`` outside 0..255 or ``seq`` outside 0..65535.
        FrameError: ``body`` is not a map with string keys or holds a type msgpack cannot pack
            (reason ``"body"``), or the encoded frame exceeds :data:`MAX_FRAME_BYTES`
            (reason ``"oversize"``).
    """
    if isinstance(kind, bool) or not isinstance(kind, int) or not 0 <= kind <= 0xFF:
        raise ValueError(f"kind must be an integer in [0, 255], got {kind!r}")
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= 0xFFFF:
        raise ValueError(f"seq must be an integer in [0, 65535], got {seq!r}")
    if not isinstance(body, dict):
        raise FrameError("body", f"body must be a dict, got {type(body).__name__}")
    if found := _non_str_key(body):  # decode_frame would reject it: fail at the sender instead
        raise FrameError("body", f"body{found[0]} keys must be strings, got {found[1]!r}")
    try:
        packed: bytes = msgpack.packb(body, use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise FrameError("body", f"body cannot be packed as MessagePack: {exc}") from None
    raw = bytearray(_HEADER.pack(FRAME_VERSION, kind, seq))
    raw += packed
    raw += _CRC.pack(crc16_ccitt_false(raw))
    encoded: bytes = cobs.encode(raw)
    if len(encoded) > MAX_FRAME_BYTES:
        raise FrameError(
            "oversize", f"frame is {len(encoded)} bytes encoded, limit {MAX_FRAME_BYTES} (body too large)"
        )
    return encoded + _DELIMITER


def decode_frame(frame: bytes | bytearray | memoryview) -> Frame:
    """Decode one COBS-encoded frame (its trailing 0x00 optional) and check it strictly.

    Checks, in order: size, COBS, length, CRC, version, body.

    Raises:
        FrameError: with ``reason`` and a message saying what was wrong: ``oversize`` (longer than
            :data:`MAX_FRAME_BYTES`), ``cobs`` (bad stuffing or a 0x00 inside), ``short`` (fewer
            bytes than header + CRC), ``crc`` (mismatch, with expected and received values),
            ``version`` (not :data:`FRAME_VERSION`), ``body`` (not exactly one MessagePack map with
            unique string keys).
    """
    data = bytes(frame)
    if data.endswith(_DELIMITER):
        data = data[:-1]
    if len(data) > MAX_FRAME_BYTES:
        raise FrameError("oversize", f"frame is {len(data)} bytes encoded, limit {MAX_FRAME_BYTES}")
    try:
        raw: bytes = cobs.decode(data)
    except cobs.DecodeError as exc:
        raise FrameError("cobs", f"bad COBS encoding: {exc}") from None
    if len(raw) < HEADER_BYTES + CRC_BYTES:
        raise FrameError(
            "short",
            f"short frame: {len(raw)} bytes after COBS decoding, need at least {HEADER_BYTES + CRC_BYTES}",
        )
    content = memoryview(raw)[:-CRC_BYTES]
    (got,) = _CRC.unpack_from(raw, len(raw) - CRC_BYTES)
    expected = crc16_ccitt_false(content)
    if got != expected:
        raise FrameError("crc", f"CRC mismatch: expected 0x{expected:04X}, got 0x{got:04X}")
    version, kind, seq = _HEADER.unpack_from(raw)
    if version != FRAME_VERSION:
        raise FrameError("version", f"unknown frame version {version}, expected {FRAME_VERSION}")
    packed = content[HEADER_BYTES:]
    if not packed:
        raise FrameError("body", "body is empty, expected a MessagePack map")
    try:
        body = msgpack.unpackb(
            packed, raw=False, strict_map_key=True, object_pairs_hook=_no_duplicate_keys, max_ext_len=0
        )
    except Exception as exc:  # msgpack raises a family of unrelated exception types
        raise FrameError("body", f"body is not valid MessagePack: {type(exc).__name__}: {exc}") from None
    if not isinstance(body, dict):
        raise FrameError("body", f"body must be a MessagePack map, got {type(body).__name__}")
    bad = [k for k in body if not isinstance(k, str)]
    if bad:
        raise FrameError("body", f"body keys must be strings, got {bad[0]!r}")
    return Frame(kind, seq, body)


class FrameReader:
    """Incremental decoder: feed it byte chunks as they arrive, get whole frames back.

    Never raises on bad input. A damaged frame is dropped and counted; decoding resumes after the
    next 0x00. The buffer never holds more than ``max_frame_bytes``: a longer run without a 0x00
    is dropped, counted once as ``"oversize"``, and skipped up to the next 0x00. Not thread-safe
    (one reader per byte stream; :class:`SerialLink` guards its own).

    Attributes:
        frames: frames decoded.
        errors: rejected frames by :data:`FrameErrorReason` (a Counter: missing reasons read 0).
        dropped_bytes: bytes, excluding 0x00 delimiters, that did not end up in a decoded frame.
    """

    def __init__(self, max_frame_bytes: int = MAX_FRAME_BYTES) -> None:
        if max_frame_bytes < 1:
            raise ValueError(f"max_frame_bytes must be >= 1, got {max_frame_bytes}")
        self.max_frame_bytes = max_frame_bytes
        self.frames = 0
        self.errors: Counter[str] = Counter()
        self.dropped_bytes = 0
        self._buf = bytearray()
        self._skipping = False  # inside an oversized run, waiting for its 0x00

    @property
    def error_count(self) -> int:
        """Rejected frames, all reasons."""
        return sum(self.errors.values())

    @property
    def buffered(self) -> int:
        """Bytes of an unfinished frame held now (always <= ``max_frame_bytes``)."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume ``data``; return the frames it completed, oldest first."""
        chunk = bytes(data)
        out: list[Frame] = []
        start = 0
        while (end := chunk.find(0, start)) >= 0:
            self._append(chunk[start:end])
            self._end_frame(out)
            start = end + 1
        self._append(chunk[start:])
        return out

    def reset(self) -> None:
        """Forget a half-received frame (counted as dropped bytes); counters are kept."""
        self.dropped_bytes += len(self._buf)
        self._buf.clear()
        self._skipping = False

    def _append(self, part: bytes) -> None:
        if not part:
            return
        if self._skipping:
            self.dropped_bytes += len(part)
            return
        if len(self._buf) + len(part) > self.max_frame_bytes:
            self.dropped_bytes += len(self._buf) + len(part)
            self.errors["oversize"] += 1
            self._buf.clear()
            self._skipping = True
            return
        self._buf += part

    def _end_frame(self, out: list[Frame]) -> None:
        if self._skipping:
            self._skipping = False
            return
        if not self._buf:
            return  # idle fill: 0x00 0x00
        data = bytes(self._buf)
        self._buf.clear()
        try:
            frame = decode_frame(data)
        except FrameError as exc:
            self.errors[exc.reason] += 1
            self.dropped_bytes += len(data)
            return
        self.frames += 1
        out.append(frame)


class SerialLink:
    """Framed, thread-safe link over a pyserial port URL; a context manager.

    Opens the port on construction (``serial.serial_for_url``, so ``/dev/ttyUSB0``,
    ``/dev/pts/N``, ``loop://`` and ``socket://host:port`` all work), discards stale input and
    writes one 0x00 so the peer drops any half-received frame.

    No background thread: :meth:`receive` and :meth:`poll` read what the port has when called.
    :meth:`send` and the receiving methods may be called from different threads; each side is
    serialised by its own lock.

    Args:
        url: port name or pyserial URL.
        baudrate: bits/s (ignored by pseudo-terminals, ``loop://`` and ``socket://``).
        read_slice: s, longest single blocking read inside :meth:`receive`; a ``receive`` may
            return up to this much after its timeout.

    Raises:
        DeviceConnectionError: the port cannot be opened (the message names it).
    """

    def __init__(self, url: str, *, baudrate: int = 115_200, read_slice: float = 0.01) -> None:
        if read_slice <= 0:
            raise ValueError(f"read_slice must be > 0 s, got {read_slice}")
        self.url = url
        self._tx_lock = threading.Lock()
        self._rx_lock = threading.Lock()
        self._reader = FrameReader()
        self._pending: deque[Frame] = deque()
        self._seq = 0
        self.sent = 0
        try:
            self._port: Any = serial.serial_for_url(url, baudrate=baudrate, timeout=read_slice)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceConnectionError(f"cannot open serial port {url!r}: {exc}") from exc
        self._closed = False
        try:
            self._port.reset_input_buffer()
            self._port.write(_DELIMITER)
        except (serial.SerialException, OSError) as exc:
            self._port.close()
            raise DeviceConnectionError(f"cannot use serial port {url!r}: {exc}") from exc

    def __enter__(self) -> SerialLink:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"SerialLink({self.url!r}, {state}, sent={self.sent}, received={self._reader.frames})"

    @property
    def reader(self) -> FrameReader:
        """The incoming decoder, for its counters (``frames``, ``errors``, ``dropped_bytes``)."""
        return self._reader

    @property
    def next_seq(self) -> int:
        """Sequence number the next :meth:`send` will use."""
        return self._seq

    @property
    def closed(self) -> bool:
        return self._closed

    def send(self, kind: int, body: dict[str, Any]) -> int:
        """Frame and write one message; return the sequence number it carried.

        The seq advances only when a frame was written, so gaps a receiver sees are real losses.

        Raises:
            ValueError / FrameError: as :func:`encode_frame`.
            DeviceConnectionError: the port is closed or the write failed.
        """
        with self._tx_lock:
            self._check_open()
            seq = self._seq
            data = encode_frame(kind, seq, body)
            try:
                self._port.write(data)
            except (serial.SerialException, OSError) as exc:
                raise DeviceConnectionError(f"write to serial port {self.url!r} failed: {exc}") from exc
            self._seq = (seq + 1) % SEQ_MODULUS
            self.sent += 1
            return seq

    def receive(self, timeout: float = 0.0) -> Frame | None:
        """Next frame, waiting up to ``timeout`` s (0: only what has arrived); None if none came.

        Raises:
            DeviceConnectionError: the port is closed or the read failed.
        """
        if timeout < 0:
            raise ValueError(f"timeout must be >= 0 s, got {timeout}")
        deadline = time.monotonic() + timeout
        with self._rx_lock:
            self._check_open()
            if not self._pending:
                self._read(block=False)
            while not self._pending and time.monotonic() < deadline:
                self._read(block=True)
            return self._pending.popleft() if self._pending else None

    def poll(self) -> list[Frame]:
        """Every frame available now, oldest first, without waiting.

        Raises:
            DeviceConnectionError: the port is closed or the read failed.
        """
        with self._rx_lock:
            self._check_open()
            self._read(block=False)
            out = list(self._pending)
            self._pending.clear()
            return out

    def close(self) -> None:
        """Close the port. Idempotent; a later send/receive raises DeviceConnectionError."""
        with self._tx_lock:
            if self._closed:
                return
            self._closed = True
        self._port.close()

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceConnectionError(f"serial port {self.url!r} is closed")

    def _read(self, *, block: bool) -> None:
        """Read what is waiting (or, if ``block``, wait up to one read slice for a byte)."""
        try:
            waiting = self._port.in_waiting
            if waiting:
                data = self._port.read(waiting)
            elif block:
                data = self._port.read(1)
                if data and (more := self._port.in_waiting):
                    data += self._port.read(more)
            else:
                return
        except Exception as exc:  # a close() from another thread may surface as any error
            if self._closed:
                raise DeviceConnectionError(f"serial port {self.url!r} was closed during a read") from exc
            if isinstance(exc, (serial.SerialException, OSError)):
                raise DeviceConnectionError(f"read from serial port {self.url!r} failed: {exc}") from exc
            raise
        if data:
            self._pending.extend(self._reader.feed(data))


# --------------------------------------------------------------------------- body field checks
# Shared by the device protocols built on this framing (encoder board, servo controller): each
# raises a MessageError naming the field, so a bad frame is refused with a clear reason.

#: Longest string field of a device message body.
MAX_BODY_STR = 32


def check_int(name: str, value: Any, lo: int, hi: int) -> int:
    """``value`` if it is an int (not a bool) in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise MessageError(f"{name} must be an integer, got {type(value).__name__}")
    if not lo <= value <= hi:
        raise MessageError(f"{name}={value} outside [{lo}, {hi}]")
    return value


def check_bool(name: str, value: Any) -> bool:
    """``value`` if it is a bool."""
    if not isinstance(value, bool):
        raise MessageError(f"{name} must be a boolean, got {type(value).__name__}")
    return value


def check_str(name: str, value: Any, min_len: int) -> str:
    """``value`` if it is a string of ``min_len`` .. :data:`MAX_BODY_STR` characters."""
    if not isinstance(value, str):
        raise MessageError(f"{name} must be a string, got {type(value).__name__}")
    if not min_len <= len(value) <= MAX_BODY_STR:
        raise MessageError(f"{name} must be {min_len}..{MAX_BODY_STR} characters, got {len(value)}")
    return value


def check_fields(kind: str, body: dict[str, Any], keys: frozenset[str]) -> None:
    """Exact key set, or a MessageError naming what is missing / unknown."""
    if missing := keys - body.keys():
        raise MessageError(
            f"{kind} missing field(s) {sorted(missing)}; expected {', '.join(sorted(keys)) or 'none'}"
        )
    if unknown := body.keys() - keys:
        raise MessageError(
            f"{kind} unknown field(s) {sorted(unknown)}; valid: {', '.join(sorted(keys)) or 'none'}"
        )


def check_proto(protocol: str, version: int, kind: str, proto: Any) -> None:
    """``proto`` is an int 0..255 equal to ``version``, the ``protocol`` this host speaks."""
    check_int(f"{kind} proto", proto, 0, 255)
    if proto != version:
        raise MessageError(
            f"{kind} proto={proto} unsupported; this host speaks {protocol} protocol {version}"
        )


class WireMessage(Protocol):
    """A device-protocol message: its frame kind and its body (the frame's MessagePack map)."""

    KIND: ClassVar[int]

    def body(self) -> dict[str, Any]: ...


@dataclass(frozen=True, slots=True)
class HelloRequestBase:
    """HELLO_REQUEST (host → device): please send a HELLO now. Each device protocol subclasses
    it with its ``KIND``, ``PROTOCOL`` name and ``VERSION``."""

    KIND: ClassVar[int]
    PROTOCOL: ClassVar[str]
    VERSION: ClassVar[int]
    KEYS: ClassVar[frozenset[str]] = frozenset({"proto"})

    proto: int

    def __post_init__(self) -> None:
        check_proto(self.PROTOCOL, self.VERSION, "HELLO_REQUEST", self.proto)

    def body(self) -> dict[str, Any]:
        return {"proto": self.proto}

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Self:
        check_fields("HELLO_REQUEST", body, cls.KEYS)
        return cls(**body)


M = TypeVar("M")


class MessageSet(Generic[M]):
    """The messages of one device protocol, by frame kind: decode a frame, encode or send one.

    Args:
        protocol: its name in errors (``"encoder"``, ``"servo"``).
        classes: the message classes; each has ``KIND`` and ``from_body(body)``.
        foreign: kinds of another device's protocol, explained in the error when one arrives
            (``{0x02: "the encoder board's SAMPLE: a master's board on this port"}``).
    """

    def __init__(
        self,
        protocol: str,
        classes: Sequence[Any],
        names: Mapping[int, str],
        foreign: Mapping[int, str] | None = None,
    ) -> None:
        self.protocol = protocol
        self.by_kind: dict[int, Any] = {c.KIND: c for c in classes}
        if len(self.by_kind) != len(classes) or set(self.by_kind) != set(names):
            raise ValueError(f"{protocol}: kinds {sorted(self.by_kind)} do not match the names {dict(names)}")
        self.names = dict(names)
        self.foreign = dict(foreign or {})

    def decode(self, frame: Frame) -> M:
        """The message in a decoded frame.

        Raises:
            MessageError: unknown kind (another device's kinds are named as such), or a body
                with missing/unknown keys, wrong types or values out of range; the message names
                the kind and the field.
        """
        cls = self.by_kind.get(frame.kind)
        if cls is None:
            valid = ", ".join(f"0x{k:02X} {n}" for k, n in self.names.items())
            hint = ""
            if frame.kind in self.foreign:
                hint = f" (0x{frame.kind:02X} is {self.foreign[frame.kind]}?)"
            raise MessageError(f"unknown {self.protocol} frame kind 0x{frame.kind:02X}{hint}; valid: {valid}")
        msg: M = cls.from_body(frame.body)
        return msg

    @staticmethod
    def encode(msg: WireMessage, seq: int) -> bytes:
        """Wire bytes of ``msg`` as frame number ``seq`` (COBS frame with its 0x00)."""
        return encode_frame(msg.KIND, seq, msg.body())

    @staticmethod
    def send(link: SerialLink, msg: WireMessage) -> int:
        """Send ``msg`` on ``link``; return the frame's seq. Raises as :meth:`SerialLink.send`."""
        return link.send(msg.KIND, msg.body())
