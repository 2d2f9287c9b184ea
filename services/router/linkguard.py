"""The router's link guard: cut off a client link that sends more than its byte budget.

zenoh 1.10.2's router cannot close a session whose messages its ACL or size caps drop: a flooder
keeps its link and its megabytes keep crossing the host's loopback TCP (docs/security.md, "Flood:
where the HOLDs come from"). The guard works below zenoh, on the router process's own sockets:
every ``period_s`` it lists the TCP sockets in ``/proc/self/fd``, reads each connected one's
``tcpi_bytes_received`` (``getsockopt(IPPROTO_TCP, TCP_INFO)``; bytes the kernel received on
the connection, whether or not zenoh has read them yet) and charges them to a token bucket per
link (``budget_mb_s`` refill, ``burst_mb`` depth). A link whose bucket runs dry is shut down
(``shutdown(SHUT_RDWR)``): zenoh's read fails, it closes that transport and the client's session
loses the router; the other links are untouched. A client that reconnects gets a new link with
a full bucket and is cut again when it floods again. Listening sockets are never touched.

The guard sees links, not identities: a link is a peer address (for a local client,
``127.0.0.1:<ephemeral port>``); TLS and the certificate's name are above it. With ``identify``
(the router gives it a look-up in its zenoh admin space: the session id of the client at each link
address) it also recognises a **repeat offender**: a zenoh client whose link is cut reconnects
by itself with the same session id, and each of its new links is cut at once for a cool-down
that doubles with every cut of that session (``cooldown_s``, up to ``max_cooldown_s``); after
the cool-down its new links get the budget and a tenth of the burst. A new session (a restarted flooder)
starts with a full bucket again.

Example (one pass, as the router's thread does it every ``period_s``)::

    guard = LinkGuard(budget_mb_s=200.0, burst_mb=100.0, on_cut=print)
    guard.scan()
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)

#: ``struct tcp_info`` (linux/tcp.h): ``tcpi_state`` is its first byte, ``__u64
#: tcpi_bytes_received`` (Linux ≥ 4.1) follows 8 bytes of flags, 24 ``__u32`` fields and four
#: ``__u64`` (pacing_rate, max_pacing_rate, bytes_acked): offset 128 (checked on Linux 6.18 by
#: ``tests/test_link_guard.py``)
TCPI_STATE_OFFSET = 0
TCPI_BYTES_RECEIVED_OFFSET = 128
TCP_INFO_LEN = 136
TCP_ESTABLISHED = 1
TCP_LISTEN = 10


@dataclass(frozen=True)
class LinkCut:
    """One link the guard shut down."""

    peer: str  # the client's address, ``host:port``
    local: str  # the router's end, ``host:port``
    received_bytes: int  # bytes received on the link in all, when it was cut
    seen_s: float  # since the guard first saw the link (0: cut at the first look)
    rate_mb_s: float | None  # received rate since the previous look, MB/s (None at the first look)
    budget_mb_s: float  # the guard's budget and burst when it cut
    burst_mb: float
    session: str = ""  # the client's zenoh session id, if ``identify`` knew it
    strikes: int = 1  # cuts of that session so far (this one included)
    banned_s: float = 0.0  # its new links are cut at once for this long (0: no cool-down)

    def describe(self) -> str:
        """The event's text."""
        rate = "at the first look"
        if self.rate_mb_s is not None:
            rate = f"{self.rate_mb_s:.0f} MB/s at the last look"
        who = ""
        if self.session:
            who = f"; session {self.session}, cut {self.strikes} time{'s' if self.strikes > 1 else ''}"
            who += f", its new links cut for {self.banned_s:g} s"
        return (
            f"cut off link from {self.peer} (to {self.local}): {self.received_bytes / 1e6:.1f} MB received "
            f"in {self.seen_s:.2f} s since first seen, {rate}; budget {self.budget_mb_s:g} MB/s, "
            f"burst {self.burst_mb:g} MB{who}"
        )


@dataclass
class _Link:
    peer: str
    local: str
    first_t: float
    last_t: float
    last_bytes: int
    tokens: float  # bytes the link may still receive at once
    cap: float  # depth of its bucket, bytes
    session: str = ""  # the zenoh session at it, once ``identify`` found it among the offenders
    peak_rate: float = 0.0  # highest rate over a window of at least ``PEAK_WINDOW_S``, bytes/s
    window_t: float = 0.0
    window_bytes: int = 0


PEAK_WINDOW_S = 0.5
#: s after its first sighting a link is still looked up among the offenders (zenoh lists a session's
#: link once its TLS and zenoh handshakes are done, not at the TCP accept)
IDENTIFY_S = 3.0
#: an offender's bucket depth after its cool-down, as a fraction of the burst
OFFENDER_BURST = 0.1


@dataclass
class LinkGuard:
    """Token bucket per connected TCP link of this process; see the module docstring.

    ``on_cut(cut)`` runs on the guard's thread after a link is shut down.
    """

    budget_mb_s: float  # refill of each link's bucket, MB/s
    burst_mb: float  # depth of the bucket (what a link may send at once above the budget), MB
    on_cut: Callable[[LinkCut], None] = lambda cut: None
    period_s: float = 0.05  # scan period, s
    # local ports whose links are guarded; None: the ports this process listens on (found at each
    # scan), i.e. the links clients opened to the router, not connections the process made itself
    ports: frozenset[int] | None = None
    # peer addresses -> the zenoh session id at each (those it knows); None: no repeat offenders
    identify: Callable[[list[str]], dict[str, str]] | None = None
    cooldown_s: float = 1.0  # a repeat offender's new links are cut for this long after its 1st cut,
    max_cooldown_s: float = 60.0  # doubling with each further cut, up to this
    _strikes: dict[str, tuple[int, float]] = field(default_factory=dict)  # session -> (cuts, banned until)
    cuts: deque[LinkCut] = field(default_factory=lambda: deque(maxlen=1000))  # the latest
    n_cuts: int = 0  # links cut so far
    _links: dict[int, _Link] = field(default_factory=dict)  # socket inode -> state
    # links seen and closed: peer -> (peak B/s, bytes)
    _peaks: dict[str, tuple[float, int]] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    # -- one pass -------------------------------------------------------------------------
    def scan(self, now: float | None = None) -> list[LinkCut]:
        """Inspect every connected TCP socket once; shut down those over budget; the cuts."""
        now = time.monotonic() if now is None else now
        seen: set[int] = set()
        cuts: list[LinkCut] = []
        established: list[tuple[int, socket.socket, int]] = []  # (inode, socket, local port)
        listening: set[int] = set()
        try:
            for inode, sock in _tcp_sockets():
                if sock[1] == TCP_LISTEN:
                    listening.add(sock[2])
                    sock[0].close()
                elif sock[1] == TCP_ESTABLISHED:
                    established.append((inode, sock[0], sock[2]))
                else:
                    sock[0].close()
            ports = self.ports if self.ports is not None else listening
            guarded = [(inode, s) for inode, s, port in established if port in ports]
            offenders = self._offenders(guarded, now)
            for inode, s in guarded:
                seen.add(inode)
                cut = self._inspect(s, inode, now, offenders)
                if cut is not None:
                    cuts.append(cut)
        finally:
            for _, s, _ in established:
                s.close()
        for inode in set(self._links) - seen:  # closed links
            gone = self._links.pop(inode)
            self._keep_peak(gone)
        for cut in cuts:
            self.cuts.append(cut)
            self.n_cuts += 1
            try:
                self.on_cut(cut)
            except Exception:  # (a report that fails must not stop the guard)
                log.exception("link guard: reporting a cut failed")
        return cuts

    def _offenders(self, guarded: list[tuple[int, socket.socket]], now: float) -> dict[int, tuple[str, bool]]:
        """inode -> (session id, in its cool-down) of the new links whose session was cut before
        (remembered until ``max_cooldown_s`` after its cool-down)."""
        self._strikes = {k: v for k, v in self._strikes.items() if now < v[1] + self.max_cooldown_s}
        if self.identify is None or not self._strikes:
            return {}
        new = {}
        for inode, s in guarded:
            link = self._links.get(inode)
            if link is None or (not link.session and now - link.first_t < IDENTIFY_S):
                with contextlib.suppress(OSError):
                    new[_addr(s.getpeername())] = inode
        if not new:
            return {}
        sessions = self._identify(list(new))
        return {
            new[peer]: (zid, self._strikes[zid][1] > now)
            for peer, zid in sessions.items()
            if peer in new and zid in self._strikes
        }

    def _identify(self, peers: list[str]) -> dict[str, str]:
        if self.identify is None:
            return {}
        try:
            return self.identify(peers)
        except Exception:  # (the look-up is a help, not a condition)
            log.exception("link guard: identifying links failed")
            return {}

    def _inspect(
        self, sock: socket.socket, inode: int, now: float, offenders: dict[int, tuple[str, bool]]
    ) -> LinkCut | None:
        try:
            info = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, TCP_INFO_LEN)
            peer, local = _addr(sock.getpeername()), _addr(sock.getsockname())
        except OSError:  # closed meanwhile
            return None
        if len(info) < TCP_INFO_LEN:
            return None  # a kernel without tcpi_bytes_received
        received = struct.unpack_from("=Q", info, TCPI_BYTES_RECEIVED_OFFSET)[0]  # (host order)
        link = self._links.get(inode)
        burst = self.burst_mb * 1e6
        known, banned = offenders.get(inode, ("", False))
        if link is None:
            # everything it received before the guard first saw it counts
            link = _Link(peer, local, now, now, 0, burst, burst, window_t=now)
            self._links[inode] = link
        if known and not link.session:  # a session cut before: a tenth of the burst
            link.session = known
            link.tokens -= link.cap * (1.0 - OFFENDER_BURST)
            link.cap *= OFFENDER_BURST
        dt = max(now - link.last_t, 0.0)
        got = received - link.last_bytes
        link.tokens = min(link.cap, link.tokens + self.budget_mb_s * 1e6 * dt) - got
        rate = got / dt if dt > 0 else 0.0
        link.last_t, link.last_bytes = now, received
        link.window_bytes += got
        if now - link.window_t >= PEAK_WINDOW_S:
            link.peak_rate = max(link.peak_rate, link.window_bytes / (now - link.window_t))
            link.window_t, link.window_bytes = now, 0
        if link.tokens >= 0 and not banned:
            return None
        session = known or self._identify([link.peer]).get(link.peer, "")
        with contextlib.suppress(OSError):  # (already closing)
            sock.shutdown(socket.SHUT_RDWR)
        strikes, cooldown = 1, 0.0
        if session:
            strikes = self._strikes.get(session, (0, 0.0))[0] + 1
            cooldown = min(self.cooldown_s * 2 ** (strikes - 1), self.max_cooldown_s)
            self._strikes[session] = (strikes, now + cooldown)
        del self._links[inode]
        if now > link.window_t:  # (the window it was cut in)
            link.peak_rate = max(link.peak_rate, link.window_bytes / (now - link.window_t))
        self._keep_peak(link)
        return LinkCut(
            link.peer,
            link.local,
            received,
            round(now - link.first_t, 3),
            round(rate / 1e6, 1) if dt > 0 else None,
            self.budget_mb_s,
            self.burst_mb,
            session,
            strikes,
            cooldown,
        )

    def _keep_peak(self, link: _Link) -> None:
        total = link.last_bytes
        if link.peer in self._peaks:
            total = max(total, self._peaks[link.peer][1])
        self._peaks[link.peer] = (max(link.peak_rate, self._peaks.get(link.peer, (0.0, 0))[0]), total)
        while len(self._peaks) > 256:  # keep the newest
            self._peaks.pop(next(iter(self._peaks)))

    def peaks(self, cut: bool = True) -> dict[str, tuple[float, float]]:
        """Links seen (the last 256 closed and every open one; with ``cut=False`` only those never
        cut): peer -> (highest received rate over ≥ 0.5 s windows in MB/s, MB in all)."""
        out = {p: (round(r / 1e6, 3), round(b / 1e6, 1)) for p, (r, b) in self._peaks.items()}
        for link in self._links.values():
            out[link.peer] = (round(link.peak_rate / 1e6, 3), round(link.last_bytes / 1e6, 1))
        if not cut:
            for c in self.cuts:
                out.pop(c.peer, None)
        return out

    # -- the thread -----------------------------------------------------------------------
    def start(self) -> LinkGuard:
        """Scan every ``period_s`` on a daemon thread until :meth:`stop`."""
        self._thread = threading.Thread(target=self._loop, name="link-guard", daemon=True)
        self._thread.start()
        return self

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.scan()
            except Exception:  # (never let the guard die silently)
                log.exception("link guard: scan failed")

    def stop(self) -> None:
        """Stop the thread (waits for it)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def _tcp_sockets() -> list[tuple[int, tuple[socket.socket, int, int]]]:
    """(inode, (socket, TCP state, local port)) of every TCP socket this process has open; each
    socket a duplicate of the process's descriptor (the caller closes it)."""
    out = []
    for inode, fd in _socket_fds():
        try:
            dup = os.dup(fd)
        except OSError:  # closed meanwhile
            continue
        try:
            if os.fstat(dup).st_ino != inode:  # the fd number was reused meanwhile
                os.close(dup)
                continue
            sock = socket.socket(fileno=dup)
        except OSError:
            os.close(dup)
            continue
        try:
            if sock.family not in (socket.AF_INET, socket.AF_INET6) or sock.type != socket.SOCK_STREAM:
                sock.close()
                continue
            state = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[TCPI_STATE_OFFSET]
            out.append((inode, (sock, state, int(sock.getsockname()[1]))))
        except (OSError, IndexError):
            sock.close()
    return out


def _socket_fds() -> list[tuple[int, int]]:
    """(inode, fd) of every socket this process has open."""
    out: list[tuple[int, int]] = []
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return out
    for name in fds:
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:
            continue
        if target.startswith("socket:["):
            out.append((int(target[8:-1]), int(name)))
    return out


def _addr(a: object) -> str:
    if isinstance(a, tuple) and len(a) >= 2:
        host = str(a[0])
        return f"[{host}]:{a[1]}" if ":" in host else f"{host}:{a[1]}"
    return str(a)
