"""``telesurg bench wakeup``: how late a control process's thread wakes up, with the kernel's
default scheduler slice and with a shorter one (what ``$TELESURG_CONTROL_SLICE_US`` makes the
launcher ask for).

Every hop of the control path is a thread waking up: zenoh's rx thread on a socket, the Python
thread that takes the sample, the loop on its timer. Under other programs' CPU hogs such a wake-up
may wait for the running hog's slice to end, unless the waking thread's own slice is shorter
(Linux ≥ 6.12, EEVDF: a shorter slice is an earlier virtual deadline). On this project's VM the two
were alike (docs/performance.md): the control processes' autogroups at nice −10 already let a
waking thread in within ~0.1 ms at p99 under two hogs.

The probe is started the way the launcher starts a control process (its own session, the
control nice for it and its scheduler autogroup where permitted, the slice asked for before it
starts), once with the kernel's slice (0) and once with ``--slice-us``,
alternating blocks; it sleeps 1 ms at a time and records how late each wake-up is. ``--load``
runs the same under background load (``cpu:N`` busy processes at normal priority, or ``idle:N``).

Example::

    telesurg bench wakeup --seconds 10 --blocks 2 --load cpu:2 --json wakeup.json
"""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench.load import Load
from telesurg.tools.bench.machine import machine, now

PCTS = (50, 90, 99, 99.9)


def probe(seconds: float, out: Path) -> None:
    """Sleep 1 ms at a time for ``seconds``; write how late each wake-up was (µs) to ``out``, and
    print the thread's slice."""
    from telesurg.shared.timing import fair_slice_us

    late = []
    end = time.perf_counter_ns() + int(seconds * 1e9)
    while (t := time.perf_counter_ns()) < end:
        time.sleep(0.001)
        late.append(time.perf_counter_ns() - t - 1_000_000)
    np.save(out, np.asarray(late, dtype=np.int64) / 1e3)
    print(fair_slice_us())


def _block(seconds: float, slice_us: float, out: Path) -> tuple[np.ndarray, float]:
    from telesurg.services.launcher import _foreground

    argv = [sys.executable, "-m", "telesurg.tools.bench.wakeup", "--probe", f"{seconds}", str(out)]
    r = subprocess.run(
        argv,
        capture_output=True,
        text=True,
        timeout=seconds + 60,
        start_new_session=True,
        preexec_fn=functools.partial(_foreground, slice_us),  # as the launcher starts a control process
    )
    if r.returncode != 0:
        raise RuntimeError(f"the wake-up probe failed: {r.stderr[-1000:]}")
    return np.load(out), float(r.stdout.split()[-1])


def _stats(us: np.ndarray) -> dict[str, float]:
    out = {f"p{p:g}": round(float(np.percentile(us, p)), 1) for p in PCTS}
    out["max"] = round(float(us.max()), 1)
    out["n"] = len(us)
    return out


def run(a: argparse.Namespace) -> dict[str, Any]:
    """Alternating blocks per load: kernel slice, then ``a.slice_us``; figures per (load, slice)."""
    from rich.console import Console
    from rich.table import Table
    from telesurg.services.launcher import control_nice

    res: dict[str, Any] = {"seconds_per_block": a.seconds, "blocks": a.blocks, "slice_us": a.slice_us}
    res["control_nice"] = control_nice()
    rows: dict[tuple[str, str], list[np.ndarray]] = {}
    slices: dict[tuple[str, str], float] = {}
    with tempfile.TemporaryDirectory(prefix="telesurg-wakeup-") as d:
        tmp = Path(d)
        for load in (None, *a.load):
            name = "idle" if load is None else load.name
            for blk in range(a.blocks):
                for which, us in (("kernel", 0.0), ("asked", a.slice_us)):
                    out = tmp / f"{name}-{which}-{blk}.npy"
                    if load is None:
                        late, got = _block(a.seconds, us, out)
                    else:
                        with load.running("", tmp):
                            late, got = _block(a.seconds, us, out)
                    rows.setdefault((name, which), []).append(late)
                    slices[(name, which)] = got
    t = Table(title=f"wake-up lateness of a 1 ms sleep, µs ({a.blocks} × {a.seconds:g} s each, alternating)")
    for c in ("load", "slice", "n", "p50", "p90", "p99", "p99.9", "max"):
        t.add_column(c, justify="right")
    figs: dict[str, dict[str, Any]] = {}
    for (name, which), blocks in rows.items():
        s: dict[str, Any] = _stats(np.concatenate(blocks))
        s["slice_us"] = slices[(name, which)]
        s["block_max"] = [round(float(b.max()), 1) for b in blocks]
        figs.setdefault(name, {})[which] = s
        label = f"{s['slice_us']:g} µs ({'kernel' if which == 'kernel' else 'asked'})"
        t.add_row(name, label, str(s["n"]), *(f"{s[k]:.0f}" for k in ("p50", "p90", "p99", "p99.9", "max")))
    Console().print(t)
    res["lateness_us"] = figs
    return res


def _load_arg(spec: str) -> Load:
    try:
        load = Load.parse(spec)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if load.kind not in ("cpu", "idle"):
        raise argparse.ArgumentTypeError(f"--load {spec}: the wake-up bench takes cpu:N or idle:N")
    return load


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["--probe"]:  # (the probe process: --probe SECONDS OUT)
        probe(float(args[1]), Path(args[2]))
        return 0
    from telesurg.services.launcher import control_slice_us
    from telesurg.shared.timing import SLICE_MAX_US, SLICE_MIN_US, check_slice_us

    ap = argparse.ArgumentParser(prog="telesurg bench wakeup", description=__doc__)
    ap.add_argument("--seconds", type=float, default=10.0, help="per block (default 10)")
    ap.add_argument("--blocks", type=int, default=2, help="alternating blocks of each slice (default 2)")
    ap.add_argument(
        "--slice-us",
        type=float,
        default=None,
        help=f"the slice to compare with the kernel's, {SLICE_MIN_US}..{SLICE_MAX_US} µs "
        "(default: $TELESURG_CONTROL_SLICE_US where set, else 100)",
    )
    ap.add_argument(
        "--load", action="append", default=[], metavar="SPEC", type=_load_arg, help="cpu:N or idle:N"
    )
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args(args)
    if not a.seconds > 0 or a.blocks < 1:
        ap.error("--seconds must be > 0 and --blocks ≥ 1")
    a.slice_us = (control_slice_us() or 100.0) if a.slice_us is None else a.slice_us
    if a.slice_us == 0:
        ap.error("--slice-us 0 is the kernel's slice: name one to compare with it")
    try:
        check_slice_us(a.slice_us)
    except ValueError as exc:
        ap.error(str(exc))
    res = run(a)
    res["date"], res["machine"] = now(), machine()
    if a.json:
        a.json.write_text(jsonio.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
