"""``telesurg bench links``: the same bare relay over a TCP loopback link and a Unix socket.

On one host the services reach their router over TCP on 127.0.0.1; zenoh also has Unix-domain
stream sockets (``unixsock-stream/<path>``), which skip the TCP stack. Per link and pair of
runs: the bare three-process relay of :mod:`telesurg.tools.bench.relay` (source → relay →
sink through a bare zenoh router in a fourth process, control-stream QoS, no telesurg code on
the path) at ``--rate`` Hz; the CPU of the four processes (user and system time from
``/proc/<pid>/stat``, from 4 s in to 1 s before the end) and the relay's end-to-end latency
p50 / p99. The links alternate, so a change of the host's state hits both.

    telesurg bench links --pairs 4 --seconds 20 --json docs/data/perf/links.json

Nothing here asserts a time: the figures go to docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench.machine import machine, now, stat_cpu_s

LINKS = ("tcp", "unixsock")
_WARM_S = 4.0  # s before the CPU window opens: the sessions are up and the stream flows


def _cpu_s(pids: Sequence[int]) -> tuple[float, float]:
    """(user, system) CPU seconds of ``pids`` so far."""
    times = [stat_cpu_s(f"/proc/{pid}/stat") for pid in pids]
    return sum(u for u, _ in times), sum(s for _, s in times)


def _router(endpoint: str) -> int:
    """A bare zenoh router listening on ``endpoint`` until SIGTERM (prints ``up`` when it is)."""
    import zenoh
    from telesurg.services.common import install_stop_handlers

    stop = threading.Event()
    install_stop_handlers(stop)
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    print("up", flush=True)
    stop.wait()
    session.close()  # type: ignore[no-untyped-call]
    return 0


def _endpoint(link: str, tmp: Path) -> str:
    if link == "unixsock":
        return f"unixsock-stream/{tmp / 'router.sock'}"
    from telesurg.services.launcher import free_port

    return f"tcp/127.0.0.1:{free_port()}"


def run_link(link: str, rate: float, seconds: float, tmp: Path) -> dict[str, Any]:
    """One run over ``link``: CPU of the four processes and the relay's end-to-end latency."""
    (tmp / "router.sock").unlink(missing_ok=True)
    ep = _endpoint(link, tmp)
    me = [sys.executable, "-m", "telesurg.tools.bench.links"]
    router = subprocess.Popen([*me, "--router", ep], stdout=subprocess.PIPE, text=True)
    procs: list[subprocess.Popen[Any]] = [router]
    try:
        assert router.stdout is not None
        if router.stdout.readline().strip() != "up":
            raise RuntimeError(f"the {link} router did not start (exit {router.wait(10)})")
        relay = [sys.executable, "-m", "telesurg.tools.bench.relay"]
        common = ["--connect", ep, "--rate", f"{rate:g}", "--seconds", f"{seconds:g}"]
        out = tmp / f"{link}.npy"
        for role in ("sink", "relay"):
            extra = ["--out", str(out)] if role == "sink" else []
            procs.append(subprocess.Popen([*relay, role, *common, *extra], stdout=subprocess.DEVNULL))
        time.sleep(1.5)  # the subscribers are declared before the source starts
        source = subprocess.Popen([*relay, "source", *common], stdout=subprocess.DEVNULL)
        procs.append(source)
        pids = [p.pid for p in procs]
        time.sleep(_WARM_S)
        u0, s0 = _cpu_s(pids)
        t0 = time.monotonic()
        time.sleep(max(1.0, seconds - _WARM_S - 1.0))
        u1, s1 = _cpu_s(pids)
        window = time.monotonic() - t0
        source.wait(seconds + 30)
        for p in procs[1:3]:  # sink, relay: stop, the sink writes its rows
            p.terminate()
        for p in procs[1:3]:
            p.wait(30)
        rows = np.load(out) if out.exists() else np.zeros((0, 3), np.int64)
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(30)
    e2e_ms = (rows[:, 2] - rows[:, 0]) / 1e6
    sent = int(rate * seconds)
    return {
        "link": link,
        "endpoint": ep,
        "received": len(rows),
        "expected": sent,
        "cpu_user": (u1 - u0) / window,
        "cpu_system": (s1 - s0) / window,
        "cpu": (u1 - u0 + s1 - s0) / window,
        "p50_ms": float(np.percentile(e2e_ms, 50)) if len(rows) else float("nan"),
        "p99_ms": float(np.percentile(e2e_ms, 99)) if len(rows) else float("nan"),
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="telesurg bench links", description=__doc__)
    ap.add_argument("--pairs", type=int, default=4, help="runs of each link, alternating (default 4)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each run, s (default 20)")
    ap.add_argument("--rate", type=float, default=1000.0, help="Hz of the relayed stream (default 1000)")
    ap.add_argument("--json", type=Path, help="write the runs and the summary here")
    ap.add_argument("--router", metavar="ENDPOINT", help=argparse.SUPPRESS)  # (the router process)
    a = ap.parse_args(argv)
    if a.router:
        return _router(a.router)
    if a.pairs < 1 or a.seconds < 8 or a.rate <= 0:
        print("telesurg bench links: needs --pairs >= 1, --seconds >= 8, --rate > 0", file=sys.stderr)
        return 2
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-links-") as d:
        for k in range(a.pairs):
            for link in LINKS:
                r = run_link(link, a.rate, a.seconds, Path(d))
                r["pair"] = k
                runs.append(r)
                print(
                    f"{link:9s} pair {k}: CPU {100 * r['cpu']:5.1f} % of a core "
                    f"(user {100 * r['cpu_user']:.1f}, system {100 * r['cpu_system']:.1f}); "
                    f"end to end p50 {r['p50_ms']:.3f} ms, "
                    f"p99 {r['p99_ms']:.3f} ms; {r['received']} of {r['expected']} received",
                    flush=True,
                )
    summary = {}
    for link in LINKS:
        mine = [r for r in runs if r["link"] == link]
        summary[link] = {
            key: float(np.median([r[key] for r in mine]))
            for key in ("cpu", "cpu_user", "cpu_system", "p50_ms", "p99_ms")
        }
    t, u = summary["tcp"], summary["unixsock"]
    print(
        f"median of {a.pairs}: tcp CPU {100 * t['cpu']:.1f} %, p50 {t['p50_ms']:.3f} ms; unixsock CPU "
        f"{100 * u['cpu']:.1f} %, p50 {u['p50_ms']:.3f} ms (× {u['cpu'] / t['cpu']:.2f} CPU, "
        f"× {u['p50_ms'] / t['p50_ms']:.2f} p50)"
    )
    if a.json:
        res = {"date": now(), "machine": machine(), "rate_hz": a.rate, "seconds": a.seconds}
        res |= {"runs": runs, "median": summary}
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(jsonio.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
