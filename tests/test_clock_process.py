"""Across hosts the watchdog's latency does not trust the hosts' clocks (issue #41, acceptance 4):
master_capture runs with its clock 300 ms off (the software clock's test skew) behind a link with
25 ms each way; the watchdog finds the offset with its clock probes (within 2 ms of the skew: the
latency it judges is then within 2 ms of the true one, sample by sample), and the latency it
publishes matches the one this test measures with the skew it knows (its own receive delay
apart: within 50 ms, where the skew is 300 ms)."""

from __future__ import annotations

import statistics
import threading
import time
from pathlib import Path

import pytest
from telesurg.shared.messages import JointSetpoint, SafetyState
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

SKEW_MS = 300.0
DELAY_MS = 25.0
#: ms: how far this test's own receipt may judge a latency from the watchdog's. The precise bound
#: is the offset's (2 ms); this one tells a corrected latency from a skewed or half-corrected one.
GROSS_MS = 50.0


def test_the_watchdog_latency_is_the_true_one_with_the_masters_clock_300ms_off(tmp_path: Path) -> None:
    overrides = {"master_capture": [f"bus.clock_skew_ms={SKEW_MS}"]}
    with Pipeline(tmp_path, overrides=overrides, mirror=False) as pipe:
        lock = threading.Lock()
        true_ms: list[tuple[float, float]] = []  # (monotonic s, servo_jp age since its master sample)
        reported: list[tuple[float, float, float]] = []  # (monotonic s, p50, clock offset), ms
        skew_ns = round(SKEW_MS * 1e6)

        def on_servo(m: JointSetpoint, key: str) -> None:
            if m.origin_ns > 0:  # this process's clock is the true one; the master's is skewed
                with lock:
                    true_ms.append((time.monotonic(), (time.time_ns() - (m.origin_ns - skew_ns)) / 1e6))

        def on_state(m: SafetyState, key: str) -> None:
            with lock:
                reported.append((time.monotonic(), m.latency_p50_ms, m.clock_offset_ms))

        k = pipe.node.keys
        pipe.node.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, on_servo, sources=["mapping"])
        pipe.node.subscribe(k.safety("arm1", "state"), SafetyState, on_state, sources=["watchdog"])
        assert pipe.wait_following(15.0)
        pipe.delay(DELAY_MS)
        time.sleep(3.0)  # the new delay fills the watchdog's 1 s window; the probes settle
        t0 = time.monotonic()
        time.sleep(5.0)
        with lock:
            truth = [v for t, v in true_ms if t >= t0 - 1.0]  # the window the first report covers
            seen = [(p50, off) for t, p50, off in reported if t >= t0 and p50 > 0]
        assert truth and len(seen) >= 10, (len(truth), len(seen))
        p50_true = statistics.median(truth)
        p50_seen = statistics.median(p50 for p50, _ in seen)
        offset = statistics.median(off for _, off in seen)
        print(
            f"true one-way latency p50 {p50_true:.2f} ms; watchdog p50 {p50_seen:.2f} ms; "
            f"clock offset {offset:+.2f} ms (skew {SKEW_MS:+.0f} ms)"
        )
        # the delay is really on the path (this test's own receipt adds its scheduling delay: a
        # second observer of a 1 kHz stream, 15-18 ms behind the watchdog once in CI)
        assert DELAY_MS <= p50_true < DELAY_MS + GROSS_MS
        # The watchdog's latency of a sample is its receipt − (origin − offset); the true one is
        # receipt − (origin − skew): they differ by exactly offset − skew, sample by sample. So the
        # offset's error bounds the latency's error at the watchdog (acceptance: within 2 ms).
        assert abs(offset - SKEW_MS) < 2.0
        # The truth seen by a second receiver (this test) adds its own scheduling delay on a
        # loaded host (3-18 ms measured in CI): the same latency within that, not a skewed one
        # (300 ms off) nor a half-corrected one (150 ms).
        assert abs(p50_seen - p50_true) < GROSS_MS
        with pipe.p.lock:  # no hold came from the skew: the site followed throughout
            assert not [s for t, s, *_ in pipe.p.safety if t >= t0 * 1e9 and s == "HOLD"]
