"""The browser master's rules (services/console/browser.py): frame checks, flood budget, the
browser clock, sample freshness and the fresh-press rule after a reconnect. No I/O."""

from __future__ import annotations

import json

import pytest
from telesurg.services.console.browser import (
    BrowserMaster,
    ClockMap,
    FrameError,
    SocketGuard,
    parse_frame,
    parse_sample,
)

GOOD = {
    "type": "sample",
    "master": "m1",
    "t": 1.0e12,
    "p": [0.01, 0.0, 0.0],
    "q": [0, 0, 0, 1],
    "clutch": False,
}


def frame(**kw: object) -> str:
    return json.dumps({**GOOD, **kw})


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("{not json", "malformed"),
        ("[1, 2]", "malformed"),
        (
            '{"type": "sample", "master": "m1", "t": NaN, "p": [0,0,0], "q": [0,0,0,1], "clutch": false}',
            "nonfinite",
        ),
        (
            '{"type": "sample", "master": "m1", "t": 1, "p": [Infinity,0,0], "q": [0,0,0,1], '
            '"clutch": false}',
            "nonfinite",
        ),
        (frame(extra=1), "unknown"),
        (json.dumps({"type": "teleport"}), "unknown"),
        (json.dumps({"type": "sample"}), "invalid"),
        ("x" * 5000, "oversized"),
    ],
)
def test_bad_frames_are_refused_by_kind(text: str, kind: str) -> None:
    with pytest.raises(FrameError) as e:
        parse_frame(text, 4096)
    assert e.value.kind == kind


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        ({"p": [2.0, 0, 0]}, "beyond"),
        ({"p": [0, 0]}, "3 numbers"),
        ({"q": [0, 0, 0, 2]}, "unit quaternion"),
        ({"clutch": 1}, "true or false"),
        ({"master": "m9"}, "not one of"),
        ({"p": [True, 0, 0]}, "number"),
        ({"device": "joystick"}, "device"),
    ],
)
def test_bad_sample_values_are_refused(fields: dict[str, object], why: str) -> None:
    obj = parse_frame(frame(**fields), 4096)
    with pytest.raises(FrameError, match=why):
        parse_sample(obj, ("m1",))


def test_binary_frames_are_refused() -> None:
    with pytest.raises(FrameError) as e:
        parse_frame(b"\x00\x01", 4096)
    assert e.value.kind == "binary"


def test_guard_counts_floods_and_marks_abuse() -> None:
    g = SocketGuard(rate_hz=100.0, burst=10.0, max_rejects=5)
    ok = sum(1 for _ in range(10) if g.admit('{"type": "ping"}', now=0.0))
    assert ok == 10
    for _ in range(5):
        with pytest.raises(FrameError):
            g.admit('{"type": "ping"}', now=0.0)
    assert g.counts == {"flood": 5} and g.abusive
    g2 = SocketGuard(rate_hz=100.0, burst=10.0, max_rejects=5)
    for i in range(50):  # at the allowed rate: never refused
        g2.admit('{"type": "ping"}', now=i * 0.011)
    assert g2.rejected == 0


def test_clock_map_takes_the_least_delayed_frame() -> None:
    c = ClockMap()
    # browser clock 5 s behind the host; transit 3 ms, then 1 ms
    assert c.stamp_ns(1000.0, 6_003_000_000) == 6_003_000_000
    assert c.stamp_ns(1010.0, 6_011_000_000) == 6_011_000_000  # offset shrinks to 5.001 s
    assert c.stamp_ns(1020.0, 6_030_000_000) == 6_021_000_000  # a late frame keeps its own time


def test_master_goes_invalid_when_quiet_and_needs_a_fresh_press() -> None:
    bm = BrowserMaster("m1", timeout_s=0.06)
    a, b = object(), object()
    pressed = parse_sample(parse_frame(frame(clutch=True), 4096), ("m1",))
    released = parse_sample(parse_frame(frame(clutch=False), 4096), ("m1",))
    bm.feed(a, released, 1, now=0.0)
    bm.feed(a, pressed, 2, now=0.01)
    cur = bm.current(0.02)
    assert cur is not None and cur.clutch
    assert bm.current(0.2) is None  # quiet for longer than the timeout: nothing published
    bm.detach(a)  # socket closed
    assert bm.current(0.2) is None
    bm.feed(b, pressed, 3, now=1.0)  # a new page with the clutch held: not a press
    cur = bm.current(1.0)
    assert cur is not None and not cur.clutch
    bm.feed(b, released, 4, now=1.01)
    bm.feed(b, pressed, 5, now=1.02)
    cur = bm.current(1.02)
    assert cur is not None and cur.clutch
    assert bm.invalidations == 1  # one outage: quiet, then closed
