"""In-process zenoh on loopback: strict decoding at the subscriber, liveliness, sequence gaps."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import pytest

from services.launcher import free_port
from shared.bus import BusConfig, Node, open_session
from shared.errors import ConfigError
from shared.messages import Header, JointSetpoint, JointState


@pytest.fixture
def endpoint() -> Iterator[str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    try:
        yield ep
    finally:
        router.close()  # type: ignore[no-untyped-call]


def wait_until(pred: Callable[[], bool], timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def test_malformed_rejected_counted_never_delivered(endpoint: str) -> None:
    got: list[JointSetpoint] = []
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "sub") as sub, Node(bus, "t", "pub") as pub:
        key = sub.keys.slave("arm1", "servo_jp")
        sub.subscribe(key, JointSetpoint, lambda m, k: got.append(m))
        out = pub.outlet(key)
        time.sleep(0.3)
        out.put(JointSetpoint(out.header(), ("j1",), (0.1,), follow=True))
        bad = [b"garbage", b"", JointState(Header("pub", 0, 0), ("j1",), (0.0,)).encode()]
        bad.append(JointSetpoint(out.header(), ("j1",), (0.2,)).encode().replace(b"\xcb", b"\xc1", 1))
        for payload in bad:
            pub.session.put(key, payload)
        out.header()  # skip a sequence number: with the corrupted one above, one gap of 2
        out.put(JointSetpoint(out.header(), ("j1",), (0.3,), follow=True))
        assert wait_until(lambda: len(got) == 2 and sub.rejected == len(bad))
        stats = sub.streams.get(key)
        assert [m.position for m in got] == [(0.1,), (0.3,)]
        assert (stats.received, stats.rejected, stats.gaps, stats.lost) == (2, 4, 1, 2)


def test_liveliness_seen_and_withdrawn(endpoint: str) -> None:
    events: list[tuple[str, bool]] = []
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "watcher") as w:
        w.watch_liveliness(w.keys.alive(), lambda s, alive: events.append((s, alive)))
        with Node(bus, "t", "worker"):
            assert wait_until(lambda: ("worker", True) in events)
        assert wait_until(lambda: ("worker", False) in events)


def test_bus_config_errors() -> None:
    with pytest.raises(ConfigError, match="valid: peer, client, router"):
        BusConfig(mode="mesh").validate()
    with pytest.raises(ConfigError, match="needs at least one --connect"):
        BusConfig(mode="client").validate()
