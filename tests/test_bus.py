"""In-process zenoh on loopback: strict decoding at the subscriber, liveliness, sequence gaps."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from conftest import wait_until
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import Header, JointSetpoint, JointState


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


def test_only_allowed_sources_reach_the_callback(endpoint: str) -> None:
    got: list[str] = []
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "sub") as sub, Node(bus, "t", "mapping") as good, Node(bus, "t", "intruder") as bad:
        key = sub.keys.slave("arm1", "servo_jp")
        sub.subscribe(key, JointSetpoint, lambda m, k: got.append(m.header.source), sources=["mapping"])
        g, b = good.outlet(key), bad.outlet(key)
        time.sleep(0.3)
        for _ in range(3):
            g.put(JointSetpoint(g.header(), ("j1",), (0.1,), follow=True))
            b.put(JointSetpoint(b.header(), ("j1",), (0.9,), follow=True))
        stats = sub.streams.get(key)
        assert wait_until(lambda: len(got) == 3 and stats.foreign == 3)
        assert got == ["mapping"] * 3 and stats.rejected == 3 and stats.gaps == 0


def test_a_single_forged_sequence_jump_cannot_silence_the_stream() -> None:
    from telesurg.shared.streams import MAX_SEQ_JUMP, StreamStats

    s = StreamStats()
    assert all(s.accept("mapping", i) for i in range(5))
    assert not s.accept("mapping", 10**12)  # forged: far ahead, unconfirmed → dropped, counted
    assert s.accept("mapping", 5) and s.rejected == 1 and s.gaps == 0  # genuine stream goes on
    assert not s.accept("mapping", 5)  # duplicate
    assert not s.accept("mapping", 3)  # old
    assert s.reordered == 2
    far = 5 + MAX_SEQ_JUMP + 10
    assert not s.accept("mapping", far)
    assert s.accept("mapping", far + 1)  # the next message confirms a genuine renumbering
    assert s.jumps == 1 and s.lost == far - 5


def test_two_subscriptions_to_one_key_both_get_every_message(endpoint: str) -> None:
    a: list[int] = []
    b: list[int] = []
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "sub") as sub, Node(bus, "t", "pub") as pub:
        key = sub.keys.slave("arm1", "servo_jp")
        sub.subscribe(key, JointSetpoint, lambda m, k: a.append(m.header.seq))
        sub.subscribe(key, JointSetpoint, lambda m, k: b.append(m.header.seq))
        out = pub.outlet(key)
        time.sleep(0.3)
        for _ in range(20):
            out.put(JointSetpoint(out.header(), ("j1",), (0.1,), follow=True))
        assert wait_until(lambda: len(a) == 20 and len(b) == 20)
        assert a == b == list(range(20)) and sub.streams.get(key).reordered == 0


def test_echo_round_trip(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "watchdog") as wd, Node(bus, "t", "master_capture"):
        time.sleep(0.2)
        rtts = [wd.echo_rtt("master_capture", timeout=1.0) for _ in range(5)]
        assert all(r is not None and 0.0 < r < 1.0 for r in rtts), rtts
        assert wd.echo_rtt("nobody", timeout=0.2) is None  # no such service: no reply


def test_command_queryable_answers_refuses_and_survives(endpoint: str) -> None:
    from telesurg.shared.errors import MessageError
    from telesurg.shared.messages import Command, CommandReply

    bus = BusConfig(connect=[endpoint])
    seen: list[Command] = []

    def handle(cmd: Command) -> CommandReply:
        seen.append(cmd)
        if cmd.name == "boom":
            raise RuntimeError("bug")
        ok = cmd.name == "teach_trocar"
        return CommandReply(h.header(), cmd.arm, cmd.name, ok, "" if ok else f"{cmd.name} refused: not now")

    with Node(bus, "t", "slave_control") as slave, Node(bus, "t", "console") as console:
        key = slave.keys.command("arm1")
        h = slave.outlet(slave.keys.events("slave_control"), control=False)  # a header source
        slave.serve(key, Command, handle, sources=["console"])
        out = console.outlet(key, control=False)
        time.sleep(0.2)
        r = console.request(key, Command(out.header(), "arm1", "teach_trocar"), CommandReply)
        assert r.accepted and r.name == "teach_trocar"
        r = console.request(key, Command(out.header(), "arm1", "insert", ("speed=0.01",)), CommandReply)
        assert not r.accepted and "insert refused" in r.reason
        with pytest.raises(MessageError, match="handler error: RuntimeError"):
            console.request(key, Command(out.header(), "arm1", "boom"), CommandReply)
        console.session.get(key, payload=b"garbage")  # malformed: answered with an error
        with Node(bus, "t", "intruder") as intruder:
            o2 = intruder.outlet(key, control=False)
            with pytest.raises(MessageError, match="may not send command"):
                intruder.request(key, Command(o2.header(), "arm1", "teach_trocar"), CommandReply)
        assert wait_until(lambda: slave.streams.get(key).rejected == 2)
        assert [c.name for c in seen] == ["teach_trocar", "insert", "boom"]
        # the service is still answering
        assert console.request(key, Command(out.header(), "arm1", "teach_trocar"), CommandReply).accepted
        with pytest.raises(TimeoutError, match="no reply"):
            console.request(
                console.keys.command("arm9"), Command(out.header(), "arm9", "x"), CommandReply, 0.3
            )


def test_a_latest_outlet_gives_a_late_subscriber_the_current_value_once(endpoint: str) -> None:
    from telesurg.shared.messages import TeleopState

    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "mapping") as pub:
        key = pub.keys.mapping("arm1", "teleop_state")
        out = pub.outlet(key, control=False, latest=True)
        plain = pub.outlet(pub.keys.mapping("arm2", "teleop_state"), control=False)
        for state in ("IDLE", "ENABLED"):
            out.put(TeleopState(out.header(), "m1", "arm1", state, "IDLE", "", 1, 0.5, 1.0, "cartesian"))
        plain.put(TeleopState(plain.header(), "m1", "arm2", "ENABLED", "IDLE", "", 1, 0.5, 1.0, "cartesian"))
        with Node(bus, "t", "console") as sub:
            got: list[tuple[str, int]] = []
            sub.subscribe(
                sub.keys.mapping("*", "teleop_state"),
                TeleopState,
                lambda m, k: got.append((m.slave, m.header.seq)),
                sources=["mapping"],
                latest=True,
            )
            # the current value at once (only from the latest outlet: nothing was published since)
            assert wait_until(lambda: got == [("arm1", 1)], 2.0), got
            out.put(
                TeleopState(out.header(), "m1", "arm1", "HOLDING", "ENABLED", "", 2, 0.5, 1.0, "cartesian")
            )
            assert wait_until(lambda: got == [("arm1", 1), ("arm1", 2)]), got
            stats = sub.streams.get(key)
            assert (stats.received, stats.gaps, stats.reordered, stats.rejected) == (2, 0, 0, 0)
        with pytest.raises(ValueError, match="latest and polled"):
            pub.subscribe(key, TeleopState, lambda m, k: None, latest=True, polled=True)


def test_a_polled_stream_keeps_its_newest_few_and_a_poll_can_be_bounded(endpoint: str) -> None:
    """``keep``: a 500 Hz stream read at a 20 Hz tick checks only its newest few (the rest dropped
    unread, a gap once the stream is known); ``poll(limit)``: at most that many per stream a call."""
    from telesurg.shared.messages import CartesianWrench

    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "slave_control") as pub, Node(bus, "t", "console") as sub:
        fast, slow = pub.keys.slave("arm1", "measured_cf"), pub.keys.slave("arm2", "measured_cf")
        got: dict[str, list[float]] = {fast: [], slow: []}

        def on(m: CartesianWrench, k: str) -> None:
            got[k].append(m.force[2])

        sub.subscribe(fast, CartesianWrench, on, sources=["slave_control"], polled=True, keep=4)
        sub.subscribe(slow, CartesianWrench, on, sources=["slave_control"], polled=True)
        with pytest.raises(ValueError, match="keep=0 outside"):
            sub.subscribe(fast, CartesianWrench, on, polled=True, keep=0)
        time.sleep(0.3)
        outs = {k: pub.outlet(k) for k in (fast, slow)}
        for i in range(1, 21):
            for out in outs.values():
                out.put(CartesianWrench(out.header(), "base", (0.0, 0.0, float(i))))
        time.sleep(0.5)
        assert sub.poll(limit=8) == 4 + 8
        assert got[fast] == [17.0, 18.0, 19.0, 20.0]  # the newest four, in order
        assert got[slow] == [float(i) for i in range(1, 9)]  # the first eight; the rest wait
        assert sub.poll() == 12 and got[slow][-1] == 20.0
        for i in range(21, 41):  # once the stream is known, the dropped ones show as a gap
            outs[fast].put(CartesianWrench(outs[fast].header(), "base", (0.0, 0.0, float(i))))
        time.sleep(0.5)
        assert sub.poll() == 4 and got[fast][-1] == 40.0
        stats = sub.streams.get(fast)
        assert stats.received == 8 and stats.gaps >= 1, stats


def test_a_state_sample_goes_out_on_change_again_after_it_and_periodically() -> None:
    """A master's buttons on the datagram link: a change goes out and again in the next
    DATAGRAM_REPEAT calls (a lost packet loses no clutch release), else every ``every`` calls."""
    from telesurg.shared.bus import DATAGRAM_REPEAT, Resend

    r = Resend(every=10)
    sent = [r.due(s) for s in ["up"] * 20 + ["down"] * 20]
    assert sent[: DATAGRAM_REPEAT + 1] == [True] * (DATAGRAM_REPEAT + 1)
    assert [i for i, x in enumerate(sent) if x][DATAGRAM_REPEAT + 1 :] == [
        9,
        19,
        20,
        21,
        22,
        23,
        24,
        25,
        29,
        39,
    ]
    r.reset()  # readings resume after a gap: the next goes out, and again after it
    assert [r.due("down") for _ in range(DATAGRAM_REPEAT + 2)] == [True] * (DATAGRAM_REPEAT + 1) + [False]


def test_a_datagram_stream_is_sealed_on_the_wire_and_opened_by_the_subscriber(tmp_path: Path) -> None:
    """A pose on the datagram link (a second, UDP session to the router): a node's subscriber gets
    the pose; a raw subscriber on the router, which holds no key, sees only sealed bytes."""
    from telesurg.services.launcher import free_port
    from telesurg.shared.auth import SEALED, init_keyring
    from telesurg.shared.messages import CartesianPose

    keys = str(init_keyring(tmp_path / "keys"))
    tcp, udp = f"tcp/127.0.0.1:{free_port()}", f"udp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[tcp, udp]))
    got: list[CartesianPose] = []
    raw: list[bytes] = []
    try:
        sub_bus = BusConfig(connect=[tcp], keys_dir=keys)
        pub_bus = BusConfig(connect=[tcp], datagram=udp, keys_dir=keys)
        with Node(sub_bus, "t", "mapping") as sub, Node(pub_bus, "t", "master_capture") as pub:
            key = pub.keys.master("m1", "measured_cp")
            sub.subscribe(key, CartesianPose, lambda m, k: got.append(m))
            _raw = router.declare_subscriber(key, lambda s: raw.append(s.payload.to_bytes()))
            out = pub.outlet(key, datagram=True)
            deadline = time.monotonic() + 5.0
            while len(got) < 5 and time.monotonic() < deadline:
                out.put(CartesianPose(out.header(), "master", (0.125, -0.25, 0.5)))
                time.sleep(0.02)
    finally:
        router.close()  # type: ignore[no-untyped-call]
    assert len(got) >= 5 and got[-1].position == (0.125, -0.25, 0.5)
    assert raw and all(p[0] == SEALED and b"master" not in p for p in raw)
