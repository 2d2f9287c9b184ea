"""Declaring a message: one ``fld`` per field gives the codec, its strict rules and the docs."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import msgpack
import pytest
from telesurg.services.docs import message_section
from telesurg.shared import messages as msgs
from telesurg.shared.errors import MessageError
from telesurg.shared.messages import Header, Message, decode, fld, message

H = Header("mapping", 3, 1_700_000_000_000_000_000)
MODES = frozenset({"disabled", "aligning", "enabled"})


@pytest.fixture
def registry() -> Iterator[None]:
    """Take the test's message types out of the registry again."""
    before = dict(msgs._REGISTRY), dict(msgs._DECODERS)
    yield
    msgs._REGISTRY.clear()
    msgs._REGISTRY.update(before[0])
    msgs._DECODERS.clear()
    msgs._DECODERS.update(before[1])


def _declare() -> type[Message]:
    @message("test_state")
    @dataclass(frozen=True, slots=True)
    class TestState(Message):
        """A test message (``test/<m>/state``)."""

        arm: str = fld("", "slave arm id", nonempty=True)
        state: str = fld("disabled", "teleop state", choices=MODES)
        scale: float = fld(1.0, "motion scale", ge=0.0, le=1.0)
        tip: tuple[float, float, float] = fld((0.0, 0.0, 0.0), "tip position", unit="m")
        joints: tuple[str, ...] = fld((), "joint names", wire="name", joint_names=True)
        q: tuple[float, ...] = fld((), "joint positions", unit="rad", same_len="joints")
        changes: int = fld(0, "state changes since start")

    return TestState


def _wire(cls: type[Message], **change: Any) -> bytes:
    d = msgpack.unpackb(cls(H, "arm1", "enabled", 0.5, (0.1, 0.2, 0.3), ("j1", "j2"), (0.0, 1.0), 4).encode())  # type: ignore[call-arg]
    d.update(change)
    return msgpack.packb(d)  # type: ignore[no-any-return]


def test_a_declared_message_round_trips_with_its_wire_keys(registry: None) -> None:
    cls = _declare()
    msg = cls(H, "arm1", "enabled", 0.5, (0.1, 0.2, 0.3), ("j1", "j2"), (0.0, 1.0), 4)  # type: ignore[call-arg]
    wire = msgpack.unpackb(msg.encode())
    assert list(wire) == [
        "v",
        "type",
        "src",
        "seq",
        "ts",
        "arm",
        "state",
        "scale",
        "tip",
        "name",
        "q",
        "changes",
    ]
    assert decode(msg.encode()) == msg
    assert {"arm", "state", "scale", "tip", "name", "q", "changes"} == cls.BODY
    assert msg.body()["name"] == ["j1", "j2"]
    assert cls.from_body(H, wire) == msg
    assert "scale: motion scale." in (cls.__doc__ or "")


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"arm": ""}, "'arm' must not be empty"),
        ({"state": "ENABLED"}, "'state'='ENABLED' is not one of"),
        ({"scale": 1.5}, r"'scale'=1.5 outside \[0, 1\]"),
        ({"scale": math.nan}, "'scale' is not finite"),
        ({"scale": True}, "'scale' must be a number"),
        ({"tip": [0.0, 0.0]}, "'tip' must have 3 elements"),
        ({"tip": [0.0, math.inf, 0.0]}, r"'tip'\[1\] is not finite"),
        ({"name": ["j1", "j1"]}, "distinct"),
        ({"q": [0.0]}, "'q' has 1 elements for 2 names"),
        ({"changes": -1}, "outside"),
        ({"changes": 1.0}, "must be an integer"),
        ({"extra": 1}, "unexpected fields"),
    ],
)
def test_a_declared_message_keeps_every_strict_rule(
    registry: None, change: dict[str, Any], needle: str
) -> None:
    cls = _declare()
    with pytest.raises(MessageError, match=needle):
        decode(_wire(cls, **change))


def test_its_docs_section_lists_every_field(registry: None) -> None:
    text = message_section(_declare())
    assert "| `scale` | `scale` | float | — | motion scale | finite, in [0, 1] |" in text
    assert "| `q` | `q` | float[] | rad | joint positions | ≤ 32 finite numbers, as many as `name` |" in text


def test_a_field_without_fld_or_without_a_rule_is_refused_at_import(registry: None) -> None:
    with pytest.raises(TypeError, match="fld"):

        @message("bad1")
        @dataclass(frozen=True, slots=True)
        class Bad1(Message):
            x: int = 0

    with pytest.raises(TypeError, match="no rule"):

        @message("bad2")
        @dataclass(frozen=True, slots=True)
        class Bad2(Message):
            x: frozenset[int] = fld(frozenset(), "a set")


def test_a_hand_written_class_still_registers_and_decodes(registry: None) -> None:
    @msgs._register
    @dataclass(frozen=True, slots=True)
    class Legacy(Message):
        """A message in the style before ``fld``."""

        TYPE: ClassVar[str] = "legacy"
        BODY: ClassVar[frozenset[str]] = frozenset({"arm"})

        arm: str = ""

        def body(self) -> dict[str, Any]:
            return {"arm": self.arm}

        @classmethod
        def from_body(cls, header: Header, d: dict[str, Any]) -> Legacy:
            return cls(header, msgs._str(d, "arm", allow_empty=False))

    m = Legacy(H, "arm1")
    assert decode(m.encode()) == m
    with pytest.raises(MessageError, match="unexpected fields"):
        decode(msgpack.packb({**msgpack.unpackb(m.encode()), "x": 1}))
    assert "Body fields: `arm`." in message_section(Legacy)
