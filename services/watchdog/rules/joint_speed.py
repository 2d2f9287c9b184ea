"""Rule ``joint_speed``: followed setpoints faster than the joint speed limits, measured over at
least ``velocity_window_ms`` of source time (the master's clock when the setpoint carries it):
above 1× the limit → DEGRADED (tag ``speed``: the slave clips it), above
``velocity_hold_factor`` × → HOLD (tag ``jump``). Both are message-level faults."""

from __future__ import annotations

from collections import deque
from typing import Any

from telesurg.services.watchdog.rules import DEGRADED, HOLD, ArmContext, Finding, Rule, register
from telesurg.shared.messages import JointSetpoint


@register
class JointSpeed(Rule):
    """Setpoint speed against the joint speed limits."""

    name = "joint_speed"
    cause = "servo_jp faster than the joint speed limit"

    def __init__(self, arm: ArmContext, cfg: Any) -> None:
        super().__init__(arm, cfg)
        # bounded (docs/security.md#bounded-queues): far beyond the velocity window at 1 kHz
        self._history: deque[tuple[int, tuple[float, ...]]] = deque(maxlen=10_000)  # (src ts ns, q)

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        if not msg.follow:
            self._history.clear()
            return None
        # a mapping that caught up after a stall publishes several samples' motion within a few
        # ms of its own clock: the master's clock (origin_ns) measures the real motion
        ts = msg.origin_ns or msg.header.stamp_ns
        hist = self._history
        if hist and ts <= hist[-1][0]:
            return None
        p = self.arm.policy
        pos = msg.position
        hist.append((ts, pos))
        span_ns = p.velocity_window_ms * 1e6
        while len(hist) > 2 and ts - hist[1][0] >= span_ns:
            hist.popleft()
        t0, q0 = hist[0]
        if ts - t0 < span_ns:
            return None
        per_s = 1e9 / (ts - t0)
        ratio = [abs(a - b) * per_s / v for a, b, v in zip(pos, q0, p.max_velocity_t, strict=True)]
        worst = max(ratio)
        if worst <= 1.0:
            return None
        j = ratio.index(worst)
        speed, limit = worst * p.max_velocity_t[j], p.max_velocity_t[j]
        text = f"servo_jp {self.arm.names[j]} at {speed:.2f} rad/s (limit {limit:.2f})"
        if worst > p.velocity_hold_factor:
            return Finding(HOLD, f"{text}: a jump, over {p.velocity_hold_factor:g}× the limit", "jump")
        return Finding(DEGRADED, f"{text}: the slave clips it", "speed")
