"""The watchdog's video rule, free of I/O: the surgeon must see what the slave does.

:class:`VideoWatch` is fed every frame's arrival (its age: arrival − capture time) and, at each
lease tick, says whether the video is fresh:

========================================  =========  ==============================================
condition                                 state      effect
========================================  =========  ==============================================
no frame for ``stale_ms``, or the last    DEGRADED   the lease allows motion at ``degraded_scale``
frame older than ``age_budget_ms``
no frame for ``hold_ms``, or the last     HOLD       the arm holds (out of follow until re-engage)
frame older than ``age_limit_ms``, or
the camera service's liveliness token
gone for ``hold_ms``
the camera's token disappears             DEGRADED   at once (SIGKILL is seen in ms, not stale_ms)
========================================  =========  ==============================================

After any non-OK state, OK comes back only once ``fresh_frames`` consecutive frames arrived
within budget: a restarted camera's first frame does not clear the verdict by itself.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class VideoPolicy:
    """Video freshness limits (ms) and the OK-again rule."""

    stale_ms: float = 250.0
    hold_ms: float = 1000.0
    age_budget_ms: float = 150.0
    age_limit_ms: float = 500.0
    fresh_frames: int = 3
    window_s: float = 2.0


@dataclass
class VideoWatch:
    """Frame arrivals of one camera → its verdict (not thread-safe: the caller locks)."""

    policy: VideoPolicy
    started: float  # monotonic s when watching began
    last_rx: float | None = None  # monotonic s of the last frame
    last_age_ms: float = 0.0
    frames: int = 0
    gaps: int = 0
    alive: bool = True
    lost_since: float | None = None  # monotonic s the camera's token disappeared
    state: str = "DEGRADED"  # the verdict of the last evaluate()
    _fresh_run: int = 0  # consecutive frames within budget since the last non-OK verdict
    _ages: deque[tuple[float, float]] = field(default_factory=deque)  # (mono s, age ms)
    _last_seq: int | None = None

    def on_frame(self, seq: int, age_ms: float, now: float) -> None:
        """One frame arrived at ``now`` (monotonic s), ``age_ms`` after its capture."""
        if self._last_seq is not None and seq > self._last_seq + 1:
            self.gaps += seq - self._last_seq - 1
        self._last_seq = seq
        self.frames += 1
        self.last_rx = now
        self.last_age_ms = max(0.0, age_ms)
        self._ages.append((now, self.last_age_ms))
        if self.last_age_ms <= self.policy.age_budget_ms:
            self._fresh_run += 1
        else:
            self._fresh_run = 0

    def on_alive(self, alive: bool, now: float) -> None:
        """The camera service's liveliness token appeared / disappeared."""
        self.alive = alive
        self.lost_since = None if alive else now
        if not alive:
            self._fresh_run = 0

    def since_frame_ms(self, now: float) -> float:
        """ms since the last frame (since watching began, before the first)."""
        return (now - (self.last_rx if self.last_rx is not None else self.started)) * 1e3

    def ages(self, now: float) -> tuple[float, float, float, int]:
        """(p50, p99, fps, samples) of the frame ages over the window ending at ``now``."""
        cutoff = now - self.policy.window_s
        while self._ages and self._ages[0][0] < cutoff:
            self._ages.popleft()
        if not self._ages:
            return 0.0, 0.0, 0.0, 0
        v = np.fromiter((a for _, a in self._ages), float, len(self._ages))
        p50, p99 = np.percentile(v, (50, 99))
        return float(p50), float(p99), len(v) / self.policy.window_s, len(v)

    def evaluate(self, now: float) -> tuple[str, str]:
        """(state ``OK`` / ``DEGRADED`` / ``HOLD``, cause ``""`` when OK) at ``now``."""
        p = self.policy
        since = self.since_frame_ms(now)
        never = self.last_rx is None
        state, cause = "OK", ""
        what = "video never received" if never else f"video stale ({since:.0f} ms"
        if not self.alive and self.lost_since is not None:
            gone = (now - self.lost_since) * 1e3
            state, cause = "DEGRADED", f"camera not alive ({gone:.0f} ms)"
            if gone > p.hold_ms:
                state = "HOLD"
        if since > p.hold_ms:
            state, cause = "HOLD", what if never else f"{what} > hold limit {p.hold_ms:g} ms)"
        elif since > p.stale_ms and state != "HOLD":
            state, cause = "DEGRADED", what if never else f"{what} > {p.stale_ms:g} ms)"
        elif not never and state == "OK":
            if self.last_age_ms > p.age_limit_ms:
                state = "HOLD"
                cause = f"video latency {self.last_age_ms:.0f} ms > limit {p.age_limit_ms:g} ms"
            elif self.last_age_ms > p.age_budget_ms:
                state, cause = (
                    "DEGRADED",
                    f"video latency {self.last_age_ms:.0f} ms > budget {p.age_budget_ms:g} ms",
                )
        if state == "OK" and self.state != "OK" and self._fresh_run < p.fresh_frames:
            state = "DEGRADED"
            cause = f"video recovering ({self._fresh_run}/{p.fresh_frames} fresh frames)"
        elif state != "OK":
            self._fresh_run = 0  # only frames after the last real cause count toward OK
        self.state = state
        return state, cause
