"""Position mapping (``mode = "position"``): master tip increments → slave tip position, any robot.

For robots without an analytic IK (and any other robot whose registry entry lists ``position``):
the master point (``measured_cp``, :func:`~telesurg.services.mapping.master_point`) moves the
slave's controlled point incrementally,
``p_slave = p_slave0 + scale · safety · R_ms · (p_master − p_master0)``, anchored at the first
master sample after an engage (no jump) and re-anchored when the watchdog's safety scale or the
operator's scale (``scale_up`` / ``scale_down`` / ``set_scale`` on ``mapping/<arm>/command``)
changes.
The target is solved by damped least squares on the registry's ``pose`` / ``jacobian``
(:func:`telesurg.shared.kinematics.solve_position`), joint-limit clamped. The orientation is free,
unless ``keep_tilt``: then the instrument keeps the tilt from the vertical it had at the engage and
turns only about the vertical, so an object it holds stays upright (a tilt the solver cannot keep
is a clamping episode). The clutch rules are the other mappings'
(:class:`~telesurg.services.mapping.engage.EngageGate`). A joint step larger than
``max_joint_step_rad`` between two samples holds the last setpoint (an ``ik_failure`` event, as the
Cartesian mapping's branch-flip check); holds on every sample for ``STUCK_S`` (the master ran ahead
while its samples stalled) disengage, and the next press re-anchors where the slave stands. A joint
riding its limit or a target out of reach is a clamping episode (``clamped`` events, counted).
The setpoints move the joints at most ``SPEED_FRACTION`` of their speed limits (by the master
samples' stamps, as the watchdog judges them): a hand faster than the arm is followed at the arm's
pace, the whole step scaled down so the path stays the same.

The joints go out as ``servo_jp`` for every sample and, as for every joint-space mapping, the
controlled point of the commanded joints as ``slave/<arm>/setpoint_cp`` at ``target_hz`` (frame
``base``: the world frame of the robot's scene, :mod:`telesurg.shared.robots`, as the slave's
``measured_cp``).
The workspace box of the Cartesian mapping (``workspace_*_mm``, the MH3F base frame) does not
apply; the watchdog's workspace does.
"""

from __future__ import annotations

import time

import numpy as np
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics import solve_position
from telesurg.shared.limits import limit_step
from telesurg.shared.messages import CartesianPose, Command, CommandReply
from telesurg.shared.robots.api import PairContext
from telesurg.shared.robots.joint_mapping import PoseJointStrategy

#: [m] a target further than this from what the solver reached counts as out of reach (clamped).
REACH_TOL = 1e-3
#: the setpoints move the joints at most this fraction of their speed limits
SPEED_FRACTION = 0.9
#: [s] a hold on every sample this long disengages (press again to go on from where it stands)
STUCK_S = 0.5
#: [rad] with ``keep_tilt``, a tilt further than this from the engage's counts as not kept (clamped).
TILT_TOL = np.radians(2.0)


class PositionMapping(PoseJointStrategy):
    """Master tip → slave tip position by damped least squares (see the module docstring)."""

    def __init__(self, gate: PairContext) -> None:
        super().__init__(gate)
        self.ik_streak = 0
        self.keep_up: np.ndarray | None = None  # keep_tilt: the world's up in the tip frame
        self.held_since = 0.0  # monotonic s of the streak's first hold
        self.vmax = np.array(self.profile.max_velocity)
        self.t_prev = 0  # ns: the stamp of the previous master sample

    def on_command(self, cmd: Command) -> CommandReply:
        """``state``, ``scale_up``, ``scale_down``, ``set_scale value=`` (the operator's motion scale)."""
        return self.gate.scale_command(cmd, "position mapping, ")

    # -- logic (lock held)
    def _engaged(self) -> None:
        self.ref = self.last = None  # anchored at the next master sample
        self.keep_up = None  # keep_tilt: the tilt at this engage
        self.ik_streak = 0

    def process(self) -> None:
        with self.gate.lock:
            msg, self.pending = self.pending, None
            if self.gate.want_engage and not self.gate.following:
                self._try_engage()
            if msg is None:
                return
            if self.gate.following and self.q_cmd is not None:
                self._follow(msg)
            self.t_prev = msg.header.stamp_ns
            self._put(msg.header.stamp_ns)

    def _follow(self, msg: CartesianPose) -> None:
        assert self.q_cmd is not None
        pm = self.master_point(self.gate.cfg, msg.position)
        try:
            anchor = self.ref is None
            if self.ref is None:
                self.ref = (pm, self.profile.tip(self.q_cmd))
            if self.keep_up is None and self.gate.cfg.keep_tilt:
                self.keep_up = self.profile.pose(self.q_cmd)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            pm0, p0 = self.ref
            target = p0 + self.gate.scale * self.gate.safety_scale * (self.r_ms @ (pm - pm0))
            sol = solve_position(
                self.profile,
                self.q_cmd,
                self.passive(target, msg, anchor=anchor),
                self.lower,
                self.upper,
                keep_up=self.keep_up,
            )
        except (KinematicsError, ValueError, np.linalg.LinAlgError) as exc:
            self._hold(f"holding last valid setpoint: {exc}")
            return
        steps = np.abs(sol.q - self.q_cmd)
        if (step := float(steps.max())) > self.gate.cfg.max_joint_step_rad:
            joint = self.profile.joint_names[int(steps.argmax())]
            self._hold(
                f"holding last valid setpoint: joint step {step:.3f} ({joint}) > "
                f"{self.gate.cfg.max_joint_step_rad}; q {np.round(self.q_cmd, 3).tolist()} → "
                f"{np.round(sol.q, 3).tolist()}"
            )
            return
        if self.ik_streak:
            self.gate.node.event(
                "ik_recovered", f"target valid again after {self.ik_streak} samples", arm=self.gate.slave
            )
            self.ik_streak = 0
        if self.t_prev and msg.header.stamp_ns > self.t_prev:
            # within the joint speed limits (by the samples' stamps, as the watchdog judges the
            # setpoints): a faster hand is followed at the arm's pace, on the same path
            dt = min((msg.header.stamp_ns - self.t_prev) / 1e9, 0.1)
            self.q_cmd = self.q_cmd + limit_step(sol.q - self.q_cmd, SPEED_FRACTION * self.vmax * dt)
        else:
            self.q_cmd = sol.q
        self.last = (pm, target)
        why = tuple(self.profile.joint_names[i] for i in sol.clamped)
        if sol.error > REACH_TOL:
            why += (f"target out of reach by {sol.error * 1e3:.1f} mm",)
        if sol.tilt_error > TILT_TOL:
            why += (f"tilt not kept, off by {np.degrees(sol.tilt_error):.1f} deg",)
        self._report_clamp(why)

    def _hold(self, text: str) -> None:
        self.gate.ik_failures += 1
        self.ik_streak += 1
        now = time.monotonic()
        if self.ik_streak == 1:
            self.held_since = now
            self.gate.node.event("ik_failure", text, arm=self.gate.slave, severity="warning")
        elif now - self.held_since > STUCK_S:
            # the target stays out of a step's reach (the master ran ahead while the samples
            # stalled): the operator's hand and the instrument no longer match; let go, and the
            # next press takes it from here without a jump
            self.gate._disengage(
                f"the target stayed out of reach for {STUCK_S:.1f} s ({self.ik_streak} samples); "
                "press again to go on from here"
            )
            self.ik_streak = 0
