"""What the scheduler did to the control path's threads, from Linux ``perf``'s scheduler trace.

``telesurg bench latency --sched-trace`` records ``sched:sched_switch`` and ``sched:sched_wakeup``
on every CPU (``perf record -a``) through the first pipeline block of each condition, and reads
back with ``perf sched timehist`` how long each thread of each control process waited between
being made runnable (woken, or preempted) and getting a CPU: per service, p50 / p99 / p99.9 / max
ms over every switch-in, and the CPU time its threads ran. It tells a loaded tail that is the
scheduler's (the control threads waited for a CPU) from one that is not (they got it at once).

It needs ``perf`` (Debian: ``linux-perf``) and root, or ``kernel.perf_event_paranoid = -1``. The
trace costs the traced block a little CPU (perf writes ~10 MB/s here); the recording is deleted
once read unless ``--keep-logs`` keeps it.
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import tempfile
from collections import defaultdict
from pathlib import Path

import numpy as np
from telesurg.shared.timing import thread_ids

#: A ``perf sched timehist`` row ends in ``comm[tid/pid]  wait  sch-delay  run-time`` (ms).
_ROW = re.compile(r"\[(\d+)(?:/\d+)?\]\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*$")


def unavailable() -> str:
    """Why the scheduler cannot be traced here ("" if it can)."""
    if shutil.which("perf") is None:
        return "no perf on this machine (Debian: apt install linux-perf)"
    try:
        paranoid = int(Path("/proc/sys/kernel/perf_event_paranoid").read_text())
    except (OSError, ValueError):
        return "no /proc/sys/kernel/perf_event_paranoid: not Linux, or no perf events"
    if os.geteuid() != 0 and paranoid > -1:
        return f"tracing every CPU needs root or kernel.perf_event_paranoid = -1 (it is {paranoid})"
    return _probe()


@functools.cache
def _probe() -> str:
    """Record the scheduler for no time at all: a kernel without the tracepoints, or a container
    without tracefs, says so here (~1 s), not after a bench block."""
    with tempfile.TemporaryDirectory() as d:
        argv = ["perf", "record", "-q", "-a", "-e", "sched:sched_switch", "-o", f"{d}/probe.data"]
        argv += ["--", "true"]
        r = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if r.returncode != 0:
        return f"perf cannot trace the scheduler here: {r.stderr.strip()[-200:] or r.returncode}"
    return ""


class SchedTrace:
    """``perf record`` of the scheduler's switches and wake-ups on every CPU for ``seconds``."""

    def __init__(self, out: Path, seconds: float) -> None:
        self.out = out
        argv = ["perf", "record", "-q", "-a", "-o", str(out)]
        argv += ["-e", "sched:sched_switch", "-e", "sched:sched_wakeup", "--", "sleep", f"{seconds:g}"]
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)

    def wait(self) -> None:
        """Wait for the recording to end; RuntimeError with perf's words if it failed."""
        _, err = self.proc.communicate()
        if self.proc.returncode != 0 or not self.out.exists():
            raise RuntimeError(f"perf record failed ({self.proc.returncode}): {err.decode().strip()[-300:]}")


def thread_services(pids: dict[str, int]) -> dict[int, str]:
    """Every thread of each service process: thread id → service name."""
    return {tid: name for name, pid in pids.items() for tid in thread_ids(pid)}  # (gone: none)


def delays(data: Path, threads: dict[int, str]) -> dict[str, dict[str, float]]:
    """Per service: how long its threads waited for a CPU once runnable (``n`` switch-ins,
    ``p50``/``p99``/``p99_9``/``max`` ms) and the CPU time they ran (``cpu_ms``)."""
    waits: dict[str, list[float]] = defaultdict(list)
    ran: dict[str, float] = defaultdict(float)
    with subprocess.Popen(
        ["perf", "sched", "timehist", "-i", str(data)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            m = _ROW.search(line)
            if m is None or (name := threads.get(int(m.group(1)))) is None:
                continue
            waits[name].append(float(m.group(3)))
            ran[name] += float(m.group(4))
    out: dict[str, dict[str, float]] = {}
    for name in sorted(waits):
        a = np.asarray(waits[name])
        q = np.percentile(a, [50, 99, 99.9])
        out[name] = {
            "n": int(a.size),
            "p50": round(float(q[0]), 4),
            "p99": round(float(q[1]), 4),
            "p99_9": round(float(q[2]), 4),
            "max": round(float(a.max()), 4),
            "cpu_ms": round(ran[name], 1),
        }
    return out
