"""The watchdog's verdict for one arm, free of I/O.

:class:`ArmSafety` is fed the arm's messages (from zenoh callbacks, under a lock held by the
caller), runs the registered safety rules on them (:mod:`telesurg.services.watchdog.rules`) and,
at every lease tick, :meth:`ArmSafety.evaluate` combines the rules' verdicts, the command-path
latency and the causes the service measured itself (liveliness, stream staleness, loss) into a
:class:`Verdict`:

=========  ==================================================================================
state      meaning
=========  ==================================================================================
OK         the arm may move at the operator's scale
DEGRADED   the arm may move, at a reduced motion scale (``degraded_scale``)
HOLD       the arm must hold; it resumes only after every cause cleared *and* a new engage
ESTOP      latched by an e-stop command; only an explicit reset leaves it (then HOLD rules apply)
=========  ==================================================================================

A rule's message-level fault holds (or degrades) for at least ``fault_latch_ms`` after the last
offending message; a HOLD lasts at least ``min_hold_ms`` after its causes cleared.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from telesurg.services.watchdog import rules as safety_rules
from telesurg.services.watchdog.rules import HOLD, ArmContext, Finding, Rule
from telesurg.services.watchdog.rules.joint_limits import outside_limits
from telesurg.services.watchdog.rules.workspace import Workspace, outside_box
from telesurg.shared.messages import CartesianWrench, EStop, JointSetpoint, MasterButtons, OperatingState

__all__ = ["STATES", "ArmSafety", "Policy", "Verdict", "outside_limits"]
log = logging.getLogger(__name__)

STATES = ("OK", "DEGRADED", "HOLD", "ESTOP")  # in increasing severity


@dataclass(frozen=True)
class Policy:
    """Limits and budgets of one arm (taken from the watchdog config and the robot model).

    Attributes:
        lower, upper: joint position limits, rad (shape (n,)).
        max_velocity: joint speed limits, rad/s (shape (n,)).
        velocity_hold_factor: a setpoint moving faster than this × the speed limit is a jump →
            HOLD; above 1× it is DEGRADED (the slave clips it).
        velocity_window_ms: setpoint speed is measured over at least this span (source time).
        workspace_min_mm, workspace_max_mm: box the Cartesian target must stay in, base frame.
        rcm_limit_mm: largest RCM error tolerated in trocar mode.
        latency_budget_ms: p90 latency above this → DEGRADED (scale × degraded_scale).
        latency_limit_ms: median (p50) latency above this → HOLD (forced out of follow).
        latency_window_s: window of the latency percentiles.
        latency_min_samples: fewer samples in the window → no latency verdict.
        degraded_scale: motion-scale factor while DEGRADED.
        fault_latch_ms: message-level faults hold at least this long.
        min_hold_ms: a HOLD lasts at least this long after its causes cleared (no flapping lease).
        require_operator: HOLD while the master reports no operator present.
    """

    lower: np.ndarray
    upper: np.ndarray
    max_velocity: np.ndarray
    velocity_hold_factor: float = 2.0
    velocity_window_ms: float = 20.0
    workspace_min_mm: tuple[float, float, float] = (150.0, -600.0, -200.0)
    workspace_max_mm: tuple[float, float, float] = (1100.0, 600.0, 800.0)
    rcm_limit_mm: float = 2.0
    latency_budget_ms: float = 100.0
    latency_limit_ms: float = 250.0
    latency_window_s: float = 1.0
    latency_min_samples: int = 20
    degraded_scale: float = 0.5
    fault_latch_ms: float = 500.0
    min_hold_ms: float = 250.0
    require_operator: bool = True

    @cached_property
    def lower_t(self) -> tuple[float, ...]:
        """``lower`` as floats (per-message checks without numpy)."""
        return tuple(float(v) for v in self.lower)

    @cached_property
    def upper_t(self) -> tuple[float, ...]:
        """``upper`` as floats."""
        return tuple(float(v) for v in self.upper)

    @cached_property
    def max_velocity_t(self) -> tuple[float, ...]:
        """``max_velocity`` as floats."""
        return tuple(float(v) for v in self.max_velocity)


@dataclass(frozen=True)
class Verdict:
    """What the watchdog decided for one arm at one tick."""

    state: str
    causes: tuple[str, ...]
    scale: float
    latency_p50_ms: float
    latency_p90_ms: float
    latency_p99_ms: float
    latency_samples: int

    @property
    def allow(self) -> bool:
        """True if the lease lets the arm move."""
        return self.state in ("OK", "DEGRADED")


@dataclass
class ArmSafety:
    """The registered safety rules and the state decision of one arm (not thread-safe).

    ``rule_settings`` is the watchdog's ``[watchdog.rules]`` table (rule name → its settings).
    """

    arm: str
    policy: Policy
    names: tuple[str, ...]
    estop: str = ""  # latched e-stop cause ("" = none)
    operator_present: bool | None = None
    latency_state: str = "OK"  # OK / DEGRADED / HOLD with hysteresis
    state: str = "HOLD"
    causes: tuple[str, ...] = ("starting",)
    _latched: dict[str, tuple[str, str, float]] = field(default_factory=dict)  # tag → (state, text, until)
    # bounded (docs/security.md#bounded-queues): 10 s of samples at 1 kHz, far beyond the 1 s
    # latency window, whatever rate or stamps a publisher sends
    _latency: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=10_000))  # (mono s, ms)
    _hold_until: float = 0.0
    _hold_causes: tuple[str, ...] = ()
    counters: dict[str, int] = field(default_factory=dict)
    # forward kinematics (q → tip position, m, base frame), for rules that check where the tip goes
    tip_of: Callable[[np.ndarray], np.ndarray] | None = None
    rule_settings: dict[str, dict[str, Any]] = field(default_factory=dict)
    rules: list[Rule] = field(init=False)
    _failed: set[str] = field(default_factory=set)  # rules whose error was logged

    def __post_init__(self) -> None:
        ctx = ArmContext(self.arm, self.policy, self.names, self.tip_of)
        self.rules = safety_rules.make_rules(ctx, self.rule_settings)

    # -- inputs -------------------------------------------------------------------------------
    def on_estop(self, msg: EStop) -> bool:
        """Latch or reset; True if the latch changed."""
        if not msg.applies_to(self.arm):
            return False
        if msg.action == "estop":
            was = self.estop
            self.estop = f"e-stop from {msg.header.source}" + (f": {msg.reason}" if msg.reason else "")
            return not was
        if self.estop:
            self.estop = ""
            return True
        return False

    def on_buttons(self, msg: MasterButtons, now: float | None = None) -> None:
        """Track operator presence; run the rules' ``on_buttons``."""
        self.operator_present = msg.operator_present
        now = time.monotonic() if now is None else now
        for r in self.rules:
            self._found(r, self._ask(r, r.on_buttons, msg, now), now)

    def add_latency(self, ms: float, now: float) -> None:
        """One latency sample (ms) observed at ``now`` (monotonic s)."""
        self._latency.append((now, max(0.0, ms)))

    def on_servo(self, msg: JointSetpoint, now: float, rx_wall_ns: int | None = None) -> None:
        """Run the rules on one joint setpoint; ``rx_wall_ns`` (same-host clocks) adds a latency
        sample. A setpoint for other joints is a fault the rules never see."""
        if rx_wall_ns is not None and msg.origin_ns > 0:
            self.add_latency((rx_wall_ns - msg.origin_ns) / 1e6, now)
        if msg.names != self.names:
            self._fault("joints", f"servo_jp joint names {list(msg.names)} != {list(self.names)}", now)
            return
        for r in self.rules:
            self._found(r, self._ask(r, r.on_servo, msg, now), now)

    def on_wrench(self, msg: CartesianWrench, now: float) -> None:
        """Run the rules on one slave tip wrench."""
        for r in self.rules:
            self._found(r, self._ask(r, r.on_wrench, msg, now), now)

    def on_slave_state(self, msg: OperatingState, now: float) -> None:
        """Run the rules on one slave operating state."""
        for r in self.rules:
            self._found(r, self._ask(r, r.on_slave_state, msg, now), now)

    # -- decision -----------------------------------------------------------------------------
    def latency(self, now: float) -> tuple[float, float, float, int]:
        """(p50, p90, p99, samples) over the window ending at ``now``."""
        lat = self._latency
        cutoff = now - self.policy.latency_window_s
        while lat and lat[0][0] < cutoff:
            lat.popleft()
        if not lat:
            return 0.0, 0.0, 0.0, 0
        v = np.fromiter((x for _, x in lat), float, len(lat))
        p50, p90, p99 = np.percentile(v, (50, 90, 99))
        return float(p50), float(p90), float(p99), len(v)

    def evaluate(
        self, now: float, hold: list[str] | None = None, degraded: list[str] | None = None
    ) -> Verdict:
        """State at ``now`` given the service's own ``hold``/``degraded`` causes."""
        p = self.policy
        hold_causes = list(hold or [])
        degraded_causes = list(degraded or [])
        p50, p90, p99, n = self.latency(now)
        if n >= p.latency_min_samples:
            # p90 against the budget, the median against the hard limit (the tail on a busy host
            # is scheduling); a level is left only 20 % below its threshold
            ls = self.latency_state
            if p50 > p.latency_limit_ms or (ls == "HOLD" and p50 > 0.8 * p.latency_limit_ms):
                ls = "HOLD"
            elif p90 > p.latency_budget_ms or (ls != "OK" and p90 > 0.8 * p.latency_budget_ms):
                ls = "DEGRADED"
            else:
                ls = "OK"
            self.latency_state = ls
        if self.latency_state == "HOLD":
            hold_causes.append(_over("p50", p50, "limit", p.latency_limit_ms))
        elif self.latency_state == "DEGRADED":
            degraded_causes.append(_over("p90", p90, "budget", p.latency_budget_ms))
        for r in self.rules:
            f = self._ask(r, r.check, now)
            if f is not None:
                (hold_causes if f.state == HOLD else degraded_causes).append(f.cause)
        for tag, (level, text, until) in list(self._latched.items()):
            if now >= until:
                del self._latched[tag]
            elif level == HOLD:
                hold_causes.append(text)
            else:
                degraded_causes.append(text)
        if self.estop:
            state, causes = "ESTOP", [self.estop, *hold_causes, *degraded_causes]
        elif hold_causes:
            state, causes = "HOLD", hold_causes + degraded_causes
        elif degraded_causes:
            state, causes = "DEGRADED", degraded_causes
        else:
            state, causes = "OK", []
        if state == "HOLD":
            self._hold_until = now + p.min_hold_ms / 1e3
            self._hold_causes = tuple(hold_causes)
        elif state != "ESTOP" and now < self._hold_until:
            state, causes = "HOLD", [f"clearing: {c}" for c in self._hold_causes] + causes
        scale = p.degraded_scale if state == "DEGRADED" else 1.0
        return Verdict(state, tuple(c[:500] for c in causes[:64]), scale, p50, p90, p99, n)

    def check_workspace(self, position: np.ndarray, now: float) -> None:
        """Fault if the tip ``position`` (m, base frame) is outside the workspace box."""
        p = self.policy
        text = outside_box(position, p.workspace_min_mm, p.workspace_max_mm)
        if text:
            self._fault("workspace", f"{Workspace.cause}: {text}", now)

    def fault(self, tag: str, text: str, now: float) -> None:
        """A message-level fault found by a check outside the rules (the commanded joints of
        slave-side motions, :mod:`telesurg.services.watchdog.commanded`): HOLD, latched."""
        self._fault(tag, text, now)

    # -- internals ----------------------------------------------------------------------------
    def _ask(self, rule: Rule, method: Callable[..., Finding | None], *args: Any) -> Finding | None:
        """``rule.method(*args)``; a rule that raises (or answers nonsense) holds the arm."""
        try:
            f = method(*args)
            if f is None or (isinstance(f, Finding) and f.state in (HOLD, "DEGRADED")):
                return f
            raise TypeError(f"returned {f!r}, not a Finding (HOLD or DEGRADED) or None")
        except Exception as exc:
            if rule.name not in self._failed:
                self._failed.add(rule.name)
                log.exception("%s: safety rule %s failed; holding", self.arm, rule.name)
            return Finding(
                HOLD, f"safety rule {rule.name} failed: {type(exc).__name__}: {exc}", f"{rule.name}!"
            )

    def _found(self, rule: Rule, f: Finding | None, now: float) -> None:
        if f is not None:
            self._latch(f.tag or rule.name, f.state, f.cause, now)

    def _latch(self, tag: str, state: str, text: str, now: float) -> None:
        self._latched[tag] = (state, text, now + self.policy.fault_latch_ms / 1e3)
        self.counters[tag] = self.counters.get(tag, 0) + 1

    def _fault(self, tag: str, text: str, now: float) -> None:
        self._latch(tag, HOLD, text, now)


def _over(stat: str, value: float, name: str, threshold: float) -> str:
    """The latency cause as the operator reads it: over the threshold, or (the 20 % hysteresis)
    under it but not yet back below 80 % of it."""
    if value > threshold:
        return f"latency {stat} {value:.1f} ms > {name} {threshold:g} ms"
    return f"latency {stat} {value:.1f} ms, not yet below {0.8 * threshold:g} ms ({name} {threshold:g} ms)"
