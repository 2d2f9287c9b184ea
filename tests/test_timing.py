"""CycleTimer: absolute deadlines, missed periods counted, sub-rates kept in periods of time."""

from __future__ import annotations

import time

import pytest

from shared.timing import CycleTimer


def test_every_keeps_a_sub_rate_in_periods_when_the_loop_runs_late() -> None:
    timer = CycleTimer(rate_hz=1000.0)
    fired = expected = 0
    for i in range(40):
        if i == 10:
            time.sleep(0.0105)  # a stall: ~10 periods slept through in one cycle
        before = timer.periods
        timer.wait()
        fired += timer.every(4)
        expected += timer.periods // 4 != before // 4  # a multiple of 4 periods was crossed
    # 40 cycles plus the ~10 missed periods: the 4-period task ran once per 4 periods of time
    # crossed (at most once per wakeup), more often than once per 4 loop iterations (10)
    assert timer.periods >= 49 and timer.overruns >= 1
    assert fired == expected > 10


def test_every_fires_once_per_n_periods_on_time() -> None:
    timer = CycleTimer(rate_hz=500.0)
    fired = [timer.wait() == 0 and timer.every(5) for _ in range(20)]
    assert sum(fired) >= 3 and not any(fired[i] and fired[i + 1] for i in range(19))


def test_rate_must_be_positive() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        CycleTimer(rate_hz=0.0)
