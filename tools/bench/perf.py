"""Performance benches: ``telesurg bench latency | soak | ik | sim`` (tables + ``--json FILE``).

* ``latency`` — in one run, alternating blocks: (a) the transport floor, a bare three-process
  zenoh relay (:mod:`telesurg.tools.bench.relay`) through the site router, and (b) the real pipeline
  master_capture → mapping → slave_control with the real services, the setpoint timed when the
  slave's control loop first uses it. One-way latency per hop and end to end (every process on one
  host stamps with the same wall clock), p50/p90/p99/max, and the pipeline/relay ratios; and each
  stage of every setpoint the slave used (:data:`STAGES`: the mapping's ``latency_log``, a tap
  subscriber in this process, the slave's use and backend step, its reference's age).
  ``--rate 0`` is unpaced: the relay's source publishes back to back, the master runs at its top
  rate (:data:`UNPACED_MASTER_HZ`).
* ``soak`` — the whole pipeline for ``--seconds`` with the recorder on the bus: messages, losses,
  reorders and duplicates per stream (the recorder's summary), every fixed-rate loop's deadline
  misses (from the services' own counters at exit), CPU % and RSS per service and of the recorder
  (psutil), and how many of each service's threads run under SCHED_FIFO. ``--no-record`` leaves
  the recorder out (it loads the loops too).
* ``ik`` — the analytic solvers (trocar-mode IK, 6-axis IK, VIP IK, PLAS all-joints mapping step):
  µs per call and solves/s, against a generic numerical IK on the same targets (``mink``, a
  benchmark extra: ``pip install -e '.[bench]'``; skipped with a note when absent), with the
  position and RCM error of each.
* ``sim`` — MuJoCo steps/s unpaced per robot model, and the real-time factor.

``latency`` and ``soak`` run the services with the deploy configs (``deploy/local/site.toml``), whose
master, mapping and slave loop threads run under SCHED_FIFO (``rt_priority = 20``, where the host
allows it); ``--rt-priority N`` sets another priority for the three, 0 the normal scheduler.

Nothing here asserts a time: the figures are printed and written, the goals are in
``docs/performance.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench import schedtrace
from telesurg.tools.bench.load import Load
from telesurg.tools.bench.machine import machine, now

PCTS = (50, 90, 99)
# --rate 0 (unpaced): the relay's source publishes back to back; master_capture runs at its top
# rate (it is a fixed-rate device loop), far above what the mapping can take, so it conflates
UNPACED_MASTER_HZ = 5000.0


def _workdir(keep: Path | None, sub: str = "") -> contextlib.AbstractContextManager[str]:
    """The bench's working directory: a temporary one, or ``keep/sub`` (made, and left with the
    services' logs and the rows of every block: ``--keep-logs``, to read what the watchdog and the
    router logged around a HOLD)."""
    if keep is None:
        return tempfile.TemporaryDirectory()
    d = keep / sub
    d.mkdir(parents=True, exist_ok=True)
    return contextlib.nullcontext(str(d))


def _stats_ms(ns: np.ndarray) -> dict[str, float]:
    ms = np.asarray(ns, dtype=float) / 1e6
    if len(ms) == 0:
        return {"n": 0}
    out = {f"p{p}": round(float(np.percentile(ms, p)), 4) for p in PCTS}
    out["max"] = round(float(ms.max()), 4)
    out["n"] = len(ms)
    return out


def _table(title: str, rows: list[tuple[str, dict[str, float]]]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title)
    t.add_column("")
    for c in ("n", "p50 ms", "p90 ms", "p99 ms", "max ms"):
        t.add_column(c, justify="right")
    for name, s in rows:
        t.add_row(
            name, str(s.get("n", 0)), *(f"{s.get(k, float('nan')):.3f}" for k in ("p50", "p90", "p99", "max"))
        )
    Console().print(t)


# ---------------------------------------------------------------------------------- latency


def _relay_block(endpoint: str, rate: float, seconds: float, tmp: Path, k: int) -> np.ndarray:
    out = tmp / f"relay{k}.npy"
    base = [sys.executable, "-m", "telesurg.tools.bench.relay"]
    common = ["--connect", endpoint, "--rate", str(rate), "--seconds", str(seconds)]
    sink = subprocess.Popen([*base, "sink", *common, "--out", str(out)], stdout=subprocess.DEVNULL)
    relay = subprocess.Popen([*base, "relay", *common], stdout=subprocess.DEVNULL)
    time.sleep(1.5)  # both subscribed
    subprocess.run([*base, "source", *common], stdout=subprocess.DEVNULL, check=True, timeout=seconds + 30)
    time.sleep(0.3)
    for p in (relay, sink):
        p.terminate()
        p.wait(10)
    rows: np.ndarray = np.load(out)
    return rows


#: The services whose loop thread ``rt_priority`` puts under SCHED_FIFO.
RT_SERVICES = ("master_capture", "mapping", "slave_control")


def _overrides(master_hz: float, rt_priority: int | None, **extra: list[str]) -> dict[str, list[str]]:
    """Config overrides of a bench pipeline: the master at ``master_hz`` with its pedal pressed
    from 0.5 s on (one engage, held), ``rt_priority`` for :data:`RT_SERVICES` (None: the deploy
    configs'), and ``extra`` per service."""
    pedal = ["scripted.clutch=[[0.5, 1e9]]", "scripted.clutch_repeat_s=0.0"]
    out: dict[str, list[str]] = {"master_capture": [f"rate_hz={master_hz}", *pedal]}
    for svc, items in extra.items():
        out.setdefault(svc, []).extend(items)
    if rt_priority is not None:
        for svc in RT_SERVICES:
            out.setdefault(svc, []).append(f"rt_priority={rt_priority}")
    return out


def fifo_threads(pid: int) -> int:
    """Threads of process ``pid`` running under SCHED_FIFO now."""
    n = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            policy = os.sched_getscheduler(int(tid)) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        except OSError:  # the thread ended meanwhile
            continue
        n += policy == os.SCHED_FIFO
    return n


def slice_threads(pid: int) -> str:
    """``"k/n"``: of the ``n`` threads of process ``pid`` under the fair scheduler, ``k`` run with
    the control slice (:func:`telesurg.services.launcher.control_slice_us`); ``"-"`` when the
    kernel's default slice is asked for or the slice cannot be read."""
    from telesurg.services.launcher import control_slice_us
    from telesurg.shared.timing import fair_slice_us

    us, k, n = control_slice_us(), 0, 0
    if not us:
        return "-"
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            got = fair_slice_us(int(tid))
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except OSError:
            return "-"
        if got is not None:
            n += 1
            k += abs(got - us) <= 1
    return f"{k}/{n}"


def _pipeline_block(
    rate: float,
    seconds: float,
    tmp: Path,
    k: int,
    rt_priority: int | None = None,
    load: Load | None = None,
    trace: bool = False,
    keep: bool = False,
) -> tuple[np.ndarray, dict[str, Any]]:
    from telesurg.services.launcher import CONTROL
    from telesurg.tools.bench.harness import Pipeline

    npy, mapping_npy = tmp / f"applied{k}.npy", tmp / f"mapped{k}.npy"
    overrides = _overrides(
        rate if rate > 0 else UNPACED_MASTER_HZ,
        rt_priority,
        slave_control=[f"latency_log={json.dumps(str(npy))}"],
        mapping=[f"latency_log={json.dumps(str(mapping_npy))}"],
    )
    with Pipeline(tmp / f"logs{k}", mirror=False, impair=False, probe=False, overrides=overrides) as p:
        tap = _ServoTap(p.node)
        t_start = time.time()  # the site is up (every service on the bus): the block begins
        with _loaded(load, p.spec.endpoint, tmp):
            tracer = schedtrace.SchedTrace(tmp / f"sched{k}.data", seconds) if trace else None
            time.sleep(seconds + 1.0)
            fifo = {n: fifo_threads(pr.pid) for n, pr in p.site.procs.items() if n in RT_SERVICES}
            sliced = {n: slice_threads(pr.pid) for n, pr in p.site.procs.items() if n in CONTROL}
            if tracer is not None:  # (the threads named while they all still run)
                threads = schedtrace.thread_services(
                    {n: pr.pid for n, pr in p.site.procs.items() if n in CONTROL}
                )
                tracer.wait()
        tap.close()
        t_stop = time.time()
        p.close()
    rows = _stages(np.load(npy), np.load(mapping_npy), tap.rows())
    logs = {f.stem: f.read_text() for f in (tmp / f"logs{k}").glob("*.log")}
    holds = watchdog_holds(logs.get("watchdog", ""), t_stop, since=t_start)
    startup = watchdog_holds(logs.get("watchdog", ""), t_start)
    sched: dict[str, Any] = {}
    if tracer is not None:
        sched = schedtrace.delays(tracer.out, threads)
        if not keep:
            tracer.out.unlink()
    return rows, {
        "sched_delay_ms": sched,
        "holds": len(holds),
        "hold_causes": holds,
        "startup_hold_causes": startup,
        "fifo_threads": fifo,
        "slice_threads": sliced,
    }


class _ServoTap:
    """The bench's own subscriber on ``servo_jp`` (a callback, normal priority, in the bench's
    process): when each setpoint reaches a subscriber on this host — the transport's share of the
    mapping → slave hop, beside the slave's pick-up. (One more copy for the router to send.)"""

    def __init__(self, node: Any) -> None:
        from telesurg.shared.messages import JointSetpoint, decode_as

        self._rows: list[tuple[int, int]] = []

        def on_sample(sample: Any) -> None:
            t = time.time_ns()
            with contextlib.suppress(Exception):  # (a foreign message: not timed)
                self._rows.append((decode_as(sample.payload.to_bytes(), JointSetpoint).header.stamp_ns, t))

        self._sub = node.session.declare_subscriber(node.keys.slave("arm1", "servo_jp"), on_sample)

    def close(self) -> None:
        self._sub.undeclare()

    def rows(self) -> np.ndarray:
        """(n, 2): servo_jp stamp, received, ns."""
        return np.array(self._rows, dtype=np.int64).reshape(-1, 2)


#: Columns of :func:`_stages`' rows (wall clock ns, one clock for every process on the host; 0 =
#: not known for that setpoint).
STAGE_COLUMNS = (
    "master_sent",  # the master sample's stamp (master_capture, right before it publishes)
    "mapping_received",  # the mapping's subscriber callback got it
    "mapping_began",  # the mapping's loop began to map it
    "servo_jp_sent",  # the servo_jp's stamp (the mapping, right before it publishes)
    "tap_received",  # servo_jp reached the bench's own subscriber (_ServoTap)
    "slave_used",  # the slave's control loop first used it (its period's command)
    "slave_stepped",  # the backend stepped (MuJoCo) / sent (serial) that period's command
    "reference_played",  # the master time the stepped command's interpolated reference plays
)


def _stages(slave: np.ndarray, mapping: np.ndarray, tap: np.ndarray) -> np.ndarray:
    """One row per setpoint the slave used (:data:`STAGE_COLUMNS`), from the slave's latency log
    (origin, stamp, used, stepped, played), the mapping's (origin, received, began, stamp) and the
    tap's (stamp, received), joined on the servo_jp stamp."""
    slave = slave.reshape(-1, slave.shape[1] if slave.ndim == 2 else 5)
    out = np.zeros((len(slave), len(STAGE_COLUMNS)), dtype=np.int64)
    out[:, 0], out[:, 3], out[:, 5] = slave[:, 0], slave[:, 1], slave[:, 2]
    if slave.shape[1] >= 5:
        out[:, 6], out[:, 7] = slave[:, 3], slave[:, 4]
    # (table, its key column, (its column, our column) pairs)
    joins = ((mapping.reshape(-1, 4), 3, ((1, 1), (2, 2))), (tap.reshape(-1, 2), 0, ((1, 4),)))
    for table, key, cols in joins:
        if len(table) == 0:
            continue
        order = np.argsort(table[:, key])
        keys = table[order, key]
        i = np.clip(np.searchsorted(keys, out[:, 3]), 0, len(keys) - 1)
        hit = keys[i] == out[:, 3]
        for src, dst in cols:
            out[hit, dst] = table[order[i[hit]], src]
    return out


def _loaded(load: Load | None, endpoint: str, tmp: Path) -> contextlib.AbstractContextManager[Any]:
    return load.running(endpoint, tmp) if load is not None else contextlib.nullcontext()


def _steady(pl: np.ndarray) -> np.ndarray:
    """The pipeline rows (:data:`STAGE_COLUMNS`) with a master stamp and a servo_jp, the start-up
    transient (the first 5 %) dropped."""
    pl = pl[(pl[:, 0] > 0) & (pl[:, 3] > 0)]
    return pl[len(pl) // 20 :]


def _latency_figures(relay_rows: list[np.ndarray], pipe_rows: list[np.ndarray]) -> dict[str, Any]:
    """Per-hop and end-to-end percentiles of the relay and the pipeline, and their ratios."""
    r = np.concatenate(relay_rows)
    pl = _steady(np.concatenate(pipe_rows))
    res: dict[str, Any] = {
        "relay": {
            "hop1": _stats_ms(r[:, 1] - r[:, 0]),
            "hop2": _stats_ms(r[:, 2] - r[:, 1]),
            "end_to_end": _stats_ms(r[:, 2] - r[:, 0]),
        },
        "pipeline": {
            "master_to_mapping_out": _stats_ms(pl[:, 3] - pl[:, 0]),
            "mapping_out_to_slave_applied": _stats_ms(pl[:, 5] - pl[:, 3]),
            "end_to_end": _stats_ms(pl[:, 5] - pl[:, 0]),
        },
        "stages": _stage_figures(pl),
    }
    e_r, e_p = res["relay"]["end_to_end"], res["pipeline"]["end_to_end"]
    res["ratio_p50"] = round(e_p["p50"] / e_r["p50"], 3)
    res["ratio_p99"] = round(e_p["p99"] / e_r["p99"], 3)
    return res


def _block_p99(blocks: list[np.ndarray]) -> list[float]:
    """End-to-end p99 (ms) of each pipeline block, its start-up transient (first 5 %) dropped."""
    out = []
    for pl in map(_steady, blocks):
        out.append(round(float(np.percentile(pl[:, 5] - pl[:, 0], 99)) / 1e6, 4) if len(pl) else float("nan"))
    return out


#: The stages of :func:`_stage_figures`: (name, label, from column, to column of STAGE_COLUMNS).
STAGES = (
    ("master_to_mapping_callback", "master sent → mapping callback", "master_sent", "mapping_received"),
    ("mapping_callback_to_loop", "mapping callback → its loop begins", "mapping_received", "mapping_began"),
    ("mapping_work", "mapping loop: map + sign + stamp", "mapping_began", "servo_jp_sent"),
    ("servo_jp_to_tap", "servo_jp sent → a subscriber (bench tap)", "servo_jp_sent", "tap_received"),
    ("tap_to_slave_used", "bench tap → slave loop uses it", "tap_received", "slave_used"),
    ("servo_jp_to_slave_used", "servo_jp sent → slave loop uses it", "servo_jp_sent", "slave_used"),
    ("slave_used_to_stepped", "slave uses it → backend steps it", "slave_used", "slave_stepped"),
    ("end_to_end_used", "END TO END: master sent → slave uses", "master_sent", "slave_used"),
    ("end_to_end_stepped", "master sent → backend steps", "master_sent", "slave_stepped"),
    ("reference_lag", "stepped command's reference: age", "reference_played", "slave_stepped"),
)


def _stage_figures(pl: np.ndarray) -> dict[str, Any]:
    """Percentiles of every stage of :data:`STAGES` over the setpoints that have both stamps."""
    col = {c: i for i, c in enumerate(STAGE_COLUMNS)}
    out = {}
    for name, _label, a, b in STAGES:
        x, y = pl[:, col[a]], pl[:, col[b]]
        ok = (x > 0) & (y > 0)
        out[name] = _stats_ms(y[ok] - x[ok])
    return out


def latency(a: argparse.Namespace) -> dict[str, Any]:
    from telesurg.services.launcher import free_port
    from telesurg.shared.bus import BusConfig, open_session

    rate = a.rate
    res: dict[str, Any] = {
        "rate_hz": rate,
        "master_rate_hz": rate if rate > 0 else UNPACED_MASTER_HZ,
        "seconds_per_block": a.seconds,
        "blocks": a.blocks,
    }
    # idle first, then each --load; the conditions alternate block by block, so a slow drift of
    # the host shows in all of them alike
    conditions: list[Load | None] = [None, *a.load]
    rows: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {_cname(c): ([], []) for c in conditions}
    holds: dict[str, list[str]] = {name: [] for name in rows}
    startup: dict[str, list[str]] = {name: [] for name in rows}
    sched: dict[str, dict[str, Any]] = {}
    blk = 0
    with _workdir(a.keep_logs) as d:
        tmp = Path(d)
        for _ in range(a.blocks):
            for c in conditions:
                blk += 1
                name = _cname(c)
                ep = f"tcp/127.0.0.1:{free_port()}"
                router = open_session(BusConfig(mode="router", listen=[ep]))
                try:
                    with _loaded(c, ep, tmp):
                        rows[name][0].append(_relay_block(ep, rate, a.seconds, tmp, blk))
                finally:
                    router.close()  # type: ignore[no-untyped-call]
                first = len(rows[name][1]) == 0  # the scheduler is traced in each one's first block
                prow, info = _pipeline_block(
                    rate,
                    a.seconds,
                    tmp,
                    blk,
                    a.rt_priority,
                    c,
                    trace=a.sched_trace and first,
                    keep=a.keep_logs is not None,
                )
                rows[name][1].append(prow)
                holds[name] += info["hold_causes"]
                startup[name] += info["startup_hold_causes"]
                if info["sched_delay_ms"]:
                    sched[name] = info["sched_delay_ms"]
                if c is None:
                    res["pipeline_fifo_threads"] = info["fifo_threads"]
                    res["pipeline_slice_threads"] = info["slice_threads"]
    for name, (relay_rows, pipe_rows) in rows.items():
        figs = _latency_figures(relay_rows, pipe_rows)
        figs["pipeline_watchdog_holds"] = len(holds[name])
        figs["pipeline_watchdog_hold_causes"] = holds[name]
        figs["pipeline_startup_hold_causes"] = startup[name]
        if name in sched:
            figs["pipeline_sched_delay_ms"] = sched[name]
        if name == "idle":
            res.update(figs)
        else:
            res.setdefault("loaded", {})[name] = figs
    idle_p99 = res["pipeline"]["end_to_end"]["p99"]
    res["pipeline_block_p99_ms"] = _block_p99(rows["idle"][1])
    for name, figs in res.get("loaded", {}).items():
        figs["pipeline_p99_vs_idle"] = round(figs["pipeline"]["end_to_end"]["p99"] / idle_p99, 3)
        # block by block (each loaded block against the idle block just before it): how far one
        # block's tail, i.e. one burst of the host, moves the ratio of the whole run
        figs["pipeline_block_p99_ms"] = _block_p99(rows[name][1])
        figs["pipeline_block_p99_vs_idle"] = [
            round(b / i, 3)
            for b, i in zip(figs["pipeline_block_p99_ms"], res["pipeline_block_p99_ms"], strict=True)
        ]
    for name in rows:
        figs = res if name == "idle" else res["loaded"][name]
        e_r, e_p = figs["relay"]["end_to_end"], figs["pipeline"]["end_to_end"]
        _table(
            f"one-way latency at {f'{rate:g} Hz' if rate > 0 else 'unpaced'}, {name} "
            f"({a.blocks} × {a.seconds:g} s each, alternating)",
            [
                ("relay: source → relay", figs["relay"]["hop1"]),
                ("relay: relay → sink", figs["relay"]["hop2"]),
                ("relay: end to end", e_r),
                ("pipeline: master → mapping out", figs["pipeline"]["master_to_mapping_out"]),
                ("pipeline: mapping out → slave applied", figs["pipeline"]["mapping_out_to_slave_applied"]),
                ("pipeline: end to end", e_p),
            ],
        )
        _table(
            f"the pipeline's stages, {name} (one row per setpoint the slave used; wall clock)",
            [(f"{label}", figs["stages"][n]) for n, label, _a, _b in STAGES],
        )
        if name in sched:
            _sched_table(name, sched[name])
        vs_idle = ""
        if name != "idle":
            blocks = ", ".join(f"× {r}" for r in figs["pipeline_block_p99_vs_idle"])
            vs_idle = f"; pipeline p99 × {figs['pipeline_p99_vs_idle']} of idle (block by block: {blocks})"
        print(
            f"{name}: pipeline / relay: p50 × {figs['ratio_p50']}, p99 × {figs['ratio_p99']}{vs_idle}; "
            f"watchdog holds {figs['pipeline_watchdog_holds']}"
            + "".join(f"\n  HOLD: {c}" for c in figs["pipeline_watchdog_hold_causes"])
            + "".join(f"\n  HOLD while the site started: {c}" for c in figs["pipeline_startup_hold_causes"])
        )
    print(f"SCHED_FIFO threads of the pipeline: {res['pipeline_fifo_threads']}")
    print(f"threads with the control slice (of the fair-scheduled ones): {res['pipeline_slice_threads']}")
    if a.plot:
        from telesurg.tools.bench.plots import plot_latency

        plot_latency([res], a.plot)
        print(f"figure: {a.plot}")
    return res


def _cname(c: Load | None) -> str:
    return "idle" if c is None else c.name


# ---------------------------------------------------------------------------------- soak

_COUNTERS = {
    "master_capture": r"sent (\d+) samples, (\d+) loop overruns",
    "slave_control": r"stopped after (\d+) cycles: (\d+) overruns",
}


_TRANSITION = re.compile(
    r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3}) watchdog .*safety_transition: \w+ → HOLD(.*)$"
)


def watchdog_holds(log: str, until: float | None = None, since: float | None = None) -> list[str]:
    """The watchdog's transitions into HOLD in its log (``→ HOLD`` with its causes), those logged
    before the wall-clock time ``until`` (s since the epoch) when given: a bench passes the moment
    it began to stop the pipeline, whose stop sequence (master_capture first) makes a HOLD of its
    own that is not the run's; and from ``since`` on when given: the measured window, apart from a
    HOLD while the services were still starting (the benches report those on their own)."""
    out = []
    for line in log.splitlines():
        m = _TRANSITION.match(line)
        if m is None:
            continue
        t = time.mktime(time.strptime(m.group(1), "%Y-%m-%d %H:%M:%S")) + int(m.group(2)) / 1e3
        if (until is None or t < until) and (since is None or t >= since):
            out.append(m.group(3).lstrip(": ").strip())
    return out


def deadline_misses(logs: dict[str, str]) -> dict[str, Any]:
    """Each fixed-rate loop's cycles, overruns and miss % from its service's log at exit."""
    misses: dict[str, Any] = {}
    for svc, pat in _COUNTERS.items():
        m = re.search(pat, logs.get(svc, ""))
        if m:
            total, over = int(m.group(1)), int(m.group(2))
            misses[svc] = {
                "cycles": total,
                "overruns": over,
                "miss_pct": round(100 * over / max(total, 1), 3),
            }
    return misses


def _soak_run(a: argparse.Namespace, load: Load | None) -> dict[str, Any]:
    import importlib

    psutil: Any = importlib.import_module("psutil")  # (no type stubs)

    from telesurg.tools.bench.harness import Pipeline

    res: dict[str, Any] = {"rate_hz": a.rate, "seconds": a.seconds}
    with _workdir(a.keep_logs, _cname(load).replace(":", "-")) as d:
        tmp = Path(d)
        overrides = _overrides(a.rate, a.rt_priority)
        with Pipeline(tmp / "logs", mirror=False, impair=False, probe=False, overrides=overrides) as p:
            rec = (
                subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        "telesurg.services.record",
                        "--out",
                        str(tmp / "soak.mcap"),
                        "--seconds",
                        str(a.seconds),
                        "--connect",
                        p.spec.endpoint,
                        "--json",
                        str(tmp / "rec.json"),
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
                if a.record
                else None
            )
            procs = {n: psutil.Process(pr.pid) for n, pr in p.site.procs.items()}
            lat = _WatchdogLatency(p.node)
            watched = dict(procs) if rec is None else {**procs, "recorder": psutil.Process(rec.pid)}
            for pr in watched.values():
                pr.cpu_percent(None)
            t_start = time.time()  # the site is up: the soak begins
            with _loaded(load, p.spec.endpoint, tmp):
                lat.start()
                time.sleep(a.seconds)
                lat.stop()
            cpu_all = {n: round(pr.cpu_percent(None), 1) for n, pr in watched.items()}
            fifo = {n: fifo_threads(pr.pid) for n, pr in watched.items()}
            sliced = {n: slice_threads(pr.pid) for n, pr in watched.items()}
            rss = {n: round(pr.memory_info().rss / 2**20, 1) for n, pr in watched.items()}
            if rec is not None:
                rec.wait(60)
            t_stop = time.time()
            p.close()
        cpu = {n: c for n, c in cpu_all.items() if n in procs}  # the pipeline's own services
        logs = {f.stem: f.read_text() for f in (tmp / "logs").glob("*.log")}
        summary = json.loads((tmp / "rec.json").read_text()) if (tmp / "rec.json").exists() else {}
    misses = deadline_misses(logs)
    res["streams"] = summary.get("keys", summary)
    res["deadline_misses"] = misses
    res["cpu_pct"] = cpu
    res["cpu_total_pct"] = round(sum(cpu.values()), 1)
    res["recorder"] = {"cpu_pct": cpu_all["recorder"], "rss_mb": rss["recorder"]} if a.record else None
    res["rss_mb"] = rss
    res["fifo_threads"] = fifo
    res["slice_threads"] = sliced
    holds = watchdog_holds(logs.get("watchdog", ""), t_stop, since=t_start)
    res["watchdog_holds"] = len(holds)
    res["watchdog_hold_causes"] = holds
    res["startup_hold_causes"] = watchdog_holds(logs.get("watchdog", ""), t_start)
    res["watchdog_latency_ms"] = lat.figures()
    from rich.console import Console
    from rich.table import Table

    res["load"] = _cname(load)
    title = f"soak: {a.seconds:g} s at {a.rate:g} Hz" + ("" if a.record else ", no recorder")
    t = Table(title=f"{title}, {_cname(load)}")
    for c in ("service", "CPU %", "RSS MB", "FIFO threads", "slice threads", "cycles", "overruns", "miss %"):
        t.add_column(c, justify="right")
    for n in cpu_all:
        mi = misses.get(n, {})
        t.add_row(
            n,
            f"{cpu_all[n]:.1f}",
            f"{rss[n]:.1f}",
            str(fifo[n]),
            sliced[n],
            str(mi.get("cycles", "")),
            str(mi.get("overruns", "")),
            str(mi.get("miss_pct", "")),
        )
    Console().print(t)
    total, holds = res["cpu_total_pct"], res["watchdog_holds"]
    causes = "; ".join(res["watchdog_hold_causes"])
    print(
        f"total CPU of the pipeline {total} % of one core (2 cores = 200 %); watchdog holds {holds}"
        + (f" ({causes})" if causes else "")
        + "".join(f"\n  HOLD while the site started: {c}" for c in res["startup_hold_causes"])
    )
    wl = res["watchdog_latency_ms"]
    if wl["windows"]:
        print(
            f"watchdog's command-path latency over {wl['windows']} windows: p99 median "
            f"{wl['p99_median']} ms, max {wl['p99_max']} ms (p50 median {wl['p50_median']} ms)"
        )
    return res


class _WatchdogLatency:
    """The watchdog's own command-path latency (master sample → watchdog, its ``safety_state``
    p50 / p99 over its window), collected between :meth:`start` and :meth:`stop`."""

    def __init__(self, node: Any) -> None:
        from telesurg.shared.messages import SafetyState

        self._on = False
        self.p50: list[float] = []
        self.p99: list[float] = []
        node.subscribe(node.keys.safety("arm1", "state"), SafetyState, self._sample, sources=["watchdog"])

    def _sample(self, m: Any, key: str) -> None:
        if self._on and m.latency_samples:
            self.p50.append(m.latency_p50_ms)
            self.p99.append(m.latency_p99_ms)

    def start(self) -> None:
        self._on = True

    def stop(self) -> None:
        self._on = False

    def figures(self) -> dict[str, Any]:
        """The median and the maximum of the windows' p99 (and the median p50), ms."""
        if not self.p99:
            return {"windows": 0}
        return {
            "windows": len(self.p99),
            "p50_median": round(float(np.median(self.p50)), 3),
            "p99_median": round(float(np.median(self.p99)), 3),
            "p99_max": round(float(np.max(self.p99)), 3),
        }


def soak(a: argparse.Namespace) -> dict[str, Any]:
    """The soak idle, then under each ``--load`` in turn (``loaded`` in the result)."""
    res = _soak_run(a, None)
    for load in a.load:
        run = res.setdefault("loaded", {})[load.name] = _soak_run(a, load)
        idle, loaded = res["watchdog_latency_ms"], run["watchdog_latency_ms"]
        if idle.get("p99_median") and loaded.get("p99_median"):  # (the goal: ≤ 1.5 with record)
            run["watchdog_p99_vs_idle"] = round(loaded["p99_median"] / idle["p99_median"], 3)
            print(f"{load.name}: the watchdog's latency p99 (median) × {run['watchdog_p99_vs_idle']} of idle")
    return res


# ---------------------------------------------------------------------------------- ik


def _time_calls(fn: Callable[[int], Any], n: int) -> float:
    t = time.perf_counter()
    for i in range(n):
        fn(i)
    return (time.perf_counter() - t) / n * 1e6


def _time_batch(fn: Callable[[], Any], min_s: float = 0.3) -> float:
    """Seconds per call of ``fn``, repeated for at least ``min_s``."""
    fn()
    reps, t = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t) < min_s or reps == 0:
        fn()
        reps += 1
    return elapsed / reps


def ik(a: argparse.Namespace) -> dict[str, Any]:
    from telesurg.shared.errors import IKError
    from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
    from telesurg.shared.robots.mh3f.kinematics import ik as ik6
    from telesurg.shared.robots.mh3f.trocar import posture_adjust, rcm_error, trocar_ik
    from telesurg.shared.robots.plas import kinematics as plas
    from telesurg.shared.robots.vip import kinematics as vip
    from telesurg.tools.bench.ik_batch import ik_batch, trocar_ik_batch

    rng = np.random.default_rng(0)
    n = a.n
    trocar = np.array([0.5, 0.0, 0.2])
    q_seed = posture_adjust(np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0]), trocar)
    d = fk(q_seed, MH3F)[:3, 0]
    q_in = trocar_ik(trocar + 0.06 * d, trocar, q_seed)
    tip0 = fk(q_in, MH3F)[:3, 3]
    tips: list[np.ndarray] = []
    while len(tips) < n:  # targets within ±15 mm sideways and ±10 mm along the shaft, all reachable
        t = tip0 + rng.uniform(-0.015, 0.015, 3) + d * rng.uniform(-0.01, 0.01)
        try:
            trocar_ik(t, trocar, q_in)
        except IKError:
            continue
        tips.append(t)
    res: dict[str, Any] = {"n": n}
    sols = [trocar_ik(t, trocar, q_in) for t in tips]
    res["trocar_ik"] = {
        "us_per_call": round(_time_calls(lambda i: trocar_ik(tips[i], trocar, q_in), n), 2),
        "pos_err_max_m": float(
            max(np.linalg.norm(fk(q, MH3F)[:3, 3] - t) for q, t in zip(sols, tips, strict=True))
        ),
        "rcm_err_max_m": float(max(rcm_error(q, trocar) for q in sols)),
    }
    poses = [fk(q, MH3F) for q in sols]
    res["ik_6axis"] = {"us_per_call": round(_time_calls(lambda i: ik6(poses[i], q_in, MH3F), n), 2)}
    geom = vip.VIP_ARM1
    w0 = vip.fk(geom.home, geom).wrist
    V = vip.select_vip(np.array(geom.home), 0.05, geom)
    ws = [w0 + rng.uniform(-0.01, 0.01, 3) for _ in range(n)]
    res["vip_ik"] = {
        "us_per_call": round(_time_calls(lambda i: vip.vip_ik(ws[i], V, geom, q4_ref=geom.home[3]), n), 2)
    }
    cfg = plas.MappingConfig()
    res["plas_map_step"] = {
        "us_per_call": round(
            _time_calls(
                lambda i: plas.map_step(np.zeros(6), np.full(6, 0.1), np.full(6, 1e-3), dt=0.005, config=cfg),
                n,
            ),
            2,
        )
    }
    for k in ("trocar_ik", "ik_6axis", "vip_ik", "plas_map_step"):
        res[k]["solves_per_s"] = round(1e6 / res[k]["us_per_call"])
    # vectorised: every target in one call (tools/bench/ik_batch.py)
    tip_arr, pose_arr = np.array(tips), np.array(poses)
    qb, okb = trocar_ik_batch(tip_arr, trocar, q_in)
    res["trocar_ik"]["batch_solves_per_s"] = round(
        n / _time_batch(lambda: trocar_ik_batch(tip_arr, trocar, q_in))
    )
    res["trocar_ik"]["batch_all_solved"] = bool(okb.all())
    res["trocar_ik"]["batch_pos_err_max_m"] = float(
        max(np.linalg.norm(fk(q, MH3F)[:3, 3] - t) for q, t in zip(qb, tips, strict=True))
    )
    res["trocar_ik"]["batch_rcm_err_max_m"] = float(max(rcm_error(q, trocar) for q in qb))
    res["ik_6axis"]["batch_solves_per_s"] = round(n / _time_batch(lambda: ik_batch(pose_arr, q_in)))
    res["generic"] = _mink_baseline(tips, trocar, q_in, n)
    if "us_per_call" in res["generic"]:
        res["speedup_trocar_vs_generic"] = round(
            res["generic"]["us_per_call"] / res["trocar_ik"]["us_per_call"], 1
        )
    from rich.console import Console
    from rich.table import Table

    tab = Table(title=f"IK, {n} targets (trocar at 500, 0, 200 mm; tips ±15 mm around 60 mm deep)")
    for c in ("solver", "µs/call", "solves/s", "batch solves/s", "pos err max", "RCM err max"):
        tab.add_column(c, justify="right")
    for k in ("trocar_ik", "ik_6axis", "vip_ik", "plas_map_step", "generic"):
        r = res[k]
        tab.add_row(
            r.get("name", k),
            str(r.get("us_per_call", "—")),
            str(r.get("solves_per_s", "—")),
            str(r.get("batch_solves_per_s", "—")),
            f"{r['pos_err_max_m']:.2e} m" if "pos_err_max_m" in r else "",
            f"{r['rcm_err_max_m']:.2e} m" if "rcm_err_max_m" in r else "",
        )
    Console().print(tab)
    if "note" in res["generic"]:
        print(res["generic"]["note"])
    return res


def _mink_baseline(tips: list[np.ndarray], trocar: np.ndarray, q0: np.ndarray, n: int) -> dict[str, Any]:
    """mink (differential IK on the MuJoCo model, QP per iteration) to the same tip targets, with the
    forceps axis through the trocar as a second task; iterate to convergence."""
    import importlib

    import mujoco

    try:
        mink: Any = importlib.import_module("mink")
    except ImportError:
        return {
            "name": "mink (not installed)",
            "note": "generic IK skipped: pip install -e '.[bench]' for mink",
        }
    from telesurg.services.slave_control.models import model_path
    from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
    from telesurg.shared.robots.mh3f.trocar import rcm_error

    model = mujoco.MjModel.from_xml_path(str(model_path("mh3f")))
    cfg = mink.Configuration(model)
    # the arm's joints in the scene's qpos (the scene has more: the tissue's spring)
    arm = np.array([model.jnt_qposadr[j] for j in model.actuator_trnid[:, 0]])

    def full(q_arm: np.ndarray) -> np.ndarray:
        q = np.array(model.qpos0, dtype=float)
        q[arm] = q_arm
        return q

    task = mink.FrameTask("tip", "site", position_cost=1.0, orientation_cost=1.0)
    m = min(n, 50)  # mink is slow: a subset of the targets
    errs, rcms, t_total, iters_total = [], [], 0.0, 0
    for tip in tips[:m]:
        cfg.update(full(q0))
        # target: tip position, orientation with x along trocar → tip (the RCM constraint as a pose)
        x = (tip - trocar) / np.linalg.norm(tip - trocar)
        T0 = fk(q0, MH3F)
        y = T0[:3, 1] - x * float(T0[:3, 1] @ x)
        y /= np.linalg.norm(y)
        R = np.column_stack([x, y, np.cross(x, y)])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, tip
        task.set_target(mink.SE3.from_matrix(T))
        t = time.perf_counter()
        iters = 0
        while iters < 200:
            iters += 1
            vel = mink.solve_ik(cfg, [task], 0.01, "daqp", 1e-3)
            cfg.integrate_inplace(vel, 0.01)
            q = cfg.q[arm].copy()
            if np.linalg.norm(fk(q, MH3F)[:3, 3] - tip) < 1e-6:
                break
        t_total += time.perf_counter() - t
        iters_total += iters
        errs.append(float(np.linalg.norm(fk(q, MH3F)[:3, 3] - tip)))
        rcms.append(rcm_error(q, trocar))
    us = t_total / m * 1e6
    return {
        "name": f"mink {mink.__version__ if hasattr(mink, '__version__') else ''} (daqp)".strip(),
        "us_per_call": round(us, 1),
        "solves_per_s": round(1e6 / us),
        "iterations_mean": round(iters_total / m, 1),
        "pos_err_max_m": max(errs),
        "rcm_err_max_m": max(rcms),
        "targets": m,
    }


# ---------------------------------------------------------------------------------- sim


def sim(a: argparse.Namespace) -> dict[str, Any]:
    import mujoco
    from telesurg.services.slave_control.models import model_names, model_path

    res: dict[str, Any] = {}
    for name in model_names():
        m = mujoco.MjModel.from_xml_path(str(model_path(name)))
        d = mujoco.MjData(m)
        steps = int(a.seconds / m.opt.timestep)
        t = time.perf_counter()
        mujoco.mj_step(m, d, nstep=steps)
        wall = time.perf_counter() - t
        res[name] = {
            "steps_per_s": round(steps / wall),
            "us_per_step": round(wall / steps * 1e6, 2),
            "realtime_factor": round(steps * m.opt.timestep / wall, 1),
            "dof": int(m.nv),
        }
    from rich.console import Console
    from rich.table import Table

    tab = Table(title=f"MuJoCo unpaced, {a.seconds:g} s of sim time per model")
    for c in ("model", "DoF", "steps/s", "µs/step", "× real time"):
        tab.add_column(c, justify="right")
    for k, r in res.items():
        tab.add_row(k, str(r["dof"]), str(r["steps_per_s"]), str(r["us_per_step"]), str(r["realtime_factor"]))
    Console().print(tab)
    return res


BENCHES: dict[str, Callable[[argparse.Namespace], dict[str, Any]]] = {
    "latency": latency,
    "soak": soak,
    "ik": ik,
    "sim": sim,
}


def _load_arg(spec: str) -> Load:
    try:
        load = Load.parse(spec)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if why := load.available():
        raise argparse.ArgumentTypeError(f"--load {spec}: {why}")
    return load


def _sched_table(name: str, figs: dict[str, dict[str, float]]) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"the control threads' wait for a CPU once runnable, {name} (perf sched; first block)")
    for col in ("service", "switch-ins", "p50 ms", "p99 ms", "p99.9 ms", "max ms", "CPU ms"):
        t.add_column(col, justify="left" if col == "service" else "right")
    for svc, f in figs.items():
        quantiles = (f"{f[k]:.3f}" for k in ("p50", "p99", "p99_9", "max"))
        t.add_row(svc, str(f["n"]), *quantiles, f"{f['cpu_ms']:.0f}")
    Console().print(t)


def main(argv: Sequence[str] | None = None, name: str = "latency") -> int:
    ap = argparse.ArgumentParser(prog=f"telesurg bench {name}", description=__doc__)
    ap.add_argument("--json", type=Path, help="write the figures here")
    if name in ("latency", "soak"):
        ap.add_argument(
            "--rate",
            type=float,
            default=1000.0,
            help="master rate, Hz (default 1000; latency: 0 = unpaced)",
        )
        ap.add_argument("--seconds", type=float, default=10.0 if name == "latency" else 60.0)
        ap.add_argument(
            "--rt-priority",
            type=int,
            help="SCHED_FIFO priority of the master, mapping and slave loop threads, 0 = normal "
            "scheduling (default: the deploy configs', 20)",
        )
    if name in ("latency", "soak"):
        ap.add_argument(
            "--load",
            action="append",
            default=[],
            metavar="SPEC",
            type=_load_arg,
            help="also measure under this background load, repeatable: cpu:N (N busy processes at "
            "normal priority), idle:N (N busy processes under SCHED_IDLE, the camera's and mirror's "
            "class), record (the recorder on the bus), stalled (a subscriber on everything that "
            "stops reading), viewer (the rerun web viewer in "
            "headless Chromium); the table shows idle and each load of the same run",
        )
    if name in ("latency", "soak"):
        ap.add_argument(
            "--keep-logs",
            type=Path,
            metavar="DIR",
            help="keep the services' logs (and the measured rows) of every block in DIR instead of "
            "a temporary directory: what the watchdog and the router logged around a HOLD",
        )
    if name == "soak":
        ap.add_argument(
            "--no-record",
            dest="record",
            action="store_false",
            help="without the recorder on the bus (no per-stream table; loop misses and CPU alone)",
        )
    if name == "latency":
        ap.add_argument("--blocks", type=int, default=2, help="alternating relay/pipeline blocks each")
        ap.add_argument("--plot", type=Path, help="write a PNG of the percentiles here")
        ap.add_argument(
            "--sched-trace",
            action="store_true",
            help="trace the scheduler (perf sched, needs perf and root) through the first pipeline "
            "block of each condition: how long each control service's threads waited for a CPU",
        )
    if name == "ik":
        ap.add_argument("--n", type=int, default=1000, help="targets")
    if name == "sim":
        ap.add_argument("--seconds", type=float, default=5.0, help="sim seconds per model")
    a = ap.parse_args(argv)
    if getattr(a, "rt_priority", None) is not None and not 0 <= a.rt_priority <= 99:
        ap.error(f"--rt-priority {a.rt_priority}: 0 (normal scheduling) or 1..99 (SCHED_FIFO)")
    keep = getattr(a, "keep_logs", None)
    if keep is not None and keep.exists() and (not keep.is_dir() or any(keep.iterdir())):
        ap.error(
            f"--keep-logs {keep}: name a new or empty directory (a run's logs are not mixed with another's)"
        )
    if getattr(a, "sched_trace", False) and (why := schedtrace.unavailable()):
        ap.error(f"--sched-trace: {why}")
    if name == "soak" and not 1.0 <= a.rate <= 5000.0:
        ap.error(f"--rate {a.rate:g}: the soak runs the master at a fixed rate in [1, 5000] Hz")
    res = BENCHES[name](a)
    res["date"], res["machine"] = now(), machine()
    if a.json:
        a.json.write_text(jsonio.dumps(res, indent=2) + "\n")
    return 0
