"""Message round trips and strict rejection of malformed payloads."""

from __future__ import annotations

import contextlib
import math

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from telesurg.shared.errors import MessageError
from telesurg.shared.messages import (
    MAX_PAYLOAD_BYTES,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    CameraImage,
    CartesianPose,
    CartesianWrench,
    ClockProbe,
    ClockReply,
    Command,
    CommandReply,
    EStop,
    Header,
    Heartbeat,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    SafetyLease,
    SafetyState,
    SceneState,
    TeleopState,
    TrialState,
    VideoFeedback,
    VideoState,
    decode,
    decode_as,
)

H = Header("test", 7, 1_700_000_000_000_000_000)
NAMES = ("j1", "j2", "j3", "j4", "j5", "j6")

EXAMPLES = [
    JointState(H, NAMES, (0.1, 0.2, 0.3, 0.4, 0.5, 0.6), (0.0,) * 6, (1.0,) * 6),
    JointState(H, ("j1",), (0.1,)),
    CartesianPose(H, "base", (0.5, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0)),
    MasterButtons(H, True, False),
    JointSetpoint(H, NAMES, (0.0, 0.2, 0.3, 0.0, -0.6, 0.0), follow=True),
    OperatingState(H, "PAUSED", "non_trocar", False, True, "clutch released", 3),
    SafetyLease(H, "arm1", True, 50.0, ""),
    SafetyState(H, "arm1", "HOLD", ("mapping not alive", "servo_jp stale (80 ms > 50 ms)")),
    SafetyEvent(H, "arm1", "transition", "warning", "OK → HOLD"),
    Heartbeat(H, "mapping", 12.5, 0),
    EStop(H, "*", "estop", "console: operator"),
    Command(H, "arm1", "jog", ("frame=forceps", "axis=x", "direction=1")),
    CommandReply(H, "arm1", "insert", False, "insert refused: forceps axis 7.3° off trocar direction"),
    CartesianWrench(H, "base", (0.0, 1.5, -2.0), (0.0, 0.0, 0.1)),
    TeleopState(
        H, "m1", "arm1", "HOLDING", "ENABLED", "slave holding: lease expired", 7, 0.5, 0.5, "cartesian"
    ),
    CameraImage(
        H, "endo", 5, 320, 240, "jpeg", "mono", 0.0, 290.0, 290.0, 160.0, 120.0, 14.0, 0.4, 0, b"\xff\xd8"
    ),
    VideoState(H, "arm1", "endo", "OK", 40.0, 23.0, 22.0, 31.0, 12.0, 240, 0),
    VideoFeedback(H, "endo", 12, 1, 812.4, 71.5, True),
    TrialState(
        H,
        2,
        12,
        "mh3f-targets",
        "Touch the green target.",
        "condition B",
        False,
        "running",
        4.25,
        60.0,
        1,
        4,
        "",
        (0.815, -0.02, 0.2575, 0.855, 0.02, 0.2575),
    ),
    SceneState(H, ("peg",), (0.01,), (-0.02,), (-0.11,), ("arm1+arm2",), (0.8, 0.9), False, 1),
    ClockProbe(H),
    ClockReply(H, 1_700_000_000_000_000_000, 1_700_000_000_300_100_000, 1_700_000_000_300_150_000),
]


def test_every_message_type_has_an_example() -> None:
    assert {m.TYPE for m in EXAMPLES} == set(MESSAGE_TYPES)


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ({"name": "Jog"}, "must match"),
        ({"name": "jog", "args": ["frame"]}, "key=value"),
        ({"args": [f"k{i}=v" for i in range(17)]}, "limit 16"),
    ],
)
def test_command_field_rules(body: dict[str, object], match: str) -> None:
    d = msgpack.unpackb(Command(H, "arm1", "jog", ("axis=x",)).encode())
    d.update(body)
    with pytest.raises(MessageError, match=match):
        decode(_pack(d))


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: m.TYPE)
def test_round_trip(msg: object) -> None:
    assert decode_as(msg.encode(), type(msg)) == msg  # type: ignore[attr-defined]


def _valid() -> dict[str, object]:
    return msgpack.unpackb(EXAMPLES[4].encode())  # type: ignore[no-any-return]


def _pack(d: object) -> bytes:
    return msgpack.packb(d)  # type: ignore[no-any-return]


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda d: d.update(position=[0.0, math.nan, 0, 0, 0, 0]), "not finite"),
        (lambda d: d.update(position=[0.0, math.inf, 0, 0, 0, 0]), "not finite"),
        (lambda d: d.update(position=[0.0, 0.1]), "2 elements for 6 names"),
        (lambda d: d.update(position="0.1"), "must be an array"),
        (lambda d: d.update(position=[0.0, "x", 0, 0, 0, 0]), "must be a number"),
        (lambda d: d.update(position=[True] * 6), "must be a number"),
        (lambda d: d.update(follow=1), "must be a boolean"),
        (lambda d: d.update(seq=-1), "outside"),
        (lambda d: d.update(seq=1.5), "must be an integer"),
        (lambda d: d.update(v=SCHEMA_VERSION - 1), "unknown schema version"),
        (lambda d: d.update(v=SCHEMA_VERSION + 1), "unknown schema version"),
        (lambda d: d.pop("v"), "unknown schema version"),
        (lambda d: d.update(type="nope"), "unknown message type"),
        (lambda d: d.update(extra=1), "unexpected fields"),
        (lambda d: d.pop("follow"), "missing field 'follow'"),
        (lambda d: d.update(src=""), "must not be empty"),
        (lambda d: d.update(name=["j"] * 40, position=[0.0] * 40), "limit"),
    ],
)
def test_rejects_malformed(mutate: object, needle: str) -> None:
    d = _valid()
    mutate(d)  # type: ignore[operator]
    with pytest.raises(MessageError, match=needle):
        decode(_pack(d))


def test_rejects_truncated_and_garbage() -> None:
    data = EXAMPLES[0].encode()
    for n in (0, 1, len(data) // 2, len(data) - 1):
        with pytest.raises(MessageError):
            decode(data[:n])
    with pytest.raises(MessageError, match="must be a map"):
        decode(_pack([1, 2, 3]))
    with pytest.raises(MessageError, match="bytes, limit"):
        decode(b"\x00" * (MAX_PAYLOAD_BYTES + 1))


def test_rejects_non_unit_quaternion_and_wrong_type() -> None:
    d = msgpack.unpackb(EXAMPLES[2].encode())
    d["orientation"] = [0.0, 0.0, 0.0, 2.0]
    with pytest.raises(MessageError, match="unit quaternion"):
        decode(_pack(d))
    with pytest.raises(MessageError, match="expected 'servo_jp', got 'pose'"):
        decode_as(EXAMPLES[2].encode(), JointSetpoint)


def test_rejects_unknown_enum_values() -> None:
    d = msgpack.unpackb(EXAMPLES[5].encode())
    d["state"] = "RUNNING"
    with pytest.raises(MessageError, match="not one of"):
        decode(_pack(d))
    assert SCHEMA_VERSION == 7


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=512))
def test_random_bytes_never_escape_as_other_errors(data: bytes) -> None:
    with contextlib.suppress(MessageError):
        decode(data)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 200), st.integers(0, 255))
def test_single_byte_mutations_decode_or_raise_message_error(pos: int, value: int) -> None:
    data = bytearray(EXAMPLES[0].encode())
    data[pos % len(data)] = value
    try:
        msg = decode(bytes(data))
    except MessageError:
        return
    assert isinstance(msg, JointState)
    assert all(math.isfinite(x) for x in msg.position)


def test_rejects_float_and_bool_versions() -> None:
    for v in (2.0, True):
        d = msgpack.unpackb(EXAMPLES[0].encode())
        d["v"] = v
        with pytest.raises(MessageError, match="unknown schema version"):
            decode(_pack(d))


def _raw_map(pairs: list[tuple[str, object]], header: str) -> bytes:
    n = len(pairs)
    head = bytes([0x80 | n]) if header == "fixmap" else b"\xde" + n.to_bytes(2, "big")
    return head + b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in pairs)


@pytest.mark.parametrize("header", ["fixmap", "map16"])
def test_a_duplicated_key_is_rejected(header: str) -> None:
    good = CartesianPose(Header("m", 1, 2), "base", (0.1, 0.2, 0.3), (0.0, 0.0, 0.0, 1.0)).encode()
    pairs = list(msgpack.unpackb(good).items())
    assert decode(_raw_map(pairs, header)) == decode(good)
    with pytest.raises(MessageError, match="duplicate keys"):
        decode(_raw_map([*pairs, ("frame", "tool")], header))


def test_an_older_recordings_operating_state_decodes_without_the_fields_added_later() -> None:
    """``is_homed`` / ``is_busy`` (CRTK, added after recordings were made) may be absent: a
    recording made before them still replays and exports; every other field stays required."""
    wire = msgpack.unpackb(OperatingState(H, "ENABLED", "trocar", True, True, "", 2).encode())
    old = {k: v for k, v in wire.items() if k not in ("is_homed", "is_busy")}
    m = decode(msgpack.packb(old))
    assert isinstance(m, OperatingState)
    assert (m.is_homed, m.is_busy, m.control_mode, m.follow) == (True, False, "trocar", True)
    del old["control_mode"]
    with pytest.raises(MessageError, match="missing field 'control_mode'"):
        decode(msgpack.packb(old))
