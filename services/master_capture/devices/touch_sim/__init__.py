"""The ``touch_sim`` master device: a simulated Touch-like haptic device held by a simulated hand.

It never met hardware: the device (mass, friction, force limit from the Touch data sheet) and the
operator's hand (a spring-damper following a scripted intent: reach, press, slide, release) are
:mod:`.model`. Unlike the other devices it takes a force: :meth:`TouchSim.write_force` (clamped to
the device's limit, as a real amplifier would). The haptic loop (``docs/haptics.md``) reads its
pose and writes its force every period; ``telesurg bench haptics`` drives it against the MuJoCo
slave.

Example: ``telesurg master-capture --set device=touch_sim --set device_options.press_mm=8``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.services.master_capture.devices.touch_sim.model import HeldDevice, TouchModel, press_and_slide


@dataclass
class TouchSimConfig:
    """``[master_capture.device_options]`` of the touch_sim device."""

    force_limit_n: float = 3.3  # N: the device's force limit (Touch data sheet: 3.3 N peak)
    friction_n: float = 0.1  # N: Coulomb friction (Touch: backdrive friction < 0.26 N)
    hand_stiffness: float = 200.0  # N/m: the simulated hand's grasp stiffness
    hand_damping: float = 3.0  # N·s/m: the simulated hand's grasp damping
    surface_mm: float = -20.0  # mm: where the script expects the tissue (below the start)
    press_mm: float = 11.0  # mm: how far the hand means to press beyond the surface
    slide_mm: float = 20.0  # mm: how far it slides along x while pressing
    step_s: float = 0.001  # s: simulation step (the device's servo period)


@register
class TouchSim(MasterDevice):
    """Simulated Touch + hand; the pedal pressed throughout."""

    name = "touch_sim"
    config = TouchSimConfig

    def __init__(self, cfg: TouchSimConfig) -> None:
        self.cfg = cfg
        model = TouchModel(
            force_limit_n=cfg.force_limit_n,
            friction_n=cfg.friction_n,
            hand_stiffness=cfg.hand_stiffness,
            hand_damping=cfg.hand_damping,
        )
        self.sim = HeldDevice(model, press_and_slide(cfg.surface_mm, cfg.press_mm, cfg.slide_mm))

    def read(self, t: float) -> DeviceSample:
        while self.sim.t + self.cfg.step_s <= t:  # catch the simulation up to t
            self.sim.step(self.cfg.step_s)
        x = self.sim.x
        return DeviceSample((float(x[0]), float(x[1]), float(x[2])), (0.0, 0.0, 0.0, 1.0), True, True)

    def write_force(self, force: np.ndarray) -> np.ndarray:
        """Command the device's force (N, master frame); returns the force applied (≤ the limit)."""
        return self.sim.write_force(force)
