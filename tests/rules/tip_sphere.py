"""A safety rule from one file: the tip must stay within a sphere around where it first followed.

Load it with ``--plugin tests/rules/tip_sphere.py``; its settings are
``[watchdog.rules.tip_sphere]`` (``--set rules.tip_sphere.radius_mm=15``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from telesurg.services.watchdog.rules import HOLD, ArmContext, Finding, Rule, register
from telesurg.shared.messages import JointSetpoint


@dataclass
class TipSphereConfig:
    """``[watchdog.rules.tip_sphere]``."""

    radius_mm: float = 50.0  # mm: how far the tip may go from its first followed position


@register
class TipSphere(Rule):
    """HOLD while a followed setpoint puts the tip more than ``radius_mm`` from the sphere's centre."""

    name = "tip_sphere"
    cause = "tip left its sphere"
    config = TipSphereConfig

    def __init__(self, arm: ArmContext, cfg: Any) -> None:
        super().__init__(arm, cfg)
        self.centre: np.ndarray | None = None  # m, base frame: the first followed tip position

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        if not msg.follow or self.arm.tip_of is None:
            return None
        tip = self.arm.tip_of(np.asarray(msg.position))
        if self.centre is None:
            self.centre = tip
        mm = float(np.linalg.norm(tip - self.centre)) * 1e3
        if mm <= self.cfg.radius_mm:
            return None
        return Finding(HOLD, f"{self.cause}: {mm:.1f} mm from its centre > {self.cfg.radius_mm:g} mm")
