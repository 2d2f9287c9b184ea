"""Rule ``workspace``: a followed setpoint whose tip (forward kinematics, base frame) is outside the
box ``workspace_min_mm`` … ``workspace_max_mm`` holds the arm (message-level fault)."""

from __future__ import annotations

import numpy as np
from telesurg.services.watchdog.rules import HOLD, Finding, Rule, register
from telesurg.shared.messages import JointSetpoint


def outside_box(position_m: np.ndarray, lo: tuple[float, ...], hi: tuple[float, ...]) -> str:
    """The axes of ``position_m`` (m) outside the box [``lo``, ``hi``] (mm) in words ("" = inside)."""
    mm = [v * 1e3 for v in position_m.tolist()]
    if all(a <= v <= b for v, a, b in zip(mm, lo, hi, strict=True)):
        return ""
    return ", ".join(
        f"{ax}={v:.0f} mm ({a:.0f}..{b:.0f})"
        for ax, v, a, b in zip("xyz", mm, lo, hi, strict=True)
        if not a <= v <= b
    )


@register
class Workspace(Rule):
    """The tip of every followed setpoint inside the workspace box."""

    name = "workspace"
    cause = "target outside the workspace"

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        tip_of = self.arm.tip_of
        if not msg.follow or tip_of is None:
            return None
        p = self.arm.policy
        text = outside_box(tip_of(np.asarray(msg.position)), p.workspace_min_mm, p.workspace_max_mm)
        return Finding(HOLD, f"{self.cause}: {text}") if text else None
