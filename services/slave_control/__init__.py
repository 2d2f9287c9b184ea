"""slave_control: runs the slave arm (MuJoCo here) and tracks servo_jp under a watchdog lease.

The control loop runs at the backend period (1 ms for MuJoCo, in real time: missed periods are
caught up by extra physics steps, and counted). Setpoints arrive on ``slave/<arm>/servo_jp``; they
are validated (joint names, joint limits) and only followed as described in
:mod:`services.slave_control.control`. The service publishes ``measured_js`` and the forceps-tip
``measured_cp`` at ``publish_hz`` and its ``operating_state`` at ``state_hz`` and on change.

Example::

    telesurg slave-control --connect tcp/127.0.0.1:7447 --set arm=arm1
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from services.common import service_main
from services.slave_control.backends import SlaveReading, make_backend
from services.slave_control.control import FollowController, Lease, Setpoint
from services.slave_control.modes import ControlModes, Jog, MotionMode
from services.slave_control.motion import SUPPORTED_JOG_AXES, PtpMotion, jog_step, ptp_duration
from shared.bus import BusConfig, Node
from shared.errors import ConfigError, IKError, KinematicsError
from shared.kinematics import MH3F, matrix_from_quat, within_limits
from shared.kinematics.trocar import axis_angle_to_trocar, pose_to_trocar, posture_adjust
from shared.messages import (
    CartesianPose,
    Command,
    CommandReply,
    EStop,
    JointSetpoint,
    JointState,
    OperatingState,
    SafetyLease,
    Sequencer,
)
from shared.timing import CycleTimer

log = logging.getLogger(__name__)
WARN = frozenset({"hold", "clipped", "engage_refused"})


@dataclass
class SlaveControlConfig:
    """slave_control config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "slave_control"  # instance id (liveliness alive/<service>, header src)
    arm: str = "arm1"  # slave arm id in keys slave/<arm>/...
    backend: str = "mujoco"  # valid: mujoco
    model: str = "mh3f"  # robot model (services/slave_control/models/<model>)
    # rad: start pose — tip at (835, 0, 301) mm, forceps pitched 29° down
    q_home: tuple[float, ...] = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    publish_hz: float = 250.0  # Hz: measured_js and measured_cp
    state_hz: float = 20.0  # Hz: operating_state (also sent on every change)
    setpoint_timeout_ms: float = 100.0  # ms: an older setpoint is stale → hold
    engage_tolerance_rad: float = 0.02  # rad: first followed setpoint must be this close to the arm
    # rad: while following, a setpoint farther than this from the previous one is refused (a jump)
    max_setpoint_step_rad: float = 0.1
    setpoint_source: str = "mapping"  # only this service may publish servo_jp for this arm
    # mm, base frame: the trocar (the scene's trocar site). The RCM error and insertion depth in
    # operating_state are measured against it from the simulated arm's tip pose.
    trocar_mm: tuple[float, float, float] = (500.0, 0.0, 200.0)
    trocar_taught: bool = True  # the configured trocar counts as taught (teach_trocar replaces it)
    jog_speed_mm_s: float = 10.0  # mm/s: Cartesian jog and insert/remove speed
    jog_joint_speed_deg_s: float = 5.0  # deg/s: joint jog speed
    ptp_speed_fraction: float = 0.2  # PTP posture adjustment at this fraction of the joint limits
    command_sources: list[str] = field(default_factory=list)  # who may send commands ([] = anyone)
    # The watchdog's liveliness token is watched too: its death revokes the lease at once
    # (in ms), instead of after the lease lifetime.
    watchdog_service: str = "watchdog"
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session


class SlaveService:
    """Inputs (zenoh callbacks) and the control loop of one slave arm."""

    def __init__(self, cfg: SlaveControlConfig, node: Node, names: tuple[str, ...]) -> None:
        self.cfg, self.node, self.names = cfg, node, names
        self.lower = np.array(MH3F.lower)
        self.upper = np.array(MH3F.upper)
        self.lock = threading.Lock()
        self.lease = Lease()
        self.setpoint: Setpoint | None = None
        self.rejected_setpoints = 0
        self.following = False  # mirrors the controller (set by the control loop)
        self.estop = ""  # latched e-stop cause ("" = none); only an explicit reset clears it
        self.cycle = 0  # control cycles executed; stamped on inputs (see control.py)
        self.dt = 0.001
        # control modes of Jinno 2014 and the slave-side motion sources (PTP, jog)
        self.modes = ControlModes()
        self.trocar = np.array(cfg.trocar_mm) / 1e3
        self.trocar_taught = cfg.trocar_taught
        self.ptp: PtpMotion | None = None
        self.q_cmd = np.array(cfg.q_home, dtype=float)  # last command (set by the loop)
        self.tip = np.zeros(3)  # last measured tip (set by the loop)
        self.rcm_error_m = 0.0  # last measured RCM error (set by update_modes)
        self.reply_seq = Sequencer(cfg.service)

    # -- operator commands (slave/<arm>/command) ----------------------------------------------
    def on_command(self, cmd: Command) -> CommandReply:
        """Answer one operator command (zenoh thread)."""
        with self.lock:
            accepted, reason = self._command(cmd)
        if accepted:
            self.node.event("command", f"{cmd.name} {' '.join(cmd.args)}: {reason}".strip(), arm=self.cfg.arm)
        return CommandReply(self.reply_seq.next(), self.cfg.arm, cmd.name, accepted, reason)

    def _command(self, cmd: Command) -> tuple[bool, str]:
        m, a = self.modes, cmd.arg_map()
        if cmd.arm != self.cfg.arm:
            return False, f"{cmd.name} refused: this is arm {self.cfg.arm}, not {cmd.arm}"
        if self.estop and cmd.name not in ("state", "stop", "abort"):
            return False, f"{cmd.name} refused: {self.estop} (reset first)"
        if cmd.name == "state":
            allowed = "; ".join(f"{k}: {', '.join(v)}" for k, v in m.allowed().items() if v)
            return True, f"{m.label}, motion {m.motion or 'none'}; allowed: {allowed}"[:500]
        if cmd.name == "teach_trocar":
            r = m.teach_trocar()
            if r.accepted:
                self.trocar = self.tip.copy()
                self.trocar_taught = True
                mm = ", ".join(f"{v * 1e3:.1f}" for v in self.trocar)
                return True, f"trocar taught at ({mm}) mm"
            return r.accepted, r.reason
        if cmd.name == "begin_posture_adjust":
            method = a.get("method", "ptp")
            if method != "ptp":
                return (
                    False,
                    f"begin_posture_adjust refused: method {method!r} is not implemented yet (ptp is)",
                )
            try:
                target = posture_adjust(self.q_cmd, self.trocar)
            except (IKError, KinematicsError) as exc:
                return False, f"begin_posture_adjust refused: {exc}"
            r = m.begin_posture_adjust(method)
            if r.accepted:
                duration = ptp_duration(self.q_cmd, target, self.cfg.ptp_speed_fraction)
                self.ptp = PtpMotion(self.q_cmd.copy(), target, duration)
                return True, f"{r.reason}; PTP of J4/J5 over {duration:.1f} s"
            return r.accepted, r.reason
        if cmd.name in ("finish_posture_adjust", "insert", "remove", "stop"):
            if cmd.name != "stop" and self.ptp is not None:
                return False, f"{cmd.name} refused: the PTP posture motion is still running"
            r = getattr(m, cmd.name)()
            return r.accepted, r.reason
        if cmd.name == "abort":
            self.ptp = None
            r = m.abort(a.get("reason", "operator abort"))
            return r.accepted, r.reason
        if cmd.name == "set_motion_mode":
            mode = a.get("mode", "")
            if mode in ("direct_teach", "playback"):
                return False, f"set_motion_mode refused: {mode} is not implemented yet"
            r = m.set_motion_mode(mode)
            return r.accepted, r.reason
        if cmd.name == "jog":
            axis = a.get("axis", "")
            if axis not in SUPPORTED_JOG_AXES:
                return (
                    False,
                    f"jog refused: axis {axis!r} not supported; valid: {', '.join(SUPPORTED_JOG_AXES)}",
                )
            try:
                direction = int(a.get("direction", "1"))
            except ValueError:
                return False, f"jog refused: direction {a.get('direction')!r} must be 1 or -1"
            r = m.jog(a.get("frame", "base"), axis, direction)
            return r.accepted, r.reason
        return False, f"unknown command {cmd.name!r}; valid: {', '.join(COMMANDS)}"

    def stop_internal(self) -> None:
        """Cancel the slave-side motion (PTP and jog); the operator must command it again."""
        with self.lock:
            self.ptp = None
            if self.modes.jog_command is not None:
                self.modes.stop()

    def internal_active(self) -> bool:
        """A slave-side motion (PTP or jog) is commanded (lock held by the caller)."""
        return self.ptp is not None or self.modes.jog_command is not None

    def update_modes(self, reading: SlaveReading) -> None:
        """Measure the forceps against the trocar and feed the control-mode machine (lock held).

        RCM error and depth come from the measured tip pose (MuJoCo's tip site); the axis angle
        from the measured joints. The RCM error is kept for ``operating_state``.
        """
        axis = matrix_from_quat(reading.tip_quat)[:, 0]
        rcm, depth = pose_to_trocar(reading.tip_position, axis, self.trocar)
        self.rcm_error_m = rcm
        try:
            angle: float | None = axis_angle_to_trocar(reading.position, self.trocar)
        except KinematicsError:  # the trocar at the wrist centre: no direction to it
            angle = None
        self.modes.update(depth, angle, self.trocar_taught)

    def on_lease(self, msg: SafetyLease, key: str) -> None:
        now = time.monotonic()
        with self.lock:
            valid_cycles = round(msg.valid_for_ms / 1e3 / self.dt)
            self.lease = Lease(msg.allow, now + msg.valid_for_ms / 1e3, msg.reason, self.cycle, valid_cycles)

    def on_watchdog_alive(self, service: str, alive: bool) -> None:
        if service == self.cfg.watchdog_service and not alive:
            with self.lock:
                self.lease = Lease(False, 0.0, f"{service} not alive")

    def on_estop(self, msg: EStop, key: str) -> None:
        if not msg.applies_to(self.cfg.arm):
            return
        with self.lock:
            was = self.estop
            if msg.action == "estop":
                self.estop = f"e-stop from {msg.header.source}" + (f": {msg.reason}" if msg.reason else "")
            else:
                self.estop = ""
        if msg.action == "estop" and not was:
            self.node.event("estop", self.estop, arm=self.cfg.arm, severity="error")
        elif msg.action == "reset" and was:
            self.node.event("estop_reset", f"e-stop reset by {msg.header.source}", arm=self.cfg.arm)

    def on_setpoint(self, msg: JointSetpoint, key: str) -> None:
        reason = ""
        q = np.array(msg.position)
        prev = self.setpoint
        if msg.names != self.names:
            reason = f"joint names {list(msg.names)} != {list(self.names)}"
        elif np.any(q < self.lower) or np.any(q > self.upper):
            bad = [
                f"{n}={np.degrees(v):.1f}°"
                for n, v, lo, hi in zip(self.names, q, self.lower, self.upper, strict=True)
                if not lo <= v <= hi
            ]
            reason = f"outside joint limits: {', '.join(bad)}"
        elif self.following and msg.follow and prev is not None and prev.follow:
            jump = float(np.max(np.abs(q - prev.position)))
            if jump > self.cfg.max_setpoint_step_rad:
                reason = f"jump of {jump:.3f} rad from the previous setpoint"
        if reason:
            self.rejected_setpoints += 1
            if self.rejected_setpoints <= 5 or self.rejected_setpoints % 1000 == 0:
                self.node.event("setpoint_rejected", reason, arm=self.cfg.arm, severity="warning")
            return
        with self.lock:
            self.setpoint = Setpoint(q, msg.follow, time.monotonic(), self.cycle)


#: Operator commands served on ``slave/<arm>/command`` (args as ``key=value``).
COMMANDS = (
    "state",
    "teach_trocar",
    "begin_posture_adjust",
    "finish_posture_adjust",
    "insert",
    "remove",
    "stop",
    "abort",
    "set_motion_mode",
    "jog",
)


def _internal_step(
    svc: SlaveService,
    ctl: FollowController,
    cfg: SlaveControlConfig,
    reading: SlaveReading,
    q_cmd: np.ndarray,
    lease: Lease,
    now: float,
    dt: float,
    vmax: np.ndarray,
    jog: Jog | None,
    ptp: PtpMotion | None,
    mode: str,
) -> np.ndarray:
    """One control period of a slave-side motion (PTP or jog), only under a valid lease."""
    ctl.pause(reading.position, "slave-side motion (PTP / jog)")
    ok = ctl.lease_ok(lease, now, svc.cycle) and not svc.estop
    ctl.lease_valid = ok
    if not ok:  # any doubt: stop the motion; the operator must command it again
        svc.stop_internal()
        ctl.holds += 1
        svc.node.event(
            "hold",
            f"slave-side motion stopped: {lease.reason or 'lease expired'}",
            arm=cfg.arm,
            severity="warning",
        )
        ctl.track(q_cmd)
        return q_cmd
    try:
        if ptp is not None:
            target = ptp.next(dt)
        else:
            assert jog is not None
            target = jog_step(
                q_cmd,
                jog.frame.value,
                jog.axis,
                jog.direction,
                dt,
                speed_m_s=cfg.jog_speed_mm_s / 1e3,
                joint_speed_rad_s=np.radians(cfg.jog_joint_speed_deg_s),
                trocar=svc.trocar if mode == "trocar" else None,
            )
            if not within_limits(target, MH3F):
                raise IKError("a joint limit is reached")
    except (IKError, KinematicsError) as exc:
        svc.stop_internal()
        svc.node.event("motion_stopped", f"slave-side motion stopped: {exc}", arm=cfg.arm, severity="warning")
        ctl.track(q_cmd)
        return q_cmd
    out: np.ndarray = q_cmd + np.clip(target - q_cmd, -vmax * dt, vmax * dt)
    if ptp is not None and ptp.done and np.allclose(out, ptp.q_to, atol=1e-9):
        with svc.lock:
            svc.ptp = None
        svc.node.event("ptp_done", "posture adjustment PTP reached its target", arm=cfg.arm)
    ctl.track(out)
    return out


def run(cfg: SlaveControlConfig, stop: threading.Event) -> None:
    """Run the slave until ``stop``."""
    if len(cfg.q_home) != len(MH3F.joint_names):
        raise ConfigError(f"q_home needs {len(MH3F.joint_names)} values")
    backend = make_backend(cfg.backend, cfg.model, cfg.q_home)
    with backend, Node(cfg.bus, cfg.site, cfg.service) as node:
        names = backend.joint_names
        if names != MH3F.joint_names:
            raise ConfigError(f"model joints {names} != kinematics {MH3F.joint_names}")
        k = node.keys
        svc = SlaveService(cfg, node, names)
        js_out = node.outlet(k.slave(cfg.arm, "measured_js"))
        cp_out = node.outlet(k.slave(cfg.arm, "measured_cp"))
        state_out = node.outlet(k.slave(cfg.arm, "operating_state"))
        node.subscribe(k.safety(cfg.arm, "lease"), SafetyLease, svc.on_lease, sources=[cfg.watchdog_service])
        node.subscribe(
            k.slave(cfg.arm, "servo_jp"), JointSetpoint, svc.on_setpoint, sources=[cfg.setpoint_source]
        )
        node.subscribe(k.estop, EStop, svc.on_estop)
        node.watch_liveliness(k.alive(cfg.watchdog_service), svc.on_watchdog_alive)
        node.serve(k.command(cfg.arm), Command, svc.on_command, sources=cfg.command_sources or None)
        vmax = np.array(MH3F.max_velocity)
        modes_every = 10  # control cycles between mode-machine updates (100 Hz)

        ctl = FollowController(
            np.array(MH3F.max_velocity),
            setpoint_timeout=cfg.setpoint_timeout_ms / 1e3,
            engage_tolerance=cfg.engage_tolerance_rad,
        )
        dt = svc.dt = backend.dt
        timer = CycleTimer(1.0 / dt)
        pub_every = max(1, round(1.0 / (dt * cfg.publish_hz)))
        state_every = max(1, round(1.0 / (dt * cfg.state_hz)))
        q_cmd = np.array(cfg.q_home, dtype=float)
        reading = backend.read()
        with svc.lock:  # the first operating_state already carries the measurements
            svc.update_modes(reading)
        last_state: tuple[bool, bool, str, str, bool] | None = None
        caught_up = 0
        log.info("slave %s (%s/%s) running at %.0f Hz", cfg.arm, cfg.backend, cfg.model, 1 / dt)
        cycle = 0
        while not stop.is_set():
            now = time.monotonic()
            with svc.lock:
                lease, sp = svc.lease, svc.setpoint
                if svc.estop:
                    lease = Lease(False, 0.0, svc.estop)
                internal = svc.internal_active()
                jog, ptp, mode = svc.modes.jog_command, svc.ptp, svc.modes.control_mode
                motion = svc.modes.motion
                master_slave = (mode == "non_trocar" and motion is None) or (
                    mode in ("non_trocar", "trocar") and motion is MotionMode.MASTER_SLAVE
                )
            if internal:
                q_cmd = _internal_step(svc, ctl, cfg, reading, q_cmd, lease, now, dt, vmax, jog, ptp, mode)
            else:
                if not master_slave:
                    ctl.pause(reading.position, f"master-slave not active in {mode} mode")
                    sp = None
                q_cmd = ctl.update(now, reading.position, q_cmd, lease, sp, dt, svc.cycle)
            svc.q_cmd = q_cmd
            backend.command(q_cmd)
            missed = timer.wait()
            backend.step(1 + missed)  # stay in real time: catch up missed periods
            caught_up += missed
            reading = backend.read()
            cycle += 1
            svc.cycle = cycle
            svc.following = ctl.following
            svc.tip = reading.tip_position
            if cycle % modes_every == 0:
                with svc.lock:
                    svc.update_modes(reading)
                    mode_events, svc.modes.events = svc.modes.events, []
                for kind, text in mode_events:
                    node.event(kind, text, arm=cfg.arm)
            for kind, text in ctl.events:
                node.event(kind, text, arm=cfg.arm, severity="warning" if kind in WARN else "info")
            ctl.events.clear()
            if cycle % pub_every == 0:
                js_out.put(
                    JointState(
                        js_out.header(),
                        names,
                        tuple(reading.position.tolist()),
                        tuple(reading.velocity.tolist()),
                        tuple(reading.effort.tolist()),
                    )
                )
                p, qt = reading.tip_position, reading.tip_quat
                cp_out.put(
                    CartesianPose(
                        cp_out.header(),
                        "base",
                        (float(p[0]), float(p[1]), float(p[2])),
                        (float(qt[0]), float(qt[1]), float(qt[2]), float(qt[3])),
                    )
                )
            lease_ok = ctl.lease_valid
            state = (ctl.following, lease_ok, ctl.reason, svc.modes.control_mode, internal)
            if state != last_state or cycle % state_every == 0:
                last_state = state
                rejected = svc.rejected_setpoints + node.streams.get(k.slave(cfg.arm, "servo_jp")).rejected
                state_out.put(
                    OperatingState(
                        state_out.header(),
                        "ENABLED" if ctl.following or internal else ("FAULT" if svc.estop else "PAUSED"),
                        svc.modes.control_mode,
                        ctl.following,
                        lease_ok,
                        ctl.reason,
                        ctl.holds,
                        round(svc.rcm_error_m * 1e3, 4),
                        ctl.clipped,
                        rejected,
                        (float(svc.trocar[0]), float(svc.trocar[1]), float(svc.trocar[2])),
                    )
                )
        log.info(
            "stopped after %d cycles: %d overruns, %d periods caught up, %d holds, %d setpoints rejected, "
            "%d cycles speed-clipped",
            cycle,
            timer.overruns,
            caught_up,
            ctl.holds,
            svc.rejected_setpoints,
            ctl.clipped,
        )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg slave-control``."""
    return service_main("slave-control", SlaveControlConfig, run, argv, __doc__ or "")
