"""The clock offset between two hosts from NTP's four timestamps (shared/clock.py): what a
skewed, drifting remote clock looks like through a jittered, queueing network."""

from __future__ import annotations

import numpy as np
import pytest
from telesurg.shared import clock
from telesurg.shared.clock import ClockFilter, ClockSample
from telesurg.shared.errors import ConfigError

MS = 1_000_000


def probe(t1: int, offset: float, out_ms: float, back_ms: float, busy_ms: float = 0.05) -> ClockSample:
    """One probe sent at ``t1`` to a host whose clock is ``offset`` ns ahead."""
    t2 = t1 + round(out_ms * MS + offset)
    t3 = t2 + round(busy_ms * MS)
    t4 = t3 - round(offset) + round(back_ms * MS)
    return ClockSample(t1, t2, t3, t4)


def test_a_symmetric_path_gives_the_offset_and_the_round_trip_exactly() -> None:
    s = probe(10**18, 300 * MS, 25.0, 25.0)
    assert s.offset_ns == pytest.approx(300 * MS)
    assert s.delay_ns == pytest.approx(50 * MS, abs=2)  # the responder's own 0.05 ms taken out


def test_queueing_jitter_is_filtered_by_the_shortest_round_trip() -> None:
    rng = np.random.default_rng(1)
    f = ClockFilter()
    t1 = 10**18
    for i in range(100):  # 20 Hz for 5 s; each direction 25 ms plus 0–10 ms of queueing
        out, back = 25 + rng.exponential(3.0), 25 + rng.exponential(3.0)
        f.add(probe(t1 + i * 50 * MS, -300 * MS, out, back), i * 0.05)
    naive = [s.offset_ns for _, s in f._samples]
    theta = f.offset_ns(5.0)
    assert theta is not None
    print(f"estimate {theta / MS:+.3f} ms; single probes spread {np.ptp(naive) / MS:.1f} ms")
    assert abs(theta + 300 * MS) < 1 * MS  # within 1 ms of the truth
    assert np.ptp(naive) > 5 * MS  # while one probe alone could be several ms off


def test_a_drifting_clock_is_followed() -> None:
    f = ClockFilter(window=400)
    t1, drift = 10**18, 50e-6  # 50 ppm: 0.5 ms every 10 s
    for i in range(400):
        t = i * 0.05
        f.add(probe(t1 + round(t * 1e9), 10 * MS + drift * t * 1e9, 5.0, 5.0), t)
    assert f.drift_ppm() == pytest.approx(50.0, rel=0.05)
    theta = f.offset_ns(30.0)  # 10 s after the last probe
    assert theta == pytest.approx(10 * MS + drift * 30e9, abs=0.05 * MS)


def test_an_impossible_probe_is_refused() -> None:
    f = ClockFilter()
    assert not f.add(ClockSample(100, 50, 60, 90), 0.0)  # answered before it was sent
    assert f.refused == 1 and f.offset_ns(0.0) is None


def test_the_skew_moves_this_processes_wall_clock_and_bad_values_are_refused() -> None:
    try:
        before = clock.wall_ns()
        clock.set_skew_ms(300.0)
        assert clock.wall_ns() - before >= 300 * MS
        for bad in (float("nan"), 1e12, -1e12):
            with pytest.raises(ConfigError, match="clock_skew_ms"):
                clock.set_skew_ms(bad)
        assert clock.wall_ns() - before >= 300 * MS  # a refused value changed nothing
    finally:
        clock.set_skew_ms(0.0)
