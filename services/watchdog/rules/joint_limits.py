"""Rule ``joint_limits``: a setpoint (``servo_jp``) outside the arm's joint limits holds the arm
(message-level fault, tag ``joint_limit``). Limits: the robot model's, rad."""

from __future__ import annotations

import math

from telesurg.services.watchdog.rules import HOLD, Finding, Rule, register
from telesurg.shared.messages import JointSetpoint


def outside_limits(
    names: tuple[str, ...], pos: tuple[float, ...], lower: tuple[float, ...], upper: tuple[float, ...]
) -> str:
    """The joints of ``pos`` outside [``lower``, ``upper``] in words ("" = all within)."""
    if all(lo <= v <= hi for v, lo, hi in zip(pos, lower, upper, strict=True)):
        return ""
    return ", ".join(
        f"{n}={math.degrees(v):.1f}° (limits {math.degrees(lo):.0f}..{math.degrees(hi):.0f}°)"
        for n, v, lo, hi in zip(names, pos, lower, upper, strict=True)
        if not lo <= v <= hi
    )


@register
class JointLimits(Rule):
    """Every setpoint within the joint limits."""

    name = "joint_limits"
    cause = "servo_jp outside joint limits"

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        p = self.arm.policy
        text = outside_limits(self.arm.names, msg.position, p.lower_t, p.upper_t)
        return Finding(HOLD, f"{self.cause}: {text}", "joint_limit") if text else None
