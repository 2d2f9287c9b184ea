"""``telesurg bench memory``: resident memory of each service of a running pipeline over time.

The bench pipeline (router, master_capture, mapping, slave_control, watchdog and the mirror
recording an ``.rrd``) runs with nothing injected; every ``--every`` seconds the bench reads
each process's RSS and where it is (``/proc/<pid>/smaps``: the brk heap, anonymous mappings,
mapped files). The table gives, per process, RSS at the end of the warm-up and at the end, and
the growth rate after the warm-up (MB/s, least-squares slope over the samples). ``--set`` changes a
service's configuration for the run, to compare variants of one process::

    telesurg bench memory --seconds 300 --json mem.json
    telesurg bench memory --seconds 300 --set mirror.rrd_footer=true
    telesurg bench memory --seconds 300 --set mirror.geometry=false

What it shows is growth, not its cause: a steady slope over a long run is a leak or an unbounded
store; a slope that flattens is a warm-up (caches, allocator arenas).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.shared.errors import TelesurgError
from telesurg.tools.bench.flood import WATCHED, add_set_argument, memory_detail, parse_sets, rss_mb
from telesurg.tools.bench.harness import Pipeline
from telesurg.tools.bench.machine import machine, now

log = logging.getLogger("telesurg.bench.memory")


def slope_mb_s(samples: Sequence[dict[str, Any]], name: str, since_s: float) -> float | None:
    """Least-squares growth rate (MB/s) of ``name``'s RSS over the samples at or after ``since_s``."""
    pts = [(s["t_s"], s["rss_mb"][name]) for s in samples if s["t_s"] >= since_s and name in s["rss_mb"]]
    if len(pts) < 3:
        return None
    t, v = np.array(pts).T
    return round(float(np.polyfit(t, v, 1)[0]), 4)


def run(args: argparse.Namespace) -> dict[str, Any]:
    """One run of the pipeline; the JSON record."""
    out = Path(args.log_dir or tempfile.mkdtemp(prefix="telesurg-memory-"))
    overrides = parse_sets(args.set)
    with Pipeline(out, overrides=overrides, impair=False) as pipe:
        if not pipe.wait_following(120):
            raise TelesurgError("the slave did not follow within 120 s")
        t0 = time.monotonic()
        samples: list[dict[str, Any]] = []
        while True:
            t = time.monotonic() - t0
            samples.append({"t_s": round(t, 1), "rss_mb": rss_mb(pipe), "detail_mb": memory_detail(pipe)})
            log.info("%5.0f s  %s", t, "  ".join(f"{k} {v}" for k, v in samples[-1]["rss_mb"].items()))
            if t >= args.seconds:
                break
            time.sleep(min(args.every, max(0.0, args.seconds - t)))
        gone = [n for n in WATCHED if n in pipe.site.procs and pipe.site.procs[n].poll() is not None]
    first = next((s for s in samples if s["t_s"] >= args.warmup), samples[-1])
    last = samples[-1]
    return {
        "seconds": args.seconds,
        "every_s": args.every,
        "warmup_s": args.warmup,
        "set": list(args.set),
        "exited_early": gone,
        "processes": {
            name: {
                "after_warmup_mb": first["rss_mb"].get(name),
                "end_mb": last["rss_mb"].get(name),
                "slope_mb_s": slope_mb_s(samples, name, args.warmup),
                "anon_after_warmup_mb": first["detail_mb"].get(name, {}).get("anon"),
                "anon_end_mb": last["detail_mb"].get(name, {}).get("anon"),
            }
            for name in WATCHED
            if name in last["rss_mb"]
        },
        "samples": samples,
        "log_dir": str(out),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench memory``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench memory",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--seconds", type=float, default=300.0, help="measured time after following starts (300)")
    ap.add_argument("--every", type=float, default=10.0, help="sampling period (s, default 10)")
    ap.add_argument("--warmup", type=float, default=60.0, help="slopes from this time on (s, default 60)")
    add_set_argument(ap, "mirror.rrd_footer=true")
    ap.add_argument("--log-dir", help="service logs and the mirror's .rrd (default: a temporary folder)")
    ap.add_argument("--json", type=Path, help="write the result here")
    ap.add_argument("--plot", type=Path, help="a PNG of each process's RSS over the run")
    args = ap.parse_args(argv)
    if not (args.every > 0 and 0 <= args.warmup < args.seconds):
        ap.error("need --every > 0 and 0 <= --warmup < --seconds")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        res = run(args)
    except TelesurgError as exc:
        print(f"telesurg bench memory: {exc}")
        return 1
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        jsonio.write(args.json, {**res, "date": now(), "machine": machine()})
    if args.plot:
        from telesurg.tools.bench.plots import plot_memory

        plot_memory(res, args.plot)
    print(f"memory: {res['seconds']:g} s, sampled every {res['every_s']:g} s; set: {res['set'] or 'none'}")
    at = f"at {res['warmup_s']:g} s"
    print(f"  {'process':<14} {at:>9} {'end':>8} {'MB/s':>8}  anon MB")
    for name, r in res["processes"].items():
        print(
            f"  {name:<14} {r['after_warmup_mb']!s:>9} {r['end_mb']!s:>8} {r['slope_mb_s']!s:>8}"
            f"  {r['anon_after_warmup_mb']} → {r['anon_end_mb']}"
        )
    if res["exited_early"]:
        print(f"  exited before the end: {', '.join(res['exited_early'])}")
        return 1
    return 0
