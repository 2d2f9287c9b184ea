"""``telesurg bench faults``: inject one fault at a time into the running pipeline and measure.

For each fault: detection time (ms from injection to the slave holding, seen in its
``operating_state``), the watchdog's reaction time, the slave tip motion after detection (mm, from
MuJoCo), whether recovery needed a new engage (a clutch press after the fault cleared), and the
control messages lost. See ``docs/safety.md`` for the figures.

Example::

    telesurg bench faults --json out/faults.json
    telesurg bench faults --only kill:mapping,cut:0.6
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench.harness import Pipeline, now_ns
from telesurg.tools.bench.machine import machine, now

log = logging.getLogger(__name__)

#: Keys the garbage burst hits (every control and safety key of arm1 / m1, plus the e-stop key).
GARBAGE_KEYS = (
    "master/m1/measured_cp",
    "master/m1/buttons",
    "slave/arm1/servo_jp",
    "slave/arm1/setpoint_cp",
    "slave/arm1/measured_js",
    "slave/arm1/measured_cp",
    "slave/arm1/operating_state",
    "safety/arm1/lease",
    "safety/arm1/state",
    "estop",
)


@dataclass(frozen=True)
class Fault:
    """One fault: how to inject it, how long it lasts, how to clear it, what must happen."""

    name: str
    inject: Callable[[Pipeline], int]
    clear: Callable[[Pipeline], int]
    duration_s: float
    expect: str  # "hold" | "estop" | "degraded" | "none"


def _kill(svc: str) -> Fault:
    return Fault(f"SIGKILL {svc}", lambda p: p.kill(svc), lambda p: p.restart(svc), 1.0, _expect(svc))


def _stop(svc: str, s: float) -> Fault:
    return Fault(f"SIGSTOP {svc} {s:g} s", lambda p: p.freeze(svc), lambda p: p.thaw(svc), s, _expect(svc))


def _expect(svc: str) -> str:
    return "none" if svc == "mirror" else "hold"


def _cut(s: float) -> Fault:
    return Fault(f"link cut {s:g} s", lambda p: p.cut(), lambda p: p.restore(), s, "hold")


def _delay(ms: float, s: float, expect: str) -> Fault:
    return Fault(f"link delay {ms:g} ms", lambda p: p.delay(ms), lambda p: p.restore(), s, expect)


def _garbage(per_key: int) -> Fault:
    def inject(p: Pipeline) -> int:
        t = now_ns()
        rng = os.urandom
        keys = [f"{p.node.keys.prefix}/{k}" for k in GARBAGE_KEYS]
        start = time.monotonic()
        for i in range(per_key):
            for k in keys:
                p.node.session.put(k, rng(1 + (i * 37) % 120))
            # spread over ~1 s so the burst measures rejection, not CPU starvation
            lag = start + (i + 1) / per_key - time.monotonic()
            if lag > 0:
                time.sleep(lag)
        return t

    return Fault(f"garbage x{per_key}/key", inject, lambda p: now_ns(), 0.5, "none")


def _estop() -> Fault:
    return Fault("e-stop, then reset", lambda p: p.estop("estop"), lambda p: p.estop("reset"), 1.0, "estop")


def default_faults(stop_s: float = 0.6) -> list[Fault]:
    """The standard fault list of the bench (and of docs/safety.md)."""
    out = [_kill(s) for s in ("master_capture", "mapping", "watchdog", "mirror")]
    out += [_stop(s, stop_s) for s in ("master_capture", "mapping", "watchdog", "mirror")]
    out += [_cut(0.6), _cut(3.0), _delay(150, 3.0, "degraded"), _delay(400, 3.0, "hold")]
    out += [_garbage(500), _estop()]
    return out


def parse_only(spec: str) -> list[Fault]:
    """``kill:mapping,stop:watchdog,cut:0.6,delay:400,garbage:200,estop`` → faults."""
    out: list[Fault] = []
    for item in filter(None, (x.strip() for x in spec.split(","))):
        kind, _, arg = item.partition(":")
        if kind == "kill":
            out.append(_kill(arg))
        elif kind == "stop":
            out.append(_stop(arg, 0.6))
        elif kind == "cut":
            out.append(_cut(float(arg or 0.6)))
        elif kind == "delay":
            ms = float(arg or 400)
            out.append(_delay(ms, 3.0, "hold" if ms > 250 else "degraded"))
        elif kind == "garbage":
            out.append(_garbage(int(arg or 500)))
        elif kind == "estop":
            out.append(_estop())
        else:
            raise ValueError(f"unknown fault {item!r}; kinds: kill stop cut delay garbage estop")
    return out


def run_fault(pipe: Pipeline, f: Fault, lead_s: float = 1.0, recover_s: float = 12.0) -> dict[str, Any]:
    """Inject ``f`` into a following pipeline, clear it, wait for recovery; the measured row.

    The injection is placed ``lead_s`` after a clutch press, so the operator's own clutch
    releases (every 4 s) do not overlap short faults. A hold is a *fault* hold: the slave's hold
    counter goes up (a clutch release pauses without counting).
    """
    p = pipe.p
    row: dict[str, Any] = {"fault": f.name, "expect": f.expect}
    if not pipe.wait_following(recover_s) or not _after_press(pipe, lead_s, recover_s):
        row["error"] = "slave not following before injection"
        return row
    lost0 = sum(p.lost().values())
    rej0 = sum(p.heartbeats.values())
    with p.lock:
        holds0 = p.op[-1][5] if p.op else 0
    t0 = f.inject(pipe)
    time.sleep(f.duration_s)
    t_clear = f.clear(pipe)
    time.sleep(0.3)
    hold = p.first_op_after(t0, lambda r: r[5] > holds0)
    held = hold is not None and hold[0] < t_clear + 0.3e9
    t_hold = hold[0] if held and hold else None
    row["held"] = held
    row["detect_ms"] = round((t_hold - t0) / 1e6, 1) if t_hold else None
    wd = p.first_safety_after(t0, ("HOLD", "ESTOP", "DEGRADED"))
    row["watchdog_ms"] = round((wd - t0) / 1e6, 1) if wd is not None and wd < t_clear + 0.3e9 else None
    with p.lock:
        states = [(r[1], r[2], r[3]) for r in p.safety if t0 <= r[0] <= t_clear + 0.3e9]
    row["watchdog_states"] = sorted({s for s, _, _ in states})
    row["min_scale"] = min((sc for _, _, sc in states), default=1.0)
    row["causes"] = next((list(c) for s, c, _ in states if s != "OK" and c), [])[:3]
    # Tip motion in the second after the hold was detected (MuJoCo: the arm must stop).
    row["motion_after_detect_mm"] = round(p.motion_after(t_hold, 1.0), 3) if t_hold else None
    # Recovery: the first follow after the hold; it must come after a new clutch press.
    resumed = pipe.wait_following(recover_s)
    row["recovered"] = resumed
    row["recovery_s"] = row["reengage_needed"] = row["motion_before_reengage_mm"] = None
    fol = p.first_op_after(t_hold, lambda r: r[1]) if t_hold else None  # the first follow after the hold
    t_followed = fol[0] if fol else None  # (None: none seen)
    if t_hold and resumed:
        t_fol = t_followed if t_followed is not None else now_ns()
        row["recovery_s"] = round((t_fol - t_clear) / 1e9, 2)  # < 0: re-engaged during the fault
        # (by publication times: the follow is the slave's answer to the press, and its state
        # may reach the probe before the press does)
        t_fol_pub = fol[1][8] if fol else t_fol
        # (the press may reach the probe after the follow it caused: a second to come)
        deadline = time.monotonic() + 1.0
        while not (pressed := p.press_between(t_hold, t_fol_pub)) and time.monotonic() < deadline:
            time.sleep(0.05)
        row["reengage_needed"] = pressed
        if not row["reengage_needed"]:  # what the probe saw, ms from the hold: to tell why
            with p.lock:
                row["seen"] = {
                    "clutch": [(round((t - t_hold) / 1e6), on) for t, on in p.clutch if t >= t_hold - 5e9],
                    "op": [
                        (round((r[0] - t_hold) / 1e6), round((r[8] - t_hold) / 1e6), r[1], r[4], r[3])
                        for r in p.op
                        if t_hold - 1e9 <= r[0] <= t_fol + 1e9
                    ][:40],
                }
        # The slave must stay put from the hold until the new engage: until the press (the
        # follow's state is published at a lower rate than the tip, which may already move)
        with p.lock:
            t_press = next((t for t, on in p.clutch if on and t_hold <= t <= t_fol_pub), t_fol)
        tips = p.tips()
        sel = (tips[:, 0] >= t_hold + 0.3e9) & (tips[:, 0] <= min(t_fol, t_press))
        p_ref = tips[max(int(np.searchsorted(tips[:, 0], t_hold + 0.3e9, side="right")) - 1, 0), 1:]
        moved = np.linalg.norm(tips[sel, 1:] - p_ref, axis=1).max() * 1e3 if sel.any() else 0.0
        row["motion_before_reengage_mm"] = round(float(moved), 3)
    row["_times_ns"] = {"inject": t0, "clear": t_clear, "hold": t_hold, "follow": t_followed}
    row["lost"] = sum(p.lost().values()) - lost0
    time.sleep(0.6)  # heartbeats are 2 Hz
    row["rejected"] = sum(p.heartbeats.values()) - rej0
    row["ok"] = _judge(row)
    return row


def _after_press(pipe: Pipeline, lead_s: float, timeout: float) -> bool:
    """Wait until ``lead_s`` after the latest clutch press while following (False: timeout)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with pipe.p.lock:
            presses = [t for t, pressed in pipe.p.clutch if pressed]
        if presses and pipe.p.following():
            since = (now_ns() - presses[-1]) / 1e9
            if lead_s <= since <= lead_s + 0.3:
                return True
        time.sleep(0.01)
    return False


def _judge(row: dict[str, Any]) -> bool:
    e = row["expect"]
    if "error" in row or not row["recovered"]:
        return False
    held_ok = not row["held"] or bool(
        row["reengage_needed"]
        and row["motion_after_detect_mm"] < 0.5
        and row["motion_before_reengage_mm"] < 0.5
    )
    if e == "none":
        # The fault itself must not hold the arm. The CPU it costs on 2 cores may delay a
        # stream past its deadline; that hold (stale, over the latency limit) is the safe
        # response to the stall, and is then judged like any other hold.
        causes = row["causes"]
        stall = bool(causes) and all("stale" in c or "latency" in c for c in causes)
        return not row["held"] or (stall and held_ok)
    if e == "degraded":  # a sudden delay first shows as a gap (stale → hold), then as latency
        return held_ok and "DEGRADED" in row["watchdog_states"] and row["min_scale"] < 1.0
    return bool(row["held"] and held_ok and (e != "estop" or "ESTOP" in row["watchdog_states"]))


def print_table(rows: list[dict[str, Any]]) -> None:
    """A rich table of the rows."""
    from rich.console import Console
    from rich.table import Table

    t = Table(title="telesurg bench faults")
    for col in (
        "fault",
        "expect",
        "detect ms",
        "watchdog ms",
        "motion mm",
        "re-engage",
        "recovery s",
        "lost",
        "rejected",
        "ok",
    ):
        t.add_column(col, justify="left" if col in ("fault", "expect") else "right")
    for r in rows:
        t.add_row(
            r["fault"],
            r["expect"],
            _fmt(r.get("detect_ms")),
            _fmt(r.get("watchdog_ms")),
            _fmt(r.get("motion_after_detect_mm")),
            _fmt(r.get("reengage_needed")),
            _fmt(r.get("recovery_s")),
            _fmt(r.get("lost")),
            _fmt(r.get("rejected")),
            "yes" if r.get("ok") else "NO",
        )
    Console(width=160).print(t)


def _fmt(v: object) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return str(v)


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench faults``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench faults",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--json", type=Path, help="write the rows as JSON here")
    ap.add_argument(
        "--only", help="comma list, e.g. kill:mapping,stop:watchdog,cut:0.6,delay:400,garbage,estop"
    )
    ap.add_argument("--log-dir", type=Path, help="service logs (default: a temporary directory)")
    ap.add_argument("--stop-s", type=float, default=0.6, help="SIGSTOP duration, s (default 0.6)")
    ap.add_argument("--plot", type=Path, metavar="FILE.png", help="draw every fault's timeline into one PNG")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(message)s")
    try:
        faults = parse_only(args.only) if args.only else default_faults(args.stop_s)
    except ValueError as exc:
        print(f"telesurg bench faults: {exc}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="telesurg-faults-") as tmp:
        log_dir = args.log_dir or Path(tmp) / "logs"
        rows = []
        with Pipeline(log_dir) as pipe:
            for i, f in enumerate(faults, 1):
                print(f"[{i}/{len(faults)}] {f.name} ...", file=sys.stderr, flush=True)
                rows.append(run_fault(pipe, f))
            if args.plot:
                from telesurg.tools.bench.plots import plot_faults

                plot_faults(pipe.p, rows, args.plot)
            codes = pipe.close()
    for r in rows:
        r.pop("_times_ns", None)
    print_table(rows)
    result = {
        "date": now(),
        "machine": machine(),
        "command": "telesurg bench faults " + " ".join(argv if argv is not None else sys.argv[2:]),
        "cpus": os.cpu_count(),
        "rows": rows,
        "exit_codes": codes,
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(jsonio.dumps(result, indent=2))
    return 0 if all(r.get("ok") for r in rows) else 1
