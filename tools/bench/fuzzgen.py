"""Deterministic generator of malformed and adversarial message payloads for fuzzing the decoder.

Bench code (used by the fuzz benchmark and the tests): it depends only on :mod:`random`, msgpack and
the message classes, never on hypothesis. Everything is derived from the message classes at runtime —
:data:`~telesurg.shared.messages.MESSAGE_TYPES`, :meth:`~telesurg.shared.messages.Message.encode`
and ``BODY`` — so fields
added to a message class are fuzzed without touching this module.

Given the same seed (``random.Random(seed)``), the same templates and the same ``n``,
:func:`fuzz_cases` yields the same payloads, in every process (no iteration over sets or hashes).

Kinds (:data:`FUZZ_KINDS`); "always invalid" means :func:`~telesurg.shared.messages.decode` must raise
:class:`~telesurg.shared.errors.MessageError` for every case of that kind derived from a *valid* template
(see :func:`always_invalid`):

=================== ======= ====================================================================
kind                always  what
=================== ======= ====================================================================
random_bytes        no [1]_ 0..200 random bytes
truncated           yes     a valid payload cut short (a strict prefix, possibly empty)
bitflip             no      1–4 random bit flips of a valid payload (may still decode)
wrong_type_field    yes     a header/body field or list element replaced by a value of a type the
                            decoder rejects (str/int/float/bool/None/list/map/bytes; an int is not
                            used for a float field), or a string field holding invalid UTF-8
nonfinite           yes     a float field or a float in a list set to NaN/+inf/-inf (float64 or
                            float32 on the wire); templates without floats get it in another field
huge_number         no      an int/float field or element set to 2**64 (as a float: msgpack has no
                            such integer), 2**64-1, 2**63, -1, -2**63, ±1e308 (fine for unbounded
                            float fields)
missing_field       yes     one required header or body key removed (or the empty map)
extra_field         yes     unknown keys added (another type's body key, case/whitespace
                            variants of header keys, an int key, a bytes key, str and bytes mixed)
bad_version         yes     ``v`` = 0, 2, "1", 1.0, -1, True, None, 2**32, [1], ...
unknown_type        yes     the type tag replaced by an unregistered tag, or by the tag of another
                            registered type (with a different body field set) keeping this body
type_confusion      no      bodies of two types mixed: one body under another's tag, a union of both
                            bodies, shared fields transplanted (e.g. a 6-joint ``position`` into a
                            pose), or a duplicated ``type`` key (the decoder keeps the last one)
oversized           yes     a payload larger than MAX_PAYLOAD_BYTES (padded string, huge array,
                            trailing bytes, random bytes), from MAX_PAYLOAD_BYTES + 1 up
long_string         yes     a string field or string list element longer than MAX_STR characters
                            (ASCII and multi-byte, also beyond the unpacker's byte limit)
long_array          yes     a list longer than its limit (MAX_JOINTS + 1 for joint-space and float
                            lists, else more than max(MAX_JOINTS, MAX_LIST)), up to 1000 elements
not_a_map           yes     top level is an array/int/str/nil/bool/float/bin/ext, a deeply nested
                            array, or two concatenated maps
boundary            no      values right at and just beyond limits: seq/ts 0, 2**63, 2**64-1,
                            2**64; floats 0, ±5e-324, 10000, 10000.0001, ±max; strings of
                            MAX_STR (+1) ASCII/multi-byte chars, empty strings; list lengths 0, 1,
                            n±1, MAX_JOINTS(+1), MAX_LIST(+1); whole joint lists resized together
                            (empty, MAX_JOINTS, MAX_JOINTS + 1); quaternion norms 1 ± 1e-3 (± 1e-9);
                            float32 encoding of every float
=================== ======= ====================================================================

.. [1] random bytes decode as a valid message with negligible probability; not guaranteed.

Example::

    >>> import random
    >>> from telesurg.tools.bench.fuzzgen import FUZZ_KINDS, default_templates, fuzz_cases
    >>> cases = list(fuzz_cases(random.Random(1), default_templates(), 100))
    >>> len(cases), cases[0].kind in FUZZ_KINDS
    (100, True)
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import math
import random
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Final, TypeVar

import msgpack
from telesurg.shared.errors import MessageError
from telesurg.shared.messages import (
    MAX_JOINTS,
    MAX_LIST,
    MAX_PAYLOAD_BYTES,
    MAX_STR,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Header,
    Message,
    decode_any,
)

__all__ = [
    "ALWAYS_INVALID_KINDS",
    "FUZZ_KINDS",
    "FuzzCase",
    "always_invalid",
    "default_templates",
    "fuzz_cases",
    "mutate",
    "valid_template",
]

FUZZ_KINDS: Final[tuple[str, ...]] = (
    "random_bytes",
    "truncated",
    "bitflip",
    "wrong_type_field",
    "nonfinite",
    "huge_number",
    "missing_field",
    "extra_field",
    "bad_version",
    "unknown_type",
    "type_confusion",
    "oversized",
    "long_string",
    "long_array",
    "not_a_map",
    "boundary",
)

#: Kinds for which :func:`~telesurg.shared.messages.decode` must reject every case derived from a valid
#: template.
ALWAYS_INVALID_KINDS: Final[frozenset[str]] = frozenset(
    {
        "truncated",
        "wrong_type_field",
        "nonfinite",
        "missing_field",
        "extra_field",
        "bad_version",
        "unknown_type",
        "oversized",
        "long_string",
        "long_array",
        "not_a_map",
    }
)

M = TypeVar("M", bound=Message)
Wire = dict[Any, Any]

#: Protocol header keys (the wire format, not message-class fields).
_V, _TYPE = "v", "type"
#: Timestamp of template headers: fixed, so templates (and cases) are reproducible.
_TEMPLATE_TS = 1_700_000_000_000_000_000
_NAN, _INF = float("nan"), float("inf")
_FLOAT_MAX = sys.float_info.max
_RANDOM_BYTES_MAX = 200
_PACKED_FLOAT: bytes = msgpack.packb(0.1)

# Value pools. Lists and maps in pools are shared between cases and never mutated.
_EXAMPLES: dict[str, tuple[Any, ...]] = {
    "str": ("fuzz", "", "1", "j1", "nan"),
    "int": (0, 1, -7, 2**40),
    "float": (0.5, -2.25, 1.0),
    "bool": (True, False),
    "none": (None,),
    "list": ([], [1, 2], ["j1"], [[0.0]], [None]),
    "map": ({}, {"a": 1}, {_V: SCHEMA_VERSION, _TYPE: "pose"}),
    "bytes": (b"", b"\x00\x01"),
}
_CATEGORIES: tuple[str, ...] = tuple(_EXAMPLES)
#: Value categories the decoder accepts for a field whose valid value has the given category.
_ACCEPTS: dict[str, frozenset[str]] = {c: frozenset({c}) for c in _CATEGORIES} | {
    "float": frozenset({"int", "float"}),
    "other": frozenset(),
}
_NONFINITE: tuple[float, ...] = (_NAN, _INF, -_INF)
_HUGE: tuple[Any, ...] = (2.0**64, 2**64 - 1, 2**63, -1, -(2**63), 1e308, -1e308)
_BAD_VERSIONS: tuple[Any, ...] = tuple(
    v
    for v in (
        0,
        1,
        2,
        "1",
        "2",
        1.0,
        2.0,
        -1,
        True,
        None,
        2**32,
        [1],
        1.5,
        "v1",
        SCHEMA_VERSION + 1,
        SCHEMA_VERSION - 1,
    )
    if not (type(v) is int and v == SCHEMA_VERSION)
)
_INT_BOUNDARY: tuple[Any, ...] = (0, 1, 2**63 - 1, 2**63, 2**64 - 1, 2.0**64, -1)
_FLOAT_BOUNDARY: tuple[Any, ...] = (
    0.0,
    -0.0,
    5e-324,
    -5e-324,
    sys.float_info.min,
    1e-9,
    1.0,
    -1.0,
    10_000.0,
    10_000.0001,
    math.nextafter(10_000.0, _INF),
    0,
    10_000,
    10_001,
    2**64 - 1,
    _FLOAT_MAX,
    -_FLOAT_MAX,
)
_STR_BOUNDARY: tuple[str, ...] = (
    "",
    " ",
    "\x00",
    "x" * MAX_STR,
    "x" * (MAX_STR + 1),
    "é" * MAX_STR,
    "€" * MAX_STR,
    "😀" * MAX_STR,
    "😀" * (MAX_STR + 1),
)
_LONG_STR_LENGTHS: tuple[int, ...] = (
    MAX_STR + 1,
    MAX_STR + 2,
    2 * MAX_STR,
    4 * MAX_STR,
    4 * MAX_STR + 1,
    3000,
)
#: Strings longer than MAX_STR: ASCII and 2-, 3-, 4-byte UTF-8 (built once; msgpack reuses their UTF-8).
_LONG_STRINGS: tuple[str, ...] = tuple(c * n for c in ("x", "é", "€", "😀") for n in _LONG_STR_LENGTHS)
#: Longer than any list limit; MAX_JOINTS * 4 is the unpacker's array limit (+1 fails in msgpack).
_LONG_ARRAY: tuple[int, ...] = (
    max(MAX_JOINTS, MAX_LIST) + 1,
    MAX_JOINTS * 4,
    MAX_JOINTS * 4 + 1,
    300,
    1000,
)
_EXTRA_KEYS: tuple[Any, ...] = ("extra", "x", "", "V", "Type", "v ", " type", "seq\x00", "header", "body")
_BAD_UTF8: tuple[bytes, ...] = (b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"abc\x80", b"\xf8\x88\x80\x80\x80")
_NOT_A_MAP_SCALARS: tuple[Any, ...] = (0, 1, -1, "", "joint_state", None, True, False, 1.5, b"", b"\x81")

# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class FuzzCase:
    """One generated payload.

    Attributes:
        kind: one of :data:`FUZZ_KINDS`.
        payload: the bytes to feed to the decoder.
        template: ``TYPE`` of the message the payload was derived from ("" for random bytes).
    """

    kind: str
    payload: bytes
    template: str


def always_invalid(kind: str) -> bool:
    """Whether every case of ``kind`` derived from a valid template must be rejected by the decoder.

    Args:
        kind: one of :data:`FUZZ_KINDS`.

    Returns:
        True for kinds that can never decode (e.g. ``truncated``, ``nonfinite``, ``oversized``); False
        for kinds that may decode (``bitflip``, ``boundary``, ``huge_number``, ``type_confusion``, and
        ``random_bytes``, which almost never does).

    Raises:
        ValueError: ``kind`` is not in :data:`FUZZ_KINDS`.
    """
    if kind not in _KIND_SET:
        raise ValueError(f"unknown fuzz kind {kind!r}; valid: {list(FUZZ_KINDS)}")
    return kind in ALWAYS_INVALID_KINDS


def valid_template(cls: type[M], *, source: str = "fuzz", seq: int = 0, n_joints: int = 6) -> M:
    """A valid instance of a message class with plausible values.

    Field values are chosen from each dataclass field's annotation (joint names ``j1..jN``, ``N``
    joint values, a unit quaternion, ``True`` flags, small counts, ...); string fields keep a
    non-empty default (enumerations). Fields the decoder still rejects are repaired from the
    decoder's error (class default, the first listed option, a generic value), so fields added to a
    message class need no change here.

    Args:
        cls: a registered message class (a value of :data:`~telesurg.shared.messages.MESSAGE_TYPES`).
        source: header source id (must be non-empty).
        seq: header sequence number.
        n_joints: joint count of joint-space fields, 1..MAX_JOINTS (joint lists may not be empty).

    Returns:
        The decoded message (so ``decode(t.encode()) == t``).

    Raises:
        ValueError: ``cls`` is not a registered message class, an argument is out of range, or no
            valid instance could be built.
    """
    if not isinstance(cls, type) or MESSAGE_TYPES.get(getattr(cls, "TYPE", "")) is not cls:
        raise ValueError(f"{cls!r} is not a registered message class; valid: {sorted(MESSAGE_TYPES)}")
    if not 1 <= n_joints <= MAX_JOINTS:
        raise ValueError(f"n_joints={n_joints} outside [1, {MAX_JOINTS}]")
    header = Header(source, seq, _TEMPLATE_TS)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name == "header" or not f.init:
            continue
        value = _plausible(f, n_joints, source)
        if value is not _KEEP:
            kwargs[f.name] = value
    try:
        wire: Wire = msgpack.unpackb(cls(header, **kwargs).encode(), raw=False)
    except Exception as exc:
        raise ValueError(f"cannot build a {cls.__name__}: {type(exc).__name__}: {exc}") from None
    try:
        default_wire: Wire = msgpack.unpackb(cls(header).encode(), raw=False)
    except Exception:
        default_wire = {}
    return _repair(cls, wire, default_wire)


def default_templates(*, source: str = "fuzz", n_joints: int = 6) -> tuple[Message, ...]:
    """One :func:`valid_template` per registered message type, in registration order.

    Args:
        source: header source id.
        n_joints: joint count of joint-space fields.

    Returns:
        The templates.

    Raises:
        ValueError: as :func:`valid_template`.
    """
    return tuple(valid_template(c, source=source, n_joints=n_joints) for c in MESSAGE_TYPES.values())


def fuzz_cases(
    rng: random.Random, templates: Sequence[Message], n: int, kinds: Sequence[str] = FUZZ_KINDS
) -> Iterator[FuzzCase]:
    """Generate ``n`` fuzz cases from valid templates.

    Kinds are dealt in shuffled rounds of ``kinds`` (every kind appears once per ``len(kinds)``
    cases); each case uses a template drawn at random. Arguments are checked when this function is
    called; the iteration itself never raises.

    Args:
        rng: the only source of randomness; the same seed gives the same cases.
        templates: valid messages to derive payloads from (e.g. :func:`default_templates`); empty
            means :func:`default_templates`. ``type_confusion`` also borrows bodies of registered
            types missing from ``templates``.
        n: number of cases.
        kinds: kinds to generate, a subset of :data:`FUZZ_KINDS`.

    Returns:
        An iterator of :class:`FuzzCase`.

    Raises:
        ValueError: ``n < 0``, ``kinds`` empty or not in :data:`FUZZ_KINDS`, or a template that
            cannot be encoded.
    """
    kinds_t = tuple(kinds)
    if not kinds_t or any(k not in _KIND_SET for k in kinds_t):
        raise ValueError(f"kinds must be a non-empty subset of {list(FUZZ_KINDS)}, got {list(kinds_t)}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    infos: list[_Info] = []
    for t in templates:
        try:
            info = _info_for(t.encode())
        except Exception as exc:
            raise ValueError(f"template {t!r} cannot be encoded: {exc}") from None
        if info is not None:
            infos.append(info)
    if not infos:
        infos = list(_default_infos())
    return _generate(rng, _Gen(infos), infos, n, kinds_t)


def mutate(rng: random.Random, payload: bytes, kinds: Sequence[str] = FUZZ_KINDS) -> tuple[str, bytes]:
    """Apply one random mutation to a payload (normally a valid one).

    A payload that is not a MessagePack map gets only byte-level mutations (``random_bytes``,
    ``truncated``, ``bitflip``, ``oversized``, ``not_a_map``). Never raises for any input bytes. The
    "always invalid" guarantees of :func:`always_invalid` hold for valid input payloads.

    Args:
        rng: source of randomness.
        payload: the payload to mutate.
        kinds: kinds to choose from (default all); kinds not applicable to the payload are skipped.

    Returns:
        ``(kind, mutated payload)``.
    """
    payload = bytes(payload)
    info = _info_for(payload) or _raw_info(payload)
    candidates = [k for k in kinds if k in _KIND_SET and _applicable(k, info)] or ["random_bytes"]
    kind = candidates[rng.randrange(len(candidates))]
    return _gen_for_mutate().case_bytes(rng, kind, info)


# --------------------------------------------------------------------------- templates

_KIND_SET: Final[frozenset[str]] = frozenset(FUZZ_KINDS)
_BYTE_KINDS: Final[frozenset[str]] = frozenset(
    {"random_bytes", "truncated", "bitflip", "oversized", "not_a_map"}
)
_KEEP: Final = object()
_QUOTED = re.compile(r"'([^']*)'")
_OPTIONS = re.compile(r"not one of (\[.*\])")
_NUMBERS = re.compile(r"\b(\d+)\b")
#: Set by tests: re-raise generator bugs instead of falling back to a truncated payload.
_STRICT = False


def _unit_quaternion() -> tuple[float, float, float, float]:
    q = (0.1, -0.2, 0.3, 0.9)
    norm = math.sqrt(sum(x * x for x in q))
    return (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)


def _plausible(f: dataclasses.Field[Any], n_joints: int, source: str) -> Any:
    """A plausible value for one dataclass field, from its annotation and name, or ``_KEEP``."""
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    t = t.replace(" ", "").replace("typing.", "")
    name = f.name.lower()
    default: Any = f.default
    factory = f.default_factory
    if default is dataclasses.MISSING and callable(factory):
        default = factory()
    if t == "bool":
        return True
    if t == "int":
        return _TEMPLATE_TS - 1_000_000 if name.endswith("_ns") else 3
    if t == "float":
        return 200.0 if name.endswith("_ms") else 12.5
    if t == "str":
        hints = {"arm": "psm1", "kind": "transition", "frame": "base", "service": source, "reason": ""}
        if name in hints:
            return hints[name]
        return default if isinstance(default, str) and default else f"{name} text"
    if t == "tuple[str,...]":
        if "name" in name or "joint" in name:
            return tuple(f"j{i + 1}" for i in range(n_joints))
        return default if default else (f"{name} 1", f"{name} 2")
    if t == "tuple[float,...]":
        return tuple(round(0.1 * (i + 1) * (-1) ** i, 6) for i in range(n_joints))
    fixed = re.fullmatch(r"tuple\[float(?:,float)*\]", t)
    if fixed:
        k = t.count("float")
        if k == 4:
            return _unit_quaternion()
        return tuple(round(0.05 * (i + 1) * (-1) ** i, 6) for i in range(k))
    return _KEEP


def _alternatives(value: Any, default: Any, error: str) -> list[Any]:
    """Candidate replacements for a field the decoder rejected."""
    out: list[Any] = []
    if default is not _KEEP and default != value:
        out.append(default)
    options = _OPTIONS.search(error)
    if options:
        try:
            parsed = ast.literal_eval(options.group(1))
        except (ValueError, SyntaxError):
            parsed = []
        if isinstance(parsed, list) and parsed:
            out.append(parsed[0])
    numbers = [int(x) for x in _NUMBERS.findall(error)]
    if isinstance(value, list):
        out.extend([0.0] * k for k in numbers if 0 < k <= MAX_JOINTS)
        out.extend(([], [0.0, 0.0, 0.0, 1.0]))
    elif isinstance(value, bool):
        out.extend((False, True))
    elif isinstance(value, int):
        out.extend((0, 1))
    elif isinstance(value, float):
        out.extend((1.0, 0.5, 100.0, 0.0))
    else:
        out.extend(("x", "", 1.0, 0))
    return out


def _blamed_key(error: str, wire: Wire) -> Any:
    for quoted in _QUOTED.findall(error):
        if quoted in wire:
            return quoted
    return None


def _repair(cls: type[M], wire: Wire, default_wire: Wire) -> M:
    """Decode ``wire``; while the decoder blames a body field, try alternatives for it."""
    body_keys = cls.BODY
    for _ in range(4 * (len(wire) + 2)):
        try:
            msg = decode_any(msgpack.packb(wire))
        except MessageError as exc:
            error = str(exc)
            key = _blamed_key(error, wire)
            if key is None or key not in body_keys:
                raise ValueError(f"cannot build a valid {cls.__name__}: {error}") from None
            for candidate in _alternatives(wire[key], default_wire.get(key, _KEEP), error):
                trial = dict(wire)
                trial[key] = candidate
                try:
                    decode_any(msgpack.packb(trial))
                except MessageError as exc2:
                    if _blamed_key(str(exc2), trial) == key:
                        continue
                wire = trial
                break
            else:
                raise ValueError(f"cannot build a valid {cls.__name__}: {error}") from None
            continue
        if not isinstance(msg, cls):
            raise ValueError(f"{cls.__name__} template decoded as {type(msg).__name__}")
        return msg
    raise ValueError(f"cannot build a valid {cls.__name__}: repair did not converge")


# --------------------------------------------------------------------------- payload analysis


def _category(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    if isinstance(value, str):
        return "str"
    if isinstance(value, (bytes, bytearray)):
        return "bytes"
    if isinstance(value, (list, tuple)):
        return "list"
    if isinstance(value, dict):
        return "map"
    return "other"


def _element_category(values: Sequence[Any]) -> str:
    cats = {_category(x) for x in values}
    if cats and cats <= {"int", "float"}:
        return "float"
    if cats == {"str"}:
        return "str"
    return ""


Slot = tuple[Any, int]  # (key, -1) for a scalar field, (key, i) for element i of a list field


@dataclass(slots=True)
class _Info:
    """A template payload analysed once, so each case costs a dict copy and one ``packb``."""

    tag: str
    payload: bytes
    wire: Wire | None
    keys: tuple[Any, ...] = ()
    required: tuple[Any, ...] = ()  # keys a message must have (not a field added later)
    body_keys: tuple[Any, ...] = ()
    allowed: frozenset[Any] = frozenset()
    cat: dict[Any, str] = dataclasses.field(default_factory=dict)
    elem: dict[Any, str] = dataclasses.field(default_factory=dict)
    type_slots: tuple[Slot, ...] = ()
    str_slots: tuple[Slot, ...] = ()
    str_keys: tuple[Any, ...] = ()
    float_slots: tuple[Slot, ...] = ()
    int_keys: tuple[Any, ...] = ()
    list_keys: tuple[Any, ...] = ()
    scalar_keys: tuple[Any, ...] = ()
    quat_keys: tuple[Any, ...] = ()
    joint_group: tuple[Any, ...] = ()
    extra_keys: tuple[Any, ...] = ()
    boundary: tuple[str, ...] = ()
    packed_keys: dict[Any, bytes] = dataclasses.field(default_factory=dict)
    packed_values: dict[Any, bytes] = dataclasses.field(default_factory=dict)
    #: Packed resized lists by (key, length): long lists cost a lookup, not a pack.
    arrays: dict[tuple[Any, int], bytes] = dataclasses.field(default_factory=dict)

    def raw_map(self, replace: dict[Any, bytes]) -> bytes:
        """This map with the values of some keys replaced by already-packed bytes.

        Args:
            replace: packed value by key, for keys of this map.

        Returns:
            The packed map, keys in the template's order.
        """
        pv = self.packed_values
        return _map_header(len(pv)) + b"".join(
            pk + (replace[k] if k in replace else pv[k]) for k, pk in self.packed_keys.items()
        )


def _raw_info(payload: bytes) -> _Info:
    return _Info(tag="", payload=payload, wire=None)


def _applicable(kind: str, info: _Info) -> bool:
    """Whether ``kind`` can mutate this payload (all kinds can mutate a valid message)."""
    if kind in ("truncated", "bitflip"):
        return bool(info.payload)
    if info.wire is None:
        return kind in _BYTE_KINDS
    if kind == "wrong_type_field":
        return bool(info.type_slots)
    if kind == "huge_number":
        return bool(info.int_keys or info.float_slots)
    if kind in ("nonfinite", "long_array"):
        return bool(info.keys)
    return True


@lru_cache(maxsize=1)
def _header_keys() -> frozenset[str]:
    """Header keys of the wire format, from an encoded default message of any registered type."""
    for cls in MESSAGE_TYPES.values():
        try:
            wire = msgpack.unpackb(cls(Header("fuzz", 0, 0)).encode(), raw=False)
        except Exception:
            continue
        return frozenset(k for k in wire if k not in cls.BODY)
    return frozenset({_V, _TYPE, "src", "seq", "ts"})


@lru_cache(maxsize=1)
def _all_body_keys() -> tuple[str, ...]:
    keys: dict[str, None] = {}
    for cls in MESSAGE_TYPES.values():
        for k in sorted(cls.BODY):
            keys.setdefault(k, None)
    return tuple(keys)


_INFO_CACHE: dict[bytes, _Info | None] = {}
_INFO_CACHE_MAX = 1024


def _info_for(payload: bytes) -> _Info | None:
    """Analyse a payload (cached); None if it is not a MessagePack map."""
    try:
        return _INFO_CACHE[payload]
    except KeyError:
        pass
    info = _analyse(payload)
    if len(_INFO_CACHE) >= _INFO_CACHE_MAX:
        _INFO_CACHE.clear()
    _INFO_CACHE[payload] = info
    return info


def _analyse(payload: bytes) -> _Info | None:
    with contextlib.suppress(Exception):
        # A valid payload is re-encoded canonically (floats as floats) so field categories are exact.
        payload = decode_any(payload).encode()
    try:
        wire = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:
        return None
    if not isinstance(wire, dict):
        return None
    tag = wire.get(_TYPE)
    tag = tag if isinstance(tag, str) else ""
    cls = MESSAGE_TYPES.get(tag)
    header = _header_keys()
    keys = tuple(wire)
    # a field added to the type later may be absent (an older recording's message decodes)
    optional = {f.wire for f in cls.FIELDS if f.absent} if cls is not None else set()
    allowed = frozenset(keys) | header | (cls.BODY if cls is not None else frozenset())
    cat = {k: _category(v) for k, v in wire.items()}
    elem = {k: _element_category(v) for k, v in wire.items() if cat[k] == "list"}
    list_keys = tuple(k for k in keys if cat[k] == "list")
    scalar_keys = tuple(k for k in keys if cat[k] != "list")
    element_slots = tuple((k, i) for k in list_keys if elem[k] for i in range(len(wire[k])))
    str_slots = tuple((k, -1) for k in scalar_keys if cat[k] == "str") + tuple(
        s for s in element_slots if elem[s[0]] == "str"
    )
    float_slots = tuple((k, -1) for k in scalar_keys if cat[k] == "float") + tuple(
        s for s in element_slots if elem[s[0]] == "float"
    )
    quat_keys = tuple(
        k
        for k in list_keys
        if elem[k] == "float" and len(wire[k]) == 4 and abs(math.hypot(*wire[k]) - 1.0) < 1e-6
    )
    # Joint-space lists: two or more lists of one length, at least one of them of strings (names).
    by_len: dict[int, list[Any]] = {}
    for k in list_keys:
        if wire[k]:
            by_len.setdefault(len(wire[k]), []).append(k)
    groups = [g for g in by_len.values() if len(g) >= 2 and any(elem[k] == "str" for k in g)]
    joint_group: tuple[Any, ...] = ()
    for g in groups:
        if len(g) > len(joint_group):
            joint_group = tuple(g)
    int_keys = tuple(k for k in scalar_keys if cat[k] == "int" and k != _V)
    boundary = tuple(
        name
        for name, ok in (
            ("int", int_keys),
            ("float", float_slots),
            ("quat", quat_keys),
            ("str", str_slots),
            ("len", list_keys),
            ("group", joint_group),
            ("f32", float_slots),
        )
        if ok
    )
    return _Info(
        tag=tag,
        payload=payload,
        wire=wire,
        keys=keys,
        required=tuple(k for k in keys if k not in optional),
        body_keys=tuple(k for k in keys if k not in header),
        allowed=allowed,
        cat=cat,
        elem=elem,
        type_slots=tuple((k, -1) for k in keys) + element_slots,
        str_slots=str_slots,
        str_keys=tuple(k for k in scalar_keys if cat[k] == "str"),
        float_slots=float_slots,
        int_keys=int_keys,
        list_keys=list_keys,
        scalar_keys=scalar_keys,
        quat_keys=quat_keys,
        joint_group=joint_group,
        extra_keys=tuple(k for k in (*_EXTRA_KEYS, *_all_body_keys()) if k not in allowed),
        boundary=boundary,
        packed_keys={k: _pack(k) for k in keys},
        packed_values={k: _pack(v) for k, v in wire.items()},
    )


@lru_cache(maxsize=1)
def _default_infos() -> tuple[_Info, ...]:
    """Analysed default templates of every registered type that can be templated."""
    out: list[_Info] = []
    for cls in MESSAGE_TYPES.values():
        try:
            info = _info_for(valid_template(cls).encode())
        except ValueError:
            continue
        if info is not None:
            out.append(info)
    return tuple(out)


# --------------------------------------------------------------------------- packing helpers


def _pack(obj: Any) -> bytes:
    out: bytes = msgpack.packb(obj, use_bin_type=True)
    return out


def _pack_f32(obj: Any) -> bytes:
    """Pack with every float as float32 (float64 if some float is beyond float32 range)."""
    try:
        out: bytes = msgpack.packb(obj, use_bin_type=True, use_single_float=True)
    except OverflowError:
        return _pack(obj)
    return out


def _map_header(n: int) -> bytes:
    if n < 16:
        return bytes((0x80 | n,))
    if n < 0x10000:
        return b"\xde" + n.to_bytes(2, "big")
    return b"\xdf" + n.to_bytes(4, "big")


def _pack_pairs(pairs: Sequence[tuple[Any, bytes]]) -> bytes:
    """A map from (key, already-packed value) pairs; keys may repeat."""
    return _map_header(len(pairs)) + b"".join(_pack(k) + v for k, v in pairs)


def _raw_str(data: bytes) -> bytes:
    """A msgpack str header followed by arbitrary (e.g. invalid UTF-8) bytes."""
    n = len(data)
    if n < 32:
        return bytes((0xA0 | n,)) + data
    if n < 0x100:
        return b"\xd9" + bytes((n,)) + data
    return b"\xda" + n.to_bytes(2, "big") + data


def _set(wire: Wire, slot: Slot, value: Any) -> Wire:
    """A copy of ``wire`` with one field or list element replaced."""
    key, i = slot
    d = dict(wire)
    if i < 0:
        d[key] = value
    else:
        lst = list(d[key])
        lst[i] = value
        d[key] = lst
    return d


def _pick(rng: random.Random, seq: Sequence[Any]) -> Any:
    return seq[rng.randrange(len(seq))]


# --------------------------------------------------------------------------- generator


class _Gen:
    """Mutators over analysed templates; ``others`` supplies bodies of other types."""

    def __init__(self, infos: Sequence[_Info]) -> None:
        by_tag: dict[str, _Info] = {}
        for info in (*infos, *_default_infos()):
            if info.wire is not None and info.tag:
                by_tag.setdefault(info.tag, info)
        self._by_tag = by_tag
        self._others: dict[str, tuple[_Info, ...]] = {}
        self._dispatch: dict[str, Callable[[random.Random, _Info], bytes]] = {
            "random_bytes": self._random_bytes,
            "truncated": self._truncated,
            "bitflip": self._bitflip,
            "wrong_type_field": self._wrong_type_field,
            "nonfinite": self._nonfinite,
            "huge_number": self._huge_number,
            "missing_field": self._missing_field,
            "extra_field": self._extra_field,
            "bad_version": self._bad_version,
            "unknown_type": self._unknown_type,
            "type_confusion": self._type_confusion,
            "oversized": self._oversized,
            "long_string": self._long_string,
            "long_array": self._long_array,
            "not_a_map": self._not_a_map,
            "boundary": self._boundary,
        }

    def case_bytes(self, rng: random.Random, kind: str, info: _Info) -> tuple[str, bytes]:
        """One mutation; on an unexpected generator error, a truncated payload (never raises)."""
        try:
            return kind, self._dispatch[kind](rng, info)
        except Exception:
            if _STRICT:
                raise
            return "truncated", info.payload[: len(info.payload) // 2]

    def _others_for(self, tag: str) -> tuple[_Info, ...]:
        try:
            return self._others[tag]
        except KeyError:
            others = tuple(i for t, i in self._by_tag.items() if t != tag)
            self._others[tag] = others
            return others

    # ---- byte level

    def _random_bytes(self, rng: random.Random, info: _Info) -> bytes:
        return rng.randbytes(rng.randrange(_RANDOM_BYTES_MAX + 1))

    def _truncated(self, rng: random.Random, info: _Info) -> bytes:
        p = info.payload
        return p[: rng.randrange(len(p))] if p else p

    def _bitflip(self, rng: random.Random, info: _Info) -> bytes:
        data = bytearray(info.payload)
        if not data:
            return bytes((1 << rng.randrange(8),))
        for _ in range(rng.randint(1, 4)):
            bit = rng.randrange(len(data) * 8)
            data[bit >> 3] ^= 1 << (bit & 7)
        return bytes(data)

    def _oversized(self, rng: random.Random, info: _Info) -> bytes:
        target = MAX_PAYLOAD_BYTES + 1 + (0 if rng.random() < 0.25 else rng.randrange(4096))
        variant = rng.randrange(4)
        wire = info.wire
        out: bytes
        if variant == 0 and wire is not None and info.keys:
            key = _pick(rng, info.body_keys if info.body_keys and rng.random() < 0.7 else info.keys)
            out = info.raw_map({key: b"\xdb" + target.to_bytes(4, "big") + b"x" * target})
        elif variant == 1 and wire is not None and info.keys:
            key = _pick(rng, info.list_keys or info.keys)
            count = target // len(_PACKED_FLOAT) + 1
            out = info.raw_map({key: b"\xdd" + count.to_bytes(4, "big") + _PACKED_FLOAT * count})
        elif variant == 2:
            chunk = rng.randbytes(1024)
            out = (chunk * (target // len(chunk) + 1))[:target]
        else:
            out = info.payload
        if len(out) < target:
            out += bytes(target - len(out))
        return out

    def _not_a_map(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        variant = rng.randrange(7)
        if variant == 0 and wire is not None:
            return _pack(list(wire.values()))
        if variant == 1 and wire is not None:
            return _pack([[k, v] for k, v in wire.items()])
        if variant == 2 and wire is not None:
            return _pack([wire])
        if variant == 3:
            depth: int = _pick(rng, (100, 1000, 5000))
            return b"\x91" * depth + b"\xc0"
        if variant == 4 and info.payload:
            return info.payload + info.payload  # two maps back to back: trailing data
        if variant == 5:
            return _pack(msgpack.ExtType(rng.randrange(128), b"\x01"))
        return _pack(_pick(rng, _NOT_A_MAP_SCALARS))

    # ---- structure aware (info.wire is a map)

    def _wrong_type_field(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        if info.str_keys and rng.random() < 0.125:
            key = _pick(rng, info.str_keys)
            return _pack_pairs(
                [(k, _raw_str(_pick(rng, _BAD_UTF8)) if k == key else _pack(v)) for k, v in wire.items()]
            )
        slot = _pick(rng, info.type_slots)
        key, i = slot
        current = info.cat[key] if i < 0 else info.elem[key]
        accepted = _ACCEPTS.get(current, _ACCEPTS["other"])
        choices = [c for c in _CATEGORIES if c not in accepted]
        return _pack(_set(wire, slot, _pick(rng, _EXAMPLES[_pick(rng, choices)])))

    def _nonfinite(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        slot = _pick(rng, info.float_slots) if info.float_slots else (_pick(rng, info.keys), -1)
        d = _set(wire, slot, _pick(rng, _NONFINITE))
        return _pack_f32(d) if rng.random() < 0.25 else _pack(d)

    def _huge_number(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        n_int = len(info.int_keys)
        j = rng.randrange(n_int + len(info.float_slots))
        slot = (info.int_keys[j], -1) if j < n_int else info.float_slots[j - n_int]
        return _pack(_set(wire, slot, _pick(rng, _HUGE)))

    def _missing_field(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        if not info.required or rng.random() < 1 / 32:
            return _pack({})
        d = dict(wire)
        del d[_pick(rng, info.required)]
        return _pack(d)

    def _extra_field(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        r = rng.random()
        keys: list[Any]
        if r < 0.1:
            keys = [rng.randrange(-5, 100)]  # non-string key (strict_map_key)
        elif r < 0.15:
            keys = [b""]  # bytes key (allowed by strict_map_key: b"" passes max_bin_len=0)
        elif r < 0.25:  # several unknown keys, str and bytes mixed
            keys = [b"", _pick(rng, info.extra_keys) if info.extra_keys else "extra"]
            rng.shuffle(keys)
        else:
            keys = [_pick(rng, info.extra_keys) if info.extra_keys else "extra"]
        extra = {k: _pick(rng, _EXAMPLES[_pick(rng, _CATEGORIES)]) for k in keys}
        return _pack({**wire, **extra} if rng.random() < 0.5 else {**extra, **wire})

    def _bad_version(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        d = dict(wire)
        d[_V] = _pick(rng, _BAD_VERSIONS)
        return _pack(d)

    def _unknown_type(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        registered, unregistered = _other_tags(info.tag)
        new = _pick(rng, registered if registered and rng.random() < 0.5 else unregistered)
        return info.raw_map({_TYPE: _pack(new)}) if _TYPE in wire else _pack({**wire, _TYPE: new})

    def _type_confusion(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        others = self._others_for(info.tag)
        if not others:
            return self._unknown_type(rng, info)
        other = _pick(rng, others)
        owire = other.wire
        assert owire is not None
        variant = rng.randrange(4)
        if variant == 0:  # this body under the other header and tag
            d = {k: owire[k] for k in owire if k not in other.body_keys}
            d.update((k, wire[k]) for k in info.body_keys)
        elif variant == 1:  # union of both bodies under the other tag
            d = dict(owire)
            d.update((k, wire[k]) for k in info.body_keys)
        elif variant == 2:  # fields shared by name transplanted into the other message
            d = dict(owire)
            shared = [k for k in info.body_keys if k in owire]
            for k in shared or info.body_keys[:1]:
                d[k] = wire[k]
        else:  # duplicated "type" key: the decoder keeps the last one
            pairs = [(k, _pack(v)) for k, v in wire.items()]
            pos = rng.randrange(len(pairs) + 1)
            pairs.insert(pos, (_TYPE, _pack(other.tag)))
            return _pack_pairs(pairs)
        return _pack(d)

    def _long_string(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        value = _pick(rng, _LONG_STRINGS)
        if not info.str_slots:
            return _pack(_set(wire, (_pick(rng, info.keys) if info.keys else _TYPE, -1), value))
        return _pack(_set(wire, _pick(rng, info.str_slots), value))

    def _fill(self, info: _Info, key: Any, length: int) -> bytes:
        """A packed list of ``length`` plausible elements for a list field (cached per template)."""
        try:
            return info.arrays[key, length]
        except KeyError:
            pass
        assert info.wire is not None
        current = info.wire[key]
        elem = info.elem.get(key, "")
        values: list[Any]
        if elem == "str" and key in info.joint_group:
            values = [f"j{i + 1}" for i in range(length)]
        elif current and elem:
            values = [current[i % len(current)] for i in range(length)]
        else:
            values = ["x"] * length if elem == "str" else [0.0] * length
        out = info.arrays[key, length] = _pack(values)
        return out

    def _long_array(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        if not info.list_keys:
            key = _pick(rng, info.body_keys or info.keys)
            return info.raw_map({key: self._fill(info, key, _pick(rng, _LONG_ARRAY))})
        key = _pick(rng, info.list_keys)
        joint_space = key in info.joint_group or info.elem.get(key) == "float"
        length = MAX_JOINTS + 1 if joint_space and rng.random() < 0.3 else _pick(rng, _LONG_ARRAY)
        keys = info.joint_group if key in info.joint_group and rng.random() < 0.5 else (key,)
        return info.raw_map({k: self._fill(info, k, length) for k in keys})

    def _boundary(self, rng: random.Random, info: _Info) -> bytes:
        wire = info.wire
        assert wire is not None
        if not info.boundary:
            return info.payload
        variant = _pick(rng, info.boundary)
        if variant == "int":
            return _pack(_set(wire, (_pick(rng, info.int_keys), -1), _pick(rng, _INT_BOUNDARY)))
        if variant == "float":
            return _pack(_set(wire, _pick(rng, info.float_slots), _pick(rng, _FLOAT_BOUNDARY)))
        if variant == "str":
            return _pack(_set(wire, _pick(rng, info.str_slots), _pick(rng, _STR_BOUNDARY)))
        if variant == "quat":
            key = _pick(rng, info.quat_keys)
            q = wire[key]
            delta = _pick(rng, (1e-3, -1e-3, 1e-3 + 1e-9, -1e-3 - 1e-9, 1e-3 - 1e-9, -1e-3 + 1e-9, -1.0))
            scale = (1.0 + delta) / math.hypot(*q)
            return _pack(_set(wire, (key, -1), [x * scale for x in q]))
        if variant == "f32":
            return _pack_f32(wire)
        if variant == "group":
            length = _pick(rng, (0, 1, MAX_JOINTS, MAX_JOINTS + 1))
            return info.raw_map({k: self._fill(info, k, length) for k in info.joint_group})
        key = _pick(rng, info.list_keys)  # "len": one list resized
        n = len(wire[key])
        lengths = (0, 1, max(n - 1, 0), n + 1, MAX_JOINTS, MAX_JOINTS + 1, MAX_LIST, MAX_LIST + 1)
        return info.raw_map({key: self._fill(info, key, _pick(rng, lengths))})


@lru_cache(maxsize=256)
def _other_tags(tag: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Registered tags whose body differs from ``tag``'s, and unregistered look-alikes of ``tag``."""
    own = MESSAGE_TYPES.get(tag)
    registered = tuple(
        t for t, c in MESSAGE_TYPES.items() if t != tag and (own is None or c.BODY != own.BODY)
    )
    base = tag or "joint_state"
    pool = ("", base.upper(), base + "\x00", base + " ", " " + base, base + "s", base[::-1], "unknown", _TYPE)
    return registered, tuple(t for t in dict.fromkeys(pool) if t not in MESSAGE_TYPES)


@lru_cache(maxsize=1)
def _gen_for_mutate() -> _Gen:
    return _Gen(())


def _generate(
    rng: random.Random, gen: _Gen, infos: Sequence[_Info], n: int, kinds: tuple[str, ...]
) -> Iterator[FuzzCase]:
    order: list[str] = []
    for _ in range(n):
        if not order:
            order = list(kinds)
            rng.shuffle(order)
        info = infos[rng.randrange(len(infos))]
        kind, payload = gen.case_bytes(rng, order.pop(), info)
        yield FuzzCase(kind, payload, "" if kind == "random_bytes" else info.tag)
