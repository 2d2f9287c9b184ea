"""The wall clock every stamp on the bus is read from, and another host's offset from it.

:func:`wall_ns` is the host's wall clock (``time.time_ns()``) plus a skew that is 0 unless a
service is started with ``bus.clock_skew_ms`` (a test or bench playing a host whose clock is off).
Headers, freshness checks and latencies all read it, so a skewed process is skewed throughout, as
a real host with a wrong clock would be.

Two hosts' clocks are compared over the bus the way NTP does it: a probe leaves at ``t1`` (the
prober's clock), arrives at ``t2`` and is answered at ``t3`` (the responder's clock), and the
answer arrives at ``t4`` (the prober's clock again)::

    offset θ = ((t2 − t1) + (t3 − t4)) / 2      the responder's clock minus the prober's
    delay  δ = (t4 − t1) − (t3 − t2)            the round trip on the network

θ is exact when the two directions take equally long; an asymmetry of ``a`` between them shifts it
by ``a / 2``. :class:`ClockFilter` keeps the recent samples and trusts the one with the smallest
round trip (the one least delayed by queues: NTP's clock filter), and follows a drift (ppm) fitted
over the samples whose round trip is near that minimum.

Example::

    f = ClockFilter()
    f.add(ClockSample(t1, t2, t3, t4), time.monotonic())
    theta = f.offset_ns(time.monotonic())  # None until the first sample
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

import numpy as np
from telesurg.shared.errors import ConfigError

#: Largest skew a process may be given, ms (an hour: beyond it nothing on the bus is fresh anyway).
MAX_SKEW_MS = 3_600_000.0

_skew_ns = 0


def set_skew_ms(ms: float) -> None:
    """Offset this process's wall clock by ``ms`` (tests and benches only; 0 in a real site)."""
    global _skew_ns
    if not -MAX_SKEW_MS <= ms <= MAX_SKEW_MS or ms != ms:
        raise ConfigError(f"clock_skew_ms={ms} outside [-{MAX_SKEW_MS:g}, {MAX_SKEW_MS:g}]")
    _skew_ns = round(ms * 1e6)


def wall_ns() -> int:
    """This process's wall clock, ns since the Unix epoch (the host's, plus the test skew)."""
    return time.time_ns() + _skew_ns


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One probe's four timestamps (ns): sent ``t1`` and answered-received ``t4`` on the prober's
    clock, received ``t2`` and answered ``t3`` on the responder's."""

    t1: int
    t2: int
    t3: int
    t4: int

    @property
    def offset_ns(self) -> float:
        """The responder's clock minus the prober's (exact for a symmetric path)."""
        return ((self.t2 - self.t1) + (self.t3 - self.t4)) / 2

    @property
    def delay_ns(self) -> int:
        """The round trip on the network (the responder's own time taken out)."""
        return (self.t4 - self.t1) - (self.t3 - self.t2)


class ClockFilter:
    """The offset of another host's clock from the recent probes (module doc).

    ``window``: probes kept; ``near_ms``: a sample whose round trip is within this of the smallest
    joins the drift fit; ``min_span_s``: the fit needs that much time between its first and last
    sample (else the best sample's offset is used as it is)."""

    def __init__(self, window: int = 200, near_ms: float = 1.0, min_span_s: float = 5.0) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        self._samples: deque[tuple[float, ClockSample]] = deque(maxlen=window)
        self._near_ns = near_ms * 1e6
        self._min_span_s = min_span_s
        self._fit: tuple[float, float, float] | None = None  # (t0, offset at t0 ns, drift ns/s)
        self.refused = 0  # samples that cannot be (answered before sent: a negative round trip)

    def add(self, s: ClockSample, mono_s: float) -> bool:
        """Take one probe made at ``mono_s`` (the prober's monotonic clock); False if refused."""
        if s.delay_ns < 0 or s.t3 < s.t2:
            self.refused += 1
            return False
        self._samples.append((mono_s, s))
        self._fit = None
        return True

    @property
    def samples(self) -> int:
        """Probes held."""
        return len(self._samples)

    def best(self) -> ClockSample | None:
        """The held probe with the smallest round trip."""
        if not self._samples:
            return None
        return min(self._samples, key=lambda m: m[1].delay_ns)[1]

    def delay_ns(self) -> int | None:
        """The smallest round trip held (the path's own, without queueing)."""
        b = self.best()
        return None if b is None else b.delay_ns

    def drift_ppm(self) -> float:
        """The responder's clock rate minus the prober's, parts per million (0 until fitted)."""
        fit = self._fitted()
        return 0.0 if fit is None else fit[2] / 1e3

    def offset_ns(self, mono_s: float) -> float | None:
        """The offset at ``mono_s``; None before the first probe."""
        fit = self._fitted()
        if fit is not None:
            t0, theta0, slope = fit
            return theta0 + slope * (mono_s - t0)
        b = self.best()
        return None if b is None else b.offset_ns

    def _fitted(self) -> tuple[float, float, float] | None:
        if self._fit is not None or len(self._samples) < 3:
            return self._fit
        floor = min(s.delay_ns for _, s in self._samples)
        near = [(t, s.offset_ns) for t, s in self._samples if s.delay_ns <= floor + self._near_ns]
        if len(near) < 3 or near[-1][0] - near[0][0] < self._min_span_s:
            return None
        t = np.array([m[0] for m in near])
        y = np.array([m[1] for m in near])
        t0 = float(t[-1])
        slope, intercept = np.polyfit(t - t0, y, 1)
        self._fit = (t0, float(intercept), float(slope))
        return self._fit


def offset_text(offset_ns: float | None, delay_ns: int | None) -> str:
    """``"+300.2 ms (round trip 1.4 ms)"``, or ``"unknown"``."""
    if offset_ns is None:
        return "unknown"
    rtt = "" if delay_ns is None else f" (round trip {delay_ns / 1e6:.1f} ms)"
    return f"{offset_ns / 1e6:+.1f} ms{rtt}"
