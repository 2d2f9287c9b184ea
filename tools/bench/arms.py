"""``telesurg bench arms``: what each arm at the control rate costs on this host.

For each N of ``--arms`` (default 1,2,4), one site on loopback drives a robot of N identical arms
(``mh3f_x<N>``, :mod:`telesurg.tools.bench.arms_robot`: N MH3F arms at one base) with the real
services: router, watchdog (every arm), slave_control (the N arms in its one control loop on
MuJoCo), mapping (pairs ``m1:arm1 … m1:armN``, the MH3F's cartesian mapping) and master_capture
(the scripted circle at ``--rate``, pedal held). Before each site, in the same run, the bare
zenoh relay (:mod:`telesurg.tools.bench.relay`, three processes) carries a stream at the same rate
through a router as ``bench latency``'s does: the transport's floor to compare with.

Per N: CPU % of each service over ``--seconds`` (psutil, after the site has settled), the slave
loop's and the master loop's deadline misses (their own counters at exit), the watchdog's HOLDs
after the start, and the end-to-end latency of every arm's setpoints (master sample stamped →
the slave's loop uses it, the slave's ``latency_log``) against the relay's end to end. Then the
CPU each arm beyond the first adds (the slope of the total over N) and the largest N that ran
without a HOLD and with under 0.1 % slave deadline misses. Nothing here asserts a time: the
figures are printed and written (``--json``); the goals are in docs/performance.md.

Example::

    telesurg bench arms --arms 1,2,4 --rate 1000 --seconds 20 --json docs/data/perf/arms.json
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench.arms_robot import robot_name, write_scene
from telesurg.tools.bench.machine import machine, now
from telesurg.tools.bench.perf import (
    _overrides,
    _relay_block,
    _stats_ms,
    _workdir,
    deadline_misses,
    watchdog_holds,
)

#: s the site runs before the CPU is sampled (engage, the first holds clearing)
SETTLE_S = 3.0
#: a slave loop missing fewer of its deadlines than this (%) with no HOLD "runs"
MISS_PCT_OK = 0.1
#: a site using this share of the host's cores or more saturates it (its figures are the host's)
SATURATED = 0.9

PLUGIN = """# written by telesurg bench arms: the robot of {n} MH3F arms
from pathlib import Path

from telesurg.tools.bench.arms_robot import register_arms

register_arms({n}, Path(__file__).resolve().parent)
"""

SITE = """# written by telesurg bench arms: {n} MH3F arms driven by one scripted master
[site]
robot = "{robot}"
pairs = [{pairs}]
plugins = ["{plugin}"]
workspace_min_mm = [150.0, -600.0, -200.0]
workspace_max_mm = [1100.0, 600.0, 800.0]

[master_capture]
rt_priority = 20

[mapping]
rt_priority = 20

[slave_control]
rt_priority = 20
"""


def write_site(n: int, d: Path) -> Path:
    """The site directory of the N-arm robot (plugin, scene, site.toml) in ``d``."""
    d.mkdir(parents=True, exist_ok=True)
    plugin = d / "arms_plugin.py"
    plugin.write_text(PLUGIN.format(n=n))
    write_scene(n, d)  # beside the plugin, which registers the robot in each service (a bad model fails here)
    pairs = ", ".join(f'"m1:arm{i}"' for i in range(1, n + 1))
    (d / "site.toml").write_text(SITE.format(n=n, robot=robot_name(n), pairs=pairs, plugin=plugin))
    return d


def _latency(tmp: Path, n: int) -> list[np.ndarray]:
    """Per arm that followed: ns, master sample stamped → the slave's loop used it, of each of its
    setpoints (the first 5 % dropped: the start)."""
    out = []
    for i in range(1, n + 1):
        f = tmp / ("applied.npy" if i == 1 else f"applied.arm{i}.npy")
        if not f.exists():
            continue
        rows = np.load(f).reshape(-1, 5)
        rows = rows[(rows[:, 0] > 0) & (rows[:, 2] > 0)]
        if len(rows):
            out.append((rows[:, 2] - rows[:, 0])[len(rows) // 20 :])
    return out


def run_arms(n: int, a: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    """One N: the relay block, then the N-arm site (module doc)."""
    psutil: Any = importlib.import_module("psutil")  # (no type stubs)

    from telesurg.services.launcher import free_port
    from telesurg.shared.bus import BusConfig, open_session
    from telesurg.tools.bench.harness import Pipeline

    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    try:
        relay = _relay_block(ep, a.rate, a.seconds, tmp, 0)
    finally:
        router.close()  # type: ignore[no-untyped-call]
    site = write_site(n, tmp / "site")
    overrides = _overrides(
        a.rate,
        a.rt_priority,
        slave_control=[f"latency_log={json.dumps(str(tmp / 'applied.npy'))}"],
    )
    with Pipeline(
        tmp / "logs", config_dir=site, mirror=False, impair=False, probe=False, overrides=overrides
    ) as p:
        time.sleep(SETTLE_S)
        procs = {name: psutil.Process(pr.pid) for name, pr in p.site.procs.items()}
        for pr in procs.values():
            pr.cpu_percent(None)
        t_start = time.time()
        time.sleep(a.seconds)
        cpu = {name: round(pr.cpu_percent(None), 1) for name, pr in procs.items()}
        t_stop = time.time()
        p.close()
    logs = {f.stem: f.read_text() for f in (tmp / "logs").glob("*.log")}
    holds = watchdog_holds(logs.get("watchdog", ""), t_stop, since=t_start)
    per_arm, r = _latency(tmp, n), relay[:, 2] - relay[:, 0]
    e2e = np.concatenate(per_arm) if per_arm else np.zeros(0, dtype=np.int64)
    res: dict[str, Any] = {
        "arms": n,
        "arms_followed": len(per_arm),  # arms whose slave used master setpoints
        "cpu_pct": cpu,
        "cpu_total_pct": round(sum(cpu.values()), 1),
        "deadline_misses": deadline_misses(logs),
        "watchdog_holds": len(holds),
        "watchdog_hold_causes": holds,
        "end_to_end_ms": _stats_ms(e2e) if len(e2e) else {},
        "relay_end_to_end_ms": _stats_ms(r),
    }
    if len(e2e):
        res["ratio_p50"] = round(res["end_to_end_ms"]["p50"] / res["relay_end_to_end_ms"]["p50"], 3)
        res["ratio_p99"] = round(res["end_to_end_ms"]["p99"] / res["relay_end_to_end_ms"]["p99"], 3)
    slave = res["deadline_misses"].get("slave_control", {})
    res["runs"] = not holds and len(per_arm) == n and slave.get("miss_pct", 100.0) < MISS_PCT_OK
    return res


def summary(rows: list[dict[str, Any]], cpus: int) -> dict[str, Any]:
    """The CPU each arm beyond the first adds (least squares over the N whose site left the host
    below :data:`SATURATED` of its cores, % of one core; None with fewer than two such N: the
    host's limit, not the arms', would set the slope) and the largest N that ran (no HOLD, slave
    misses under :data:`MISS_PCT_OK` %)."""
    free = [r for r in rows if r["cpu_total_pct"] < SATURATED * 100 * cpus]
    ns = np.array([r["arms"] for r in free], dtype=float)
    cpu = np.array([r["cpu_total_pct"] for r in free])
    slope = round(float(np.polyfit(ns, cpu, 1)[0]), 1) if len(set(ns.tolist())) > 1 else None
    ran = [r["arms"] for r in rows if r["runs"]]
    return {
        "cpu_per_added_arm_pct": slope,
        "saturated_from_arms": min((r["arms"] for r in rows if r not in free), default=None),
        "largest_arms_without_misses": max(ran) if ran else 0,
    }


def _print(rows: list[dict[str, Any]], summ: dict[str, Any], rate: float) -> None:
    from rich.console import Console
    from rich.table import Table

    services = list(dict.fromkeys(s for r in rows for s in r["cpu_pct"]))
    t = Table(title=f"bench arms: a robot of N MH3F arms at {rate:g} Hz, CPU % of one core (2 cores = 200 %)")
    for c in ("N", *services, "total", "slave miss %", "HOLDs", "e2e p50 / p99 ms", "relay p50 / p99 ms"):
        t.add_column(c, justify="right")
    for r in rows:
        e, rl = r["end_to_end_ms"], r["relay_end_to_end_ms"]
        t.add_row(
            str(r["arms"]),
            *(f"{r['cpu_pct'].get(s, 0.0):.1f}" for s in services),
            f"{r['cpu_total_pct']:.1f}",
            str(r["deadline_misses"].get("slave_control", {}).get("miss_pct", "-")),
            str(r["watchdog_holds"]),
            f"{e['p50']:.2f} / {e['p99']:.2f}" if e else "-",
            f"{rl['p50']:.2f} / {rl['p99']:.2f}",
        )
    Console(width=max(160, Console().width)).print(t)
    slope = summ["cpu_per_added_arm_pct"]
    print(
        (
            f"each arm beyond the first: {slope} % of a core"
            if slope is not None
            else "each arm beyond the first: -"
        )
        + (
            f"; the host is saturated (≥ {SATURATED:.0%} of its cores) from N = {summ['saturated_from_arms']}"
            if summ["saturated_from_arms"] is not None
            else ""
        )
        + f"; largest N without a HOLD or {MISS_PCT_OK} % slave misses: {summ['largest_arms_without_misses']}"
    )
    for r in rows:
        for c in r["watchdog_hold_causes"][:3]:
            print(f"  N={r['arms']} HOLD: {c}")


def _arms_arg(text: str) -> list[int]:
    try:
        ns = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: arm counts separated by commas, e.g. 1,2,4") from None
    if not ns or any(not 1 <= x <= 16 for x in ns):
        raise argparse.ArgumentTypeError(f"{text!r}: each count in [1, 16]")
    return ns


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="telesurg bench arms", description=__doc__)
    ap.add_argument("--arms", type=_arms_arg, default=[1, 2, 4], help="arm counts, e.g. 1,2,4")
    ap.add_argument("--rate", type=float, default=1000.0, help="master (and control) rate, Hz")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured seconds per N")
    ap.add_argument(
        "--rt-priority",
        type=int,
        help="SCHED_FIFO priority of the master, mapping and slave loops (default: the site's, 20)",
    )
    ap.add_argument("--keep-logs", type=Path, metavar="DIR", help="keep each N's logs in DIR/N<k>")
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args(argv)
    if not 1.0 <= a.rate <= 5000.0:
        ap.error(f"--rate {a.rate:g}: in [1, 5000] Hz")
    if a.seconds <= 0:
        ap.error(f"--seconds {a.seconds:g}: > 0")
    rows = []
    for n in a.arms:
        with _workdir(a.keep_logs, f"N{n}") as d:
            rows.append(run_arms(n, a, Path(d)))
    summ = summary(rows, os.cpu_count() or 1)
    _print(rows, summ, a.rate)
    if a.json:
        res = {"rate_hz": a.rate, "seconds": a.seconds, "rows": rows, **summ}
        res["date"], res["machine"] = now(), machine()
        a.json.write_text(jsonio.dumps(res, indent=2) + "\n")
    return 0
