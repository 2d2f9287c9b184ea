"""slave_control: runs the slave arm and tracks servo_jp under a watchdog lease.

The arm is the MuJoCo simulation (``backend = "mujoco"``) or a real arm's joint-servo controller
on a serial port (``backend = "serial"``, :mod:`telesurg.services.slave_control.serial_backend`,
``docs/hardware.md``), optionally with the MuJoCo model as its shadow. A backend fault (link lost,
controller fault or watchdog, shadow divergence) holds the arm like a revoked lease, with the
fault as the reason, until it clears and a new engage comes.

The control loop runs at the backend period (1 ms for MuJoCo, in real time: missed periods are
caught up by extra physics steps, and counted; ``serial_rate_hz`` for a serial arm). Setpoints
arrive on ``slave/<arm>/servo_jp``; they are validated (joint names, joint limits) and only
followed as described in :mod:`telesurg.services.slave_control.control`. The service publishes
``measured_js`` and the forceps-tip ``measured_cp`` at ``publish_hz``, the estimated external
wrench at the tip ``measured_cf`` (for masters with force feedback) at ``wrench_hz``, and its
``operating_state`` at ``state_hz`` and on change. Rates count periods of real time, so they
hold when the loop wakes late and catches up.

Example::

    telesurg slave-control --connect tcp/127.0.0.1:7447 --set arm=arm1
    telesurg slave-control --connect tcp/127.0.0.1:7447 --set backend=serial \
        --set serial_port=/dev/ttyACM0 --set shadow=true
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from telesurg.services.common import service_main
from telesurg.services.slave_control.backends import PUSH_POINTS, FaultHold, SlaveReading, make_backend
from telesurg.services.slave_control.control import WARN, FollowController, Lease, Setpoint, limit_step
from telesurg.services.slave_control.modes import ControlMode, ControlModes, Jog, MotionMode, Phase
from telesurg.services.slave_control.motion import SUPPORTED_JOG_AXES, PtpMotion, jog_step, ptp_duration
from telesurg.services.slave_control.teach import (
    NAME_RE,
    Playback,
    TaughtPoint,
    TeachConfig,
    TeachStore,
    direct_teach_step,
    playback_problem,
)
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError, IKError, KinematicsError
from telesurg.shared.kinematics import MH3F, jacobian, matrix_from_quat, within_limits
from telesurg.shared.kinematics.trocar import axis_angle_to_trocar, pose_to_trocar, posture_adjust
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
from telesurg.shared.timing import CycleTimer, check_rt_priority, start_loop

log = logging.getLogger(__name__)


@dataclass
class SlaveControlConfig:
    """slave_control config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "slave_control"  # instance id (liveliness alive/<service>, header src)
    arm: str = "arm1"  # slave arm id in keys slave/<arm>/...
    backend: str = "mujoco"  # valid: mujoco, serial (a real arm's servo controller, docs/hardware.md)
    # robot model (services/slave_control/models/<model>): mh3f (one forceps arm, trocar modes);
    # plas, vip: two joint-space arms arm1/arm2 in one process (see joint_slave.py)
    model: str = "mh3f"
    # rad: start pose — tip at (835, 0, 301) mm, forceps pitched 29° down
    q_home: tuple[float, ...] = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    publish_hz: float = 250.0  # Hz: measured_js and measured_cp
    wrench_hz: float = 50.0  # Hz: measured_cf (estimated tip wrench; MuJoCo and torque-sensing arms)
    state_hz: float = 20.0  # Hz: operating_state (also sent on every change)
    setpoint_timeout_ms: float = 100.0  # ms: an older setpoint is stale → hold
    # ms: joint slaves interpolate sparse setpoints over their period, at most this long
    interpolation_max_ms: float = 100.0
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
    ptp_speed_fraction: float = 0.2  # PTP moves (posture, playback) at this fraction of the joint limits
    playback_speed_mm_s: float = 20.0  # mm/s: tip speed of a playback in trocar mode
    playback_dwell_s: float = 0.3  # s: the arm rests this long at each taught point of a playback
    # JSON file of taught trocars and programs ("" = kept in memory only); loaded at start, so a
    # taught trocar (the current one) survives a restart
    state_file: str = ""
    teach: TeachConfig = field(default_factory=TeachConfig)  # direct-teach admittance
    # .npy written at exit: one row per setpoint the control loop applied (origin_ns of the master
    # sample, the setpoint's stamp, the wall time it was applied, ns) — for telesurg bench latency
    latency_log: str = ""
    command_sources: list[str] = field(default_factory=list)  # who may send commands ([] = anyone)
    # The watchdog's liveliness token is watched too: its death revokes the lease at once
    # (in ms), instead of after the lease lifetime.
    watchdog_service: str = "watchdog"
    # -- backend = "serial": the joint-servo controller (shared/servo_protocol.py) --
    # serial port or pyserial URL: /dev/ttyACM0, /dev/serial/by-id/... (survives re-plugging),
    # /dev/pts/N (telesurg device emulate-slave), socket://host:port
    serial_port: str = ""
    serial_baud: int = 500_000  # bit/s: the firmware's BAUD (pseudo-terminals ignore it)
    serial_rate_hz: float = 100.0  # Hz: control rate = one SETPOINT per period (the loop's rate)
    # ms: sent in every SETPOINT: the controller stops the joints if no newer one comes in time
    serial_timeout_ms: float = 100.0
    serial_stale_ms: float = 100.0  # ms: no valid STATE for this long → link lost: HOLD, re-open
    # ms: wait this long for the HELLO (an Arduino resets when the port opens: ~1.5 s boot)
    serial_handshake_ms: float = 3000.0
    serial_reconnect_s: float = 0.5  # s: re-open a lost port / re-enable after a watchdog trip this often
    # (0, 1]: setpoints are rate-limited to this fraction of the joint speed limits (bring-up: 0.1)
    serial_speed_fraction: float = 1.0
    # false: handshake and read the arm but never ENABLE it (bring-up step 1: the slave holds
    # with that cause, measured_js shows the joints as you move the arm by hand)
    serial_enable: bool = True
    # MuJoCo shadow (backend = "serial" only): the model runs beside the real arm, fed the same
    # setpoints; a divergence above shadow_limit_rad on any joint for shadow_grace_ms → HOLD
    shadow: bool = False
    shadow_limit_rad: float = 0.05  # rad (m for prismatic joints): a stuck or slipping joint
    shadow_grace_ms: float = 200.0  # ms: how long the divergence may exceed the limit
    shadow_report_s: float = 1.0  # s: period of the "shadow" divergence events
    # SCHED_FIFO priority of the control loop's thread, 1-99 (0: the normal scheduler): a FIFO
    # loop is not preempted by the other processes' threads; needs root or CAP_SYS_NICE (docs/deploy.md)
    rt_priority: int = 0
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session


class SlaveService:
    """Inputs (zenoh callbacks) and the control loop of one slave arm."""

    def __init__(self, cfg: SlaveControlConfig, node: Node, names: tuple[str, ...]) -> None:
        self.cfg, self.node, self.names = cfg, node, names
        self.limits_lo, self.limits_hi = tuple(MH3F.lower), tuple(MH3F.upper)
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
        self.playback: Playback | None = None
        self.playback_name = ""
        self.posture_target: np.ndarray | None = None  # joints after the posture adjustment
        self.store = TeachStore(cfg.state_file or None, cfg.arm)
        if self.store.current_trocar:
            self.trocar = np.array(self.store.trocars[self.store.current_trocar])
            self.trocar_taught = True
        self.backend_push = None  # set by run(): the simulated hand, if the backend has one
        self.reading: SlaveReading | None = None  # last reading (set by the loop)
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
            name = a.get("name", "default")
            if not NAME_RE.match(name):
                return False, f"teach_trocar refused: invalid name {name!r}"
            r = m.teach_trocar()
            if r.accepted:
                self.trocar = self.tip.copy()
                self.trocar_taught = True
                self.store.trocars[name] = (float(self.tip[0]), float(self.tip[1]), float(self.tip[2]))
                self.store.current_trocar = name
                self.store.save()
                mm = ", ".join(f"{v * 1e3:.1f}" for v in self.trocar)
                return True, f"trocar {name!r} taught at ({mm}) mm"
            return r.accepted, r.reason
        if cmd.name == "begin_posture_adjust":
            return self._begin_posture(a.get("method", "ptp"), a.get("program", ""))
        if cmd.name in ("finish_posture_adjust", "insert", "remove"):
            if self.ptp is not None:
                return False, f"{cmd.name} refused: the PTP posture motion is still running"
            if self.playback is not None:
                return False, f"{cmd.name} refused: playback of {self.playback_name!r} is still running"
            r = getattr(m, cmd.name)()
            if r.accepted and cmd.name == "finish_posture_adjust":
                self.posture_target = None
            return r.accepted, r.reason
        if cmd.name == "stop":
            if self.playback is not None:
                self.playback = None
                return True, f"playback of {self.playback_name!r} stopped"
            r = m.stop()
            return r.accepted, r.reason
        if cmd.name == "abort":
            self.ptp = self.playback = None
            r = m.abort(a.get("reason", "operator abort"))
            if m.phase is None:
                self.posture_target = None
            return r.accepted, r.reason
        if cmd.name == "set_motion_mode":
            before = m.motion
            r = m.set_motion_mode(a.get("mode", ""))
            if r.accepted and m.motion is not before:
                self.playback = None  # a new motion mode ends a running playback
            return r.accepted, r.reason
        if cmd.name in ("teach_point", "clear_program", "play"):
            return self._program_command(cmd.name, a.get("program", ""))
        if cmd.name == "programs":
            names = ", ".join(f"{k} ({len(v)} points)" for k, v in sorted(self.store.programs.items()))
            trocars = ", ".join(sorted(self.store.trocars))
            return True, f"programs: {names or 'none'}; trocars: {trocars or 'none'}"[:500]
        if cmd.name == "load_trocar":
            return self._load_trocar(a.get("name", ""))
        if cmd.name == "push":
            return self._push(a)
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

    def _begin_posture(self, method: str, program: str) -> tuple[bool, str]:
        """begin_posture_adjust: target J4/J5 (ptp, jog, direct_teach) or an aligned program."""
        m = self.modes
        angle: float | None = None
        if method == "playback":
            pts = self.store.programs.get(program)
            if pts is None:
                return False, f"begin_posture_adjust refused: no program {program!r} (teach_point first)"
            if problem := playback_problem(pts, "non_trocar", self.trocar if self.trocar_taught else None):
                return False, f"begin_posture_adjust refused: program {program!r}: {problem}"
            angle = axis_angle_to_trocar(np.array(pts[-1].q), self.trocar)
            target = np.array(pts[-1].q)
        else:
            try:
                target = posture_adjust(self.q_cmd, self.trocar)
            except (IKError, KinematicsError) as exc:
                return False, f"begin_posture_adjust refused: {exc}"
        r = m.begin_posture_adjust(method, program_axis_angle_rad=angle)
        if not r.accepted:
            return r.accepted, r.reason
        self.posture_target = target
        if self.reading is not None:  # the machine knows the J4/J5 distance at once (posture jog)
            self.update_modes(self.reading)
        j45 = np.degrees(target[3:5] - self.q_cmd[3:5])
        to_go = f"J4 {j45[0]:+.1f}°, J5 {j45[1]:+.1f}° to go"
        if method == "ptp":
            duration = ptp_duration(self.q_cmd, target, self.cfg.ptp_speed_fraction)
            self.ptp = PtpMotion(self.q_cmd.copy(), target, duration)
            return True, f"{r.reason}; PTP of J4/J5 over {duration:.1f} s"
        if method == "playback":
            self._start_playback(program, "non_trocar")
            return True, f"{r.reason}; playing {program!r} ({len(self.store.programs[program])} points)"
        if method == "jog":
            return True, f"{r.reason}; jog J4/J5 toward the target ({to_go})"
        return True, f"{r.reason}; push the forceps: J4/J5 follow toward the target ({to_go})"

    def _start_playback(self, program: str, mode: str) -> None:
        self.playback_name = program
        self.playback = Playback(
            list(self.store.programs[program]),
            mode,
            self.trocar.copy() if mode == "trocar" else None,
            np.array(MH3F.max_velocity) * self.cfg.ptp_speed_fraction,
            self.cfg.playback_speed_mm_s / 1e3,
            self.cfg.playback_dwell_s,
        )

    def _program_command(self, name: str, program: str) -> tuple[bool, str]:
        """teach_point, clear_program, play (lock held)."""
        m = self.modes
        if not NAME_RE.match(program):
            return False, f"{name} refused: program={program!r} is not a valid name"
        if self.playback is not None:
            return False, f"{name} refused: playback of {self.playback_name!r} is running (stop it first)"
        if name == "clear_program":
            if self.store.programs.pop(program, None) is None:
                return False, f"clear_program refused: no program {program!r}"
            self.store.save()
            return True, f"program {program!r} cleared"
        if name == "teach_point":
            if self.reading is None:
                return False, "teach_point refused: no measurement yet"
            if self.internal_active() and m.motion is not MotionMode.DIRECT_TEACH:
                return False, "teach_point refused: the arm is moving (stop first)"
            r = self.reading
            tip = (float(r.tip_position[0]), float(r.tip_position[1]), float(r.tip_position[2]))
            point = TaughtPoint(tuple(float(v) for v in r.position), tip, m.control_mode)
            if problem := self.store.add_point(program, point):
                return False, f"teach_point refused: {problem}"
            self.store.save()
            n = len(self.store.programs[program])
            mm = ", ".join(f"{v * 1e3:.1f}" for v in tip)
            return True, f"point {n} of {program!r} taught at ({mm}) mm in {m.control_mode} mode"
        # play
        if m.motion is not MotionMode.PLAYBACK or m.phase is not None:
            return False, (
                f"play refused in {m.label}: select the playback motion mode in non_trocar or trocar "
                "mode (posture adjustment by playback starts its program itself)"
            )
        pts = self.store.programs.get(program)
        if pts is None:
            return False, f"play refused: no program {program!r}"
        trocar = self.trocar if self.trocar_taught else None
        if problem := playback_problem(pts, m.control_mode, trocar):
            return False, f"play refused: program {program!r}: {problem}"
        self._start_playback(program, m.control_mode)
        return True, f"playing {program!r} ({len(pts)} points) in {m.control_mode} mode"

    def _load_trocar(self, name: str) -> tuple[bool, str]:
        if name not in self.store.trocars:
            known = ", ".join(sorted(self.store.trocars)) or "none"
            return False, f"load_trocar refused: no trocar {name!r} (taught: {known})"
        if self.modes.control is not ControlMode.NON_TROCAR:
            where = self.modes.label
            return False, f"load_trocar refused in {where}: the trocar changes in non_trocar mode only"
        self.trocar = np.array(self.store.trocars[name])
        self.trocar_taught = True
        self.store.current_trocar = name
        self.store.save()
        mm = ", ".join(f"{v * 1e3:.1f}" for v in self.trocar)
        return True, f"trocar {name!r} loaded: ({mm}) mm"

    def _push(self, a: dict[str, str]) -> tuple[bool, str]:
        """Simulated hand: push the forceps tip (MuJoCo only)."""
        if self.backend_push is None:
            return False, f"push refused: the {self.cfg.backend} backend has no simulated hand"
        try:
            f = np.array([float(a.get(k, "0")) for k in ("fx", "fy", "fz")])
            seconds = float(a.get("seconds", "1"))
        except ValueError:
            return False, "push refused: fx, fy, fz (N) and seconds must be numbers"
        if not (np.all(np.isfinite(f)) and np.linalg.norm(f) <= 100.0 and 0.0 < seconds <= 10.0):
            return False, "push refused: |force| must be ≤ 100 N and 0 < seconds ≤ 10"
        at = a.get("at", "tip")
        if at not in PUSH_POINTS:
            return False, f"push refused: at={at!r}; valid: {', '.join(PUSH_POINTS)}"
        self.backend_push(f, seconds, at)
        return True, f"pushing the {at} with ({f[0]:.1f}, {f[1]:.1f}, {f[2]:.1f}) N for {seconds:.2f} s"

    def stop_internal(self, reason: str = "stopped") -> None:
        """Cancel the slave-side motion (PTP, jog, playback, direct teach); the operator must
        command it again."""
        with self.lock:
            self.ptp = self.playback = None
            if self.modes.jog_command is not None:
                self.modes.stop()
            if self.modes.motion is MotionMode.DIRECT_TEACH:
                self.modes.abort(reason)
                if self.modes.phase is None:
                    self.posture_target = None

    def internal_active(self) -> bool:
        """A slave-side motion is commanded (lock held by the caller): PTP, jog, playback, or
        direct teach (the arm moves when pushed)."""
        return (
            self.ptp is not None
            or self.modes.jog_command is not None
            or self.playback is not None
            or self.modes.motion is MotionMode.DIRECT_TEACH
        )

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
        j45 = None
        if self.posture_target is not None:
            d = self.posture_target[3:5] - reading.position[3:5]
            j45 = (float(d[0]), float(d[1]))
        self.modes.update(depth, angle, self.trocar_taught, j45_to_target_rad=j45)
        if self.modes.phase is None:
            self.posture_target = None

    def on_lease(self, msg: SafetyLease, key: str) -> None:
        now = self.node.received(key)  # polled: the previous tick, so a lease never outlasts its grant
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
        # plain float arithmetic on the message's tuples: numpy on 6 values costs ~10× more, and
        # this runs for every setpoint (1 kHz)
        reason = ""
        pos = msg.position
        prev = self.setpoint
        if msg.names != self.names:
            reason = f"joint names {list(msg.names)} != {list(self.names)}"
        elif not all(lo <= v <= hi for v, lo, hi in zip(pos, self.limits_lo, self.limits_hi, strict=True)):
            bad = [
                f"{n}={math.degrees(v):.1f}°"
                for n, v, lo, hi in zip(self.names, pos, self.limits_lo, self.limits_hi, strict=True)
                if not lo <= v <= hi
            ]
            reason = f"outside joint limits: {', '.join(bad)}"
        elif self.following and msg.follow and prev is not None and prev.follow:
            jump = max(abs(v - w) for v, w in zip(pos, prev.position.tolist(), strict=True))
            if jump > self.cfg.max_setpoint_step_rad:
                reason = f"jump of {jump:.3f} rad from the previous setpoint"
        if reason:
            self.rejected_setpoints += 1
            if self.rejected_setpoints <= 5 or self.rejected_setpoints % 1000 == 0:
                self.node.event("setpoint_rejected", reason, arm=self.cfg.arm, severity="warning")
            return
        with self.lock:
            self.setpoint = Setpoint(
                np.array(pos),
                msg.follow,
                self.node.received(key),
                self.cycle,
                origin_ns=msg.origin_ns,
                stamp_ns=msg.header.stamp_ns,
            )


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
    "teach_point",
    "clear_program",
    "programs",
    "play",
    "load_trocar",
    "push",
)


def tip_wrench(
    q: np.ndarray, tau_ext: np.ndarray
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """External force (N) and torque (N·m) at the forceps tip, base frame, from the external
    joint torques: ``τ = Jᵀ [F; M]`` solved by least squares (the minimum-norm answer near a
    singularity)."""
    w = np.linalg.lstsq(jacobian(q, MH3F).T, tau_ext, rcond=1e-6)[0]
    return (float(w[0]), float(w[1]), float(w[2])), (float(w[3]), float(w[4]), float(w[5]))


@dataclass
class Internal:
    """The slave-side motion of one control period (a snapshot taken under the lock)."""

    jog: Jog | None
    ptp: PtpMotion | None
    playback: Playback | None
    teach: bool  # direct teach: the arm follows a push
    mode: str  # control mode
    phase: Phase | None


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
    job: Internal,
) -> np.ndarray:
    """One control period of a slave-side motion (PTP, jog, playback, direct teach), only under a
    valid lease."""
    ctl.pause(reading.position, "slave-side motion (PTP / jog / playback / direct teach)")
    ok = ctl.lease_ok(lease, now, svc.cycle) and not svc.estop
    ctl.lease_valid = ok
    if not ok:  # any doubt: stop the motion; the operator must command it again
        why = lease.reason or "lease expired"
        svc.stop_internal(f"lease: {why}")
        ctl.holds += 1
        svc.node.event("hold", f"slave-side motion stopped: {why}", arm=cfg.arm, severity="warning")
        ctl.track(q_cmd)
        return q_cmd
    try:
        if job.ptp is not None:
            target = job.ptp.next(dt)
        elif job.playback is not None:
            target = job.playback.next(q_cmd, dt)
        elif job.jog is not None:
            jog = job.jog
            target = jog_step(
                q_cmd,
                jog.frame.value,
                jog.axis,
                jog.direction,
                dt,
                speed_m_s=cfg.jog_speed_mm_s / 1e3,
                joint_speed_rad_s=np.radians(cfg.jog_joint_speed_deg_s),
                trocar=svc.trocar if job.mode == "trocar" else None,
            )
            pt = svc.posture_target
            if job.phase is Phase.POSTURE and pt is not None and jog.axis in ("j4", "j5"):
                j = int(jog.axis[1]) - 1  # a posture jog stops exactly at its target, never past it
                if (target[j] - pt[j]) * jog.direction > 0:
                    target[j] = pt[j]
        else:
            tau = reading.external_torque
            if tau is None:
                raise IKError("direct teach needs an external torque estimate from the backend")
            target = direct_teach_step(
                q_cmd,
                tau,
                dt,
                "posture" if job.phase is Phase.POSTURE else job.mode,
                cfg.teach,
                trocar=svc.trocar,
                posture_target=svc.posture_target,
            )
        if not within_limits(target, MH3F):
            raise IKError("a joint limit is reached")
    except (IKError, KinematicsError) as exc:
        if job.teach:  # direct teach: do not follow this push, stay in the mode
            ctl.track(q_cmd)
            return q_cmd
        svc.stop_internal(str(exc))
        svc.node.event("motion_stopped", f"slave-side motion stopped: {exc}", arm=cfg.arm, severity="warning")
        ctl.track(q_cmd)
        return q_cmd
    out: np.ndarray = q_cmd + limit_step(target - q_cmd, vmax * dt)
    if job.ptp is not None and job.ptp.done and np.allclose(out, job.ptp.q_to, atol=1e-9):
        with svc.lock:
            svc.ptp = None
        svc.node.event("ptp_done", "posture adjustment PTP reached its target", arm=cfg.arm)
    pb = job.playback
    if pb is not None:
        for i in pb.reached:
            err = float(np.linalg.norm(reading.tip_position - np.array(pb.points[i].tip))) * 1e3
            svc.node.event(
                "point_reached",
                f"{svc.playback_name} point {i + 1}/{len(pb.points)}: tip {err:.3f} mm from the taught point",
                arm=cfg.arm,
            )
        pb.reached.clear()
        if pb.done:
            with svc.lock:
                if svc.playback is pb:
                    svc.playback = None
            svc.node.event("playback_done", f"playback of {svc.playback_name} finished", arm=cfg.arm)
    ctl.track(out)
    return out


def run(cfg: SlaveControlConfig, stop: threading.Event) -> None:
    """Run the slave until ``stop``."""
    check_rt_priority(cfg.rt_priority)
    from telesurg.shared import robots

    if robots.get(cfg.model).slave_family != "trocar":
        from telesurg.services.slave_control.joint_slave import run_joint_slave
        from telesurg.shared.robots import arms_of

        arms = arms_of(cfg.model)
        backend = make_backend(cfg.backend, cfg.model, (), tuple(p.tip_site for p in arms), cfg)
        run_joint_slave(cfg, stop, backend, arms)
        return
    if len(cfg.q_home) != len(MH3F.joint_names):
        raise ConfigError(f"q_home needs {len(MH3F.joint_names)} values")
    backend = make_backend(cfg.backend, cfg.model, cfg.q_home, cfg=cfg)
    with backend, Node(cfg.bus, cfg.site, cfg.service) as node:
        names = backend.joint_names
        if names != MH3F.joint_names:
            raise ConfigError(f"model joints {names} != kinematics {MH3F.joint_names}")
        k = node.keys
        svc = SlaveService(cfg, node, names)
        svc.backend_push = getattr(backend, "push", None)
        js_out = node.outlet(k.slave(cfg.arm, "measured_js"))
        cp_out = node.outlet(k.slave(cfg.arm, "measured_cp"))
        cf_out = node.outlet(k.slave(cfg.arm, "measured_cf"))
        state_out = node.outlet(k.slave(cfg.arm, "operating_state"))
        # Leases and setpoints are read by the control loop at each tick (Node.poll): the loop
        # wakes every period anyway, and a callback thread per message cost a GIL hand-over each.
        lease_key, servo_key = k.safety(cfg.arm, "lease"), k.slave(cfg.arm, "servo_jp")
        node.subscribe(lease_key, SafetyLease, svc.on_lease, sources=[cfg.watchdog_service], polled=True)
        node.subscribe(servo_key, JointSetpoint, svc.on_setpoint, sources=[cfg.setpoint_source], polled=True)
        node.subscribe(k.estop, EStop, svc.on_estop)
        node.watch_liveliness(k.alive(cfg.watchdog_service), svc.on_watchdog_alive)
        node.serve(k.command(cfg.arm), Command, svc.on_command, sources=cfg.command_sources or None)
        vmax = np.array(MH3F.max_velocity)
        modes_every = 10  # control cycles between mode-machine updates (100 Hz)
        # Sub-rate tasks run in different cycles (phases 0-3 below: with these periods of 4, 10,
        # 20 and 50 cycles no two of them ever share a cycle), so no cycle carries the sum of their
        # work: measured_js/cp at phase 0, modes 1, measured_cf 2, operating_state 3.

        ctl = FollowController(
            np.array(MH3F.max_velocity),
            setpoint_timeout=cfg.setpoint_timeout_ms / 1e3,
            engage_tolerance=cfg.engage_tolerance_rad,
        )
        dt = svc.dt = backend.dt
        timer = CycleTimer(1.0 / dt)
        pub_every = max(1, round(1.0 / (dt * cfg.publish_hz)))
        wrench_every = max(1, round(1.0 / (dt * cfg.wrench_hz)))
        state_every = max(1, round(1.0 / (dt * cfg.state_hz)))
        reading = backend.read()
        # start from the measured joints (MuJoCo: q_home; a real arm: wherever it stands)
        q_cmd = svc.q_cmd = reading.position.copy()
        with svc.lock:  # the first operating_state already carries the measurements
            svc.update_modes(reading)
        held = FaultHold()  # a backend fault (link, controller, shadow) holds like a revoked lease
        shadow_every = max(1, round(cfg.shadow_report_s / dt))
        last_state: tuple[bool, bool, str, str, bool, str] | None = None
        applied = np.zeros((300_000, 3), dtype=np.int64) if cfg.latency_log else None
        n_applied = 0
        last_sp: Setpoint | None = None
        log.info("slave %s (%s/%s) running at %.0f Hz", cfg.arm, cfg.backend, cfg.model, 1 / dt)
        start_loop(cfg.rt_priority)
        cycle = 0
        while not stop.is_set():
            node.poll()
            now = time.monotonic()
            with svc.lock:
                lease, sp = svc.lease, svc.setpoint
                if svc.estop:
                    lease = Lease(False, 0.0, svc.estop)
                internal = svc.internal_active()
                mode, motion = svc.modes.control_mode, svc.modes.motion
                job = Internal(
                    svc.modes.jog_command,
                    svc.ptp,
                    svc.playback,
                    motion is MotionMode.DIRECT_TEACH,
                    mode,
                    svc.modes.phase,
                )
                master_slave = (mode == "non_trocar" and motion is None) or (
                    mode in ("non_trocar", "trocar") and motion is MotionMode.MASTER_SLAVE
                )
            if applied is not None and sp is not None and sp is not last_sp and n_applied < len(applied):
                applied[n_applied] = (sp.origin_ns, sp.stamp_ns, time.time_ns())
                n_applied += 1
            last_sp = sp
            if reading.fault or held.active:
                if reading.fault and internal:
                    svc.stop_internal(f"fault: {reading.fault}")
                ctl.lease_valid = ctl.lease_ok(lease, now, svc.cycle)
                q_cmd = held.update(ctl, reading.fault, reading.position)
            elif internal:
                q_cmd = _internal_step(svc, ctl, cfg, reading, q_cmd, lease, now, dt, vmax, job)
            else:
                if not master_slave:
                    ctl.pause(reading.position, f"master-slave not active in {mode} mode")
                    sp = None
                q_cmd = ctl.update(now, reading.position, q_cmd, lease, sp, dt, svc.cycle)
            svc.q_cmd = q_cmd
            backend.command(q_cmd)
            missed = timer.wait()
            backend.step(1 + missed)  # stay in real time: catch up missed periods
            reading = backend.read()
            cycle += 1
            svc.cycle = cycle
            svc.following = ctl.following
            svc.tip = reading.tip_position
            svc.reading = reading
            if timer.every(modes_every, 1):
                with svc.lock:
                    svc.update_modes(reading)
                    mode_events, svc.modes.events = svc.modes.events, []
                for kind, text in mode_events:
                    node.event(kind, text, arm=cfg.arm)
            for kind, text in ctl.events:
                node.event(kind, text, arm=cfg.arm, severity="warning" if kind in WARN else "info")
            ctl.events.clear()
            if reading.divergence is not None and timer.every(shadow_every):
                node.event("shadow", f"shadow divergence {reading.divergence.describe()}", arm=cfg.arm)
            if timer.every(pub_every):
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
            if reading.external_torque is not None and timer.every(wrench_every, 2):
                f, m = tip_wrench(reading.position, reading.external_torque)
                cf_out.put(CartesianWrench(cf_out.header(), "base", f, m))
            lease_ok = ctl.lease_valid
            state = (ctl.following, lease_ok, ctl.reason, svc.modes.control_mode, internal, held.cause)
            if state != last_state or timer.every(state_every, 3):
                last_state = state
                rejected = svc.rejected_setpoints + node.streams.get(k.slave(cfg.arm, "servo_jp")).rejected
                op = "ENABLED" if ctl.following or internal else ("FAULT" if svc.estop else "PAUSED")
                state_out.put(
                    OperatingState(
                        state_out.header(),
                        "FAULT" if held.active else op,
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
        if applied is not None:
            np.save(cfg.latency_log, applied[:n_applied])
        log.info(
            "stopped after %d cycles: %d overruns, %d periods caught up, %d holds, %d setpoints rejected, "
            "%d cycles speed-clipped",
            cycle,
            timer.overruns,
            timer.periods - timer.cycles,  # periods caught up
            ctl.holds,
            svc.rejected_setpoints,
            ctl.clipped,
        )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg slave-control``."""
    return service_main("slave-control", SlaveControlConfig, run, argv, __doc__ or "")
