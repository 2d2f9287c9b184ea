"""The slave's RCM guard of slave-side motions with the forceps in the trocar (issue #20).

A motion in trocar mode, an insertion or a removal stops when the measured RCM error exceeds
``RCM_STOP_MM`` or grows more than ``RCM_STOP_SLACK_MM`` above the smallest error measured since
the motion started: a removal that starts off the trocar (the way out of the watchdog's RCM hold)
runs while it does not stray further. The process-level case is
``tests/test_trocar_recovery_process.py`` (state 4) and ``tests/test_keepout_process.py``.
"""

from __future__ import annotations

from telesurg.services.slave_control import SlaveControlConfig
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.mh3f.modes import Frame, Jog, Phase
from telesurg.shared.robots.mh3f.motions import (
    RCM_STOP_MM,
    RCM_STOP_SLACK_MM,
    Internal,
    TrocarMotions,
)


def _motions() -> TrocarMotions:
    return TrocarMotions(SlaveControlConfig(model="mh3f"), arm_profile("mh3f", "arm1"))


def _job(jog: Jog, mode: str, phase: Phase | None) -> Internal:
    return Internal(jog, None, None, False, mode, phase)


def test_a_motion_in_the_trocar_stops_beyond_the_bound() -> None:
    m = _motions()
    job = _job(Jog(Frame.BASE, "x", 1), "trocar", None)
    m.rcm_error_m = 0.2e-3
    assert m.rcm_guard_problem(job) == ""
    m.rcm_error_m = (RCM_STOP_MM - 0.05) * 1e-3  # grown by more than the slack, but under the bound
    assert m.rcm_guard_problem(job) == ""
    m.rcm_error_m = (RCM_STOP_MM + 0.05) * 1e-3
    why = m.rcm_guard_problem(job)
    assert why.startswith("RCM error 1.55 mm > 1.50 mm"), why


def test_a_removal_off_the_trocar_runs_while_it_does_not_stray_further() -> None:
    m = _motions()
    job = _job(Jog(Frame.FORCEPS, "x", -1), "transitional", Phase.REMOVE)
    m.rcm_error_m = 7.7e-3  # left there by the RCM hold
    assert m.rcm_guard_problem(job) == ""
    m.rcm_error_m = 7.5e-3  # less: fine, and the new floor
    assert m.rcm_guard_problem(job) == ""
    m.rcm_error_m = (7.5 + RCM_STOP_SLACK_MM - 0.01) * 1e-3
    assert m.rcm_guard_problem(job) == ""
    m.rcm_error_m = (7.5 + RCM_STOP_SLACK_MM + 0.05) * 1e-3
    assert "> 7.75 mm" in m.rcm_guard_problem(job)
    # a new removal (commanded again) starts from where it is
    assert m.rcm_guard_problem(_job(Jog(Frame.FORCEPS, "x", -1), "transitional", Phase.REMOVE)) == ""


def test_no_guard_outside_the_trocar() -> None:
    m = _motions()
    m.rcm_error_m = 0.05  # the axis far from the trocar: posture adjustment, jogs outside
    assert m.rcm_guard_problem(_job(Jog(Frame.BASE, "z", 1), "non_trocar", None)) == ""
    assert m.rcm_guard_problem(_job(Jog(Frame.JOINT, "j4", 1), "transitional", Phase.POSTURE)) == ""
