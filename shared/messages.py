"""Typed telesurg messages, MessagePack on the wire, one strict decoder.

Every payload is a MessagePack map with a common header::

    {"v": 2, "type": "joint_state", "src": "slave_control", "seq": 42, "ts": 1700000000000000000,
     ...body fields...}

* ``v``    schema version (int, must equal :data:`SCHEMA_VERSION`)
* ``type`` message type tag (one of :data:`MESSAGE_TYPES`)
* ``src``  source id: the publishing service instance (str)
* ``seq``  per-stream sequence number, starts at 0, +1 per message (int >= 0)
* ``ts``   source timestamp, wall clock, ns since the Unix epoch (int >= 0)

:func:`decode` is the only entry point for incoming bytes. It validates strictly — exact field set,
types, array shapes, finite numbers, string and array sizes, total payload size — and raises
:class:`~telesurg.shared.errors.MessageError` with a message naming the field. Nothing half-decoded escapes.

Example::

    >>> from telesurg.shared.messages import Header, JointSetpoint, decode
    >>> m = JointSetpoint(Header("mapping", 0, 1), ("j1",), (0.1,), follow=True)
    >>> decode(m.encode()) == m
    True
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
from telesurg.shared.errors import MessageError

SCHEMA_VERSION = 2  # 2: safety fields (origin_ns, latency, scale, rcm, clipped), estop
#: Largest payload accepted by :func:`decode`, bytes.
MAX_PAYLOAD_BYTES = 64 * 1024
#: Largest joint count in any joint-space message.
MAX_JOINTS = 32
#: Longest string field (names, reasons), characters.
MAX_STR = 512
#: Most entries in a list-of-strings field (e.g. safety causes).
MAX_LIST = 64

_HEADER_KEYS = frozenset({"v", "type", "src", "seq", "ts"})
_U64_MAX = 2**64 - 1
#: Largest ``seq`` / ``ts``: int64, so every consumer (numpy, rerun, MCAP) can hold them.
_I64_MAX = 2**63 - 1


def now_ns() -> int:
    """Source timestamp for headers: wall clock, ns since the Unix epoch."""
    return time.time_ns()


@dataclass(frozen=True, slots=True)
class Header:
    """Common header of every message.

    Attributes:
        source: publishing service instance id, e.g. ``"mapping"``.
        seq: per-stream sequence number (0, 1, 2, ...).
        stamp_ns: source timestamp, wall clock ns since the Unix epoch.
    """

    source: str
    seq: int
    stamp_ns: int


# --------------------------------------------------------------------------- field validators


def _get(d: dict[str, Any], key: str) -> Any:
    try:
        return d[key]
    except KeyError:
        raise MessageError(f"missing field {key!r}") from None


def _str(d: dict[str, Any], key: str, *, allow_empty: bool = True) -> str:
    v = _get(d, key)
    if not isinstance(v, str):
        raise MessageError(f"field {key!r} must be a string, got {type(v).__name__}")
    if len(v) > MAX_STR:
        raise MessageError(f"field {key!r} is {len(v)} chars, limit {MAX_STR}")
    if not allow_empty and not v:
        raise MessageError(f"field {key!r} must not be empty")
    return v


def _int(d: dict[str, Any], key: str, lo: int = 0, hi: int = _U64_MAX) -> int:
    v = _get(d, key)
    if isinstance(v, bool) or not isinstance(v, int):
        raise MessageError(f"field {key!r} must be an integer, got {type(v).__name__}")
    if not lo <= v <= hi:
        raise MessageError(f"field {key!r}={v} outside [{lo}, {hi}]")
    return v


def _bool(d: dict[str, Any], key: str) -> bool:
    v = _get(d, key)
    if not isinstance(v, bool):
        raise MessageError(f"field {key!r} must be a boolean, got {type(v).__name__}")
    return v


def _float(d: dict[str, Any], key: str) -> float:
    v = _get(d, key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise MessageError(f"field {key!r} must be a number, got {type(v).__name__}")
    f = float(v)
    if not math.isfinite(f):
        raise MessageError(f"field {key!r} is not finite ({f})")
    return f


def _nonneg(d: dict[str, Any], key: str) -> float:
    f = _float(d, key)
    if f < 0.0:
        raise MessageError(f"field {key!r}={f} must be >= 0")
    return f


def _floats(
    d: dict[str, Any], key: str, length: int | None = None, *, max_len: int = MAX_JOINTS
) -> tuple[float, ...]:
    v = _get(d, key)
    if not isinstance(v, (list, tuple)):
        raise MessageError(f"field {key!r} must be an array, got {type(v).__name__}")
    if length is not None and len(v) != length:
        raise MessageError(f"field {key!r} must have {length} elements, got {len(v)}")
    if len(v) > max_len:
        raise MessageError(f"field {key!r} has {len(v)} elements, limit {max_len}")
    # fast path (every control message): all floats, and a finite sum means no nan/inf among
    # them; anything else (ints, a bad element, a sum that overflows) takes the checked loop
    if all(type(x) is float for x in v) and math.isfinite(sum(v)):
        return tuple(v)
    out = []
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise MessageError(f"field {key!r}[{i}] must be a number, got {type(x).__name__}")
        f = float(x)
        if not math.isfinite(f):
            raise MessageError(f"field {key!r}[{i}] is not finite ({f})")
        out.append(f)
    return tuple(out)


def _strs(d: dict[str, Any], key: str, *, max_len: int = MAX_LIST) -> tuple[str, ...]:
    v = _get(d, key)
    if not isinstance(v, (list, tuple)):
        raise MessageError(f"field {key!r} must be an array, got {type(v).__name__}")
    if len(v) > max_len:
        raise MessageError(f"field {key!r} has {len(v)} elements, limit {max_len}")
    out = []
    for i, x in enumerate(v):
        if not isinstance(x, str) or len(x) > MAX_STR:
            raise MessageError(f"field {key!r}[{i}] must be a string of <= {MAX_STR} chars")
        out.append(x)
    return tuple(out)


_NAMES_SEEN: dict[tuple[Any, ...], tuple[str, ...]] = {}  # joint-name lists already validated
_NAMES_SEEN_MAX = 64


def _joint_names(d: dict[str, Any]) -> tuple[str, ...]:
    v = d.get("name")
    if type(v) is list:
        try:
            known = _NAMES_SEEN.get(tuple(v))  # a stream repeats its names in every message
        except TypeError:  # an unhashable element: the checks below reject it
            known = None
        if known is not None:
            return known
    names = _validated_joint_names(d)
    if len(_NAMES_SEEN) >= _NAMES_SEEN_MAX:
        _NAMES_SEEN.clear()
    _NAMES_SEEN[names] = names
    return names


def _validated_joint_names(d: dict[str, Any]) -> tuple[str, ...]:
    names = _strs(d, "name", max_len=MAX_JOINTS)
    if not names:
        raise MessageError("field 'name' must list at least one joint")
    if len(set(names)) != len(names) or not all(names):
        raise MessageError("field 'name' must hold distinct, non-empty joint names")
    return names


def _map_len(payload: bytes | bytearray | memoryview) -> int:
    """Entries declared by the MessagePack map header at the start of ``payload`` (-1: not a map).

    A map that decodes to fewer keys than it declares had duplicate keys (the decoder keeps the
    last one). Messages have no nested maps (no field takes one), so the top level is all there
    is to check."""
    b = bytes(payload[:5])
    if not b:
        return -1
    if 0x80 <= b[0] <= 0x8F:
        return b[0] & 0x0F
    if b[0] == 0xDE and len(b) >= 3:
        return int.from_bytes(b[1:3], "big")
    if b[0] == 0xDF and len(b) >= 5:
        return int.from_bytes(b[1:5], "big")
    return -1


def _choice(d: dict[str, Any], key: str, options: frozenset[str]) -> str:
    v = _str(d, key)
    if v not in options:
        raise MessageError(f"field {key!r}={v!r} is not one of {sorted(options)}")
    return v


def _unit_quat(d: dict[str, Any], key: str) -> tuple[float, float, float, float]:
    q = _floats(d, key, 4)
    n = math.sqrt(sum(x * x for x in q))
    if abs(n - 1.0) > 1e-3:
        raise MessageError(f"field {key!r} must be a unit quaternion [x, y, z, w], norm={n:.6g}")
    return (q[0], q[1], q[2], q[3])


def _vec3(d: dict[str, Any], key: str) -> tuple[float, float, float]:
    p = _floats(d, key, 3)
    return (p[0], p[1], p[2])


def _same_len(key: str, names: Sequence[str], values: Sequence[float]) -> None:
    if len(values) != len(names):
        raise MessageError(f"field {key!r} has {len(values)} elements for {len(names)} names")


# --------------------------------------------------------------------------- messages

M = TypeVar("M", bound="Message")
_REGISTRY: dict[str, type[Message]] = {}


def _register(cls: type[M]) -> type[M]:
    _REGISTRY[cls.TYPE] = cls
    return cls


@dataclass(frozen=True, slots=True)
class Message:
    """Base of every message: a header plus typed body fields (subclasses)."""

    TYPE: ClassVar[str] = ""
    BODY: ClassVar[frozenset[str]] = frozenset()

    header: Header

    def body(self) -> dict[str, Any]:
        """Body fields as plain msgpack-able values."""
        raise NotImplementedError

    @classmethod
    def from_body(cls: type[M], header: Header, d: dict[str, Any]) -> M:
        """Build from a validated header and a raw body map; raise MessageError if invalid."""
        raise NotImplementedError

    def encode(self) -> bytes:
        """MessagePack bytes of this message."""
        h = self.header
        d: dict[str, Any] = {
            "v": SCHEMA_VERSION,
            "type": self.TYPE,
            "src": h.source,
            "seq": h.seq,
            "ts": h.stamp_ns,
        }
        d.update(self.body())
        out: bytes = msgpack.packb(d, use_bin_type=True)
        return out


@_register
@dataclass(frozen=True, slots=True)
class JointState(Message):
    """Measured joint state (CRTK ``measured_js``).

    Attributes:
        names: joint names, e.g. ``("j1", ..., "j6")``.
        position: rad for revolute joints, m for prismatic.
        velocity: rad/s or m/s (same length as names, may be empty).
        effort: N·m or N (same length as names, may be empty).
    """

    TYPE: ClassVar[str] = "joint_state"
    BODY: ClassVar[frozenset[str]] = frozenset({"name", "position", "velocity", "effort"})

    names: tuple[str, ...] = ()
    position: tuple[float, ...] = ()
    velocity: tuple[float, ...] = ()
    effort: tuple[float, ...] = ()

    def body(self) -> dict[str, Any]:
        return {
            "name": list(self.names),
            "position": list(self.position),
            "velocity": list(self.velocity),
            "effort": list(self.effort),
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> JointState:
        names = _joint_names(d)
        pos = _floats(d, "position")
        _same_len("position", names, pos)
        vel = _floats(d, "velocity")
        eff = _floats(d, "effort")
        if vel:
            _same_len("velocity", names, vel)
        if eff:
            _same_len("effort", names, eff)
        return cls(header, names, pos, vel, eff)


@_register
@dataclass(frozen=True, slots=True)
class CartesianPose(Message):
    """A Cartesian pose (CRTK ``measured_cp`` / ``setpoint_cp``).

    Attributes:
        frame: name of the reference frame, e.g. ``"base"`` (slave base) or ``"master"``.
        position: (x, y, z) in m.
        orientation: unit quaternion (x, y, z, w).
    """

    TYPE: ClassVar[str] = "pose"
    BODY: ClassVar[frozenset[str]] = frozenset({"frame", "position", "orientation"})

    frame: str = "base"
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def body(self) -> dict[str, Any]:
        return {
            "frame": self.frame,
            "position": list(self.position),
            "orientation": list(self.orientation),
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> CartesianPose:
        return cls(header, _str(d, "frame"), _vec3(d, "position"), _unit_quat(d, "orientation"))


@_register
@dataclass(frozen=True, slots=True)
class CartesianWrench(Message):
    """A wrench at the tool tip (CRTK ``measured_cf``): what the environment exerts on the tool.

    Attributes:
        frame: reference frame of both vectors, e.g. ``"base"``.
        force: (fx, fy, fz) in N.
        torque: (tx, ty, tz) in N·m, about the tip.
    """

    TYPE: ClassVar[str] = "wrench"
    BODY: ClassVar[frozenset[str]] = frozenset({"frame", "force", "torque"})

    frame: str = "base"
    force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    torque: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def body(self) -> dict[str, Any]:
        return {"frame": self.frame, "force": list(self.force), "torque": list(self.torque)}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> CartesianWrench:
        return cls(header, _str(d, "frame"), _vec3(d, "force"), _vec3(d, "torque"))


@_register
@dataclass(frozen=True, slots=True)
class MasterButtons(Message):
    """Master device buttons (``master/<arm>/buttons``), published with every pose sample.

    Attributes:
        clutch: clutch pedal pressed — the slave follows only while pressed.
        operator_present: operator head/hand sensor; False disengages.
    """

    TYPE: ClassVar[str] = "buttons"
    BODY: ClassVar[frozenset[str]] = frozenset({"clutch", "operator_present"})

    clutch: bool = False
    operator_present: bool = False

    def body(self) -> dict[str, Any]:
        return {"clutch": self.clutch, "operator_present": self.operator_present}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> MasterButtons:
        return cls(header, _bool(d, "clutch"), _bool(d, "operator_present"))


@_register
@dataclass(frozen=True, slots=True)
class JointSetpoint(Message):
    """Joint position setpoint (CRTK ``servo_jp``).

    Attributes:
        names: joint names (must match the slave's).
        position: rad / m.
        follow: True while the mapping follows the master; False means "hold" (the position is
            then the last setpoint, informational). A slave resumes only on a False → True edge.
        origin_ns: source timestamp (``ts``) of the master sample this setpoint was computed
            from, 0 if none. Receivers on the same host measure end-to-end latency with it.
    """

    TYPE: ClassVar[str] = "servo_jp"
    BODY: ClassVar[frozenset[str]] = frozenset({"name", "position", "follow", "origin_ns"})

    names: tuple[str, ...] = ()
    position: tuple[float, ...] = ()
    follow: bool = False
    origin_ns: int = 0

    def body(self) -> dict[str, Any]:
        return {
            "name": list(self.names),
            "position": list(self.position),
            "follow": self.follow,
            "origin_ns": self.origin_ns,
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> JointSetpoint:
        names = _joint_names(d)
        pos = _floats(d, "position")
        _same_len("position", names, pos)
        return cls(header, names, pos, _bool(d, "follow"), _int(d, "origin_ns"))


OPERATING_STATES = frozenset({"DISABLED", "ENABLED", "PAUSED", "FAULT"})
CONTROL_MODES = frozenset({"non_trocar", "transitional", "trocar", "joint"})


@_register
@dataclass(frozen=True, slots=True)
class OperatingState(Message):
    """Slave arm operating state (CRTK ``operating_state``), ~20 Hz and on change.

    Attributes:
        state: ``ENABLED`` (moving under a lease), ``PAUSED`` (holding), ``DISABLED``, ``FAULT``.
        control_mode: ``non_trocar`` / ``transitional`` / ``trocar`` (the forceps arm), or
            ``joint`` (a joint-space slave without trocar modes: PLAS, VIP arms).
        follow: True while the slave tracks servo_jp.
        lease_ok: True while a fresh watchdog lease allows motion.
        reason: why the slave holds ("" while following).
        holds: number of times the slave entered hold since start.
        rcm_error_mm: distance from the trocar point to the forceps axis line, mm, from the
            measured (simulated or real) arm's tip pose; meaningful once the forceps is through
            the trocar (the watchdog checks it only in trocar mode).
        clipped: control cycles in which the slave's joint speed limit clipped the setpoint.
        rejected: setpoints the slave refused (limits, jumps, wrong joints, foreign source).
        trocar: the trocar point the slave uses (taught or configured), m, base frame; the
            mapping uses it for master–slave motion in trocar mode.
    """

    TYPE: ClassVar[str] = "operating_state"
    BODY: ClassVar[frozenset[str]] = frozenset(
        {
            "state",
            "control_mode",
            "follow",
            "lease_ok",
            "reason",
            "holds",
            "rcm_error_mm",
            "clipped",
            "rejected",
            "trocar",
        }
    )

    state: str = "DISABLED"
    control_mode: str = "non_trocar"
    follow: bool = False
    lease_ok: bool = False
    reason: str = ""
    holds: int = 0
    rcm_error_mm: float = 0.0
    clipped: int = 0
    rejected: int = 0
    trocar: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def body(self) -> dict[str, Any]:
        return {
            "state": self.state,
            "control_mode": self.control_mode,
            "follow": self.follow,
            "lease_ok": self.lease_ok,
            "reason": self.reason,
            "holds": self.holds,
            "rcm_error_mm": self.rcm_error_mm,
            "clipped": self.clipped,
            "rejected": self.rejected,
            "trocar": list(self.trocar),
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> OperatingState:
        return cls(
            header,
            _choice(d, "state", OPERATING_STATES),
            _choice(d, "control_mode", CONTROL_MODES),
            _bool(d, "follow"),
            _bool(d, "lease_ok"),
            _str(d, "reason"),
            _int(d, "holds"),
            _nonneg(d, "rcm_error_mm"),
            _int(d, "clipped"),
            _int(d, "rejected"),
            _vec3(d, "trocar"),
        )


SAFETY_STATES = frozenset({"OK", "DEGRADED", "HOLD", "ESTOP"})


@_register
@dataclass(frozen=True, slots=True)
class SafetyLease(Message):
    """Permission to move, from the watchdog to one slave arm (``safety/<arm>/lease``).

    The slave may move only while ``allow`` is True and less than ``valid_for_ms`` has passed
    since it received this lease (relative, so clocks need not agree across hosts).

    Attributes:
        arm: slave arm id this lease is for.
        allow: True grants motion; False orders an immediate hold.
        valid_for_ms: lifetime from reception, ms (> 0).
        reason: why motion is not allowed ("" when allowed).
    """

    TYPE: ClassVar[str] = "lease"
    BODY: ClassVar[frozenset[str]] = frozenset({"arm", "allow", "valid_for_ms", "reason"})

    arm: str = ""
    allow: bool = False
    valid_for_ms: float = 0.0
    reason: str = ""

    def body(self) -> dict[str, Any]:
        return {
            "arm": self.arm,
            "allow": self.allow,
            "valid_for_ms": self.valid_for_ms,
            "reason": self.reason,
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> SafetyLease:
        valid = _float(d, "valid_for_ms")
        if not 0.0 < valid <= 10_000.0:
            raise MessageError(f"field 'valid_for_ms'={valid} outside (0, 10000]")
        return cls(header, _str(d, "arm", allow_empty=False), _bool(d, "allow"), valid, _str(d, "reason"))


@_register
@dataclass(frozen=True, slots=True)
class SafetyState(Message):
    """Watchdog's view of one arm (``safety/<arm>/state``), on change and at a low rate.

    Attributes:
        arm: slave arm id.
        state: ``OK`` / ``DEGRADED`` / ``HOLD`` / ``ESTOP``.
        causes: human-readable causes of a non-OK state.
        scale: motion-scale factor the mapping must apply, in [0, 1] (1 when OK; reduced while
            DEGRADED by the latency budget).
        latency_p50_ms / latency_p90_ms / latency_p99_ms: master → watchdog latency of the arm's
            command path over the last window, ms (0 while unknown).
        latency_samples: samples in that window.
    """

    TYPE: ClassVar[str] = "safety_state"
    BODY: ClassVar[frozenset[str]] = frozenset(
        {
            "arm",
            "state",
            "causes",
            "scale",
            "latency_p50_ms",
            "latency_p90_ms",
            "latency_p99_ms",
            "latency_samples",
        }
    )

    arm: str = ""
    state: str = "HOLD"
    causes: tuple[str, ...] = ()
    scale: float = 1.0
    latency_p50_ms: float = 0.0
    latency_p90_ms: float = 0.0
    latency_p99_ms: float = 0.0
    latency_samples: int = 0

    def body(self) -> dict[str, Any]:
        return {
            "arm": self.arm,
            "state": self.state,
            "causes": list(self.causes),
            "scale": self.scale,
            "latency_p50_ms": self.latency_p50_ms,
            "latency_p90_ms": self.latency_p90_ms,
            "latency_p99_ms": self.latency_p99_ms,
            "latency_samples": self.latency_samples,
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> SafetyState:
        scale = _float(d, "scale")
        if not 0.0 <= scale <= 1.0:
            raise MessageError(f"field 'scale'={scale} outside [0, 1]")
        return cls(
            header,
            _str(d, "arm", allow_empty=False),
            _choice(d, "state", SAFETY_STATES),
            _strs(d, "causes"),
            scale,
            _nonneg(d, "latency_p50_ms"),
            _nonneg(d, "latency_p90_ms"),
            _nonneg(d, "latency_p99_ms"),
            _int(d, "latency_samples"),
        )


ESTOP_ACTIONS = frozenset({"estop", "reset"})


@_register
@dataclass(frozen=True, slots=True)
class EStop(Message):
    """Emergency stop or its reset (``estop``), from the console or any service.

    The watchdog and slave_control both latch an e-stop: the arm holds until an explicit
    ``reset`` and then a new engage.

    Attributes:
        arm: arm id, or ``"*"`` for every arm of the site.
        action: ``estop`` or ``reset``.
        reason: who/why, shown in events (e.g. ``"console: operator"``).
    """

    TYPE: ClassVar[str] = "estop"
    BODY: ClassVar[frozenset[str]] = frozenset({"arm", "action", "reason"})

    arm: str = "*"
    action: str = "estop"
    reason: str = ""

    def body(self) -> dict[str, Any]:
        return {"arm": self.arm, "action": self.action, "reason": self.reason}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> EStop:
        return cls(
            header, _str(d, "arm", allow_empty=False), _choice(d, "action", ESTOP_ACTIONS), _str(d, "reason")
        )

    def applies_to(self, arm: str) -> bool:
        """True if this command is for ``arm``."""
        return self.arm in ("*", arm)


@_register
@dataclass(frozen=True, slots=True)
class SafetyEvent(Message):
    """A discrete event worth a line in the log (``safety/events``, ``<role>/<arm>/events``).

    Attributes:
        arm: arm id the event concerns ("" for system-wide).
        kind: short machine-readable tag, e.g. ``"transition"``, ``"ik_failure"``, ``"engage"``.
        severity: ``info`` / ``warning`` / ``error``.
        text: human-readable description including the cause.
    """

    TYPE: ClassVar[str] = "event"
    BODY: ClassVar[frozenset[str]] = frozenset({"arm", "kind", "severity", "text"})
    SEVERITIES: ClassVar[frozenset[str]] = frozenset({"info", "warning", "error"})

    arm: str = ""
    kind: str = ""
    severity: str = "info"
    text: str = ""

    def body(self) -> dict[str, Any]:
        return {"arm": self.arm, "kind": self.kind, "severity": self.severity, "text": self.text}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> SafetyEvent:
        return cls(
            header,
            _str(d, "arm"),
            _str(d, "kind", allow_empty=False),
            _choice(d, "severity", cls.SEVERITIES),
            _str(d, "text"),
        )


@_register
@dataclass(frozen=True, slots=True)
class Heartbeat(Message):
    """Periodic service heartbeat (``heartbeat/<service>``), 2 Hz.

    Attributes:
        service: service instance id.
        uptime_s: seconds since the service started.
        rejected: messages this service's strict decoder rejected so far (all keys).
    """

    TYPE: ClassVar[str] = "heartbeat"
    BODY: ClassVar[frozenset[str]] = frozenset({"service", "uptime_s", "rejected"})

    service: str = ""
    uptime_s: float = 0.0
    rejected: int = 0

    def body(self) -> dict[str, Any]:
        return {"service": self.service, "uptime_s": self.uptime_s, "rejected": self.rejected}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> Heartbeat:
        return cls(
            header,
            _str(d, "service", allow_empty=False),
            _nonneg(d, "uptime_s"),
            _int(d, "rejected"),
        )


_COMMAND_NAME = re.compile(r"^[a-z][a-z0-9_]{0,63}$")


@_register
@dataclass(frozen=True, slots=True)
class Command(Message):
    """An operator command to one arm, sent as a zenoh query to ``slave/<arm>/command``.

    Attributes:
        arm: arm id the command is for.
        name: command name, ``[a-z][a-z0-9_]*`` (e.g. ``teach_trocar``, ``insert``, ``jog``).
        args: ``key=value`` strings (e.g. ``("frame=forceps", "axis=x", "direction=1")``);
            the handler parses and validates them.
    """

    TYPE: ClassVar[str] = "command"
    BODY: ClassVar[frozenset[str]] = frozenset({"arm", "name", "args"})

    arm: str = ""
    name: str = ""
    args: tuple[str, ...] = ()

    def body(self) -> dict[str, Any]:
        return {"arm": self.arm, "name": self.name, "args": list(self.args)}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> Command:
        name = _str(d, "name", allow_empty=False)
        if not _COMMAND_NAME.match(name):
            raise MessageError(f"field 'name'={name!r} must match [a-z][a-z0-9_]{{0,63}}")
        args = _strs(d, "args", max_len=16)
        for a in args:
            if "=" not in a:
                raise MessageError(f"field 'args' entry {a!r} must look like key=value")
        return cls(header, _str(d, "arm", allow_empty=False), name, args)

    def arg_map(self) -> dict[str, str]:
        """``args`` as a dict (a repeated key keeps the last value)."""
        return dict(a.split("=", 1) for a in self.args)


@_register
@dataclass(frozen=True, slots=True)
class CommandReply(Message):
    """The answer to a :class:`Command`: accepted, or refused with the reason.

    Attributes:
        arm: arm id.
        name: the command answered.
        accepted: True if the command was carried out (or started).
        reason: why it was refused ("" when accepted), or a short note.
    """

    TYPE: ClassVar[str] = "command_reply"
    BODY: ClassVar[frozenset[str]] = frozenset({"arm", "name", "accepted", "reason"})

    arm: str = ""
    name: str = ""
    accepted: bool = False
    reason: str = ""

    def body(self) -> dict[str, Any]:
        return {"arm": self.arm, "name": self.name, "accepted": self.accepted, "reason": self.reason}

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> CommandReply:
        return cls(header, _str(d, "arm"), _str(d, "name"), _bool(d, "accepted"), _str(d, "reason"))


#: The teleop states of one master → slave pair (:class:`TeleopState`, services/mapping/engage.py).
TELEOP_STATES = frozenset({"DISABLED", "IDLE", "ENGAGING", "ENABLED", "HOLDING"})


@_register
@dataclass(frozen=True, slots=True)
class TeleopState(Message):
    """The mapping's teleop state of one pair (``mapping/<slave arm>/teleop_state``), at 10 Hz
    and on every change; the mapping also answers a query on the key with the current state.

    Attributes:
        master: master arm id of the pair.
        slave: slave arm id of the pair.
        state: ``DISABLED`` (a press would be refused: operator absent, slave not allowed to move,
            no fresh slave joints), ``IDLE`` (clutch released, ready), ``ENGAGING`` (a new press
            seen: the engage is tried at the next master sample), ``ENABLED`` (the slave follows
            the master), ``HOLDING`` (clutch pressed but not following: a disengage the operator
            did not make, a refused engage, or the pedal was down at start; release and press).
        previous: the state before ``state`` (equal to ``state`` before the first change).
        reason: why the pair is in ``state`` (e.g. ``slave holding: lease expired``); it may
            change within a state (a DISABLED pair's hold reason), ``since_ns`` then stays.
        since_ns: wall-clock time ``state`` was entered, ns since the Unix epoch.
        scale: the operator's motion scale in use (changed by ``set_scale`` / ``scale_up`` /
            ``scale_down``), in (0, 2].
        safety_scale: the watchdog's motion-scale factor applied on top of it, in [0, 1].
        mode: the mapping mode, e.g. ``cartesian``, ``all_joints``, ``vip``.
    """

    TYPE: ClassVar[str] = "teleop_state"
    BODY: ClassVar[frozenset[str]] = frozenset(
        {"master", "slave", "state", "previous", "reason", "since_ns", "scale", "safety_scale", "mode"}
    )

    master: str = ""
    slave: str = ""
    state: str = "DISABLED"
    previous: str = "DISABLED"
    reason: str = ""
    since_ns: int = 0
    scale: float = 1.0
    safety_scale: float = 1.0
    mode: str = "cartesian"

    def body(self) -> dict[str, Any]:
        return {
            "master": self.master,
            "slave": self.slave,
            "state": self.state,
            "previous": self.previous,
            "reason": self.reason,
            "since_ns": self.since_ns,
            "scale": self.scale,
            "safety_scale": self.safety_scale,
            "mode": self.mode,
        }

    @classmethod
    def from_body(cls, header: Header, d: dict[str, Any]) -> TeleopState:
        scale = _float(d, "scale")
        if not 0.0 < scale <= 2.0:
            raise MessageError(f"field 'scale'={scale} outside (0, 2]")
        safety = _float(d, "safety_scale")
        if not 0.0 <= safety <= 1.0:
            raise MessageError(f"field 'safety_scale'={safety} outside [0, 1]")
        return cls(
            header,
            _str(d, "master", allow_empty=False),
            _str(d, "slave", allow_empty=False),
            _choice(d, "state", TELEOP_STATES),
            _choice(d, "previous", TELEOP_STATES),
            _str(d, "reason"),
            _int(d, "since_ns", hi=_I64_MAX),
            scale,
            safety,
            _str(d, "mode", allow_empty=False),
        )


#: Every message class by its type tag.
MESSAGE_TYPES: dict[str, type[Message]] = dict(_REGISTRY)

AnyMessage = (
    JointState
    | CartesianPose
    | MasterButtons
    | JointSetpoint
    | OperatingState
    | SafetyLease
    | SafetyState
    | SafetyEvent
    | EStop
    | Command
    | CommandReply
    | Heartbeat
    | TeleopState
)


def decode(payload: bytes | bytearray | memoryview) -> AnyMessage:
    """Decode and validate one payload; raise :class:`MessageError` on anything malformed."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MessageError(f"payload is {len(payload)} bytes, limit {MAX_PAYLOAD_BYTES}")
    try:
        d = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_str_len=MAX_STR * 4,
            max_bin_len=0,
            max_array_len=MAX_JOINTS * 4,
            max_map_len=32,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises a family of unrelated exception types
        raise MessageError(f"not a valid MessagePack payload: {type(exc).__name__}: {exc}") from None
    if not isinstance(d, dict):
        raise MessageError(f"payload must be a map, got {type(d).__name__}")
    if len(d) != _map_len(payload):
        raise MessageError("duplicate keys in a map")
    version = d.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise MessageError(f"unknown schema version {version!r}, expected {SCHEMA_VERSION}")
    tag = d.get("type")
    cls = _REGISTRY.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise MessageError(f"unknown message type {tag!r}; valid: {sorted(_REGISTRY)}")
    extra = set(d) - _HEADER_KEYS - cls.BODY
    if extra:
        raise MessageError(f"{tag}: unexpected fields {sorted(map(repr, extra))}")
    header = Header(
        _str(d, "src", allow_empty=False), _int(d, "seq", hi=_I64_MAX), _int(d, "ts", hi=_I64_MAX)
    )
    msg = cls.from_body(header, d)
    return msg  # type: ignore[return-value]


def decode_as(payload: bytes | bytearray | memoryview, cls: type[M]) -> M:
    """Decode a payload that must be of type ``cls`` (e.g. on a key that carries one type)."""
    msg = decode(payload)
    if not isinstance(msg, cls):
        raise MessageError(f"expected {cls.TYPE!r}, got {msg.TYPE!r}")
    return msg


@dataclass
class Sequencer:
    """Builds headers for one outgoing stream: source id, running seq, timestamp."""

    source: str
    seq: int = 0
    clock: Callable[[], int] = field(default=now_ns)

    def next(self) -> Header:
        """Header for the next message of this stream."""
        h = Header(self.source, self.seq, self.clock())
        self.seq += 1
        return h
