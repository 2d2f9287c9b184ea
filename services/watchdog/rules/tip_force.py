"""Rule ``tip_force``: the force the tissue exerts on the instrument (``measured_cf``) above the
tissue's force limit → DEGRADED at once (the surgeon is told; the haptic master already pushes
back), HOLD once it has stayed above for ``hold_after_ms`` (or at once above ``hold_factor`` × the
limit). Both are message-level faults (they latch ``fault_latch_ms``), with the force and the limit
in the cause.

The default limit, 4 N, is a conservative round figure below the few-newton forces at which
studies of liver retraction and indentation report parenchymal damage; a site sets its own per
procedure (``--set rules.tip_force.limit_n=2.5``). docs/haptics.md, "Safety".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from telesurg.services.watchdog.rules import DEGRADED, HOLD, ArmContext, Finding, Rule, register
from telesurg.shared.messages import CartesianWrench


@dataclass
class TipForceConfig:
    """``[watchdog.rules.tip_force]``."""

    limit_n: float = 4.0  # N: the tissue-force limit (see the module doc)
    hold_after_ms: float = 200.0  # ms: above the limit this long → HOLD
    hold_factor: float = 1.5  # above this × the limit → HOLD at once


@register
class TipForce(Rule):
    """Tip force against the tissue-force limit."""

    name = "tip_force"
    cause = "tip force above the tissue limit"
    config = TipForceConfig

    def __init__(self, arm: ArmContext, cfg: Any) -> None:
        super().__init__(arm, cfg)
        self.above_since: float | None = None  # monotonic s: when the force went above the limit

    def on_wrench(self, msg: CartesianWrench, now: float) -> Finding | None:
        f = math.sqrt(sum(v * v for v in msg.force))
        limit = self.cfg.limit_n
        if f <= limit:
            self.above_since = None
            return None
        if self.above_since is None:
            self.above_since = now
        text = f"{self.cause}: {f:.2f} N > {limit:g} N"
        held_ms = (now - self.above_since) * 1e3
        if f > self.cfg.hold_factor * limit:
            return Finding(HOLD, f"{text} (over {self.cfg.hold_factor:g}× the limit)", "tip_force_hold")
        if held_ms >= self.cfg.hold_after_ms:
            return Finding(HOLD, f"{text} for {held_ms:.0f} ms", "tip_force_hold")
        return Finding(DEGRADED, text, "tip_force")
