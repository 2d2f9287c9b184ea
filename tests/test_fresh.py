"""Freshness (issue #39, acceptance 1): genuine messages captured and sent again by a stranger are
refused — puts by age and by a per-key, per-signer window; queries by age and a single-use id;
replies by their binding to the query; e-stop resets by their order after the latest e-stop —
counted (``replayed``), reported naming the signer, and never acted on."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from conftest import wait_until
from telesurg.shared import auth
from telesurg.shared.authority import Authority, AuthorityConfig
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.fresh import Freshness, SenderWindow
from telesurg.shared.messages import Command, CommandReply, EStop, Header, SafetyEvent, SafetyLease

S = 1_000_000_000  # ns
SID_A, SID_B = b"A" * 8, b"B" * 8


def _fresh(now: int = 1000 * S, **kw: Any) -> Freshness:
    return Freshness(5000, 500, clock=lambda: now, **kw)


# -- the rules, without a bus ---------------------------------------------------------------------
def test_age_stale_future_and_before_the_receiver_started() -> None:
    f = _fresh(start_ns=1)
    now = 1000 * S
    assert f.age_problem("mapping", now - 4 * S, now) == ""
    assert "s ago (limit 5 s)" in f.age_problem("mapping", now - 6 * S, now + 1 * S)
    assert "in the future" in f.age_problem("mapping", now + S, now)
    assert f.age_problem("mapping", now + S // 4, now) == ""  # within the clock tolerance
    # a message from before this receiver started (beyond the tolerance) is refused however young
    f = _fresh()
    assert "before this receiver started" in f.age_problem("mapping", now - S, now)
    assert f.age_problem("mapping", now - S // 4, now) == ""
    # the clock-offset hook: a signer whose clock runs 3 s ahead
    f.offsets["console"] = 3 * S
    assert f.age_problem("console", now + 3 * S, now) == ""
    assert "before this receiver started" in f.age_problem("console", now + 2 * S, now + S)
    with pytest.raises(ConfigError, match="max_age_ms"):
        Freshness(50, 500)


def test_per_signer_window_seq_and_sessions() -> None:
    f = _fresh(start_ns=1)
    now = 1000 * S
    w = SenderWindow()
    assert f.put_problem("mapping", w, SID_A, 5, now - 10, now) == ""
    f.took(w, SID_A, 5, now - 10)
    assert "seq 5 not after 5" in f.put_problem("mapping", w, SID_A, 5, now - 10, now)
    assert "seq 3 not after 5" in f.put_problem("mapping", w, SID_A, 3, now - 5, now)
    assert f.put_problem("mapping", w, SID_A, 9, now, now) == ""  # a gap forward is fine
    # a new session with an older stamp: an old recording of the signer, refused
    assert "stamped 0.000 s before the signer's last" in f.put_problem("mapping", w, SID_B, 0, now - 20, now)
    assert f.put_problem("mapping", w, SID_B, 0, now, now) == ""  # a restart: newer stamp
    # a latest value (bound to our query) is not aged, but the window still holds
    assert f.put_problem("mapping", w, SID_A, 6, now - 60 * S, now, bound=True) == ""
    assert "not after" in f.put_problem("mapping", w, SID_A, 4, now - 60 * S, now, bound=True)


def test_queries_are_single_use_within_the_age_window() -> None:
    clock = [1000 * S]
    f = Freshness(5000, 500, clock=lambda: clock[0], start_ns=1)
    now = clock[0]
    assert f.query_problem("console", SID_A, 7, now - S, now) == ""
    assert "replayed query (seq 7" in f.query_problem("console", SID_A, 7, now - S, now + S)
    assert f.query_problem("console", SID_A, 8, now - S, now) == ""  # another id
    assert f.query_problem("mapping", SID_A, 7, now - S, now) == ""  # another signer
    # after the window the id is forgotten, and its copy fails the age rule instead
    later = now + 10 * S
    assert "s ago" in f.query_problem("console", SID_A, 7, now - S, later)
    assert f.query_problem("console", SID_A, 9, later, later) == "" and len(f._used) == 1


def test_a_reset_older_than_the_latest_estop_never_clears() -> None:
    a = Authority(AuthorityConfig(operators=["console"]))
    assert a.estop_order("reset", 5) == ""  # nothing latched yet: in order
    assert a.estop_order("estop", 10) == ""
    assert "before the latest e-stop" in a.estop_order("reset", 8)  # an old reset, replayed
    assert a.estop_order("estop", 7) == ""  # an e-stop is always taken …
    assert "before the latest e-stop" in a.estop_order("reset", 9)  # … and the latest one counts
    assert a.estop_order("reset", 11) == "" and a.refused == 2


# -- on a real bus: a stranger without the keyring resends what it captured -----------------------
class Capture:
    """A stranger's zenoh session (no keyring) that records what it sees on a key."""

    def __init__(self, endpoint: str, key: str) -> None:
        self.session = open_session(BusConfig(connect=[endpoint]))
        self.got: list[tuple[bytes, bytes]] = []
        self._sub = self.session.declare_subscriber(key, self._on)

    def _on(self, sample: Any) -> None:
        att = sample.attachment
        self.got.append((sample.payload.to_bytes(), att.to_bytes() if att is not None else b""))

    def replay(self, key: str, items: list[tuple[bytes, bytes]]) -> None:
        for payload, att in items:
            self.session.put(key, payload, attachment=att)

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


def test_replayed_puts_are_refused_counted_and_reported(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint], clock_tolerance_ms=100)
    got: list[int] = []
    events: list[SafetyEvent] = []
    with Node(bus, "t", "watchdog") as wd, Node(bus, "t", "mirror") as mirror:
        key = wd.keys.safety("arm1", "lease")
        spy = Capture(endpoint, key)
        sub = Node(bus, "t", "slave_control")
        try:
            sub.subscribe(key, SafetyLease, lambda m, k: got.append(m.header.seq), sources=["watchdog"])
            mirror.subscribe(sub.keys.events("slave_control"), SafetyEvent, lambda m, k: events.append(m))
            out = wd.outlet(key)
            time.sleep(0.3)
            for _ in range(3):
                out.put(SafetyLease(out.header(), "arm1", True, 250.0, ""))
            assert wait_until(lambda: len(got) == 3 and len(spy.got) == 3)
            captured = list(spy.got)
            stats = sub.streams.get(key)
            spy.replay(key, captured)  # 0.1 s later: the same session's old numbers
            assert wait_until(lambda: stats.replayed == 3)
            assert got == [0, 1, 2] and stats.rejected == 3 and stats.as_dict()["replayed"] == 3
            assert wait_until(lambda: sum(e.kind == "replayed" for e in events) == 3)
            assert all("signed by 'watchdog'" in e.text and "not after 2" in e.text for e in events)
        finally:
            sub.close()
        # the receiver restarts (it forgot the window): what was captured before still fails
        time.sleep(0.2)
        with Node(bus, "t", "slave_control") as sub2:
            got.clear()
            sub2.subscribe(key, SafetyLease, lambda m, k: got.append(m.header.seq), sources=["watchdog"])
            time.sleep(0.3)
            spy.replay(key, captured)
            s2 = sub2.streams.get(key)
            assert wait_until(lambda: s2.replayed == 3)
            assert wait_until(lambda: sum("before this receiver started" in e.text for e in events) == 3)
            out.put(SafetyLease(out.header(), "arm1", True, 250.0, ""))  # the genuine one goes on
            assert wait_until(lambda: got == [3]) and s2.received == 1
        spy.close()


def test_one_identity_between_anothers_resets_nothing(endpoint: str) -> None:
    """The issue's e-stop case: the console's reset, the watchdog's e-stop, then the old reset
    (and the old e-stop) sent again — the latch is never cleared by the replay."""
    bus = BusConfig(connect=[endpoint])
    seen: list[tuple[str, str]] = []
    with Node(bus, "t", "console") as console, Node(bus, "t", "watchdog") as wd:
        key = console.keys.estop
        spy = Capture(endpoint, key)
        with Node(bus, "t", "slave_control") as slave:
            slave.subscribe(key, EStop, lambda m, k: seen.append((m.header.source, m.action)))
            c_out, w_out = console.outlet(key), wd.outlet(key)
            time.sleep(0.3)
            c_out.put(EStop(c_out.header(), "*", "estop", "operator"))
            c_out.put(EStop(c_out.header(), "*", "reset", ""))
            assert wait_until(lambda: len(seen) == 2 and len(spy.got) == 2)
            w_out.put(EStop(w_out.header(), "*", "estop", "watchdog"))
            assert wait_until(lambda: len(seen) == 3)
            spy.replay(key, [spy.got[1]])  # the old reset after another identity's e-stop
            spy.replay(key, spy.got[:2])  # the console's old e-stop, then its old reset
            stats = slave.streams.get(key)
            assert wait_until(lambda: stats.replayed == 3)
            time.sleep(0.1)
            assert seen == [("console", "estop"), ("console", "reset"), ("watchdog", "estop")]
            # a fresh e-stop from any identity still latches, a fresh reset still clears
            w_out.put(EStop(w_out.header(), "*", "estop", "again"))
            assert wait_until(lambda: len(seen) == 4)
            c_out.put(EStop(c_out.header(), "*", "reset", ""))
            assert wait_until(lambda: seen[3:] == [("watchdog", "estop"), ("console", "reset")])
        spy.close()


def _serve(node: Node, key: str, handled: list[str]) -> None:
    rh = node.outlet(node.keys.events(node.service), control=False)

    def handle(cmd: Command) -> CommandReply:
        handled.append(cmd.name)
        return CommandReply(rh.header(), cmd.arm, cmd.name, True, f"done {cmd.name}")

    node.serve(key, Command, handle)


def test_a_replayed_query_is_answered_rejected_and_never_handled(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    handled: list[str] = []
    with Node(bus, "t", "mapping") as mapping, Node(bus, "t", "console") as console:
        key = mapping.keys.mapping_command("arm1")
        _serve(mapping, key, handled)
        # the stranger also answers the key (to read the queries), with nothing
        spy = open_session(BusConfig(connect=[endpoint]))
        queries: list[tuple[bytes, bytes]] = []

        seen: list[int] = []

        def read(q: Any) -> None:
            seen.append(1)
            if q.attachment is not None:  # not the probes below
                queries.append((q.payload.to_bytes(), q.attachment.to_bytes()))

        h = spy.declare_queryable(key, read)
        # the spy's queryable is routed once a query reaches it (the mapping rejects the probes)
        deadline = time.monotonic() + 10
        while not seen and time.monotonic() < deadline:
            list(console.session.get(key, payload=b"probe", timeout=0.5))
        assert seen, "the spy's queryable never received a query"
        rejected0 = mapping.streams.get(key).rejected
        seq = console.outlet(console.keys.events("x"), control=False)
        r = console.request(key, Command(seq.header(), "arm1", "set_scale", ("value=0.5",)), CommandReply)
        deadline = time.monotonic() + 5  # the reply may come before the spy's callback ran
        while not queries and time.monotonic() < deadline:
            time.sleep(0.01)
        assert r.accepted and handled == ["set_scale"] and len(queries) == 1
        h.undeclare()
        for _ in range(2):
            replies = list(spy.get(key, payload=queries[0][0], attachment=queries[0][1], timeout=2.0))
            assert replies and replies[0].err is not None
            assert b"rejected: replayed query" in replies[0].err.payload.to_bytes()
        assert handled == ["set_scale"]
        stats = mapping.streams.get(key)
        assert stats.replayed == 2 and stats.rejected - rejected0 == 2
        spy.close()  # type: ignore[no-untyped-call]


def test_a_reply_to_another_query_is_refused(endpoint: str) -> None:
    """A stranger answering with a genuine signed reply of an earlier query: not bound to this
    query, so the requester skips it (and takes the genuine reply, or fails without one)."""
    bus = BusConfig(connect=[endpoint])
    handled: list[str] = []
    with Node(bus, "t", "slave_control") as slave, Node(bus, "t", "console") as console:
        key = slave.keys.command("arm1")
        # a genuine signed reply, bound to some earlier query (what a stranger could have kept)
        body = CommandReply(Header("slave_control", 0, time.time_ns()), "arm1", "state", True, "OLD").encode()
        old = slave.signer.attach(auth.REPLY, key, body, bind=b"an earlier query's attachment")
        spy = open_session(BusConfig(connect=[endpoint]))
        lock = threading.Lock()
        answered: list[int] = []

        def lie(q: Any) -> None:
            with lock:
                answered.append(1)
            q.reply(key, body, attachment=old)

        h = spy.declare_queryable(key, lie)
        seq = console.outlet(console.keys.events("x"), control=False)
        # the stranger's queryable is reachable once a plain query reaches it (no sleep and hope)
        assert wait_until(lambda: any(True for _ in console.session.get(key, timeout=0.2)) or bool(answered))
        base = len(answered)
        with pytest.raises(MessageError, match="not a reply to this query"):
            console.request(key, Command(seq.header(), "arm1", "state"), CommandReply, 1.0)
        _serve(slave, key, handled)  # now the genuine server answers too

        def genuine() -> bool:
            try:
                return (
                    console.request(key, Command(seq.header(), "arm1", "state"), CommandReply).reason
                    == "done state"
                )
            except MessageError:  # (the genuine queryable not reached yet: only the stranger answered)
                return False

        assert wait_until(genuine)
        for _ in range(3):
            r = console.request(key, Command(seq.header(), "arm1", "state"), CommandReply)
            assert r.reason == "done state"
        # every query reached the stranger too, and its answers were skipped, never taken
        # (a request returns at the genuine reply: the stranger's may not have been looked at)
        assert wait_until(lambda: len(answered) - base >= 5) and console.streams.get(key).unauthenticated >= 1
        h.undeclare()
        spy.close()  # type: ignore[no-untyped-call]


def test_a_late_number_is_reordered_and_a_second_copy_is_a_replay(endpoint: str) -> None:
    """A number the stream skipped, arriving late (a genuine reordering), is dropped and counted
    as reordered, not as a replay; the same message once more is a replay."""
    bus = BusConfig(connect=[endpoint])
    got: list[int] = []
    with Node(bus, "t", "watchdog") as wd, Node(bus, "t", "slave_control") as sub:
        key = wd.keys.safety("arm1", "lease")
        sub.subscribe(key, SafetyLease, lambda m, k: got.append(m.header.seq), sources=["watchdog"])
        time.sleep(0.3)
        msgs = {
            s: SafetyLease(Header("watchdog", s, time.time_ns()), "arm1", True, 250.0, "").encode()
            for s in range(3)
        }
        for s in (0, 2, 1, 1):
            wd.session.put(key, msgs[s], attachment=wd.signer.attach(auth.PUT, key, msgs[s]))
            time.sleep(0.05)
        stats = sub.streams.get(key)
        assert wait_until(lambda: stats.replayed == 1)
        assert got == [0, 2] and stats.reordered == 1 and stats.rejected == 1
