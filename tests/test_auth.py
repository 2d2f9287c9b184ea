"""Message authentication (issue #17): the keyring, HMAC authenticators in the zenoh attachment,
rejection before decoding, sequence windows only authenticated messages move, session ids."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import wait_until
from telesurg.shared import auth
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.messages import (
    Command,
    CommandReply,
    Header,
    JointSetpoint,
    MasterButtons,
    SafetyEvent,
    SafetyLease,
)
from telesurg.shared.streams import StreamStats

KEY = "telesurg/t/slave/arm1/servo_jp"


@pytest.fixture
def ring(tmp_path: Path) -> auth.Keyring:
    return auth.Keyring.load(auth.init_keyring(tmp_path / "keys", ("mapping", "watchdog")))


def _sp(src: str = "mapping", seq: int = 0, q: float = 0.1) -> bytes:
    return JointSetpoint(Header(src, seq, time.time_ns()), ("j1",), (q,), follow=True).encode()


# -- keyring -----------------------------------------------------------------------------------
def test_keyring_files_are_private_and_hold_random_keys(tmp_path: Path) -> None:
    d = auth.init_keyring(tmp_path / "k", ("mapping", "watchdog"))
    assert stat.S_IMODE(d.stat().st_mode) == 0o700
    files = sorted(d.iterdir())
    assert [f.name for f in files] == ["mapping.key", "watchdog.key"]
    assert all(stat.S_IMODE(f.stat().st_mode) == 0o600 for f in files)
    ring = auth.Keyring.load(d)
    assert ring.keys["mapping"] != ring.keys["watchdog"] and len(ring.keys["mapping"]) == 32
    auth.init_keyring(d, ("mapping",))  # kept, not replaced
    assert auth.Keyring.load(d).keys["mapping"] == ring.keys["mapping"]
    os.chmod(d / "mapping.key", 0o644)
    with pytest.raises(ConfigError, match="open to others"):
        auth.Keyring.load(d)
    with pytest.raises(ConfigError, match="telesurg keys init"):
        auth.Keyring.load(tmp_path / "none")


def test_a_node_without_a_keyring_refuses_to_start(endpoint: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no keyring at .*telesurg keys init"):
        Node(BusConfig(connect=[endpoint], keys_dir=str(tmp_path / "absent")), "t", "watchdog")


def test_keys_cli_init_list_export_import(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}

    def cli(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "telesurg.services.cli", "keys", *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
        )

    a, b = tmp_path / "slave-site", tmp_path / "console-host"
    assert cli("init", str(a)).returncode == 0
    listed = cli("list", str(a)).stdout.split()
    assert {"watchdog", "mapping", "slave_control", "console", "master_capture"} <= set(listed)
    console_key = auth.Keyring.load(a).keys["console"]
    pack = tmp_path / "pack"
    out = cli("export", "master_capture", "console", "--to", "console", "--keys", str(a), "--out", str(pack))
    assert out.returncode == 0, out.stderr
    assert cli("import", str(pack), "--keys", str(b)).returncode == 0
    site, host = auth.Keyring.load(a), auth.Keyring.load(b)
    # the console host has its own identities' keys and a link, nothing of the site's identities
    assert host.keys == {"console": console_key, "master_capture": host.keys["master_capture"]}
    assert set(host.links) == {"slave-site"} and host.links["slave-site"].claims == ("*",)
    # the site no longer holds them: it verifies them through the link to the console host
    assert "console" not in site.keys and "master_capture" not in site.keys
    assert site.links["console"].claims == ("master_capture", "console")
    assert "link to host console: signs as master_capture, console" in cli("list", str(a)).stdout
    again = cli("export", "console", "--to", "console", "--keys", str(a), "--out", str(tmp_path / "p2"))
    assert again.returncode == 2 and "no key for 'console'" in again.stderr
    bad = cli("list", str(tmp_path / "nope"))
    assert bad.returncode == 2 and "telesurg keys init" in bad.stderr


# -- authenticators ------------------------------------------------------------------------------
def test_sign_verify_and_every_forgery_fails(ring: auth.Keyring, tmp_path: Path) -> None:
    signer = auth.Signer("mapping", ring.keys["mapping"])
    payload = _sp()
    att = signer.attach(auth.PUT, KEY, payload)
    who = auth.verify(ring, auth.PUT, KEY, payload, att)
    assert (who.signer, who.sid) == ("mapping", signer.sid)
    cases = {
        "unsigned": (auth.PUT, KEY, payload, None),
        "tampered payload": (auth.PUT, KEY, payload.replace(b"mapping", b"mappinG"), att),
        "tampered mac": (auth.PUT, KEY, payload, att[:-1] + bytes([att[-1] ^ 1])),
        "replayed on another key": (auth.PUT, "telesurg/t/slave/arm2/servo_jp", payload, att),
        "replayed as a query": (auth.QUERY, KEY, payload, att),
        "truncated": (auth.PUT, KEY, payload, att[:10]),
    }
    for what, (kind, key, p, a) in cases.items():
        with pytest.raises(auth.AuthError):
            auth.verify(ring, kind, key, p, a)
        assert what
    other = auth.Keyring.load(auth.init_keyring(tmp_path / "other", ("mapping",)))
    wrong_key = auth.Signer("mapping", other.keys["mapping"]).attach(auth.PUT, KEY, payload)
    with pytest.raises(auth.AuthError, match="bad authenticator"):
        auth.verify(ring, auth.PUT, KEY, payload, wrong_key)
    stranger = auth.Signer("intruder", b"\x00" * 32).attach(auth.PUT, KEY, payload)
    with pytest.raises(auth.AuthError, match="unknown signer 'intruder'"):
        auth.verify(ring, auth.PUT, KEY, payload, stranger)
    # the sid is covered: the same MAC under another session id fails
    forged_sid = att[:2] + bytes(8) + att[10:]
    with pytest.raises(auth.AuthError, match="bad authenticator"):
        auth.verify(ring, auth.PUT, KEY, payload, forged_sid)


def test_a_key_added_later_is_found_and_unknown_names_are_looked_up_rarely(ring: auth.Keyring) -> None:
    assert ring.key("console") is None
    auth.write_key(ring.path, "console")
    assert ring.key("console") is None  # looked up a moment ago: not again within a second
    time.sleep(auth.LOOKUP_INTERVAL_S + 0.05)
    assert ring.key("console") is not None


# -- sequence windows ------------------------------------------------------------------------------
def test_a_new_session_id_is_a_restart_and_seq_zero_is_not() -> None:
    sid1, sid2 = auth.new_sid(), auth.new_sid()
    s = StreamStats()
    t = 1_000
    assert all(s.accept("mapping", i, 0, sid1, t + i) for i in range(100))
    assert not s.accept("mapping", 0, 0, sid1, t + 200)  # seq 0 in the same session: old, dropped
    assert s.restarts == 0 and s.lost == 0
    assert s.accept("mapping", 0, 0, sid2, t + 300)  # the publisher restarted: new session
    assert s.restarts == 1 and s.lost == 0 and s.last_seq == 0
    # a message of the earlier session sent again (older stamp) cannot switch back to it
    assert not s.accept("mapping", 100, 0, sid1, t + 99)
    assert s.stale_sessions == 1 and s.last_seq == 0 and s.restarts == 1


# -- the bus: reject before decoding, count, report, change nothing ------------------------------
def test_forged_messages_change_nothing_of_the_genuine_stream(endpoint: str) -> None:
    """Unsigned, wrongly signed and signer ≠ src messages — with a seq jump, seq 0 — are rejected
    before decoding, counted as unauthenticated, reported once as an event naming the key and the
    claimed signer, and leave the window, source, loss counters and arrival time untouched."""
    bus = BusConfig(connect=[endpoint])
    got: list[float] = []
    events: list[SafetyEvent] = []
    with (
        Node(bus, "t", "slave_control") as sub,
        Node(bus, "t", "mapping") as pub,
        Node(bus, "t", "intruder") as bad,
        Node(bus, "t", "mirror") as mirror,
    ):
        key = sub.keys.slave("arm1", "servo_jp")
        sub.subscribe(key, JointSetpoint, lambda m, k: got.append(m.position[0]), sources=["mapping"])
        mirror.subscribe(sub.keys.events("slave_control"), SafetyEvent, lambda m, k: events.append(m))
        out = pub.outlet(key)
        time.sleep(0.3)
        for _ in range(3):
            out.put(JointSetpoint(out.header(), ("j1",), (0.1,), follow=True))
        stats = sub.streams.get(key)
        assert wait_until(lambda: stats.received == 3)
        before = (stats.last_seq, stats.source, stats.sid, stats.last_rx_ns, stats.lost, stats.restarts)
        # 1. unsigned, src = mapping, a seq jump and seq 0
        pub.session.put(key, _sp("mapping", 99_000, 2.0))
        pub.session.put(key, _sp("mapping", 0, 2.0))
        # 2. signed by an identity the receiver knows, claiming src = mapping
        forger = auth.Signer("intruder", bad.keyring.keys["intruder"])
        p = _sp("mapping", 99_001, 2.0)
        bad.session.put(key, p, attachment=forger.attach(auth.PUT, key, p))
        # 3. a made-up signer "mapping" with a guessed key
        p = _sp("mapping", 99_002, 2.0)
        bad.session.put(key, p, attachment=auth.Signer("mapping", b"\x01" * 32).attach(auth.PUT, key, p))
        assert wait_until(lambda: stats.unauthenticated == 4)
        time.sleep(0.2)
        assert (
            stats.last_seq,
            stats.source,
            stats.sid,
            stats.last_rx_ns,
            stats.lost,
            stats.restarts,
        ) == before
        assert stats.rejected == 4 and stats.foreign == 0 and got == [0.1] * 3
        out.put(JointSetpoint(out.header(), ("j1",), (0.3,), follow=True))  # the genuine one goes on
        assert wait_until(lambda: got[-1:] == [0.3]) and stats.gaps == 0 and stats.lost == 0
        # each of the 4 is reported (the first five per key are); the two sessions' puts may
        # arrive in either order
        assert wait_until(lambda: sum(e.kind == "unauthenticated" for e in events) >= 4)
        texts = [e.text for e in events if e.kind == "unauthenticated"]
        assert all(key in t for t in texts)
        assert sum("'?'" in t and "no authenticator" in t for t in texts) == 2
        assert any("'intruder'" in t and "not the header src" in t for t in texts)


def test_queries_and_replies_are_authenticated(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    seen: list[str] = []
    with Node(bus, "t", "slave_control") as slave, Node(bus, "t", "console") as console:
        key = slave.keys.command("arm1")
        rh = slave.outlet(slave.keys.events("slave_control"), control=False)

        def handle(cmd: Command) -> CommandReply:
            seen.append(cmd.header.source)
            return CommandReply(rh.header(), cmd.arm, cmd.name, True, "")

        slave.serve(key, Command, handle)
        o = console.outlet(key, control=False)
        time.sleep(0.2)
        assert console.request(key, Command(o.header(), "arm1", "state"), CommandReply).accepted
        # unsigned: refused with the reason, never handled
        forged = Command(Header("console", 5, time.time_ns()), "arm1", "reset").encode()
        replies = list(console.session.get(key, payload=forged, timeout=2.0))
        assert (
            replies
            and replies[0].err is not None
            and b"no authenticator" in replies[0].err.payload.to_bytes()
        )
        assert seen == ["console"] and slave.streams.get(key).unauthenticated == 1
        # a reply that is not signed by its src is refused by the requester
        with Node(bus, "t", "imposter") as imp:
            fake = f"telesurg/t/slave/{'arm7'}/command"

            def lie(q: object) -> None:
                body = CommandReply(
                    Header("slave_control", 0, time.time_ns()), "arm7", "x", True, ""
                ).encode()
                q.reply(fake, body)  # type: ignore[attr-defined]

            h = imp.session.declare_queryable(fake, lie)
            time.sleep(0.2)
            with pytest.raises(MessageError, match="no authenticator"):
                console.request(fake, Command(o.header(), "arm7", "x"), CommandReply)
            h.undeclare()


def test_a_restarted_publisher_is_a_new_session(endpoint: str) -> None:
    """A genuine restart (new process, seq from 0) is delivered at once and counted as one
    restart, with no loss; a lease stream's window did not move on anything forged."""
    bus = BusConfig(connect=[endpoint])
    got: list[int] = []
    with Node(bus, "t", "slave_control") as sub:
        key = sub.keys.safety("arm1", "lease")
        sub.subscribe(key, SafetyLease, lambda m, k: got.append(m.header.seq), sources=["watchdog"])
        for _ in range(2):
            with Node(bus, "t", "watchdog") as wd:
                out = wd.outlet(key)
                time.sleep(0.3)
                for _ in range(5):
                    out.put(SafetyLease(out.header(), "arm1", True, 100.0, ""))
                assert wait_until(lambda: len(got) in (5, 10))
        stats = sub.streams.get(key)
        assert wait_until(lambda: got == [0, 1, 2, 3, 4] * 2), got
        assert (stats.restarts, stats.lost, stats.gaps, stats.rejected) == (1, 0, 0, 0)


def test_the_recorder_writes_only_authenticated_samples(endpoint: str, tmp_path: Path) -> None:
    """A forgery on the bus never reaches a recording (a replay would publish it as genuine)."""
    from telesurg.services.record import Recorder

    bus = BusConfig(connect=[endpoint])
    with Node(bus, "t", "record") as node, Node(bus, "t", "master_capture") as pub:
        rec = Recorder(tmp_path / "r.mcap", "t")
        with rec:
            rec.subscribe(node.session, node.keys.all, node.keyring)
            key = pub.keys.master("m1", "buttons")
            out = pub.outlet(key)
            time.sleep(0.3)
            for _ in range(3):
                out.put(MasterButtons(out.header(), True, True))
                forged = MasterButtons(Header("master_capture", 99, time.time_ns()), False, True)
                pub.session.put(key, forged.encode())
            assert wait_until(lambda: rec.unauthenticated == 3)
            time.sleep(0.3)
            summary = rec.close()
    assert summary["master/m1/buttons"]["messages"] == 3
