"""Giving freed memory back to the operating system (glibc's allocator), for long-running processes.

glibc keeps what a program frees for reuse: free chunks inside its arenas stay resident, and the
top of a thread's arena is released only above a *dynamic* trim threshold that rises to 64 MB
once large blocks have been freed. A process whose native threads (zenoh's receive threads,
rerun's batcher and sinks) allocate in bursts — the mirror catching up after being starved of
CPU — keeps its peak as resident memory. :class:`Trimmer` fixes the trim threshold
(``mallopt(M_TRIM_THRESHOLD)``, which also stops the dynamic adjustment) and calls
``malloc_trim(0)`` (every arena: free pages inside free chunks are returned) at most once per
period. On a C library without these functions (musl, macOS) it does nothing and says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time
from typing import Any

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # mallopt parameter (malloc.h)


def _libc() -> Any | None:
    """glibc's handle, or None where ``malloc_trim`` / ``mallopt`` do not exist."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        libc.malloc_trim.argtypes, libc.malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    except (OSError, AttributeError, TypeError):
        return None
    return libc


class Trimmer:
    """Return freed memory to the OS every ``period_s`` (0: never; nothing is changed)."""

    def __init__(self, period_s: float, trim_threshold: int = 128 * 1024) -> None:
        self.period_s = period_s
        self.trims = 0
        self.cpu_s = 0.0  # thread CPU time spent in malloc_trim
        self._next = time.monotonic() + period_s
        self._libc = _libc() if period_s > 0 else None
        self.available = self._libc is not None
        if period_s > 0 and self._libc is None:
            log.info("malloc_trim not available (not glibc): freed memory stays with the allocator")
        elif self._libc is not None and self._libc.mallopt(M_TRIM_THRESHOLD, trim_threshold) != 1:
            log.warning("mallopt(M_TRIM_THRESHOLD, %d) refused", trim_threshold)

    def maybe_trim(self, now: float | None = None) -> bool:
        """Trim if the period has passed since the last trim; True if it trimmed."""
        if self._libc is None:
            return False
        now = time.monotonic() if now is None else now
        if now < self._next:
            return False
        self._next = now + self.period_s
        t0 = time.thread_time()
        self._libc.malloc_trim(0)
        self.cpu_s += time.thread_time() - t0
        self.trims += 1
        return True
