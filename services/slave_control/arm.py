"""The arm core: one per slave arm, the same for every robot and every backend.

An :class:`ArmCore` owns everything that decides whether and where one arm moves: its watchdog
lease, its setpoints (validated), the e-stop latch, the backend-fault hold
(:class:`FaultHold`), the follow/engage rule (:class:`~.control.FollowController`) and the
publication of what it measures (``measured_js``, ``measured_cp``, ``measured_cf``,
``operating_state``) and of the latency log. Every slave — the MH3F forceps arm, each PLAS and
VIP arm, on MuJoCo or on a real arm's serial controller (with or without its MuJoCo shadow) —
runs through it; :func:`telesurg.services.slave_control.run` only steps the backend.

Rules (one of each, for every arm):

* **Lease age.** Leases and setpoints are read by the control loop (polled subscriptions, one
  :meth:`~telesurg.shared.bus.Node.poll` per period). A lease is aged from the *previous* poll —
  the earliest moment it can have arrived (:meth:`~telesurg.shared.bus.Node.received`) — so a
  lease never outlasts its grant by the polling interval. It allows motion while it says
  ``allow`` and is younger than its ``valid_for_ms``; as for every input age (``control.py``) it
  has expired only when both the wall clock and the control cycles executed since it came say
  so. The watchdog's liveliness token dying revokes it at once: the token of the watchdog
  session whose leases this node authenticates (``alive/watchdog/<sid>``,
  :mod:`telesurg.shared.presence`), so another token for the watchdog (a stranger's) does not
  hide the death, and a lease of that session still queued here is dropped. **Stamp age:** whatever those
  clocks say, a lease is honoured at most its ``valid_for_ms`` + ``lease_stamp_slack_ms`` after
  its own header stamp, and a setpoint at most ``setpoint_max_age_ms`` after its stamp, judged on
  this host's wall clock at the moment of use (the watchdog and the mapping run on the slave
  site's host: one clock) — so after a freeze (SIGSTOP/SIGCONT) the arm never acts on the
  permissions and setpoints queued before it, not even in the replayed periods.
* **Setpoints.** A ``servo_jp`` is refused (counted in ``operating_state.rejected``, an event,
  nothing else changes) when its joint names are not the arm's, a joint is outside its limits,
  its header stamp is more than ``setpoint_max_age_ms`` away from this host's wall clock (stale
  or from a clock that disagrees: any doubt → hold), or, while following, it is more than
  ``max_setpoint_step_rad`` from the previous followed setpoint (a jump). An accepted setpoint is
  followed only while younger than ``setpoint_timeout_ms`` (by arrival; see ``control.py``).
* **E-stop.** An ``EStop`` for the arm (or ``*``) latches until an explicit reset: the arm
  holds at once and every slave-side motion stops; commands other than ``state``/``stop``/
  ``abort`` are refused.
* **Follow/engage.** After any hold the arm follows only after a new engage whose first setpoint
  is within ``engage_tolerance_rad`` of the measured joints; the commanded joints move at most
  the joint speed limits per period (scaled as a whole, :func:`~.control.limit_step`).
* **Catch-up after a stall.** The physics stays in real time and the command never moves more
  than one period's speed-limited step per period of physics. A simulated backend (its physics
  advances only when stepped) replays the periods the loop slept through, one physics step
  each, with the command of that period computed at that period's time (so the arm stays on its
  commanded path, and the lease and setpoint ages are judged at that time) — the last
  :data:`REPLAY_MAX_PERIODS` of them; through the earlier ones of a longer stall it held its
  command, as a real arm does (this bounds the work between waking and publishing). A real arm
  lived through the stall by itself holding its last command, so its loop simply goes on from
  the measured state (its MuJoCo shadow is stepped by the missed periods with that held command).
* **measured_cp.** The arm's controlled point (the profile's tip: the MH3F forceps tip, the PLAS
  arm tip, the VIP wrist W) as a full pose with a real orientation, from the forward kinematics
  of the measured joints, in the robot's ``base`` frame (the MuJoCo model's world frame, in which
  every arm of the robot is mounted). ``measured_cf`` is the external wrench at that point in the
  same frame, from the backend's external joint torques (``τ = Jᵀ [F; M]``); it is published
  for every arm whose backend estimates them (MuJoCo; a serial controller reports none).

Motions plug in as :class:`MotionSource`: each period the core asks the arm's slave-side source
(trocar modes, PTP, jog, teach/playback) whether it is active and, if so, for the commanded
joints; otherwise the arm follows the master through its default source, :class:`ServoFollow`
(``servo_jp``, through the :class:`~.control.SetpointInterpolator`: the VIP/PLAS consoles at
25 Hz, the MH3F's mapping at 250 Hz — its servos never see a step, which they would answer each
at its own pace, off the trocar's RCM). The trocar arm pauses its setpoint timeline through the
periods it held its command in a stall and makes the delay up afterwards (at :data:`CATCHUP`× the
master's pace, within :data:`CATCHUP_SPEED_FRACTION` of its joint speed limits), so it resumes
along the master's path where it stopped; an arm that falls further behind than
``follow_max_lag_ms`` (a host that stalls it more than it makes up) holds until a new engage.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from telesurg.services.slave_control.control import (
    WARN,
    FollowController,
    Lease,
    Setpoint,
    SetpointInterpolator,
)
from telesurg.shared.authority import Authority, summary
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import AuthorityError
from telesurg.shared.haptics import SlavePortWork
from telesurg.shared.limits import limit_step
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    Command,
    CommandReply,
    EStop,
    JointSetpoint,
    JointState,
    OperatingState,
    SafetyLease,
    Sequencer,
)
from telesurg.shared.robots.api import ArmReading, AttachedSource, MotionError, MotionSource

if TYPE_CHECKING:
    from telesurg.services.slave_control import SlaveControlConfig
    from telesurg.services.slave_control.backends import SlaveReading
    from telesurg.shared.bus import Node, Outlet
    from telesurg.shared.robots import ArmProfile

__all__ = ["ArmCore", "ArmReading", "AttachedSource", "MotionError", "MotionSource", "ServoFollow"]

log = logging.getLogger(__name__)

#: The frame of measured_cp / measured_cf for every arm (see the module doc).
FRAME = "base"
#: Missed periods a simulation replays after a stall (the catch-up rule): 20 ms at 1 kHz, at most
#: ~2 ms of work (a jog's IK included) before the loop publishes again.
REPLAY_MAX_PERIODS = 20
#: Playback rate of an arm's setpoint timeline while it makes up a stall, at most
#: (:class:`~.control.SetpointInterpolator`): a stall of 100 ms is made up within 100 ms.
CATCHUP = 2.0
#: ... and no faster than this fraction of the joint speed limits: the catch-up is never
#: speed-clipped (a clipped step leaves the trocar's RCM), and the servos keep the trocar arm's RCM
#: within 0.3 mm at it (``trocar_limits.TROCAR_SPEED_FRACTION``: 1.4 mm at 0.7 ×, 3.1 mm at
#: 0.875 ×). The mapping keeps every trocar-mode step within 0.4 × them, so it is always made up
#: at ≥ 1.25×.
CATCHUP_SPEED_FRACTION = 0.5
#: Accepted setpoints kept between two control periods (the interpolator gets every one of them).
PENDING_MAX = 256
#: Setpoints the interpolator keeps: 1.2 s at 250 Hz, longer than the longest stall an arm still
#: follows through (a lease lives 250 ms), so a paused timeline always resumes on kept setpoints
#: (a timeline behind by more, after several stalls, keeps its unplayed ones: up to 4 windows).
INTERP_WINDOW = 300


@dataclass
class ServoFollow:
    """Master–slave following, the arm's default motion source: the reference is the newest
    accepted ``servo_jp`` — or, for an arm whose setpoints are interpolated (``interpolate``: the
    joint-space family fed by a console at 25 Hz, and the trocar arm at 250 Hz, whose servos must
    never see a step: a step answered joint by joint leaves the RCM), the
    :class:`~.control.SetpointInterpolator`'s smooth 1 kHz replay of every accepted setpoint on
    the master's clock. The core's follow/engage rule (:class:`~.control.FollowController`)
    decides whether the arm follows it."""

    interpolate: bool
    interp: SetpointInterpolator
    _last_follow: bool = False

    def reference(self, sp: Setpoint | None, arrived: list[Setpoint], now: float) -> Setpoint | None:
        """The setpoint to follow at time ``now`` (``arrived``: the setpoints accepted since the
        last call, oldest first, ``sp`` the newest)."""
        if not self.interpolate or sp is None:
            return sp
        for a in arrived:
            if a.follow and not self._last_follow:
                self.interp.reset()  # a new engage starts a new timeline (no jump)
            self.interp.push(a.position, a.source_time, a.received)
            self._last_follow = a.follow
        if sp.follow and (ref := self.interp.sample(now)) is not None:
            return Setpoint(ref, True, sp.received, sp.cycle)
        return sp


@dataclass
class FaultHold:
    """What an arm does while its backend reports a fault (``SlaveReading.fault``).

    Like a revoked lease, with the fault as the reason: the follow controller stops following and
    is disarmed (after the fault a new engage — clutch released, then pressed — is needed), the
    command freezes at the joints measured when the fault began, and when the fault clears the
    command restarts from the joints measured then (the arm may have stopped or been moved
    meanwhile: the old command must not pull it back). Events go to ``ctl.events``: ``hold`` with
    the cause at the onset and whenever the cause changes, ``fault_cleared`` at the end.

    Attributes:
        cause: the fault being held ("" = none).
    """

    cause: str = ""
    _q: np.ndarray | None = None

    @property
    def active(self) -> bool:
        return bool(self.cause)

    def update(self, ctl: FollowController, fault: str, q_meas: np.ndarray) -> np.ndarray:
        """The joint command of this period, given the backend's ``fault`` ("" = none)."""
        if not fault:
            ctl.events.append(("fault_cleared", f"{self.cause}: cleared; waiting for a new engage"))
            self.cause, self._q = "", None
            q = q_meas.copy()
            ctl.track(q)
            return q
        if self._q is None:
            self._q = q_meas.copy()
            if ctl.following:
                ctl.holds += 1
        if fault != self.cause:
            ctl.events.append(("hold", fault))
        self.cause = fault
        ctl.following = False
        ctl.armed = False
        ctl.reason = fault
        ctl.track(self._q)
        return self._q.copy()


def tip_wrench(
    jac: np.ndarray, tau_ext: np.ndarray
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """External force (N) and torque (N·m) at the controlled point from the external joint
    torques: ``τ = Jᵀ [F; M]`` solved by least squares (the minimum-norm answer near a
    singularity, and for arms with fewer than 6 joints)."""
    w = np.linalg.lstsq(jac.T, tau_ext, rcond=1e-6)[0]
    return (float(w[0]), float(w[1]), float(w[2])), (float(w[3]), float(w[4]), float(w[5]))


@dataclass
class ArmCore:
    """Inputs (zenoh threads), control decisions and outputs of one slave arm.

    Args:
        profile: the arm (joint names, limits, speeds, FK).
        index: positions of the arm's joints in the backend's joint vector (a slice when they
            are contiguous: no copy per period).
        cfg: slave_control's config (setpoint, engage and rate keys).
        dt: control period, s.
        node: the bus (None in unit tests: no events, no outputs).
        motion: the arm's slave-side motion source (None: the arm only follows servo_jp).
        interpolate: interpolate the setpoints to the control rate (slave_control: every arm).
        catchup: > 1: pause the setpoint timeline through a stall and make it up at this rate.
    """

    profile: ArmProfile
    index: np.ndarray | slice
    cfg: SlaveControlConfig
    dt: float = 0.001
    node: Node | None = None
    motion: MotionSource | None = None
    interpolate: bool = False
    lock: threading.Lock = field(default_factory=threading.Lock)
    lease: Lease = field(default_factory=Lease)
    setpoint: Setpoint | None = None
    fresh_setpoint: bool = False  # a new setpoint arrived since the loop last looked
    # playback rate of the interpolated timeline while it makes up a stall, at most (1: never; see
    # CATCHUP and control.SetpointInterpolator)
    catchup: float = 1.0
    _arrived: list[Setpoint] = field(default_factory=list)  # accepted since the loop last looked
    estop: str = ""  # latched e-stop cause ("" = none); only an explicit reset clears it
    rejected: int = 0  # setpoints refused by the rules above
    cycle: int = 0  # control cycles executed; stamped on inputs (see control.py)
    following: bool = False  # mirrors the controller (set by the control loop)
    # a slave-side motion drove the arm in the last period (its commanded joints go out on
    # setpoint_js for the watchdog, publish_commanded)
    commanding: bool = False
    held: FaultHold = field(default_factory=FaultHold)
    ctl: FollowController = field(init=False)
    servo: ServoFollow = field(init=False)
    outlets: dict[str, Outlet] = field(default_factory=dict)
    reading: ArmReading | None = None  # last reading (set by the loop)
    q_cmd: np.ndarray = field(init=False)  # last command (set by the loop)
    _last_state: tuple[object, ...] | None = None
    _reply_seq: Sequencer = field(init=False)
    authority: Authority = field(init=False)  # who may command, e-stop, reset (cfg.authority)
    _applied: np.ndarray | None = None
    _n_applied: int = 0
    _last_sp: Setpoint | None = None
    _step_row: int | None = None  # latency-log row waiting for its step time (stepped)
    # the slave port's E_in_s for bilateral force feedback (docs/haptics.md, "Energy"), published
    # on measured_cf
    port_work: SlavePortWork = field(default_factory=SlavePortWork)
    _free_calls: int = 0  # publish_wrench calls in a row without contact
    # the backend's tool (jaws) of this arm ("" = none) and their closure commanded now, 0 open …
    # 1 closed (-1: no jaws): the followed setpoints' grip, kept through a hold
    tool: str = ""
    grip: float = -1.0
    _grip_sp: float = -1.0  # the newest accepted setpoint's grip

    def __post_init__(self) -> None:
        p, cfg = self.profile, self.cfg
        self.ctl = FollowController(
            np.array(p.max_velocity),
            setpoint_timeout=cfg.setpoint_timeout_ms / 1e3,
            engage_tolerance=cfg.engage_tolerance_rad,
        )
        self.servo = ServoFollow(
            self.interpolate,
            SetpointInterpolator(
                cfg.interpolation_max_ms / 1e3,
                window=INTERP_WINDOW,
                catchup=self.catchup,
                max_speed=CATCHUP_SPEED_FRACTION * np.array(p.max_velocity),
            ),
        )
        self._max_lag = cfg.follow_max_lag_ms / 1e3
        self.q_cmd = np.array(p.home, dtype=float)
        self._lower, self._upper = tuple(p.lower), tuple(p.upper)
        self._vmax = np.array(p.max_velocity)
        self._reply_seq = Sequencer(cfg.service)
        self.authority = Authority(cfg.authority)
        self._lease_slack_ns = round(cfg.lease_stamp_slack_ms * 1e6)
        self._sp_max_age_ns = round(cfg.setpoint_max_age_ms * 1e6)
        if cfg.latency_log:
            self._applied = np.zeros((300_000, 5), dtype=np.int64)
        if self.motion is not None:
            self.motion.attach(self)
            self.ctl.keepout = self.motion.follow_keepout

    @property
    def arm(self) -> str:
        return self.profile.arm

    def event(self, kind: str, text: str, severity: str = "info") -> None:
        if self.node is not None:
            self.node.event(kind, text, arm=self.arm, severity=severity)

    # -- wiring ---------------------------------------------------------------------------------
    def connect(self, node: Node) -> None:
        """Subscribe the arm's inputs and declare its outputs on ``node``."""
        k, cfg, arm = node.keys, self.cfg, self.arm
        self.node = node
        for stream in ("measured_js", "measured_cp", "measured_cf", "operating_state", "setpoint_js"):
            self.outlets[stream] = node.outlet(k.slave(arm, stream))
        # polled: read by the control loop at each tick (see the lease-age rule)
        node.subscribe(
            k.safety(arm, "lease"), SafetyLease, self.on_lease, sources=[cfg.watchdog_service], polled=True
        )
        node.subscribe(
            k.slave(arm, "servo_jp"),
            JointSetpoint,
            self.on_setpoint,
            sources=[cfg.setpoint_source],
            polled=True,
        )
        node.subscribe(k.estop, EStop, self.on_estop)
        node.watch_liveliness(k.alive(cfg.watchdog_service), self.on_watchdog_alive)
        node.serve(k.command(arm), Command, self.on_command, sources=cfg.command_sources or None)

    # -- inputs (zenoh threads / the loop's poll) ----------------------------------------------
    def on_lease(self, msg: SafetyLease, key: str) -> None:
        now = self.node.received(key) if self.node is not None else time.monotonic()
        if self.node is not None and self.node.presence.vanished(
            self.cfg.watchdog_service, self.node.streams.get(key).sid
        ):
            return  # queued from a watchdog session whose token has vanished: it is dead
        with self.lock:
            valid_cycles = round(msg.valid_for_ms / 1e3 / self.dt)
            self.lease = Lease(
                msg.allow,
                now + msg.valid_for_ms / 1e3,
                msg.reason,
                self.cycle,
                valid_cycles,
                msg.header.stamp_ns,
                round(msg.valid_for_ms * 1e6),
            )

    def on_watchdog_alive(self, service: str, alive: bool) -> None:
        if service == self.cfg.watchdog_service and not alive:
            with self.lock:
                self.lease = Lease(False, 0.0, f"{service} not alive")

    def on_estop(self, msg: EStop, key: str) -> None:
        if not msg.applies_to(self.arm):
            return
        if problem := self.authority.estop_problem(msg.header.source, msg.action):
            self.event("estop_refused", problem, "warning")
            return
        node, src = self.node, msg.header.source
        stamp = node.fresh.local_ns(src, msg.header.stamp_ns) if node is not None else msg.header.stamp_ns
        if stale := self.authority.estop_order(msg.action, stamp):
            if node is not None:
                node.replayed(key, src, stale)
            return
        with self.lock:
            was = self.estop
            if msg.action == "estop":
                self.estop = f"e-stop from {msg.header.source}" + (f": {msg.reason}" if msg.reason else "")
            else:
                self.estop = ""
        if msg.action == "estop" and not was:
            self.event("estop", self.estop, "error")
        elif msg.action == "reset" and was:
            self.event("estop_reset", f"e-stop reset by {msg.header.source}")

    def setpoint_problem(self, msg: JointSetpoint) -> str:
        """Why ``msg`` is refused ("" = accepted); see the module doc."""
        # plain float arithmetic on the message's tuples: numpy on 6 values costs ~10× more, and
        # this runs for every setpoint (1 kHz)
        p, pos = self.profile, msg.position
        if msg.names != p.joint_names:
            return f"joint names {list(msg.names)} != {list(p.joint_names)}"
        if not all(lo <= v <= hi for v, lo, hi in zip(pos, self._lower, self._upper, strict=True)):
            bad = [
                f"{n}={v:.4f}"
                for n, v, lo, hi in zip(p.joint_names, pos, self._lower, self._upper, strict=True)
                if not lo <= v <= hi
            ]
            return f"outside joint limits: {', '.join(bad)}"
        age_ms = (wall_ns() - msg.header.stamp_ns) / 1e6
        if abs(age_ms) > self.cfg.setpoint_max_age_ms:
            when = f"{age_ms:.0f} ms ago" if age_ms > 0 else f"{-age_ms:.0f} ms in the future"
            return f"stale: stamped {when} (limit {self.cfg.setpoint_max_age_ms:g} ms)"
        prev = self.setpoint
        if self.following and msg.follow and prev is not None and prev.follow:
            jump = max(abs(v - w) for v, w in zip(pos, prev.position.tolist(), strict=True))
            if jump > self.cfg.max_setpoint_step_rad:
                return f"jump of {jump:.3f} rad from the previous setpoint"
        return ""

    def on_setpoint(self, msg: JointSetpoint, key: str) -> None:
        if reason := self.setpoint_problem(msg):
            self.rejected += 1
            if self.rejected <= 5 or self.rejected % 1000 == 0:
                self.event("setpoint_rejected", reason, "warning")
            return
        received = self.node.received(key) if self.node is not None else time.monotonic()
        with self.lock:
            self.setpoint = Setpoint(
                np.array(msg.position),
                msg.follow,
                received,
                self.cycle,
                (msg.origin_ns or msg.header.stamp_ns) / 1e9,
                origin_ns=msg.origin_ns,
                stamp_ns=msg.header.stamp_ns,
            )
            self.fresh_setpoint = True
            self._grip_sp = msg.grip
            self._arrived.append(self.setpoint)
            del self._arrived[:-PENDING_MAX]

    def on_command(self, cmd: Command) -> CommandReply:
        """Answer one operator command (zenoh thread) the operator authority allows
        (:mod:`telesurg.shared.authority`): a refusal is an event and raises
        :class:`~telesurg.shared.errors.AuthorityError` (the query's error reply names the reason);
        a motion-starting command first gets a ``confirm required`` reply with a token."""
        try:
            verdict = self.authority.check(cmd)
        except AuthorityError as exc:
            self.event("command_refused", str(exc), "warning")
            raise
        if verdict.command is None:
            self.event("confirm_required", f"{summary(cmd)} from {cmd.header.source!r}")
            return CommandReply(
                self._reply_seq.next(), self.arm, cmd.name, False, verdict.reason, verdict.token
            )
        cmd = verdict.command
        if cmd.arm != self.arm:
            ok, reason = False, f"{cmd.name} refused: this is arm {self.arm}, not {cmd.arm}"
        elif self.motion is not None:
            ok, reason = self.motion.command(cmd)
            if ok:
                self.event("command", f"{cmd.name} {' '.join(cmd.args)}: {reason}".strip())
        elif cmd.name == "state":
            with self.lock:
                ok, reason = True, f"joint slave, {'following' if self.ctl.following else self.ctl.reason}"
        else:
            ok, reason = False, f"unknown command {cmd.name!r} for a joint slave; valid: state"
        return CommandReply(self._reply_seq.next(), self.arm, cmd.name, ok, reason)

    # -- control (the loop's thread) -----------------------------------------------------------
    def arm_reading(self, r: SlaveReading) -> ArmReading:
        """This arm's share of the backend reading ``r``."""
        i = self.index
        q = r.position[i]
        tau = None if r.external_torque is None else r.external_torque[i]
        # the contact wrench on this arm's own instrument, about its controlled point
        touch = None if r.site_wrenches is None else r.site_wrenches.get(self.profile.tip_site)
        return ArmReading(q, r.velocity[i], r.effort[i], self.profile, tau, r.fault, touch)

    def start(self, reading: ArmReading) -> None:
        """Before the first period: start from the measured joints (MuJoCo: the home pose; a real
        arm: wherever it stands)."""
        self.reading = reading
        self.q_cmd = reading.position.copy()
        if self.motion is not None:
            self.motion.measure(reading, self.q_cmd)

    def control(self, now: float, reading: ArmReading) -> np.ndarray:
        """The arm's joint command for the period at time ``now`` (s, monotonic)."""
        q_meas, q_cmd, ctl, motion = reading.position, self.q_cmd, self.ctl, self.motion
        with self.lock:
            lease, sp, arrived = self.lease, self.setpoint, self._arrived
            grip_sp = self._grip_sp
            self.fresh_setpoint = False
            self._arrived = []
            if self.estop:
                lease = Lease(False, 0.0, self.estop)
            internal = motion is not None and motion.active()
            blocked = motion.blocks_following() if motion is not None else ""
        lease, sp = self._stamp_age(lease, sp)
        if arrived and self._sp_max_age_ns:  # the stamp-age rule for every one the timeline gets
            wall = wall_ns()
            arrived = [a for a in arrived if not a.stamp_ns or wall - a.stamp_ns <= self._sp_max_age_ns]
        logged = self._log_applied(sp)
        if reading.fault or self.held.active:
            if reading.fault and internal and motion is not None:
                motion.stop(f"fault: {reading.fault}")
            if motion is not None:
                motion.braking(q_cmd, self.dt, False)  # a fault: stand still, no controlled stop
            ctl.lease_valid = ctl.lease_ok(lease, now, self.cycle)
            out = self.held.update(ctl, reading.fault, q_meas)
        elif internal and motion is not None:
            out = self._internal(motion, lease, now, reading)
            self.commanding = True
        elif motion is not None and (brake := motion.braking(q_cmd, self.dt, not self.estop)) is not None:
            # a stopped joint PTP ramps down along its path (any lease: the arm would coast anyway)
            out = q_cmd + limit_step(brake - q_cmd, self._vmax * self.dt)
            ctl.track(out)
            self.commanding = True
        else:
            if blocked:
                ctl.pause(q_meas, blocked)
                sp = None
            sp = self.servo.reference(sp, arrived, now)
            if (
                ctl.following
                and self.interpolate
                and self.catchup > 1.0
                and (lag := self.servo.interp.behind) > self._max_lag
            ):
                # the host stalled the slave (or its setpoints) more than the catch-up made up:
                # hold rather than follow the master ever further behind (a new engage restarts)
                ctl.hold(
                    q_meas,
                    f"the slave fell {lag * 1e3:.0f} ms behind the master (stalls not made up; "
                    f"limit follow_max_lag_ms = {self._max_lag * 1e3:g})",
                )
            out = ctl.update(now, q_meas, q_cmd, lease, sp, self.dt, self.cycle)
            if ctl.following and self.tool and grip_sp >= 0.0:  # the jaws follow only with the arm
                self.grip = grip_sp
            if logged and ctl.following and self.interpolate and self._applied is not None:
                self._applied[self._n_applied - 1, 4] = round(self.servo.interp.played * 1e9)
        self.q_cmd = out
        return out

    def stepped(self, wall_ns: int) -> None:
        """The backend stepped (sent) the command of the period (wall clock ``wall_ns``): the
        latency log's "acts" time of the setpoint first used in it."""
        if self._step_row is not None and self._applied is not None:
            self._applied[self._step_row, 3] = wall_ns
            self._step_row = None

    def stalled(self, seconds: float) -> None:
        """The arm held its command through ``seconds`` of a stall of the control loop (the
        catch-up rule): an arm that catches up (``catchup`` > 1) pauses its setpoint timeline as
        long, so it resumes along the master's path where it stopped — never across to the newest
        setpoint (a speed-clipped jump answered joint by joint leaves the trocar's RCM) — and then
        makes up the delay at ``catchup``."""
        if self.interpolate and self.catchup > 1.0:
            self.servo.interp.pause(seconds)

    def _stamp_age(self, lease: Lease, sp: Setpoint | None) -> tuple[Lease, Setpoint | None]:
        """The stamp-age rule: judged on this host's wall clock *now* (also in a replayed period:
        the stamps are as old as they are), a lease older than its lifetime +
        ``lease_stamp_slack_ms`` is revoked and a setpoint older than ``setpoint_max_age_ms`` is
        dropped (the controller sees no setpoint: stale), however recently they arrived."""
        wall = wall_ns()
        if lease.allow and lease.stamp_ns:
            age = wall - lease.stamp_ns
            if age > lease.valid_ns + self._lease_slack_ns:
                lease = Lease(
                    False,
                    0.0,
                    f"lease expired (stamped {age / 1e6:.0f} ms ago, valid {lease.valid_ns / 1e6:g} ms)",
                )
        if sp is not None and sp.stamp_ns and wall - sp.stamp_ns > self._sp_max_age_ns:
            sp = None
        return lease, sp

    def _internal(self, motion: MotionSource, lease: Lease, now: float, reading: ArmReading) -> np.ndarray:
        """One period of a slave-side motion, only under a valid lease."""
        ctl, q_cmd = self.ctl, self.q_cmd
        ctl.pause(reading.position, "slave-side motion (PTP / jog / playback / direct teach)")
        ok = ctl.lease_valid = ctl.lease_ok(lease, now, self.cycle)
        if not ok:  # any doubt: stop the motion; the operator must command it again
            why = lease.reason or "lease expired"
            with self.lock:
                motion.stop(f"lease: {why}")
            ctl.holds += 1
            self.event("hold", f"slave-side motion stopped: {why}", "warning")
            ctl.track(q_cmd)
            return q_cmd
        try:
            target = motion.next(q_cmd, reading, self.dt)
            p = self.profile
            if not all(lo <= v <= hi for v, lo, hi in zip(target.tolist(), p.lower, p.upper, strict=True)):
                raise MotionError("a joint limit is reached")
        except MotionError as exc:
            with self.lock:
                motion.stop(str(exc))
            self.event("motion_stopped", f"slave-side motion stopped: {exc}", "warning")
            ctl.track(q_cmd)
            return q_cmd
        out: np.ndarray = q_cmd + limit_step(target - q_cmd, self._vmax * self.dt)
        motion.reached(out, reading)
        ctl.track(out)
        return out

    def _log_applied(self, sp: Setpoint | None) -> bool:
        """Latency log: a row for ``sp`` if the loop uses it for the first time (True)."""
        a = self._applied
        new = a is not None and sp is not None and sp is not self._last_sp and self._n_applied < len(a)
        if new:
            assert a is not None and sp is not None
            a[self._n_applied] = (sp.origin_ns, sp.stamp_ns, wall_ns(), 0, 0)
            self._step_row = self._n_applied
            self._n_applied += 1
        self._last_sp = sp
        return new

    def after_period(self, cycle: int, reading: ArmReading) -> None:
        """After the backend stepped: remember the reading, drain the controller's events."""
        self.cycle = cycle
        self.following = self.ctl.following
        self.reading = reading
        for kind, text in self.ctl.events:
            self.event(kind, text, "warning" if kind in WARN else "info")
        self.ctl.events.clear()

    def measure(self, reading: ArmReading) -> None:
        """Sub-rate update of the motion source from the measurements (100 Hz)."""
        if self.motion is not None:
            self.motion.measure(reading, self.q_cmd)

    # -- outputs -------------------------------------------------------------------------------
    def publish_measured(self, r: ArmReading) -> None:
        """measured_js and measured_cp."""
        js, cp = self.outlets["measured_js"], self.outlets["measured_cp"]
        js.put(
            JointState(
                js.header(),
                self.profile.joint_names,
                tuple(r.position.tolist()),
                tuple(r.velocity.tolist()),
                tuple(r.effort.tolist()),
            )
        )
        t = r.tip_pose
        cp.put(
            CartesianPose(cp.header(), FRAME, (float(t[0, 3]), float(t[1, 3]), float(t[2, 3])), r.tip_quat)
        )

    def publish_commanded(self) -> None:
        """setpoint_js: the joints commanded by a slave-side motion (PTP, jog, playback,
        insert/remove, direct teach) since the last call, for the watchdog's checks (joint limits,
        speed, workspace, patient keep-out); nothing while the arm follows servo_jp or holds."""
        if not self.commanding:
            return
        self.commanding = False
        out = self.outlets["setpoint_js"]
        out.put(JointState(out.header(), self.profile.joint_names, tuple(self.q_cmd.tolist()), (), ()))

    def publish_wrench(self, r: ArmReading, quiet_every: int = 1) -> None:
        """measured_cf: the contact wrench on the instrument when the backend measures contacts
        (MuJoCo with a touchable scene: what a tip force sensor reads), else the estimate from
        the external joint torques; nothing when the backend has neither. Out of contact (a zero
        contact wrench) only every ``quiet_every``-th call is sent, the first at once: the
        contact rate where there is something to feel, the sub-rate in free space."""
        if r.contact_wrench is not None:
            w = r.contact_wrench
            f, m = (float(w[0]), float(w[1]), float(w[2])), (float(w[3]), float(w[4]), float(w[5]))
        elif r.external_torque is not None:
            f, m = tip_wrench(self.profile.jacobian(r.position), r.external_torque)
        else:
            return
        energy = self.port_work.add(np.array(f), r.tip_pose[:3, 3])
        if r.contact_wrench is not None and not r.contact_wrench.any():
            self._free_calls += 1
            if (self._free_calls - 1) % quiet_every:
                return
        else:
            self._free_calls = 0
        out = self.outlets["measured_cf"]
        out.put(CartesianWrench(out.header(), FRAME, f, m, energy))

    def publish_state(self, force: bool, servo_rejected: int) -> None:
        """operating_state on change, or when ``force`` (its sub-rate)."""
        ctl, motion = self.ctl, self.motion
        with self.lock:
            internal = motion is not None and motion.active()
            mode = motion.control_mode if motion is not None else "joint"
            rcm_mm, trocar = motion.state_fields() if motion is not None else (0.0, (0.0, 0.0, 0.0))
            estop = self.estop
        grip = round(self.grip, 2)
        state = (
            ctl.following,
            ctl.lease_valid,
            ctl.reason,
            mode,
            internal,
            self.held.cause,
            bool(estop),
            grip,
        )
        if state == self._last_state and not force:
            return
        self._last_state = state
        if self.held.active:
            op = "FAULT"
        elif ctl.following or internal:
            op = "ENABLED"
        else:
            op = "FAULT" if estop else "PAUSED"
        out = self.outlets["operating_state"]
        out.put(
            OperatingState(
                out.header(),
                op,
                mode,
                ctl.following,
                ctl.lease_valid,
                ctl.reason,
                ctl.holds,
                rcm_mm,
                ctl.clipped,
                self.rejected + servo_rejected,
                trocar,
                is_busy=internal,
                grip=grip,
            )
        )

    def close(self) -> None:
        """At exit: write the latency log, log the counters."""
        if self._applied is not None:
            path = self.cfg.latency_log
            if self.cfg.latency_log.endswith(".npy") and self.arm != self.cfg.arm:
                path = f"{path[:-4]}.{self.arm}.npy"  # one file per arm; cfg.arm's keeps the name
            np.save(path, self._applied[: self._n_applied])
        log.info(
            "%s: %d holds, %d setpoints rejected, %d cycles speed-clipped, %d clamped by the keep-out",
            self.arm,
            self.ctl.holds,
            self.rejected,
            self.ctl.clipped,
            self.ctl.keepout_clamped,
        )
