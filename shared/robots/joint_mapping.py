"""The joint-space mapping strategies' common part: engage, clamp reporting, setpoint publication.

Both the robots' joint-space strategies (PLAS ``all_joints``, VIP ``vip``) and the generic
``position`` mapping build on it. Rules kept from the Cartesian mapping: engage on a *new* clutch
press with the operator present, a fresh slave joint state and a slave lease (the pair's engage
state machine decides); the first setpoint is where the slave is (no jump); every sample produces
a ``servo_jp`` (``follow`` says whether to track it) with ``origin_ns`` = the master sample's stamp;
the watchdog's safety scale multiplies the motion. While following, the controlled point of the
commanded joints (the robot profile's ``tip``, model world frame) goes out on
``slave/<arm>/setpoint_cp`` at ``target_hz``.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from telesurg.shared.bus import Outlet
from telesurg.shared.haptics.slave_pc import SlavePassivity
from telesurg.shared.messages import CartesianPose, CartesianWrench, JointSetpoint, Message, SafetyState
from telesurg.shared.robots.api import PairContext
from telesurg.shared.robots.registry import arm_profile
from telesurg.shared.teleop.master import master_point
from telesurg.shared.teleop.work_frame import master_rotation, rotation_of

log = logging.getLogger(__name__)

#: Samples without clamping that end a clamping episode.
CLAMP_QUIET = 50


class JointStrategy:
    """Engage and clamp reporting shared by the joint-space mapping strategies (the pair's lock held
    where noted). ``gate``: the pair's engage state machine (:class:`~.api.PairContext`)."""

    #: the master stream it maps: (key suffix, message type)
    MASTER_INPUT: tuple[str, type[Message]] = ("measured_cp", CartesianPose)

    def __init__(self, gate: PairContext) -> None:
        self.gate = gate
        cfg, node, slave = gate.cfg, gate.node, gate.slave
        profile = arm_profile(cfg.model, slave)
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
        with self.gate.lock:
            if msg.scale != self.gate.safety_scale:
                self.gate.safety_scale = msg.scale
                self.rescaled()
                self.gate._publish_state()

    def rescaled(self) -> None:
        """The safety scale changed while following (lock held)."""

    # -- logic (lock held)
    def _engaged(self) -> None:
        """Take the references at engage (lock held; q_meas is fresh)."""

    def _try_engage(self) -> None:
        if not self.gate._may_engage():
            return
        assert self.gate.q_meas is not None
        self.q_cmd = self.gate.q_meas.copy()
        self._engaged()
        self.gate._engaged_now(f"engaged {self.gate.master} → {self.gate.slave} ({self.gate.cfg.mode})")

    def close(self) -> None:
        """The service stops (nothing to write)."""

    def _report_clamp(self, joints: tuple[str, ...]) -> None:
        """Count clamped samples; one event when an episode starts and one when it has been over
        for :data:`CLAMP_QUIET` samples (a joint riding its limit does not flood the log)."""
        if joints:
            self.gate.clamped += 1
            self._unclamped = 0
            if not self._clamping:
                self._clamping = True
                text = f"joint limit holds {', '.join(joints)}"
                self.gate.node.event("clamped", text, arm=self.gate.slave, severity="warning")
        elif self._clamping:
            self._unclamped += 1
            if self._unclamped >= CLAMP_QUIET:
                self._clamping = False
                self.gate.node.event("clamped", "joints back inside their limits", arm=self.gate.slave)

    def _put(self, origin_ns: int) -> None:
        q = self.q_cmd if self.gate.following and self.q_cmd is not None else self.gate.q_meas
        if q is None:
            return
        q = np.clip(q, self.lower, self.upper)
        self.servo_out.put(
            JointSetpoint(
                self.servo_out.header(),
                self.profile.joint_names,
                tuple(float(x) for x in q),
                follow=self.gate.following,
                origin_ns=origin_ns,
                grip=self.gate.grip_command(),
            )
        )
        now = time.monotonic()
        if self.gate.following and now >= self.target_next:
            self.target_next = max(self.target_next + self.target_period, now)
            p = self.profile.tip(q)
            out = self.target_out
            out.put(CartesianPose(out.header(), "base", (float(p[0]), float(p[1]), float(p[2]))))


class PoseJointStrategy(JointStrategy):
    """A joint-space mapping driven by the master's tip (``measured_cp``): the VIP and position
    mappings. The slave point follows the master point's increments from an anchor
    ``ref = (master point, slave point)``; ``last`` is the latest such pair while following, the
    re-anchor when a scale changes."""

    def __init__(self, gate: PairContext) -> None:
        super().__init__(gate)
        self.r_ms = master_rotation(gate.cfg)
        gate.rotation = rotation_of(self.r_ms)
        self.master_point = master_point
        self.pending: CartesianPose | None = None
        self.ref: tuple[np.ndarray, np.ndarray] | None = None  # (master point, slave point) anchor
        self.last: tuple[np.ndarray, np.ndarray] | None = None  # last (master point, slave target)
        # TDPA's slave port (cfg.slave_passivity): backs the slave point off along the contact force
        self.spc = SlavePassivity(gate.cfg.haptics_force_scale) if gate.cfg.slave_passivity else None

    def on_contact_force(self, msg: CartesianWrench, key: str) -> None:
        """The slave's contact force (base frame), for the slave passivity controller."""
        if self.spc is not None:
            with self.gate.lock:
                self.spc.force = np.array(msg.force)

    def passive(self, target: np.ndarray, msg: CartesianPose, *, anchor: bool = False) -> np.ndarray:
        """The slave point's target after TDPA's slave passivity controller (``target`` itself
        without one; lock held). ``anchor``: the engagement's first sample, where the slave port
        starts counting. The controller acts on the mapped point (the VIP: the wrist reference),
        whose motion stands in for the instrument's under the contact force."""
        spc = self.spc
        if spc is None:
            return target
        if anchor:
            spc.engage_at(msg.energy_in_j, msg.header.stamp_ns)
        k = self.gate.scale * self.gate.safety_scale
        return spc.follow(target, msg.energy_in_j, msg.header.stamp_ns, k)

    def close(self) -> None:
        """The service stops: say what the slave passivity controller saw and did, if one ran."""
        if self.spc is not None:
            log.info("[%s] %s", self.gate.slave, self.spc.report())

    def on_master(self, msg: CartesianPose, key: str) -> None:
        with self.gate.lock:
            if self.pending is not None:
                self.gate.conflated += 1
            self.pending = msg
            self.gate.master_rx = time.monotonic()
        self.gate.work.set()

    def rescaled(self) -> None:
        """The safety or the operator's scale changed (lock held): re-anchor, no jump."""
        if self.gate.following and self.last is not None:
            self.ref = self.last  # the new scale applies from here on
