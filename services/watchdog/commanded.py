"""The commanded joints of slave-side motions (``slave/<arm>/setpoint_js``), checked like servo_jp.

Slave-side motions — PTP posture adjustment, jogs, teach playback, insert/remove, direct teach —
are commanded by slave_control itself, not by the mapping, so the watchdog never saw them in
``servo_jp``. While one drives an arm the slave publishes its commanded joints on
``setpoint_js`` (``setpoint_js_hz``, 100 Hz), and :class:`CommandedCheck` holds them to the
rules of followed setpoints (:meth:`~telesurg.services.watchdog.logic.ArmSafety.on_servo`):

* joint names and joint limits;
* speed: faster than ``velocity_hold_factor`` × the joint speed limits over
  ``velocity_window_ms`` (source time) is a jump (the slave rate-limits its commands to 1×);
* the workspace box, by forward kinematics of the commanded joints; as with the keep-out below,
  a motion that starts with the tip outside the box (an arm started there) may move — back in —
  but not further out (the tip's distance outside may not grow by more than
  :data:`FURTHER_OUT_TOL_M`); leaving the box is a fault at once;
* the **patient keep-out** (robots of the trocar family, :mod:`telesurg.shared.robots.mh3f.keepout`):
  the forceps shaft may enter the patient box only through the trocar the slave reports
  (``operating_state.trocar``; none known yet: no entry anywhere). The joint path between two
  consecutive samples is checked at 0.005 rad steps by forward kinematics, so a sweep through
  the patient between two samples is found too. As in the slave's own check, a motion that
  starts with the forceps already crossing the box may move (it must be able to get out), but not
  deeper: the shaft's length inside the box may not grow by more than :data:`DEEPER_TOL_M`.

And the stream itself: while the slave's ``operating_state`` says a slave-side motion drives the
arm (``ENABLED`` and not following ``servo_jp``), ``setpoint_js`` must be fresh — older than the
deadline (``setpoint_js_deadline_ms``, counted from the motion's start at the earliest) is a HOLD
like any stale control stream: a slave that does not publish it (or a site whose router drops
it) would move unchecked.

A violation is a message-level fault of :class:`~telesurg.services.watchdog.logic.ArmSafety`:
HOLD with the reason, for at least ``fault_latch_ms``; the slave stops the motion when the lease
says hold, and the operator must command it again. I/O-free; the caller holds the watchdog's lock.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from telesurg.services.watchdog.logic import ArmSafety, outside_limits
from telesurg.shared.errors import KinematicsError
from telesurg.shared.messages import JointState, OperatingState
from telesurg.shared.robots.mh3f.keepout import PatientBox, path_problem, pose_problem, shaft_inside_m

#: s: samples further apart than this (source time) belong to different motions: the path between
#: them is not checked (the arm held still in between), only each sample.
NEW_MOTION_GAP_S = 0.1
#: m: a pose already crossing the patient box may move (to get out) but its shaft may not go this
#: much deeper into the box.
DEEPER_TOL_M = 0.0005
#: m: a tip already outside the workspace box may move (back in) but not this much further out.
FURTHER_OUT_TOL_M = 0.0005


@dataclass
class CommandedCheck:
    """The watchdog's checks of one arm's ``setpoint_js`` (see the module doc).

    Args:
        safety: the arm's verdict logic; a violation is its fault (HOLD with the reason).
        box_min_mm, box_max_mm: the patient box, base frame, mm; ``None``: the robot has no
            patient keep-out (not the trocar family).
        tip_of: forward kinematics (q → controlled point, m) for the workspace check.
    """

    safety: ArmSafety
    box_min_mm: tuple[float, float, float] | None = None
    box_max_mm: tuple[float, float, float] | None = None
    tip_of: Callable[[np.ndarray], np.ndarray] | None = None
    trocar: tuple[float, float, float] | None = None  # from operating_state (None: not known yet)
    # monotonic s at which the slave's operating_state began to report a slave-side motion (None:
    # it reports none): setpoint_js must be fresh from then on
    motion_since: float | None = None
    checked: int = 0  # setpoint_js samples checked
    faults: int = 0  # samples that found a violation
    _prev: tuple[int, np.ndarray, float, float] | None = None  # (stamp ns, q, shaft in box m, tip out m)
    _history: deque[tuple[int, tuple[float, ...]]] = field(default_factory=lambda: deque(maxlen=1000))

    def on_slave_state(self, msg: OperatingState, now: float) -> None:
        """The trocar the slave uses (the one place the patient may be entered), and whether a
        slave-side motion drives the arm (``ENABLED``, not following ``servo_jp``)."""
        t = msg.trocar
        self.trocar = (float(t[0]), float(t[1]), float(t[2])) if any(t) else None
        moving = msg.state == "ENABLED" and not msg.follow
        if not moving:
            self.motion_since = None
        elif self.motion_since is None:
            self.motion_since = now

    def box(self) -> PatientBox | None:
        """The patient box with the current trocar, or None without a keep-out."""
        lo, hi = self.box_min_mm, self.box_max_mm
        if lo is None or hi is None:
            return None
        return PatientBox(
            (lo[0] / 1e3, lo[1] / 1e3, lo[2] / 1e3), (hi[0] / 1e3, hi[1] / 1e3, hi[2] / 1e3), self.trocar
        )

    def on_setpoint_js(self, msg: JointState, now: float) -> str:
        """Check one sample of commanded joints; the fault's text ("" = none new)."""
        self.checked += 1
        s, p = self.safety, self.safety.policy
        if msg.names != s.names:
            return self._fault("joints", f"setpoint_js joint names {list(msg.names)} != {list(s.names)}", now)
        pos = msg.position
        text = outside_limits(s.names, pos, p.lower_t, p.upper_t)
        if text:
            return self._fault("joint_limit", f"slave-side motion outside joint limits: {text}", now)
        q = np.asarray(pos, dtype=np.float64)
        ts = msg.header.stamp_ns
        prev = self._prev
        if prev is not None and not 0 < ts - prev[0] <= NEW_MOTION_GAP_S * 1e9:
            prev = None  # another motion (or a reordered sample): no path back to the last one
            self._history.clear()
        found = self._speed(ts, pos, now)
        out = 0.0
        if self.tip_of is not None:
            out, text = self._outside(self.tip_of(q))
            # a motion's first sample may be outside (an arm started there); then only back in
            if out > 0.0 and prev is not None and (prev[3] == 0.0 or out > prev[3] + FURTHER_OUT_TOL_M):
                found = self._fault("workspace", f"slave-side motion: tip outside the workspace: {text}", now)
        box = self.box()
        inside = 0.0
        if box is not None:
            try:
                inside = shaft_inside_m(q, box)
                if prev is None:
                    problem = None  # a motion's first sample: it may start crossing (to get out)
                elif prev[2] == 0.0 or pose_problem(prev[1], box) is None:
                    problem = path_problem(prev[1], q, box)  # clear before: the path may not cross
                else:  # crossing already: out, or along, but not deeper
                    grew = inside - prev[2]
                    problem = (
                        f"the forceps would go {grew * 1e3:.1f} mm deeper into the patient outside the trocar"
                        if grew > DEEPER_TOL_M and pose_problem(q, box) is not None
                        else None
                    )
            except KinematicsError as exc:
                problem = f"no forward kinematics: {exc}"
            if problem:
                found = self._fault("keepout", f"slave-side motion: patient keep-out: {problem}", now)
        self._prev = (ts, q, inside, out)
        return found

    def _outside(self, tip: np.ndarray) -> tuple[float, str]:
        """How far [m] the tip ``tip`` (base frame) is outside the workspace box, and where."""
        p = self.safety.policy
        lo, hi = p.workspace_min_mm, p.workspace_max_mm
        mm = [v * 1e3 for v in tip.tolist()]
        gaps = [max(a - v, 0.0, v - b) for v, a, b in zip(mm, lo, hi, strict=True)]
        if not any(gaps):
            return 0.0, ""
        text = ", ".join(
            f"{ax}={v:.0f} mm ({a:.0f}..{b:.0f})"
            for ax, v, a, b, g in zip("xyz", mm, lo, hi, gaps, strict=True)
            if g > 0.0
        )
        return math.sqrt(sum(g * g for g in gaps)) / 1e3, text

    def _speed(self, ts: int, pos: tuple[float, ...], now: float) -> str:
        """The servo_jp speed rule on the commanded joints: only a jump (> hold factor) faults."""
        p = self.safety.policy
        hist = self._history
        hist.append((ts, pos))
        span_ns = p.velocity_window_ms * 1e6
        while len(hist) > 2 and ts - hist[1][0] >= span_ns:
            hist.popleft()
        t0, q0 = hist[0]
        if ts - t0 < span_ns:
            return ""
        per_s = 1e9 / (ts - t0)
        ratio = [abs(a - b) * per_s / v for a, b, v in zip(pos, q0, p.max_velocity_t, strict=True)]
        worst = max(ratio)
        if worst <= p.velocity_hold_factor:
            return ""
        j = ratio.index(worst)
        return self._fault(
            "jump",
            f"slave-side motion {self.safety.names[j]} at {worst * p.max_velocity_t[j]:.2f} rad/s "
            f"(limit {p.max_velocity_t[j]:.2f}): a jump, over {p.velocity_hold_factor:g}× the limit",
            now,
        )

    def _fault(self, tag: str, text: str, now: float) -> str:
        self.faults += 1
        self.safety.fault(tag, text, now)
        return text
