"""The watchdog's verdict for one arm, free of I/O so every rule can be tested on its own.

:class:`ArmSafety` is fed the arm's messages (from zenoh callbacks, under a lock held by the
caller) and, at every lease tick, :meth:`ArmSafety.evaluate` combines them with the causes the
service measured itself (liveliness, stream staleness, loss) into a :class:`Verdict`:

=========  ==================================================================================
state      meaning
=========  ==================================================================================
OK         the arm may move at the operator's scale
DEGRADED   the arm may move, at a reduced motion scale (latency over budget, lossy streams,
           setpoints faster than the joints can follow)
HOLD       the arm must hold; it resumes only after every cause cleared *and* a new engage
ESTOP      latched by an e-stop command; only an explicit reset leaves it (then HOLD rules apply)
=========  ==================================================================================

Faults seen in single messages (a setpoint outside the joint limits, a jump, a target outside
the workspace, the RCM drifting in trocar mode) hold for at least ``fault_latch_ms`` after the
last offending message, so a fault cannot flicker the lease.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from telesurg.shared.messages import EStop, JointSetpoint, MasterButtons, OperatingState

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


def outside_limits(
    names: tuple[str, ...], pos: tuple[float, ...], lower: tuple[float, ...], upper: tuple[float, ...]
) -> str:
    """The joints of ``pos`` outside [``lower``, ``upper``] in words ("" = all within): a fault's
    text. Plain float comparisons first (1 kHz; numpy on 6 values costs ~10× more)."""
    if all(lo <= v <= hi for v, lo, hi in zip(pos, lower, upper, strict=True)):
        return ""
    return ", ".join(
        f"{n}={math.degrees(v):.1f}° (limits {math.degrees(lo):.0f}..{math.degrees(hi):.0f}°)"
        for n, v, lo, hi in zip(names, pos, lower, upper, strict=True)
        if not lo <= v <= hi
    )


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
    """Message-level safety checks and the state decision of one arm (not thread-safe)."""

    arm: str
    policy: Policy
    names: tuple[str, ...]
    estop: str = ""  # latched e-stop cause ("" = none)
    operator_present: bool | None = None
    latency_state: str = "OK"  # OK / DEGRADED / HOLD with hysteresis
    state: str = "HOLD"
    causes: tuple[str, ...] = ("starting",)
    _latched: dict[str, tuple[str, float]] = field(default_factory=dict)  # tag → (text, until)
    # bounded (docs/security.md#bounded-queues): 10 s of samples at 1 kHz, far beyond the 1 s
    # latency window and the velocity window, whatever rate or stamps a publisher sends
    _latency: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=10_000))  # (mono s, ms)
    _history: deque[tuple[int, tuple[float, ...]]] = field(
        default_factory=lambda: deque(maxlen=10_000)
    )  # (src ts ns, q)
    _hold_until: float = 0.0
    _hold_causes: tuple[str, ...] = ()
    counters: dict[str, int] = field(default_factory=dict)
    # forward kinematics (q → tip position, m): followed setpoints are checked against the
    # workspace where the slave would actually put the tip
    tip_of: Callable[[np.ndarray], np.ndarray] | None = None

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

    def on_buttons(self, msg: MasterButtons) -> None:
        """Track operator presence."""
        self.operator_present = msg.operator_present

    def add_latency(self, ms: float, now: float) -> None:
        """One latency sample (ms) observed at ``now`` (monotonic s)."""
        self._latency.append((now, max(0.0, ms)))

    def on_servo(self, msg: JointSetpoint, now: float, rx_wall_ns: int | None = None) -> None:
        """Check one joint setpoint; ``rx_wall_ns`` (same-host clocks) adds a latency sample."""
        if rx_wall_ns is not None and msg.origin_ns > 0:
            self.add_latency((rx_wall_ns - msg.origin_ns) / 1e6, now)
        if msg.names != self.names:
            self._fault("joints", f"servo_jp joint names {list(msg.names)} != {list(self.names)}", now)
            return
        p = self.policy
        pos = msg.position
        text = outside_limits(self.names, pos, p.lower_t, p.upper_t)
        if text:
            self._fault("joint_limit", f"servo_jp outside joint limits: {text}", now)
        if not msg.follow:
            self._history.clear()
            return
        q = np.asarray(pos)
        if self.tip_of is not None:
            self.check_workspace(self.tip_of(q), now)
        # speed on the master's clock when the setpoint carries it (origin_ns): a mapping that
        # caught up after a stall publishes several samples' motion within a few ms, which is
        # not a faster motion
        ts = msg.origin_ns or msg.header.stamp_ns
        if self._history and ts <= self._history[-1][0]:
            return
        hist = self._history
        hist.append((ts, pos))
        span_ns = p.velocity_window_ms * 1e6
        while len(hist) > 2 and ts - hist[1][0] >= span_ns:
            hist.popleft()
        t0, q0 = hist[0]
        if ts - t0 >= span_ns:
            per_s = 1e9 / (ts - t0)
            ratio = [abs(a - b) * per_s / v for a, b, v in zip(pos, q0, p.max_velocity_t, strict=True)]
            worst = max(ratio)
            if worst > 1.0:
                j = ratio.index(worst)
                speed, limit = worst * p.max_velocity_t[j], p.max_velocity_t[j]
                text = f"servo_jp {self.names[j]} at {speed:.2f} rad/s (limit {limit:.2f})"
                if worst > p.velocity_hold_factor:
                    self._fault("jump", f"{text}: a jump, over {p.velocity_hold_factor:g}× the limit", now)
                else:
                    self._latch("speed", f"{text}: the slave clips it", now)

    def check_workspace(self, position: np.ndarray, now: float) -> None:
        """Fault if the tip ``position`` (m, base frame) is outside the workspace box."""
        p = self.policy
        lo, hi = p.workspace_min_mm, p.workspace_max_mm
        mm = [v * 1e3 for v in position.tolist()]
        if not all(a <= v <= b for v, a, b in zip(mm, lo, hi, strict=True)):
            text = ", ".join(
                f"{ax}={v:.0f} mm ({a:.0f}..{b:.0f})"
                for ax, v, a, b in zip("xyz", mm, lo, hi, strict=True)
                if not a <= v <= b
            )
            self._fault("workspace", f"target outside the workspace: {text}", now)

    def on_slave_state(self, msg: OperatingState, now: float) -> None:
        """Check the RCM error reported by the slave in trocar mode."""
        if msg.control_mode == "trocar" and msg.rcm_error_mm > self.policy.rcm_limit_mm:
            self._fault(
                "rcm",
                f"RCM error {msg.rcm_error_mm:.2f} mm > limit {self.policy.rcm_limit_mm:.2f} mm "
                "in trocar mode (way out: remove, docs/trocar.md)",
                now,
            )

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
            # The budget judges p90 and the hard limit the median: a slow link shifts them all,
            # while the tail (p99) on a busy 2-core host is dominated by CPU scheduling, and the
            # burst of queued messages after one stall must not force the arm out of follow (a
            # stall longer than a deadline is caught as stale anyway).
            # Hysteresis: a level is left only 20 % below its threshold.
            ls = self.latency_state
            if p50 > p.latency_limit_ms or (ls == "HOLD" and p50 > 0.8 * p.latency_limit_ms):
                ls = "HOLD"
            elif p90 > p.latency_budget_ms or (ls != "OK" and p90 > 0.8 * p.latency_budget_ms):
                ls = "DEGRADED"
            else:
                ls = "OK"
            self.latency_state = ls
        if self.latency_state == "HOLD":
            hold_causes.append(f"latency p50 {p50:.1f} ms > limit {p.latency_limit_ms:g} ms")
        elif self.latency_state == "DEGRADED":
            degraded_causes.append(f"latency p90 {p90:.1f} ms > budget {p.latency_budget_ms:g} ms")
        if p.require_operator and self.operator_present is False:
            hold_causes.append("operator not present")
        for tag, (text, until) in list(self._latched.items()):
            if now >= until:
                del self._latched[tag]
            elif tag == "speed":
                degraded_causes.append(text)
            else:
                hold_causes.append(text)
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

    def fault(self, tag: str, text: str, now: float) -> None:
        """A message-level fault found by a check outside this class (the commanded joints of
        slave-side motions, :mod:`telesurg.services.watchdog.commanded`): HOLD, latched."""
        self._fault(tag, text, now)

    # -- internals ----------------------------------------------------------------------------
    def _latch(self, tag: str, text: str, now: float) -> None:
        self._latched[tag] = (text, now + self.policy.fault_latch_ms / 1e3)
        self.counters[tag] = self.counters.get(tag, 0) + 1

    def _fault(self, tag: str, text: str, now: float) -> None:
        self._latch(tag, text, now)
