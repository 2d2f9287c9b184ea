"""Session recorder for ``telesurg demo --report``: stream counts, gaps, tracking error, holds.

The report judges the slave from what the mapping *published*, never from the mapping's config
(an operator's ``set_scale`` mid-session, or the watchdog's motion-scale factor, change what the
mapping does; its config file does not know):

* The tip tracking error compares the slave forceps tip (``slave/<arm>/measured_cp``) with the
  mapping's Cartesian target (``slave/<arm>/setpoint_cp``, published at the mapping's
  ``target_hz`` while following: a decimated copy of the ``servo_jp`` stream the slave follows).
  The target at a slave sample's source time is interpolated between the two setpoints around it
  (all processes share the host's wall clock); a slave sample between two setpoints further than
  :data:`MAX_REF_GAP_S` apart is not judged. The error of a sample is its distance from the
  median offset of its engaged segment (a constant offset, e.g. a frame convention, is reported
  apart as ``offset_mm``), after a settling time at the start of the segment.
* The motion scales in use are the mapping's :class:`~telesurg.shared.messages.TeleopState`
  (the operator's scale and the watchdog's factor), recorded as the mapping changed them.
* What the operator experienced of the watchdog: its :class:`~telesurg.shared.messages.SafetyState`
  (``safety/<arm>/state``, sent on every change) is followed, and every change *into* HOLD,
  DEGRADED or ESTOP is counted with the causes it carried (:class:`WatchdogTransitions`), beside
  the slave's own fault holds (``OperatingState.holds``). A watchdog HOLD revokes the lease and
  the slave holds too; a DEGRADED arm keeps moving at a reduced scale, so the slave's count does
  not see it. The state received first is the starting point, not a transition.

A segment ends when the slave's ``follow`` flag drops, which is up to the slave's setpoint
timeout (100 ms) after the master's clutch release; the last ``RELEASE_TRIM_S`` of each segment
are not judged.

:func:`tracking_error` also judges against the scaled master motion (``p_slave(t) −
scale·R_ms·p_master(t)`` constant while following) for a caller that knows the scale and the
rotation it set (e.g. a test that configured the site, cutting its segments where the watchdog's
factor changes: the mapping re-anchors there).

The report is strict JSON: a figure that could not be computed is ``null``, never NaN.
"""

from __future__ import annotations

import functools
import logging
import math
import re
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
    TeleopState,
)

log = logging.getLogger(__name__)


@dataclass
class TrackingError:
    """Tip tracking error over the settled, engaged samples, mm."""

    mean_mm: float
    max_mm: float
    samples: int
    segments: int
    offset_mm: float = float("nan")  # mean length of the segments' median offsets

    def as_dict(self) -> dict[str, Any]:
        """For strict JSON (None for a figure that could not be computed)."""
        return {
            "mean_mm": _finite(self.mean_mm),
            "max_mm": _finite(self.max_mm),
            "offset_mm": _finite(self.offset_mm),
            "samples": self.samples,
            "segments": self.segments,
        }


def _finite(v: float, digits: int = 4) -> float | None:
    return round(v, digits) if math.isfinite(v) else None


RELEASE_TRIM_S = 0.15  # s: not judged at the end of an engagement (setpoint timeout + margin)
#: s: two setpoint_cp samples further apart than this are not interpolated between (at 100 Hz:
#: five missed setpoints, e.g. an IK failure holding the target)
MAX_REF_GAP_S = 0.05


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


def tracking_error(
    master: np.ndarray,
    slave: np.ndarray,
    segments: list[tuple[int, int]] | list[tuple[int, int, float, bool]],
    scale: float,
    r_ms: np.ndarray,
    settle_s: float = 0.5,
    *,
    interpolate: bool = False,
) -> TrackingError:
    """Tracking error of the slave tip against a reference motion: the scaled master motion, or
    (``scale`` 1, ``r_ms`` identity, ``interpolate``) the mapping's published target.

    Args:
        master: (N, 4) rows of (t_ns, x, y, z) of the reference: the master tip (master frame)
            or the mapping's setpoint_cp (base frame), m.
        slave: (M, 4) rows of (t_ns, x, y, z) slave tip, base frame, m.
        segments: engaged intervals (ns), or (t0, t1, scale, is_engage_start) parts (e.g. an
            engagement cut where the scale changed; the settle time applies only at an
            engagement's start).
        scale: mapping motion scale (for plain intervals).
        r_ms: (3, 3) rotation of the reference frame in the slave base frame.
        settle_s: s skipped at the start of each segment.
        interpolate: the reference at a slave sample's time is interpolated between the reference
            samples around it (a decimated copy of a faster stream the slave follows, such as
            setpoint_cp of servo_jp), not the last one at or before it; slave samples between two
            reference samples more than :data:`MAX_REF_GAP_S` apart are skipped.
    """
    errors: list[np.ndarray] = []
    offsets: list[float] = []
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
        ts, ps = slave[sel, 0], slave[sel, 1:]
        if interpolate:
            i = np.clip(np.searchsorted(master[:, 0], ts, side="left"), 1, len(master) - 1)
            near = master[i, 0] - master[i - 1, 0] <= MAX_REF_GAP_S * 1e9
            ts, ps, i = ts[near], ps[near], i[near]
            if len(ts) < 10:
                continue
            pm = np.column_stack([np.interp(ts, master[:, 0], master[:, c]) for c in (1, 2, 3)])
        else:
            pm = master[np.searchsorted(master[:, 0], ts, side="right") - 1, 1:]
        offset = ps - k * pm @ r_ms.T
        median = np.median(offset, axis=0)
        errors.append(np.linalg.norm(offset - median, axis=1))
        offsets.append(float(np.linalg.norm(median)))
        used += 1
    if not errors:
        return TrackingError(float("nan"), float("nan"), 0, 0)
    e = np.concatenate(errors) * 1e3
    return TrackingError(float(e.mean()), float(e.max()), int(e.size), used, 1e3 * float(np.mean(offsets)))


#: The watchdog states whose entries are counted: the ones the operator notices (OK is the way back).
WATCHDOG_COUNTED = ("HOLD", "DEGRADED", "ESTOP")
#: Transitions kept in full per arm (the counts cover them all).
MAX_TRANSITIONS = 50
_FIGURES = re.compile(r"\s*\([^)]*\)|\b\d+(?:\.\d+)?\b")


def cause_kind(cause: str) -> str:
    """A watchdog cause without its figures, so the same cause counts once however late the stream
    was: ``"master/m1/measured_cp stale (95 ms > 80 ms)"`` → ``"master/m1/measured_cp stale"``,
    ``"latency p90 105.8 ms > budget 100 ms"`` → ``"latency p90 # ms > budget # ms"``."""
    return _FIGURES.sub(lambda m: "" if m.group(0).lstrip().startswith("(") else "#", cause).strip()


@dataclass
class WatchdogTransitions:
    """The watchdog's state changes of one arm, as its SafetyState stream showed them."""

    state: str | None = None  # the last state received (None before the first)
    initial: str | None = None  # the first state received: the starting point
    entered: dict[str, int] = field(default_factory=lambda: dict.fromkeys(WATCHDOG_COUNTED, 0))
    causes: dict[str, dict[str, int]] = field(default_factory=dict)  # state → cause kind → times
    transitions: list[dict[str, Any]] = field(default_factory=list)  # the last MAX_TRANSITIONS

    def add(self, msg: SafetyState) -> None:
        """Take the next SafetyState of the arm (in the order published)."""
        old, self.state = self.state, msg.state
        if old is None:
            self.initial = msg.state
            return
        if msg.state == old:
            return
        if msg.state in self.entered:
            self.entered[msg.state] += 1
            kinds = self.causes.setdefault(msg.state, {})
            for kind in dict.fromkeys(cause_kind(c) for c in msg.causes) or ("(no cause given)",):
                kinds[kind] = kinds.get(kind, 0) + 1
        self.transitions.append(
            {"t_ns": msg.header.stamp_ns, "from": old, "to": msg.state, "causes": list(msg.causes)}
        )
        del self.transitions[:-MAX_TRANSITIONS]

    def as_dict(self) -> dict[str, Any]:
        """For strict JSON."""
        return {
            "state": self.state,
            "initial": self.initial,
            "entered": dict(self.entered),
            "causes": {s: dict(c) for s, c in self.causes.items()},
            "transitions": [dict(t) for t in self.transitions],
        }

    def summary(self) -> str:
        """One line: ``"2 HOLD, 1 DEGRADED, 0 ESTOP (causes: HOLD: master/m1/measured_cp stale ×2; …)"``."""
        counts = ", ".join(f"{self.entered[s]} {s}" for s in WATCHDOG_COUNTED)
        why = "; ".join(
            f"{s}: " + ", ".join(f"{k} ×{n}" for k, n in sorted(c.items(), key=lambda kv: -kv[1]))
            for s, c in self.causes.items()
        )
        return f"{counts} (causes: {why})" if why else counts


#: s between the recorder's polls of its streams (zenoh buffers POLL_CAPACITY messages a stream:
#: 4 s at 1 kHz)
POLL_S = 0.2


@dataclass
class SessionRecorder:
    """Subscribes to one master→slave pair and keeps what a report needs (its node's own: the
    recorder polls it). :meth:`close` stops the polling thread (the node's end does too)."""

    node: Node
    master_arm: str = "m1"
    slave_arm: str = "arm1"
    mapping_source: str = "mapping"  # the mapping's service id: only its target and state count
    watchdog_source: str = "watchdog"  # the watchdog's service id: only its safety state counts
    lock: threading.Lock = field(default_factory=threading.Lock)
    slave: list[tuple[int, float, float, float]] = field(default_factory=list)
    target: list[tuple[int, float, float, float]] = field(default_factory=list)  # setpoint_cp
    follow: list[tuple[int, bool]] = field(default_factory=list)
    teleop: list[TeleopState] = field(default_factory=list)  # the mapping's, every one received
    holds: int = 0  # the slave's fault holds (OperatingState.holds)
    watchdog: dict[str, WatchdogTransitions] = field(default_factory=dict)  # per slave arm
    events: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        k = self.node.keys
        self.keys = {
            "master_cp": k.master(self.master_arm, "measured_cp"),
            "servo_jp": k.slave(self.slave_arm, "servo_jp"),
            "setpoint_cp": k.slave(self.slave_arm, "setpoint_cp"),
            "measured_js": k.slave(self.slave_arm, "measured_js"),
            "measured_cp": k.slave(self.slave_arm, "measured_cp"),
            "operating_state": k.slave(self.slave_arm, "operating_state"),
            "teleop_state": k.mapping(self.slave_arm, "teleop_state"),
            "safety_state": k.safety(self.slave_arm, "state"),
        }
        mapping = [self.mapping_source] if self.mapping_source else None
        watchdog = [self.watchdog_source] if self.watchdog_source else None
        # the streams (100 Hz – 1 kHz) wait in zenoh's buffer until the recorder's thread polls
        # them: no thread wake-up per message (Node.subscribe ``polled``), half the demo
        # launcher's CPU (docs/performance.md), which the browser drawing the viewer gets instead
        sub = functools.partial(self.node.subscribe, polled=True)
        sub(self.keys["master_cp"], CartesianPose, self._ignore)
        sub(self.keys["measured_cp"], CartesianPose, self._on_slave)
        sub(self.keys["setpoint_cp"], CartesianPose, self._on_target, sources=mapping)
        sub(self.keys["servo_jp"], JointSetpoint, self._ignore)
        sub(self.keys["measured_js"], JointState, self._ignore)
        sub(self.keys["operating_state"], OperatingState, self._on_state)
        self.node.subscribe(
            self.keys["teleop_state"], TeleopState, self._on_teleop, sources=mapping, latest=True
        )
        self.node.subscribe(self.keys["safety_state"], SafetyState, self._on_safety, sources=watchdog)
        self.node.subscribe(k.events(), SafetyEvent, self._on_event)
        self._poll_lock = threading.Lock()
        self._stop = threading.Event()
        self._poller = threading.Thread(target=self._poll_loop, name="report-poll", daemon=True)
        self._poller.start()

    def poll(self) -> int:
        """Take in what the streams buffered since the last poll (the thread does every
        :data:`POLL_S`); returns the count."""
        with self._poll_lock:
            return self.node.poll()

    def _poll_loop(self) -> None:
        while not self._stop.wait(POLL_S):
            try:
                self.poll()
            except Exception as exc:  # the node closed under it: nothing more to take in
                if not self._stop.is_set():
                    log.debug("report: polling ended: %r", exc)
                return

    def close(self) -> None:
        """Stop polling (what arrives afterwards is not counted); idempotent."""
        self._stop.set()
        if self._poller is not threading.current_thread():
            self._poller.join(timeout=2.0)

    def _ignore(self, msg: Message, key: str) -> None:
        pass  # counted by node.streams

    def _on_slave(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            self.slave.append((msg.header.stamp_ns, *msg.position))

    def _on_target(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            self.target.append((msg.header.stamp_ns, *msg.position))

    def _on_state(self, msg: OperatingState, key: str) -> None:
        with self.lock:
            self.follow.append((msg.header.stamp_ns, msg.follow))
            self.holds = max(self.holds, msg.holds)

    def _on_teleop(self, msg: TeleopState, key: str) -> None:
        with self.lock:
            self.teleop.append(msg)

    def _on_safety(self, msg: SafetyState, key: str) -> None:
        with self.lock:
            self.watchdog.setdefault(msg.arm, WatchdogTransitions()).add(msg)

    def _on_event(self, msg: SafetyEvent, key: str) -> None:
        with self.lock:
            self.events.append(f"{msg.header.source} [{msg.arm}] {msg.kind}: {msg.text}")

    def report(self) -> dict[str, Any]:
        """Counts, gaps, tracking error, the mapping's teleop states and scales, the watchdog's
        transitions and the slave's holds, events (strict JSON: ``json.dumps(..., allow_nan=False)``
        holds). Takes in what the streams buffered first (:meth:`poll`)."""
        self.poll()
        with self.lock:
            slave = np.array(self.slave, dtype=float).reshape(-1, 4)
            target = np.array(sorted(self.target), dtype=float).reshape(-1, 4)
            follow = sorted(self.follow)
            teleop = sorted(self.teleop, key=lambda m: m.header.seq)
            events = list(self.events)
            holds = self.holds
            watchdog = {arm: w.as_dict() for arm, w in sorted(self.watchdog.items())}
            summary = "; ".join(f"watchdog [{a}]: {w.summary()}" for a, w in sorted(self.watchdog.items()))
        err = tracking_error(
            target, slave, engaged_segments(follow, RELEASE_TRIM_S), 1.0, np.eye(3), interpolate=True
        )
        streams = {name: self.node.streams.get(key).as_dict() for name, key in self.keys.items()}
        scales: list[dict[str, Any]] = []  # each change of the scales the mapping used
        states: dict[str, int] = {}  # times each teleop state was entered
        for i, m in enumerate(teleop):
            if not scales or (scales[-1]["scale"], scales[-1]["safety_scale"]) != (m.scale, m.safety_scale):
                scales.append(
                    {"since_ns": m.header.stamp_ns, "scale": m.scale, "safety_scale": m.safety_scale}
                )
            if i == 0 or m.since_ns != teleop[i - 1].since_ns:
                states[m.state] = states.get(m.state, 0) + 1
        last = teleop[-1] if teleop else None
        return {
            "streams": streams,
            "tip_tracking_error_mm": err.as_dict(),
            "tracking_reference": "setpoint_cp",
            "mapping": {
                "mode": last.mode if last else None,
                "scale": last.scale if last else None,  # the operator's scale at the end
                "scales": scales,
                "teleop_state": last.state if last else None,
                "teleop_states_entered": states,
            },
            "holds": holds,  # the slave's fault holds
            # per arm: the watchdog's entries into HOLD / DEGRADED / ESTOP and their causes
            "watchdog": watchdog,
            "summary": f"{summary or 'watchdog: no safety state received'}; slave holds: {holds}",
            "engagements": sum(1 for e in events if " engage:" in e),
            "events": events[-100:],
        }
