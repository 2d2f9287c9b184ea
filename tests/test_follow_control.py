"""The slave's follow/hold rules (telesurg.services.slave_control.control), without I/O."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from telesurg.services.slave_control.control import FollowController, Lease, Setpoint

VMAX = np.full(6, 2.0)
DT = 0.001


def make() -> tuple[FollowController, np.ndarray, Lease]:
    return FollowController(VMAX), np.zeros(6), Lease(True, 1e9, "")


def test_needs_follow_edge_then_tracks_rate_limited() -> None:
    ctl, q, lease = make()
    target = np.full(6, 0.01)
    q = ctl.update(0.0, q, q, lease, Setpoint(target, True, 0.0), DT)
    assert not ctl.following and "engage" in ctl.reason  # no False seen yet: no follow
    ctl.update(0.0, q, q, lease, Setpoint(np.zeros(6), False, 0.0), DT)
    q2 = ctl.update(0.0, q, q, lease, Setpoint(target, True, 0.0), DT)
    assert ctl.following
    np.testing.assert_allclose(q2, VMAX * DT)  # limited to max speed × dt


def test_lease_expiry_and_revocation_hold() -> None:
    ctl, q, lease = make()
    ctl.update(0.0, q, q, lease, Setpoint(q, False, 0.0), DT)
    ctl.update(0.0, q, q, lease, Setpoint(q, True, 0.0), DT)
    assert ctl.following
    moved = np.full(6, 0.05)
    out = ctl.update(0.05, moved, moved, Lease(False, 1e9, "mapping not alive"), Setpoint(q, True, 0.05), DT)
    assert not ctl.following and ctl.holds == 1 and "mapping not alive" in ctl.reason
    np.testing.assert_allclose(out, moved)  # holds where it is, ignores the setpoint
    ctl2, q, _ = make()
    ctl2.update(0.0, q, q, Lease(True, 0.05, ""), Setpoint(q, False, 0.0), DT)
    ctl2.update(0.01, q, q, Lease(True, 0.05, ""), Setpoint(q, True, 0.01), DT)
    ctl2.update(0.06, q, q, Lease(True, 0.05, ""), Setpoint(q, True, 0.06), DT)
    assert not ctl2.following and ctl2.reason == "lease expired"


def test_resume_after_hold_needs_new_engage_and_no_jump() -> None:
    ctl, q, lease = make()
    ctl.update(0.0, q, q, lease, Setpoint(q, False, 0.0), DT)
    ctl.update(0.0, q, q, lease, Setpoint(q, True, 0.0), DT)
    ctl.update(0.2, q, q, lease, Setpoint(q, True, 0.0), DT)  # stale setpoint
    assert not ctl.following and ctl.reason == "setpoint stream stale"
    ctl.update(0.3, q, q, lease, Setpoint(q, True, 0.3), DT)
    assert not ctl.following  # follow=True continuing is not a new engage
    ctl.update(0.3, q, q, lease, Setpoint(q, False, 0.3), DT)
    far = np.full(6, 0.5)
    out = ctl.update(0.3, q, q, lease, Setpoint(far, True, 0.3), DT)
    assert not ctl.following and "engage refused" in ctl.reason
    np.testing.assert_allclose(out, q)


def test_speed_limit_scales_the_whole_step_so_the_joints_stay_synchronised() -> None:
    ctl, q, lease = make()
    ctl.update(0.0, q, q, lease, Setpoint(q, False, 0.0), DT)
    target = np.zeros(6)
    target[1], target[2] = 0.01, 0.002  # joint 2 is over its 2 mrad step limit, joint 3 is not
    out = ctl.update(0.0, q, q, lease, Setpoint(target, True, 0.0), DT)
    np.testing.assert_allclose(out[1:3], [0.002, 0.0004])  # both scaled by 1/5: same direction
    assert ctl.clipped == 1


def test_speed_clipping_is_counted_and_reported() -> None:
    ctl, q, lease = make()
    ctl.clip_quiet_cycles = 5
    ctl.update(0.0, q, q, lease, Setpoint(q, False, 0.0), DT)
    target = np.zeros(6)
    target[1] = 0.01  # 10 mrad ahead: 5 cycles at 2 mrad per cycle
    for _ in range(12):
        q = ctl.update(0.0, q, q, lease, Setpoint(target, True, 0.0), DT)
    assert ctl.following and ctl.clipped == 4  # the 5th step lands exactly
    kinds = [k for k, _ in ctl.events]
    texts = [t for k, t in ctl.events if k == "clipped"]
    assert kinds.count("clipped") == 2
    assert "joint 2" in texts[0] and "0.0100 rad behind" in texts[0]
    assert "ended after 4 cycles" in texts[1]


def test_interpolator_is_smooth_between_sparse_jittery_setpoints_and_never_overshoots() -> None:
    from telesurg.services.slave_control.control import SetpointInterpolator

    rng = np.random.default_rng(3)
    ip = SetpointInterpolator()
    assert ip.sample(0.0) is None
    values = [0.0, 0.1, 0.3, 0.3, -0.2, -0.2, 0.05]
    arrivals = [k * 0.04 + 0.002 + rng.uniform(0.0, 0.012) for k in range(len(values))]  # jitter
    out, k = [], 0
    for i in range(int(0.04 * len(values) / 0.001) + 80):  # 1 kHz
        t = i * 0.001
        while k < len(values) and arrivals[k] <= t:
            ip.push(np.array([values[k]]), k * 0.04, arrivals[k])  # source time: exact 40 ms
            k += 1
        v = ip.sample(t)
        if v is not None:
            out.append(float(v[0]))
    a = np.array(out)
    assert a.min() >= -0.2 - 1e-12 and a.max() <= 0.3 + 1e-12  # within the setpoints' range
    assert a[-1] == 0.05  # ran dry: holds the last setpoint
    steps = np.abs(np.diff(a))
    assert steps.max() <= 0.5 / 40 + 1e-9  # the largest increment spread over its 40 ms
    # constant speed between setpoints despite the arrival jitter: the speed changes only at
    # the (source-timed) setpoint instants, not where packets happened to arrive
    assert np.count_nonzero(np.abs(np.diff(steps)) > 1e-9) <= 2 * len(values)
    ip.push(np.array([9.0]), 0.0, 1.0)  # older than the newest: ignored
    assert ip.sample(10.0)[0] == 0.05  # type: ignore[index]


def test_interpolator_pause_resumes_on_the_path_and_catches_up() -> None:
    """A stall of the arm's loop (``pause``) and a dry buffer shift the timeline back: the
    reference goes on along the setpoints where it stopped, never across to the newest one; with
    ``catchup`` it then plays faster until the delay is made up, without a jump."""
    from telesurg.services.slave_control.control import SetpointInterpolator

    ip = SetpointInterpolator(catchup=1.25, window=300)
    period = 0.004  # 250 Hz source: one setpoint per 4 ms, a ramp of 1 rad/s
    out: list[float] = []
    k = 0
    t = 0.0
    stall = (0.3, 0.4)  # the arm held its command through this (s, local clock)
    while t < 2.0:
        while k * period + 0.001 <= t:
            ip.push(np.array([k * period]), k * period, k * period + 0.001)
            k += 1
        if stall[0] <= t < stall[1]:
            t = stall[1]
            ip.pause(stall[1] - stall[0])
            continue
        v = ip.sample(t)
        if v is not None:
            out.append(float(v[0]))
        t = round(t + 0.001, 6)
    a = np.array(out)
    steps = np.diff(a)
    assert steps.min() >= -1e-12  # never back
    assert steps.max() <= 1.25e-3 + 1e-9  # at most the catch-up speed: no jump after the stall
    i = round(stall[0] / 0.001) - 1  # (no output at t = 0)
    assert a[i] - a[i - 1] <= 1.25e-3 + 1e-9  # resumed where it stopped
    assert ip.behind == 0.0  # 100 ms made up at 0.25 s/s within 0.4 s
    # last sample at 1.999 s: 1 ms transport and the buffer delay behind the source, as before the stall
    assert a[-1] == pytest.approx(1.999 - 0.001 - ip.delay, abs=1e-9)


def test_interpolator_thawed_process_never_steps_back_along_the_path() -> None:
    """A frozen slave process: the setpoints queued through a 117 ms stall all arrive at the thaw
    and are pushed before the first missed period's reference is sampled (at that period's time,
    as slave_control.run does). The stall must not be counted twice: the reference resumes where
    it stopped (it stepped back ~110 ms of motion before: a speed-clipped jump off the RCM)."""
    from telesurg.services.slave_control.control import SetpointInterpolator

    ip = SetpointInterpolator(catchup=1.25, window=300)
    period, k, out = 0.004, 0, []
    for n in range(2, 300):  # 0.3 s of 1 kHz samples of a 1 rad/s ramp sent at 250 Hz
        t = n * 0.001
        while k * period + 0.001 <= t:
            ip.push(np.array([k * period]), k * period, k * period + 0.001)
            k += 1
        out.append(float(ip.sample(t)[0]))  # type: ignore[index]
    t_stop, t_wake = 0.3, 0.417
    while k * period + 0.001 <= t_wake:  # queued through the stall: all "arrive" at the thaw
        ip.push(np.array([k * period]), k * period, t_wake)
        k += 1
    out.append(float(ip.sample(t_stop)[0]))  # type: ignore[index]  # the first missed period
    ip.pause(0.117 - 0.020)  # held its command through all but the last 20 periods
    for n in range(398, 1200):
        t = n * 0.001
        while k * period + 0.001 <= t:
            ip.push(np.array([k * period]), k * period, k * period + 0.001)
            k += 1
        out.append(float(ip.sample(t)[0]))  # type: ignore[index]
    steps = np.diff(np.array(out))
    assert steps.min() >= -1e-12  # never back
    assert steps.max() <= 1.25e-3 + 1e-9  # no jump: at most the catch-up speed
    assert ip.behind == pytest.approx(0.0, abs=1e-9)  # made up by 1.2 s


@pytest.mark.parametrize("speed", [0.1, 0.8])
def test_interpolator_catchup_stays_within_the_speed_bound(speed: float) -> None:
    """With ``max_speed`` the catch-up is as fast as ``catchup`` allows on a slow motion and no
    faster than the bound on a fast one (the arm's follow controller never clips it)."""
    from telesurg.services.slave_control.control import SetpointInterpolator

    ip = SetpointInterpolator(0.1, window=300, catchup=2.0, max_speed=np.array([1.0]))
    period, k, out, made_up, n = 0.004, 0, [], None, 1
    while n < 3000:
        t = n * 0.001
        while k * period + 0.001 <= t:
            ip.push(np.array([speed * k * period]), k * period, k * period + 0.001)
            k += 1
        out.append(float(ip.sample(t)[0]))  # type: ignore[index]
        if n == 500:
            ip.pause(0.2)  # the arm held its command through a 200 ms stall
            n += 200
        elif n > 700 and made_up is None and ip.behind == 0.0:
            made_up = (n - 700) * 0.001
        n += 1
    steps = np.diff(np.array(out))
    assert steps.max() <= min(2.0 * speed, 1.0) * 1e-3 + 1e-9 and steps.min() >= -1e-12
    assert made_up is not None
    # 200 ms made up at (rate - 1) s/s: 2x on the slow ramp, 1/0.8 = 1.25x on the fast one
    rate = 2.0 if speed < 0.5 else 1.25
    assert made_up == pytest.approx(0.2 / (rate - 1.0), abs=0.01)


def test_interpolator_without_catchup_keeps_the_shift() -> None:
    from telesurg.services.slave_control.control import SetpointInterpolator

    ip = SetpointInterpolator()
    ip.push(np.array([0.0]), 0.0, 0.001)
    ip.push(np.array([0.004]), 0.004, 0.005)
    ip.sample(0.01)
    ip.pause(0.05)
    assert ip.behind == pytest.approx(0.05)
    ip.sample(1.0)
    assert ip.behind == pytest.approx(0.05)


def _interpolate_a_rough_stream(seed: int) -> tuple[float, float, float]:
    """A 1 rad/s ramp sampled at 250 Hz with back-to-back samples and source stalls, delivered
    with jittery latency and transport freezes (bursts), sampled at 1 kHz by a loop that stalls
    (whole-process freezes, ordered as slave_control.run orders them) or polls a period late.
    (largest step per period, most negative step, shift left at the end)."""
    from telesurg.services.slave_control.control import SetpointInterpolator

    rng = np.random.default_rng(seed)
    ip = SetpointInterpolator(0.1, window=300, catchup=1.25)
    ts_list, t = [], 0.0
    while t < 6.0:
        r = rng.random()
        t += rng.uniform(0.0, 1e-4) if r < 0.05 else rng.uniform(0.02, 0.3) if r < 0.08 else 0.004
        ts_list.append(t)
    ts = np.array(ts_list)
    arr = ts + 0.001 + rng.exponential(0.002, ts.size)
    for _ in range(6):  # transport freezes: what was sent meanwhile arrives at their end
        a, d = rng.uniform(0, 6), rng.uniform(0.02, 0.6)
        arr = np.where((arr > a) & (arr < a + d), a + d, arr)
    arr = np.maximum.accumulate(arr)
    stalls = {round(float(rng.uniform(0.2, 6.0)), 3): float(rng.uniform(0.02, 0.5)) for _ in range(6)}
    i, t_loc, out = 0, 0.0, []
    while t_loc < 6.5:
        if stall := stalls.get(round(t_loc, 3), 0.0):
            missed = int(stall / 0.001)
            t_wake = t_loc + missed * 0.001
            while i < ts.size and arr[i] <= t_wake:  # all "arrive" at the thaw
                ip.push(np.array([ts[i]]), ts[i], t_wake)
                i += 1
            got = [ip.sample(t_loc)]
            held = max(0, missed - 20)
            ip.pause(held * 0.001)
            got += [ip.sample(t_loc + p * 0.001) for p in range(held + 1, missed + 1)]
            t_loc = t_wake + 0.001
        else:
            late_poll = rng.random() < 0.02  # (a starved loop thread: what arrived waits a period)
            while not late_poll and i < ts.size and arr[i] <= t_loc:
                ip.push(np.array([ts[i]]), ts[i], arr[i])
                i += 1
            got = [ip.sample(t_loc)]
            t_loc += 0.001
        out += [float(v[0]) for v in got if v is not None]
    steps = np.diff(np.array(out))
    return float(steps.max()), float(steps.min()), ip.behind


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=40, deadline=None)
def test_interpolator_never_jumps_on_a_rough_stream(seed: int) -> None:
    """Whatever the arrival pattern and loop stalls, the reference moves along the path at most at
    the catch-up speed and never back (found by this test: a dry buffer resumed ahead, a long first
    gap started part-way along it, a timeline behind by more than the window skipped ahead, a
    setpoint pushed a period after it arrived resumed a dry buffer part-way)."""
    fastest, back, _ = _interpolate_a_rough_stream(seed)
    assert fastest <= 1.25e-3 + 1e-9 and back >= -1e-12


@given(st.integers(0, 2**32 - 1))
@settings(max_examples=30, deadline=None)
def test_interpolator_catchup_never_plays_a_segment_too_fast(seed: int) -> None:
    """Segments of mixed speeds (0.05 or 0.7 of the bound, as the mapping's clamped trocar steps)
    at 250 Hz, in bursts (a stalled mapping or master: samples 20 µs apart) and with gaps, sampled
    at 1 kHz by a loop that stalls and catches up at up to 2×: no period plays faster than
    ``max_speed`` (the rate is judged on every segment the period may reach, not only the first:
    a slow segment followed by a burst of fast ones was played at 2 × 0.7)."""
    from telesurg.services.slave_control.control import SetpointInterpolator

    rng = np.random.default_rng(seed)
    ip = SetpointInterpolator(0.1, window=300, catchup=2.0, max_speed=np.array([1.0]))
    ts, qs, t, q = [], [], 0.0, 0.0
    while t < 4.0:
        r = rng.random()
        dt = 2e-5 if r < 0.3 else rng.uniform(0.02, 0.2) if r < 0.33 else 0.004
        t += dt
        q += (0.7 if rng.random() < 0.5 else 0.05) * min(dt, 0.012)
        ts.append(t)
        qs.append(q)
    arr = np.maximum.accumulate(np.array(ts) + 0.001)
    i, t_loc, out = 0, 0.0, []
    stalls = {round(float(rng.uniform(0.2, 4.0)), 3): float(rng.uniform(0.03, 0.2)) for _ in range(8)}
    while t_loc < 4.2:
        while i < len(ts) and arr[i] <= t_loc:
            ip.push(np.array([qs[i]]), ts[i], arr[i])
            i += 1
        v = ip.sample(t_loc)
        if v is not None:
            out.append(float(v[0]))
        if stall := stalls.get(round(t_loc, 3), 0.0):
            ip.pause(stall)  # (held through the stall: the next period plays 1 ms of motion)
            t_loc += stall
        t_loc = round(t_loc + 0.001, 6)
    steps = np.diff(np.array(out))
    assert steps.max() <= 1.0e-3 * (1 + 1e-3) and steps.min() >= -1e-12  # (1e-3: the clock's rounding)
