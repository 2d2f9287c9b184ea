"""The fuzz payload generator (telesurg.tools.bench.fuzzgen) and the strict decoder under its payloads."""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import os
import random
import subprocess
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import msgpack
import pytest
import telesurg.tools.bench.fuzzgen as fz
from hypothesis import given, settings
from hypothesis import strategies as st
from telesurg.shared.errors import MessageError
from telesurg.shared.messages import (
    MAX_JOINTS,
    MAX_PAYLOAD_BYTES,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Message,
    decode,
    decode_as,
)
from telesurg.tools.bench.fuzzgen import (
    ALWAYS_INVALID_KINDS,
    FUZZ_KINDS,
    FuzzCase,
    always_invalid,
    default_templates,
    fuzz_cases,
    mutate,
    valid_template,
)

ROOT = Path(__file__).resolve().parents[1]

#: Found by this generator: a registered type with two unexpected keys, one str and one bytes (b""
#: passes ``strict_map_key`` and ``max_bin_len=0``), made ``decode`` raise TypeError from
#: ``sorted(extra)`` instead of MessageError. {"v": SCHEMA_VERSION, "type": "heartbeat", "x": 0, b"": 0}
MIXED_KEY_BUG = bytes.fromhex(f"84a176{SCHEMA_VERSION:02x}a474797065a9686561727462656174a17800c40000")


@pytest.fixture(autouse=True)
def strict_generator(monkeypatch: pytest.MonkeyPatch) -> None:
    """Surface generator bugs instead of the never-raise fallback."""
    monkeypatch.setattr(fz, "_STRICT", True)


def _decode(payload: bytes) -> Message | None:
    """``decode`` or None if rejected; any exception other than MessageError fails the test."""
    try:
        return decode(payload)
    except MessageError:
        return None
    except Exception as exc:
        raise AssertionError(f"decode raised {type(exc).__name__}: {exc}; payload {payload.hex()}") from exc


def _check_decoded(msg: Message, payload: bytes) -> None:
    assert decode(msg.encode()) == msg, payload.hex()
    assert decode_as(payload, type(msg)) == msg
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        values = value if isinstance(value, tuple) else (value,)
        assert all(math.isfinite(x) for x in values if isinstance(x, float)), (f.name, payload.hex())


@pytest.fixture(scope="module")
def templates() -> tuple[Message, ...]:
    return (
        *default_templates(),
        *default_templates(n_joints=1, source="a"),
        *default_templates(n_joints=MAX_JOINTS, source="x" * 40),
    )


def _digest(cases: Iterable[FuzzCase]) -> str:
    h = hashlib.sha256()
    for c in cases:
        h.update(f"{c.kind}|{c.template}|".encode() + c.payload)
    return h.hexdigest()


# --------------------------------------------------------------------------- templates


@pytest.mark.parametrize("n_joints", [1, 6, MAX_JOINTS])
@pytest.mark.parametrize("cls", list(MESSAGE_TYPES.values()), ids=list(MESSAGE_TYPES))
def test_valid_template_round_trips(cls: type[Message], n_joints: int) -> None:
    t = valid_template(cls, source="src1", seq=5, n_joints=n_joints)
    assert type(t) is cls
    assert decode_as(t.encode(), cls) == t  # (a camera image only decodes as one, on its key)
    assert (t.header.source, t.header.seq) == ("src1", 5)
    for f in dataclasses.fields(t):
        value = getattr(t, f.name)
        if "name" in f.name and isinstance(value, tuple):
            assert value == tuple(f"j{i + 1}" for i in range(n_joints))
    assert valid_template(cls, source="src1", seq=5, n_joints=n_joints) == t  # deterministic


def test_valid_template_rejects_bad_arguments() -> None:
    cls = next(iter(MESSAGE_TYPES.values()))
    for n in (-1, 0, MAX_JOINTS + 1):
        with pytest.raises(ValueError, match="n_joints"):
            valid_template(cls, n_joints=n)
    with pytest.raises(ValueError, match="registered"):
        valid_template(Message)
    with pytest.raises(ValueError):
        valid_template(cls, source="")  # the header needs a source


# --------------------------------------------------------------------------- generation


def test_deterministic_for_a_seed(templates: tuple[Message, ...]) -> None:
    a = list(fuzz_cases(random.Random(7), templates, 1000))
    b = list(fuzz_cases(random.Random(7), templates, 1000))
    assert a == b
    assert _digest(a) != _digest(fuzz_cases(random.Random(8), templates, 1000))


def test_deterministic_across_processes() -> None:
    """No dependence on str hashing (PYTHONHASHSEED) or other per-process state."""
    code = (  # _digest, inline
        "import hashlib, random\n"
        "from telesurg.tools.bench.fuzzgen import default_templates, fuzz_cases\n"
        "h = hashlib.sha256()\n"
        "for c in fuzz_cases(random.Random(3), default_templates(), 500):\n"
        "    h.update(f'{c.kind}|{c.template}|'.encode() + c.payload)\n"
        "print(h.hexdigest())\n"
    )
    digests = set()
    for hash_seed in ("0", "12345"):
        env = {**os.environ, "PYTHONHASHSEED": hash_seed}
        out = subprocess.run(
            [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
        )
        digests.add(out.stdout.strip())
    assert digests == {_digest(fuzz_cases(random.Random(3), default_templates(), 500))}


def test_every_kind_is_produced_in_shuffled_rounds(templates: tuple[Message, ...]) -> None:
    rounds = 5
    cases = list(fuzz_cases(random.Random(1), templates, rounds * len(FUZZ_KINDS)))
    assert collections.Counter(c.kind for c in cases) == {k: rounds for k in FUZZ_KINDS}
    for c in cases:
        assert isinstance(c.payload, bytes)
        assert c.template == "" if c.kind == "random_bytes" else c.template in MESSAGE_TYPES


def test_kinds_subset_and_templates_used(templates: tuple[Message, ...]) -> None:
    cases = list(fuzz_cases(random.Random(2), templates, 500, kinds=["bitflip", "missing_field"]))
    assert {c.kind for c in cases} == {"bitflip", "missing_field"}
    assert {c.template for c in cases} == set(MESSAGE_TYPES)


def test_empty_templates_mean_default_templates() -> None:
    a = list(fuzz_cases(random.Random(4), [], 200))
    b = list(fuzz_cases(random.Random(4), default_templates(), 200))
    assert a == b


def test_bad_arguments_raise_at_call_time(templates: tuple[Message, ...]) -> None:
    rng = random.Random(0)
    with pytest.raises(ValueError, match="kinds"):
        fuzz_cases(rng, templates, 1, kinds=["nope"])
    with pytest.raises(ValueError, match="kinds"):
        fuzz_cases(rng, templates, 1, kinds=[])
    with pytest.raises(ValueError, match="n must be"):
        fuzz_cases(rng, templates, -1)
    assert list(fuzz_cases(rng, templates, 0)) == []


def test_always_invalid_classification() -> None:
    assert set(FUZZ_KINDS) > ALWAYS_INVALID_KINDS
    for kind in FUZZ_KINDS:
        assert always_invalid(kind) is (kind in ALWAYS_INVALID_KINDS)
    for kind in (
        "nonfinite",
        "oversized",
        "bad_version",
        "not_a_map",
        "long_string",
        "long_array",
        "truncated",
    ):
        assert always_invalid(kind)
    for kind in ("random_bytes", "bitflip", "boundary", "huge_number", "type_confusion"):
        assert not always_invalid(kind)
    with pytest.raises(ValueError, match="unknown fuzz kind"):
        always_invalid("nope")


def test_case_shapes(templates: tuple[Message, ...]) -> None:
    payloads = {t.encode() for t in templates}
    lengths = {len(p) for p in payloads}
    for c in fuzz_cases(random.Random(5), templates, 4000):
        if c.kind == "random_bytes":
            assert len(c.payload) <= 200
        elif c.kind == "oversized":
            assert len(c.payload) > MAX_PAYLOAD_BYTES
        elif c.kind == "truncated":
            assert any(len(c.payload) < len(p) and p.startswith(c.payload) for p in payloads)
        elif c.kind == "bitflip":
            assert len(c.payload) in lengths
            flips = min(
                sum(bin(x ^ y).count("1") for x, y in zip(c.payload, p, strict=True))
                for p in payloads
                if len(p) == len(c.payload)
            )
            assert 1 <= flips <= 4
        elif c.kind == "not_a_map":
            with pytest.raises(MessageError):
                decode(c.payload)


def test_generation_streams_every_case_asked(templates: tuple[Message, ...]) -> None:
    """20 000 cases come out one at a time, each with a payload (the rate is the bench's figure:
    ``telesurg bench fuzz`` prints it)."""
    n = 20_000
    count = sum(1 for c in fuzz_cases(random.Random(1), templates, n) if c.payload is not None)
    assert count == n


# --------------------------------------------------------------------------- the decoder under fuzz


@pytest.mark.parametrize("kind", sorted(ALWAYS_INVALID_KINDS))
def test_always_invalid_kinds_are_rejected(kind: str, templates: tuple[Message, ...]) -> None:
    for c in fuzz_cases(random.Random(FUZZ_KINDS.index(kind)), templates, 2000, kinds=[kind]):
        assert c.kind == kind
        msg = _decode(c.payload)
        assert msg is None, f"{kind} case from {c.template} decoded as {msg!r}: {c.payload.hex()}"


def test_all_kinds_only_message_error_and_round_trip(templates: tuple[Message, ...]) -> None:
    decoded: collections.Counter[str] = collections.Counter()
    for c in fuzz_cases(random.Random(11), templates, 8_000):
        msg = _decode(c.payload)
        if msg is not None:
            assert not always_invalid(c.kind), (c.kind, c.payload.hex())
            _check_decoded(msg, c.payload)
            decoded[c.kind] += 1
    # The may-decode kinds do produce valid messages (values at limits, smuggled tags, ...).
    assert {"boundary", "huge_number", "bitflip", "type_confusion"} <= set(decoded)


def _mutations(rng: random.Random, payload: bytes, depth: int) -> Iterator[tuple[str, bytes]]:
    for _ in range(depth):
        kind, payload = mutate(rng, payload)
        yield kind, payload


def test_mutate_is_deterministic_and_labels_kinds(templates: tuple[Message, ...]) -> None:
    payload = templates[0].encode()
    a = list(_mutations(random.Random(9), payload, 300))
    assert a == list(_mutations(random.Random(9), payload, 300))
    assert {k for k, _ in a} <= set(FUZZ_KINDS)


@pytest.mark.parametrize("kind", sorted(ALWAYS_INVALID_KINDS))
def test_mutate_always_invalid_kinds(kind: str, templates: tuple[Message, ...]) -> None:
    rng = random.Random(21)
    for t in templates:
        for _ in range(10):
            got, payload = mutate(rng, t.encode(), kinds=[kind])
            assert got == kind
            assert _decode(payload) is None, (kind, payload.hex())


@settings(max_examples=300, deadline=None, database=None)
@given(st.binary(max_size=2048))
def test_decode_arbitrary_bytes_only_raises_message_error(data: bytes) -> None:
    msg = _decode(data)
    if msg is not None:
        _check_decoded(msg, data)


@settings(max_examples=300, deadline=None, database=None)
@given(st.integers(0, 2**32), st.integers(1, 4))
def test_decode_mutated_valid_payloads_only_raises_message_error(seed: int, depth: int) -> None:
    rng = random.Random(seed)
    cls = list(MESSAGE_TYPES.values())[seed % len(MESSAGE_TYPES)]
    template = valid_template(cls, n_joints=1 + seed % MAX_JOINTS)
    for kind, payload in _mutations(rng, template.encode(), depth):
        assert kind in FUZZ_KINDS
        msg = _decode(payload)
        if msg is not None:
            _check_decoded(msg, payload)


@settings(max_examples=300, deadline=None, database=None)
@given(st.integers(0, 2**32), st.binary(max_size=512))
def test_mutate_never_raises_on_arbitrary_bytes(seed: int, data: bytes) -> None:
    kind, payload = mutate(random.Random(seed), data)
    assert kind in FUZZ_KINDS
    assert isinstance(payload, bytes)
    _decode(payload)


def test_regression_mixed_str_and_bytes_extra_keys() -> None:
    expected = {"v": SCHEMA_VERSION, "type": "heartbeat", "x": 0, b"": 0}
    assert msgpack.unpackb(MIXED_KEY_BUG, strict_map_key=False) == expected
    with pytest.raises(MessageError, match="unexpected fields"):
        decode(MIXED_KEY_BUG)
    keys = {t.TYPE: set(msgpack.unpackb(t.encode())) for t in default_templates()}
    mixed = 0
    for c in fuzz_cases(random.Random(0), default_templates(), 2000, kinds=["extra_field"]):
        extra = set(msgpack.unpackb(c.payload, strict_map_key=False)) - keys[c.template]
        mixed += {type(k) for k in extra} == {str, bytes}
    assert mixed > 0  # the generator keeps producing this shape
