"""One cycle timer for every fixed-rate loop, with overrun accounting.

Example::

    timer = CycleTimer(rate_hz=500)
    while running:
        do_work()
        timer.wait()            # sleeps to the next absolute deadline
    print(timer.overruns)
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import gc
import logging
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from telesurg.shared.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class CycleTimer:
    """Absolute-deadline loop pacing: no drift, missed cycles are skipped and counted.

    Attributes:
        rate_hz: loop rate, Hz (> 0).
        resync: what a late cycle does. False (control loops): wait for the next deadline on the
            grid, skipping the periods it overran. True (a camera): start the next cycle at once
            and restart the grid from it, so a frame finished a little late costs that little,
            not a whole period; the lateness adds up, and each whole period of it counts as
            missed (so cycles + missed still span the time elapsed).
        overruns: cycles whose work ended after the next deadline.
        cycles: cycles completed.
        periods: periods elapsed (cycles plus the deadlines missed), the loop's time in periods.
    """

    rate_hz: float
    resync: bool = False
    overruns: int = 0
    cycles: int = 0
    periods: int = 0
    _before: int = field(init=False, default=0)
    _period_ns: int = field(init=False)
    _next_ns: int = field(init=False)
    _late_ns: int = field(init=False, default=0)

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
            self.overruns += 1
            if self.resync:  # missed: the lateness summed over cycles, in whole periods
                self._late_ns += now - self._next_ns
                missed = self._late_ns // self._period_ns
                self._late_ns -= missed * self._period_ns
                self._next_ns = now
            else:
                missed = (now - self._next_ns) // self._period_ns + 1
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


#: sched_setattr / sched_getattr syscall numbers by machine (Python's os has neither).
_SCHED_ATTR_SYSCALLS = {"x86_64": (314, 315), "aarch64": (274, 275)}
#: The bounds Linux clamps a requested fair slice to (µs).
SLICE_MIN_US, SLICE_MAX_US = 100, 100_000


class _SchedAttr(ctypes.Structure):
    # struct sched_attr (include/uapi/linux/sched/types.h), SCHED_ATTR_SIZE_VER1
    _fields_ = [
        ("size", ctypes.c_uint32),
        ("policy", ctypes.c_uint32),
        ("flags", ctypes.c_uint64),
        ("nice", ctypes.c_int32),
        ("priority", ctypes.c_uint32),
        ("runtime", ctypes.c_uint64),
        ("deadline", ctypes.c_uint64),
        ("period", ctypes.c_uint64),
        ("util_min", ctypes.c_uint32),
        ("util_max", ctypes.c_uint32),
    ]


#: The fair scheduler's policies (the ones a slice belongs to).
_FAIR_POLICIES = (os.SCHED_OTHER, getattr(os, "SCHED_BATCH", 3))


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _sched_attr_call(setting: bool, tid: int, attr: _SchedAttr) -> None:
    nrs = _SCHED_ATTR_SYSCALLS.get(platform.machine())
    if nrs is None or not hasattr(os, "sched_getscheduler"):
        raise OSError(f"sched_setattr: not available on {platform.system()} {platform.machine()}")
    libc = _libc()
    if setting:
        rc = libc.syscall(nrs[0], tid, ctypes.byref(attr), 0)
    else:
        rc = libc.syscall(nrs[1], tid, ctypes.byref(attr), ctypes.sizeof(attr), 0)
    if rc != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"sched_{'set' if setting else 'get'}attr: {os.strerror(err)}")


def _sched_attr(tid: int) -> _SchedAttr:
    attr = _SchedAttr(size=ctypes.sizeof(_SchedAttr))
    _sched_attr_call(False, tid, attr)
    return attr


def fair_slice_us(tid: int = 0) -> float | None:
    """The EEVDF slice of thread ``tid`` (0: the calling one) in µs, or None when the thread is
    not under the fair scheduler (e.g. SCHED_FIFO). Raises OSError where Linux cannot say."""
    attr = _sched_attr(tid)
    return float(attr.runtime) / 1e3 if attr.policy in _FAIR_POLICIES else None


def check_slice_us(us: float) -> None:
    """Raise ConfigError unless ``us`` is 0 (the kernel's own slice) or within the bounds Linux
    takes (:data:`SLICE_MIN_US`..:data:`SLICE_MAX_US`)."""
    ok = isinstance(us, int | float) and not isinstance(us, bool)
    if not ok or not (us == 0 or SLICE_MIN_US <= us <= SLICE_MAX_US):
        raise ConfigError(f"slice {us!r} µs: 0 (the kernel's default) or {SLICE_MIN_US}..{SLICE_MAX_US} µs")


def set_fair_slice(us: float, tid: int = 0) -> str:
    """Ask Linux's fair scheduler (EEVDF, Linux ≥ 6.12) for a ``us`` µs slice for thread ``tid``
    (0: the calling one); 0 leaves it as it is. Threads and processes it starts later inherit it.

    A short slice gives a thread that wakes up an earlier virtual deadline, so it may preempt a
    thread of another program that is using up its own (longer) slice instead of waiting for it
    to end. (On this project's VM, with the control processes' autogroups at nice −10, it made no
    measurable difference: docs/performance.md.) It changes no share of the CPU (nice does that),
    and it needs no privilege. The policy and nice value stay;
    a thread not under the fair scheduler (SCHED_FIFO) is left alone.

    Returns:
        "" when set (or 0), else why not (an older kernel ignores the request: read back).
    """
    check_slice_us(us)
    if us == 0:
        return ""
    try:
        attr = _sched_attr(tid)
        if attr.policy not in _FAIR_POLICIES:
            return ""
        attr.size, attr.flags, attr.runtime = ctypes.sizeof(_SchedAttr), 0, int(us * 1e3)
        _sched_attr_call(True, tid, attr)
        got = fair_slice_us(tid)
    except OSError as exc:
        return f"a {us:g} µs scheduler slice refused ({exc}); the kernel's default slice stays"
    if got is not None and abs(got - us) > 1:
        return f"a {us:g} µs scheduler slice not taken (Linux ≥ 6.12 has them); the slice is {got:g} µs"
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


#: The launcher sets this in a best-effort service's environment (mirror, camera): the nice
#: value its process steps down to once it is up (:func:`step_down`).
BEST_EFFORT_ENV = "TELESURG_BEST_EFFORT_NICE"


def parse_best_effort_nice(raw: str, default: int = 19) -> int:
    """The best-effort nice value written in ``raw`` (:data:`BEST_EFFORT_ENV`; "" → ``default``).
    ConfigError unless 0..19."""
    try:
        n = int(raw) if raw.strip() else default
    except ValueError:
        n = -1
    if not 0 <= n <= 19:
        raise ConfigError(f"{BEST_EFFORT_ENV}={raw!r}: a nice value 0..19 (0: normal priority)")
    return n


def thread_ids(pid: int = 0) -> set[int]:
    """The thread ids of process ``pid`` (0: this one); empty when it is gone (or no /proc)."""
    try:
        return {int(t) for t in os.listdir(f"/proc/{pid or 'self'}/task")}
    except OSError:  # gone, or no /proc
        return set()


def _each_thread(pid: int, set_one: Callable[[int], None]) -> int:
    """Apply ``set_one`` to every thread of process ``pid`` (0: this one), again to any thread
    started meanwhile (a thread inherits its policy from the one that starts it); the count."""
    done: set[int] = set()
    for _ in range(3):
        new = thread_ids(pid) - done
        if not new:
            break
        for tid in new:
            with contextlib.suppress(OSError):  # a thread that just ended
                set_one(tid)
        done |= new
    return len(done)


def set_autogroup_nice(pid: int, nice: int) -> bool:
    """Give the scheduler autogroup of ``pid`` (0: this process) the nice value ``nice``, where
    Linux has autogroups (``kernel.sched_autogroup_enabled``); False where it cannot.

    A session is an autogroup, and the scheduler shares the CPU between autogroups first: a
    process's own nice value or ``SCHED_IDLE`` counts only against the threads of its own group,
    not against a CPU hog in another session. A value ≥ 0 needs no privilege, < 0 root or
    ``CAP_SYS_NICE``."""
    try:
        Path(f"/proc/{pid or 'self'}/autogroup").write_text(f"{nice}\n")
    except OSError:
        return False
    return True


def set_best_effort(pid: int = 0, nice: int = 19) -> str:
    """Put process ``pid`` (0: this one) below every normal program: each of its threads under
    ``SCHED_IDLE`` (nice ``nice`` where that is refused) and its autogroup at nice ``nice``.

    With autogroups (Linux's default) the CPU is shared between sessions first, so the autogroup's
    nice is what puts a service started in a session of its own below the others; ``SCHED_IDLE``
    does it where autogroups are off. Returns what was done, for the log."""

    def one(tid: int) -> None:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except (AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, tid, nice)

    n = _each_thread(pid, one)
    group = set_autogroup_nice(pid, nice)
    return f"{n} threads under SCHED_IDLE" + (f", its autogroup at nice {nice}" if group else "")


def set_normal_priority(pid: int) -> None:
    """Undo :func:`set_best_effort` for process ``pid`` as far as permitted (leaving
    ``SCHED_IDLE`` and lowering nice may need privilege; the autogroup's nice 0 does not)."""

    def one(tid: int) -> None:
        os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, 0)

    _each_thread(pid, one)
    set_autogroup_nice(pid, 0)


def step_down() -> None:
    """Called by a best-effort service once it is up: if the launcher asked for it
    (:data:`BEST_EFFORT_ENV` 1..19; 0: stay), go below every normal program
    (:func:`set_best_effort`).

    A best-effort service starts at normal priority and steps down only now: at the lowest
    priority from the start, its imports and set-up got ~2 % of a CPU on a host where two
    programs keep both cores busy, and it did not come up within the launcher's 30 s."""
    raw = os.environ.get(BEST_EFFORT_ENV, "").strip()
    if not raw:
        return
    try:
        nice = parse_best_effort_nice(raw)
    except ConfigError as exc:
        log.warning("%s; staying at normal priority", exc)
        return
    if nice == 0:
        log.info("set up; at normal priority (%s=0)", BEST_EFFORT_ENV)
        return
    log.info("set up; best-effort from now on: %s", set_best_effort(0, nice))
