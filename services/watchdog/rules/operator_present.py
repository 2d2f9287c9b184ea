"""Rule ``operator_present``: with ``require_operator``, the arm holds while the master's buttons
say no operator is present (a level: it clears with the next message saying present)."""

from __future__ import annotations

from typing import Any

from telesurg.services.watchdog.rules import HOLD, ArmContext, Finding, Rule, register
from telesurg.shared.messages import MasterButtons


@register
class OperatorPresent(Rule):
    """The operator-presence switch of the master."""

    name = "operator_present"
    cause = "operator not present"

    def __init__(self, arm: ArmContext, cfg: Any) -> None:
        super().__init__(arm, cfg)
        self.present: bool | None = None  # None: no buttons seen yet

    def on_buttons(self, msg: MasterButtons, now: float) -> Finding | None:
        self.present = msg.operator_present
        return None

    def check(self, now: float) -> Finding | None:
        if self.arm.policy.require_operator and self.present is False:
            return Finding(HOLD, self.cause)
        return None
