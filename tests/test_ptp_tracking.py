"""Why the measured forceps entered the patient next to the trocar after a posture PTP, and that the
arm now stays on its checked path (issue #20, acceptance 2).

The keep-out process test (``tests/test_keepout_process.py``, seed 20, PTP at 0.8 of the joint
limits) measured the forceps 1.5–1.6 mm inside the torso, 8.4–8.6 mm off the trocar line, in two
runs at one pose: the end of the posture PTP from its program ``r06`` (``START`` below). The
planned path was clear — it ends with the tip 0.7 mm above the slave's keep-out box, the axis
through the trocar — but the PTP ran at constant speed and stopped at once: J5 (1.3 rad in 0.31 s,
at its 30 N·m force limit) lagged 27 mrad behind its command and then overshot the end by 13 mrad,
which tipped the forceps 8 mm off the trocar and 1.6 mm into the torso. Here the slave's own pieces —
:class:`ArmCore` with :class:`TrocarMotions`, its speed limit and commands — drive the MuJoCo MH3F
(1 ms physics, the MJCF's position servos) on one simulated clock, and the patient is judged from
the MJCF like the process test does. The PTP now has a smooth (cosine) profile, and a PTP stopped
under way (``abort``, a lost lease) ramps down along its path over 30 ms instead of freezing its
command (frozen at full speed: 6.5 mrad off the line here, up to 15 mrad over 60 PTPs of that test).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import ArmCore
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.control import Lease
from telesurg.shared.messages import Command, Header
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.mh3f.motions import TrocarMotions
from telesurg.shared.robots.mh3f.trocar import posture_adjust
from test_keepout_process import Patient

DT = 0.001
#: the keep-out process test's program r06 (seed 20): its posture PTP ended in the torso
START = np.array([0.37461, -0.202895, 0.273922, 0.320924, -0.205154, -0.809262])
LEASE = Lease(True, 1e9, "", None, 0)  # valid throughout (no stamp: the stamp-age rule is off)
NO_LEASE = Lease(False, 0.0, "HOLD: test")


def _cmd(name: str, *args: str) -> Command:
    return Command(Header("console", 0, time.time_ns()), "arm1", name, args)


def run(stop: str, stop_at: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """The posture PTP from ``START`` through the slave's core on MuJoCo; ``stop`` ("", "abort",
    "hold") at ``stop_at`` of its duration. (measured joints at every 1 ms, the PTP's target)."""
    cfg = SlaveControlConfig(model="mh3f", robot={"ptp_speed_fraction": 0.8})
    profile = arm_profile("mh3f", "arm1")
    motions = TrocarMotions(cfg, profile)
    core = ArmCore(profile, np.arange(6), cfg, DT, motion=motions)
    measured = []
    with MujocoBackend("mh3f", tuple(START)) as sim:
        reading = core.arm_reading(sim.read())
        core.start(reading)
        ok, reason = motions.command(_cmd("begin_posture_adjust", "method=ptp"))
        assert ok, reason
        assert motions.ptp is not None
        duration = motions.ptp.duration_s
        lease = LEASE
        for i in range(round(seconds / DT)):
            if stop and i == round(stop_at * duration / DT):
                if stop == "abort":
                    assert motions.command(_cmd("abort", "reason=test"))[0]
                else:
                    lease = NO_LEASE
            core.lease = lease
            sim.command(core.control(i * DT, reading))
            sim.step(1)
            reading = core.arm_reading(sim.read())
            core.after_period(i + 1, reading)
            if i % 10 == 0:
                core.measure(reading)
            measured.append(reading.position.copy())
    return np.array(measured), posture_adjust(START, np.array(motions.rcfg.trocar_mm) / 1e3)


def off_line_mrad(q: np.ndarray, q_to: np.ndarray) -> tuple[float, float]:
    """Largest distance (mrad, joint space) of ``q`` from the line START → ``q_to``, and how far
    it went past ``q_to`` along it."""
    d = q_to - START
    u = d / np.linalg.norm(d)
    along = (q - START) @ u
    perp = np.linalg.norm(q - START - np.outer(along, u), axis=1)
    return float(perp.max()) * 1e3, float(along.max() - np.linalg.norm(d)) * 1e3


def test_the_posture_ptp_that_ended_in_the_torso_now_stays_out() -> None:
    q, q_to = run("", 0.0, 1.0)
    pen, _ = Patient().penetration(q)
    off, past = off_line_mrad(q, q_to)
    print(f"in the torso {pen.max() * 1e3:.2f} mm; off the line {off:.2f} mrad, past the end {past:.2f}")
    assert np.abs(q[-1] - q_to).max() < 1e-3  # it got there
    assert pen.max() == 0.0  # (the constant-speed PTP: 1.61 mm deep)
    assert off < 1.0 and past < 1.0  # (constant speed: 6.7 mrad off the line, 13.1 past the end)


@pytest.mark.parametrize("stop", ["abort", "hold"])
def test_a_ptp_stopped_at_full_speed_stays_on_its_path(stop: str) -> None:
    q, q_to = run(stop, 0.5, 0.6)
    off, _ = off_line_mrad(q, q_to)
    moved = np.abs(q[-1] - q[-200]).max()
    print(f"{stop} at full speed: off the line {off:.2f} mrad, at rest {q[-1] - START}")
    assert moved < 1e-4  # it stopped (short of the target)
    assert np.abs(q[-1] - q_to).max() > 0.1
    assert off < 2.0  # (its command frozen at once: 6.5 mrad; constant-speed PTP: 6.7)
