"""mapping: master samples → slave joint setpoints, through the robot's mapping strategy, with clutch.

One pair per ``pairs`` entry (``"master_arm:slave_arm"``): the engage/clutch state machine
(:class:`~telesurg.services.mapping.engage.EngageGate`, the same for every robot: DISABLED / IDLE /
ENGAGING / ENABLED / HOLDING, published on ``mapping/<arm>/teleop_state``) composes the strategy
of ``mode`` that the robot registers (:attr:`telesurg.shared.robots.RobotSpec.strategies`: mh3f
``cartesian``, plas ``all_joints``, vip ``vip``) or the generic ``position`` mapping
(:mod:`.position`, any robot). The strategy maps the master stream it names
(``master/<m>/measured_cp`` or ``measured_js``) and publishes ``slave/<arm>/servo_jp`` for every
sample (``follow`` tells the slave whether to track it) and ``slave/<arm>/setpoint_cp`` while
following. The watchdog's ``safety/<arm>/state`` scale multiplies the motion (re-anchored, no
jump); the operator's scale commands come on ``mapping/<arm>/command``.

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

from telesurg.services.common import service_main
from telesurg.services.mapping.engage import EngageGate
from telesurg.services.mapping.position import PositionMapping
from telesurg.shared import robots
from telesurg.shared.authority import Authority, AuthorityConfig, summary
from telesurg.shared.bus import BusConfig, Node, only
from telesurg.shared.errors import AuthorityError, ConfigError
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    Command,
    CommandReply,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyState,
    Sequencer,
)
from telesurg.shared.pairs import parse_pair
from telesurg.shared.robots.api import (
    CameraFollower,
    CommandServer,
    ForceFollower,
    MappingStrategy,
    PairContext,
)
from telesurg.shared.teleop.work_frame import MASTER_FRAMES
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
    # position mode: the instrument keeps the tilt from the vertical it had at the engage and turns
    # only about the vertical, so a held object stays upright (false: its orientation is free)
    keep_tilt: bool = False
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
    # force feedback (docs/haptics.md): TDPA's slave passivity controller on the targets (the MH3F's
    # cartesian, the VIP and the position modes): from the contact force (slave/<arm>/measured_cf)
    # and the master's energy (measured_cp.energy_in_j) it backs the instrument off along the force
    # when the slave port would take more energy out of the network than the master put in
    slave_passivity: bool = False
    haptics_force_scale: float = 0.5  # keep equal to master_capture.haptics.force_scale
    # deg: the teleop state's limit_wall stands this far before the slave's nearest joint limit (the
    # MH3F's mapping, pen master; a haptic master renders it as a wall: docs/haptics.md)
    limit_wall_margin_deg: float = 5.0
    # Only these services may publish the inputs (others are rejected and counted; "" = anyone;
    # several comma-separated: a site with two masters, "master_capture,master_capture_2").
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
        strategy_factory(self.model, self.mode)
        robot.make_config(self.robot)
        if self.master_frame not in MASTER_FRAMES:
            raise ConfigError(
                f"master_frame {self.master_frame!r} invalid; valid: {', '.join(MASTER_FRAMES)}"
            )
        if self.master_mode not in MASTER_MODES:
            raise ConfigError(f"master_mode {self.master_mode!r} invalid; valid: {', '.join(MASTER_MODES)}")
        if not 10.0 <= self.dummy_forceps_mm <= 1000.0:
            raise ConfigError(f"dummy_forceps_mm={self.dummy_forceps_mm} outside [10, 1000]")
        if not 0.0 <= self.limit_wall_margin_deg <= 45.0:
            raise ConfigError(f"limit_wall_margin_deg={self.limit_wall_margin_deg} outside [0, 45]")
        if any(a >= b for a, b in zip(self.workspace_min_mm, self.workspace_max_mm, strict=True)):
            raise ConfigError("workspace_min_mm must be below workspace_max_mm on every axis")
        for p in self.pairs:
            robot.arm(parse_pair(p)[1])


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


#: The mapping service's own modes, for any robot that lists them (mode → strategy factory).
GENERIC_MODES: dict[str, Callable[[PairContext], MappingStrategy]] = {"position": PositionMapping}


def strategy_factory(model: str, mode: str) -> Callable[[PairContext], MappingStrategy]:
    """The factory of ``mode``'s strategy for robot ``model``: the robot's own, else a generic one.

    Raises:
        ConfigError: the robot lists the mode but nothing maps it.
    """
    spec = robots.get(model)
    make = spec.strategies.get(mode) or GENERIC_MODES.get(mode)
    if make is None:
        raise ConfigError(
            f"robot model {model!r} lists mapping mode {mode!r} but registers no strategy for it"
        )
    return make


class Pair(EngageGate):
    """One master → slave pair: the engage state machine composing its mapping strategy
    (:attr:`strategy`). Thread-safe: zenoh callbacks call in."""

    def __init__(
        self, cfg: MappingConfig, node: Node, master: str, slave: str, work: threading.Event
    ) -> None:
        names = robots.arm_profile(cfg.model, slave).joint_names
        super().__init__(cfg, node, master, slave, work, names)
        self.strategy: MappingStrategy = strategy_factory(cfg.model, cfg.mode)(self)

    def on_master(self, msg: Any, key: str) -> None:
        self.strategy.on_master(msg, key)

    def on_safety_state(self, msg: SafetyState, key: str) -> None:
        self.strategy.on_safety_state(msg, key)

    def process(self) -> None:
        """Map the newest master sample, if any (the service loop)."""
        self.strategy.process()

    def _rescaled(self) -> None:
        self.strategy.rescaled()


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
            a = Pair(cfg, node, master, slave, work)
            st = a.strategy
            stream, kind = st.MASTER_INPUT
            node.subscribe(k.master(master, stream), kind, a.on_master, sources=m_src)
            if isinstance(st, CommandServer):
                node.serve(k.mapping_command(slave), Command, guarded(node, authority, slave, st.on_command))
            if cfg.camera and isinstance(st, CameraFollower):
                node.subscribe(
                    k.camera(cfg.camera, "measured_cp"),
                    CartesianPose,
                    st.on_camera_pose,
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
            if cfg.slave_passivity:
                if not isinstance(st, ForceFollower):
                    raise ConfigError(
                        f"mapping.slave_passivity: mode {cfg.mode!r} has no slave passivity controller "
                        "(the MH3F's cartesian, the VIP's and the position mappings have one)"
                    )
                cf = k.slave(slave, "measured_cf")
                sub(cf, CartesianWrench, st.on_contact_force, sources=s_src, polled=True)
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
            a.strategy.close()
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
