"""The stamp-age rule of the arm core (issue #17): a lease or setpoint that *arrived* just now
but was *stamped* long ago — what a thawed slave finds in its queue — moves nothing, whatever the
arrival and cycle clocks say; a fresh one still does."""

from __future__ import annotations

import time

import numpy as np
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import ArmCore
from telesurg.shared.messages import Header, JointSetpoint, SafetyLease
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.api import ArmReading

ARM = "arm1"


def _setup() -> tuple[ArmCore, np.ndarray, list[float]]:
    p = arm_profile("mh3f", ARM)
    core = ArmCore(p, np.arange(len(p.joint_names)), SlaveControlConfig(model="mh3f"), 0.001)
    q = np.array(p.home)
    core.start(ArmReading(q, q * 0, q * 0, p))
    return core, q, [100.0]


def _lease(core: ArmCore, stamp_ns: int, seq: int) -> None:
    core.on_lease(SafetyLease(Header("watchdog", seq, stamp_ns), ARM, True, 100.0, ""), "")


def _sp(core: ArmCore, q: np.ndarray, follow: bool, stamp_ns: int, seq: int) -> None:
    p = core.profile
    core.on_setpoint(JointSetpoint(Header("mapping", seq, stamp_ns), p.joint_names, tuple(q), follow), "")


def _run(core: ArmCore, q: np.ndarray, t: list[float], n: int) -> np.ndarray:
    for _ in range(n):
        t[0] += 0.001
        r = ArmReading(q, q * 0, q * 0, core.profile)
        q = core.control(t[0], r)
        core.after_period(core.cycle + 1, r)
    return q


def test_a_fresh_lease_follows_and_an_old_stamped_one_holds_at_once() -> None:
    core, q, t = _setup()
    now = time.time_ns()
    _lease(core, now, 0)
    _sp(core, q, False, now, 0)
    q = _run(core, q, t, 5)
    _sp(core, q, True, time.time_ns(), 1)
    q = _run(core, q, t, 5)
    assert core.ctl.following
    # a freeze: the newest lease (arrival: now, cycle: now) was stamped 2 s ago by the watchdog
    old = time.time_ns() - 2_000_000_000
    _lease(core, old, 1)
    target = q.copy()
    target[0] += 0.05
    _sp(core, target, True, time.time_ns(), 2)  # even a fresh setpoint
    q1 = _run(core, q, t, 20)
    assert not core.ctl.following and "lease expired (stamped" in core.ctl.reason, core.ctl.reason
    assert np.abs(q1 - q).max() < 1e-9  # 0 rad: it held where it was


def test_an_accepted_setpoint_is_not_followed_once_its_stamp_is_old() -> None:
    core, q, t = _setup()
    _lease(core, time.time_ns(), 0)
    _sp(core, q, False, time.time_ns(), 0)
    q = _run(core, q, t, 5)
    stamp = time.time_ns()
    target = q.copy()
    target[0] += 0.001
    _sp(core, q, True, stamp, 1)
    q = _run(core, q, t, 2)
    _sp(core, target, True, stamp, 2)
    assert core.ctl.following
    # the process stops here for longer than setpoint_max_age_ms: the setpoint it holds is old
    assert core.setpoint is not None
    core.setpoint.stamp_ns = stamp - round(core.cfg.setpoint_max_age_ms * 1e6) - 1
    _lease(core, time.time_ns(), 1)  # a fresh lease: only the setpoint's age stops it
    q1 = _run(core, q, t, 20)
    assert not core.ctl.following and core.ctl.reason == "setpoint stream stale"
    assert np.abs(q1 - q).max() < 1e-9
