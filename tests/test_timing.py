"""CycleTimer: absolute deadlines, missed periods counted, sub-rates kept in periods of time."""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable

import pytest
import telesurg.shared.timing
from helpers import run_unprivileged
from telesurg.services.mapping import MappingConfig
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control import run as run_slave
from telesurg.shared.errors import ConfigError
from telesurg.shared.timing import CycleTimer, check_rt_priority, set_realtime


class FakeClock:
    """monotonic_ns and sleep for telesurg.shared.timing: sleeping advances the clock exactly."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def monotonic_ns(self) -> int:
        return self.ns

    def sleep(self, s: float) -> None:
        self.ns += round(s * 1e9)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    c = FakeClock()
    monkeypatch.setattr(telesurg.shared.timing.time, "monotonic_ns", c.monotonic_ns)
    monkeypatch.setattr(telesurg.shared.timing.time, "sleep", c.sleep)
    return c


def test_on_time_every_fires_once_per_n_periods(clock: FakeClock) -> None:
    timer = CycleTimer(rate_hz=1000.0)
    fired = []
    for _ in range(40):
        clock.ns += 200_000  # 0.2 ms of work per 1 ms cycle
        assert timer.wait() == 0
        fired.append(timer.every(4))
    assert timer.periods == 40 and timer.overruns == 0
    assert sum(fired) == 10 and fired[3] and not fired[2]


def test_a_stall_is_counted_and_sub_rates_keep_their_rate_in_time(clock: FakeClock) -> None:
    timer = CycleTimer(rate_hz=1000.0)
    fired = 0
    missed = []
    for i in range(40):
        clock.ns += 10_500_000 if i == 10 else 200_000  # cycle 10 stalls for 10.5 ms
        missed.append(timer.wait())
        fired += timer.every(4)
    assert missed[10] == 10 and sum(missed) == 10 and timer.overruns == 1
    assert timer.periods == 50
    # 50 periods of time hold 12 multiples of 4; the stall's one wakeup crossed three of them
    # (12, 16, 20) and runs the task once, with the caught-up state
    assert fired == 12 - 2


def test_a_resyncing_timer_starts_a_late_cycle_at_once(clock: FakeClock) -> None:
    """A camera's frame finished 5 ms late starts the next at once: 45 ms between frames, not the
    80 ms of a skipped period. The lateness adds up: each whole period of it counts as missed."""
    timer = CycleTimer(rate_hz=25.0, resync=True)
    starts = [clock.ns]
    missed = []
    for work_ms in (10, 45, 10, 10, 130, 10, 75, 10):
        clock.ns += work_ms * 1_000_000
        missed.append(timer.wait())
        starts.append(clock.ns)
    gaps_ms = [(b - a) / 1e6 for a, b in itertools.pairwise(starts)]
    assert gaps_ms == [40, 45, 40, 40, 130, 40, 75, 40]
    # late by 5, then 90 (95: two periods, 15 left), then 35 (50: one period, 10 left)
    assert missed == [0, 0, 0, 0, 2, 0, 1, 0] and timer.overruns == 3
    # cycles + missed span the time: 450 ms = 11 periods of 40 ms and the 10 ms still owed
    assert timer.periods == 11 and starts[-1] - starts[0] == 450_000_000


def test_rate_must_be_positive() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        CycleTimer(rate_hz=0.0)


def test_sub_rates_with_different_phases_never_share_a_cycle(clock: FakeClock) -> None:
    timer = CycleTimer(rate_hz=1000.0)
    tasks = ((4, 0), (10, 1), (20, 2), (50, 3))  # slave_control's measured, modes, wrench, state
    fired = {t: 0 for t in tasks}
    for _ in range(1000):
        clock.ns += 200_000
        timer.wait()
        due = [t for t in tasks if timer.every(*t)]
        assert len(due) <= 1, (timer.periods, due)
        for t in due:
            fired[t] += 1
    assert fired == {(4, 0): 250, (10, 1): 100, (20, 2): 50, (50, 3): 20}


def _policy_in_thread(fn: Callable[[], object]) -> tuple[object, int, int, int]:
    """Run ``fn`` in a new thread; its result, that thread's policy and priority afterwards, and
    the policy of a thread it starts then."""
    out: list[tuple[object, int, int, int]] = []

    def body() -> None:
        r = fn()
        child: list[int] = []
        t = threading.Thread(target=lambda: child.append(os.sched_getscheduler(0)))
        t.start()
        t.join()
        out.append((r, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, child[0]))

    th = threading.Thread(target=body)
    th.start()
    th.join()
    return out[0]


def test_rt_priority_is_checked() -> None:
    for bad in (-1, 100, True, 2.5, "20"):
        with pytest.raises(ConfigError, match="rt_priority"):
            check_rt_priority(bad)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"rt_priority=100"):
        MappingConfig(rt_priority=100).validate()
    with pytest.raises(ConfigError, match=r"rt_priority=-1"):  # refused before anything starts
        run_slave(SlaveControlConfig(rt_priority=-1), threading.Event())


def test_set_realtime_changes_only_the_calling_thread() -> None:
    before = os.sched_getscheduler(0)
    assert _policy_in_thread(lambda: set_realtime(0))[1] == before  # 0: left as it is
    why, policy, prio, child = _policy_in_thread(lambda: set_realtime(7))
    if why:  # not permitted here: the thread keeps its policy, and the reason says what is needed
        assert "CAP_SYS_NICE" in str(why) and policy == before
    else:
        assert policy & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO and prio == 7
        assert child == os.SCHED_OTHER  # threads it starts get the normal policy back
    assert os.sched_getscheduler(0) == before  # this (the calling) thread is untouched


def test_set_realtime_refused_without_the_privilege() -> None:
    r = run_unprivileged(  # (root drops to "nobody", and with it CAP_SYS_NICE)
        "from telesurg.shared.timing import set_realtime",
        "why = set_realtime(7)\n"
        "print(repr(why)); sys.exit(0 if why and os.sched_getscheduler(0) == os.SCHED_OTHER else 1)\n",
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "needs root, CAP_SYS_NICE or an rtprio" in r.stdout
