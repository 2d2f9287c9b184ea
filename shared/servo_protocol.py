"""Joint-servo protocol: what the host and a slave arm's servo controller say over
:mod:`~telesurg.shared.serial_link`.

A real slave arm (a hobby-servo arm, a custom PLAS-like robot, an industrial arm behind a
microcontroller bridge) is driven from joint position setpoints by a controller on a serial port.
The host (slave_control's ``serial`` backend) sends setpoints at its control rate; the controller
servoes the joints, streams its measured state and stops on its own when the setpoints stop (a
second, hardware-side watchdog). Pure module: no I/O, no threads; :mod:`telesurg.shared.serial_link` and
:mod:`telesurg.shared.robots` are imported lazily. Reference firmware: ``firmware/servo_controller``;
emulator: ``telesurg device emulate-slave``; bring-up of a real arm: ``docs/robots.md`` (Hardware).

Frame layout (from :mod:`telesurg.shared.serial_link`, frame version 1)
--------------------------------------------------------------
Every message is one frame, ``COBS(raw) 0x00`` on the wire, with the raw frame::

    offset  size  field
    0       1     version   u8, 1
    1       1     kind      u8, see the table below
    2       2     seq       u16 little-endian, +1 per frame the sender writes (any kind), mod 2**16
    4       n     body      one MessagePack map, string keys (exact key set per kind, below)
    4+n     2     CRC       u16 little-endian, CRC-16/CCITT-FALSE over bytes 0 .. 4+n-1

Kinds
-----
=====  ===============  ===================  ==============================================
kind   name             direction            when
=====  ===============  ===================  ==============================================
0x21   HELLO            controller → host    at boot and on HELLO_REQUEST (never otherwise)
0x22   STATE            controller → host    at the controller's rate (``rate_hz``), always
0x30   HELLO_REQUEST    host → controller    when the host opens the port (and until a HELLO)
0x31   ENABLE           host → controller    after an accepted HELLO and a first STATE
0x32   DISABLE          host → controller    on a controller fault and when the host stops
0x33   SETPOINT         host → controller    once per host control period while enabled
=====  ===============  ===================  ==============================================

The kinds differ from the encoder board's (0x01, 0x02, 0x10, :mod:`telesurg.shared.encoder_protocol`) so
an encoder board on the servo port is recognised and named in the error. Any other kind is
rejected (:class:`~telesurg.shared.errors.MessageError`). Bodies hold exactly the keys below: a missing or
an unknown key, a wrong type or a value out of range rejects the message. Integers are
MessagePack integers of any width; booleans are not integers. Reals are MessagePack float 32 or
float 64 (an integer is accepted where a real is expected); every real must be finite. Joint
vectors (``[real, ...]``) hold one value per joint, in the controller's joint order (HELLO),
radians for revolute and metres for prismatic joints; their lengths are 1..:data:`MAX_JOINTS`.

HELLO body (kind 0x21)::

    "proto"         int     servo protocol version, must be PROTO_VERSION = 1
    "model"         str     robot model, 1..32 chars: "mh3f", "plas", "vip" (shared/robots.py)
    "fw"            str     firmware version, 0..32 chars
    "joints"        int     n, joints the controller drives, 1..16
    "lower"         [real]  n joint lower limits, rad / m
    "upper"         [real]  n joint upper limits (each > its lower limit)
    "max_velocity"  [real]  n joint speed limits, rad/s / m/s, each > 0
    "rate_hz"       int     STATE rate, Hz, 1..10_000

STATE body (kind 0x22)::

    "t_us"              int     controller clock at the measurement, µs, 0..2**32-1 (wraps)
    "q"                 [real]  n measured joint positions, rad / m
    "qd"                [real]  n measured joint velocities, rad/s / m/s
    "current"           [real]  n motor currents, A (0.0 where the hardware cannot measure)
    "fault"             int     fault bits, 0..127 (FAULT_* below; bits 7-15 reserved, 0); latched
    "last_seq_applied"  int     "seq" of the last SETPOINT (or ENABLE) applied, 0..2**32-1; 0 at boot
    "watchdog_tripped"  bool    the controller's own watchdog stopped the joints (latched)
    "enabled"           bool    the controller follows SETPOINTs now

HELLO_REQUEST body (kind 0x30)::

    "proto"  int  protocol version the host speaks (1)

ENABLE body (kind 0x31)::

    "seq"  int  0..2**32-1: the host's setpoint counter; the controller sets last_seq_applied to it

DISABLE body (kind 0x32): the empty map ``{}``.

SETPOINT body (kind 0x33)::

    "seq"         int     0..2**32-1, +1 per SETPOINT (mod 2**32), continuing from ENABLE's seq
    "q"           [real]  n joint position targets, rad / m, inside the HELLO limits
    "timeout_ms"  int     1..10_000: stop the joints if no newer SETPOINT arrives within this

Fault bits (STATE ``fault``)::

    0x01 FAULT_ESTOP       the controller's emergency-stop input is open
    0x02 FAULT_OVERCURRENT a motor current above its limit
    0x04 FAULT_FOLLOWING   a joint cannot reach its target (following error)
    0x08 FAULT_LIMIT       a measured joint outside its limits
    0x10 FAULT_SUPPLY      supply voltage out of range
    0x20 FAULT_SETPOINT    a SETPOINT outside the limits or with the wrong joint count arrived
    0x40 FAULT_INTERNAL    anything else (firmware assertion, sensor lost)

What the controller does
------------------------
* It boots **disabled**, sends a HELLO, then a STATE every ``1 / rate_hz`` s, whatever happens.
* ENABLE ``{"seq": s}``: clears the latched faults whose cause is gone and the watchdog trip,
  sets every joint's target to its measured position (no motion), ``last_seq_applied = s``, and
  enables (``enabled`` true) unless a fault is still present.
* SETPOINT ``{"seq", "q", "timeout_ms"}`` while enabled: applied only if ``seq`` is newer than
  ``last_seq_applied`` (modulo 2**32: a duplicate or a late SETPOINT is ignored); one outside the
  limits or with the wrong joint count sets FAULT_SETPOINT and stops. The joints then move toward
  ``q`` no faster than ``max_velocity``. SETPOINTs while disabled are ignored.
* Its watchdog: once a SETPOINT has been applied, if no newer one arrives within its
  ``timeout_ms``, it holds every joint where it is, sets ``watchdog_tripped`` and disables.
* On any fault it holds the joints where they are and disables; faults stay latched until an
  ENABLE finds their cause gone.
* DISABLE: hold the joints where they are and disable (a controller with brakes may apply them).

What the host does (slave_control ``backend = "serial"``)
---------------------------------------------------------
1. Opens the port, sends HELLO_REQUEST (again every 0.5 s) and **sends nothing else** until a
   HELLO reports the expected model, joint count and joint limits (:meth:`ServoRobot.check_hello`);
   a different robot is refused with an error naming what differs.
2. Waits for a STATE (the arm's position), sends ENABLE, waits for a STATE that applied it
   (``last_seq_applied`` = the ENABLE's ``seq``) and reports ``enabled``.
3. Every control period: one SETPOINT, limit- and rate-checked (clamped and counted) first.
4. Holds, with the cause, on: no valid STATE for ``serial.stale_ms`` (the link is closed and
   re-opened, with a new handshake), a fault bit (DISABLE; latched until the controller restarts
   or the link is re-opened), a watchdog trip (ENABLE again after ``serial.reconnect_s``), a
   restart (a HELLO, then a STATE disabled with ``last_seq_applied`` 0: ENABLE again), any other
   disable (latched like a fault). After any hold the slave moves again only after a new engage.

Example SETPOINT, seq 7, frame seq 9, two joints, ``{"seq": 7, "q": [0.5, -0.25], "timeout_ms": 100}``::

    raw  01 33 09 00                                      version 1, kind SETPOINT, frame seq 9
         83                                               map of 3
         a3 73 65 71  07                                  "seq": 7
         a1 71  92 cb 3f e0 00 00 00 00 00 00             "q": [float64 0.5,
                   cb bf d0 00 00 00 00 00 00                   float64 -0.25]
         aa 74 69 6d 65 6f 75 74 5f 6d 73  64             "timeout_ms": 100
         a4 cb                                            CRC 0xCBA4, little-endian
    wire 04 01 33 09 0d 83 a3 73 65 71 07 a1 71 92 cb 3f e0 01 01 01 01 01 04 cb bf d0 01
         01 01 01 01 0f aa 74 69 6d 65 6f 75 74 5f 6d 73 64 a4 cb 00
         (COBS: code bytes 04 0d 01 … 0f replace the raw 0x00s; 47 bytes)

Link budget: with every real a float64, a STATE of 6 joints is at most 253 bytes on the wire, a
SETPOINT of 6 joints 89 bytes (a float32 firmware saves 4 bytes per real: 181 bytes per STATE).
At 500 000 bit/s (50 000 bytes/s, the reference firmware's rate) a 6-joint controller can send
~270 float32 STATEs/s; it sends 100, and the host's 100 SETPOINTs/s use 18 % of the other
direction. 115 200 bit/s is too slow for 100 Hz in both directions with 6 joints.

Example::

    >>> from telesurg.shared.servo_protocol import Setpoint, decode_message, encode_message
    >>> from telesurg.shared.serial_link import decode_frame
    >>> decode_message(decode_frame(encode_message(Setpoint(7, (0.5, -0.25), 100), 9)))
    Setpoint(seq=7, q=(0.5, -0.25), timeout_ms=100)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from telesurg.shared.errors import MessageError
from telesurg.shared.serial_link import HelloRequestBase, MessageSet, check_proto
from telesurg.shared.serial_link import check_bool as _bool
from telesurg.shared.serial_link import check_fields as _fields
from telesurg.shared.serial_link import check_int as _int
from telesurg.shared.serial_link import check_str as _str

if TYPE_CHECKING:
    from telesurg.shared.serial_link import Frame

#: Version of the body layouts above; HELLO and HELLO_REQUEST carry it as ``proto``.
PROTO_VERSION = 1
KIND_HELLO = 0x21
KIND_STATE = 0x22
KIND_HELLO_REQUEST = 0x30
KIND_ENABLE = 0x31
KIND_DISABLE = 0x32
KIND_SETPOINT = 0x33
KIND_NAMES = {
    KIND_HELLO: "HELLO",
    KIND_STATE: "STATE",
    KIND_HELLO_REQUEST: "HELLO_REQUEST",
    KIND_ENABLE: "ENABLE",
    KIND_DISABLE: "DISABLE",
    KIND_SETPOINT: "SETPOINT",
}
#: Kinds of the master's encoder board (shared/encoder_protocol.py): named when one shows up here.
ENCODER_KINDS = {0x01: "HELLO", 0x02: "SAMPLE", 0x10: "HELLO_REQUEST"}

FAULT_ESTOP = 0x01
FAULT_OVERCURRENT = 0x02
FAULT_FOLLOWING = 0x04
FAULT_LIMIT = 0x08
FAULT_SUPPLY = 0x10
FAULT_SETPOINT = 0x20
FAULT_INTERNAL = 0x40
#: Fault bit → short name (for the cause a host reports), in bit order.
FAULT_NAMES = {
    FAULT_ESTOP: "e-stop input open",
    FAULT_OVERCURRENT: "overcurrent",
    FAULT_FOLLOWING: "following error",
    FAULT_LIMIT: "joint outside its limits",
    FAULT_SUPPLY: "supply voltage out of range",
    FAULT_SETPOINT: "invalid setpoint received",
    FAULT_INTERNAL: "internal error",
}
FAULT_MASK = 0x7F

#: Most joints a controller may declare.
MAX_JOINTS = 16
#: Sequence counters (SETPOINT/ENABLE ``seq``, ``last_seq_applied``) and ``t_us`` wrap at this.
U32_MODULUS = 1 << 32
#: Longest controller-side timeout a SETPOINT may ask for, ms.
MAX_TIMEOUT_MS = 10_000


def describe_faults(bits: int) -> str:
    """``"overcurrent, following error (0x06)"`` for fault bits 0x06; ``"none"`` for 0."""
    if not bits:
        return "none"
    names = [name for bit, name in FAULT_NAMES.items() if bits & bit]
    return f"{', '.join(names)} (0x{bits:02X})"


def seq_delta32(a: int, b: int) -> int:
    """Signed distance from setpoint counter ``a`` to ``b`` modulo 2**32, in [-2**31, 2**31)."""
    return ((b - a + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)


# --------------------------------------------------------------------------- field checks


def _reals(name: str, value: Any, n: int | None = None) -> tuple[float, ...]:
    """A joint vector: a list/tuple of 1..MAX_JOINTS finite numbers (``n`` of them if given)."""
    if not isinstance(value, (list, tuple)):
        raise MessageError(f"{name} must be an array, got {type(value).__name__}")
    if n is not None and len(value) != n:
        raise MessageError(f"{name} has {len(value)} values, expected {n} (one per joint)")
    if not 1 <= len(value) <= MAX_JOINTS:
        raise MessageError(f"{name} has {len(value)} values, need 1..{MAX_JOINTS}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise MessageError(f"{name}[{i}] must be a number, got {type(v).__name__}")
        f = float(v)
        if not math.isfinite(f):
            raise MessageError(f"{name}[{i}]={f} is not finite")
        out.append(f)
    return tuple(out)


def _check_proto(kind: str, proto: int) -> None:
    check_proto("servo", PROTO_VERSION, kind, proto)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Hello:
    """HELLO (controller → host): which robot the controller drives, and its limits.

    Attributes:
        model: robot model, e.g. ``"mh3f"``.
        fw: firmware version string.
        joints: joints the controller drives (n).
        lower, upper: joint limits, rad / m, n each.
        max_velocity: joint speed limits, rad/s / m/s, n.
        rate_hz: STATE rate, Hz.
        proto: servo protocol version, must be :data:`PROTO_VERSION`.
    """

    KIND: ClassVar[int] = KIND_HELLO
    KEYS: ClassVar[frozenset[str]] = frozenset(
        {"proto", "model", "fw", "joints", "lower", "upper", "max_velocity", "rate_hz"}
    )

    model: str
    fw: str
    joints: int
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_velocity: tuple[float, ...]
    rate_hz: int
    proto: int = PROTO_VERSION

    def __post_init__(self) -> None:
        _check_proto("HELLO", self.proto)
        _str("HELLO model", self.model, 1)
        _str("HELLO fw", self.fw, 0)
        n = _int("HELLO joints", self.joints, 1, MAX_JOINTS)
        lower = _reals("HELLO lower", self.lower, n)
        upper = _reals("HELLO upper", self.upper, n)
        vmax = _reals("HELLO max_velocity", self.max_velocity, n)
        for i, (lo, hi, v) in enumerate(zip(lower, upper, vmax, strict=True)):
            if not lo < hi:
                raise MessageError(f"HELLO joint {i + 1}: lower {lo} must be below upper {hi}")
            if not v > 0:
                raise MessageError(f"HELLO joint {i + 1}: max_velocity {v} must be > 0")
        _int("HELLO rate_hz", self.rate_hz, 1, 10_000)
        object.__setattr__(self, "lower", lower)  # a list from the wire becomes a tuple of floats
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "max_velocity", vmax)

    def body(self) -> dict[str, Any]:
        return {
            "proto": self.proto,
            "model": self.model,
            "fw": self.fw,
            "joints": self.joints,
            "lower": list(self.lower),
            "upper": list(self.upper),
            "max_velocity": list(self.max_velocity),
            "rate_hz": self.rate_hz,
        }

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Hello:
        _fields("HELLO", body, cls.KEYS)
        return cls(**body)  # __post_init__ checks types and ranges


@dataclass(frozen=True, slots=True)
class State:
    """STATE (controller → host): one measurement of every joint, and the controller's status.

    Attributes:
        t_us: controller clock, µs modulo 2**32.
        q: measured joint positions, rad / m.
        qd: measured joint velocities, rad/s / m/s.
        current: motor currents, A.
        fault: latched fault bits (``FAULT_*``).
        last_seq_applied: ``seq`` of the last SETPOINT or ENABLE applied.
        watchdog_tripped: the controller's watchdog stopped the joints (latched until ENABLE).
        enabled: the controller follows SETPOINTs.
    """

    KIND: ClassVar[int] = KIND_STATE
    KEYS: ClassVar[frozenset[str]] = frozenset(
        {"t_us", "q", "qd", "current", "fault", "last_seq_applied", "watchdog_tripped", "enabled"}
    )

    t_us: int
    q: tuple[float, ...]
    qd: tuple[float, ...]
    current: tuple[float, ...]
    fault: int = 0
    last_seq_applied: int = 0
    watchdog_tripped: bool = False
    enabled: bool = False

    def __post_init__(self) -> None:
        _int("STATE t_us", self.t_us, 0, U32_MODULUS - 1)
        q = _reals("STATE q", self.q)
        qd = _reals("STATE qd", self.qd, len(q))
        current = _reals("STATE current", self.current, len(q))
        fault = _int("STATE fault", self.fault, 0, 0xFFFF)
        if fault & ~FAULT_MASK:
            raise MessageError(
                f"STATE fault=0x{fault:04X} sets reserved bits (valid: 0x{FAULT_MASK:02X}, "
                f"{', '.join(f'0x{b:02X} {n}' for b, n in FAULT_NAMES.items())})"
            )
        _int("STATE last_seq_applied", self.last_seq_applied, 0, U32_MODULUS - 1)
        _bool("STATE watchdog_tripped", self.watchdog_tripped)
        _bool("STATE enabled", self.enabled)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "qd", qd)
        object.__setattr__(self, "current", current)

    def body(self) -> dict[str, Any]:
        return {
            "t_us": self.t_us,
            "q": list(self.q),
            "qd": list(self.qd),
            "current": list(self.current),
            "fault": self.fault,
            "last_seq_applied": self.last_seq_applied,
            "watchdog_tripped": self.watchdog_tripped,
            "enabled": self.enabled,
        }

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> State:
        _fields("STATE", body, cls.KEYS)
        return cls(**body)


@dataclass(frozen=True, slots=True)
class HelloRequest(HelloRequestBase):
    """HELLO_REQUEST (host → controller): please send a HELLO now."""

    KIND: ClassVar[int] = KIND_HELLO_REQUEST
    PROTOCOL: ClassVar[str] = "servo"
    VERSION: ClassVar[int] = PROTO_VERSION

    proto: int = PROTO_VERSION


@dataclass(frozen=True, slots=True)
class Enable:
    """ENABLE (host → controller): clear the latched faults and the watchdog trip, hold, follow.

    Attributes:
        seq: the host's setpoint counter; the next SETPOINT carries ``seq + 1``.
    """

    KIND: ClassVar[int] = KIND_ENABLE
    KEYS: ClassVar[frozenset[str]] = frozenset({"seq"})

    seq: int

    def __post_init__(self) -> None:
        _int("ENABLE seq", self.seq, 0, U32_MODULUS - 1)

    def body(self) -> dict[str, Any]:
        return {"seq": self.seq}

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Enable:
        _fields("ENABLE", body, cls.KEYS)
        return cls(**body)


@dataclass(frozen=True, slots=True)
class Disable:
    """DISABLE (host → controller): hold the joints where they are and stop following."""

    KIND: ClassVar[int] = KIND_DISABLE
    KEYS: ClassVar[frozenset[str]] = frozenset()

    def body(self) -> dict[str, Any]:
        return {}

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Disable:
        _fields("DISABLE", body, cls.KEYS)
        return cls()


@dataclass(frozen=True, slots=True)
class Setpoint:
    """SETPOINT (host → controller): joint position targets.

    Attributes:
        seq: setpoint counter, +1 per SETPOINT modulo 2**32.
        q: joint position targets, rad / m.
        timeout_ms: the controller stops the joints if no newer SETPOINT arrives within this.
    """

    KIND: ClassVar[int] = KIND_SETPOINT
    KEYS: ClassVar[frozenset[str]] = frozenset({"seq", "q", "timeout_ms"})

    seq: int
    q: tuple[float, ...]
    timeout_ms: int

    def __post_init__(self) -> None:
        _int("SETPOINT seq", self.seq, 0, U32_MODULUS - 1)
        object.__setattr__(self, "q", _reals("SETPOINT q", self.q))
        _int("SETPOINT timeout_ms", self.timeout_ms, 1, MAX_TIMEOUT_MS)

    def body(self) -> dict[str, Any]:
        return {"seq": self.seq, "q": list(self.q), "timeout_ms": self.timeout_ms}

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> Setpoint:
        _fields("SETPOINT", body, cls.KEYS)
        return cls(**body)


ServoMessage = Hello | State | HelloRequest | Enable | Disable | Setpoint
#: The servo protocol's messages by kind; the encoder board's kinds are named when one arrives.
MESSAGES: MessageSet[ServoMessage] = MessageSet(
    "servo",
    (Hello, State, HelloRequest, Enable, Disable, Setpoint),
    KIND_NAMES,
    foreign={k: f"the encoder board's {n}: a master's board on this port" for k, n in ENCODER_KINDS.items()},
)


def decode_message(frame: Frame) -> ServoMessage:
    """The servo-protocol message in a decoded frame (see :meth:`MessageSet.decode`).

    Raises:
        MessageError: unknown kind (an encoder board's kinds are named as such), or a body with
            missing/unknown keys, wrong types or values out of range; the message names the kind
            and the field.
    """
    return MESSAGES.decode(frame)


#: Wire bytes of a message as frame number ``seq``: ``encode_message(msg, seq)``.
encode_message = MESSAGES.encode
#: Send a message on a :class:`SerialLink`, return its seq: ``send_message(link, msg)``.
send_message = MESSAGES.send


# --------------------------------------------------------------------------- the expected robot


@dataclass(frozen=True)
class ServoRobot:
    """The robot a host expects behind its servo port: every joint of a model's arms, in order.

    Attributes:
        model: robot model (a name of :func:`telesurg.shared.robots.names`).
        joint_names: the model's joint names (MuJoCo names: ``j1`` … for mh3f, ``arm1_d1`` … for
            the two-arm models), the controller's joint order.
        lower, upper: joint limits, rad / m.
        max_velocity: joint speed limits, rad/s / m/s.
        home: start pose of every arm (the emulator starts there), rad / m.
    """

    model: str
    joint_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_velocity: tuple[float, ...]
    home: tuple[float, ...]

    @classmethod
    def of(cls, model: str, arm: str = "arm1") -> ServoRobot:
        """Every arm of ``model`` (``telesurg.shared.robots.arms_of``), concatenated.

        Raises:
            ConfigError: unknown model (the message names the valid ones).
        """
        from telesurg.shared.robots import arms_of

        arms = arms_of(model, arm)
        return cls(
            model,
            tuple(j for a in arms for j in a.model_joints),
            tuple(v for a in arms for v in a.lower),
            tuple(v for a in arms for v in a.upper),
            tuple(v for a in arms for v in a.max_velocity),
            tuple(v for a in arms for v in a.home),
        )

    @property
    def joints(self) -> int:
        return len(self.joint_names)

    def hello(self, rate_hz: int, fw: str = "") -> Hello:
        """The HELLO a controller of this robot sends."""
        return Hello(self.model, fw, self.joints, self.lower, self.upper, self.max_velocity, rate_hz)

    def check_hello(self, hello: Hello, tol: float = 1e-4) -> None:
        """Refuse a controller that does not drive this robot.

        Model and joint count must be equal, every joint limit equal within ``tol`` (rad / m: a
        float32 firmware rounds ±2π to within 3e-7). ``max_velocity`` is not compared: a host
        rate-limits to the smaller of its own and the controller's speed limits.

        Raises:
            MessageError: what differs, with both values (the first difference found).
        """
        who = f"controller (model {hello.model!r}, fw {hello.fw!r})"
        if hello.model != self.model:
            raise MessageError(f"{who} drives model {hello.model!r}, expected {self.model!r}: wrong robot")
        if hello.joints != self.joints:
            raise MessageError(f"{who} has {hello.joints} joints, model {self.model} has {self.joints}")
        for name, got, want in (("lower", hello.lower, self.lower), ("upper", hello.upper, self.upper)):
            for j, g, w in zip(self.joint_names, got, want, strict=True):
                if abs(g - w) > tol:
                    raise MessageError(
                        f"{who}: joint {j} {name} limit {g:.6g}, expected {w:.6g} "
                        f"(differs by {abs(g - w):.3g} > {tol:g}): wrong robot or firmware limits"
                    )
