"""``telesurg bench flood``: 1 MB messages on a control key and a master key; memory and holds.

A running pipeline (watchdog, slave_control, mapping, master_capture, mirror; the scripted
master re-clutches every 4 s) is flooded for ``--seconds`` (default 10) by a client sending
``--size`` (default 1 MiB) messages as fast as it can, alternating between a control key
(``slave/arm1/servo_jp``) and a master key (``master/m1/measured_cp``). Recorded:

* RSS of router, watchdog, mapping, mirror and slave_control before the flood, at its peak and
  ``--after`` s (default 30) after it (``/proc``, through psutil);
* the watchdog's entries into HOLD during the flood (+1 s) and in a quiet window of the same
  length before it, and whether the slave followed again afterwards;
* messages sent by the flooder and how many reached a subscriber (the bench's probe).

and, to find what the flood does to the control path, per window: the CPU each site process used
(and each thread of the router by name: zenoh's ``rx-*``, ``tx-*`` pools), the host's CPU
(``/proc/stat``: user, system, softirq, steal; ``ksoftirqd``; softnet drops and squeezes), and
the causes the watchdog gave for each entry into HOLD.

``--rounds N`` then alternates N quiet and N flood windows of ``--window`` s (default 5) on the
same pipeline: the host's other load changes slowly compared with a window, so the HOLD entries
of the two kinds of window compare the flood with its absence under the same load.
``--separate`` floods from a process of its own (nice 0, its own session and scheduler
autogroup: an attacker's process), not from a thread of the bench process (which also hosts the
probe). ``--no-mirror`` leaves the mirror out (it runs under ``SCHED_IDLE`` and may not start on
a saturated host); ``--acl-log off`` runs the router without its ACL log.

``--site locked`` (default) runs the locked-down site (``telesurg up --acl``: local mutual TLS,
deploy/slave-site/acl.json5, size caps) and floods from an identity the ACL refuses on those keys
(``site-mirror``); ``--flooder master_capture`` floods from an identity the ACL allows on the master
key (only the size cap stops it). ``--site open`` runs the plain local site; with
``--no-caps`` the router's size caps are off (the situation before them).

Example::

    telesurg bench flood --json docs/data/perf/flood.json
    telesurg bench flood --site open --no-caps --json out/flood-open.json
    telesurg bench flood --separate --rounds 5 --json out/flood-rounds.json
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from telesurg.services.launcher import deploy_dir
from telesurg.shared import jsonio
from telesurg.shared.bus import BusConfig, open_session
from telesurg.shared.errors import TelesurgError
from telesurg.tools.bench.harness import Pipeline, now_ns
from telesurg.tools.bench.machine import machine, now, stat_cpu_s

log = logging.getLogger("telesurg.bench.flood")

WATCHED = ("router", "watchdog", "mapping", "mirror", "slave_control")
KEYS = ("slave/arm1/servo_jp", "master/m1/measured_cp")


def add_set_argument(ap: argparse.ArgumentParser, example: str) -> None:
    """``--set SERVICE.KEY=VALUE`` (repeatable): a service config override for the bench's pipeline
    (read with :func:`parse_sets`)."""
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SERVICE.KEY=VALUE",
        help=f"a service config override (repeatable), e.g. {example}",
    )


def parse_sets(items: Sequence[str]) -> dict[str, list[str]]:
    """``SERVICE.KEY=VALUE`` items as the pipeline's per-service overrides."""
    out: dict[str, list[str]] = {}
    for item in items:
        name, dot, rest = item.partition(".")
        if not dot or "=" not in rest or name not in WATCHED:
            names = ", ".join(WATCHED)
            raise TelesurgError(f"--set {item!r}: expected SERVICE.KEY=VALUE with SERVICE one of {names}")
        out.setdefault(name, []).append(rest)
    return out


def rss_mb(pipe: Pipeline) -> dict[str, float]:
    """Resident set size of each watched process, MB."""
    psutil: Any = importlib.import_module("psutil")  # (no type stubs)
    out: dict[str, float] = {}
    for name in WATCHED:
        if name in pipe.site.procs and pipe.site.procs[name].poll() is None:
            out[name] = round(psutil.Process(pipe.site.pid(name)).memory_info().rss / 1e6, 1)
    return out


def memory_detail(pipe: Pipeline) -> dict[str, dict[str, float]]:
    """Where each watched process's resident memory is, MB (``/proc/<pid>/smaps``): ``heap``
    (the brk heap: glibc's main arena), ``anon`` (anonymous mappings: glibc's thread arenas and
    large ``mmap`` allocations, Rust's allocations through them, thread stacks) and ``file``
    (code and data of the binaries and libraries)."""
    out: dict[str, dict[str, float]] = {}
    for name in WATCHED:
        if name not in pipe.site.procs or pipe.site.procs[name].poll() is not None:
            continue
        kb = {"heap": 0, "anon": 0, "file": 0}
        files: dict[str, int] = {}
        kind, path = "anon", ""
        try:
            with open(f"/proc/{pipe.site.pid(name)}/smaps") as f:
                for line in f:
                    parts = line.split()
                    if parts and "-" in parts[0] and len(parts) >= 5:  # a mapping's header line
                        path = parts[5] if len(parts) > 5 else ""
                        kind = "heap" if path == "[heap]" else "file" if path.startswith("/") else "anon"
                    elif parts and parts[0] == "Rss:":
                        kb[kind] += int(parts[1])
                        if kind == "file":
                            base = path.rsplit("/", 1)[-1]
                            files[base] = files.get(base, 0) + int(parts[1])
        except OSError:
            continue
        out[name] = {k: round(v / 1024, 1) for k, v in kb.items()}
        for base, v in sorted(files.items(), key=lambda kv: -kv[1])[:3]:  # the largest mapped files
            out[name][f"file:{base}"] = round(v / 1024, 1)
    return out


def holds_between(pipe: Pipeline, t0: int, t1: int) -> int:
    """The watchdog's entries into HOLD with a probe time in [t0, t1)."""
    return len(hold_causes(pipe, t0, t1))


def hold_causes(pipe: Pipeline, t0: int, t1: int) -> list[list[str]]:
    """The causes the watchdog gave for each entry into HOLD with a probe time in [t0, t1)."""
    with pipe.p.lock:
        states = [(t, s, causes) for t, s, causes, *_ in pipe.p.safety]
    out: list[list[str]] = []
    prev = ""
    for t, s, causes in states:
        if s == "HOLD" and prev != "HOLD" and t0 <= t < t1:
            out.append(list(causes))
        prev = s
    return out


def _ticks(path: str) -> float:
    """utime + stime (s) of a ``/proc/.../stat`` file (0 if gone)."""
    try:
        return sum(stat_cpu_s(path))
    except (OSError, IndexError):
        return 0.0


def _comm(path: str) -> str:
    try:
        with open(path) as f:
            return f.read().strip()
    except OSError:
        return "?"


def cpu_snapshot(pipe: Pipeline) -> dict[str, Any]:
    """CPU seconds so far of every site process (and of this bench process: the flooder's
    thread and the probe), and of each thread of the router by name (zenoh's runtime pools:
    ``rx-*``, ``tx-*``, ``net-*``, ``acc-*``, ``app-*``)."""
    procs: dict[str, float] = {}
    for name, p in pipe.site.procs.items():
        if p.poll() is None:
            procs[name] = _ticks(f"/proc/{p.pid}/stat")
    procs["bench (flooder + probe)"] = _ticks(f"/proc/{os.getpid()}/stat")
    with contextlib.suppress(OSError):  # the kernel's softirq threads: loopback TCP delivery they take over
        for pid in os.listdir("/proc"):
            if pid.isdigit() and _comm(f"/proc/{pid}/comm").startswith("ksoftirqd/"):
                procs["ksoftirqd"] = procs.get("ksoftirqd", 0.0) + _ticks(f"/proc/{pid}/stat")
    threads: dict[str, float] = {}
    if "router" in pipe.site.procs:
        task = f"/proc/{pipe.site.pid('router')}/task"
        with contextlib.suppress(OSError):
            for tid in os.listdir(task):
                name = _comm(f"{task}/{tid}/comm")
                threads[name] = threads.get(name, 0.0) + _ticks(f"{task}/{tid}/stat")
    host: dict[str, float] = {}
    with contextlib.suppress(OSError), open("/proc/stat") as f:
        names = ("user", "nice", "system", "idle", "iowait", "irq", "softirq", "steal")
        fields = f.readline().split()[1:9]
        host = {n: int(v) / os.sysconf("SC_CLK_TCK") for n, v in zip(names, fields, strict=False)}
    with contextlib.suppress(OSError, ValueError), open("/proc/net/softnet_stat") as f:
        # per CPU: processed, dropped, time_squeeze (hex): softirq ran out of budget, the rest of
        # the backlog waits for ksoftirqd (counts, not seconds; cpu_share reports them per second)
        rows = [line.split() for line in f]
        host["softnet_dropped"] = float(sum(int(r[1], 16) for r in rows))
        host["softnet_time_squeeze"] = float(sum(int(r[2], 16) for r in rows))
    return {
        "t": time.monotonic(),
        "procs": procs,
        "router_threads": threads,
        "host": host,
        "load": os.getloadavg(),
    }


def cpu_share(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Cores used between two :func:`cpu_snapshot` calls (1.0 = one core busy all the time)."""
    dt = max(b["t"] - a["t"], 1e-6)

    def rate(x: dict[str, float], y: dict[str, float]) -> dict[str, float]:
        used = {k: (v - x.get(k, 0.0)) / dt for k, v in y.items()}
        return {k: round(v, 3) for k, v in sorted(used.items(), key=lambda kv: -kv[1])}

    return {
        "seconds": round(dt, 2),
        "cores": rate(a["procs"], b["procs"]),
        "router_threads_cores": rate(a["router_threads"], b["router_threads"]),
        "host_cores": rate(a["host"], b["host"]),  # the whole VM (/proc/stat): user, softirq, steal, ...
        "load_average_1min": [round(a["load"][0], 2), round(b["load"][0], 2)],
    }


def send(bus: BusConfig, site: str, seconds: float, size: int, ready: Any = None) -> int:
    """Put ``size``-byte messages on :data:`KEYS` in turn for ``seconds`` from ``bus``'s identity,
    as fast as one zenoh publisher takes them; the number of ``put()`` calls. ``ready()``, if
    given, is called once the session and publishers are up, before the first put."""
    payload = b"\xa5" * size
    sent = 0
    tx = open_session(bus)
    try:
        pubs = [tx.declare_publisher(f"telesurg/{site}/{k}") for k in KEYS]
        if ready is not None:
            ready()
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            pubs[sent % 2].put(payload)
            sent += 1
    finally:
        tx.close()  # type: ignore[no-untyped-call]
    return sent


class FloodProcess:
    """:func:`send` in a process of its own (its own session and scheduler autogroup, nice 0: an
    attacker's process on the host, not a thread of the bench). :meth:`start` returns once its
    session and publishers are up (the interpreter's start is no part of a flood window);
    :meth:`run` floods and returns the number of ``put()`` calls."""

    def __init__(self, bus: BusConfig, site: str, seconds: float, size: int) -> None:
        argv = [sys.executable, "-m", "telesurg.tools.bench.flood", "--send-only", json.dumps(asdict(bus))]
        argv += ["--site-name", site, "--seconds", str(seconds), "--size", str(size)]
        self.seconds = seconds
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None,  # (the bench's: a failure to connect shows)
            text=True,
            start_new_session=True,
        )

    def start(self) -> FloodProcess:
        """Wait until the flooder is connected and ready."""
        assert self.proc.stdout is not None
        for line in self.proc.stdout:  # (zenoh may log to stdout before)
            if line.strip() == "ready":
                return self
        self.proc.kill()
        self.proc.wait()
        raise TelesurgError(f"the flooding process did not start (exit code {self.proc.returncode})")

    def run(self) -> int:
        """Flood now; the number of ``put()`` calls (once the flooder says so: its interpreter's
        exit is no part of a flood window either; :meth:`close` waits for it)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write("go\n")
        self.proc.stdin.flush()
        for line in self.proc.stdout:
            if line.startswith("sent "):
                return int(line.split()[1])
        raise TelesurgError(f"the flooding process failed (exit code {self.proc.wait()})")

    def close(self) -> None:
        """Wait for the process to exit (kill it after 30 s)."""
        try:
            self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()


def _send_only(args: argparse.Namespace) -> int:
    """The flooding process of ``--separate``: connect, say ``ready``, wait for ``go``, flood."""

    def ready() -> None:
        print("ready", flush=True)
        sys.stdin.readline()

    bus = BusConfig(**json.loads(args.send_only))
    print(f"sent {send(bus, args.site_name, args.seconds, args.size, ready)}", flush=True)
    return 0


def flood(
    pipe: Pipeline, bus: BusConfig, seconds: float, size: int, proc: FloodProcess | None = None
) -> dict[str, Any]:
    """Flood from ``bus``'s identity (from ``proc``, started, if given); sent / delivered counts
    and peak RSS."""
    site = pipe.spec.site
    delivered = [0]
    peak: dict[str, float] = {}
    rx = pipe.node.session

    def on_big(sample: Any) -> None:
        if len(sample.payload) > 64 * 1024:
            delivered[0] += 1

    subs = [rx.declare_subscriber(f"telesurg/{site}/{k}", on_big) for k in KEYS]
    stop = threading.Event()

    def sample_rss() -> None:
        while not stop.wait(0.5):
            for name, mb in rss_mb(pipe).items():
                peak[name] = max(peak.get(name, 0.0), mb)

    sampler = threading.Thread(target=sample_rss, daemon=True)
    sampler.start()
    try:
        sent = proc.run() if proc is not None else send(bus, site, seconds, size)
    finally:
        stop.set()
        sampler.join()
        for s in subs:
            s.undeclare()  # type: ignore[no-untyped-call]
    return {"sent": sent, "delivered_over_64k": delivered[0], "peak_rss_mb": peak}


def link_cuts(pipe: Pipeline) -> list[float]:
    """MB received on each link the router's link guard cut off so far (its log's ``link_cut``
    lines), in order."""
    try:
        text = (pipe.log_dir / "router.log").read_text(errors="replace")
    except OSError:
        return []
    out = []
    for line in text.splitlines():
        if "link_cut: cut off link" in line:
            with contextlib.suppress(ValueError, IndexError):
                out.append(float(line.split(": ", 3)[-1].split(" MB received")[0].rsplit(" ", 1)[-1]))
    return out


def alternate(pipe: Pipeline, bus: BusConfig, args: argparse.Namespace) -> list[dict[str, Any]]:
    """``args.rounds`` pairs of a quiet window and a flood window, ``args.window`` s each (+0.5 s
    for the watchdog's state to arrive): HOLD entries and their causes, CPU per process, per window.
    The host's other load changes slowly compared with a window, so the two kinds see the same."""
    out: list[dict[str, Any]] = []
    cuts_before = len(link_cuts(pipe))
    for i in range(args.rounds):
        for kind in ("quiet", "flood"):
            proc = None
            if kind == "flood" and args.separate:
                proc = FloodProcess(bus, pipe.spec.site, args.window, args.size).start()
            t0, c0 = now_ns(), cpu_snapshot(pipe)
            sent = 0
            if kind == "quiet":
                time.sleep(args.window)
            elif proc is not None:
                sent = proc.run()
            else:
                sent = send(bus, pipe.spec.site, args.window, args.size)
            c1 = cpu_snapshot(pipe)
            time.sleep(0.5)
            causes = hold_causes(pipe, t0, now_ns())
            if proc is not None:
                proc.close()
            cuts = link_cuts(pipe)
            out.append(
                {
                    "round": i,
                    "kind": kind,
                    "sent": sent,
                    "hold_causes": causes,
                    "link_cuts": len(cuts) - cuts_before,
                    "cut_mb": cuts[cuts_before:],
                    "cpu": cpu_share(c0, c1),
                }
            )
            log.info(
                "round %d %s: %d HOLD entries, %d put calls, %d links cut",
                i,
                kind,
                len(causes),
                sent,
                len(cuts) - cuts_before,
            )
            cuts_before = len(cuts)
    return out


def run(args: argparse.Namespace) -> dict[str, Any]:
    """One flood against a fresh pipeline; the JSON record."""
    out = Path(args.log_dir or tempfile.mkdtemp(prefix="telesurg-flood-"))
    overrides: dict[str, list[str]] = {}
    if args.no_caps:
        overrides["router"] = ["max_message_bytes=0", "max_bulk_bytes=0"]
    if args.acl_log is not None:  # (after the harness's acl_log="denied" on the command line)
        overrides.setdefault("router", []).append(f'acl_log="{args.acl_log}"')
    overrides.setdefault("router", []).extend(args.router_set)
    for name, items in parse_sets(args.set).items():
        overrides.setdefault(name, []).extend(items)
    acl = deploy_dir() / "slave-site" / "acl.json5" if args.site == "locked" else None
    with Pipeline(out, overrides=overrides, impair=False, acl=acl, mirror=not args.no_mirror) as pipe:
        if not pipe.wait_following(120):
            raise TelesurgError("the slave did not follow within 120 s")
        time.sleep(args.settle)
        bus = pipe.spec.client_bus(args.flooder) if acl else BusConfig(connect=[pipe.spec.endpoint])
        quiet0 = now_ns()
        quiet_start = rss_mb(pipe)  # the drift over a window as long as the flood, without it
        cpu_q0 = cpu_snapshot(pipe)
        time.sleep(args.seconds + 1.0)
        cpu_q1 = cpu_snapshot(pipe)
        base = rss_mb(pipe)
        base_detail = memory_detail(pipe)
        proc = FloodProcess(bus, pipe.spec.site, args.seconds, args.size).start() if args.separate else None
        t0 = now_ns()
        cpu_f0 = cpu_snapshot(pipe)
        result = flood(pipe, bus, args.seconds, args.size, proc)
        cpu_f1 = cpu_snapshot(pipe)
        t1 = now_ns()
        time.sleep(1.0)
        causes_flood = hold_causes(pipe, t0, now_ns())
        if proc is not None:
            proc.close()
        cuts_flood = link_cuts(pipe)
        causes_quiet = hold_causes(pipe, quiet0, t0)
        t_after0 = now_ns()
        time.sleep(max(0.0, args.after - 1.0))
        causes_after = hold_causes(pipe, t_after0, now_ns())
        after = rss_mb(pipe)
        after_detail = memory_detail(pipe)
        followed_after = pipe.wait_following(10)
        rounds = alternate(pipe, bus, args) if args.rounds else []
    return {
        "site": args.site,
        "mirror": not args.no_mirror,
        "size_caps": not args.no_caps,
        "acl_log": args.acl_log or "denied",
        "flooder": args.flooder if acl else "any local client (open site)",
        "keys": list(KEYS),
        "message_bytes": args.size,
        "seconds": round((t1 - t0) / 1e9, 2),
        "sent": result["sent"],
        "delivered_over_64k": result["delivered_over_64k"],
        "rss_mb": {
            name: {
                "before": base.get(name),
                "peak": result["peak_rss_mb"].get(name),
                "after": after.get(name),
                "after_minus_before": round(after[name] - base[name], 1)
                if name in after and name in base
                else None,
            }
            for name in WATCHED
        },
        "quiet_drift_mb": {
            name: round(base[name] - quiet_start[name], 1)
            for name in WATCHED
            if name in base and name in quiet_start
        },
        "memory_detail_mb": {"before": base_detail, "after": after_detail},
        "malloc_arena_max": os.environ.get("MALLOC_ARENA_MAX", ""),
        "after_s": args.after,
        "holds_during_flood": len(causes_flood),
        "holds_quiet_window_before": len(causes_quiet),
        "holds_after": len(causes_after),
        "hold_causes": {"quiet_before": causes_quiet, "flood": causes_flood, "after": causes_after},
        "cpu": {"quiet_before": cpu_share(cpu_q0, cpu_q1), "flood": cpu_share(cpu_f0, cpu_f1)},
        "followed_after": followed_after,
        "router_set": list(args.router_set),
        "set": list(args.set),
        "link_cuts_flood": len(cuts_flood),
        "link_cut_mb_flood": cuts_flood,
        "flooder_process": "separate" if args.separate else "a thread of the bench",
        "rounds": rounds,
        "rounds_holds": {
            kind: sum(len(r["hold_causes"]) for r in rounds if r["kind"] == kind)
            for kind in ("quiet", "flood")
        },
        "rounds_link_cuts": sum(r["link_cuts"] for r in rounds if r["kind"] == "flood"),
        "rounds_seconds": {
            kind: round(sum(r["cpu"]["seconds"] + 0.5 for r in rounds if r["kind"] == kind), 1)
            for kind in ("quiet", "flood")
        },
        "logs": str(out),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench flood``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench flood", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--site", choices=("locked", "open"), default="locked", help="default: locked")
    ap.add_argument("--flooder", default="mirror", help="local identity that floods (locked site)")
    ap.add_argument("--no-caps", action="store_true", help="the router's size caps off")
    ap.add_argument(
        "--no-mirror",
        action="store_true",
        help="without the mirror (it runs under SCHED_IDLE and may not start on a saturated host)",
    )
    ap.add_argument(
        "--acl-log",
        choices=("off", "denied", "all"),
        help="the router's acl_log (default: the bench pipeline's, denied)",
    )
    ap.add_argument(
        "--separate",
        action="store_true",
        help="flood from a process of its own (nice 0, its own session), not a thread of the bench",
    )
    ap.add_argument(
        "--rounds",
        type=int,
        default=0,
        help="afterwards, this many pairs of a quiet and a flood window (HOLDs per kind of window)",
    )
    ap.add_argument("--window", type=float, default=5.0, help="length of each window of --rounds (s)")
    ap.add_argument(
        "--router-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a router config override (repeatable), e.g. link_rx_budget_mb_s=0 (the link guard off)",
    )
    add_set_argument(ap, "mirror.malloc_trim_s=0")
    ap.add_argument("--send-only", metavar="BUS_JSON", help=argparse.SUPPRESS)  # (the flooding process)
    ap.add_argument("--site-name", default="local", help=argparse.SUPPRESS)
    ap.add_argument("--seconds", type=float, default=10.0, help="flood duration (default 10)")
    ap.add_argument("--size", type=int, default=1 << 20, help="message bytes (default 1 MiB)")
    ap.add_argument("--after", type=float, default=30.0, help="RSS measured this long after (s)")
    ap.add_argument(
        "--settle",
        type=float,
        default=240.0,
        help="wait after following starts (s, default 240: the mirror's RSS rises in steps for its "
        "first ~200 s, docs/security.md; a shorter settle counts that against the flood)",
    )
    ap.add_argument("--log-dir", help="service logs (default: a temporary folder)")
    ap.add_argument("--json", type=Path, help="write the result here")
    args = ap.parse_args(argv)
    if args.send_only:  # the flooding process of --separate
        return _send_only(args)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        res = run(args)
    except TelesurgError as exc:
        print(f"telesurg bench flood: {exc}")
        return 1
    print(f"flood: {res['sent']} x {res['message_bytes']} B in {res['seconds']} s from {res['flooder']}")
    print(f"  delivered (> 64 KiB) to the probe: {res['delivered_over_64k']}")
    print(f"  {'process':<14} {'before':>8} {'peak':>8} {'after':>8}  MB (after = +{res['after_s']:g} s)")
    for name, r in res["rss_mb"].items():
        drift = res["quiet_drift_mb"].get(name)
        print(f"  {name:<14} {r['before']!s:>8} {r['peak']!s:>8} {r['after']!s:>8}  (no-flood drift {drift})")
    for name, d in res["memory_detail_mb"]["after"].items():
        b = res["memory_detail_mb"]["before"].get(name, {})
        print(f"  {name:<14} " + ", ".join(f"{k} {b.get(k)} → {v}" for k, v in d.items()))
    for window, c in res["cpu"].items():
        print(f"  cores used, {window} ({c['seconds']} s, load average {c['load_average_1min']}):")
        print("    " + ", ".join(f"{k} {v}" for k, v in c["cores"].items()))
        print("    host: " + ", ".join(f"{k} {v}" for k, v in c["host_cores"].items()))
        threads = c["router_threads_cores"].items()
        print("    router threads: " + ", ".join(f"{k} {v}" for k, v in threads if v))
    print(
        f"  HOLDs: {res['holds_during_flood']} during the flood (+1 s), "
        f"{res['holds_quiet_window_before']} in a quiet window before, {res['holds_after']} after; "
        f"followed after: {res['followed_after']}"
    )
    print(
        f"  links the router cut off during the flood: {res['link_cuts_flood']} {res['link_cut_mb_flood']} MB"
    )
    if res["rounds"]:
        print(
            f"  rounds of {args.window:g} s: HOLD entries {res['rounds_holds']} "
            f"in {res['rounds_seconds']} s, "
            f"{res['rounds_link_cuts']} links cut"
        )
    for window, causes in res["hold_causes"].items():
        for c in causes:
            print(f"    HOLD ({window}): {'; '.join(c)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        jsonio.write(args.json, {**res, "date": now(), "machine": machine()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
