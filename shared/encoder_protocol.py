"""Encoder-board protocol: what the master's microcontroller sends over :mod:`telesurg.shared.serial_link`.

The all-joints ergonomic master (Shim 2015, Table 3 / Section 2.3) has six joints: joint 1, the
shoulder slide, is read as an on/off switch; joints 2-5 (elbow yaw, wrist yaw, wrist pitch, wrist
roll) by rotary quadrature encoders of 400 counts per revolution; joint 6, the finger slide, by a
linear potentiometer. A microcontroller (reference sketch: ``firmware/encoder_board``) samples them
and streams frames to the host; :class:`Calibration` turns the raw readings into joint values
(rad / m). Pure module: no I/O, no threads; :mod:`telesurg.shared.serial_link` is imported lazily.

Frame layout (from :mod:`telesurg.shared.serial_link`, version 1)
--------------------------------------------------------
Every message is one frame, ``COBS(raw) 0x00`` on the wire, with the raw frame::

    offset  size  field
    0       1     version   u8, 1
    1       1     kind      u8, see the table below
    2       2     seq       u16 little-endian, +1 per frame the sender writes (any kind), mod 2**16
    4       n     body      one MessagePack map, string keys (exact key set per kind, below)
    4+n     2     CRC       u16 little-endian, CRC-16/CCITT-FALSE over bytes 0 .. 4+n-1

COBS removes every 0x00 from the raw frame (1 code byte per started 254-byte block), so 0x00 only
ever ends a frame; a receiver resynchronises on it after line noise.

Kinds
-----
=====  ===============  ===============  ==================================================
kind   name             direction        when
=====  ===============  ===============  ==================================================
0x01   HELLO            board → host     at boot, every second, and on HELLO_REQUEST
0x02   SAMPLE           board → host     at the board's sample rate (``rate_hz``)
0x10   HELLO_REQUEST    host → board     when the host opens the port
=====  ===============  ===============  ==================================================

Any other kind is rejected (:class:`~telesurg.shared.errors.MessageError`). Bodies hold exactly the keys
below: a missing or an unknown key, a wrong type or a value out of range rejects the message.
Integers are MessagePack integers of any width (a sender may always use the smallest, like
``msgpack.packb``, or fixed widths); booleans are not integers.

HELLO body (kind 0x01)::

    "proto"           int  encoder protocol version, must be PROTO_VERSION = 1
    "model"           str  board model, 1..32 chars, e.g. "plas-master"
    "fw"              str  firmware version, 0..32 chars, e.g. "0.1.0"
    "joints"          int  master joints, 1..16 (plas-master: 6)
    "encoders"        int  entries of SAMPLE "counts", 0..8 (plas-master: 4, joints 2-5)
    "counts_per_rev"  int  encoder counts per revolution after quadrature decoding, 1..1_000_000
    "rate_hz"         int  nominal SAMPLE rate, Hz, 1..10_000

SAMPLE body (kind 0x02)::

    "t_us"    int        board clock when the inputs were read, µs, 0..2**32-1 (wraps: micros())
    "counts"  [int, ...] encoder counts since power-up, one per encoder, each a signed 32-bit int
    "pot"     int        linear potentiometer, 10-bit ADC reading, 0..1023
    "sw"      int        switches, 0..7: bit0 joint-1 switch pressed, bit1 clutch pedal pressed,
                         bit2 operator present; bits 3-7 are reserved and must be 0

HELLO_REQUEST body (kind 0x10)::

    "proto"   int  protocol version the host speaks (1)

Example SAMPLE, seq 7, ``{"t_us": 1234567, "counts": [100, -3, 0, 2000], "pot": 700, "sw": 6}``::

    raw  01 02 07 00                                   version 1, kind SAMPLE, seq 7
         84                                            map of 4
         a4 74 5f 75 73  ce 00 12 d6 87                "t_us": uint32 1234567
         a6 63 6f 75 6e 74 73  94 64 fd 00 cd 07 d0    "counts": [100, -3, 0, uint16 2000]
         a3 70 6f 74  cd 02 bc                         "pot": uint16 700
         a2 73 77  06                                  "sw": 6 (clutch + operator present)
         a9 19                                         CRC 0x19A9, little-endian
    wire 04 01 02 07 08 84 a4 74 5f 75 73 ce 0e 12 d6 87 a6 63 6f 75 6e 74 73 94 64 fd
         11 cd 07 d0 a3 70 6f 74 cd 02 bc a2 73 77 06 a9 19 00
         (COBS: code byte 04 prepended, 08 0e 11 replace the three raw 0x00s; 44 bytes)

A SAMPLE is at most 58 bytes on the wire (four encoders, every integer at full width), so a 115200
bit/s UART (11 520 bytes/s) carries at most ~198 SAMPLEs/s: the reference firmware sends 100 Hz at
115200 bit/s, 500 Hz needs 500 000 bit/s.

Example::

    >>> from telesurg.shared.encoder_protocol import Calibration, Sample
    >>> r = Calibration().convert(Sample(t_us=0, counts=(100, 0, 0, 0), pot=512, sw=0b110))
    >>> round(r.joints[1], 6), r.clutch, r.operator_present   # 100 counts of 400 = 90° on joint 2
    (1.570796, True, True)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.serial_link import HelloRequestBase, MessageSet, check_proto
from telesurg.shared.serial_link import check_fields as _fields
from telesurg.shared.serial_link import check_int as _int
from telesurg.shared.serial_link import check_str as _str

if TYPE_CHECKING:
    from telesurg.shared.serial_link import Frame

#: Version of the body layouts below; HELLO and HELLO_REQUEST carry it as ``proto``.
PROTO_VERSION = 1
KIND_HELLO = 0x01
KIND_SAMPLE = 0x02
KIND_HELLO_REQUEST = 0x10
KIND_NAMES = {KIND_HELLO: "HELLO", KIND_SAMPLE: "SAMPLE", KIND_HELLO_REQUEST: "HELLO_REQUEST"}

#: Largest potentiometer reading (10-bit ADC).
POT_MAX = 1023
#: ``sw`` bits.
SW_JOINT1 = 0x01
SW_CLUTCH = 0x02
SW_OPERATOR = 0x04
SW_MASK = SW_JOINT1 | SW_CLUTCH | SW_OPERATOR
#: Most encoder channels a SAMPLE may carry.
MAX_ENCODERS = 8
#: Most joints a board may declare.
MAX_JOINTS = 16
#: The board clock ``t_us`` counts modulo this (Arduino ``micros()``).
T_US_MODULUS = 1 << 32
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


# --------------------------------------------------------------------------- field checks


def _check_proto(kind: str, proto: int) -> None:
    check_proto("encoder", PROTO_VERSION, kind, proto)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Hello:
    """HELLO (board → host): who the board is and how its SAMPLEs are laid out.

    Attributes:
        model: board model, e.g. ``"plas-master"``.
        fw: firmware version string.
        joints: master joints the board serves.
        encoders: length of every SAMPLE's ``counts``.
        counts_per_rev: encoder counts per revolution (after quadrature decoding).
        rate_hz: nominal SAMPLE rate, Hz.
        proto: encoder protocol version, must be :data:`PROTO_VERSION`.
    """

    KIND: ClassVar[int] = KIND_HELLO
    KEYS: ClassVar[frozenset[str]] = frozenset(
        {"proto", "model", "fw", "joints", "encoders", "counts_per_rev", "rate_hz"}
    )

    model: str
    fw: str
    joints: int
    encoders: int
    counts_per_rev: int
    rate_hz: int
    proto: int = PROTO_VERSION

    def __post_init__(self) -> None:
        _check_proto("HELLO", self.proto)
        _str("HELLO model", self.model, 1)
        _str("HELLO fw", self.fw, 0)
        _int("HELLO joints", self.joints, 1, MAX_JOINTS)
        _int("HELLO encoders", self.encoders, 0, MAX_ENCODERS)
        _int("HELLO counts_per_rev", self.counts_per_rev, 1, 1_000_000)
        _int("HELLO rate_hz", self.rate_hz, 1, 10_000)

    def body(self) -> dict[str, Any]:
        return {
            "proto": self.proto,
            "model": self.model,
            "fw": self.fw,
            "joints": self.joints,
            "encoders": self.encoders,
            "counts_per_rev": self.counts_per_rev,
            "rate_hz": self.rate_hz,
        }

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Hello:
        _fields("HELLO", body, cls.KEYS)
        return cls(**body)  # __post_init__ checks types and ranges


@dataclass(frozen=True, slots=True)
class Sample:
    """SAMPLE (board → host): one reading of every input.

    Attributes:
        t_us: board clock at the reading, µs modulo 2**32.
        counts: encoder counts, one per encoder channel (signed 32-bit).
        pot: potentiometer ADC reading, 0..:data:`POT_MAX`.
        sw: switch bits (:data:`SW_JOINT1`, :data:`SW_CLUTCH`, :data:`SW_OPERATOR`).
    """

    KIND: ClassVar[int] = KIND_SAMPLE
    KEYS: ClassVar[frozenset[str]] = frozenset({"t_us", "counts", "pot", "sw"})

    t_us: int
    counts: tuple[int, ...]
    pot: int
    sw: int

    def __post_init__(self) -> None:
        _int("SAMPLE t_us", self.t_us, 0, T_US_MODULUS - 1)
        if not isinstance(self.counts, tuple):
            raise MessageError(f"SAMPLE counts must be an array, got {type(self.counts).__name__}")
        if len(self.counts) > MAX_ENCODERS:
            raise MessageError(f"SAMPLE counts has {len(self.counts)} entries, limit {MAX_ENCODERS}")
        for i, c in enumerate(self.counts):
            _int(f"SAMPLE counts[{i}]", c, _I32_MIN, _I32_MAX)
        _int("SAMPLE pot", self.pot, 0, POT_MAX)
        sw = _int("SAMPLE sw", self.sw, 0, 255)
        if sw & ~SW_MASK:
            raise MessageError(
                f"SAMPLE sw=0x{sw:02X} sets reserved bits (valid: bit0 joint 1, bit1 clutch, bit2 operator)"
            )

    @property
    def joint1_switch(self) -> bool:
        """Joint-1 (shoulder slide) switch pressed."""
        return bool(self.sw & SW_JOINT1)

    @property
    def clutch(self) -> bool:
        """Clutch pedal pressed."""
        return bool(self.sw & SW_CLUTCH)

    @property
    def operator_present(self) -> bool:
        """Operator-present sensor active."""
        return bool(self.sw & SW_OPERATOR)

    def body(self) -> dict[str, Any]:
        return {"t_us": self.t_us, "counts": list(self.counts), "pot": self.pot, "sw": self.sw}

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Sample:
        _fields("SAMPLE", body, cls.KEYS)
        counts = body["counts"]
        if not isinstance(counts, list):
            raise MessageError(f"SAMPLE counts must be an array, got {type(counts).__name__}")
        return cls(t_us=body["t_us"], counts=tuple(counts), pot=body["pot"], sw=body["sw"])


@dataclass(frozen=True, slots=True)
class HelloRequest(HelloRequestBase):
    """HELLO_REQUEST (host → board): please send a HELLO now."""

    KIND: ClassVar[int] = KIND_HELLO_REQUEST
    PROTOCOL: ClassVar[str] = "encoder"
    VERSION: ClassVar[int] = PROTO_VERSION

    proto: int = PROTO_VERSION


EncoderMessage = Hello | Sample | HelloRequest
#: The encoder protocol's messages by kind.
MESSAGES: MessageSet[EncoderMessage] = MessageSet("encoder", (Hello, Sample, HelloRequest), KIND_NAMES)


def decode_message(frame: Frame) -> EncoderMessage:
    """The encoder-protocol message in a decoded frame (see :meth:`MessageSet.decode`).

    Raises:
        MessageError: unknown kind, or a body with missing/unknown keys, wrong types or values
            out of range; the message names the kind and the field.
    """
    return MESSAGES.decode(frame)


#: Wire bytes of a message as frame number ``seq``: ``encode_message(msg, seq)``.
encode_message = MESSAGES.encode
#: Send a message on a :class:`SerialLink`, return its seq: ``send_message(link, msg)``.
send_message = MESSAGES.send


# --------------------------------------------------------------------------- calibration


@dataclass(frozen=True, slots=True)
class MasterReading:
    """A SAMPLE in joint units.

    Attributes:
        joints: joint values, rad (revolute) / m (prismatic), ``Calibration.joints`` of them.
            Joints no sensor reads (joint 1, the shoulder-slide switch) are 0.0.
        joint1_switch: joint-1 switch pressed.
        clutch: clutch pedal pressed.
        operator_present: operator-present sensor active.
        t_us: board clock of the reading, µs modulo 2**32.
    """

    joints: tuple[float, ...]
    joint1_switch: bool
    clutch: bool
    operator_present: bool
    t_us: int


@dataclass(frozen=True)
class Calibration:
    """Raw board readings → joint values. Defaults: the plas-master reference board, uncalibrated.

    Encoder channel ``k`` drives joint ``encoder_joints[k]`` (1-based)::

        q = direction[k] * (counts[k] - zero_counts[k]) * 2π / counts_per_rev      [rad]

    and the potentiometer drives joint ``pot_joint`` (0: no potentiometer)::

        q = (pot - pot_zero) * pot_m_per_count                                     [m]

    Joints no sensor reads are 0.0. Raises :class:`~telesurg.shared.errors.ConfigError` when inconsistent.
    """

    joints: int = 6  # master joints (plas-master: d1, theta2..theta5, d6); HELLO must agree
    # 1-based joint read by each encoder channel; thesis §2.3: encoders on joints 2-5
    encoder_joints: tuple[int, ...] = (2, 3, 4, 5)
    zero_counts: tuple[int, ...] = (0, 0, 0, 0)  # counts: each channel's reading at joint zero
    direction: tuple[int, ...] = (1, 1, 1, 1)  # +1 / -1: counts rise / fall as the joint angle rises
    counts_per_rev: int = 400  # counts per encoder revolution (Nemicon 7S: 400); HELLO must agree
    pot_joint: int = 6  # 1-based joint read by the potentiometer (finger slide d6); 0: none
    pot_zero: float = 511.5  # ADC counts at joint zero (mid-stroke of the default)
    pot_m_per_count: float = 0.030 / 1023  # m per ADC count (30 mm stroke); negative flips direction

    def __post_init__(self) -> None:
        n = len(self.encoder_joints)
        if not 1 <= self.joints <= MAX_JOINTS:
            raise ConfigError(f"calibration joints={self.joints} outside [1, {MAX_JOINTS}]")
        if n > MAX_ENCODERS:
            raise ConfigError(f"calibration has {n} encoder channels, limit {MAX_ENCODERS}")
        if len(self.zero_counts) != n or len(self.direction) != n:
            raise ConfigError(
                f"calibration zero_counts ({len(self.zero_counts)}) and direction ({len(self.direction)}) "
                f"need one entry per encoder channel ({n}, encoder_joints={list(self.encoder_joints)})"
            )
        used = [*self.encoder_joints, *([self.pot_joint] if self.pot_joint else [])]
        if any(not 1 <= j <= self.joints for j in used):
            raise ConfigError(f"calibration joints {used} must be in [1, {self.joints}] (pot_joint 0: none)")
        if len(set(used)) != len(used):
            raise ConfigError(f"calibration reads a joint twice: encoder_joints + pot_joint = {used}")
        if any(d not in (1, -1) for d in self.direction):
            raise ConfigError(f"calibration direction {list(self.direction)}: each must be 1 or -1")
        if self.counts_per_rev < 1:
            raise ConfigError(f"calibration counts_per_rev={self.counts_per_rev} must be >= 1")
        if (
            not math.isfinite(self.pot_zero)
            or not math.isfinite(self.pot_m_per_count)
            or not self.pot_m_per_count
        ):
            raise ConfigError(
                f"calibration pot_zero={self.pot_zero}, pot_m_per_count={self.pot_m_per_count}: "
                "must be finite, pot_m_per_count non-zero"
            )

    @property
    def encoders(self) -> int:
        """Encoder channels a SAMPLE must carry."""
        return len(self.encoder_joints)

    def check_hello(self, hello: Hello) -> None:
        """Refuse a board whose layout differs from this calibration.

        Raises:
            MessageError: joints, encoders or counts_per_rev differ (the message gives both).
        """
        for name, got, want in (
            ("joints", hello.joints, self.joints),
            ("encoders", hello.encoders, self.encoders),
            ("counts_per_rev", hello.counts_per_rev, self.counts_per_rev),
        ):
            if got != want:
                raise MessageError(
                    f"board {hello.model!r} (fw {hello.fw!r}) reports {name}={got}, configured {want}; "
                    "wrong board or calibration"
                )

    def convert(self, sample: Sample) -> MasterReading:
        """``sample`` in joint units.

        Raises:
            MessageError: ``sample.counts`` does not have one entry per encoder channel.
        """
        if len(sample.counts) != self.encoders:
            raise MessageError(
                f"SAMPLE counts has {len(sample.counts)} entries, configured encoders: {self.encoders}"
            )
        q = [0.0] * self.joints
        scale = 2.0 * math.pi / self.counts_per_rev
        for j, c, z, d in zip(
            self.encoder_joints, sample.counts, self.zero_counts, self.direction, strict=True
        ):
            q[j - 1] = d * (c - z) * scale
        if self.pot_joint:
            q[self.pot_joint - 1] = (sample.pot - self.pot_zero) * self.pot_m_per_count
        return MasterReading(
            tuple(q), sample.joint1_switch, sample.clutch, sample.operator_present, sample.t_us
        )

    def raw(self, joints: Sequence[float]) -> tuple[tuple[int, ...], int]:
        """Inverse of :meth:`convert`: the (counts, pot) a board reads at ``joints`` (rad / m).

        Counts are rounded to the nearest count, the pot reading also clipped to 0..1023. For
        emulators and tests.
        """
        if len(joints) != self.joints:
            raise ValueError(f"need {self.joints} joint values, got {len(joints)}")
        scale = self.counts_per_rev / (2.0 * math.pi)
        counts = tuple(
            z + d * round(joints[j - 1] * scale)
            for j, z, d in zip(self.encoder_joints, self.zero_counts, self.direction, strict=True)
        )
        pot = 0
        if self.pot_joint:
            pot = round(self.pot_zero + joints[self.pot_joint - 1] / self.pot_m_per_count)
            pot = min(max(pot, 0), POT_MAX)
        return counts, pot
