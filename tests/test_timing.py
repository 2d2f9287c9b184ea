"""CycleTimer: absolute deadlines, missed periods counted, sub-rates kept in periods of time."""

from __future__ import annotations

import pytest

import shared.timing
from shared.timing import CycleTimer


class FakeClock:
    """monotonic_ns and sleep for shared.timing: sleeping advances the clock exactly."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def monotonic_ns(self) -> int:
        return self.ns

    def sleep(self, s: float) -> None:
        self.ns += round(s * 1e9)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    c = FakeClock()
    monkeypatch.setattr(shared.timing.time, "monotonic_ns", c.monotonic_ns)
    monkeypatch.setattr(shared.timing.time, "sleep", c.sleep)
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
