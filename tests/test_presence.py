"""Presence by authenticated session (shared/presence.py): a stranger's liveliness token for a
service does not keep the service alive once the token of its genuine session is gone — the
unit rules, then over real zenoh sessions on loopback."""

from __future__ import annotations

import time

import zenoh
from conftest import wait_until
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import Heartbeat
from telesurg.shared.presence import Presence

A, B, X = b"\x0a" * 8, b"\x0b" * 8, b"\xee" * 8


def _watched() -> tuple[Presence, list[tuple[str, bool]]]:
    p = Presence()
    seen: list[tuple[str, bool]] = []
    p.run(p.watch(lambda s: s == "watchdog", lambda s, alive: seen.append((s, alive))))
    return p, seen


def test_the_genuine_token_vanishing_is_a_death_whatever_other_tokens_exist() -> None:
    p, seen = _watched()
    p.run(p.token("watchdog", A, True))
    p.run(p.authenticated("watchdog", A))
    p.run(p.token("watchdog", X, True))  # a stranger's token, another session id
    assert seen == [("watchdog", True)]
    p.run(p.token("watchdog", A, False))
    assert seen == [("watchdog", True), ("watchdog", False)]
    assert not p.alive("watchdog") and p.vanished("watchdog", A) and not p.vanished("watchdog", X)


def test_before_anything_is_authenticated_presence_is_any_token() -> None:
    p, seen = _watched()
    p.run(p.token("watchdog", X, True))
    assert seen == [("watchdog", True)] and p.alive("watchdog")
    p.run(p.token("watchdog", X, False))
    assert seen == [("watchdog", True), ("watchdog", False)]


def test_a_restart_is_alive_again_a_token_from_before_the_death_never() -> None:
    p, seen = _watched()
    p.run(p.token("watchdog", X, True))  # a stranger's token, declared before the death
    for call in (p.token("watchdog", A, True), p.authenticated("watchdog", A), p.token("watchdog", A, False)):
        p.run(call)
    assert not p.alive("watchdog") and seen[-1] == ("watchdog", False)
    p.run(p.token("watchdog", B, True))  # the restarted watchdog's token (nothing signed yet)
    assert p.alive("watchdog") and seen[-1] == ("watchdog", True)
    p.run(p.authenticated("watchdog", B))  # its first message: the genuine session now
    p.run(p.token("watchdog", B, False))  # and its death is seen at once, X or not
    assert not p.alive("watchdog") and seen[-1] == ("watchdog", False)
    # a message of a dead session still queued somewhere does not bring it back
    assert p.vanished("watchdog", A) and p.vanished("watchdog", B)


def test_other_services_are_not_reported_to_a_watcher() -> None:
    p, seen = _watched()
    p.run(p.token("mapping", A, True))
    assert seen == [] and p.alive("mapping")


def test_a_strangers_tokens_do_not_hide_a_dead_service(endpoint: str) -> None:
    """Real sessions: the watcher authenticates the worker's heartbeats; a plain zenoh client
    (no key) declares ``alive/worker`` and ``alive/worker/<its own sid>``; the worker's node
    closes (its token undeclared, as a killed process's is dropped by the router): the watcher
    reports it dead though the stranger's tokens are still there. (zenoh itself merges tokens of
    one key: the stranger's copy of the exact key is the router ACL's to refuse.)"""
    events: list[tuple[str, bool]] = []
    bus = BusConfig(connect=[endpoint])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    with Node(bus, "t", "watcher") as w, zenoh.open(conf) as stranger:
        w.watch_liveliness(w.keys.alive("worker"), lambda s, alive: events.append((s, alive)))
        w.subscribe(w.keys.heartbeat("worker"), Heartbeat, lambda m, k: None, sources=["worker"])
        worker = Node(bus, "t", "worker")
        try:
            assert wait_until(lambda: ("worker", True) in events)
            assert wait_until(lambda: w.presence.genuine("worker") == worker.signer.sid, 5.0)
            lv = stranger.liveliness()
            tokens = [
                lv.declare_token(w.keys.alive("worker").removesuffix("/*")),
                lv.declare_token(w.keys.alive_token("worker", "5eed5eed5eed5eed")),
            ]
            time.sleep(0.3)
            assert events == [("worker", True)]
        finally:
            worker.close()
        assert wait_until(lambda: ("worker", False) in events), events
        assert w.presence.vanished("worker", worker.signer.sid)
        for t in tokens:
            t.undeclare()
