"""LinkImpairer: an echo server on loopback behind the impairer; pass, cut, delay, reset, close, CLI."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from telesurg.tools.bench.impair import ImpairerProcess, LinkImpairer, parse_hostport
from telesurg.tools.bench.netprofile import LinkProfile

pytestmark = pytest.mark.timeout(30)

REPO = Path(__file__).resolve().parents[1]


class EchoServer:
    """Threaded TCP echo server on 127.0.0.1; counts connections and bytes received."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.address: tuple[str, int] = self.sock.getsockname()[:2]
        self.lock = threading.Lock()
        self.accepted = 0
        self.finished = 0  # connections whose client side reached EOF / error
        self.received = 0
        self.conns: list[socket.socket] = []
        self.threads: list[threading.Thread] = []
        self.thread = threading.Thread(target=self._accept_loop, name="echo-accept", daemon=True)
        self.thread.start()

    def _accept_loop(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            with self.lock:
                self.accepted += 1
                self.conns.append(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name="echo-conn", daemon=True)
            self.threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            while True:
                data = conn.recv(65536)
                if not data:
                    break
                with self.lock:
                    self.received += len(data)
                conn.sendall(data)
        except OSError:
            pass
        finally:
            with self.lock:
                self.finished += 1

    def close_connections(self) -> None:
        with self.lock:
            conns = list(self.conns)
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes accept() on Linux
        self.sock.close()
        self.thread.join(2.0)
        self.close_connections()
        for t in self.threads:
            t.join(2.0)
        for conn in self.conns:
            conn.close()


def wait_until(pred: Callable[[], bool], timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def recv_exact(sock: socket.socket, n: int, timeout: float = 3.0) -> bytes:
    sock.settimeout(timeout)
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(65536, n - len(buf)))
        if not chunk:
            raise EOFError(f"EOF after {len(buf)} of {n} bytes")
        buf += chunk
    return bytes(buf)


def nothing_arrives(sock: socket.socket, within: float) -> bool:
    sock.settimeout(within)
    try:
        data = sock.recv(65536)
    except TimeoutError:
        return True
    raise AssertionError(f"expected nothing, got {data[:40]!r} ({len(data)} bytes)")


def sees_close(sock: socket.socket, timeout: float = 3.0) -> bool:
    """True once the peer closed or reset the connection."""
    sock.settimeout(timeout)
    try:
        while sock.recv(65536):
            pass
    except (ConnectionResetError, ConnectionAbortedError, BrokenPipeError):
        return True
    except TimeoutError:
        return False
    return True


def connect(link: LinkImpairer) -> socket.socket:
    sock = socket.create_connection(link.address, timeout=3.0)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def round_trip(sock: socket.socket, payload: bytes) -> bytes:
    sock.sendall(payload)
    return recv_exact(sock, len(payload))


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


@pytest.fixture
def echo() -> Iterator[EchoServer]:
    server = EchoServer()
    try:
        yield server
    finally:
        server.close()


@pytest.fixture
def link(echo: EchoServer) -> Iterator[LinkImpairer]:
    with LinkImpairer(echo.address) as imp:
        yield imp


# ------------------------------------------------------------------ pass-through


def test_address_and_endpoint(link: LinkImpairer) -> None:
    host, port = link.address
    assert host == "127.0.0.1" and port > 0
    assert link.endpoint == f"tcp/127.0.0.1:{port}"
    assert link.state == "pass"
    assert link.delay_ms == 0


def test_pass_through_round_trips_bytes_exactly(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        for payload in (b"hello", bytes(range(256)), b"\x00" * 1000):
            assert round_trip(sock, payload) == payload
    total = 5 + 256 + 1000
    assert link.stats()["accepted"] == 1
    assert echo.received == total
    # the counters are updated just after each send: the client may read a moment earlier
    assert wait_until(lambda: link.stats()["bytes_up"] == link.stats()["bytes_down"] == total)


def test_pass_through_1mb(link: LinkImpairer) -> None:
    payload = random.Random(7).randbytes(1 << 20)
    with connect(link) as sock:
        sender = threading.Thread(target=sock.sendall, args=(payload,), daemon=True)
        sender.start()
        echoed = recv_exact(sock, len(payload), timeout=4.0)
        sender.join(2.0)
    assert echoed == payload
    assert wait_until(lambda: link.stats()["bytes_up"] == link.stats()["bytes_down"] == 1 << 20)


def test_many_small_messages_keep_order(link: LinkImpairer) -> None:
    msgs = [f"msg-{i:05d};".encode() for i in range(2000)]
    with connect(link) as sock:
        for m in msgs:
            sock.sendall(m)
        assert recv_exact(sock, sum(map(len, msgs))) == b"".join(msgs)


def test_two_connections_are_independent(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as a, connect(link) as b:
        assert round_trip(a, b"from-a") == b"from-a"
        assert round_trip(b, b"from-b") == b"from-b"
        assert link.stats()["active"] == 2
    assert echo.accepted == 2


# ------------------------------------------------------------------ cut / restore


def test_cut_holds_bytes_then_restore_delivers_in_order(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"up") == b"up"
        link.cut()
        assert link.state == "cut"
        before = link.stats()
        parts = [f"part{i};".encode() for i in range(50)] + [random.Random(1).randbytes(100_000)]

        def send_parts() -> None:
            for p in parts:
                sock.sendall(p)

        sender = threading.Thread(target=send_parts, daemon=True)
        sender.start()
        assert nothing_arrives(sock, 0.3)
        assert link.stats()["bytes_up"] == before["bytes_up"]
        assert echo.received == 2  # nothing reached the target during the cut
        link.restore()
        assert link.state == "pass"
        assert recv_exact(sock, sum(map(len, parts))) == b"".join(parts)
        sender.join(2.0)
        assert round_trip(sock, b"after") == b"after"


def test_cut_holds_the_down_direction_too(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        sock.sendall(b"x")  # reaches the echo server...
        assert wait_until(lambda: echo.received == 1)
        link.cut()  # ...but its echo may only just be on its way back
        sock.sendall(b"held")
        got = b""
        sock.settimeout(0.3)
        with contextlib.suppress(TimeoutError):
            got = sock.recv(100)
        assert got in (b"", b"x")
        link.restore()
        assert got + recv_exact(sock, 5 - len(got)) == b"xheld"


def test_connection_accepted_during_cut_is_forwarded_after_restore(
    link: LinkImpairer, echo: EchoServer
) -> None:
    link.cut()
    with connect(link) as sock:
        sock.sendall(b"knock")
        assert nothing_arrives(sock, 0.3)
        assert wait_until(lambda: link.stats()["accepted"] == 1)  # (the impairer's thread accepts)
        assert echo.accepted == 0  # not connected to the target while cut
        link.restore()
        assert recv_exact(sock, 5) == b"knock"
    assert echo.accepted == 1


def test_control_before_start_applies() -> None:
    server = EchoServer()
    imp = LinkImpairer(server.address)
    try:
        imp.cut()
        assert imp.state == "cut"
        imp.start()
        imp.start()  # idempotent
        with connect(imp) as sock:
            sock.sendall(b"a")
            assert nothing_arrives(sock, 0.2)
            imp.restore()
            assert recv_exact(sock, 1) == b"a"
    finally:
        imp.close()
        server.close()


# ------------------------------------------------------------------ delay


def test_delay_adds_latency_each_way(link: LinkImpairer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"warm") == b"warm"
        link.set_delay(50)
        assert link.state == "delay"
        assert link.delay_ms == pytest.approx(50)
        for _ in range(3):
            t0 = time.monotonic()
            assert round_trip(sock, b"ping") == b"ping"
            assert time.monotonic() - t0 >= 0.090
        payload = random.Random(2).randbytes(200_000)
        sender = threading.Thread(target=sock.sendall, args=(payload,), daemon=True)
        sender.start()
        assert recv_exact(sock, len(payload)) == payload
        sender.join(2.0)
        link.restore()
        assert link.state == "pass"
        assert round_trip(sock, b"fast") == b"fast"


def test_delay_keeps_order_of_spaced_writes(link: LinkImpairer) -> None:
    link.set_delay(30)
    with connect(link) as sock:
        msgs = [f"{i:03d}".encode() for i in range(20)]
        for m in msgs:
            sock.sendall(m)
            time.sleep(0.002)
        link.set_delay(0)  # a lower delay must not let later chunks overtake earlier ones
        sock.sendall(b"end")
        assert recv_exact(sock, 63) == b"".join(msgs) + b"end"


def test_restore_releases_delayed_data_at_once(link: LinkImpairer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"warm") == b"warm"
        link.set_delay(3000)
        sock.sendall(b"slow")
        assert nothing_arrives(sock, 0.2)
        t0 = time.monotonic()
        link.restore()
        assert recv_exact(sock, 4) == b"slow"
        assert time.monotonic() - t0 < 2.0


def test_set_delay_ends_a_cut(link: LinkImpairer) -> None:
    with connect(link) as sock:
        link.cut()
        sock.sendall(b"q")
        assert nothing_arrives(sock, 0.2)
        link.set_delay(20)
        assert link.state == "delay"
        assert recv_exact(sock, 1) == b"q"


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_set_delay_rejects_bad_values(link: LinkImpairer, bad: float) -> None:
    with pytest.raises(ValueError):
        link.set_delay(bad)
    assert link.state == "pass"


# ------------------------------------------------------------------ resets and closes


def test_reset_connections_client_sees_reset(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"hi") == b"hi"
        link.reset_connections()
        assert link.stats()["active"] == 0
        assert sees_close(sock)
    assert wait_until(lambda: echo.finished == 1)  # the target side was reset too
    with connect(link) as sock2:  # the listener is still up
        assert round_trip(sock2, b"again") == b"again"


def test_reset_connections_during_cut(link: LinkImpairer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"hi") == b"hi"
        link.cut()
        link.reset_connections()
        assert sees_close(sock)
    link.restore()


def test_target_refused_closes_client() -> None:
    with LinkImpairer(("127.0.0.1", closed_port())) as imp, connect(imp) as sock:
        assert sees_close(sock)
        assert wait_until(lambda: imp.stats()["refused"] == 1)
        assert imp.stats()["active"] == 0


def test_target_close_closes_client(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"hi") == b"hi"
        echo.close_connections()
        assert sees_close(sock)
    assert wait_until(lambda: link.stats()["active"] == 0)


def test_client_close_closes_target(link: LinkImpairer, echo: EchoServer) -> None:
    with connect(link) as sock:
        assert round_trip(sock, b"hi") == b"hi"
    assert wait_until(lambda: echo.finished == 1)
    assert wait_until(lambda: link.stats()["active"] == 0)


def test_close_joins_thread_and_closes_port(echo: EchoServer) -> None:
    imp = LinkImpairer(echo.address)
    imp.start()
    name = imp.thread_name
    assert name in {t.name for t in threading.enumerate()}
    with connect(imp) as sock:
        assert round_trip(sock, b"hi") == b"hi"
        imp.close()
        assert sees_close(sock)
    imp.close()  # idempotent
    assert not [t for t in threading.enumerate() if t.name == name]
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(imp.address, timeout=1.0).close()
    with pytest.raises(RuntimeError):
        imp.start()
    assert wait_until(lambda: echo.finished == 1)


def test_close_without_start_closes_port(echo: EchoServer) -> None:
    imp = LinkImpairer(echo.address)
    address = imp.address
    imp.close()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(address, timeout=1.0).close()


def test_close_while_cut_with_held_connection(echo: EchoServer) -> None:
    imp = LinkImpairer(echo.address)
    imp.start()
    with connect(imp) as sock:
        imp.cut()
        sock.sendall(b"held")
        imp.close()
        assert sees_close(sock)
    assert not [t for t in threading.enumerate() if t.name == imp.thread_name]


# ------------------------------------------------------------------ CLI


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:7447", ("127.0.0.1", 7447)),
        ("tcp/127.0.0.1:7448", ("127.0.0.1", 7448)),
        ("[::1]:0", ("::1", 0)),
        ("localhost:80", ("localhost", 80)),
    ],
)
def test_parse_hostport(text: str, expected: tuple[str, int]) -> None:
    assert parse_hostport(text) == expected


@pytest.mark.parametrize("text", ["7447", ":7447", "host:", "host:x", "host:70000"])
def test_parse_hostport_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        parse_hostport(text)


def test_cli_runs_until_sigint(echo: EchoServer) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "telesurg.tools.bench.impair", "--listen", "127.0.0.1:0"]
    cmd += ["--target", f"{echo.address[0]}:{echo.address[1]}", "--delay-ms", "5"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("impair: tcp/127.0.0.1:"), line
        host, port = parse_hostport(line.split()[1])
        with socket.create_connection((host, port), timeout=3.0) as sock:
            assert round_trip(sock, b"via cli") == b"via cli"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=4.0) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


# ------------------------------------------------------------------ in a process of its own


def test_a_process_impairer_delays_cuts_and_refuses_bad_commands(echo: EchoServer) -> None:
    with ImpairerProcess(echo.address) as link:
        port = int(link.endpoint.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port), timeout=5.0) as sock:
            assert round_trip(sock, b"warm") == b"warm"
            link.set_delay(50)
            t0 = time.monotonic()
            assert round_trip(sock, b"ping") == b"ping"
            assert time.monotonic() - t0 >= 0.090  # 50 ms each way
            assert link.set_profile(LinkProfile(delay_ms=20, jitter_ms=5)) == LinkProfile(20, 5)
            with pytest.raises(RuntimeError, match="error"):
                link.set_delay(-1)  # refused by the process; the link keeps its profile
            link.cut()
            sock.sendall(b"held")
            sock.settimeout(0.3)
            with pytest.raises(TimeoutError):
                sock.recv(4)
            link.restore()
            sock.settimeout(5.0)
            assert recv_exact(sock, 4) == b"held"
        with pytest.raises(RuntimeError, match="unknown command"):
            link.command("teleport")
    with pytest.raises(RuntimeError, match="not started"):
        link.cut()
