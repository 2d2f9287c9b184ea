"""The MH3F's Cartesian mapping (``mode = "cartesian"``): master pose → forceps tip → joints, with clutch.

dVRK-style: on engage (a clutch-pedal press), the current master pose and the current slave tip
pose become the references; afterwards
``p_slave = p_slave0 + scale · R_ms · (p_master − p_master0)``
and the slave orientation follows the master's rotation increment (``orientation="follow"``) or
stays as it was at engage (``"fixed"``). The target is clamped into the workspace box
(``workspace_min_mm``/``workspace_max_mm``, base frame; each clamping episode an event) and goes
through the 6-axis IK (:mod:`.kinematics`, nearest branch, joint limits); in the slave's trocar
mode through the trocar IK with the nearest feasible target (:mod:`.trocar_clamp`). An IK failure
or a branch flip (a joint step over ``max_joint_step_rad``) holds the last valid setpoint and
publishes an event. With a camera (``camera`` set), master motion is mapped in its view frame and a
camera move re-anchors at the current target (:meth:`CartesianMapping.on_camera_pose`).

Publishes ``slave/<arm>/servo_jp`` for every master sample and ``slave/<arm>/setpoint_cp`` (the
target, ``base`` frame) at ``target_hz`` while following. The engage state machine is the mapping
service's (:class:`~telesurg.shared.robots.api.PairContext`).
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
from telesurg.shared.bus import Outlet
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import IKError
from telesurg.shared.haptics.slave_pc import SlavePassivity
from telesurg.shared.kinematics import matrix_from_quat, quat_from_matrix
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    Command,
    CommandReply,
    JointSetpoint,
    Message,
    OperatingState,
    SafetyState,
)
from telesurg.shared.robots.api import PairContext
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.robots.mh3f.trocar import trocar_ik
from telesurg.shared.robots.mh3f.trocar_clamp import TrocarClamp
from telesurg.shared.robots.registry import get
from telesurg.shared.teleop.camera_frame import view_rotation
from telesurg.shared.teleop.limit_wall import NO_WALL, limit_wall
from telesurg.shared.teleop.master import master_point
from telesurg.shared.teleop.work_frame import master_rotation, rotation_of

log = logging.getLogger(__name__)
#: s between two limit_wall computations (the teleop state's rate: it carries them)
WALL_PERIOD_S = 0.1


class CartesianMapping:
    """Mapping state of one master → slave pair. Thread-safe: zenoh callbacks call in."""

    MASTER_INPUT: tuple[str, type[Message]] = ("measured_cp", CartesianPose)  # the master stream it maps

    def __init__(self, gate: PairContext) -> None:
        self.gate = gate
        cfg, node, slave = gate.cfg, gate.node, gate.slave
        self.geom = MH3F
        self.r_ms = master_rotation(cfg)  # (a camera pose replaces it: on_camera_pose)
        gate.rotation = rotation_of(self.r_ms)
        self.r_ms_rows: list[list[float]] = self.r_ms.tolist()
        self.camera_poses = 0  # camera view-frame changes applied (on_camera_pose)
        self.servo_out: Outlet = node.outlet(node.keys.slave(slave, "servo_jp"))
        self.target_out: Outlet = node.outlet(node.keys.slave(slave, "setpoint_cp"), control=False)
        self.target_period = 1.0 / cfg.target_hz
        self.target_next = 0.0
        self.q_last: np.ndarray | None = None
        # anchor of the engagement: master point, slave tip (floats), B = rm0ᵀ r_msᵀ rs0 (the target
        # rotation is r_ms R(q) B) and the slave rotation rs0 (see _set_ref)
        self.ref: tuple[list[float], list[float], np.ndarray, np.ndarray] | None = None
        self.ik_streak = 0
        self.last_pose: CartesianPose | None = None  # last master sample mapped while following
        self.last_target: np.ndarray | None = None  # its slave target (4×4)
        # workspace box, m, as floats (the per-sample clamp in _target)
        self.ws_lo = [v / 1e3 for v in cfg.workspace_min_mm]
        self.ws_hi = [v / 1e3 for v in cfg.workspace_max_mm]
        self._clamping = False
        self.trocar_clamp = TrocarClamp(
            node, slave, self.geom, get(cfg.model).make_config(cfg.robot).trocar_depth_mm
        )
        # Newest master sample not yet mapped. The zenoh callback only stores it; the service
        # loop maps it. If mapping ever falls behind, it maps the newest sample and skips the
        # rest (counted in ``conflated``) instead of queueing latency.
        self.pending: CartesianPose | None = None
        self.last_stamp_ns = 0  # header stamp of the last servo_jp sent (wall clock, ns)
        self.pending_rx_ns = 0  # wall clock (ns) when ``pending`` reached the callback
        # cfg.latency_log: (origin, received, mapping began, published) ns per servo_jp sent
        self.trace: np.ndarray | None = np.zeros((300_000, 4), dtype=np.int64) if cfg.latency_log else None
        self.traced = 0
        # TDPA's slave port (cfg.slave_passivity): backs the target off along the contact force
        self.spc = SlavePassivity(cfg.haptics_force_scale) if cfg.slave_passivity else None
        self.wall_next = 0.0  # monotonic s: the next limit_wall (at the teleop state's rate)

    # -- inputs -----------------------------------------------------------------------
    def on_safety_state(self, msg: SafetyState, key: str) -> None:
        with self.gate.lock:
            if msg.scale == self.gate.safety_scale:
                return
            old, self.gate.safety_scale = self.gate.safety_scale, msg.scale
            self.rescaled()
            self.gate._publish_state()
        self.gate.node.event(
            "scale",
            f"motion scale {self.gate.scale * old:.3g} → {self.gate.scale * msg.scale:.3g} "
            f"(safety {msg.state}{': ' + '; '.join(msg.causes) if msg.causes else ''})",
            arm=self.gate.slave,
            severity="warning" if msg.scale < 1.0 else "info",
        )

    def on_contact_force(self, msg: CartesianWrench, key: str) -> None:
        """The slave's contact force (base frame), for the slave passivity controller."""
        if self.spc is not None:
            with self.gate.lock:
                self.spc.force = np.array(msg.force)

    def on_camera_pose(self, msg: CartesianPose, key: str) -> None:
        """The camera's pose: map in its view frame from now on, re-anchored (no jump)."""
        r = view_rotation(msg)
        with self.gate.lock:
            if np.allclose(r, self.r_ms, atol=1e-9):
                return
            first = self.camera_poses == 0
            self.camera_poses += 1
            self.r_ms = r
            self.r_ms_rows = r.tolist()
            self.gate.rotation = rotation_of(r)
            self.rescaled()
        if first or self.gate.following:
            self.gate.node.event(
                "camera_frame",
                f"master motion mapped in camera {self.gate.cfg.camera}'s view"
                + (" (re-anchored while following)" if self.gate.following else ""),
                arm=self.gate.slave,
            )

    def rescaled(self) -> None:
        """Re-anchor at the current target: a new scale applies to motion from here on (lock held)."""
        if self.gate.following and self.last_pose is not None and self.last_target is not None:
            lp, lt = self.last_pose, self.last_target
            self._set_ref(
                master_point(self.gate.cfg, lp.position),
                matrix_from_quat(np.array(lp.orientation)),
                lt[:3, 3].copy(),
                lt[:3, :3].copy(),
            )

    def on_command(self, cmd: Command) -> CommandReply:
        """``state``, ``scale_up``, ``scale_down``, ``set_scale value=`` (the operator's motion scale)."""
        return self.gate.scale_command(cmd, "")

    def on_master(self, msg: CartesianPose, key: str) -> None:
        with self.gate.lock:
            self.gate.master_rx = time.monotonic()

            if self.pending is not None:
                self.gate.conflated += 1
            self.pending = msg
            self.pending_rx_ns = wall_ns()
        self.gate.work.set()

    def process(self) -> None:
        """Map the newest master sample, if any (older unprocessed ones are skipped)."""
        with self.gate.lock:
            msg, self.pending = self.pending, None
            if msg is None:
                return
            rx_ns, begin_ns = self.pending_rx_ns, wall_ns()
            if self.gate.want_engage and not self.gate.following:
                self._try_engage(msg)
            sent = self.servo_out.sent
            self._publish(msg)
            tr = self.trace
            if tr is not None and self.servo_out.sent > sent and self.traced < len(tr):
                tr[self.traced] = (msg.header.stamp_ns, rx_ns, begin_ns, self.last_stamp_ns)
                self.traced += 1

    # -- internals (lock held) ------------------------------------------------------------
    def close(self) -> None:
        """The service stops: write the latency trace (``latency_log``), if any."""
        if self.trace is not None:
            np.save(self.gate.cfg.latency_log, self.trace[: self.traced])
        if self.spc is not None:
            log.info("[%s] %s", self.gate.slave, self.spc.report())

    def _try_engage(self, pose: CartesianPose) -> None:
        if not self.gate._may_engage():
            return
        assert self.gate.q_meas is not None
        t_s0 = fk(self.gate.q_meas, self.geom)
        self._set_ref(
            master_point(self.gate.cfg, pose.position),
            matrix_from_quat(np.array(pose.orientation)),
            t_s0[:3, 3].copy(),
            t_s0[:3, :3].copy(),
        )
        self.q_last = self.gate.q_meas.copy()
        self.trocar_clamp.reset(pose.header.stamp_ns)
        self.last_pose = self.last_target = None
        self.ik_streak = 0
        if self.spc is not None:
            self.spc.engage_at(pose.energy_in_j, pose.header.stamp_ns)
        k = self.gate.scale * self.gate.safety_scale
        self.gate._engaged_now(f"engaged {self.gate.master} → {self.gate.slave} at scale {k:.3g}")

    def _set_ref(self, pm0: np.ndarray, rm0: np.ndarray, ps0: np.ndarray, rs0: np.ndarray) -> None:
        """Anchor at (master point, master rotation, slave tip, slave rotation), kept in the form
        :meth:`_target` uses for every sample: floats for the positions, ``B = rm0ᵀ r_msᵀ rs0`` so
        the target rotation is ``r_ms R(q) B``."""
        self.ref = (pm0.tolist(), ps0.tolist(), rm0.T @ self.r_ms.T @ rs0, rs0)

    def _target(self, pose: CartesianPose) -> np.ndarray:
        # Runs for every master sample: plain floats for the 3-vectors (numpy on 3 values costs
        # several µs per operation), numpy only for the two 3×3 products.
        assert self.ref is not None
        pm, ps, b_rot, rs0 = self.ref
        r = self.r_ms_rows
        m = (
            pose.position
            if self.gate.cfg.master_mode == "pen"
            else master_point(self.gate.cfg, pose.position).tolist()
        )
        k = self.gate.scale * self.gate.safety_scale
        d0, d1, d2 = m[0] - pm[0], m[1] - pm[1], m[2] - pm[2]
        p = [ps[i] + k * (r[i][0] * d0 + r[i][1] * d1 + r[i][2] * d2) for i in range(3)]
        clamped = [min(max(v, lo), hi) for v, lo, hi in zip(p, self.ws_lo, self.ws_hi, strict=True)]
        t = np.eye(4)
        if clamped != p:
            self.gate.clamped += 1
            if not self._clamping:
                self._clamping = True
                moved = ", ".join(
                    f"{ax} {a * 1e3:.1f}→{b * 1e3:.1f} mm"
                    for ax, a, b in zip("xyz", p, clamped, strict=True)
                    if a != b
                )
                self.gate.node.event(
                    "clamped",
                    f"target clamped into the workspace: {moved}",
                    arm=self.gate.slave,
                    severity="warning",
                )
        elif self._clamping:
            self._clamping = False
            self.gate.node.event("clamped", "target back inside the workspace", arm=self.gate.slave)
        t[:3, 3] = clamped
        if self.gate.cfg.orientation == "follow":
            t[:3, :3] = self.r_ms @ matrix_from_quat(pose.orientation) @ b_rot
        else:
            t[:3, :3] = rs0
        return t

    def _publish(self, pose: CartesianPose) -> None:
        if self.gate.following:
            target = self._target(pose)
            if self.spc is not None:
                k = self.gate.scale * self.gate.safety_scale
                target[:3, 3] = self.spc.follow(target[:3, 3], pose.energy_in_j, pose.header.stamp_ns, k)
            assert self.q_last is not None
            try:
                st = self.gate.slave_state
                if st is not None and st.control_mode == "trocar":
                    # trocar mode: the tip follows the master; the forceps pivots about the
                    # trocar (remote centre of motion), its roll kept continuous; a target out of
                    # reach, depth or joint speed is brought to the nearest feasible one
                    tc = self.trocar_clamp.solve(
                        target[:3, 3], np.array(st.trocar), self.q_last, pose.header.stamp_ns
                    )
                    q, target[:3, 3] = tc.q, tc.tip
                else:
                    q = ik(target, self.q_last, self.geom)
                step = max(abs(a - b) for a, b in zip(q.tolist(), self.q_last.tolist(), strict=True))
                if step > self.gate.cfg.max_joint_step_rad:
                    raise IKError(f"branch flip: joint step {step:.3f} rad")
            except IKError as exc:
                self.gate.ik_failures += 1
                self.ik_streak += 1
                if self.ik_streak == 1:
                    self.gate.node.event(
                        "ik_failure",
                        f"holding last valid setpoint: {exc}",
                        arm=self.gate.slave,
                        severity="warning",
                    )
            else:
                if self.ik_streak:
                    self.gate.node.event(
                        "ik_recovered",
                        f"IK valid again after {self.ik_streak} samples",
                        arm=self.gate.slave,
                    )
                self.ik_streak = 0
                self.q_last = q
                self.last_pose, self.last_target = pose, target
                now = time.monotonic()
                if now >= self.wall_next:
                    self.wall_next = now + WALL_PERIOD_S
                    self.gate.limit_wall = self._limit_wall(pose, target, q, st)
                if now >= self.target_next:
                    self.target_next = max(self.target_next + self.target_period, now)
                    h = self.target_out.header()
                    quat = quat_from_matrix(target[:3, :3])
                    self.target_out.put(CartesianPose(h, "base", _vec3(target[:3, 3]), _quat(quat)))
        q_pub = self.q_last if self.q_last is not None else self.gate.q_meas
        if q_pub is None:
            return
        h = self.servo_out.header()
        self.last_stamp_ns = h.stamp_ns
        self.servo_out.put(
            JointSetpoint(
                h,
                self.geom.joint_names,
                tuple(q_pub.tolist()),
                follow=self.gate.following,
                origin_ns=pose.header.stamp_ns,
                grip=self.gate.grip_command(),
            )
        )

    def _limit_wall(
        self, pose: CartesianPose, target: np.ndarray, q: np.ndarray, st: OperatingState | None
    ) -> tuple[float, float, float, float]:
        """The slave's nearest joint limit as a wall in the master frame (shared/teleop/limit_wall.py),
        linearised at this target; none with a virtual-trocar master (its handle is not the
        mapped point)."""
        cfg = self.gate.cfg
        if cfg.master_mode != "pen":
            return NO_WALL
        rot = target[:3, :3]
        if st is not None and st.control_mode == "trocar":
            trocar = np.array(st.trocar)

            def solve(p: np.ndarray) -> np.ndarray:
                return trocar_ik(p, trocar, q, geom=self.geom)
        else:

            def solve(p: np.ndarray) -> np.ndarray:
                t = np.eye(4)
                t[:3, :3], t[:3, 3] = rot, p
                return ik(t, q, self.geom)

        k = self.gate.scale * self.gate.safety_scale
        return limit_wall(
            solve,
            target[:3, 3],
            q,
            np.array(self.geom.lower),
            np.array(self.geom.upper),
            math.radians(cfg.limit_wall_margin_deg),
            k * self.r_ms,
            np.array(pose.position),
        )


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _quat(q: np.ndarray) -> tuple[float, float, float, float]:
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
