"""mapping: master pose → slave joint setpoints (Cartesian incremental mapping with clutch).

dVRK-style: on engage (a clutch-pedal press), the current master pose and the current slave tip
pose become the references; afterwards
``p_slave = p_slave0 + scale · R_ms · (p_master − p_master0)``
and the slave orientation follows the master's rotation increment (``orientation="follow"``) or
stays as it was at engage (``"fixed"``). Engaging or re-clutching therefore never makes the slave
jump. The target goes through the 6-axis IK (nearest branch, joint limits); an IK failure or a
branch flip holds the last valid setpoint and publishes an event.

The slave target is clamped into the workspace box (``workspace_min_mm``/``workspace_max_mm``);
each clamping episode is counted and reported as an event naming the axis and the change. The
watchdog's ``safety/<arm>/state`` carries a motion-scale factor (< 1 while DEGRADED, e.g. over
the latency budget); the mapping multiplies its scale by it, re-anchoring so the change makes no
jump.

The service publishes ``slave/<arm>/servo_jp`` for every master sample (``follow`` tells the
slave whether to track it), ``slave/<arm>/setpoint_cp`` (the Cartesian target, at ``target_hz``
for display) while following, and each pair's teleop state (DISABLED / IDLE / ENGAGING /
ENABLED / HOLDING, its reason and the scales in use) on ``mapping/<arm>/teleop_state`` at 10 Hz
and on every change (:mod:`telesurg.services.mapping.engage`).

Master modes (``master_mode``): ``pen`` maps the master position as the tip; ``virtual_trocar``
(Jinno 2014, Fig. 7) treats it as the handle of a dummy forceps pivoting in a virtual trocar on the
console and maps the dummy tip beyond the fulcrum (:func:`master_point`), so the surgeon feels the
same fulcrum effect as with the real forceps in the patient.

Work frame (``master_frame = "work"``): master motion is mapped in the laparoscope's view frame
(``work_frame_rpy_deg``, as the slave's ``work`` jogs), the master's axes as the surgeon sees the
picture (:mod:`telesurg.services.mapping.work_frame`); with ``camera`` set, the camera's pose
replaces it once it arrives.

Camera frame (``camera`` set, Cartesian mode): master motion is mapped in the endoscope's view
frame, the dVRK convention — the master frame is the surgeon's view (x right, y up, z toward the
surgeon), so moving the hand to the right moves the instrument to the right *in the picture*.
``R_ms`` is then the camera's rotation (``camera/<cam>/measured_cp``, optical frame) times
``diag(1, −1, −1)``; until the first camera pose arrives, and at a site without a camera, the
fixed ``master_to_slave_rpy_deg`` applies. A camera move re-anchors at the current target, so it
makes no jump (:meth:`ArmMapping.on_camera_pose`).

Engage needs a *new* pedal press: after any disengage not made by the operator (master stream
stale, slave holding, operator absent) the pedal must be released and pressed again.

Example::

    telesurg mapping --connect tcp/127.0.0.1:7447 --set 'pairs=["m1:arm1"]' --set scale=0.5
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.services.common import service_main
from telesurg.services.mapping.camera_frame import view_rotation
from telesurg.services.mapping.engage import EngageGate
from telesurg.services.mapping.joints import AllJointsMapping, PoseJointBase, VipMapping
from telesurg.services.mapping.master import master_point
from telesurg.services.mapping.position import PositionMapping
from telesurg.services.mapping.trocar import TrocarClamp
from telesurg.services.mapping.work_frame import MASTER_FRAMES, master_rotation
from telesurg.shared import robots
from telesurg.shared.authority import Authority, AuthorityConfig, summary
from telesurg.shared.bus import BusConfig, Node, Outlet, only
from telesurg.shared.errors import AuthorityError, ConfigError, IKError
from telesurg.shared.kinematics import matrix_from_quat, quat_from_matrix
from telesurg.shared.messages import (
    CartesianPose,
    Command,
    CommandReply,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyState,
    Sequencer,
)
from telesurg.shared.pairs import parse_pair
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.timing import check_rt_priority, start_loop

log = logging.getLogger(__name__)
ORIENTATION_MODES = ("follow", "fixed")
MASTER_MODES = ("pen", "virtual_trocar")


@dataclass
class MappingConfig:
    """mapping config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "mapping"  # instance id (liveliness alive/<service>, header src)
    pairs: list[str] = field(default_factory=lambda: ["m1:arm1"])  # "master_arm:slave_arm"
    # the mapping mode, one the robot's registry entry lists (`telesurg robots`): the robot's own
    # strategies (mh3f: cartesian; plas: all_joints; vip: vip) or the generic position (master tip
    # increments → slave tip position by damped least squares, any robot)
    mode: str = "cartesian"
    model: str = "mh3f"  # slave robot model, a name in the robot registry (shared/robots)
    # the robot's own knobs (its config dataclass, shared/robots/<model>/config.py; e.g.
    # --set robot.vip_ev_mm=40): checked against the robot's config at start
    robot: dict[str, Any] = field(default_factory=dict)
    scale: float = 0.5  # slave translation / master translation (motion scaling), 0 < scale <= 2
    orientation: str = "follow"  # follow: apply master rotation increments; fixed: keep engage pose
    # pen: the master position is the tip; virtual_trocar (Jinno 2014, Fig. 7): it is the handle of
    # a dummy forceps pivoting in a virtual trocar, and the dummy tip beyond it is mapped
    master_mode: str = "pen"
    virtual_trocar_mm: tuple[float, float, float] = (0.0, 0.0, -100.0)  # master frame
    dummy_forceps_mm: float = 250.0  # handle → dummy tip, along the dummy forceps
    # Rotation of the master frame expressed in the slave base frame, roll/pitch/yaw in degrees.
    master_to_slave_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # fixed: the master frame is master_to_slave_rpy_deg; work: master motion in the work frame,
    # the laparoscope's view (master x = image right, y = image up, z = toward the surgeon;
    # services/mapping/work_frame.py): the camera's pose where `camera` is set, else
    # work_frame_rpy_deg
    master_frame: str = "fixed"
    # deg, roll/pitch/yaw of the work frame (x image right, y image down, z into the image) in the
    # slave base frame, as slave_control's `work` jogs; default: looking down, patient's head up
    work_frame_rpy_deg: tuple[float, float, float] = (180.0, 0.0, -90.0)
    # camera id: map master motion in its view frame (camera/<cam>/measured_cp; Cartesian mode;
    # "" = the fixed master_to_slave_rpy_deg, a site without a camera)
    camera: str = ""
    camera_source: str = "camera"  # the only publisher accepted on camera/<cam>/measured_cp
    master_timeout_ms: float = 100.0  # ms: master stream older than this disengages
    slave_timeout_ms: float = 100.0  # ms: slave measured_js older than this refuses engage
    # rad: a setpoint step larger than this between two samples is an IK branch flip → hold
    max_joint_step_rad: float = 0.1
    target_hz: float = 100.0  # Hz: setpoint_cp (for display; servo_jp carries every sample)
    workspace_min_mm: tuple[float, float, float] = (150.0, -600.0, -200.0)  # target box, base frame
    workspace_max_mm: tuple[float, float, float] = (1100.0, 600.0, 800.0)
    # Only these services may publish the inputs (others are rejected and counted; "" = anyone).
    master_source: str = "master_capture"
    slave_source: str = "slave_control"
    watchdog_source: str = "watchdog"
    # SCHED_FIFO priority of the thread that maps the samples, 1-99 (0: the normal scheduler): it
    # is not preempted mid-sample by the other processes' threads; needs root or CAP_SYS_NICE
    rt_priority: int = 0
    # .npy written at exit (cartesian mode): one row per servo_jp sent — the master sample's stamp,
    # when its callback got it, when the loop began to map it and the servo_jp's own stamp (wall
    # clock, ns) — for the stages of telesurg bench latency ("" = none)
    latency_log: str = ""
    # who may send the operator's commands (scale, VIP) and the confirmation of VIP changes
    # (shared/authority.py; set once for the site in [site.authority])
    authority: AuthorityConfig = field(default_factory=AuthorityConfig)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        check_rt_priority(self.rt_priority)
        if not 1.0 <= self.target_hz <= 1000.0:
            raise ConfigError(f"target_hz={self.target_hz} outside [1, 1000]")
        if not 0.0 < self.scale <= 2.0:
            raise ConfigError(f"scale={self.scale} outside (0, 2]")
        if self.orientation not in ORIENTATION_MODES:
            raise ConfigError(
                f"orientation {self.orientation!r} invalid; valid: {', '.join(ORIENTATION_MODES)}"
            )
        robot = robots.get(self.model)
        if self.mode not in robot.mapping_modes:
            raise ConfigError(
                f"mapping mode {self.mode!r} does not fit robot model {self.model!r}; "
                f"modes that fit it: {', '.join(robot.mapping_modes)}"
            )
        robot.make_config(self.robot)
        if self.master_frame not in MASTER_FRAMES:
            raise ConfigError(
                f"master_frame {self.master_frame!r} invalid; valid: {', '.join(MASTER_FRAMES)}"
            )
        if self.master_mode not in MASTER_MODES:
            raise ConfigError(f"master_mode {self.master_mode!r} invalid; valid: {', '.join(MASTER_MODES)}")
        if not 10.0 <= self.dummy_forceps_mm <= 1000.0:
            raise ConfigError(f"dummy_forceps_mm={self.dummy_forceps_mm} outside [10, 1000]")
        if any(a >= b for a, b in zip(self.workspace_min_mm, self.workspace_max_mm, strict=True)):
            raise ConfigError("workspace_min_mm must be below workspace_max_mm on every axis")
        for p in self.pairs:
            robot.arm(parse_pair(p)[1])


class ArmMapping(EngageGate):
    """Mapping state of one master → slave pair. Thread-safe: zenoh callbacks call in."""

    MASTER_INPUT = ("measured_cp", CartesianPose)  # the master stream it maps

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        super().__init__(cfg, node, master, slave, work, MH3F.joint_names)
        self.geom = MH3F
        self.r_ms = master_rotation(cfg)  # (a camera pose replaces it: on_camera_pose)
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
            node, slave, self.geom, robots.get(cfg.model).make_config(cfg.robot).trocar_depth_mm
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

    # -- inputs -----------------------------------------------------------------------
    def on_safety_state(self, msg: SafetyState, key: str) -> None:
        with self.lock:
            if msg.scale == self.safety_scale:
                return
            old, self.safety_scale = self.safety_scale, msg.scale
            self._rescaled()
            self._publish_state()
        self.node.event(
            "scale",
            f"motion scale {self.scale * old:.3g} → {self.scale * msg.scale:.3g} "
            f"(safety {msg.state}{': ' + '; '.join(msg.causes) if msg.causes else ''})",
            arm=self.slave,
            severity="warning" if msg.scale < 1.0 else "info",
        )

    def on_camera_pose(self, msg: CartesianPose, key: str) -> None:
        """The camera's pose: map in its view frame from now on, re-anchored (no jump)."""
        r = view_rotation(msg)
        with self.lock:
            if np.allclose(r, self.r_ms, atol=1e-9):
                return
            first = self.camera_poses == 0
            self.camera_poses += 1
            self.r_ms = r
            self.r_ms_rows = r.tolist()
            self._rescaled()
        if first or self.following:
            self.node.event(
                "camera_frame",
                f"master motion mapped in camera {self.cfg.camera}'s view"
                + (" (re-anchored while following)" if self.following else ""),
                arm=self.slave,
            )

    def _rescaled(self) -> None:
        """Re-anchor at the current target: a new scale applies to motion from here on (lock held)."""
        if self.following and self.last_pose is not None and self.last_target is not None:
            lp, lt = self.last_pose, self.last_target
            self._set_ref(
                master_point(self.cfg, lp.position),
                matrix_from_quat(np.array(lp.orientation)),
                lt[:3, 3].copy(),
                lt[:3, :3].copy(),
            )

    def on_command(self, cmd: Command) -> CommandReply:
        """``state``, ``scale_up``, ``scale_down``, ``set_scale value=`` (the operator's motion scale)."""
        return self.scale_command(cmd, "")

    def on_master(self, msg: CartesianPose, key: str) -> None:
        self.on_master_pose(msg, key)

    def on_master_pose(self, msg: CartesianPose, key: str) -> None:
        with self.lock:
            self.master_rx = time.monotonic()

            if self.pending is not None:
                self.conflated += 1
            self.pending = msg
            self.pending_rx_ns = time.time_ns()
        self.work.set()

    def process(self) -> None:
        """Map the newest master sample, if any (older unprocessed ones are skipped)."""
        with self.lock:
            msg, self.pending = self.pending, None
            if msg is None:
                return
            rx_ns, begin_ns = self.pending_rx_ns, time.time_ns()
            if self.want_engage and not self.following:
                self._try_engage(msg)
            sent = self.servo_out.sent
            self._publish(msg)
            tr = self.trace
            if tr is not None and self.servo_out.sent > sent and self.traced < len(tr):
                tr[self.traced] = (msg.header.stamp_ns, rx_ns, begin_ns, self.last_stamp_ns)
                self.traced += 1

    # -- internals (lock held) ------------------------------------------------------------
    def _try_engage(self, pose: CartesianPose) -> None:
        if not self._may_engage():
            return
        assert self.q_meas is not None
        t_s0 = fk(self.q_meas, self.geom)
        self._set_ref(
            master_point(self.cfg, pose.position),
            matrix_from_quat(np.array(pose.orientation)),
            t_s0[:3, 3].copy(),
            t_s0[:3, :3].copy(),
        )
        self.q_last = self.q_meas.copy()
        self.trocar_clamp.reset(pose.header.stamp_ns)
        self.last_pose = self.last_target = None
        self.ik_streak = 0
        k = self.scale * self.safety_scale
        self._engaged_now(f"engaged {self.master} → {self.slave} at scale {k:.3g}")

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
        m = pose.position if self.cfg.master_mode == "pen" else master_point(self.cfg, pose.position).tolist()
        k = self.scale * self.safety_scale
        d0, d1, d2 = m[0] - pm[0], m[1] - pm[1], m[2] - pm[2]
        p = [ps[i] + k * (r[i][0] * d0 + r[i][1] * d1 + r[i][2] * d2) for i in range(3)]
        clamped = [min(max(v, lo), hi) for v, lo, hi in zip(p, self.ws_lo, self.ws_hi, strict=True)]
        t = np.eye(4)
        if clamped != p:
            self.clamped += 1
            if not self._clamping:
                self._clamping = True
                moved = ", ".join(
                    f"{ax} {a * 1e3:.1f}→{b * 1e3:.1f} mm"
                    for ax, a, b in zip("xyz", p, clamped, strict=True)
                    if a != b
                )
                self.node.event(
                    "clamped",
                    f"target clamped into the workspace: {moved}",
                    arm=self.slave,
                    severity="warning",
                )
        elif self._clamping:
            self._clamping = False
            self.node.event("clamped", "target back inside the workspace", arm=self.slave)
        t[:3, 3] = clamped
        if self.cfg.orientation == "follow":
            t[:3, :3] = self.r_ms @ matrix_from_quat(pose.orientation) @ b_rot
        else:
            t[:3, :3] = rs0
        return t

    def _publish(self, pose: CartesianPose) -> None:
        if self.following:
            target = self._target(pose)
            assert self.q_last is not None
            try:
                st = self.slave_state
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
                if step > self.cfg.max_joint_step_rad:
                    raise IKError(f"branch flip: joint step {step:.3f} rad")
            except IKError as exc:
                self.ik_failures += 1
                self.ik_streak += 1
                if self.ik_streak == 1:
                    self.node.event(
                        "ik_failure",
                        f"holding last valid setpoint: {exc}",
                        arm=self.slave,
                        severity="warning",
                    )
            else:
                if self.ik_streak:
                    self.node.event(
                        "ik_recovered",
                        f"IK valid again after {self.ik_streak} samples",
                        arm=self.slave,
                    )
                self.ik_streak = 0
                self.q_last = q
                self.last_pose, self.last_target = pose, target
                now = time.monotonic()
                if now >= self.target_next:
                    self.target_next = max(self.target_next + self.target_period, now)
                    h = self.target_out.header()
                    quat = quat_from_matrix(target[:3, :3])
                    self.target_out.put(CartesianPose(h, "base", _vec3(target[:3, 3]), _quat(quat)))
        q_pub = self.q_last if self.q_last is not None else self.q_meas
        if q_pub is None:
            return
        h = self.servo_out.header()
        self.last_stamp_ns = h.stamp_ns
        self.servo_out.put(
            JointSetpoint(
                h,
                self.geom.joint_names,
                tuple(q_pub.tolist()),
                follow=self.following,
                origin_ns=pose.header.stamp_ns,
            )
        )


def _vec3(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _quat(q: np.ndarray) -> tuple[float, float, float, float]:
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def guarded(
    node: Node, authority: Authority, slave: str, handler: Callable[[Command], CommandReply]
) -> Callable[[Command], CommandReply]:
    """``handler`` behind the operator authority (:mod:`telesurg.shared.authority`): a refusal is
    an event and an error reply with the reason; a command that needs confirming is answered with
    a token and reaches ``handler`` only when confirmed."""
    seq = Sequencer(node.service)

    def on_command(cmd: Command) -> CommandReply:
        try:
            verdict = authority.check(cmd)
        except AuthorityError as exc:
            node.event("command_refused", str(exc), arm=slave, severity="warning")
            raise
        if verdict.command is None:
            node.event("confirm_required", f"{summary(cmd)} from {cmd.header.source!r}", arm=slave)
            return CommandReply(seq.next(), slave, cmd.name, False, verdict.reason, verdict.token)
        return handler(verdict.command)

    return on_command


#: mapping mode → the pair class that maps it (interim: the strategies are still service classes)
PAIRS: dict[str, type[ArmMapping | AllJointsMapping | VipMapping | PositionMapping]] = {
    "cartesian": ArmMapping,
    "all_joints": AllJointsMapping,
    "vip": VipMapping,
    "position": PositionMapping,
}


def run(cfg: MappingConfig, stop: threading.Event) -> None:
    """Map until ``stop``."""
    cfg.validate()
    authority = Authority(cfg.authority)
    with Node(cfg.bus, cfg.site, cfg.service) as node:
        k = node.keys
        arms = []
        work = threading.Event()  # set by every master sample
        for pair in cfg.pairs:
            master, slave = parse_pair(pair)
            m_src, s_src, w_src = (
                only(cfg.master_source),
                only(cfg.slave_source),
                only(cfg.watchdog_source),
            )
            a = PAIRS[cfg.mode](cfg, node, master, slave, work)
            stream, kind = a.MASTER_INPUT
            on_master: Callable[[Any, str], None] = a.on_master
            node.subscribe(k.master(master, stream), kind, on_master, sources=m_src)
            if isinstance(a, (ArmMapping, PoseJointBase)):  # the pairs that serve commands
                node.serve(k.mapping_command(slave), Command, guarded(node, authority, slave, a.on_command))
            if cfg.camera and isinstance(a, ArmMapping):
                node.subscribe(
                    k.camera(cfg.camera, "measured_cp"),
                    CartesianPose,
                    a.on_camera_pose,
                    sources=only(cfg.camera_source),
                    polled=True,
                )
            # The other inputs are read by the service loop (Node.poll) right before it maps a
            # sample: no callback thread per message contending for the GIL with the mapping.
            sub = node.subscribe
            sub(k.master(master, "buttons"), MasterButtons, a.on_buttons, sources=m_src, polled=True)
            sub(k.slave(slave, "measured_js"), JointState, a.on_slave_js, sources=s_src, polled=True)
            sub(
                k.slave(slave, "operating_state"),
                OperatingState,
                a.on_slave_state,
                sources=s_src,
                polled=True,
            )
            sub(k.safety(slave, "state"), SafetyState, a.on_safety_state, sources=w_src, polled=True)
            arms.append(a)
            log.info("mapping %s → %s (%s), scale %.2f", master, slave, cfg.mode, cfg.scale)
        check_period = 0.01  # s: master staleness check
        start_loop(cfg.rt_priority)
        last_check = last_iter = time.monotonic()
        while not stop.is_set():
            work.wait(check_period)
            work.clear()
            node.poll()
            for a in arms:
                a.process()
                a.publish_state()
            now = time.monotonic()
            stalled = now - last_iter > 2 * check_period  # we were descheduled: let queued
            last_iter = now  # samples arrive before judging anything stale
            if now - last_check >= check_period and not stalled:
                last_check = now
                for a in arms:
                    a.check_timeouts()
        for a in arms:
            if isinstance(a, ArmMapping) and a.trace is not None:
                np.save(cfg.latency_log, a.trace[: a.traced])
            log.info(
                "%s → %s: %d IK failures, %d samples skipped (conflated), %d targets clamped",
                a.master,
                a.slave,
                a.ik_failures,
                a.conflated,
                a.clamped,
            )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg mapping``."""
    return service_main("mapping", MappingConfig, run, argv, __doc__ or "")
