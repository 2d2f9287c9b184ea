"""Joint-space slave for multi-arm models without trocar modes (PLAS, VIP): one process, N arms.

Each arm of the robot profile (:mod:`telesurg.shared.robots`) is a slave of its own: its own lease from the
watchdog (``safety/<arm>/lease``), its own ``servo_jp`` with the arm's joint names, its own
follow/hold logic (:class:`~telesurg.services.slave_control.control.FollowController`: lease, freshness,
new engage, no jump, speed limit) and its own ``measured_js`` / ``measured_cp`` (the profile's
controlled point) / ``operating_state`` (``control_mode = "joint"``). One arm holding does not stop
the other. The e-stop latch applies per arm (``EStop.arm`` or ``*``). A backend fault (a serial
arm's link or controller, its shadow) holds every arm, with the fault as the reason.

Sparse setpoints are interpolated to the control rate (:class:`SetpointInterpolator`: a console at
25 Hz, the slave servoing at 1 kHz, no steps and no overshoot beyond the setpoints).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from telesurg.services.slave_control.backends import FaultHold, SlaveBackend
from telesurg.services.slave_control.control import (
    WARN,
    FollowController,
    Lease,
    Setpoint,
    SetpointInterpolator,
)
from telesurg.shared.bus import Node, Outlet
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import (
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
from telesurg.shared.robots import ArmProfile
from telesurg.shared.timing import CycleTimer, start_loop

if TYPE_CHECKING:
    from telesurg.services.slave_control import SlaveControlConfig

log = logging.getLogger(__name__)


@dataclass
class ArmSlave:
    """Inputs (zenoh threads) and per-arm control state of one arm."""

    profile: ArmProfile
    index: np.ndarray  # positions of the arm's joints in the backend's joint vector
    ctl: FollowController
    max_step_rad: float
    service: str
    lock: threading.Lock = field(default_factory=threading.Lock)
    lease: Lease = field(default_factory=Lease)
    setpoint: Setpoint | None = None
    fresh_setpoint: bool = False  # a new setpoint arrived since the loop last looked
    estop: str = ""
    rejected: int = 0
    cycle: int = 0
    dt: float = 0.001
    interp: SetpointInterpolator = field(default_factory=SetpointInterpolator)
    last_follow: bool = False
    outlets: dict[str, Outlet] = field(default_factory=dict)
    last_state: tuple[object, ...] | None = None
    reply_seq: Sequencer | None = None
    node: Node | None = None
    held: FaultHold = field(default_factory=FaultHold)  # a backend fault holds like a revoked lease

    def on_lease(self, msg: SafetyLease, key: str) -> None:
        now = time.monotonic()
        with self.lock:
            cycles = round(msg.valid_for_ms / 1e3 / self.dt)
            self.lease = Lease(msg.allow, now + msg.valid_for_ms / 1e3, msg.reason, self.cycle, cycles)

    def on_setpoint(self, msg: JointSetpoint, key: str) -> None:
        p = self.profile
        q = np.array(msg.position)
        reason = ""
        if msg.names != p.joint_names:
            reason = f"joint names {list(msg.names)} != {list(p.joint_names)}"
        elif np.any(q < np.array(p.lower)) or np.any(q > np.array(p.upper)):
            bad = [
                f"{n}={v:.4f}"
                for n, v, lo, hi in zip(p.joint_names, q, p.lower, p.upper, strict=True)
                if not lo <= v <= hi
            ]
            reason = f"outside joint limits: {', '.join(bad)}"
        else:
            with self.lock:
                prev = self.setpoint
                following = self.ctl.following
            if following and msg.follow and prev is not None and prev.follow:
                jump = float(np.max(np.abs(q - prev.position)))
                if jump > self.max_step_rad:
                    reason = f"jump of {jump:.3f} from the previous setpoint"
        if reason:
            self.rejected += 1
            if self.node is not None and (self.rejected <= 5 or self.rejected % 1000 == 0):
                self.node.event("setpoint_rejected", reason, arm=p.arm, severity="warning")
            return
        with self.lock:
            src = (msg.origin_ns or msg.header.stamp_ns) / 1e9
            self.setpoint = Setpoint(q, msg.follow, time.monotonic(), self.cycle, src)
            self.fresh_setpoint = True

    def on_estop(self, msg: EStop, key: str) -> None:
        if not msg.applies_to(self.profile.arm):
            return
        with self.lock:
            was = self.estop
            self.estop = f"e-stop from {msg.header.source}" if msg.action == "estop" else ""
        if self.node is not None and bool(was) != bool(self.estop):
            kind, sev = ("estop", "error") if self.estop else ("estop_reset", "info")
            self.node.event(
                kind, self.estop or f"e-stop reset by {msg.header.source}", arm=self.profile.arm, severity=sev
            )

    def on_command(self, cmd: Command) -> CommandReply:
        assert self.reply_seq is not None
        if cmd.arm != self.profile.arm:
            ok, reason = False, f"{cmd.name} refused: this is arm {self.profile.arm}, not {cmd.arm}"
        elif cmd.name == "state":
            with self.lock:
                ok, reason = True, f"joint slave, {'following' if self.ctl.following else self.ctl.reason}"
        else:
            ok, reason = False, f"unknown command {cmd.name!r} for a joint slave; valid: state"
        return CommandReply(self.reply_seq.next(), self.profile.arm, cmd.name, ok, reason)


def run_joint_slave(
    cfg: SlaveControlConfig, stop: threading.Event, backend: SlaveBackend, arms: tuple[ArmProfile, ...]
) -> None:
    """Control every arm of ``arms`` on ``backend`` until ``stop``."""
    with backend, Node(cfg.bus, cfg.site, cfg.service) as node:
        k = node.keys
        names = list(backend.joint_names)
        slaves: list[ArmSlave] = []
        for p in arms:
            missing = [j for j in p.model_joints if j not in names]
            if missing:
                raise ConfigError(f"model {cfg.model} has no joints {missing} for arm {p.arm}")
            a = ArmSlave(
                p,
                np.array([names.index(j) for j in p.model_joints]),
                FollowController(
                    np.array(p.max_velocity),
                    setpoint_timeout=cfg.setpoint_timeout_ms / 1e3,
                    engage_tolerance=cfg.engage_tolerance_rad,
                ),
                cfg.max_setpoint_step_rad,
                cfg.service,
                dt=backend.dt,
                interp=SetpointInterpolator(max_period=cfg.interpolation_max_ms / 1e3),
                reply_seq=Sequencer(cfg.service),
                node=node,
            )
            for stream in ("measured_js", "measured_cp", "operating_state"):
                a.outlets[stream] = node.outlet(k.slave(p.arm, stream))
            node.subscribe(k.safety(p.arm, "lease"), SafetyLease, a.on_lease, sources=[cfg.watchdog_service])
            node.subscribe(
                k.slave(p.arm, "servo_jp"), JointSetpoint, a.on_setpoint, sources=[cfg.setpoint_source]
            )
            node.serve(k.command(p.arm), Command, a.on_command, sources=cfg.command_sources or None)
            node.subscribe(k.estop, EStop, a.on_estop)
            slaves.append(a)

        def on_watchdog_alive(service: str, alive: bool) -> None:
            if service == cfg.watchdog_service and not alive:
                for a in slaves:
                    with a.lock:
                        a.lease = Lease(False, 0.0, f"{service} not alive")

        node.watch_liveliness(k.alive(cfg.watchdog_service), on_watchdog_alive)
        dt = backend.dt
        timer = CycleTimer(1.0 / dt)
        pub_every = max(1, round(1.0 / (dt * cfg.publish_hz)))
        state_every = max(1, round(1.0 / (dt * cfg.state_hz)))
        reading = backend.read()
        q_cmd = reading.position.copy()
        shadow_every = max(1, round(cfg.shadow_report_s / dt))
        log.info("joint slave %s: arms %s at %.0f Hz", cfg.model, ", ".join(p.arm for p in arms), 1 / dt)
        start_loop(cfg.rt_priority)
        cycle = 0

        def period(now: float) -> None:
            """One control period at time ``now``: each arm's next command, one physics step."""
            for a in slaves:
                if reading.fault or a.held.active:  # no motion; a new engage after the fault
                    with a.lock:
                        lease = a.lease
                    a.ctl.lease_valid = a.ctl.lease_ok(lease, now, a.cycle)
                    q_cmd[a.index] = a.held.update(a.ctl, reading.fault, reading.position[a.index])
                else:
                    q_cmd[a.index] = _control(a, now, reading.position[a.index], q_cmd[a.index], dt)
            backend.command(q_cmd)
            backend.step(1)

        while not stop.is_set():
            period(time.monotonic())
            missed = timer.wait()
            # Periods the loop slept through (scheduling stalls) are replayed at once, one by one,
            # each with the reference of its own time: the arm keeps moving smoothly instead of
            # holding the old command for the stall and jumping afterwards, and what is published
            # next is the caught-up state.
            t_wake = time.monotonic()
            for late in range(missed, 0, -1):
                reading = backend.read()
                period(t_wake - late * dt)
            reading = backend.read()
            cycle += 1
            if reading.divergence is not None and timer.every(shadow_every):
                node.event("shadow", f"shadow divergence {reading.divergence.describe()}")
            for i, a in enumerate(slaves):
                a.cycle = cycle
                for kind, text in a.ctl.events:
                    node.event(kind, text, arm=a.profile.arm, severity="warning" if kind in WARN else "info")
                a.ctl.events.clear()
                if timer.every(pub_every):
                    _publish(a, reading.position[a.index], reading.velocity[a.index], reading.effort[a.index])
                    if reading.site_positions is not None:
                        tip = reading.site_positions[i]
                        out = a.outlets["measured_cp"]
                        out.put(
                            CartesianPose(
                                out.header(), "world", (float(tip[0]), float(tip[1]), float(tip[2]))
                            )
                        )
                state = (a.ctl.following, a.ctl.lease_valid, a.ctl.reason, bool(a.estop), a.held.cause)
                if state != a.last_state or timer.every(state_every, 1):
                    a.last_state = state
                    out = a.outlets["operating_state"]
                    rejected = a.rejected + node.streams.get(k.slave(a.profile.arm, "servo_jp")).rejected
                    out.put(
                        OperatingState(
                            out.header(),
                            "ENABLED"
                            if a.ctl.following
                            else ("FAULT" if a.estop or a.held.active else "PAUSED"),
                            "joint",
                            a.ctl.following,
                            a.ctl.lease_valid,
                            a.ctl.reason,
                            a.ctl.holds,
                            0.0,
                            a.ctl.clipped,
                            rejected,
                        )
                    )
        for a in slaves:
            log.info(
                "%s: %d holds, %d setpoints rejected, %d cycles speed-clipped",
                a.profile.arm,
                a.ctl.holds,
                a.rejected,
                a.ctl.clipped,
            )


def _control(a: ArmSlave, now: float, q_meas: np.ndarray, q_cmd: np.ndarray, dt: float) -> np.ndarray:
    """One control period of arm ``a`` at time ``now``: the next joint command."""
    with a.lock:
        lease, sp, fresh = a.lease, a.setpoint, a.fresh_setpoint
        a.fresh_setpoint = False
        if a.estop:
            lease = Lease(False, 0.0, a.estop)
    if sp is not None and fresh:
        if sp.follow and not a.last_follow:
            a.interp.reset()  # a new engage starts a new timeline (no jump)
        a.interp.push(sp.position, sp.source_time, sp.received)
        a.last_follow = sp.follow
    if sp is not None and sp.follow:
        ref = a.interp.sample(now)
        if ref is not None:
            sp = Setpoint(ref, True, sp.received, sp.cycle)
    return a.ctl.update(now, q_meas, q_cmd, lease, sp, dt, a.cycle)


def _publish(a: ArmSlave, q: np.ndarray, v: np.ndarray, e: np.ndarray) -> None:
    out = a.outlets["measured_js"]
    out.put(
        JointState(
            out.header(), a.profile.joint_names, tuple(q.tolist()), tuple(v.tolist()), tuple(e.tolist())
        )
    )
