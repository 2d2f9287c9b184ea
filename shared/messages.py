"""Typed telesurg messages, MessagePack on the wire, one strict decoder.

Every payload is a MessagePack map with a common header::

    {"v": 6, "type": "joint_state", "src": "slave_control", "seq": 42, "ts": 1700000000000000000,
     ...body fields...}

* ``v``    schema version (int, must equal :data:`SCHEMA_VERSION`)
* ``type`` message type tag (one of :data:`MESSAGE_TYPES`)
* ``src``  source id: the publishing service instance (str)
* ``seq``  per-stream sequence number, starts at 0, +1 per message (int >= 0)
* ``ts``   source timestamp, wall clock, ns since the Unix epoch (int >= 0)

:func:`decode` is the only entry point for incoming bytes. It validates strictly — exact field set,
types, array shapes, finite numbers, string and array sizes, total payload size — and raises
:class:`~telesurg.shared.errors.MessageError` with a message naming the field. Nothing half-decoded escapes.

Each field is declared once, as a dataclass field whose default is :func:`fld` (the default, what it
means, its unit and its rules); :func:`message` derives from those declarations the encoder, the
strict decoder (generated Python, like the dataclass ``__init__``), ``BODY``, ``body()``,
``from_body()``, the ``Attributes`` section of the docstring and the table in docs/messages.md
(``telesurg docs messages``). The rules follow from the annotation — ``str`` ≤ :data:`MAX_STR`
characters, ``bool``, ``int`` in [0, 2⁶⁴−1], ``float`` finite, ``tuple[float, ...]`` ≤
:data:`MAX_JOINTS` finite numbers, ``tuple[float, float, float]`` exactly three, ``tuple[str, ...]``
≤ :data:`MAX_LIST` strings — narrowed by :func:`fld`'s keywords. A new message::

    @message("teleop_state")
    @dataclass(frozen=True, slots=True)
    class TeleopState(Message):
        \"\"\"The mapping's per-pair state (``mapping/<m>/teleop_state``).\"\"\"

        arm: str = fld("", "slave arm id", nonempty=True)
        state: str = fld("disabled", "teleop state", choices=TELEOP_STATES)
        scale: float = fld(1.0, "motion scale applied", ge=0.0, le=1.0)

A class written the older way (``BODY``, ``body()``, ``from_body()`` by hand, ``@_register``) still
works; adding a field to an existing type, or a new type, changes the wire format.

Example::

    >>> from telesurg.shared.messages import Header, JointSetpoint, decode
    >>> m = JointSetpoint(Header("mapping", 0, 1), ("j1",), (0.1,), follow=True)
    >>> decode(m.encode()) == m
    True
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import msgpack
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import MessageError

# 2: safety fields (origin_ns, latency, scale, rcm, clipped), estop; 3: heartbeat polled_s;
# 4: clock probes, safety_state.clock_offset_ms; pose / wrench energy_in_j (docs/haptics.md);
# 5: heartbeat replayed, lost; 6: teleop_state rotation; 7: teleop_state limit_wall
SCHEMA_VERSION = 7
#: Largest payload accepted by :func:`decode`, bytes.
MAX_PAYLOAD_BYTES = 64 * 1024
#: Largest joint count in any joint-space message.
MAX_JOINTS = 32
#: Longest string field (names, reasons), characters.
MAX_STR = 512
#: Most entries in a list-of-strings field (e.g. safety causes).
MAX_LIST = 64
#: most loose objects a scene state lists
MAX_OBJECTS = 16
#: Largest ``camera_image`` payload, bytes: images have their own limit, on their own key
#: (``camera/<cam>/image``), and only ``decode_as(payload, CameraImage)`` accepts one
#: (:data:`Message.MAX_PAYLOAD`); :func:`decode` keeps :data:`MAX_PAYLOAD_BYTES` and no bin values.
MAX_IMAGE_PAYLOAD_BYTES = 2 * 1024 * 1024
#: Largest encoded image (the ``data`` bin field of ``camera_image``), bytes.
MAX_IMAGE_BYTES = MAX_IMAGE_PAYLOAD_BYTES - 4096
#: Most entries in one MessagePack map / array, checked while unpacking (before any field check).
MAX_MAP_LEN = 32
MAX_ARRAY_LEN = MAX_JOINTS * 4

_HEADER_KEYS = frozenset({"v", "type", "src", "seq", "ts"})
_U64_MAX = 2**64 - 1
#: Largest ``seq`` / ``ts``: int64, so every consumer (numpy, rerun, MCAP) can hold them.
_I64_MAX = 2**63 - 1


def now_ns() -> int:
    """Source timestamp for headers: wall clock, ns since the Unix epoch (:func:`clock.wall_ns`)."""
    return wall_ns()


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


def _bytes(d: dict[str, Any], key: str, max_len: int, *, allow_empty: bool = True) -> bytes:
    v = _get(d, key)
    if not isinstance(v, bytes):
        raise MessageError(f"field {key!r} must be bytes (MessagePack bin), got {type(v).__name__}")
    if len(v) > max_len:
        raise MessageError(f"field {key!r} is {len(v)} bytes, limit {max_len}")
    if not allow_empty and not v:
        raise MessageError(f"field {key!r} must not be empty")
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


def _joint_names(d: dict[str, Any], key: str = "name") -> tuple[str, ...]:
    v = d.get(key)
    if type(v) is list:
        try:
            known = _NAMES_SEEN.get(tuple(v))  # a stream repeats its names in every message
        except TypeError:  # an unhashable element: the checks below reject it
            known = None
        if known is not None:
            return known
    names = _validated_joint_names(d, key)
    if len(_NAMES_SEEN) >= _NAMES_SEEN_MAX:
        _NAMES_SEEN.clear()
    _NAMES_SEEN[names] = names
    return names


def _validated_joint_names(d: dict[str, Any], key: str) -> tuple[str, ...]:
    names = _strs(d, key, max_len=MAX_JOINTS)
    if not names:
        raise MessageError(f"field {key!r} must list at least one joint")
    if len(set(names)) != len(names) or not all(names):
        raise MessageError(f"field {key!r} must hold distinct, non-empty joint names")
    return names


def _map_len(payload: bytes | bytearray | memoryview) -> int:
    """Entries declared by the MessagePack map header at the start of ``payload`` (-1: not a map).

    A map that decodes to fewer keys than it declares had duplicate keys (the decoder keeps the
    last one). Messages have no nested maps (no field takes one), so the top level is all there
    is to check."""
    if not payload:
        return -1
    b0 = payload[0]
    if 0x80 <= b0 <= 0x8F:
        return b0 & 0x0F
    if b0 == 0xDE and len(payload) >= 3:
        return int.from_bytes(payload[1:3], "big")
    if b0 == 0xDF and len(payload) >= 5:
        return int.from_bytes(payload[1:5], "big")
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


# --------------------------------------------------------------------------- declarations

T = TypeVar("T")
M = TypeVar("M", bound="Message")
_SPEC_KEY = "telesurg.message"


@dataclass(frozen=True, slots=True)
class FieldSpec:
    """One body field of a message: wire key, kind, rules, and what it means (from :func:`fld`).

    Attributes:
        name: Python attribute.
        wire: key in the MessagePack map.
        kind: ``str``, ``bool``, ``int``, ``float``, ``floats`` (number array), ``strs`` (string
            array), ``names`` (joint names: 1 to MAX_JOINTS distinct non-empty strings) or
            ``bytes`` (a MessagePack bin of at most ``max_len`` bytes; only in a type with its own
            ``MAX_BIN``, e.g. ``camera_image``).
        doc: what the field means.
        unit: unit of a number or number array ("" for none).
        length: exact element count of a fixed-length array (None: variable).
        max_len: most elements of an array.
        nonempty: a string that must not be empty.
        choices: the only values a string may take.
        pattern: regular expression a string must match in full.
        lo, hi: bounds of a number (None: unbounded); ``lo_open`` / ``hi_open`` exclude them.
        same_len: Python name of the field an array must be as long as; ``empty_ok``: or empty.
        unit_quat: a 4-array that must be a unit quaternion ``[x, y, z, w]`` (norm 1 ± 1e-3).
        check: a further check of the decoded value (raises MessageError); ``check_doc`` says
            what it checks.
        absent: ``(default,)`` for a field added to a type after messages of it were recorded:
            a message without it (an older recording) decodes with that default; ``()`` (every
            other field): a message without it is refused.
    """

    name: str
    wire: str
    kind: str
    doc: str
    unit: str = ""
    length: int | None = None
    max_len: int = 0
    nonempty: bool = False
    choices: frozenset[str] | None = None
    pattern: str | None = None
    lo: float | None = None
    lo_open: bool = False
    hi: float | None = None
    hi_open: bool = False
    same_len: str | None = None
    empty_ok: bool = False
    unit_quat: bool = False
    check: Callable[[Any], None] | None = None
    check_doc: str = ""
    absent: tuple[Any, ...] = ()  # (default,): a field added later, absent in older recordings


def _interval(s: FieldSpec) -> str:
    return f"{'(' if s.lo_open else '['}{s.lo:g}, {s.hi:g}{')' if s.hi_open else ']'}"


def fld(
    default: T,
    doc: str,
    *,
    unit: str = "",
    wire: str | None = None,
    nonempty: bool = False,
    choices: frozenset[str] | None = None,
    pattern: str | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    max_len: int | None = None,
    same_len: str | None = None,
    empty_ok: bool = False,
    unit_quat: bool = False,
    joint_names: bool = False,
    check: Callable[[Any], None] | None = None,
    check_doc: str = "",
    added: bool = False,
) -> T:
    """Declare one message field: its default and everything the codec and the docs need.

    Args:
        default: value of a message built without it (immutable: a tuple for arrays).
        doc: what the field means (docstring and docs/messages.md).
        unit: unit of a number or number array, e.g. ``"m"``, ``"rad / m"``, ``"ms"``.
        wire: key in the MessagePack map, if not the attribute name.
        nonempty: a string that must not be empty.
        choices: the only values a string may take.
        pattern: regular expression a string must match in full.
        ge, gt, le, lt: bounds of a number (an ``int`` defaults to [0, 2⁶⁴−1]).
        max_len: most elements of a variable-length array (default MAX_JOINTS for numbers,
            MAX_LIST for strings).
        same_len: attribute name of the field this array must be as long as; ``empty_ok``: or
            empty.
        unit_quat: a ``tuple[float, float, float, float]`` that must be a unit quaternion.
        joint_names: a ``tuple[str, ...]`` of 1 to MAX_JOINTS distinct, non-empty joint names.
        check: a further check of the decoded value, raising MessageError; ``check_doc`` says
            what it checks, for the docs.
        added: the field was added to the type after messages of it were recorded: a message
            without it (an older recording) decodes with ``default``; every other field must be
            present.

    Returns:
        A dataclass field (typed as its default, so the class keeps its annotations).
    """
    if (ge is not None and gt is not None) or (le is not None and lt is not None):
        raise TypeError("fld: give one lower and one upper bound at most")
    spec = FieldSpec(
        name="",  # name, kind, length and the array default of max_len: from the class (_spec)
        wire=wire or "",
        kind="",
        doc=doc,
        unit=unit,
        max_len=max_len or 0,
        nonempty=nonempty,
        choices=choices,
        pattern=pattern,
        lo=ge if gt is None else gt,
        lo_open=gt is not None,
        hi=le if lt is None else lt,
        hi_open=lt is not None,
        same_len=same_len,
        empty_ok=empty_ok,
        unit_quat=unit_quat,
        check=check,
        check_doc=check_doc,
        absent=(default,) if added else (),
    )
    out: T = field(default=default, metadata={_SPEC_KEY: (spec, joint_names)})
    return out


def _spec(name: str, tp: Any, declared: tuple[FieldSpec, bool]) -> FieldSpec:
    """Complete a field's :func:`fld` declaration with its name and the kind its annotation gives."""
    spec, joint_names = declared
    args = typing.get_args(tp)
    kind, length = "", None
    if tp in (str, bool, int, float):
        kind = tp.__name__
    elif typing.get_origin(tp) is tuple and args and all(a is float for a in args if a is not Ellipsis):
        kind = "floats"
        length = None if args[-1] is Ellipsis else len(args)
    elif typing.get_origin(tp) is tuple and args == (str, Ellipsis):
        kind = "names" if joint_names else "strs"
    elif tp is bytes:
        kind = "bytes"
        if not spec.max_len:
            raise TypeError(f"field {name!r}: a bytes field needs max_len (bytes)")
    if not kind:
        raise TypeError(f"field {name!r}: the codec has no rule for {tp!r}")
    if spec.unit_quat and length != 4:
        raise TypeError(f"field {name!r}: a unit quaternion is a tuple[float, float, float, float]")
    return dataclasses.replace(
        spec,
        name=name,
        wire=spec.wire or name,
        kind=kind,
        length=length,
        max_len=spec.max_len or length or (MAX_JOINTS if kind in ("floats", "names") else MAX_LIST),
        lo=0 if kind == "int" and spec.lo is None else spec.lo,
    )


# --------------------------------------------------------------------------- generated codec


def _body_lines(cls_name: str, specs: Sequence[FieldSpec], env: dict[str, Any]) -> list[str]:
    """Python source (4-space indent) checking every body field of ``d`` into ``x_<name>``.

    Each check is a fast test of the common valid value; anything else goes to the matching
    ``_str`` / ``_int`` / ``_float`` / ``_floats`` helper, which raises the error naming the field
    (or accepts what the fast test was too narrow for, e.g. an int in a float field)."""
    out: list[str] = []
    for s in specs:
        x, w = f"x_{s.name}", repr(s.wire)
        if s.absent:  # (added later: an older recording's message has the default)
            env[f"A_{s.name}"] = s.absent[0]
            out += [f"    {x} = d.get({w}, A_{s.name})"]
        else:
            out += [
                "    try:",
                f"        {x} = d[{w}]",
                "    except KeyError:",
                f"        raise _E({'missing field ' + repr(s.wire)!r}) from None",
            ]
        if s.kind == "str":
            empty = " or not " + x if s.nonempty else ""
            out += [
                f"    if type({x}) is not str or len({x}) > {MAX_STR}{empty}:",
                f"        {x} = _str(d, {w}, allow_empty={not s.nonempty})",
            ]
            if s.choices is not None:
                env[f"C_{s.name}"] = s.choices
                env[f"CS_{s.name}"] = sorted(s.choices)
                out += [
                    f"    if {x} not in C_{s.name}:",
                    f'        raise _E(f"field {w}={{{x}!r}} is not one of {{CS_{s.name}}}")',
                ]
            if s.pattern is not None:
                env[f"P_{s.name}"] = re.compile(s.pattern)
                out += [
                    f"    if not P_{s.name}.fullmatch({x}):",
                    f'        raise _E(f"field {w}={{{x}!r}} must match {_braces(s.pattern)}")',
                ]
        elif s.kind == "bool":
            out += [
                f"    if {x} is not True and {x} is not False:",
                f'        raise _E(f"field {w} must be a boolean, got {{type({x}).__name__}}")',
            ]
        elif s.kind == "int":
            lo, hi = int(s.lo or 0), _U64_MAX if s.hi is None else int(s.hi)
            out += [
                f"    if type({x}) is not int or not {lo} <= {x} <= {hi}:",
                f"        {x} = _int(d, {w}, {lo}, {hi})",
            ]
        elif s.kind == "float":
            out += [f"    if type({x}) is not float or {x} - {x} != 0.0:", f"        {x} = _float(d, {w})"]
            if s.lo is not None or s.hi is not None:
                conds = []
                if s.lo is not None:
                    conds.append(f"{x} {'<=' if s.lo_open else '<'} {s.lo!r}")
                if s.hi is not None:
                    conds.append(f"{x} {'>=' if s.hi_open else '>'} {s.hi!r}")
                if s.lo is not None and s.hi is not None:
                    why = f"outside {_interval(s)}"
                elif s.lo is not None:
                    why = f"must be {'>' if s.lo_open else '>='} {s.lo:g}"
                else:
                    why = f"must be {'<' if s.hi_open else '<='} {s.hi:g}"
                out += [f"    if {' or '.join(conds)}:", f'        raise _E(f"field {w}={{{x}}} {why}")']
        elif s.kind == "floats" and s.length:
            n = s.length
            fast = " and ".join(f"type({x}[{i}]) is float" for i in range(n))
            total = " + ".join(f"{x}[{i}]" for i in range(n))
            out += [
                f"    if type({x}) is list and len({x}) == {n} and {fast} and _isfinite({total}):",
                f"        {x} = ({', '.join(f'{x}[{i}]' for i in range(n))},)",
                "    else:",
                f"        {x} = _floats(d, {w}, {n})",
            ]
        elif s.kind == "floats":
            out += [
                f"    if (type({x}) is list and len({x}) <= {s.max_len}"
                f" and all([type(e) is float for e in {x}]) and _isfinite(sum({x}))):",
                f"        {x} = tuple({x})",
                "    else:",
                f"        {x} = _floats(d, {w}, max_len={s.max_len})",
            ]
        elif s.kind == "names":
            out.append(f"    {x} = _joint_names(d, {w})")
        elif s.kind == "strs":
            out.append(f"    {x} = _strs(d, {w}, max_len={s.max_len})")
        elif s.kind == "bytes":
            lo = 1 if s.nonempty else 0
            out += [
                f"    if type({x}) is not bytes or not {lo} <= len({x}) <= {s.max_len}:",
                f"        {x} = _bytes(d, {w}, {s.max_len}, allow_empty={not s.nonempty})",
            ]
        if s.same_len:
            ref = next((r for r in specs if r.name == s.same_len), None)
            if ref is None or specs.index(ref) > specs.index(s):
                raise TypeError(f"{cls_name}.{s.name}: same_len={s.same_len!r} must name an earlier field")
            y, may_be_empty = f"x_{ref.name}", f"{x} and " if s.empty_ok else ""
            out += [
                f"    if {may_be_empty}len({x}) != len({y}):",
                f'        raise _E(f"field {w} has {{len({x})}} elements for {{len({y})}} names")',
            ]
        if s.unit_quat:
            out += [
                f"    n = _sqrt({x}[0] * {x}[0] + {x}[1] * {x}[1] + {x}[2] * {x}[2] + {x}[3] * {x}[3])",
                "    if not abs(n - 1.0) <= 1e-3:",
                f'        raise _E(f"field {w} must be a unit quaternion [x, y, z, w], norm={{n:.6g}}")',
            ]
        if s.check is not None:
            env[f"K_{s.name}"] = s.check
            out.append(f"    K_{s.name}({x})")
    return out


def _braces(text: str) -> str:
    """``text`` inside an f-string literal."""
    return text.replace("{", "{{").replace("}", "}}")


def _compile(cls: type[Message], specs: tuple[FieldSpec, ...]) -> None:
    """Generate and attach ``encode``, ``body``, ``from_body`` and the wire decoder of ``cls``."""
    env: dict[str, Any] = {
        "_E": MessageError,
        "_str": _str,
        "_int": _int,
        "_float": _float,
        "_floats": _floats,
        "_strs": _strs,
        "_bytes": _bytes,
        "_joint_names": _joint_names,
        "_isfinite": math.isfinite,
        "_sqrt": math.sqrt,
        "_packb": msgpack.packb,
        "_Header": Header,
        "_I64": _I64_MAX,
        "_cls": cls,
        "_ALLOWED": _HEADER_KEYS | cls.BODY,
        "_new": object.__new__,
    }
    # The decoder fills the frozen, slotted instances through their slot descriptors: the checks
    # above are all the validation there is (no __post_init__), and this halves the cost of
    # building a message and its header (frozen __init__ goes through object.__setattr__).
    names = ["header", *(s.name for s in specs)]
    for owner, attrs in ((cls, names), (Header, ["source", "seq", "stamp_ns"])):
        for a in attrs:
            slot = next((k.__dict__[a] for k in owner.__mro__ if a in k.__dict__), None)
            if not isinstance(slot, types.MemberDescriptorType):
                raise TypeError(f"{owner.__name__}.{a}: message classes must be slots dataclasses")
            env[f"S_{owner.__name__}_{a}"] = slot.__set__
    tag = cls.TYPE
    body = _body_lines(cls.__name__, specs, env)
    args = ", ".join(f"x_{s.name}" for s in specs)
    items = "".join(f", {s.wire!r}: self.{s.name}" for s in specs)
    lists = ", ".join(
        f"{s.wire!r}: "
        + (f"list(self.{s.name})" if s.kind in ("floats", "strs", "names") else f"self.{s.name}")
        for s in specs
    )
    header = [
        "    if not d.keys() <= _ALLOWED:",
        f'        raise _E(f"{tag}: unexpected fields {{sorted(map(repr, set(d) - _ALLOWED))}}")',
        "    try:",
        "        src, seq, ts = d['src'], d['seq'], d['ts']",
        "    except KeyError:",
        "        src = _str(d, 'src', allow_empty=False)",
        "        seq = _int(d, 'seq', hi=_I64)",
        "        ts = _int(d, 'ts', hi=_I64)",
        f"    if type(src) is not str or not 0 < len(src) <= {MAX_STR}:",
        "        src = _str(d, 'src', allow_empty=False)",
        "    if type(seq) is not int or not 0 <= seq <= _I64:",
        "        seq = _int(d, 'seq', hi=_I64)",
        "    if type(ts) is not int or not 0 <= ts <= _I64:",
        "        ts = _int(d, 'ts', hi=_I64)",
        "    header = _new(_Header)",
        "    S_Header_source(header, src)",
        "    S_Header_seq(header, seq)",
        "    S_Header_stamp_ns(header, ts)",
    ]
    build = [
        "    msg = _new(_cls)",
        *(f"    S_{cls.__name__}_{n}(msg, {'header' if n == 'header' else 'x_' + n})" for n in names),
        "    return msg",
    ]
    src = "\n".join(
        [
            "def from_wire(d):",
            *header,
            *body,
            *build,
            "",
            "def from_body(cls, header, d):",
            *body,
            f"    return cls(header, {args})",
            "",
            "def encode(self):",
            "    h = self.header",
            f"    return _packb({{'v': {SCHEMA_VERSION}, 'type': {tag!r}, 'src': h.source, 'seq': h.seq,"
            f" 'ts': h.stamp_ns{items}}}, use_bin_type=True)",
            "",
            "def body(self):",
            f"    return {{{lists}}}",
        ]
    )
    exec(compile(src, f"<telesurg codec {cls.__name__}>", "exec"), env)  # the codec, as dataclasses does
    from_body = env["from_body"]
    from_body.__doc__ = f"Build a {cls.__name__} from a header and a raw body map; MessageError if invalid."
    env["encode"].__doc__ = "MessagePack bytes of this message."
    env["body"].__doc__ = "Body fields as plain msgpack-able values."
    cls.from_body = classmethod(from_body)  # type: ignore[method-assign,assignment]
    cls.encode = env["encode"]  # type: ignore[method-assign]
    cls.body = env["body"]  # type: ignore[method-assign]
    _DECODERS[tag] = env["from_wire"]


def _attributes_doc(specs: Sequence[FieldSpec]) -> str:
    lines = ["", "", "    Attributes:"]
    for s in specs:
        unit = f" [{s.unit}]" if s.unit else ""
        lines.append(f"        {s.name}: {s.doc}{unit}.")
    return "\n".join(lines)


def message(tag: str) -> Callable[[type[M]], type[M]]:
    """Class decorator: register a message dataclass under ``tag`` and derive its codec.

    Every field but ``header`` must be declared with :func:`fld`; the wire map lists them in
    declaration order after the header."""

    def wrap(cls: type[M]) -> type[M]:
        if not dataclasses.is_dataclass(cls) or tag in _REGISTRY:
            raise TypeError(f"@message({tag!r}) needs a new tag on a dataclass")
        hints = typing.get_type_hints(cls)
        specs = []
        for f in dataclasses.fields(cls):
            if f.name == "header":
                continue
            if _SPEC_KEY not in f.metadata:
                raise TypeError(f"{cls.__name__}.{f.name}: declare it with fld(...)")
            specs.append(_spec(f.name, hints[f.name], f.metadata[_SPEC_KEY]))
        cls.TYPE = tag
        cls.FIELDS = tuple(specs)
        cls.BODY = frozenset(s.wire for s in specs)
        if len(cls.BODY) != len(specs) or cls.BODY & _HEADER_KEYS:
            raise TypeError(f"{cls.__name__}: wire keys must be distinct and not header keys")
        cls.__doc__ = (cls.__doc__ or "").rstrip() + _attributes_doc(specs)
        _compile(cls, cls.FIELDS)
        _REGISTRY[tag] = cls
        return cls

    return wrap


def _register(cls: type[M]) -> type[M]:
    """Register a message class written by hand (``BODY``, ``body()``, ``from_body()``)."""
    _REGISTRY[cls.TYPE] = cls

    def from_wire(d: dict[str, Any]) -> Message:
        extra = set(d) - _HEADER_KEYS - cls.BODY
        if extra:
            raise MessageError(f"{cls.TYPE}: unexpected fields {sorted(map(repr, extra))}")
        header = Header(
            _str(d, "src", allow_empty=False), _int(d, "seq", hi=_I64_MAX), _int(d, "ts", hi=_I64_MAX)
        )
        return cls.from_body(header, d)

    _DECODERS[cls.TYPE] = from_wire
    return cls


_REGISTRY: dict[str, type[Message]] = {}
#: The wire decoder of each tag: checked map (after version and tag) → message.
_DECODERS: dict[str, Callable[[dict[str, Any]], Message]] = {}

# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Message:
    """Base of every message: a header plus typed body fields (subclasses)."""

    TYPE: ClassVar[str] = ""
    BODY: ClassVar[frozenset[str]] = frozenset()
    #: The body fields, in wire order (set by :func:`message`; empty for a hand-written class).
    FIELDS: ClassVar[tuple[FieldSpec, ...]] = ()
    #: Largest payload of this type :func:`decode_as` accepts, and the largest bin value in it
    #: (0: none); only a bulk type on its own key (``camera_image``) raises them.
    MAX_PAYLOAD: ClassVar[int] = MAX_PAYLOAD_BYTES
    MAX_BIN: ClassVar[int] = 0

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


@message("joint_state")
@dataclass(frozen=True, slots=True)
class JointState(Message):
    """Measured joint state (CRTK ``measured_js``)."""

    names: tuple[str, ...] = fld((), "joint names, e.g. `j1` … `j6`", wire="name", joint_names=True)
    position: tuple[float, ...] = fld((), "joint positions", unit="rad / m", same_len="names")
    velocity: tuple[float, ...] = fld(
        (), "joint velocities", unit="rad/s / m/s", same_len="names", empty_ok=True
    )
    effort: tuple[float, ...] = fld((), "joint efforts", unit="N·m / N", same_len="names", empty_ok=True)


@message("pose")
@dataclass(frozen=True, slots=True)
class CartesianPose(Message):
    """A Cartesian pose (CRTK ``measured_cp`` / ``setpoint_cp``)."""

    frame: str = fld("base", 'reference frame, e.g. `"base"` (slave base) or `"master"` (master device)')
    position: tuple[float, float, float] = fld((0.0, 0.0, 0.0), "`[x, y, z]`", unit="m")
    orientation: tuple[float, float, float, float] = fld(
        (0.0, 0.0, 0.0, 1.0), "orientation `[x, y, z, w]` (scalar last)", unit_quat=True
    )
    energy_in_j: float = fld(
        0.0,
        "bilateral force feedback (docs/haptics.md): energy that has flowed into the network at the "
        "master port since the pair engaged, `E_in_m`, for the slave's passivity observer "
        "(0: no haptic master)",
        unit="J",
        ge=0.0,
    )


@message("wrench")
@dataclass(frozen=True, slots=True)
class CartesianWrench(Message):
    """A wrench at the tool tip (CRTK ``measured_cf``): what the environment exerts on the tool."""

    frame: str = fld("base", 'reference frame of both vectors, e.g. `"base"`')
    force: tuple[float, float, float] = fld((0.0, 0.0, 0.0), "force `[fx, fy, fz]` at the tip", unit="N")
    torque: tuple[float, float, float] = fld(
        (0.0, 0.0, 0.0), "torque `[tx, ty, tz]` about the tip", unit="N·m"
    )
    energy_in_j: float = fld(
        0.0,
        "bilateral force feedback (docs/haptics.md): energy that has flowed into the network at the "
        "slave port since the slave started, `E_in_s` in slave units (the environment's work on "
        "the instrument along its motion; the master multiplies it by force_scale / position_scale), "
        "for the master's passivity observer (0: a slave that measures no force)",
        unit="J",
        ge=0.0,
    )


@message("buttons")
@dataclass(frozen=True, slots=True)
class MasterButtons(Message):
    """Master device buttons (``master/<arm>/buttons``), on change and at a steady rate."""

    clutch: bool = fld(
        False, "clutch pedal pressed; the slave follows only while pressed (engage needs a new press)"
    )
    operator_present: bool = fld(
        False, "operator detected at the console (head/hand sensor); false disengages"
    )
    grip: float = fld(
        0.0,
        "the master's gripper: 0 open … 1 closed (an omega.7's grip, a stylus button held = 1); "
        "the slave's jaws follow it while engaged, once it has come to their closure",
        ge=0.0,
        le=1.0,
        added=True,
    )


@message("servo_jp")
@dataclass(frozen=True, slots=True)
class JointSetpoint(Message):
    """Joint position setpoint (CRTK ``servo_jp``)."""

    names: tuple[str, ...] = fld((), "joint names (must match the slave's)", wire="name", joint_names=True)
    position: tuple[float, ...] = fld((), "joint setpoint", unit="rad / m", same_len="names")
    follow: bool = fld(
        False,
        "true while the mapping follows the master; false = hold (the position is then the last "
        "setpoint, informational). A slave resumes only on a false → true edge",
    )
    origin_ns: int = fld(
        0,
        "source timestamp (`ts`) of the master sample this setpoint was computed from, 0 if none; "
        "receivers on the same host measure end-to-end latency with it",
        unit="ns",
    )
    grip: float = fld(
        -1.0,
        "the jaws' closure to follow with this setpoint, 0 open … 1 closed; -1: none (the jaws keep "
        "their last command). Followed only while the slave follows",
        ge=-1.0,
        le=1.0,
        added=True,
    )


OPERATING_STATES = frozenset({"DISABLED", "ENABLED", "PAUSED", "FAULT"})
CONTROL_MODES = frozenset({"non_trocar", "transitional", "trocar", "joint"})


@message("operating_state")
@dataclass(frozen=True, slots=True)
class OperatingState(Message):
    """Slave arm operating state (CRTK ``operating_state``), ~20 Hz and on change."""

    state: str = fld(
        "DISABLED",
        "`ENABLED` (moving under a lease), `PAUSED` (holding), `DISABLED`, `FAULT` (an e-stop is latched)",
        choices=OPERATING_STATES,
    )
    control_mode: str = fld(
        "non_trocar",
        "`non_trocar` / `transitional` / `trocar` (the forceps arm's modes), or `joint` (a joint-space "
        "slave without trocar modes: PLAS, VIP arms)",
        choices=CONTROL_MODES,
    )
    follow: bool = fld(False, "the slave is tracking `servo_jp`")
    lease_ok: bool = fld(False, "a fresh watchdog lease allows motion")
    reason: str = fld("", 'why the slave holds (`""` while following)')
    holds: int = fld(
        0, "times the slave entered a fault hold since start (a clutch-release pause is not counted)"
    )
    rcm_error_mm: float = fld(
        0.0,
        "distance from the trocar point to the forceps axis line of the measured (simulated or real) "
        "arm's tip pose; meaningful once the forceps is through the trocar (the watchdog checks it "
        "only in trocar mode)",
        unit="mm",
        ge=0.0,
    )
    clipped: int = fld(0, "control cycles in which the slave's joint speed limit clipped the setpoint")
    rejected: int = fld(
        0,
        "setpoints the slave refused: its own checks (names, limits, jumps) + the `servo_jp` "
        "subscription's rejections (decoder, foreign source, implausible sequence jump)",
    )
    trocar: tuple[float, float, float] = fld(
        (0.0, 0.0, 0.0),
        "the trocar point the slave uses (taught or configured), base frame; the mapping uses it "
        "for master–slave motion in trocar mode",
        unit="m",
    )
    is_homed: bool = fld(
        True,
        "CRTK `is_homed`: the arm's joint positions are referenced; slave_control has no homing "
        "procedure and always sends true (the MuJoCo arms start at their home pose)",
        added=True,
    )
    is_busy: bool = fld(
        False,
        "CRTK `is_busy`: a slave-side motion (PTP, jog, playback, direct teach) is running; "
        "`servo_jp` is not followed meanwhile",
        added=True,
    )
    grip: float = fld(
        -1.0,
        "the jaws' closure commanded now, 0 open … 1 closed (kept through a hold: a hold never "
        "releases what the jaws hold); -1: the arm has no jaws",
        ge=-1.0,
        le=1.0,
        added=True,
    )


SAFETY_STATES = frozenset({"OK", "DEGRADED", "HOLD", "ESTOP"})


@message("lease")
@dataclass(frozen=True, slots=True)
class SafetyLease(Message):
    """Permission to move, from the watchdog to one slave arm (``safety/<arm>/lease``).

    The slave may move only while ``allow`` is True and less than ``valid_for_ms`` has passed
    since it received this lease (relative, so clocks need not agree across hosts).
    """

    arm: str = fld("", "slave arm id this lease is for", nonempty=True)
    allow: bool = fld(False, "true grants motion; false orders an immediate hold")
    valid_for_ms: float = fld(0.0, "lifetime counted from reception", unit="ms", gt=0.0, le=10_000.0)
    reason: str = fld("", 'why motion is not allowed (`""` when allowed)')


@message("safety_state")
@dataclass(frozen=True, slots=True)
class SafetyState(Message):
    """Watchdog's view of one arm (``safety/<arm>/state``), on change and at a low rate."""

    arm: str = fld("", "slave arm id", nonempty=True)
    state: str = fld("HOLD", "`OK` / `DEGRADED` / `HOLD` / `ESTOP`", choices=SAFETY_STATES)
    causes: tuple[str, ...] = fld((), "human-readable causes of a non-OK state")
    scale: float = fld(
        1.0,
        "motion-scale factor the mapping must apply (1 when OK; reduced while DEGRADED by the "
        "latency budget)",
        ge=0.0,
        le=1.0,
    )
    latency_p50_ms: float = fld(
        0.0,
        "median master → watchdog latency of the arm's command path over the last window (0 while unknown)",
        unit="ms",
        ge=0.0,
    )
    latency_p90_ms: float = fld(0.0, "90th percentile of that latency", unit="ms", ge=0.0)
    latency_p99_ms: float = fld(0.0, "99th percentile of that latency", unit="ms", ge=0.0)
    latency_samples: int = fld(0, "latency samples in that window")
    clock_offset_ms: float = fld(
        0.0,
        "the master host's clock minus the watchdog's, estimated over the bus (clock probes); the "
        "latency above is corrected by it (0 while unknown)",
        unit="ms",
    )


ESTOP_ACTIONS = frozenset({"estop", "reset"})


@message("estop")
@dataclass(frozen=True, slots=True)
class EStop(Message):
    """Emergency stop or its reset (``estop``), from the console or any service.

    The watchdog and slave_control both latch an e-stop: the arm holds until an explicit
    ``reset`` and then a new engage.
    """

    arm: str = fld("*", 'arm id, or `"*"` for every arm of the site', nonempty=True)
    action: str = fld("estop", "`estop` or `reset`", choices=ESTOP_ACTIONS)
    reason: str = fld("", 'who / why, shown in events (e.g. `"console: operator"`)')

    def applies_to(self, arm: str) -> bool:
        """True if this command is for ``arm``."""
        return self.arm in ("*", arm)


EVENT_SEVERITIES = frozenset({"info", "warning", "error"})


@message("event")
@dataclass(frozen=True, slots=True)
class SafetyEvent(Message):
    """A discrete event worth a line in the log (``events/<service>``)."""

    SEVERITIES: ClassVar[frozenset[str]] = EVENT_SEVERITIES

    arm: str = fld("", 'arm id the event concerns (`""` for system-wide)')
    kind: str = fld(
        "", 'short machine-readable tag, e.g. `"transition"`, `"ik_failure"`, `"engage"`', nonempty=True
    )
    severity: str = fld("info", "`info` / `warning` / `error`", choices=EVENT_SEVERITIES)
    text: str = fld("", "human-readable description including the cause")


@message("heartbeat")
@dataclass(frozen=True, slots=True)
class Heartbeat(Message):
    """Periodic service heartbeat (``heartbeat/<service>``), 2 Hz."""

    service: str = fld("", "service instance id", nonempty=True)
    uptime_s: float = fld(0.0, "time since the service started (monotonic clock)", unit="s", ge=0.0)
    rejected: int = fld(0, "messages this service's strict decoder rejected so far (all keys)")
    polled_s: float = fld(
        -1.0,
        "time since the service's loop last took in its buffered streams (-1: it buffers none); "
        "a count above is final for what was sent before then",
        unit="s",
        ge=-1.0,
    )
    replayed: int = fld(
        0,
        "of ``rejected``, those the freshness rules refused (replayed, or late: a receiver that "
        "fell behind sees its oldest messages too old)",
        ge=0,
    )
    lost: int = fld(0, "sequence numbers this service's subscriptions never saw so far (all keys)", ge=0)


@message("clock_probe")
@dataclass(frozen=True, slots=True)
class ClockProbe(Message):
    """A clock probe (query on ``echo/<service>``): its header ``ts`` is when it left (NTP's t1)."""


@message("clock_reply")
@dataclass(frozen=True, slots=True)
class ClockReply(Message):
    """The answer to a :class:`ClockProbe` (``shared/clock.py``), on the responder's clock."""

    probe_ns: int = fld(0, "the probe's `ts`, echoed (t1, the prober's clock)", unit="ns")
    received_ns: int = fld(0, "when the probe arrived (t2)", unit="ns")
    sent_ns: int = fld(0, "when this answer left (t3)", unit="ns")


def _key_value_args(args: tuple[str, ...]) -> None:
    for a in args:
        if "=" not in a:
            raise MessageError(f"field 'args' entry {a!r} must look like key=value")


@message("command")
@dataclass(frozen=True, slots=True)
class Command(Message):
    """An operator command to one arm, sent as a zenoh query to ``slave/<arm>/command``."""

    arm: str = fld("", "arm id the command is for", nonempty=True)
    name: str = fld(
        "",
        "command name (e.g. `teach_trocar`, `insert`, `jog`)",
        nonempty=True,
        pattern=r"[a-z][a-z0-9_]{0,63}",
    )
    args: tuple[str, ...] = fld(
        (),
        '`key=value` strings (e.g. `("frame=forceps", "axis=x", "direction=1")`); the handler parses '
        "and validates them",
        max_len=16,
        check=_key_value_args,
        check_doc="each `key=value`",
    )

    def arg_map(self) -> dict[str, str]:
        """``args`` as a dict (a repeated key keeps the last value)."""
        return dict(a.split("=", 1) for a in self.args)


@message("command_reply")
@dataclass(frozen=True, slots=True)
class CommandReply(Message):
    """The answer to a :class:`Command`: accepted, or refused with the reason."""

    arm: str = fld("", "arm id")
    name: str = fld("", "the command answered")
    accepted: bool = fld(False, "true if the command was carried out (or started)")
    reason: str = fld("", 'why it was refused (`""` when accepted), or a short note')
    confirm: str = fld(
        "",
        "a motion-starting command's confirmation token (refused with `confirm required`): send the "
        'same command again with `confirm=<token>` added to carry it out (`""` otherwise)',
        pattern=r"[0-9a-f]{0,32}",
    )


#: The teleop states of one master → slave pair (:class:`TeleopState`, services/mapping/engage.py).
TELEOP_STATES = frozenset({"DISABLED", "IDLE", "ENGAGING", "ENABLED", "HOLDING"})


@message("teleop_state")
@dataclass(frozen=True, slots=True)
class TeleopState(Message):
    """The mapping's teleop state of one pair (``mapping/<slave arm>/teleop_state``), at 10 Hz
    and on every change; the mapping also answers a query on the key with the current state."""

    master: str = fld("", "master arm id of the pair", nonempty=True)
    slave: str = fld("", "slave arm id of the pair (the `<arm>` of the key)", nonempty=True)
    state: str = fld(
        "DISABLED",
        "`DISABLED` (a press would be refused: operator absent, slave not allowed to move, no fresh "
        "slave joints), `IDLE` (clutch released, ready), `ENGAGING` (a new press seen: the engage "
        "is tried at the next master sample), `ENABLED` (the slave follows the master), `HOLDING` "
        "(clutch pressed but not following: a disengage the operator did not make, a refused "
        "engage, or the pedal was down at start; release and press)",
        choices=TELEOP_STATES,
    )
    previous: str = fld(
        "DISABLED",
        "the state before `state` (equal to `state` before the first change)",
        choices=TELEOP_STATES,
    )
    reason: str = fld(
        "",
        "why the pair is in `state` (e.g. `slave holding: lease expired`); it may change within a "
        "state (a DISABLED pair's hold reason), `since_ns` then stays",
    )
    since_ns: int = fld(
        0, "wall-clock time `state` was entered, since the Unix epoch", unit="ns", le=_I64_MAX
    )
    scale: float = fld(
        1.0,
        "the operator's motion scale in use (changed by `set_scale` / `scale_up` / `scale_down`)",
        gt=0.0,
        le=2.0,
    )
    safety_scale: float = fld(1.0, "the watchdog's motion-scale factor applied on top of it", ge=0.0, le=1.0)
    mode: str = fld(
        "cartesian", "the mapping mode, e.g. `cartesian`, `all_joints`, `vip`, `position`", nonempty=True
    )
    rotation: tuple[float, float, float, float] = fld(
        (0.0, 0.0, 0.0, 1.0),
        "`R_ms`, the rotation from the master's frame to the slave's base frame that the mapping "
        "moves the slave with (the camera's view or the work frame), `[x, y, z, w]`; identity for a "
        "joint-space mapping. A haptic master renders the slave's force through its transpose",
        unit_quat=True,
    )
    limit_wall: tuple[float, float, float, float] = fld(
        (0.0, 0.0, 0.0, 0.0),
        "the slave's nearest joint limit as a wall in the master's frame, `[nx, ny, nz, d]`: the "
        "master point may move where `n·x ≤ d` before a slave joint comes within the mapping's "
        "`limit_wall_margin_deg` of its limit (linearised at the current pose, refreshed with the "
        "state); a haptic master renders it as a wall (docs/haptics.md). All zero: none near (no "
        "limit within 50 mm of master motion, not following, or a mapping without one)",
    )


#: Encodings of :class:`CameraImage` (``jpeg``: baseline JPEG, 8-bit RGB or grey, on
#: ``camera/<cam>/image``; ``h264``: one H.264 access unit, Annex B, on ``camera/<cam>/video``).
IMAGE_ENCODINGS = frozenset({"jpeg", "h264"})
#: Image layouts: ``mono``, or ``stereo_sbs`` (left eye in the left half, right eye in the right).
IMAGE_LAYOUTS = frozenset({"mono", "stereo_sbs"})


@message("camera_image")
@dataclass(frozen=True, slots=True)
class CameraImage(Message):
    """One encoded camera frame (``camera/<cam>/image``), at the camera's rate; newest wins.

    A bulk type on its own key: accepted only by ``decode_as(payload, CameraImage)``, up to
    ``MAX_IMAGE_PAYLOAD_BYTES`` (:func:`decode` refuses it: it allows no bin values). The
    intrinsics are a pinhole model of one eye in pixels, in the OpenCV convention of the pose on
    ``camera/<cam>/measured_cp`` (x right, y down, z along the view): a point ``(x, y, z)`` of
    the camera frame lands at ``u = fx·x/z + cx``, ``v = fy·y/z + cy`` (right eye of a stereo
    pair: the same, ``baseline_m`` along +x, in the right half of the image)."""

    MAX_PAYLOAD: ClassVar[int] = MAX_IMAGE_PAYLOAD_BYTES
    MAX_BIN: ClassVar[int] = MAX_IMAGE_BYTES

    camera: str = fld("", "camera id (the `<cam>` of the key)", nonempty=True)
    capture_ns: int = fld(
        0,
        "wall-clock time the picture was taken (render: the slave state it shows was received; a "
        "real camera: the frame was read), since the Unix epoch; age = arrival − `capture_ns`",
        unit="ns",
        le=_I64_MAX,
    )
    width: int = fld(0, "image width (whole image: both eyes of a stereo pair)", unit="px", ge=1, le=8192)
    height: int = fld(0, "image height", unit="px", ge=1, le=8192)
    encoding: str = fld("jpeg", "encoding of `data`", choices=IMAGE_ENCODINGS)
    layout: str = fld("mono", "`mono` or `stereo_sbs` (side by side, left eye left)", choices=IMAGE_LAYOUTS)
    baseline_m: float = fld(0.0, "stereo baseline (0 for mono)", unit="m", ge=0.0, le=1.0)
    fx: float = fld(1.0, "focal length along x, one eye", unit="px", gt=0.0, le=1e6)
    fy: float = fld(1.0, "focal length along y", unit="px", gt=0.0, le=1e6)
    cx: float = fld(0.0, "principal point x, one eye", unit="px", ge=-1e5, le=1e5)
    cy: float = fld(0.0, "principal point y", unit="px", ge=-1e5, le=1e5)
    render_ms: float = fld(
        0.0,
        "time to produce the picture (render, or read and decode a real camera's frame)",
        unit="ms",
        ge=0.0,
    )
    encode_ms: float = fld(0.0, "time to encode it", unit="ms", ge=0.0)
    dropped: int = fld(0, "frames the camera dropped so far (not sent: the next was due, or stale)")
    data: bytes = fld(
        b"\xff\xd8\xff\xd9",
        "the encoded image (default: an empty JPEG, start and end markers)",
        nonempty=True,
        max_len=MAX_IMAGE_BYTES,
    )


VIDEO_STATES = frozenset({"OK", "DEGRADED", "HOLD", "OFF"})


@message("video_state")
@dataclass(frozen=True, slots=True)
class VideoState(Message):
    """The watchdog's view of the video an arm is driven by (``safety/<arm>/video``), with each
    ``safety_state``: the frame age from capture to arrival at the watchdog, and its verdict."""

    arm: str = fld("", "slave arm id", nonempty=True)
    camera: str = fld("", "camera id watched", nonempty=True)
    state: str = fld(
        "OFF",
        "`OK` (fresh), `DEGRADED` (stale or over the age budget: scale reduced), `HOLD` (beyond "
        "the hard limit), `OFF` (no video required for this arm)",
        choices=VIDEO_STATES,
    )
    since_frame_ms: float = fld(
        0.0, "time since the last frame arrived (0 before the first)", unit="ms", ge=0.0
    )
    age_ms: float = fld(
        0.0, "age of the last frame at its arrival (arrival − `capture_ns`)", unit="ms", ge=0.0
    )
    age_p50_ms: float = fld(0.0, "median frame age over the last window (0 while unknown)", unit="ms", ge=0.0)
    age_p99_ms: float = fld(0.0, "99th percentile of that age", unit="ms", ge=0.0)
    fps: float = fld(0.0, "frames per second arrived over that window", unit="1/s", ge=0.0)
    frames: int = fld(0, "frames received since start")
    gaps: int = fld(0, "frames missing in the sequence since start (dropped by the camera or the link)")


@message("video_feedback")
@dataclass(frozen=True, slots=True)
class VideoFeedback(Message):
    """A viewer's report on a camera's H.264 stream (``camera/<cam>/video_feedback``, 2 Hz and at
    once when it needs a keyframe): the camera adapts its bitrate to it (shared/video.py)."""

    camera: str = fld("", "camera id (the `<cam>` of the key)", nonempty=True)
    frames: int = fld(0, "frames received since the last report", ge=0, le=100_000)
    lost: int = fld(0, "frames missing in the sequence since the last report", ge=0, le=100_000)
    kbps: float = fld(0.0, "bitrate received since the last report", unit="kbit/s", ge=0.0, le=1e6)
    age_p50_ms: float = fld(
        0.0, "median frame age at arrival since the last report (0: none arrived)", unit="ms", ge=0.0, le=1e6
    )
    keyframe: bool = fld(False, "the viewer needs a keyframe (it lost a frame, or just started)")


TRIAL_PHASES = frozenset({"setup", "ready", "running", "done", "failed"})


@message("trial_state")
@dataclass(frozen=True, slots=True)
class TrialState(Message):
    """The current trial of a study (``study/trial``, from ``telesurg study``: 4 Hz and on change):
    what the operator's console shows — the task, its instructions, the trial's clock and, at the
    end, its score. In a blinded study ``condition`` is the trial's code, never the condition."""

    trial: int = fld(0, "the trial's number, 1-based (0: none)", ge=0, le=100_000)
    trials: int = fld(0, "trials in the participant's schedule", ge=0, le=100_000)
    task: str = fld("", "the task's registered name (`mh3f-targets`)")
    instructions: str = fld("", "what the operator is told")
    condition: str = fld("", "the condition as the operator may see it: its code when blinded")
    practice: bool = fld(False, "a practice trial (not scored)")
    phase: str = fld(
        "setup",
        "`setup` (the site starts, the arm is set up), `ready` (press the clutch to start), "
        "`running` (the clock runs while the slave follows), `done`, `failed`",
        choices=TRIAL_PHASES,
    )
    elapsed_s: float = fld(0.0, "the trial's clock: time following since the go", unit="s", ge=0.0, le=1e6)
    time_limit_s: float = fld(0.0, "the task's time limit (of time following)", unit="s", ge=0.0, le=1e6)
    goals_reached: int = fld(0, "goals reached so far, in order", ge=0, le=10_000)
    goals: int = fld(0, "the task's goals", ge=0, le=10_000)
    result: str = fld("", 'the score at the end, one line (`""` before)')
    goal_points: tuple[float, ...] = fld(
        (),
        "the goals' positions in order, x y z each (the slave's base frame): the console draws them",
        unit="m",
    )


@message("scene_state")
@dataclass(frozen=True, slots=True)
class SceneState(Message):
    """What the slave's simulation holds besides the arms (``slave/<arm>/scene``, ~20 Hz, MuJoCo
    scenes with loose objects or jaws): each loose object, who holds it, and whether the
    instruments touch each other. The same message on every arm's key of the slave."""

    objects: tuple[str, ...] = fld(
        (), "the scene's loose objects (MuJoCo bodies with a free joint)", max_len=MAX_OBJECTS
    )
    x: tuple[float, ...] = fld(
        (), "each object's position: x (the slave's base frame)", unit="m", same_len="objects"
    )
    y: tuple[float, ...] = fld((), "… y", unit="m", same_len="objects")
    z: tuple[float, ...] = fld((), "… z", unit="m", same_len="objects")
    held_by: tuple[str, ...] = fld(
        (),
        'per object, the arms whose both jaws touch it, "+"-joined (`"arm1+arm2"` in a hand-over; '
        '`""`: none)',
        same_len="objects",
    )
    jaws: tuple[float, ...] = fld(
        (), "each arm's measured jaw closure in arm order, 0 open … 1 closed (empty: no jaws)", max_len=8
    )
    in_collision: bool = fld(False, "two arms' instruments touch now")
    collisions: int = fld(
        0, "instrument collisions since the slave started (each a new contact between two arms)", ge=0
    )

    def object(self, name: str) -> tuple[tuple[float, float, float], tuple[str, ...]] | None:
        """Object ``name``'s position (m) and the arms that hold it; None if the scene has none."""
        if name not in self.objects:
            return None
        i = self.objects.index(name)
        return (self.x[i], self.y[i], self.z[i]), tuple(a for a in self.held_by[i].split("+") if a)


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
    | ClockProbe
    | ClockReply
    | TeleopState
    | CameraImage
    | VideoState
    | VideoFeedback
    | TrialState
    | SceneState
)


def decode(payload: bytes | bytearray | memoryview) -> AnyMessage:
    """Decode and validate one payload; raise :class:`MessageError` on anything malformed.

    At most :data:`MAX_PAYLOAD_BYTES` and no bin values: a ``camera_image`` is decoded only by
    ``decode_as(payload, CameraImage)``, on its own key."""
    return _decode(payload, MAX_PAYLOAD_BYTES, 0)


def _decode(payload: bytes | bytearray | memoryview, max_payload: int, max_bin: int) -> AnyMessage:
    if len(payload) > max_payload:
        raise MessageError(f"payload is {len(payload)} bytes, limit {max_payload}")
    try:
        d = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_str_len=MAX_STR * 4,
            max_bin_len=max_bin,
            max_array_len=MAX_ARRAY_LEN,
            max_map_len=MAX_MAP_LEN,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises a family of unrelated exception types
        raise MessageError(f"not a valid MessagePack payload: {type(exc).__name__}: {exc}") from None
    if type(d) is not dict:
        raise MessageError(f"payload must be a map, got {type(d).__name__}")
    n = payload[0] - 0x80  # a fixmap (up to 15 keys: every message but the longest)
    if len(d) != (n if 0 <= n <= 15 else _map_len(payload)):
        raise MessageError("duplicate keys in a map")
    version = d.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise MessageError(f"unknown schema version {version!r}, expected {SCHEMA_VERSION}")
    tag = d.get("type")
    from_wire = _DECODERS.get(tag) if type(tag) is str else None
    if from_wire is None:
        raise MessageError(f"unknown message type {tag!r}; valid: {sorted(_REGISTRY)}")
    return from_wire(d)  # type: ignore[return-value]


def decode_any(payload: bytes | bytearray | memoryview) -> AnyMessage:
    """:func:`decode`, or else a ``camera_image`` with its own limits: for readers of every key
    (the recorder, a replay, the fuzzer), which do not know a key's type in advance. A payload the
    small limits refuse (too large, or holding a bin value) is decoded with the image limits, and
    its error is then the image decoder's."""
    try:
        return decode(payload)
    except MessageError as exc:
        if len(payload) <= MAX_PAYLOAD_BYTES and "max_bin_len" not in str(exc):
            raise
    return _decode(payload, MAX_IMAGE_PAYLOAD_BYTES, MAX_IMAGE_BYTES)


def decode_as(payload: bytes | bytearray | memoryview, cls: type[M]) -> M:
    """Decode a payload that must be of type ``cls`` (e.g. on a key that carries one type), with
    the size limits of ``cls`` (``cls.MAX_PAYLOAD``, ``cls.MAX_BIN``: a camera image's own)."""
    msg = _decode(payload, cls.MAX_PAYLOAD, cls.MAX_BIN)
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
