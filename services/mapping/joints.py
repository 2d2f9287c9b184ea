"""Mappings for the joint-space slaves: all-joints (PLAS, Shim 2015) and VIP (Jang 2014).

Both keep the Cartesian mapping's rules: engage on a *new* clutch press with the operator present,
a fresh slave joint state and a slave lease; the first setpoint is where the slave is (no jump);
disengage on clutch release, operator absence, a stale master stream or a holding slave; every
sample produces a ``servo_jp`` (``follow`` says whether to track it) with ``origin_ns`` = the
master sample's stamp; the watchdog's safety scale multiplies the motion. While following, the
controlled point of the commanded joints (the robot profile's ``tip``: PLAS tip, VIP wrist, model
world frame, the point and frame of the slave's ``measured_cp``) goes out on
``slave/<arm>/setpoint_cp`` at ``target_hz``, as the Cartesian mapping's target does.

* :class:`AllJointsMapping` (``mode = "all_joints"``): master ``measured_js`` increments become
  slave joint increments, integrated per sample (:func:`telesurg.shared.robots.plas.kinematics.map_step`,
  Table-6
  factors or the tip-exact alternative); the master's joint 1 is the on/off switch driving slave
  d1 at ``d1_speed_mm_s``; joint limits clamp and report (one event per clamping episode).
* :class:`VipMapping` (``mode = "vip"``): master tip increments (``measured_cp``, scaled) move the
  wrist reference W; the elbow goes on the line W–V of the arm's virtual incision port V
  (:func:`telesurg.shared.robots.vip.kinematics.vip_ik`). V is chosen at the first engage from the current
  joints
  (:func:`~telesurg.shared.robots.vip.kinematics.select_vip`, ``vip_ev_mm``) and can be set or reallocated
  by an
  operator command on ``mapping/<arm>/command`` while the arm is not following and the slave runs
  no slave-side motion (a new V moves the elbow); every change is an event. ``reallocate_vip``
  takes the joints the slave measures: after an elbow jog on the slave (Step 2 of the paper,
  :mod:`telesurg.shared.robots.vip.elbow_jog`) the new VIP line goes through the moved elbow
  (the reply says how far the elbow was off the previous line and how far the VIP moved). The
  operator's scale commands work as in the other modes. An IK failure (e.g. a joint limit) holds
  the last setpoint.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import numpy as np
from telesurg.services.mapping.engage import EngageGate
from telesurg.services.mapping.master import master_point
from telesurg.services.mapping.scale import SCALE_COMMANDS
from telesurg.services.mapping.work_frame import master_rotation
from telesurg.shared.bus import Node, Outlet
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.elbow import off_line
from telesurg.shared.limits import limit_step
from telesurg.shared.messages import (
    CartesianPose,
    Command,
    CommandReply,
    JointSetpoint,
    JointState,
    SafetyState,
)
from telesurg.shared.robots import arm_profile, get

if TYPE_CHECKING:
    from telesurg.services.mapping import MappingConfig


#: Samples without clamping that end a clamping episode.
CLAMP_QUIET = 50


class _JointBase(EngageGate):
    """Engage and clamp reporting shared by the joint-space mappings (lock-protected)."""

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        profile = arm_profile(cfg.model, slave)
        super().__init__(cfg, node, master, slave, work, profile.joint_names)
        self.profile = profile
        self.lower, self.upper = np.array(profile.lower), np.array(profile.upper)
        self.servo_out: Outlet = node.outlet(node.keys.slave(slave, "servo_jp"))
        self.target_out: Outlet = node.outlet(node.keys.slave(slave, "setpoint_cp"), control=False)
        self.target_period = 1.0 / cfg.target_hz
        self.target_next = 0.0
        self.q_cmd: np.ndarray | None = None
        self._clamping = False
        self._unclamped = 0  # samples without clamping since the last clamped one

    # -- inputs (zenoh threads)
    def on_safety_state(self, msg: SafetyState, key: str) -> None:
        with self.lock:
            if msg.scale != self.safety_scale:
                self.safety_scale = msg.scale
                self._rescaled()
                self._publish_state()

    def _rescaled(self) -> None:
        """The safety scale changed while following (lock held)."""

    # -- logic (lock held)
    def _engaged(self) -> None:
        """Take the references at engage (lock held; q_meas is fresh)."""

    def _try_engage(self) -> None:
        if not self._may_engage():
            return
        assert self.q_meas is not None
        self.q_cmd = self.q_meas.copy()
        self._engaged()
        self._engaged_now(f"engaged {self.master} → {self.slave} ({self.cfg.mode})")

    def _report_clamp(self, joints: tuple[str, ...]) -> None:
        """Count clamped samples; one event when an episode starts and one when it has been over
        for :data:`CLAMP_QUIET` samples (a joint riding its limit does not flood the log)."""
        if joints:
            self.clamped += 1
            self._unclamped = 0
            if not self._clamping:
                self._clamping = True
                text = f"joint limit holds {', '.join(joints)}"
                self.node.event("clamped", text, arm=self.slave, severity="warning")
        elif self._clamping:
            self._unclamped += 1
            if self._unclamped >= CLAMP_QUIET:
                self._clamping = False
                self.node.event("clamped", "joints back inside their limits", arm=self.slave)

    def _put(self, origin_ns: int) -> None:
        q = self.q_cmd if self.following and self.q_cmd is not None else self.q_meas
        if q is None:
            return
        q = np.clip(q, self.lower, self.upper)
        self.servo_out.put(
            JointSetpoint(
                self.servo_out.header(),
                self.profile.joint_names,
                tuple(float(x) for x in q),
                follow=self.following,
                origin_ns=origin_ns,
            )
        )
        now = time.monotonic()
        if self.following and now >= self.target_next:
            self.target_next = max(self.target_next + self.target_period, now)
            p = self.profile.tip(q)
            out = self.target_out
            out.put(CartesianPose(out.header(), "base", (float(p[0]), float(p[1]), float(p[2]))))


class AllJointsMapping(_JointBase):
    """Master joints → slave joints by the Table-6 factors (see the module docstring)."""

    MASTER_INPUT = ("measured_js", JointState)  # the master stream it maps

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        from telesurg.shared.robots.plas import kinematics as plas

        super().__init__(cfg, node, master, slave, work)
        self.plas = plas
        rcfg = get(cfg.model).make_config(cfg.robot)
        self.config = plas.MappingConfig(mode=rcfg.all_joints_mode, d1_speed=rcfg.d1_speed_mm_s / 1e3)
        self.pending: JointState | None = None
        self.qm_prev: np.ndarray | None = None
        self.t_prev = 0

    def on_master(self, msg: JointState, key: str) -> None:
        self.on_master_js(msg, key)

    def on_master_js(self, msg: JointState, key: str) -> None:
        if len(msg.position) != 6:
            return
        with self.lock:
            if self.pending is not None:
                self.conflated += 1
            self.pending = msg
            self.master_rx = time.monotonic()
        self.work.set()

    def _engaged(self) -> None:
        self.qm_prev = None

    def process(self) -> None:
        with self.lock:
            msg, self.pending = self.pending, None
            if self.want_engage and not self.following:
                self._try_engage()
            if msg is None:
                return
            qm = np.array(msg.position)
            if self.following and self.q_cmd is not None:
                if self.qm_prev is not None:
                    dt = min(max((msg.header.stamp_ns - self.t_prev) / 1e9, 0.0), 0.1)
                    switch = 1 if qm[0] >= 0.5 else 0
                    dq = (qm - self.qm_prev) * self.safety_scale
                    try:
                        step = self.plas.map_step(
                            self.q_cmd,
                            self.qm_prev,
                            dq,
                            dt=dt * self.safety_scale,
                            switch=switch,
                            config=self.config,
                        )
                        self.q_cmd = step.q
                        self._report_clamp(step.clamped)
                    except KinematicsError as exc:
                        self.ik_failures += 1
                        if self.ik_failures <= 5:
                            self.node.event(
                                "ik_failure", f"holding: {exc}", arm=self.slave, severity="warning"
                            )
                self.qm_prev, self.t_prev = qm, msg.header.stamp_ns
            self._put(msg.header.stamp_ns)


class PoseJointBase(_JointBase):
    """A joint-space mapping driven by the master's tip (``measured_cp``): the VIP and position
    mappings. The slave point follows the master point's increments from an anchor
    ``ref = (master point, slave point)``; ``last`` is the latest such pair while following, the
    re-anchor when a scale changes."""

    MASTER_INPUT = ("measured_cp", CartesianPose)  # the master stream it maps

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        super().__init__(cfg, node, master, slave, work)
        self.r_ms = master_rotation(cfg)
        self.master_point = master_point
        self.pending: CartesianPose | None = None
        self.ref: tuple[np.ndarray, np.ndarray] | None = None  # (master point, slave point) anchor
        self.last: tuple[np.ndarray, np.ndarray] | None = None  # last (master point, slave target)

    def on_master(self, msg: CartesianPose, key: str) -> None:
        self.on_master_pose(msg, key)

    def on_master_pose(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            if self.pending is not None:
                self.conflated += 1
            self.pending = msg
            self.master_rx = time.monotonic()
        self.work.set()

    def _rescaled(self) -> None:
        """The safety or the operator's scale changed (lock held): re-anchor, no jump."""
        if self.following and self.last is not None:
            self.ref = self.last  # the new scale applies from here on


class VipMapping(PoseJointBase):
    """Master tip → wrist reference → VIP elbow → joints (see the module docstring)."""

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        from telesurg.shared.robots.vip import kinematics as vip

        super().__init__(cfg, node, master, slave, work)
        self.vip = vip
        self.vip_ev_mm: float = get(cfg.model).make_config(cfg.robot).vip_ev_mm
        self.geom = vip.VIP_ARM1 if slave == "arm1" else vip.VIP_ARM2
        self.V: np.ndarray | None = None  # the virtual incision port, m, world frame
        self.vmax = np.array(self.profile.max_velocity)
        self.t_prev = 0

    def _engaged(self) -> None:
        assert self.q_meas is not None and self.buttons is not None
        if self.V is None:
            self.V = self.vip.select_vip(self.q_meas, self.vip_ev_mm / 1e3, self.geom)
            self._vip_event("VIP chosen at the first engage from the current joints")
        self.ref = None  # taken from the next master sample

    def _vip_event(self, why: str) -> None:
        assert self.V is not None
        mm = ", ".join(f"{v * 1e3:.1f}" for v in self.V)
        self.node.event("vip", f"VIP of {self.slave} at ({mm}) mm: {why}", arm=self.slave)

    def process(self) -> None:
        with self.lock:
            msg, self.pending = self.pending, None
            if self.want_engage and not self.following:
                self._try_engage()
            if msg is None:
                return
            pm = self.master_point(self.cfg, msg.position)
            if self.following and self.q_cmd is not None and self.V is not None and self.ref is None:
                # the engage's first sample only anchors: its setpoint is where the slave is, so the
                # slave's engage check (within engage_tolerance_rad of the arm) holds even when the
                # elbow then moves over to a new VIP's line
                self.ref = (pm, self.vip.fk(self.q_cmd, self.geom).wrist)
                self.last = self.ref
            elif self.following and self.q_cmd is not None and self.V is not None:
                assert self.ref is not None
                pm0, w0 = self.ref
                w = w0 + self.scale * self.safety_scale * (self.r_ms @ (pm - pm0))
                try:
                    q = self.vip.vip_ik(w, self.V, self.geom, q4_ref=float(self.q_cmd[3]))
                    # at most half the joint speed limits per sample: after a new VIP the elbow
                    # moves over to its new line gradually instead of jumping
                    dt = min(max((msg.header.stamp_ns - self.t_prev) / 1e9, 0.001), 0.1)
                    self.q_cmd = self.q_cmd + limit_step(q - self.q_cmd, 0.5 * self.vmax * dt)
                    self.last = (pm, w)
                    self._report_clamp(())
                except (IKError, KinematicsError) as exc:
                    self.ik_failures += 1
                    self._report_clamp(("IK: " + str(exc)[:200],))
            self.t_prev = msg.header.stamp_ns
            self._put(msg.header.stamp_ns)

    def on_command(self, cmd: Command) -> CommandReply:
        """``state``, ``set_vip x= y= z=`` (mm, world), ``reallocate_vip [ev_mm=]`` (from joints),
        and the operator's scale commands (``scale_up``, ``scale_down``, ``set_scale value=``)."""
        if cmd.name in SCALE_COMMANDS and cmd.arm == self.slave:
            return self.scale_command(cmd, "vip mapping, ")
        with self.lock:
            ok, reason = self._command(cmd)
        if ok and cmd.name != "state":
            self._vip_event(f"{cmd.name} by the operator")
        return CommandReply(self.reply_seq.next(), self.slave, cmd.name, ok, reason)

    def _command(self, cmd: Command) -> tuple[bool, str]:
        a = cmd.arg_map()
        if cmd.arm != self.slave:
            return False, f"{cmd.name} refused: this mapping drives {self.slave}, not {cmd.arm}"
        if cmd.name == "state":
            v = "none" if self.V is None else ", ".join(f"{x * 1e3:.1f}" for x in self.V)
            return True, f"VIP ({v}) mm; {'following' if self.following else 'not following'}"
        if cmd.name not in ("set_vip", "reallocate_vip"):
            valid = ", ".join(("state", "set_vip", "reallocate_vip", *SCALE_COMMANDS))
            return False, f"unknown command {cmd.name!r}; valid: {valid}"
        if self.following:
            return False, f"{cmd.name} refused: release the clutch first (a new VIP moves the elbow)"
        if self.q_meas is None:
            return False, f"{cmd.name} refused: no slave joint state yet"
        st = self.slave_state
        if st is not None and st.state == "ENABLED" and not st.follow:
            # a slave-side motion (the elbow jog) is moving the joints the VIP would come from
            return False, f"{cmd.name} refused: the slave is moving (elbow jog): let it end or stop it"
        try:
            if cmd.name == "set_vip":
                V = np.array([float(a[k]) for k in ("x", "y", "z")]) / 1e3
                w = self.vip.fk(self.q_meas, self.geom).wrist
                self.vip.vip_ik(w, V, self.geom, q4_ref=float(self.q_meas[3]))  # reachable from here?
            else:
                ev = float(a.get("ev_mm", self.vip_ev_mm)) / 1e3
                V = self.vip.select_vip(self.q_meas, ev, self.geom)
        except KeyError as exc:
            return False, f"set_vip refused: missing {exc} (x=, y=, z= in mm)"
        except ValueError as exc:  # KinematicsError / IKError are ValueErrors, and float() errors
            return False, f"{cmd.name} refused: {exc}"
        old, self.V = self.V, V
        mm = ", ".join(f"{x * 1e3:.1f}" for x in V)
        pose = self.vip.fk(self.q_meas, self.geom)
        w = pose.wrist
        moved = np.linalg.norm(self.vip.vip_elbow(w, V, self.geom) - pose.elbow)
        note = (
            f"; the elbow moves {moved * 1e3:.1f} mm to its new line after the next engage"
            if moved > 1e-4
            else ""
        )
        if old is not None:  # Step 2 shows here: how far the elbow had left the previous line
            off = off_line(pose.elbow, w, old)
            note += (
                f"; VIP moved {np.linalg.norm(V - old) * 1e3:.1f} mm, the elbow was "
                f"{off * 1e3:.1f} mm off the previous VIP line"
            )
        return True, f"VIP at ({mm}) mm{note}"
