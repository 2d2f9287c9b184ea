"""One cycle timer for every fixed-rate loop, with overrun accounting.

Example::

    timer = CycleTimer(rate_hz=500)
    while running:
        do_work()
        timer.wait()            # sleeps to the next absolute deadline
    print(timer.overruns)
"""

from __future__ import annotations

import gc
import logging
import os
import time
from dataclasses import dataclass, field

from telesurg.shared.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class CycleTimer:
    """Absolute-deadline loop pacing: no drift, missed cycles are skipped and counted.

    Attributes:
        rate_hz: loop rate, Hz (> 0).
        overruns: cycles whose work ended after the next deadline.
        cycles: cycles completed.
        periods: periods elapsed (cycles plus the deadlines missed), the loop's time in periods.
    """

    rate_hz: float
    overruns: int = 0
    cycles: int = 0
    periods: int = 0
    _before: int = field(init=False, default=0)
    _period_ns: int = field(init=False)
    _next_ns: int = field(init=False)

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        self._period_ns = round(1e9 / self.rate_hz)
        self._next_ns = time.monotonic_ns() + self._period_ns
        _fine_timer_slack()

    @property
    def period_s(self) -> float:
        """Loop period, s."""
        return self._period_ns / 1e9

    @property
    def deadline_s(self) -> float:
        """The next deadline (the end of the current period), monotonic s."""
        return self._next_ns / 1e9

    def wait(self) -> int:
        """Sleep until the next deadline; return how many deadlines were missed (0 normally)."""
        self.cycles += 1
        now = time.monotonic_ns()
        missed = 0
        if now > self._next_ns:
            missed = (now - self._next_ns) // self._period_ns + 1
            self.overruns += 1
            self._next_ns += missed * self._period_ns
        delay = self._next_ns - now
        if delay > 0:
            time.sleep(delay / 1e9)
        self._next_ns += self._period_ns
        self._before = self.periods
        self.periods += 1 + int(missed)
        return int(missed)

    def every(self, n: int, phase: int = 0) -> bool:
        """True if the last :meth:`wait` crossed period ``phase + k·n``: a sub-rate task keeps its
        rate (in periods of time, not loop iterations) when the loop runs late. Give sub-rate
        tasks different phases so they do not all land in the same cycle (its work would be the
        sum of theirs, and overrun)."""
        return (self.periods - phase) // n != (self._before - phase) // n


def settle_gc() -> None:
    """Collect once and freeze what survives (call when a service is set up, before its loop).

    Everything allocated while setting up (zenoh, MuJoCo, numpy, the model) moves to the
    permanent generation, so the collector's full passes no longer scan it: a full pass over a
    set-up service's ~10⁵ objects takes milliseconds, more than a 1 ms control period."""
    gc.collect()
    gc.freeze()


def start_loop(rt_priority: int = 0) -> None:
    """Call in a loop's thread when the service is set up, right before the loop: settle the
    garbage collector (:func:`settle_gc`) and, if ``rt_priority`` > 0, run the thread under
    ``SCHED_FIFO`` (:func:`set_realtime`; a refusal is logged as a warning, the loop runs on)."""
    settle_gc()
    if why := set_realtime(rt_priority):
        log.warning("%s", why)
    elif rt_priority:
        log.info("loop thread under SCHED_FIFO, priority %d", rt_priority)


def check_rt_priority(priority: int) -> None:
    """Raise ConfigError unless ``priority`` is 0 (normal scheduling) or 1..99 (SCHED_FIFO)."""
    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise ConfigError(f"rt_priority={priority!r}: 0 (normal scheduling) or 1..99 (SCHED_FIFO)")


def set_realtime(priority: int) -> str:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (1-99); 0 leaves it as it is.

    For a fixed-rate loop on a busy host: a FIFO thread is never preempted by normal threads, so
    its cycle is not cut by them. Only this thread changes (not the process's other threads), and
    threads it starts later get the normal policy back (``SCHED_RESET_ON_FORK``). Linux throttles
    real-time threads to 95 % of each second, so a runaway loop cannot freeze the host.

    Returns:
        "" when set (or 0), else why not; the thread then keeps its normal policy.
    """
    check_rt_priority(priority)
    if priority == 0:
        return ""
    try:
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return (
            f"SCHED_FIFO {priority} refused ({exc}): it needs root, CAP_SYS_NICE or an rtprio "
            "limit (docs/deploy.md); running under the normal scheduler"
        )
    return ""


def _fine_timer_slack() -> None:
    """Ask Linux for 1 µs timer slack on this thread (default 50 µs): sleeps end closer to their
    deadline. Harmless where unsupported."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, 1000, 0, 0, 0)  # PR_SET_TIMERSLACK, ns
    except (OSError, AttributeError):
        pass
