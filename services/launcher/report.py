"""Session recorder for ``telesurg demo --report``: stream counts, gaps, tracking error, holds.

The tracking error compares the slave forceps tip with the *scaled master motion*: while the
slave follows, ``p_slave(t) − scale·R_ms·p_master(t)`` must stay constant (it is the offset the
mapping fixes at engage). The error of a sample is its distance from the median offset of its
engaged segment, after a settling time at the start of the segment. The master position used for
a slave sample is the last master sample published at or before the slave sample's source time
(all processes share the host's wall clock): the slave cannot follow motion the master never
published, e.g. while the master process was descheduled.

A segment ends when the slave's ``follow`` flag drops, which is up to the slave's setpoint
timeout (100 ms) after the master's clutch release; the master moves on meanwhile, so the last
``RELEASE_TRIM_S`` of each segment are not judged.

When the watchdog changes the motion-scale factor (DEGRADED, e.g. over the latency budget), the
mapping re-anchors; the segment is split there and each part uses the scale then in effect.
"""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.shared.bus import Node
from telesurg.shared.messages import (
    CartesianPose,
    JointSetpoint,
    JointState,
    Message,
    OperatingState,
    SafetyEvent,
    SafetyState,
)


@dataclass
class TrackingError:
    """Tip tracking error over the settled, engaged samples, mm."""

    mean_mm: float
    max_mm: float
    samples: int
    segments: int

    def as_dict(self) -> dict[str, Any]:
        """For JSON."""
        return {
            "mean_mm": round(self.mean_mm, 4),
            "max_mm": round(self.max_mm, 4),
            "samples": self.samples,
            "segments": self.segments,
        }


RELEASE_TRIM_S = 0.15  # s: not judged at the end of an engagement (setpoint timeout + margin)


def engaged_segments(follow: list[tuple[int, bool]], trim_end_s: float = 0.0) -> list[tuple[int, int]]:
    """[(t_start_ns, t_end_ns)] where ``follow`` (time-sorted (ns, flag) samples) is True, each
    end moved ``trim_end_s`` earlier (segments that vanish are dropped)."""
    out = []
    start: int | None = None
    for t, f in follow:
        if f and start is None:
            start = t
        elif not f and start is not None:
            out.append((start, t))
            start = None
    if start is not None and follow:
        out.append((start, follow[-1][0]))
    trim = round(trim_end_s * 1e9)
    return [(a, b - trim) for a, b in out if b - trim > a]


def split_by_scale(
    segments: list[tuple[int, int]], factors: list[tuple[int, float]], scale: float
) -> list[tuple[int, int, float, bool]]:
    """Cut engaged segments where the safety scale factor changes.

    Returns (t0, t1, effective scale, starts an engagement) per part; ``factors`` are time-sorted
    (ns, factor) samples of the watchdog's state.
    """
    out = []
    for t0, t1 in segments:
        cuts = [t for t, _ in _changes(factors) if t0 < t < t1]
        bounds = [t0, *cuts, t1]
        for i, (a, b) in enumerate(itertools.pairwise(bounds)):
            out.append((a, b, scale * _factor_at(factors, a), i == 0))
    return out


def _changes(factors: list[tuple[int, float]]) -> list[tuple[int, float]]:
    out: list[tuple[int, float]] = []
    for t, f in factors:
        if not out or out[-1][1] != f:
            out.append((t, f))
    return out


def _factor_at(factors: list[tuple[int, float]], t: int) -> float:
    f = 1.0
    for tf, v in factors:
        if tf > t:
            break
        f = v
    return f


def tracking_error(
    master: np.ndarray,
    slave: np.ndarray,
    segments: list[tuple[int, int]] | list[tuple[int, int, float, bool]],
    scale: float,
    r_ms: np.ndarray,
    settle_s: float = 0.5,
) -> TrackingError:
    """Tracking error of the slave tip against the scaled master motion.

    Args:
        master: (N, 4) rows of (t_ns, x, y, z) master tip, master frame, m.
        slave: (M, 4) rows of (t_ns, x, y, z) slave tip, base frame, m.
        segments: engaged intervals (ns), or (t0, t1, scale, is_engage_start) parts from
            :func:`split_by_scale` (the settle time applies only at an engagement's start).
        scale: mapping motion scale (for plain intervals).
        r_ms: (3, 3) rotation of the master frame in the slave base frame.
        settle_s: s skipped at the start of each segment.
    """
    errors: list[np.ndarray] = []
    used = 0
    if len(master) < 2 or len(slave) == 0:
        return TrackingError(float("nan"), float("nan"), 0, 0)
    for seg in segments:
        t0, t1 = seg[0], seg[1]
        k, settle = (seg[2], seg[3]) if len(seg) == 4 else (scale, True)
        sel = (slave[:, 0] >= t0 + (settle_s * 1e9 if settle else 0.0)) & (slave[:, 0] <= t1)
        sel &= (slave[:, 0] >= master[0, 0]) & (slave[:, 0] <= master[-1, 0])
        if sel.sum() < 10:
            continue
        ts = slave[sel, 0]
        pm = master[np.searchsorted(master[:, 0], ts, side="right") - 1, 1:]
        offset = slave[sel, 1:] - k * pm @ r_ms.T
        errors.append(np.linalg.norm(offset - np.median(offset, axis=0), axis=1))
        used += 1
    if not errors:
        return TrackingError(float("nan"), float("nan"), 0, 0)
    e = np.concatenate(errors) * 1e3
    return TrackingError(float(e.mean()), float(e.max()), int(e.size), used)


@dataclass
class SessionRecorder:
    """Subscribes to one master→slave pair and keeps what a report needs."""

    node: Node
    master_arm: str = "m1"
    slave_arm: str = "arm1"
    lock: threading.Lock = field(default_factory=threading.Lock)
    master: list[tuple[int, float, float, float]] = field(default_factory=list)
    slave: list[tuple[int, float, float, float]] = field(default_factory=list)
    follow: list[tuple[int, bool]] = field(default_factory=list)
    factors: list[tuple[int, float]] = field(default_factory=list)  # watchdog scale factor
    holds: int = 0
    events: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        k = self.node.keys
        self.keys = {
            "master_cp": k.master(self.master_arm, "measured_cp"),
            "servo_jp": k.slave(self.slave_arm, "servo_jp"),
            "measured_js": k.slave(self.slave_arm, "measured_js"),
            "measured_cp": k.slave(self.slave_arm, "measured_cp"),
            "operating_state": k.slave(self.slave_arm, "operating_state"),
        }
        self.node.subscribe(self.keys["master_cp"], CartesianPose, self._on_master)
        self.node.subscribe(self.keys["measured_cp"], CartesianPose, self._on_slave)
        self.node.subscribe(self.keys["servo_jp"], JointSetpoint, self._ignore)
        self.node.subscribe(self.keys["measured_js"], JointState, self._ignore)
        self.node.subscribe(self.keys["operating_state"], OperatingState, self._on_state)
        self.node.subscribe(k.events(), SafetyEvent, self._on_event)
        self.node.subscribe(k.safety(self.slave_arm, "state"), SafetyState, self._on_safety)

    def _ignore(self, msg: Message, key: str) -> None:
        pass  # counted by node.streams

    def _on_master(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            self.master.append((msg.header.stamp_ns, *msg.position))

    def _on_slave(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            self.slave.append((msg.header.stamp_ns, *msg.position))

    def _on_state(self, msg: OperatingState, key: str) -> None:
        with self.lock:
            self.follow.append((msg.header.stamp_ns, msg.follow))
            self.holds = max(self.holds, msg.holds)

    def _on_safety(self, msg: SafetyState, key: str) -> None:
        with self.lock:
            self.factors.append((msg.header.stamp_ns, msg.scale))

    def _on_event(self, msg: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append(f"{msg.header.source} [{msg.arm}] {msg.kind}: {msg.text}")

    def report(self, scale: float, r_ms: np.ndarray) -> dict[str, Any]:
        """Counts, gaps, tracking error, holds, events."""
        with self.lock:
            master = np.array(self.master, dtype=float).reshape(-1, 4)
            slave = np.array(self.slave, dtype=float).reshape(-1, 4)
            follow = sorted(self.follow)
            factors = sorted(self.factors)
            events = list(self.events)
            holds = self.holds
        parts = split_by_scale(engaged_segments(follow, RELEASE_TRIM_S), factors, scale)
        err = tracking_error(master, slave, parts, scale, r_ms)
        streams = {name: self.node.streams.get(key).as_dict() for name, key in self.keys.items()}
        return {
            "streams": streams,
            "tip_tracking_error_mm": err.as_dict(),
            "holds": holds,
            "engagements": sum(1 for e in events if " engage:" in e),
            "events": events[-100:],
        }
