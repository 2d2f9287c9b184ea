"""The slave's follow/hold logic, free of I/O so it can be tested on its own.

Rules (safety first — any doubt means hold):

* The slave moves only while a lease from the watchdog allows it and has not expired.
* It tracks ``servo_jp`` only while the setpoint says ``follow`` and is fresh.
* After any hold it resumes only on a new engage: a ``follow=False`` setpoint must be seen before
  a ``follow=True`` one counts, and the first followed setpoint must be close to where the arm is
  (no jump); otherwise the engage is refused with a reason.
* Commanded joints move toward the target no faster than the joint speed limits; a step that is
  too fast is scaled down as a whole (:func:`limit_step`), so the joints stay synchronised and
  the arm keeps to the commanded path in joint space (per-joint clipping would bend it — off the
  trocar's remote centre in trocar mode). Clipping
  reports itself: ``clipped`` counts the cycles in which the limit cut a step, and each clipping
  episode produces an event when it starts (which joint, how far behind) and when it ends.

Ages are judged on two clocks: wall time *and* control cycles executed since the input arrived.
An input is stale (or a lease expired) only when both say so. A slave process that was itself
descheduled for a while therefore does not hold on inputs that are merely waiting in its queue;
a silent input still times out after the same time once the loop runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def limit_step(want: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """``want`` scaled down uniformly so that no joint exceeds its step limit ``lim`` (> 0)."""
    ratio = float(np.max(np.abs(want) / lim))
    if ratio <= 1.0:
        return want
    out: np.ndarray = want / ratio
    return out


@dataclass
class SetpointInterpolator:
    """Turns sparse setpoints (e.g. a 25 Hz console) into a smooth 1 kHz joint reference.

    First-order hold delayed by one setpoint period: when setpoint ``k`` arrives the reference
    moves linearly from where it is to ``k`` over the measured period between setpoints ``k-1`` and
    ``k`` (``period`` clamped to [``min_period``, ``max_period``]). Every output is a convex
    combination of the previous output and an accepted setpoint, so it never leaves the box of
    the joint limits both lie in (no overshoot), and its speed is constant within a period (no
    steps except at setpoint arrivals, bounded by the setpoint increments).

    Attributes:
        min_period: s; shortest interpolation time (faster streams are followed as they come).
        max_period: s; longest (a late setpoint is not spread over the gap).
    """

    min_period: float = 0.001
    max_period: float = 0.1
    _from: np.ndarray | None = None
    _to: np.ndarray | None = None
    _t_to: float = 0.0  # arrival time of _to
    _period: float = 0.0
    _out: np.ndarray | None = None

    def push(self, q: np.ndarray, t: float) -> None:
        """A new setpoint ``q`` arrived at time ``t`` (s)."""
        if self._to is None:
            self._from = self._to = q.copy()
            self._out = q.copy()
            self._t_to = t
            self._period = self.min_period
            return
        self._period = min(max(t - self._t_to, self.min_period), self.max_period)
        self._from = self._out.copy() if self._out is not None else self._to.copy()
        self._to = q.copy()
        self._t_to = t

    def sample(self, t: float) -> np.ndarray | None:
        """Reference at time ``t`` (None before the first setpoint)."""
        if self._to is None or self._from is None:
            return None
        s = min(max((t - self._t_to) / self._period, 0.0), 1.0)
        self._out = self._from + s * (self._to - self._from)
        return self._out

    def reset(self) -> None:
        """Forget the history (after a hold: the next setpoint starts a new segment)."""
        self._from = self._to = self._out = None


@dataclass
class Lease:
    """Latest lease as seen by the slave (times on the local monotonic clock, s).

    ``cycle``/``valid_cycles``: control cycle at reception and lifetime in cycles (None: wall
    time only).
    """

    allow: bool = False
    expires: float = 0.0
    reason: str = "no lease received"
    cycle: int | None = None
    valid_cycles: int = 0


@dataclass
class Setpoint:
    """Latest accepted setpoint (receive time on the local monotonic clock, s; control cycle)."""

    position: np.ndarray
    follow: bool
    received: float
    cycle: int | None = None


@dataclass
class FollowController:
    """Decides each control period what the joints should do.

    Attributes:
        max_velocity: per-joint speed limit, rad/s, shape (n,).
        setpoint_timeout: s; an older setpoint is stale → hold.
        engage_tolerance: rad; the first followed setpoint must be this close to the arm.
    """

    max_velocity: np.ndarray
    setpoint_timeout: float = 0.1
    engage_tolerance: float = 0.02
    following: bool = False
    armed: bool = False  # a follow=False setpoint was seen since the last hold
    holds: int = 0
    lease_valid: bool = False  # the lease verdict of the last update (what the decision used)
    reason: str = "waiting for engage"
    events: list[tuple[str, str]] = field(default_factory=list)  # (kind, text), drained by caller
    clipped: int = 0  # cycles in which the speed limit clipped the step
    clip_quiet_cycles: int = 100  # an episode ends after this many unclipped cycles
    _hold_q: np.ndarray | None = None
    _episode: int = 0  # cycles clipped in the current episode (0: none)
    _episode_lag: float = 0.0  # largest lag behind the target in the episode, rad
    _quiet: int = 0

    def lease_ok(self, lease: Lease, now: float, cycle: int | None = None) -> bool:
        """True while the lease allows motion and has not expired (wall time and cycles)."""
        if not lease.allow:
            return False
        if now < lease.expires:
            return True
        return cycle is not None and lease.cycle is not None and cycle - lease.cycle < lease.valid_cycles

    def _fresh(self, sp: Setpoint | None, now: float, cycle: int | None, dt: float) -> bool:
        if sp is None:
            return False
        if now - sp.received <= self.setpoint_timeout:
            return True
        return cycle is not None and sp.cycle is not None and (cycle - sp.cycle) * dt <= self.setpoint_timeout

    def update(
        self,
        now: float,
        q_meas: np.ndarray,
        q_cmd: np.ndarray,
        lease: Lease,
        sp: Setpoint | None,
        dt: float,
        cycle: int | None = None,
    ) -> np.ndarray:
        """Next commanded joint position (rad) after one period ``dt`` (s) at control ``cycle``."""
        ok = self.lease_valid = self.lease_ok(lease, now, cycle)
        fresh = self._fresh(sp, now, cycle, dt)
        if self.following:
            cause = ""
            if not ok:
                cause = f"lease: {lease.reason}" if not lease.allow else "lease expired"
            elif not fresh:
                cause = "setpoint stream stale"
            elif sp is not None and not sp.follow:
                cause = "clutch released"
            if cause:
                self._hold(q_meas, cause, fault=cause != "clutch released")
        else:
            if sp is not None and fresh and not sp.follow:
                self.armed = True
            if not ok:
                self.reason = f"lease: {lease.reason}" if not lease.allow else "lease expired"
            elif sp is not None and fresh and sp.follow:
                if not self.armed:
                    self.reason = "waiting for a new engage (clutch)"
                else:
                    jump = float(np.max(np.abs(sp.position - q_meas)))
                    if jump > self.engage_tolerance:
                        self.armed = False
                        self.reason = f"engage refused: setpoint {jump:.3f} rad from arm"
                        self.events.append(("engage_refused", self.reason))
                    else:
                        self.following = True
                        self.reason = ""
                        self.events.append(("follow", "following servo_jp"))
            else:
                self.reason = "waiting for engage" if self.armed else self.reason
        if self.following and sp is not None:
            target = sp.position
        else:
            if self._hold_q is None:
                self._hold_q = q_cmd.copy()
            target = self._hold_q
        want = target - q_cmd
        lim = self.max_velocity * dt
        out: np.ndarray = q_cmd + limit_step(want, lim)
        if self.following:
            self._hold_q = None
            self._account_clip(want, lim)
        return out

    def _account_clip(self, want: np.ndarray, lim: np.ndarray) -> None:
        over = np.abs(want) - lim
        j = int(np.argmax(over))
        if over[j] > 1e-12:
            self.clipped += 1
            self._quiet = 0
            lag = float(abs(want[j]))
            if not self._episode:
                self.events.append(
                    ("clipped", f"speed limit clips the setpoint: joint {j + 1} is {lag:.4f} rad behind")
                )
            self._episode += 1
            self._episode_lag = max(self._episode_lag, lag)
        elif self._episode:
            self._quiet += 1
            if self._quiet >= self.clip_quiet_cycles:
                self.events.append(
                    (
                        "clipped",
                        f"speed clipping ended after {self._episode} cycles "
                        f"(largest lag {self._episode_lag:.4f} rad)",
                    )
                )
                self._episode, self._episode_lag, self._quiet = 0, 0.0, 0

    def pause(self, q_meas: np.ndarray, cause: str) -> None:
        """Stop following servo_jp without a fault (another motion source takes over)."""
        if self.following:
            self._hold(q_meas, cause, fault=False)
        self.armed = False
        self.reason = cause

    def track(self, q_cmd: np.ndarray) -> None:
        """Another motion source moved the command to ``q_cmd``: hold there when it stops."""
        self._hold_q = q_cmd.copy()

    def _hold(self, q_meas: np.ndarray, cause: str, *, fault: bool) -> None:
        self.following = False
        self.armed = False
        self.reason = cause
        self._hold_q = q_meas.copy()
        if fault:
            self.holds += 1
        self.events.append(("hold" if fault else "pause", cause))
