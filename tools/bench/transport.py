"""``telesurg bench transport``: zenoh link protocols for a 1 kHz control stream under packet loss.

Two network namespaces are joined by a :class:`~telesurg.tools.bench.impair.PacketLink` — a TUN
device in each, every IP packet forwarded by this process with a one-way delay and independent random loss —
so each protocol meets real packet loss and its own retransmission: TCP and TLS retransmit in
the kernel and hold every later byte until the lost one arrives (head-of-line blocking), QUIC
streams retransmit in user space, UDP and QUIC datagrams (``?rel=0``) do not retransmit at all.

In one namespace a zenoh router subscribes (the slave site); in the other a client publishes a
stream at ``--rate-hz`` with the control-stream QoS of :meth:`telesurg.shared.bus.Node.outlet` (express,
real-time priority, congestion control BLOCK; reliable, except ``quic-mixed``: best effort over
datagrams, and ``tls+datagram``: the deployed datagram link, best effort over UDP beside the
mutual-TLS session, through the site's ACL). Both stamp CLOCK_MONOTONIC, which namespaces share,
so latency is one-way. The loss
is switched on after the session is up and the stream flows (handshake robustness is not what
is measured). Per protocol and loss rate: delivered %, one-way latency p50/p99/max, and
**stalls** — receive gaps longer than ``--stall-ms`` (no sample reached the slave) — their
count, p99 and longest. TLS and QUIC use mutual TLS with certificates from
:mod:`telesurg.services.certs`, as the deployed site does.

Root only (namespaces, TUN devices). Nothing here asserts a time: the figures go to
``docs/deploy.md``.

Example::

    telesurg bench transport --json docs/data/transport.json
    telesurg bench transport --transports tls,udp --loss 0,0.02 --delay-ms 20 --seconds 10
    telesurg bench transport --profile 5g-microhand --transports tcp,tls,udp,quic \\
        --json docs/data/transport-5g-microhand.json

``--profile NAME`` (and ``--jitter-ms``, ``--burst``, ``--rate-kbps``, ``--outage``, ...: see
:mod:`telesurg.tools.bench.netprofile`) sets the whole link; its loss is the one loss rate run
unless ``--loss`` lists others.
"""

from __future__ import annotations

import argparse
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import IO, Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.shared.bus import BusConfig, open_datagram_session, open_session
from telesurg.shared.errors import ConfigError
from telesurg.shared.timing import CycleTimer
from telesurg.tools.bench.impair import NetNamespace, PacketLink, netns_available
from telesurg.tools.bench.machine import machine, now
from telesurg.tools.bench.netprofile import LinkProfile, add_profile_args, profile_from_args

#: name → (endpoint scheme, endpoint suffix, mutual TLS, best-effort publisher)
TRANSPORTS: dict[str, tuple[str, str, bool, bool]] = {
    "tcp": ("tcp", "", False, False),
    "tls": ("tls", "", True, False),
    "udp": ("udp", "", False, False),
    "quic": ("quic", "", True, False),
    "quic-dgram": ("quic", "?rel=0", True, False),
    "quic-mixed": ("quic", "?mixed_rel=1", True, True),
    # the deployed datagram link (shared/bus.py ``datagram``): a mutual-TLS session and a second,
    # publish-only session on the router's udp/ listener that carries the stream best effort,
    # through the site's ACL (deploy/slave-site/acl.json5), on the master pose's key
    "tls+datagram": ("tls", "", True, True),
}
ACL = Path(__file__).resolve().parents[2] / "deploy" / "slave-site" / "acl.json5"
KEY = "bench/transport/stream"
DATAGRAM_KEY = "telesurg/lab/master/m1/measured_cp"  # the one key the ACL lets a UDP transport put
HEADER = struct.Struct("<qq")  # seq, send time (monotonic ns)
PORT = 7447
ADDR_PUB, ADDR_SUB = "10.251.0.1", "10.251.0.2"


@dataclass
class RunResult:
    """One protocol at one loss rate."""

    transport: str
    loss: float  # packet-loss probability per direction
    delay_ms: float  # one-way delay added by the link
    profile: str = ""  # the link profile's name ("" without one)
    link_profile: str = ""  # what the link did, one line (LinkProfile.describe)
    sent: int = 0  # samples published (after the warm-up)
    received: int = 0  # distinct samples delivered
    latency_ms: dict[str, float] = field(default_factory=dict)  # p50, p99, max of one-way latency
    stalls: int = 0  # receive gaps longer than the stall threshold
    stall_ms: dict[str, float] = field(default_factory=dict)  # p50, p99, max of those gaps
    stalled_pct: float = 0.0  # % of the run inside such a gap
    link: dict[str, int] = field(default_factory=dict)  # packets forwarded / lost by the link
    load: float = 0.0  # 1-min load average at the end of the run (other work on the host)
    error: str = ""  # why the run produced no figures

    @property
    def delivered_pct(self) -> float:
        """Delivered samples, % of those sent."""
        return 100.0 * self.received / self.sent if self.sent else 0.0


def _bus(transport: str, role: str, certs: Path) -> BusConfig:
    scheme, suffix, mtls, _ = TRANSPORTS[transport]
    ep = f"{scheme}/{ADDR_SUB}:{PORT}{suffix}"
    if role == "sub":
        cfg = BusConfig(mode="router", listen=[ep])
        ident = "slave-site"
    else:
        cfg = BusConfig(mode="client", connect=[ep])
        ident = "console"
    if transport == "tls+datagram":
        if role == "sub":
            cfg.listen.append(f"udp/{ADDR_SUB}:{PORT}")
            cfg.acl_file = str(ACL)
        else:
            cfg.datagram = f"udp/{ADDR_SUB}:{PORT}"
    if mtls:
        cfg.tls_root_ca = str(certs / "ca.pem")
        cfg.tls_cert, cfg.tls_key = str(certs / f"{ident}.pem"), str(certs / f"{ident}.key")
        cfg.mtls = True
    return cfg


# ----------------------------------------------------------------------------- roles


def run_sub(transport: str, certs: Path, out: Path) -> int:
    """Router + subscriber: record (seq, sent ns, received ns) until SIGINT/SIGTERM, write ``out``."""
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    rows: list[tuple[int, int, int]] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        now = time.monotonic_ns()
        seq, t_sent = HEADER.unpack_from(sample.payload.to_bytes())
        with lock:
            rows.append((seq, t_sent, now))

    session = open_session(_bus(transport, "sub", certs))
    key = DATAGRAM_KEY if transport == "tls+datagram" else KEY
    _sub = session.declare_subscriber(key, on_sample)  # keep a reference: undeclared on GC
    print("ready", flush=True)
    stop.wait()
    session.close()  # type: ignore[no-untyped-call]
    with lock:
        np.save(out, np.array(rows, dtype=np.int64).reshape(-1, 3))
    return 0


def run_pub(transport: str, certs: Path, rate_hz: float, seconds: float, size: int) -> int:
    """Client publisher: ``seconds`` of samples at ``rate_hz``; prints ``started`` then ``sent N``."""
    import zenoh

    best_effort = TRANSPORTS[transport][3]
    bus = _bus(transport, "pub", certs)
    main_session = session = open_session(bus)
    key, congestion = KEY, zenoh.CongestionControl.BLOCK
    if bus.datagram:  # the datagram session beside the TLS one, as Node.outlet(datagram=True) has it
        session = open_datagram_session(bus)
        key, congestion = DATAGRAM_KEY, zenoh.CongestionControl.DROP
    pub = session.declare_publisher(
        key,
        express=True,
        priority=zenoh.Priority.REAL_TIME,
        congestion_control=congestion,
        reliability=zenoh.Reliability.BEST_EFFORT if best_effort else zenoh.Reliability.RELIABLE,
    )
    pad = b"\0" * max(0, size - HEADER.size)
    timer = CycleTimer(rate_hz)
    n = int(rate_hz * seconds)
    print("started", flush=True)
    for seq in range(n):
        pub.put(HEADER.pack(seq, time.monotonic_ns()) + pad)
        timer.wait()
    print(f"sent {n} overruns {timer.overruns}", flush=True)
    time.sleep(0.5)  # let the last samples leave before the session closes
    session.close()  # type: ignore[no-untyped-call]
    if main_session is not session:
        main_session.close()  # type: ignore[no-untyped-call]
    return 0


# ----------------------------------------------------------------------------- analysis


def _pcts(values: np.ndarray) -> dict[str, float]:
    if values.size == 0:
        return {}
    return {
        "p50": round(float(np.percentile(values, 50)), 2),
        "p99": round(float(np.percentile(values, 99)), 2),
        "max": round(float(values.max()), 2),
    }


def analyse(rows: np.ndarray, result: RunResult, first_seq: int, stall_ms: float) -> RunResult:
    """Fill ``result`` from the subscriber's rows, counting from sample ``first_seq`` (loss on)."""
    rows = rows[rows[:, 0] >= first_seq]
    _, idx = np.unique(rows[:, 0], return_index=True)
    rows = rows[np.sort(idx)]
    result.received = len(rows)
    if not len(rows):
        result.error = "nothing delivered"
        return result
    result.latency_ms = _pcts((rows[:, 2] - rows[:, 1]) / 1e6)
    recv = np.sort(rows[:, 2])
    gaps = np.diff(recv) / 1e6
    stalls = gaps[gaps > stall_ms]
    result.stalls = len(stalls)
    result.stall_ms = _pcts(stalls)
    span = (recv[-1] - recv[0]) / 1e6
    result.stalled_pct = round(100.0 * float(stalls.sum()) / span, 2) if span > 0 else 0.0
    return result


# ----------------------------------------------------------------------------- orchestration


def _readline(stream: IO[str], want: str, timeout: float) -> str:
    """The first line of ``stream`` starting with ``want`` (raises TimeoutError / EOFError)."""
    box: list[str] = []

    def read() -> None:
        for line in stream:
            if line.startswith(want):
                box.append(line.strip())
                return

    t = threading.Thread(target=read, daemon=True)
    t.start()
    t.join(timeout)
    if not box:
        raise TimeoutError(f"no {want!r} line within {timeout:g} s")
    return box[0]


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def measure(
    transport: str,
    loss: float,
    *,
    prof: LinkProfile,
    profile_name: str = "",
    seconds: float,
    rate_hz: float,
    size: int,
    stall_ms: float,
    certs: Path,
    work: Path,
    seed: int,
) -> RunResult:
    """One run: fresh namespaces and link, router+subscriber, publisher; ``prof`` without its loss
    and outages from the start, with ``loss`` (and the outages) from 1 s on."""
    lossy = replace(prof, loss=loss)
    result = RunResult(transport, loss, prof.delay_ms, profile_name, lossy.describe())
    tag = f"{os.getpid() % 100000}"
    me = [sys.executable, "-m", "telesurg.tools.bench.transport"]
    common = ["--transport", transport, "--certs", str(certs)]
    out = work / f"{transport}-{loss:g}.npy"
    with (
        NetNamespace(f"tsb-pub-{tag}") as ns_pub,
        NetNamespace(f"tsb-sub-{tag}") as ns_sub,
        PacketLink(ns_pub.name, ns_sub.name, addr_a=ADDR_PUB, addr_b=ADDR_SUB, seed=seed) as link,
    ):
        link.set_profile(replace(prof, loss=0.0, outage_ms=0.0))
        env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
        sub = subprocess.Popen(
            ns_sub.cmd([*me, "--role", "sub", *common, "--out", str(out)]),
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        pub: subprocess.Popen[str] | None = None
        try:
            assert sub.stdout is not None
            _readline(sub.stdout, "ready", 30.0)
            warm_s = 1.0
            run_s = f"{seconds + warm_s:g}"
            pub_args = ["--rate-hz", f"{rate_hz:g}", "--size", str(size), "--seconds", run_s]
            pub = subprocess.Popen(
                ns_pub.cmd([*me, "--role", "pub", *common, *pub_args]),
                stdout=subprocess.PIPE,
                text=True,
                env=env,
            )
            assert pub.stdout is not None
            _readline(pub.stdout, "started", 30.0)
            time.sleep(warm_s)
            link.set_profile(lossy)
            before = dict(link.counts)
            line = _readline(pub.stdout, "sent", seconds + 30.0)
            result.sent = int(line.split()[1]) - int(rate_hz * warm_s)
            link.set_loss(0.0)
            result.link = {k: v - before[k] for k, v in link.counts.items() if k != "cut"}
            result.load = round(os.getloadavg()[0], 2)
            pub.wait(10)
            time.sleep(1.0)  # stragglers (a retransmission after the last sample)
        except (TimeoutError, subprocess.TimeoutExpired) as exc:
            result.error = str(exc)
        finally:
            if pub is not None:
                _stop(pub)
            _stop(sub)
    if result.error:
        return result
    if not out.exists():
        result.error = "subscriber wrote no results"
        return result
    return analyse(np.load(out), result, int(rate_hz * 1.0), stall_ms)


def table(results: Sequence[RunResult], stall_ms: float) -> str:
    """Markdown table of the runs."""
    lines = [
        f"| link | loss % | delivered % | latency p50 ms | p99 ms | max ms | stalls > {stall_ms:g} ms "
        "| stall p99 ms | longest stall ms | time stalled % | load |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in results:
        if r.error:
            lines.append(f"| {r.transport} | {100 * r.loss:g} | – | {r.error} | | | | | | | |")
            continue
        lat, st = r.latency_ms, r.stall_ms
        lines.append(
            f"| {r.transport} | {100 * r.loss:g} | {r.delivered_pct:.2f} | {lat.get('p50', 0):.1f} "
            f"| {lat.get('p99', 0):.1f} | {lat.get('max', 0):.1f} | {r.stalls} | "
            f"{st.get('p99', 0):.0f} | {st.get('max', 0):.0f} | {r.stalled_pct:.2f} | {r.load:.1f} |"
        )
    return "\n".join(lines)


def _make_certs(where: Path) -> Path:
    from telesurg.services.certs import CertsConfig, make_certs

    make_certs(CertsConfig(out=where, hosts=("localhost", ADDR_SUB)))
    return where


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench transport``: 0 when every run produced figures, 1 otherwise, 2 if unsupported."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench transport",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument(
        "--transports",
        default="tcp,tls,udp,quic,quic-dgram,tls+datagram",
        help=f"comma-separated, from {', '.join(TRANSPORTS)} (default: all but quic-mixed)",
    )
    ap.add_argument("--loss", help="loss probabilities (default: the profile's, else 0,0.01,0.05)")
    ap.add_argument("--seconds", type=float, default=10.0, help="measured seconds per run (default 10)")
    ap.add_argument("--rate-hz", type=float, default=1000.0, help="stream rate (default 1000)")
    ap.add_argument("--size", type=int, default=128, help="payload bytes (default 128)")
    ap.add_argument("--stall-ms", type=float, default=20.0, help="a receive gap above this is a stall")
    ap.add_argument("--seed", type=int, default=1, help="seed of the link's loss generator")
    ap.add_argument("--json", type=Path, help="write the results here")
    add_profile_args(ap, delay_default=10.0, loss=False)
    # internal: the two ends, started inside the namespaces
    ap.add_argument("--role", choices=("sub", "pub"), help=argparse.SUPPRESS)
    ap.add_argument("--transport", choices=tuple(TRANSPORTS), help=argparse.SUPPRESS)
    ap.add_argument("--certs", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role == "sub":
        return run_sub(args.transport, args.certs, args.out)
    if args.role == "pub":
        return run_pub(args.transport, args.certs, args.rate_hz, args.seconds, args.size)

    transports = [t.strip() for t in args.transports.split(",") if t.strip()]
    bad = [t for t in transports if t not in TRANSPORTS]
    if bad:
        print(f"telesurg bench transport: unknown {bad}; valid: {', '.join(TRANSPORTS)}", file=sys.stderr)
        return 2
    try:
        prof = profile_from_args(args, delay_default=10.0, loss=False)
        default_loss = f"{prof.loss:g}" if args.profile else "0,0.01,0.05"
        losses = [float(x) for x in (args.loss or default_loss).split(",")]
        for loss in losses:
            replace(prof, loss=loss)  # validates
    except (ConfigError, ValueError) as exc:
        print(f"telesurg bench transport: {exc}", file=sys.stderr)
        return 2
    if why := netns_available():
        print(f"telesurg bench transport: {why}", file=sys.stderr)
        return 2
    results: list[RunResult] = []
    with tempfile.TemporaryDirectory(prefix="ts-transport-") as tmp:
        certs = _make_certs(Path(tmp) / "certs")
        for loss in losses:
            for t in transports:
                r = measure(
                    t,
                    loss,
                    prof=prof,
                    profile_name=args.profile,
                    seconds=args.seconds,
                    rate_hz=args.rate_hz,
                    size=args.size,
                    stall_ms=args.stall_ms,
                    certs=certs,
                    work=Path(tmp),
                    seed=args.seed,
                )
                results.append(r)
                print(table([r], args.stall_ms).splitlines()[-1], flush=True)
    named = f"profile {args.profile}: " if args.profile else ""
    header = (
        f"{args.rate_hz:g} Hz × {args.size} B, {args.seconds:g} s per run, {named}{prof.describe()} "
        f"(loss per packet and direction as in the table), {os.cpu_count()} CPUs"
    )
    print(f"\n{header}\n\n{table(results, args.stall_ms)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        data = {
            "when": now(),
            "machine": machine(),
            "setup": header,
            "stall_ms": args.stall_ms,
            "runs": [asdict(r) | {"delivered_pct": round(r.delivered_pct, 3)} for r in results],
        }
        args.json.write_text(jsonio.dumps(data, indent=2) + "\n")
    return 1 if any(r.error for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
