"""A UDP datagram flow for measuring a link: a sender stamps each datagram, a receiver records it.

Both ends read CLOCK_REALTIME, which network namespaces share — the sender just before the send,
the receiver's kernel when the datagram arrives (``SO_TIMESTAMPNS``: the receiver's own wake-up
is not counted) — so the rows give the one-way delay of every datagram. Used by the link-profile
tests, run inside the namespaces of a :class:`~telesurg.tools.bench.impair.PacketLink`::

    ip netns exec B python -m telesurg.tools.bench.udpflow recv 10.251.0.2 9000 --out rows.npy
    ip netns exec A python -m telesurg.tools.bench.udpflow send 10.251.0.2 9000 --count 2000 \\
        --interval-ms 1 --size 100

The receiver prints ``ready`` once bound and writes an int64 array of rows (sequence number,
send ns, receive ns, datagram bytes), in arrival order, when it has seen nothing for
``--idle-s`` after the first datagram (or at ``--max-s``, or on SIGINT/SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import socket
import struct
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

HEADER = struct.Struct("<qq")  # sequence number, send time (CLOCK_REALTIME ns)
_TIMESPEC = struct.Struct("@ll")  # struct timespec of SO_TIMESTAMPNS
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; Python 3.11 does not name it
IP_UDP_OVERHEAD = 28  # bytes of IPv4 + UDP header around each datagram


def send(addr: str, port: int, count: int, interval_ms: float, size: int) -> int:
    """Send ``count`` datagrams of ``size`` bytes, one every ``interval_ms`` (on a fixed schedule)."""
    pad = b"\0" * max(0, size - HEADER.size)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        t0 = time.monotonic()
        for seq in range(count):
            wait = t0 + seq * interval_ms / 1000.0 - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            with contextlib.suppress(OSError):  # ENOBUFS: the device queue is full; it is lost
                sock.sendto(HEADER.pack(seq, time.time_ns()) + pad, (addr, port))
    print(f"sent {count}", flush=True)
    return 0


def recv(addr: str, port: int, out: Path, idle_s: float, max_s: float) -> int:
    """Record every datagram until idle for ``idle_s`` after the first one; write ``out``."""
    stop = [False]

    def on_signal(*_: object) -> None:
        stop[0] = True

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    rows: list[tuple[int, int, int, int]] = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        sock.bind((addr, port))
        sock.settimeout(0.05)
        print("ready", flush=True)
        deadline = time.monotonic() + max_s
        last = 0.0
        while not stop[0] and time.monotonic() < deadline:
            try:
                data, anc, _, _ = sock.recvmsg(65536, 64)
            except TimeoutError:
                if rows and time.monotonic() - last > idle_s:
                    break
                continue
            last = time.monotonic()
            now = time.time_ns()
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    now = sec * 1_000_000_000 + nsec
            seq, sent = HEADER.unpack_from(data)
            rows.append((seq, sent, now, len(data)))
    np.save(out, np.array(rows, dtype=np.int64).reshape(-1, 4))
    print(f"received {len(rows)}", flush=True)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m telesurg.tools.bench.udpflow send|recv ...``."""
    ap = argparse.ArgumentParser(
        prog="udpflow", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    ap.add_argument("role", choices=("send", "recv"))
    ap.add_argument("addr", help="the receiver's IPv4 address")
    ap.add_argument("port", type=int)
    ap.add_argument("--count", type=int, default=1000, help="datagrams to send")
    ap.add_argument("--interval-ms", type=float, default=1.0, help="between two sends, ms")
    ap.add_argument("--size", type=int, default=64, help="UDP payload bytes (>= 16)")
    ap.add_argument("--out", type=Path, help="receiver: the rows (.npy)")
    ap.add_argument("--idle-s", type=float, default=1.0, help="receiver: stop this long after the last")
    ap.add_argument("--max-s", type=float, default=60.0, help="receiver: stop after this long at most")
    args = ap.parse_args(argv)
    if args.role == "send":
        return send(args.addr, args.port, args.count, args.interval_ms, max(args.size, HEADER.size))
    if args.out is None:
        ap.error("recv needs --out")
    return recv(args.addr, args.port, args.out, args.idle_s, args.max_s)


if __name__ == "__main__":
    sys.exit(main())
