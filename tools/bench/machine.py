"""The machine a bench's figures came from, written into every bench's JSON.

A figure is only comparable with another from the same machine in the same state. On the
project's VM the same ``bench viewer`` command kept up one day and fell 30–40 s behind the next;
the cause was the VM itself — restarted at 20:06 UTC on 2026-12-04, after which the bare zenoh
relay hop took ~1.34× as long (docs/performance.md) — which no JSON said. So each bench writes
the CPU model, the kernel and the time the host booted (``/proc/stat`` ``btime``): a new boot
time between two series of figures says they came from different machines, however alike their
names.

    res["date"], res["machine"] = now(), machine()
"""

from __future__ import annotations

import os
import platform
import sys
import time
from pathlib import Path
from typing import Any


def now() -> str:
    """The date and time, UTC, as every bench writes it (``2026-12-05 06:40:00 UTC``)."""
    return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())


def _cpu_model() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def booted() -> str | None:
    """When the host booted (UTC, from ``/proc/stat`` ``btime``); None where there is no /proc."""
    try:
        for line in Path("/proc/stat").read_text().splitlines():
            if line.startswith("btime "):
                return time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(int(line.split()[1])))
    except (OSError, ValueError):
        pass
    return None


def machine() -> dict[str, Any]:
    """CPUs, CPU model, kernel, boot time, Python and the 1-minute load average now."""
    return {
        "cpus": os.cpu_count(),
        "cpu_model": _cpu_model(),
        "kernel": platform.release(),
        "booted": booted(),
        "python": sys.version.split()[0],
        "loadavg_1min": round(os.getloadavg()[0], 2),
    }


def stat_cpu_s(path: str) -> tuple[float, float]:
    """(user, system) CPU seconds so far of a process or thread, from its ``/proc/.../stat``
    (``utime``, ``stime``); OSError if it is gone."""
    with open(path) as f:
        fields = f.read().rsplit(")", 1)[1].split()  # (after the command name, which may hold spaces)
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick
