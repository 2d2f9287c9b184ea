"""Rule ``rcm``: in the control modes ``modes`` (default ``trocar``), an RCM error reported by the
slave (``operating_state.rcm_error_mm``) above ``rcm_limit_mm`` holds the arm (message-level
fault)."""

from __future__ import annotations

from dataclasses import dataclass, field

from telesurg.services.watchdog.rules import HOLD, Finding, Rule, register
from telesurg.shared.messages import OperatingState


@dataclass
class RcmSettings:
    """``[watchdog.rules.rcm]``."""

    modes: list[str] = field(default_factory=lambda: ["trocar"])  # slave control modes with an RCM


@register
class Rcm(Rule):
    """The remote centre of motion within ``rcm_limit_mm``."""

    name = "rcm"
    cause = "RCM error over the limit"
    config = RcmSettings

    def on_slave_state(self, msg: OperatingState, now: float) -> Finding | None:
        limit = self.arm.policy.rcm_limit_mm
        if msg.control_mode not in self.cfg.modes or msg.rcm_error_mm <= limit:
            return None
        return Finding(
            HOLD,
            f"RCM error {msg.rcm_error_mm:.2f} mm > limit {limit:.2f} mm "
            f"in {msg.control_mode} mode (way out: remove, docs/trocar.md)",
        )
