"""One cycle timer for every fixed-rate loop, with overrun accounting.

Example::

    timer = CycleTimer(rate_hz=500)
    while running:
        do_work()
        timer.wait()            # sleeps to the next absolute deadline
    print(timer.overruns)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field


@dataclass
class CycleTimer:
    """Absolute-deadline loop pacing: no drift, missed cycles are skipped and counted.

    Attributes:
        rate_hz: loop rate, Hz (> 0).
        overruns: cycles whose work ended after the next deadline.
        cycles: cycles completed.
    """

    rate_hz: float
    overruns: int = 0
    cycles: int = 0
    _period_ns: int = field(init=False)
    _next_ns: int = field(init=False)

    def __post_init__(self) -> None:
        if self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        self._period_ns = round(1e9 / self.rate_hz)
        self._next_ns = time.monotonic_ns() + self._period_ns

    @property
    def period_s(self) -> float:
        """Loop period, s."""
        return self._period_ns / 1e9

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
        return int(missed)
