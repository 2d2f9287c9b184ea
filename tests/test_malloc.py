"""telesurg.shared.malloc: freed native memory goes back to the OS (glibc), in a process of its own."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

SCRIPT = r"""
import ctypes, ctypes.util, json, sys, threading
from telesurg.shared.malloc import Trimmer

libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]

def anon_mb():
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024

def burst():
    # a native thread's burst: 1001 buffers of 48 KiB carved one after another from its arena
    # (48 MB: within one of glibc's 64 MiB thread heaps), touched; all but the last freed, so they
    # lie below a live block and glibc cannot give them back by trimming the arena's top
    blocks = [libc.malloc(48 * 1024) for _ in range(1001)]
    for b in blocks:
        ctypes.memset(b, 1, 48 * 1024)
    burst.keep = blocks.pop()
    for b in blocks:
        libc.free(b)

t = threading.Thread(target=burst); t.start(); t.join()
period = float(sys.argv[1])
before = anon_mb()
trimmer = Trimmer(period)
trimmed = trimmer.maybe_trim(now=1e12)
print(json.dumps({"before": before, "after": anon_mb(), "trimmed": trimmed, "trims": trimmer.trims,
                  "available": trimmer.available}))
"""


def run(period: float) -> dict[str, float]:
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(period)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out: dict[str, float] = json.loads(proc.stdout)
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc and /proc: Linux")
def test_a_burst_freed_by_a_thread_goes_back_to_the_os_only_when_trimming_is_on() -> None:
    on, off = run(30.0), run(0.0)
    print(on, off)
    assert on["available"] and on["trimmed"] and on["trims"] == 1
    # 48 MB were touched and freed, still resident: returned when trimmed
    assert on["before"] > 40 and on["before"] - on["after"] > 35, on
    # without trimming it stays (a few MB may go back by glibc's own top-of-heap trim)
    assert not off["trimmed"] and off["before"] > 40 and off["after"] > off["before"] - 10, off
