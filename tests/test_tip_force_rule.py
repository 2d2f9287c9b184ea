"""The ``tip_force`` safety rule: a tip force above the tissue limit gives DEGRADED, then HOLD,
with the force and the limit in the cause (watchdog logic, no processes)."""

from __future__ import annotations

from telesurg.services.watchdog import WatchdogConfig
from telesurg.services.watchdog.logic import ArmSafety
from telesurg.shared.messages import CartesianWrench, Header, MasterButtons
from telesurg.shared.robots.mh3f.kinematics import MH3F


def wrench(fz: float, ms: float) -> CartesianWrench:
    return CartesianWrench(Header("slave_control", 0, int(ms * 1e6)), "base", (0.0, 0.0, fz), (0.0, 0.0, 0.0))


def arm() -> ArmSafety:
    a = ArmSafety("arm1", WatchdogConfig().policy(), MH3F.joint_names)
    a.on_buttons(MasterButtons(Header("m", 0, 0), True, True))
    return a


def test_tissue_force_within_the_limit_is_ok() -> None:
    a = arm()
    for i in range(100):
        a.on_wrench(wrench(3.9, i * 2.0), i * 0.002)
    assert a.evaluate(0.2).state == "OK"


def test_force_above_the_limit_degrades_then_holds_with_the_cause() -> None:
    a = arm()
    a.on_wrench(wrench(4.5, 0.0), 0.0)
    v = a.evaluate(0.0)
    assert v.state == "DEGRADED" and v.allow
    assert "tip force above the tissue limit: 4.50 N > 4 N" in v.causes[0]
    for i in range(1, 120):  # 4.5 N held for 240 ms at 500 Hz
        a.on_wrench(wrench(4.5, i * 2.0), i * 0.002)
    v = a.evaluate(0.24)
    assert v.state == "HOLD" and not v.allow
    assert any("for 2" in c and "4.50 N > 4 N" in c for c in v.causes), v.causes


def test_a_large_force_holds_at_once() -> None:
    a = arm()
    a.on_wrench(wrench(-7.0, 0.0), 0.0)
    v = a.evaluate(0.0)
    assert v.state == "HOLD" and "7.00 N" in v.causes[0] and "1.5× the limit" in v.causes[0]
