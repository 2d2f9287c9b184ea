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
* A followed step the arm's keep-out refuses (:attr:`FollowController.keepout`: the patient's
  body, ``shared/kinematics/keepout.py``) is clamped at the surface: the command goes only as far
  as allowed and waits there while the setpoints stay beyond it. ``keepout_clamped`` counts those
  cycles; each episode is an event (``keepout_clamped``) when it starts (why, where) and when it
  ends, as the mapping reports its workspace clamp.

Ages are judged on two clocks: wall time *and* control cycles executed since the input arrived.
An input is stale (or a lease expired) only when both say so. A slave process that was itself
descheduled for a while therefore does not hold on inputs that are merely waiting in its queue;
a silent input still times out after the same time once the loop runs.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from telesurg.shared.limits import limit_step

#: Follow-controller event kinds published as warnings.
WARN = frozenset({"hold", "clipped", "engage_refused", "keepout_clamped"})

#: A followed step clamped by the keep-out: (q_from, q_to) → (the joints allowed, why clamped or "").
Keepout = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, str]]


@dataclass
class SetpointInterpolator:
    """Turns sparse setpoints (e.g. a 25 Hz console) into a smooth 1 kHz joint reference.

    A jitter buffer on the *source* clock: every setpoint carries the time it was sampled at the
    source (the master's stamp, ``origin_ns``), and the reference replays that timeline, linearly
    interpolated between consecutive setpoints, ``delay`` behind the second setpoint's arrival
    (``delay`` = 1.5 source periods, at most ``max_period``). Arrival jitter up to half a period
    therefore does not reach the motion, and the clocks need not agree (only their offset counts,
    fixed when the timeline starts). The playback clock runs at the local clock's rate and never
    jumps: if the buffer runs dry (the stream stalled) the reference holds the last setpoint and,
    when setpoints come again, resumes from there (the timeline shifts by the stall).

    The played source time never goes backward (a shift counted from an arrival time ahead of the
    sampled time, e.g. setpoints queued through a freeze of the whole process and "arriving" at the
    thaw, resumes where the playback stopped instead of stepping back along the path).

    Every output is a convex combination of two consecutive accepted setpoints, so it never leaves
    the box of the joint limits they lie in (no overshoot); its speed is constant between
    setpoints (no steps); it never extrapolates. :meth:`reset` starts a new timeline (engage).

    **Catch-up.** The timeline shifts back by every stall (the buffer ran dry, or the arm held its
    command through a stall of its own loop: :meth:`pause`), so the reference goes on along the
    setpoints' path from where it stopped instead of cutting across to the newest one. With
    ``catchup`` > 1 the playback clock then runs that much faster than the local clock until the
    shift is made up, so a stall does not add latency for the rest of the engagement (the
    reference's speed is the source's × ``catchup`` meanwhile; 1 = never catch up). With
    ``max_speed`` the rate is also bounded so that the played speed of every coordinate stays
    within it (a slow motion is made up at ``catchup``, a fast one no faster than the arm can go:
    the follow controller never clips it), and never below 1.

    How far the timeline runs behind (:attr:`behind`) is for the caller to bound: the arm holds
    when it exceeds its limit (``follow_max_lag_ms``; a host that stalls more than the catch-up
    makes up would otherwise let the slave fall ever further behind the master).

    Attributes:
        max_period: s; the longest delay.
        window: setpoints kept (more while the timeline runs behind them, up to 4 windows).
        catchup: playback rate (× the local clock) while the timeline runs behind its start, at most.
        max_speed: per-coordinate speed bound of the catch-up playback (units/s; None: none).
    """

    max_period: float = 0.1
    window: int = 50
    catchup: float = 1.0
    max_speed: np.ndarray | None = None
    _pts: list[tuple[float, np.ndarray]] = field(default_factory=list)  # (source time s, q)
    _offset: float | None = None  # local time - source time of the playback clock, s
    _delay: float = 0.0
    _shift: float = 0.0  # s the timeline was shifted back by stalls and has not yet made up
    _t_last: float | None = None  # local time of the last sample, s
    _tp_last: float | None = None  # source time the last sample played, s (None: none yet)
    played: float = 0.0  # source time (s) of the reference the last sample returned (0: none yet)

    def push(self, q: np.ndarray, t_source: float, t_arrival: float) -> None:
        """A setpoint ``q`` sampled at ``t_source`` (source clock, s) arrived at ``t_arrival``."""
        pts = self._pts
        if pts and t_source <= pts[-1][0]:
            return  # duplicate or reordered: the timeline only moves forward
        # the reference held what it plays at least until the last sample: a resume or a start
        # is counted from then (a setpoint that arrived before that sample and is pushed only now,
        # e.g. while the loop thread was starved, would otherwise resume part-way: a step)
        t_held = t_arrival if self._t_last is None else max(t_arrival, self._t_last)
        if self._offset is not None and pts:
            behind = t_held - self._offset - self._delay - pts[-1][0]
            if behind > 0.0:  # the reference has been holding the last setpoint: resume there
                self._offset += behind
                self._shift += behind
        pts.append((t_source, q.copy()))
        if (excess := len(pts) - self.window) > 0:
            # never drop a setpoint not yet played (after several stalls the timeline may run
            # behind by more than the window: dropping its path would make the reference jump
            # ahead); a hard cap of 4 windows bounds the memory
            playing = bisect.bisect_right(pts, self.played, key=lambda p: p[0]) - 1
            del pts[: excess if len(pts) > 4 * self.window else min(excess, max(0, playing))]
        if self._offset is None and len(pts) >= 2:
            self._delay = min(1.5 * (pts[-1][0] - pts[-2][0]), self.max_period)
            self._offset = t_arrival - t_source
            # the reference has held the first setpoint until now: the timeline starts there
            # (with a first gap longer than the delay it would start part-way along it: a step)
            late = t_held - self._delay - pts[-2][0] - self._offset
            if late > 0.0:
                self._offset += late
                self._shift += late

    @property
    def delay(self) -> float:
        """Buffer delay of the current timeline, s."""
        return self._delay

    @property
    def behind(self) -> float:
        """How far (s) the timeline runs behind its start offset: stalls not yet made up."""
        return self._shift

    def pause(self, seconds: float) -> None:
        """The arm held its command for ``seconds`` (a stall of its own loop): the playback clock
        stops for as long, so the reference resumes on the path where the command stopped."""
        if self._offset is not None and seconds > 0.0:
            self._offset += seconds
            self._shift += seconds
            if self._t_last is not None:  # the paused time is not played: nothing to make up in it
                self._t_last += seconds

    def sample(self, t: float) -> np.ndarray | None:
        """Reference at local time ``t`` (s); None before the first setpoint."""
        pts = self._pts
        if not pts:
            return None
        if self._offset is None:
            self._t_last = t  # (holding the first setpoint until the timeline starts)
            return pts[0][1]
        if self._t_last is not None and t > self._t_last and self._shift > 0.0 and self.catchup > 1.0:
            gain = min(self._shift, (self._catchup_rate(t - self._t_last) - 1.0) * (t - self._t_last))
            self._offset -= gain
            self._shift -= gain
        if self._t_last is not None and t < self._t_last:
            t = self._t_last  # never played backward
        self._t_last = t
        tp = t - self._offset - self._delay  # the source time being played now
        if self._tp_last is not None and tp < self._tp_last:
            # never played backward along the path: a shift counted from an arrival time ahead of
            # this sample (a frozen process: its queued setpoints all "arrive" at the thaw, after
            # the stalled period this sample computes) would step the arm back (a speed-clipped
            # jump that leaves the trocar's RCM); the playback resumes where it stopped instead
            back = self._tp_last - tp
            self._offset -= back
            self._shift = max(0.0, self._shift - back)
            tp = self._tp_last
        # what is played: a reference holding the newest setpoint (the buffer ran dry) has played
        # that setpoint's time, not beyond (a later resume from there is no step back)
        self._tp_last = min(tp, pts[-1][0])
        if tp <= pts[0][0]:
            self.played = pts[0][0]
            return pts[0][1]
        if tp >= pts[-1][0]:
            self.played = pts[-1][0]
            return pts[-1][1]  # ran dry: hold the newest setpoint
        self.played = tp
        i = bisect.bisect_right(pts, tp, key=lambda p: p[0])  # pts[i - 1][0] <= tp < pts[i][0]
        (ta, qa), (tb, qb) = pts[i - 1], pts[i]
        out: np.ndarray = qa + (tp - ta) / (tb - ta) * (qb - qa)
        return out

    def _catchup_rate(self, span: float) -> float:
        """Playback rate while behind for the next ``span`` s of local time: ``catchup``, lowered so
        that every segment it may play (from the played time up to ``catchup`` × ``span`` of
        source time further: a burst of closely stamped setpoints is many segments) stays within
        ``max_speed``; at least 1."""
        if self.max_speed is None or self._tp_last is None:
            return self.catchup
        pts = self._pts
        i = bisect.bisect_right(pts, self._tp_last, key=lambda p: p[0])
        end = self._tp_last + self.catchup * span
        ratio = 0.0  # the fastest segment's speed / max_speed
        for j in range(max(i, 1), min(len(pts), max(i, 1) + 256)):
            (ta, qa), (tb, qb) = pts[j - 1], pts[j]
            ratio = max(ratio, float(np.max(np.abs(qb - qa) / self.max_speed)) / (tb - ta))
            if tb >= end:
                break
        if ratio <= 0.0:
            return self.catchup
        return max(1.0, min(self.catchup, 1.0 / ratio))

    def reset(self) -> None:
        """Forget the history (a new engage starts a new timeline)."""
        self._pts.clear()
        self._offset = None
        self._delay = 0.0
        self._shift = 0.0
        self._t_last = None
        self._tp_last = None


@dataclass
class Lease:
    """Latest lease as seen by the slave (times on the local monotonic clock, s).

    ``cycle``/``valid_cycles``: control cycle at reception and lifetime in cycles (None: wall
    time only). ``stamp_ns``/``valid_ns``: its own stamp and lifetime, for the stamp-age rule
    (``arm.py``: a lease is never honoured longer than its lifetime after its own stamp, whatever
    the arrival and cycle clocks say — a thawed process does not act on old permissions).
    """

    allow: bool = False
    expires: float = 0.0
    reason: str = "no lease received"
    cycle: int | None = None
    valid_cycles: int = 0
    stamp_ns: int = 0  # the lease's own header stamp (the watchdog's wall clock, ns; 0: unknown)
    valid_ns: int = 0  # its lifetime, ns (valid_for_ms)


@dataclass
class Setpoint:
    """Latest accepted setpoint (receive time on the local monotonic clock, s; control cycle;
    source sampling time, s on the source's clock, 0 if unknown)."""

    position: np.ndarray
    follow: bool
    received: float
    cycle: int | None = None
    source_time: float = 0.0
    origin_ns: int = 0  # master sample stamp behind the setpoint (wall clock, ns; 0: unknown)
    stamp_ns: int = 0  # the setpoint's own header stamp (mapping publish time, ns)


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
    # the arm's keep-out of followed steps (None: none); see the module doc
    keepout: Keepout | None = None
    keepout_clamped: int = 0  # followed cycles whose step the keep-out clamped
    _ko_episode: int = 0  # cycles clamped in the current keep-out episode (0: none)
    _ko_quiet: int = 0
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
            if self.keepout is not None:
                out, why = self.keepout(q_cmd, out)
                self._account_keepout(why)
                if why:  # waiting at the surface: not the speed limit's doing
                    return out
            self._account_clip(want, lim)
        return out

    def _account_keepout(self, why: str) -> None:
        if why:
            self.keepout_clamped += 1
            self._ko_quiet = 0
            if not self._ko_episode:
                self.events.append(("keepout_clamped", f"setpoint clamped at the patient's surface: {why}"))
            self._ko_episode += 1
        elif self._ko_episode:
            self._ko_quiet += 1
            if self._ko_quiet >= self.clip_quiet_cycles:
                self.events.append(
                    (
                        "keepout_clamped",
                        f"setpoints clear of the patient again after {self._ko_episode} clamped cycles",
                    )
                )
                self._ko_episode, self._ko_quiet = 0, 0

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

    def hold(self, q_meas: np.ndarray, cause: str) -> None:
        """Stop following servo_jp for ``cause`` (a fault: counted, a new engage is needed)."""
        if self.following:
            self._hold(q_meas, cause, fault=True)

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
        if self._ko_episode:
            self.events.append(
                (
                    "keepout_clamped",
                    f"keep-out clamp ended with following after {self._ko_episode} clamped cycles",
                )
            )
            self._ko_episode, self._ko_quiet = 0, 0
