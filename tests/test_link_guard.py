"""The router's link guard cuts off a flooding link (issue #17, acceptance 2).

zenoh's router drops what its ACL or size caps refuse but keeps the sender's link open, so a
flooder's megabytes keep crossing the host. The link guard (services/router/linkguard.py) shuts
down a client's TCP link once it has sent more than its byte budget. Here:

* in-process, on real loopback TCP sockets: ``tcpi_bytes_received`` is read at the right offset,
  the link over budget is shut down (its peer reads end-of-stream), a quiet link and the
  listening socket are left alone;
* the real router process, 1 MiB puts from a client in a process of its own: the router cuts the
  flooder's link after a bounded amount of data, publishes a signed ``link_cut`` event naming the
  flooder's address and zenoh session, and a genuine low-rate client keeps its link and its
  messages — the same sockets before and after, no cut among them.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from telesurg.services.launcher import free_port
from telesurg.services.router import RouterConfig
from telesurg.services.router.linkguard import LinkCut, LinkGuard
from telesurg.shared.auth import init_keyring
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import SafetyEvent

psutil: Any = pytest.importorskip("psutil")

MB = 1_000_000


def _pair(listener: socket.socket) -> tuple[socket.socket, socket.socket]:
    client = socket.create_connection(listener.getsockname())
    server, _ = listener.accept()
    return client, server


def test_guard_shuts_down_the_link_over_budget_only() -> None:
    with socket.create_server(("127.0.0.1", 0)) as listener:
        loud_client, loud_server = _pair(listener)
        quiet_client, quiet_server = _pair(listener)
        cuts: list[LinkCut] = []
        guard = LinkGuard(1.0, 1.0, cuts.append, ports=frozenset({listener.getsockname()[1]}))
        try:
            assert guard.scan() == []  # nothing received yet
            drained = [0]

            def drain() -> None:  # the receiver reads, as zenoh does
                with contextlib.suppress(OSError):
                    while chunk := loud_server.recv(1 << 20):
                        drained[0] += len(chunk)

            reader = threading.Thread(target=drain, daemon=True)
            reader.start()
            quiet_client.sendall(b"x" * 1000)
            loud_client.sendall(b"y" * (3 * MB))
            assert quiet_server.recv(1000) == b"x" * 1000
            deadline = time.monotonic() + 30
            while drained[0] < 3 * MB and time.monotonic() < deadline:
                time.sleep(0.01)
            guard.scan()
            assert len(cuts) == 1, cuts
            cut = cuts[0]
            assert cut.peer == f"127.0.0.1:{loud_client.getsockname()[1]}"
            assert cut.local == f"127.0.0.1:{listener.getsockname()[1]}"
            assert cut.received_bytes == 3 * MB  # tcpi_bytes_received at offset 128
            assert f"127.0.0.1:{loud_client.getsockname()[1]}" in cut.describe()
            reader.join(5)
            assert not reader.is_alive(), "the receiver's end was not shut down"
            # the loud link is shut down: its client reads end-of-stream (or a reset)
            loud_client.settimeout(5)
            with contextlib.suppress(ConnectionResetError):
                assert loud_client.recv(10) == b""
            # the quiet link and the listener still work
            quiet_client.sendall(b"z")
            assert quiet_server.recv(1) == b"z"
            c, s = _pair(listener)
            c.close()
            s.close()
            guard.scan()
            assert len(cuts) == 1
        finally:
            for sock in (loud_client, loud_server, quiet_client, quiet_server):
                sock.close()


def test_a_repeat_offender_is_cut_at_once_during_its_cool_down() -> None:
    """A zenoh client reconnects by itself with the same session id: its new link is cut at the
    first look while the cool-down lasts, whatever it sent; another session's link is not."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        sessions: dict[str, str] = {}
        cuts: list[LinkCut] = []
        port = listener.getsockname()[1]
        guard = LinkGuard(1.0, 1.0, cuts.append, ports=frozenset({port}), identify=lambda peers: sessions)
        socks = []
        try:
            flooder, server = _pair(listener)
            socks += [flooder, server]
            sessions[f"127.0.0.1:{flooder.getsockname()[1]}"] = "f100d"
            guard.scan()
            flooder.sendall(b"y" * 200_000)  # fits the receive buffer
            _received(guard, server, 200_000)
            flooder.sendall(b"y" * 2_000_000)
            _drain_until_cut(guard, server, cuts, 1)
            assert (cuts[0].session, cuts[0].strikes, cuts[0].banned_s) == ("f100d", 1, 1.0)
            assert "session f100d, cut 1 time, its new links cut for 1 s" in cuts[0].describe()
            # it reconnects (same session) and sends 10 bytes: cut at once, cool-down doubled
            again, server2 = _pair(listener)
            other, server3 = _pair(listener)  # and a genuine client (another session)
            socks += [again, server2, other, server3]
            sessions[f"127.0.0.1:{again.getsockname()[1]}"] = "f100d"
            sessions[f"127.0.0.1:{other.getsockname()[1]}"] = "9e9e"
            again.sendall(b"0123456789")
            other.sendall(b"0123456789")
            guard.scan()
            assert len(cuts) == 2, cuts
            assert (cuts[1].peer, cuts[1].strikes, cuts[1].banned_s) == (
                f"127.0.0.1:{again.getsockname()[1]}",
                2,
                2.0,
            )
        finally:
            for sock in socks:
                sock.close()


def _received(guard: LinkGuard, server: socket.socket, n: int) -> None:
    got = 0
    while got < n:
        got += len(server.recv(1 << 20))
    assert guard.scan() == []


def _drain_until_cut(guard: LinkGuard, server: socket.socket, cuts: list[LinkCut], n: int) -> None:
    server.settimeout(0.2)
    deadline = time.monotonic() + 30
    while len(cuts) < n and time.monotonic() < deadline:
        with contextlib.suppress(TimeoutError, OSError):
            server.recv(1 << 20)
        guard.scan()
    assert len(cuts) == n, cuts


def test_guard_config_is_validated() -> None:
    for bad in ({"link_rx_budget_mb_s": 0.5}, {"link_rx_burst_mb": 0.0}, {"link_guard_period_s": 5.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            RouterConfig(**bad).validate()  # type: ignore[arg-type]
    RouterConfig(link_rx_budget_mb_s=0.0).validate()  # 0: no guard


FLOODER = """
import json, os, sys, time
import zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
payload = os.urandom(1 << 20)
with zenoh.open(conf) as s:
    pub = s.declare_publisher("telesurg/local/slave/arm1/servo_jp")
    print("ready", s.zid(), flush=True)
    sys.stdin.readline()
    end = time.monotonic() + float(sys.argv[2])
    n = 0
    while time.monotonic() < end:
        pub.put(payload)
        n += 1
    print(f"sent {n}", flush=True)
"""


def _ports_to(pid: int, port: int) -> set[int]:
    """Local ports of ``pid``'s established TCP connections to ``port``."""
    out = set()
    for c in psutil.Process(pid).net_connections(kind="tcp"):
        if c.raddr and c.raddr.port == port and c.status == psutil.CONN_ESTABLISHED:
            out.add(c.laddr.port)
    return out


@pytest.mark.process
def test_router_cuts_off_a_flooding_client_and_keeps_the_genuine_one(tmp_path: Path) -> None:
    keys = init_keyring(tmp_path / "keys", ("console", "router"))
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    budget, burst = 5.0, 5.0
    argv = [sys.executable, "-m", "telesurg.services.cli", "router", "--listen", ep, "--keyring", str(keys)]
    argv += ["--set", f"link_rx_budget_mb_s={budget}", "--set", f"link_rx_burst_mb={burst}"]
    router_log = tmp_path / "router.log"
    with router_log.open("wb") as log_file:
        router = subprocess.Popen(argv, stdout=log_file, stderr=subprocess.STDOUT)
    flooder = None
    try:
        bus = BusConfig(connect=[ep], keys_dir=str(keys))
        deadline = time.monotonic() + 60
        while True:  # the router process is up once a session opens
            try:
                node = Node(bus, "local", "console")
                break
            except ConnectionError:
                assert router.poll() is None, router_log.read_text()
                assert time.monotonic() < deadline, "the router did not come up within 60 s"
                time.sleep(0.5)
        with node:
            events: list[SafetyEvent] = []
            node.subscribe(node.keys.events("router"), SafetyEvent, lambda m, k: events.append(m))
            # a genuine low-rate stream, 100 Hz of 16 bytes, and a subscriber of the flooded key
            genuine: list[float] = []
            big = [0]
            session = node.session
            session.declare_subscriber("telesurg/local/genuine", lambda s: genuine.append(time.monotonic()))

            def on_slave(sample: Any) -> None:
                if len(sample.payload) > 64 * 1024:
                    big[0] += 1

            session.declare_subscriber("telesurg/local/slave/**", on_slave)
            pub = session.declare_publisher("telesurg/local/genuine")
            stop = threading.Event()

            def tick() -> None:
                while not stop.wait(0.01):
                    pub.put(b"0123456789abcdef")

            ticker = threading.Thread(target=tick, daemon=True)
            ticker.start()
            time.sleep(1.0)
            genuine_ports = _ports_to(os.getpid(), port)
            assert genuine_ports, "the test's own session has no link to the router"

            flooder = subprocess.Popen(
                [sys.executable, "-c", FLOODER, ep, "4"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
            assert flooder.stdout is not None and flooder.stdin is not None
            ready, flooder_zid = flooder.stdout.readline().split()
            assert ready == "ready"
            flooder_ports = _ports_to(flooder.pid, port)
            n_before = len(genuine)
            flooder.stdin.write("go\n")
            flooder.stdin.flush()
            while flooder.poll() is None:  # the ports of the links it reconnects with
                try:
                    flooder_ports |= _ports_to(flooder.pid, port)
                except psutil.Error:
                    break
                time.sleep(0.02)
            out, _ = flooder.communicate(timeout=60)
            assert "sent" in out, out
            time.sleep(1.0)
            n_during = len(genuine) - n_before
            stop.set()
            ticker.join()

            assert router.poll() is None, "the router exited"
            cut_text = [e.text for e in events if e.kind == "link_cut"]
            print(f"{len(cut_text)} link_cut events; first: {cut_text[:1]}")
            print(f"flooder links seen {sorted(flooder_ports)}, genuine links {sorted(genuine_ports)}")
            print(f"genuine messages during the flood: {n_during}; 1 MiB messages delivered: {big[0]}")
            assert cut_text, f"no link_cut event; router log:\n{router_log.read_text()[-3000:]}"
            assert all(e.severity == "warning" for e in events if e.kind == "link_cut")
            cut_ports = set()
            for text in cut_text:
                m = re.search(r"from 127\.0\.0\.1:(\d+) .*: ([\d.]+) MB received", text)
                assert m, text
                cut_ports.add(int(m.group(1)))
                # bounded: the burst and budget, plus what loopback carries between two looks
                assert float(m.group(2)) < 400, text
            assert cut_ports & flooder_ports, (cut_ports, flooder_ports)
            # the flooder's session is named, and it reconnects by itself: its new links are cut at once
            assert f"session {flooder_zid}, cut 1 time," in cut_text[0], cut_text[0]
            print("repeat cuts:", [t for t in cut_text if "cut 1 time," not in t][:2])
            assert not cut_ports & genuine_ports, "a genuine link was cut"
            # the genuine client kept its links (the same sockets) and its messages
            assert genuine_ports <= _ports_to(os.getpid(), port)
            assert n_during > 0
            n_after = len(genuine)
            pub.put(b"still here")
            time.sleep(0.5)
            assert len(genuine) > n_after
            assert big[0] == 0  # (the size cap: no 1 MiB message reached a subscriber)
        assert "panic" not in router_log.read_text().lower()
    finally:
        if flooder is not None:
            if flooder.poll() is None:
                flooder.kill()
            flooder.communicate()
        router.send_signal(signal.SIGINT)
        try:
            router.wait(15)
        except subprocess.TimeoutExpired:
            router.kill()
            router.wait()
    log_text = router_log.read_text()
    assert re.search(r"link guard: \d+ links cut", log_text), log_text[-2000:]
    json.dumps(cut_text)  # (plain strings)
