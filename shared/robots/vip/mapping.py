"""VIP mapping (``mode = "vip"``, Jang 2014): master tip → wrist reference → VIP elbow → joints.

Master tip increments (``measured_cp``, scaled) move the wrist reference W; the elbow goes on the
line W–V of the arm's virtual incision port V (:func:`telesurg.shared.robots.vip.kinematics.vip_ik`).
V is chosen at the first engage from the current joints
(:func:`~telesurg.shared.robots.vip.kinematics.select_vip`, the robot knob ``vip_ev_mm``) and can
be set or reallocated by an operator command on ``mapping/<arm>/command`` while the arm is not
following and the slave runs no slave-side motion (a new V moves the elbow); every change is an
event. ``reallocate_vip`` takes the joints the slave measures: after an elbow jog on the slave
(:mod:`telesurg.shared.robots.vip.elbow_jog`) the new VIP line goes through the moved elbow. The
operator's scale commands work as in the other modes. An IK failure holds the last setpoint.
"""

from __future__ import annotations

import numpy as np
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.elbow import off_line
from telesurg.shared.limits import limit_step
from telesurg.shared.messages import Command, CommandReply
from telesurg.shared.robots.api import PairContext
from telesurg.shared.robots.joint_mapping import PoseJointStrategy
from telesurg.shared.robots.registry import get
from telesurg.shared.teleop.scale import SCALE_COMMANDS


class VipMapping(PoseJointStrategy):
    """Master tip → wrist reference → VIP elbow → joints (see the module docstring)."""

    def __init__(self, gate: PairContext) -> None:
        from telesurg.shared.robots.vip import kinematics as vip

        super().__init__(gate)
        cfg = gate.cfg
        self.vip = vip
        rcfg = get(cfg.model).make_config(cfg.robot)
        self.vip_ev_mm: float = rcfg.vip_ev_mm
        site_vip = rcfg.vips_mm.get(gate.slave)
        self.site_vip = None if site_vip is None else np.array(site_vip, dtype=float) / 1e3
        self.geom = vip.VIP_ARM1 if gate.slave == "arm1" else vip.VIP_ARM2
        self.V: np.ndarray | None = None  # the virtual incision port, m, world frame
        self.vmax = np.array(self.profile.max_velocity)
        self.t_prev = 0

    def _engaged(self) -> None:
        assert self.gate.q_meas is not None and self.gate.buttons is not None
        if self.V is None and self.site_vip is not None:
            self.V = self.site_vip.copy()
            self._vip_event("VIP set by the site (vips_mm) at the first engage")
        elif self.V is None:
            self.V = self.vip.select_vip(self.gate.q_meas, self.vip_ev_mm / 1e3, self.geom)
            self._vip_event("VIP chosen at the first engage from the current joints")
        self.ref = None  # taken from the next master sample

    def _vip_event(self, why: str) -> None:
        assert self.V is not None
        mm = ", ".join(f"{v * 1e3:.1f}" for v in self.V)
        self.gate.node.event("vip", f"VIP of {self.gate.slave} at ({mm}) mm: {why}", arm=self.gate.slave)

    def process(self) -> None:
        with self.gate.lock:
            msg, self.pending = self.pending, None
            if self.gate.want_engage and not self.gate.following:
                self._try_engage()
            if msg is None:
                return
            pm = self.master_point(self.gate.cfg, msg.position)
            if self.gate.following and self.q_cmd is not None and self.V is not None and self.ref is None:
                # the engage's first sample only anchors: its setpoint is where the slave is, so the
                # slave's engage check (within engage_tolerance_rad of the arm) holds even when the
                # elbow then moves over to a new VIP's line
                self.ref = (pm, self.vip.fk(self.q_cmd, self.geom).wrist)
                self.last = self.ref
                self.passive(self.ref[1], msg, anchor=True)
            elif self.gate.following and self.q_cmd is not None and self.V is not None:
                assert self.ref is not None
                pm0, w0 = self.ref
                w = w0 + self.gate.scale * self.gate.safety_scale * (self.r_ms @ (pm - pm0))
                try:
                    q = self.vip.vip_ik(self.passive(w, msg), self.V, self.geom, q4_ref=float(self.q_cmd[3]))
                    # at most half the joint speed limits per sample: after a new VIP the elbow
                    # moves over to its new line gradually instead of jumping
                    dt = min(max((msg.header.stamp_ns - self.t_prev) / 1e9, 0.001), 0.1)
                    self.q_cmd = self.q_cmd + limit_step(q - self.q_cmd, 0.5 * self.vmax * dt)
                    self.last = (pm, w)
                    self._report_clamp(())
                except (IKError, KinematicsError) as exc:
                    self.gate.ik_failures += 1
                    self._report_clamp(("IK: " + str(exc)[:200],))
            self.t_prev = msg.header.stamp_ns
            self._put(msg.header.stamp_ns)

    def on_command(self, cmd: Command) -> CommandReply:
        """``state``, ``set_vip x= y= z=`` (mm, world), ``reallocate_vip [ev_mm=]`` (from joints),
        and the operator's scale commands (``scale_up``, ``scale_down``, ``set_scale value=``)."""
        if cmd.name in SCALE_COMMANDS and cmd.arm == self.gate.slave:
            return self.gate.scale_command(cmd, "vip mapping, ")
        with self.gate.lock:
            ok, reason = self._command(cmd)
        if ok and cmd.name != "state":
            self._vip_event(f"{cmd.name} by the operator")
        return CommandReply(self.gate.reply_seq.next(), self.gate.slave, cmd.name, ok, reason)

    def _command(self, cmd: Command) -> tuple[bool, str]:
        a = cmd.arg_map()
        if cmd.arm != self.gate.slave:
            return False, f"{cmd.name} refused: this mapping drives {self.gate.slave}, not {cmd.arm}"
        if cmd.name == "state":
            v = "none" if self.V is None else ", ".join(f"{x * 1e3:.1f}" for x in self.V)
            return True, f"VIP ({v}) mm; {'following' if self.gate.following else 'not following'}"
        if cmd.name not in ("set_vip", "reallocate_vip"):
            valid = ", ".join(("state", "set_vip", "reallocate_vip", *SCALE_COMMANDS))
            return False, f"unknown command {cmd.name!r}; valid: {valid}"
        if self.gate.following:
            return False, f"{cmd.name} refused: release the clutch first (a new VIP moves the elbow)"
        if self.gate.q_meas is None:
            return False, f"{cmd.name} refused: no slave joint state yet"
        st = self.gate.slave_state
        if st is not None and st.state == "ENABLED" and not st.follow:
            # a slave-side motion (the elbow jog) is moving the joints the VIP would come from
            return False, f"{cmd.name} refused: the slave is moving (elbow jog): let it end or stop it"
        try:
            if cmd.name == "set_vip":
                V = np.array([float(a[k]) for k in ("x", "y", "z")]) / 1e3
                w = self.vip.fk(self.gate.q_meas, self.geom).wrist
                self.vip.vip_ik(w, V, self.geom, q4_ref=float(self.gate.q_meas[3]))  # reachable from here?
            else:
                ev = float(a.get("ev_mm", self.vip_ev_mm)) / 1e3
                V = self.vip.select_vip(self.gate.q_meas, ev, self.geom)
        except KeyError as exc:
            return False, f"set_vip refused: missing {exc} (x=, y=, z= in mm)"
        except ValueError as exc:  # KinematicsError / IKError are ValueErrors, and float() errors
            return False, f"{cmd.name} refused: {exc}"
        old, self.V = self.V, V
        mm = ", ".join(f"{x * 1e3:.1f}" for x in V)
        pose = self.vip.fk(self.gate.q_meas, self.geom)
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
