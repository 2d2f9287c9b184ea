"""Userspace TCP link impairer: cut, delay and reset a "network link" on loopback (no netem needed).

A :class:`LinkImpairer` is a TCP proxy. Put it between a console-side zenoh client and the
slave-side zenoh router and it behaves like the network link between them:

* pass (default): bytes are forwarded as soon as they are read (``TCP_NODELAY`` on both sockets);
* :meth:`~LinkImpairer.cut`: nothing is read or written any more, so bytes wait in the kernel
  socket buffers, exactly as if the cable were pulled while TCP retransmits; nothing is lost and
  :meth:`~LinkImpairer.restore` lets it flow again, in order;
* :meth:`~LinkImpairer.set_delay`: every chunk is forwarded no earlier than its read time plus
  the delay, per direction (a round trip gains twice the delay);
* :meth:`~LinkImpairer.reset_connections`: every forwarded connection is reset (RST) at once.

One thread (named ``impair-<port>``) runs a ``selectors`` event loop over non-blocking sockets;
delayed chunks wait in a per-direction queue and the loop's select timeout is the next due time,
so there is no polling. Control calls are handed to that thread and return once it has applied
them: after :meth:`~LinkImpairer.cut` returns, not one more byte is forwarded.

Example::

    with LinkImpairer(target=("127.0.0.1", 7447)) as link:
        console = BusConfig(mode="client", connect=[link.endpoint])
        ...
        link.cut()              # cable pulled: bytes wait in kernel buffers
        link.restore()          # they flow again, intact and in order
        link.set_delay(20)      # +20 ms each way
        link.reset_connections()

Or as a process: ``telesurg impair --listen 127.0.0.1:7448 --target 127.0.0.1:7447 --delay-ms 20``;
with ``--control`` it also reads commands on stdin (``cut``, ``restore``, ``delay MS``, ``reset``,
``stats``; one ``ok ...`` / ``error ...`` line back each), so a test can drive an impairer that
runs inside a network namespace (``ip netns exec NS telesurg impair --control ...``).

A TCP proxy cannot lose packets: TCP below it retransmits. For packet loss, :class:`PacketLink`
(root only) joins two network namespaces with a TUN device in each and forwards every IP packet
through this process with delay, random loss and cut, so TCP, TLS, UDP and QUIC links see real
loss and the kernel's own retransmission (``tools/bench/transport.py`` uses it)::

    with NetNamespace("ts-a") as a, NetNamespace("ts-b") as b, PacketLink(a.name, b.name) as link:
        link.set_delay(10)      # ms one way
        link.set_loss(0.02)     # 2 % of packets, each direction, independently
        link.set_profile(profile("5g-microhand", burst=3))   # or a whole network profile
        subprocess.run(a.cmd(["python", "-m", "..."]))   # reaches b at link.addr_b

Network profiles (delay, jitter, bursty loss, bandwidth cap, reordering, outages; the named ones
of issue #41) are :mod:`telesurg.tools.bench.netprofile`; ``telesurg impair --profile NAME`` applies
what a TCP proxy can of one (delay, jitter, cap).
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import fcntl
import heapq
import logging
import math
import os
import random
import selectors
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from types import FrameType, TracebackType
from typing import Any

from telesurg.shared.errors import ConfigError
from telesurg.tools.bench.netprofile import (
    LinkModel,
    LinkProfile,
    add_profile_args,
    profile,
    profile_from_args,
)

log = logging.getLogger(__name__)

_CHUNK = 65536  # bytes per recv
_HIGH_WATER = 4 * 1024 * 1024  # stop reading a direction with this much waiting in user space
_CONTROL_TIMEOUT_S = 10.0  # a control call waits this long for the loop thread at most
_CONNECT_PENDING = {0, errno.EINPROGRESS, errno.EAGAIN, errno.EWOULDBLOCK, errno.EALREADY}
_LINGER_RST = struct.pack("ii", 1, 0)  # SO_LINGER on, 0 s: close() sends RST

_LISTEN = object()  # selector key data of the listening socket
_WAKE = object()  # selector key data of the wake-up socket


class _Pipe:
    """One direction of a forwarded connection: chunks read from the source wait here until due."""

    __slots__ = ("blocked", "eof", "queue", "queued", "shaped_at", "up")

    def __init__(self, up: bool) -> None:
        self.up = up  # client → target
        self.queue: deque[tuple[float, memoryview]] = deque()  # (due monotonic s, bytes), in order
        self.queued = 0  # bytes in ``queue``
        self.eof = False  # the source closed: close the pair once ``queue`` is drained
        self.blocked = False  # last send was partial: wait until the destination is writable
        self.shaped_at = 0.0  # when the bandwidth cap lets the newest chunk go (monotonic s)


class _Pair:
    """One accepted client connection and its connection to the target."""

    __slots__ = ("client", "closed", "cmask", "down", "peer", "phase", "target", "tmask", "up")

    def __init__(self, client: socket.socket, peer: str) -> None:
        self.client = client
        self.target: socket.socket | None = None
        self.phase = "waiting"  # waiting (accepted during a cut) | connecting | open
        self.up = _Pipe(up=True)
        self.down = _Pipe(up=False)
        self.cmask = 0  # selector events registered for ``client``
        self.tmask = 0  # selector events registered for ``target``
        self.closed = False
        self.peer = peer


def _nodelay(sock: socket.socket) -> None:
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def _format_endpoint(host: str, port: int) -> str:
    return f"tcp/[{host}]:{port}" if ":" in host else f"tcp/{host}:{port}"


class LinkImpairer:
    """TCP proxy: listen on ``listen`` and forward each accepted connection to ``target``.

    The listening socket is bound in the constructor (so :attr:`address` and :attr:`endpoint`
    are known before :meth:`start`); connections wait in the backlog until :meth:`start`.
    Control methods may be called from any thread, before or after :meth:`start`.

    Half-close is not forwarded: when either side closes, the bytes already read from it are
    delivered to the other side, then both connections are closed. A connection that fails
    (reset, broken pipe) resets the other side.

    Args:
        target: ``(host, port)`` to forward to, e.g. the zenoh router's listen address.
        listen: ``(host, port)`` to listen on; port 0 picks a free port.
        seed: seed of the jitter (reproducible per-chunk delays).

    Raises:
        OSError: the listen address cannot be bound or a host name cannot be resolved.
    """

    def __init__(
        self, target: tuple[str, int], listen: tuple[str, int] = ("127.0.0.1", 0), seed: int | None = None
    ) -> None:
        family, _, _, _, addr = socket.getaddrinfo(target[0], target[1], type=socket.SOCK_STREAM)[0]
        self._target_family = family
        self._target_addr: Any = addr
        self._target = (str(addr[0]), int(addr[1]))
        lfamily, _, _, _, laddr = socket.getaddrinfo(
            listen[0], listen[1], type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
        lsock = socket.socket(lfamily, socket.SOCK_STREAM)
        try:
            lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            lsock.bind(laddr)
            lsock.listen(128)
            lsock.setblocking(False)
            name = lsock.getsockname()
        except BaseException:
            lsock.close()
            raise
        self._lsock = lsock
        self._address = (str(name[0]), int(name[1]))
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._lock = threading.Lock()
        self._commands: deque[tuple[Callable[[], None], threading.Event]] = deque()
        self._thread: threading.Thread | None = None
        self._loop_active = False
        self._stopping = False
        self._closed = False
        self._pairs: set[_Pair] = set()
        # state: written by the loop thread only (or by the caller while no loop runs)
        self._cut = False
        self._delay_s = 0.0
        self._jitter_s = 0.0  # ± uniform per chunk, in order (a byte stream cannot reorder)
        self._rate_bps = 0.0  # bandwidth cap, bytes/s (0: none)
        self._rng = random.Random(seed)
        # counters
        self._accepted = 0
        self._refused = 0
        self._bytes_up = 0
        self._bytes_down = 0

    # ----------------------------------------------------------------- public API

    @property
    def address(self) -> tuple[str, int]:
        """The actual listen address ``(host, port)`` (port 0 → the port chosen)."""
        return self._address

    @property
    def endpoint(self) -> str:
        """The zenoh endpoint to connect to instead of the target, e.g. ``tcp/127.0.0.1:40123``."""
        return _format_endpoint(*self._address)

    @property
    def target(self) -> tuple[str, int]:
        """The resolved target address ``(host, port)``."""
        return self._target

    @property
    def thread_name(self) -> str:
        """Name of the impairer's event-loop thread (``impair-<port>``)."""
        return f"impair-{self._address[1]}"

    @property
    def state(self) -> str:
        """``"cut"`` while cut, else ``"delay"`` if a delay is set, else ``"pass"``."""
        if self._cut:
            return "cut"
        return "delay" if self._delay_s > 0 or self._jitter_s > 0 or self._rate_bps > 0 else "pass"

    @property
    def delay_ms(self) -> float:
        """One-way added latency, ms (0 in pass mode)."""
        return self._delay_s * 1000.0

    def stats(self) -> dict[str, int]:
        """Counters since construction.

        Returns:
            ``accepted`` (client connections), ``active`` (connection pairs open now),
            ``refused`` (target connections that failed), ``bytes_up`` (client → target, bytes
            written to the target) and ``bytes_down`` (target → client).
        """
        return {
            "accepted": self._accepted,
            "active": len(self._pairs),
            "refused": self._refused,
            "bytes_up": self._bytes_up,
            "bytes_down": self._bytes_down,
        }

    def start(self) -> None:
        """Start the event-loop thread (idempotent).

        Raises:
            RuntimeError: the impairer was closed.
        """
        with self._lock:
            if self._closed:
                raise RuntimeError("LinkImpairer is closed")
            if self._thread is not None:
                return
            self._loop_active = True
            self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the loop thread, join it and close every socket (idempotent).

        Open connection pairs are closed normally (FIN), the listening port is closed.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            thread = self._thread
            if self._loop_active:
                self._commands.append((self._request_stop, threading.Event()))
        self._wake()
        if thread is not None and thread is not threading.current_thread():
            thread.join()
        for pair in list(self._pairs):  # only if never started, or the loop died
            self._close_pair(pair)
        with contextlib.suppress(Exception):
            self._sel.close()
        for sock in (self._lsock, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                sock.close()

    def __enter__(self) -> LinkImpairer:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def cut(self) -> None:
        """Cut the link: stop reading and writing in both directions, keep every byte.

        Sockets stay open and unread data stays in the kernel buffers (senders block as on a
        pulled cable while TCP retransmits); data already read waits in the impairer. New
        connections are accepted but not connected to the target until the link is back.
        """
        self._control(self._apply_cut)

    def set_delay(self, ms: float) -> None:
        """Add ``ms`` of one-way latency per direction (0 → pass-through); ends a cut.

        Every chunk read from now on is forwarded no earlier than its read time plus ``ms``,
        in order. Chunks already waiting keep their due time.

        Args:
            ms: one-way delay, ms (finite, >= 0).

        Raises:
            ValueError: ``ms`` is negative or not finite.
        """
        if not math.isfinite(ms) or ms < 0:
            raise ValueError(f"delay must be a finite number of ms >= 0, got {ms!r}")
        delay_s = ms / 1000.0
        self._control(lambda: self._apply_link(delay_s, release=False))

    def set_profile(self, prof: LinkProfile) -> LinkProfile:
        """Apply what a TCP proxy can of ``prof``: delay, jitter (uniform, in order), bandwidth cap.

        A byte stream cannot lose or reorder packets (TCP below retransmits) and a cut holds bytes
        rather than dropping them: loss, reordering and outages are left out (use
        :class:`PacketLink`). Ends a cut.

        Returns:
            The profile applied (``prof`` without loss, reordering and outages).
        """
        applied = replace(prof, loss=0.0, burst=1.0, reorder=0.0, outage_ms=0.0)
        delay_s, jitter_s, rate = prof.delay_ms / 1000.0, prof.jitter_ms / 1000.0, prof.rate_kbps * 125.0

        def apply() -> None:
            self._jitter_s, self._rate_bps = jitter_s, rate
            self._apply_link(delay_s, release=False)

        self._control(apply)
        return applied

    def restore(self) -> None:
        """Back to pass-through (no cut, no delay); everything held back flows now, in order."""

        def apply() -> None:
            self._jitter_s = self._rate_bps = 0.0
            self._apply_link(0.0, release=True)

        self._control(apply)

    def reset_connections(self) -> None:
        """Reset (RST) every current connection pair, both sides; the listener stays up."""
        self._control(self._apply_reset)

    # ----------------------------------------------------------------- control plumbing

    def _control(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the loop thread and wait for it (or here, if no loop runs)."""
        with self._lock:
            if not self._loop_active:
                fn()
                return
            done = threading.Event()
            self._commands.append((fn, done))
        self._wake()
        if not done.wait(_CONTROL_TIMEOUT_S):
            raise RuntimeError(f"{self.thread_name}: event loop did not answer a control call")

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # BlockingIOError: a wake-up is already pending
            self._wake_w.send(b"\0")

    def _run_commands(self) -> None:
        with contextlib.suppress(OSError):
            while self._wake_r.recv(4096):
                pass
        with self._lock:
            commands = list(self._commands)
            self._commands.clear()
        for fn, done in commands:
            try:
                fn()
            except Exception:
                log.debug("%s: control call failed", self.thread_name, exc_info=True)
            finally:
                done.set()

    def _request_stop(self) -> None:
        self._stopping = True

    def _apply_cut(self) -> None:
        self._cut = True
        self._refresh_all()

    def _apply_link(self, delay_s: float, release: bool) -> None:
        self._cut = False
        self._delay_s = delay_s
        for pair in list(self._pairs):
            if release:
                for pipe in (pair.up, pair.down):
                    pipe.queue = deque((0.0, view) for _, view in pipe.queue)
            if pair.phase == "waiting":
                self._connect(pair)
        self._refresh_all()

    def _apply_reset(self) -> None:
        for pair in list(self._pairs):
            self._close_pair(pair, reset=True)

    def _refresh_all(self) -> None:
        for pair in list(self._pairs):
            self._update(pair)

    # ----------------------------------------------------------------- event loop

    def _run(self) -> None:
        try:
            self._sel.register(self._lsock, selectors.EVENT_READ, _LISTEN)
            self._sel.register(self._wake_r, selectors.EVENT_READ, _WAKE)
            while not self._stopping:
                for key, mask in self._sel.select(self._timeout()):
                    data = key.data
                    if data is _WAKE:
                        self._run_commands()
                    elif data is _LISTEN:
                        self._accept()
                    else:
                        pair, is_client = data
                        if not pair.closed:
                            self._on_event(pair, is_client, mask)
                self._flush_due()
        except Exception:
            log.debug("%s: event loop failed", self.thread_name, exc_info=True)
        finally:
            self._loop_exit()

    def _loop_exit(self) -> None:
        for pair in list(self._pairs):
            self._close_pair(pair)
        with contextlib.suppress(Exception):
            self._sel.unregister(self._lsock)
        with contextlib.suppress(Exception):
            self._sel.unregister(self._wake_r)
        with self._lock:
            self._loop_active = False
            commands = list(self._commands)
            self._commands.clear()
        for fn, done in commands:  # late control calls: apply them here, nothing to wait for
            try:
                fn()
            except Exception:
                log.debug("%s: control call failed", self.thread_name, exc_info=True)
            finally:
                done.set()

    def _timeout(self) -> float | None:
        """Seconds until the next delayed chunk is due; None (block) when nothing is waiting."""
        if self._cut:
            return None
        first: float | None = None
        for pair in self._pairs:
            for pipe in (pair.up, pair.down):
                if pipe.queue and not pipe.blocked:
                    due = pipe.queue[0][0]
                    if first is None or due < first:
                        first = due
        if first is None:
            return None
        return max(0.0, first - time.monotonic())

    def _flush_due(self) -> None:
        if self._cut or not self._pairs:
            return
        now = time.monotonic()
        for pair in list(self._pairs):
            touched = False
            for pipe in (pair.up, pair.down):
                if not pair.closed and pipe.queue and not pipe.blocked and pipe.queue[0][0] <= now:
                    self._flush(pair, pipe, now)
                    touched = True
            if touched:
                self._update(pair)

    def _accept(self) -> None:
        while True:
            try:
                conn, addr = self._lsock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionAbortedError:
                continue
            except OSError as exc:
                log.debug("%s: accept failed: %s", self.thread_name, exc)
                return
            self._accepted += 1
            conn.setblocking(False)
            _nodelay(conn)
            pair = _Pair(conn, f"{addr[0]}:{addr[1]}")
            self._pairs.add(pair)
            log.debug("%s: accepted %s", self.thread_name, pair.peer)
            if self._cut:
                self._update(pair)  # held until the link is back
            else:
                self._connect(pair)

    def _connect(self, pair: _Pair) -> None:
        """Start a non-blocking connect to the target; completion is a writable event."""
        try:
            sock = socket.socket(self._target_family, socket.SOCK_STREAM)
        except OSError as exc:
            log.debug("%s: cannot create target socket: %s", self.thread_name, exc)
            self._close_pair(pair)
            return
        pair.target = sock
        pair.phase = "connecting"
        try:
            sock.setblocking(False)
            _nodelay(sock)
            err = sock.connect_ex(self._target_addr)
        except OSError as exc:
            err = exc.errno or errno.ECONNREFUSED
        if err not in _CONNECT_PENDING:
            self._refuse(pair, err)
            return
        self._update(pair)

    def _connected(self, pair: _Pair) -> None:
        assert pair.target is not None
        try:
            err = pair.target.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
        except OSError as exc:
            err = exc.errno or errno.ECONNREFUSED
        if err:
            self._refuse(pair, err)
            return
        pair.phase = "open"
        log.debug("%s: %s connected to target", self.thread_name, pair.peer)
        self._update(pair)

    def _refuse(self, pair: _Pair, err: int) -> None:
        self._refused += 1
        log.debug(
            "%s: target %s:%d failed for %s: %s", self.thread_name, *self._target, pair.peer, os.strerror(err)
        )
        self._close_pair(pair)

    def _on_event(self, pair: _Pair, is_client: bool, mask: int) -> None:
        try:
            if not is_client and pair.phase == "connecting":
                if mask & selectors.EVENT_WRITE:
                    self._connected(pair)
                return
            if pair.phase != "open" or self._cut:
                return
            if mask & selectors.EVENT_READ:
                self._read(pair, pair.up if is_client else pair.down)
            if not pair.closed and mask & selectors.EVENT_WRITE:
                pipe = pair.down if is_client else pair.up  # the direction that writes to this socket
                pipe.blocked = False
                self._flush(pair, pipe, time.monotonic())
            self._update(pair)
        except Exception:
            log.debug("%s: %s: unexpected error", self.thread_name, pair.peer, exc_info=True)
            self._close_pair(pair, reset=True)

    def _read(self, pair: _Pair, pipe: _Pipe) -> None:
        src = pair.client if pipe.up else pair.target
        assert src is not None
        try:
            data = src.recv(_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            log.debug(
                "%s: %s: %s side failed: %s",
                self.thread_name,
                pair.peer,
                "client" if pipe.up else "target",
                exc,
            )
            self._close_pair(pair, reset=True)
            return
        if not data:
            log.debug("%s: %s: %s closed", self.thread_name, pair.peer, "client" if pipe.up else "target")
            pipe.eof = True
            if not pipe.queue:
                self._close_pair(pair)
            return
        now = time.monotonic()
        start = now
        if self._rate_bps > 0:
            start = max(now, pipe.shaped_at) + len(data) / self._rate_bps
            pipe.shaped_at = start
        due = start + self._delay_s
        if self._jitter_s > 0:
            due = max(start, due + self._rng.uniform(-self._jitter_s, self._jitter_s))
        if pipe.queue and pipe.queue[-1][0] > due:
            due = pipe.queue[-1][0]  # the delay went down: never overtake earlier chunks
        pipe.queue.append((due, memoryview(data)))
        pipe.queued += len(data)
        if due <= now:
            self._flush(pair, pipe, now)

    def _flush(self, pair: _Pair, pipe: _Pipe, now: float) -> None:
        """Send the due chunks of ``pipe``; a partial send waits for a writable event."""
        if self._cut or pipe.blocked or pair.closed:
            return
        dst = pair.target if pipe.up else pair.client
        assert dst is not None
        queue = pipe.queue
        while queue:
            due, view = queue[0]
            if due > now:
                break
            try:
                sent = dst.send(view)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as exc:
                log.debug(
                    "%s: %s: send to %s failed: %s",
                    self.thread_name,
                    pair.peer,
                    "target" if pipe.up else "client",
                    exc,
                )
                self._close_pair(pair, reset=True)
                return
            pipe.queued -= sent
            if pipe.up:
                self._bytes_up += sent
            else:
                self._bytes_down += sent
            if sent < len(view):
                queue[0] = (due, view[sent:])
                pipe.blocked = True
                break
            queue.popleft()
        if not queue and pipe.eof:
            self._close_pair(pair)

    def _update(self, pair: _Pair) -> None:
        """Register exactly the events the pair needs now (none while cut)."""
        if pair.closed:
            return
        cmask = tmask = 0
        if pair.phase == "connecting":
            tmask = selectors.EVENT_WRITE
        elif pair.phase == "open" and not self._cut:
            if not pair.up.eof and pair.up.queued < _HIGH_WATER:
                cmask |= selectors.EVENT_READ
            if pair.down.blocked:
                cmask |= selectors.EVENT_WRITE
            if not pair.down.eof and pair.down.queued < _HIGH_WATER:
                tmask |= selectors.EVENT_READ
            if pair.up.blocked:
                tmask |= selectors.EVENT_WRITE
        pair.cmask = self._set_mask(pair.client, pair.cmask, cmask, (pair, True))
        if pair.target is not None:
            pair.tmask = self._set_mask(pair.target, pair.tmask, tmask, (pair, False))

    def _set_mask(self, sock: socket.socket, old: int, new: int, data: tuple[_Pair, bool]) -> int:
        if new == old:
            return old
        if old == 0:
            self._sel.register(sock, new, data)
        elif new == 0:
            self._sel.unregister(sock)
        else:
            self._sel.modify(sock, new, data)
        return new

    def _close_pair(self, pair: _Pair, reset: bool = False) -> None:
        if pair.closed:
            return
        pair.closed = True
        self._pairs.discard(pair)
        for sock, mask in ((pair.client, pair.cmask), (pair.target, pair.tmask)):
            if sock is None:
                continue
            if mask:
                with contextlib.suppress(Exception):
                    self._sel.unregister(sock)
            if reset:
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RST)
            with contextlib.suppress(OSError):
                sock.close()
        pair.cmask = pair.tmask = 0
        for pipe in (pair.up, pair.down):
            pipe.queue.clear()
            pipe.queued = 0
        log.debug("%s: %s closed%s", self.thread_name, pair.peer, " (reset)" if reset else "")


# --------------------------------------------------------------------- packet link (root)

_RT_PRIORITY = 20  # SCHED_FIFO priority of the packet link's thread (below the kernel's threads)
_TUNSETIFF = 0x400454CA
_IFF_TUN = 0x0001
_IFF_NO_PI = 0x1000


def netns_available() -> str:
    """ "" if network namespaces and TUN devices can be used here, else the reason they cannot."""
    if os.geteuid() != 0:
        return "needs root (network namespaces, TUN devices)"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2)"
    if not os.path.exists("/dev/net/tun"):
        return "needs /dev/net/tun"
    probe = f"ts-probe-{os.getpid()}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"`ip netns add` failed: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ""


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise OSError(f"ip {' '.join(args)}: {r.stderr.strip()}")


class NetNamespace:
    """A network namespace, created on enter (loopback up) and deleted on exit.

    Args:
        name: namespace name (``ip netns``); must not exist yet.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._made = False

    def __enter__(self) -> NetNamespace:
        _ip("netns", "add", self.name)
        self._made = True
        try:
            _ip("-n", self.name, "link", "set", "lo", "up")
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Delete the namespace (idempotent); its interfaces go with it."""
        if self._made:
            self._made = False
            subprocess.run(["ip", "netns", "del", self.name], capture_output=True)

    def cmd(self, argv: Sequence[str]) -> list[str]:
        """``argv`` run inside the namespace (``ip netns exec`` execs it: same PID)."""
        return ["ip", "netns", "exec", self.name, *argv]


class PacketLink:
    """A point-to-point IP link between two network namespaces, forwarded by this process.

    A TUN device is made in each namespace (``addr_a`` in ``ns_a``, ``addr_b`` in ``ns_b``, a /32
    route to each other); one thread (``packetlink-<name>``) reads every IP packet from one device
    and writes it to the other when a :class:`~telesurg.tools.bench.netprofile.LinkModel` of the
    link's :class:`~telesurg.tools.bench.netprofile.LinkProfile` says (one model per direction):
    delay and jitter (in order unless reordering is asked), random or bursty loss, a bandwidth
    cap with a tail-drop queue, scheduled outages. Every packet is dropped while the link is cut
    — as on a real link, the endpoints' own TCP (or QUIC) retransmits, UDP datagrams are gone.
    Root only; the devices vanish on :meth:`close`.

    Args:
        ns_a, ns_b: existing network namespaces (e.g. :class:`NetNamespace`).
        addr_a, addr_b: IPv4 addresses of the two ends.
        name: device-name stem (``<name>a``, ``<name>b``; at most 14 characters).
        seed: seed of the random parts (reproducible drops and jitter for a given packet sequence).
        realtime: run the forwarding thread at SCHED_FIFO priority (if allowed): on a loaded host
            its wake-up latency would add to every delay.

    Raises:
        OSError: not root, no TUN support, or the namespaces do not exist.
    """

    def __init__(
        self,
        ns_a: str,
        ns_b: str,
        *,
        addr_a: str = "10.251.0.1",
        addr_b: str = "10.251.0.2",
        name: str = "",
        seed: int | None = None,
        realtime: bool = True,
    ) -> None:
        self.addr_a, self.addr_b = addr_a, addr_b
        self._realtime = realtime
        stem = name or f"tsl{os.getpid() % 100000}"
        if len(stem) > 14:
            raise ValueError(f"device name stem {stem!r} longer than 14 characters")
        self.name = stem
        self._seed = seed
        self._lock = threading.Lock()
        self._profile = LinkProfile()
        self._version = 0  # bumped on every profile change: the loop thread reconfigures its models
        self._since = time.monotonic()  # when the profile last changed: outages count from here
        self._models: dict[int, LinkModel] = {}  # by source device: one per direction
        self._model_version: dict[int, int] = {}
        self._arrivals = 0
        self._cut = False
        self._stop = False
        self._thread: threading.Thread | None = None
        #: packets forwarded; dropped by loss, by the full queue of the bandwidth cap, by a
        #: scheduled outage, by a cut
        self.counts = {"forwarded": 0, "lost": 0, "queue": 0, "outage": 0, "cut": 0}
        self._fds: list[int] = []
        try:
            for ns, dev, mine, peer in (
                (ns_a, f"{stem}a", addr_a, addr_b),
                (ns_b, f"{stem}b", addr_b, addr_a),
            ):
                fd = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC)
                self._fds.append(fd)
                fcntl.ioctl(fd, _TUNSETIFF, struct.pack("16sH", dev.encode(), _IFF_TUN | _IFF_NO_PI))
                os.set_blocking(fd, False)
                _ip("link", "set", "dev", dev, "netns", ns)
                _ip("-n", ns, "addr", "add", mine, "peer", f"{peer}/32", "dev", dev)
                _ip("-n", ns, "link", "set", dev, "up")
            self._wake_r, self._wake_w = os.pipe()
        except BaseException:
            for fd in self._fds:
                os.close(fd)
            raise

    @property
    def state(self) -> str:
        """``cut``, else ``impaired`` (a profile other than a perfect link), else ``pass``."""
        if self._cut:
            return "cut"
        return "impaired" if self._profile != LinkProfile() else "pass"

    @property
    def profile(self) -> LinkProfile:
        """The profile each direction applies now."""
        return self._profile

    def set_profile(self, prof: LinkProfile) -> None:
        """Apply ``prof`` to both directions (each with its own random state); ends a cut.

        Packets already queued keep their times; outages count from now.
        """
        with self._lock:
            self._profile = prof
            self._cut = False
            self._version += 1
            self._since = time.monotonic()

    def set_delay(self, ms: float) -> None:
        """One-way delay per direction, ms (finite, >= 0); packets already queued keep theirs."""
        if not math.isfinite(ms) or ms < 0:
            raise ValueError(f"delay must be a finite number of ms >= 0, got {ms!r}")
        with self._lock:
            self._profile = replace(self._profile, delay_ms=ms)
            self._version += 1
            self._since = time.monotonic()

    def set_loss(self, probability: float) -> None:
        """Drop each packet with this probability (0 <= p < 1), each direction independently
        (in bursts if the profile has a burst length)."""
        if not 0.0 <= probability < 1.0:
            raise ValueError(f"loss probability must be in [0, 1), got {probability!r}")
        with self._lock:
            self._profile = replace(self._profile, loss=probability)
            self._version += 1
            self._since = time.monotonic()

    def cut(self) -> None:
        """Drop every packet, both ways, until :meth:`restore` (queued packets are dropped too)."""
        with self._lock:
            self._cut = True

    def restore(self) -> None:
        """No cut and a perfect link (no delay, no loss, no profile)."""
        with self._lock:
            self._cut = False
            self._profile = LinkProfile()
            self._version += 1
            self._since = time.monotonic()

    def start(self) -> None:
        """Start forwarding (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"packetlink-{self.name}", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the thread and close both devices (idempotent)."""
        if not self._fds:
            return
        self._stop = True
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"\0")
        if self._thread is not None:
            self._thread.join(5.0)
        for fd in (*self._fds, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []

    def __enter__(self) -> PacketLink:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _run(self) -> None:
        fa, fb = self._fds
        # by destination: a heap of (due, arrival number, packet): a reordered packet leaves late
        queues: dict[int, list[tuple[float, int, bytes]]] = {fa: [], fb: []}
        if self._realtime:  # the link's own wake-up is delay it adds: run ahead of other work
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(_RT_PRIORITY))
            except OSError as exc:
                log.debug("packetlink %s: no real-time priority: %s", self.name, exc)
        sel = selectors.SelectSelector()  # select(2) takes a µs timeout; epoll rounds up to whole ms
        sel.register(fa, selectors.EVENT_READ, fb)
        sel.register(fb, selectors.EVENT_READ, fa)
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        try:
            while not self._stop:
                now = time.monotonic()
                due = [q[0][0] for q in queues.values() if q]
                timeout = max(0.0, min(due) - now) if due else None
                for key, _ in sel.select(timeout):
                    if key.data is None:
                        continue
                    self._drain(int(key.fd), queues[key.data])
                now = time.monotonic()
                for dst, q in queues.items():
                    while q and q[0][0] <= now:
                        pkt = heapq.heappop(q)[2]
                        with contextlib.suppress(OSError):  # ENOBUFS etc.: the packet is lost
                            os.write(dst, pkt)
        except Exception:
            log.debug("packetlink %s failed", self.name, exc_info=True)
        finally:
            sel.close()

    def _model(self, src: int, version: int, prof: LinkProfile, since: float) -> LinkModel:
        """The model of the direction read from ``src``, reconfigured if the profile changed."""
        model = self._models.get(src)
        if model is None:
            seed = None if self._seed is None else f"{self._seed}-{self._fds.index(src)}"
            model = self._models[src] = LinkModel(prof, seed=seed, start=since)
        elif self._model_version.get(src) != version:
            model.reconfigure(prof, start=since)
        self._model_version[src] = version
        return model

    def _drain(self, src: int, queue: list[tuple[float, int, bytes]]) -> None:
        with self._lock:
            cut, prof, version, since = self._cut, self._profile, self._version, self._since
        if cut:
            queue.clear()
        now = time.monotonic()
        model = self._model(src, version, prof, since)
        while True:
            try:
                pkt = os.read(src, 65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            if cut:
                self.counts["cut"] += 1
                continue
            due = model.admit(now, len(pkt))
            if isinstance(due, str):
                self.counts["lost" if due == "loss" else due] += 1
            else:
                self.counts["forwarded"] += 1
                self._arrivals += 1
                heapq.heappush(queue, (due, self._arrivals, pkt))


# --------------------------------------------------------------------- CLI


def parse_hostport(text: str) -> tuple[str, int]:
    """Parse ``HOST:PORT``, ``[IPV6]:PORT`` or a zenoh endpoint ``tcp/HOST:PORT``.

    Args:
        text: the address.

    Returns:
        ``(host, port)``.

    Raises:
        ValueError: not of that form, or the port is not in 0..65535.
    """
    s = text.strip()
    if s.startswith("tcp/"):
        s = s[4:]
    host, sep, port_text = s.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host:
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"bad port in {text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port out of range in {text!r}")
    return host, port


def _hostport_arg(text: str) -> tuple[str, int]:
    try:
        return parse_hostport(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def control_command(link: LinkImpairer, line: str) -> str:
    """Apply one text command to ``link``; the reply line (``ok <state> <delay ms>`` or ``error ...``).

    Commands: ``cut``, ``restore``, ``delay MS``, ``link MS JITTER_MS`` (delay and jitter),
    ``profile NAME`` (its delay, jitter and cap), ``reset``, ``stats``.
    """
    words = line.split()
    try:
        match words:
            case ["cut"]:
                link.cut()
            case ["restore"]:
                link.restore()
            case ["delay", ms]:
                link.set_delay(float(ms))
            case ["link", ms, jitter]:
                link.set_profile(LinkProfile(delay_ms=float(ms), jitter_ms=float(jitter)))
            case ["profile", name]:
                link.set_profile(profile(name))
            case ["reset"]:
                link.reset_connections()
            case ["stats"]:
                return "ok " + " ".join(f"{k}={v}" for k, v in link.stats().items())
            case _:
                return (
                    f"error unknown command {line.strip()!r}; valid: cut, restore, delay MS, "
                    "link MS JITTER_MS, profile NAME, reset, stats"
                )
    except (ValueError, RuntimeError) as exc:  # (ConfigError is a ValueError)
        return f"error {exc}"
    return f"ok {link.state} {link.delay_ms:g}"


class ImpairerProcess:
    """A :class:`LinkImpairer` in a process of its own (``telesurg impair --control``), driven
    over its stdin: the same calls, none of the caller's CPU or GIL. A test process busy with its
    own subscriptions would otherwise delay the link it impairs (a 25 ms link measured 360 ms).

    Example::

        with ImpairerProcess(target=("127.0.0.1", 7447)) as link:
            console = BusConfig(mode="client", connect=[link.endpoint])
            link.set_delay(20)
    """

    def __init__(self, target: tuple[str, int], listen: tuple[str, int] = ("127.0.0.1", 0)) -> None:
        self._target, self._listen = target, listen
        self._proc: subprocess.Popen[str] | None = None
        self._endpoint = ""
        self._lock = threading.Lock()

    @property
    def endpoint(self) -> str:
        """The zenoh endpoint to connect to instead of the target (after :meth:`start`)."""
        if not self._endpoint:
            raise RuntimeError("impairer not started")
        return self._endpoint

    def start(self) -> None:
        """Start the process; returns once it listens."""
        argv = [sys.executable, "-m", "telesurg.tools.bench.impair", "--control", "--log-level", "WARNING"]
        (lh, lp), (th, tp) = self._listen, self._target
        argv += ["--listen", f"{lh}:{lp}", "--target", f"{th}:{tp}"]
        pipe = subprocess.PIPE
        self._proc = subprocess.Popen(argv, stdin=pipe, stdout=pipe, text=True, bufsize=1)
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline()
        if not line.startswith("impair: "):
            self.close()
            raise RuntimeError(f"telesurg impair did not start: {line.strip() or 'no output'}")
        self._endpoint = line.split()[1]

    def command(self, line: str) -> str:
        """Send one control command; its reply (``ok ...``), or RuntimeError with the error."""
        proc = self._proc
        if proc is None or proc.stdin is None or proc.stdout is None:
            raise RuntimeError("impairer not started")
        with self._lock:
            proc.stdin.write(line + "\n")
            proc.stdin.flush()
            reply = proc.stdout.readline().strip()
        if not reply.startswith("ok"):
            raise RuntimeError(f"impairer: {line}: {reply or 'exited'}")
        return reply

    def cut(self) -> None:
        """Stop forwarding (bytes wait in the kernel buffers)."""
        self.command("cut")

    def restore(self) -> None:
        """Forward again, no delay."""
        self.command("restore")

    def set_delay(self, ms: float) -> None:
        """Delay every chunk ``ms`` each way."""
        self.command(f"delay {float(ms)!r}")

    def set_profile(self, prof: LinkProfile) -> LinkProfile:
        """Apply a profile's delay and jitter (what this process applies of a profile)."""
        self.command(f"link {prof.delay_ms!r} {prof.jitter_ms!r}")
        return LinkProfile(delay_ms=prof.delay_ms, jitter_ms=prof.jitter_ms)

    def reset_connections(self) -> None:
        """Reset (RST) every forwarded connection."""
        self.command("reset")

    def close(self) -> None:
        """End the process (EOF on its stdin, then SIGTERM, then SIGKILL)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        with contextlib.suppress(OSError, ValueError):
            if proc.stdin is not None:
                proc.stdin.close()
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()

    def __enter__(self) -> ImpairerProcess:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _control_loop(link: LinkImpairer, stop: threading.Event) -> None:
    for line in sys.stdin:
        if line.strip():
            print(control_command(link, line), flush=True)
    stop.set()  # EOF: whoever drove us is gone


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg impair``: run a :class:`LinkImpairer` until SIGINT/SIGTERM.

    Prints one line ``impair: <endpoint> -> <target endpoint> ...`` on stdout once listening.

    Args:
        argv: command-line arguments without the program name (default ``sys.argv[1:]``).

    Returns:
        0 after a requested stop, 1 if the listen address cannot be bound, 2 on a bad profile.
    """
    parser = argparse.ArgumentParser(
        prog="telesurg impair",
        description="TCP link impairer: forward --listen to --target, optionally with a link profile's "
        "delay, jitter and bandwidth cap (a TCP proxy cannot lose packets).",
    )
    parser.add_argument(
        "--listen",
        type=_hostport_arg,
        default=("127.0.0.1", 7448),
        metavar="HOST:PORT",
        help="address to listen on (default 127.0.0.1:7448; port 0 picks one)",
    )
    parser.add_argument(
        "--target",
        type=_hostport_arg,
        default=("127.0.0.1", 7447),
        metavar="HOST:PORT",
        help="address to forward to, e.g. the zenoh router (default 127.0.0.1:7447)",
    )
    add_profile_args(parser, delay_default=0.0)
    parser.add_argument(
        "--control",
        action="store_true",
        help="read commands on stdin (cut, restore, delay MS, profile NAME, reset, stats); "
        "EOF stops the impairer",
    )
    parser.add_argument("--seed", type=int, help="seed of the jitter (default: a fresh one)")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    args = parser.parse_args(argv)
    try:
        prof = profile_from_args(args)
    except ConfigError as exc:
        print(f"telesurg impair: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=getattr(logging, str(args.log_level).upper(), logging.INFO),
        format="%(asctime)s impair %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, on_signal)
    try:
        try:
            link = LinkImpairer(target=args.target, listen=args.listen, seed=args.seed)
        except OSError as exc:
            print(f"telesurg impair: {exc}", file=sys.stderr)
            return 1
        with link:
            applied = link.set_profile(prof) if prof != LinkProfile() else prof
            print(
                f"impair: {link.endpoint} -> {_format_endpoint(*link.target)} ({link.state}, "
                f"{link.delay_ms:g} ms)",
                flush=True,
            )
            if applied != prof:
                log.warning(
                    "a TCP proxy cannot lose, reorder or drop packets: applied %s of %s; loss, "
                    "reordering and outages need the packet link (tools/bench/impair.py PacketLink, root)",
                    applied.describe(),
                    prof.describe(),
                )
            if args.control:
                threading.Thread(target=_control_loop, args=(link, stop), daemon=True).start()
            stop.wait()
            log.info("stopping; %s", link.stats())
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
