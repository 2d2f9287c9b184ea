"""slave_control: runs the slave arms and tracks servo_jp under a watchdog lease.

The robot (``model``, :mod:`telesurg.shared.robots`) is the MuJoCo simulation
(``backend = "mujoco"``) or a real arm's joint-servo controller on a serial port
(``backend = "serial"``, :mod:`telesurg.services.slave_control.serial_backend`,
``docs/robots.md`` (Hardware)), optionally with the MuJoCo model as its shadow. Every arm of the robot
(the MH3F's one forceps arm, PLAS's and VIP's two arms) is an
:class:`~telesurg.services.slave_control.arm.ArmCore` of its own — its own lease
(``safety/<arm>/lease``), ``servo_jp``, follow/hold logic, e-stop latch and outputs; one arm
holding does not stop another — and the same core for every robot and backend: lease age,
setpoint validation, e-stop, engage, speed limit, the catch-up after a stall and the frame of
``measured_cp`` are stated once, in :mod:`telesurg.services.slave_control.arm`. A backend fault
(link lost, controller fault or watchdog, shadow divergence) holds every arm like a revoked
lease, with the fault as the reason, until it clears and a new engage comes. An arm whose robot
registers slave-side motions gets its motion source from the registry
(:attr:`~telesurg.shared.robots.RobotSpec.motions`: the MH3F's trocar modes, PTP, jog,
teach/playback; the VIP's elbow jog); the others follow servo_jp only. Every arm follows
servo_jp interpolated to the control rate on the master's clock (the trocar arm too: a step
answered joint by joint by the servos leaves the trocar's RCM;
``arm.ServoFollow``).

The control loop runs at the backend period (1 ms for MuJoCo, in real time: missed periods are
replayed, and counted; ``serial.rate_hz`` for a serial arm). Setpoints arrive on
``slave/<arm>/servo_jp``. Each arm publishes ``measured_js`` and its controlled point's
``measured_cp`` (full pose, ``base`` frame) at ``publish_hz``, the external wrench at
that point ``measured_cf`` (for masters with force feedback; backends that estimate external
torques) at ``wrench_hz`` (from the contact forces on the instrument, when the backend measures
them, at ``contact_wrench_hz``), and its ``operating_state`` at ``state_hz`` and on change; while a
slave-side motion drives an arm, its commanded joints go out on ``setpoint_js`` at
``setpoint_js_hz`` for the watchdog, which checks them as it checks followed ``servo_jp``. Rates count
periods of real time, so they hold when the loop wakes late and catches up.

Example::

    telesurg slave-control --connect tcp/127.0.0.1:7447 --set arm=arm1
    telesurg slave-control --connect tcp/127.0.0.1:7447 --set model=vip
    telesurg slave-control --connect tcp/127.0.0.1:7447 --set backend=serial \
        --set serial.port=/dev/ttyACM0 --set shadow=true
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.services.common import service_main
from telesurg.services.slave_control.arm import CATCHUP, REPLAY_MAX_PERIODS, ArmCore, MotionSource
from telesurg.services.slave_control.backends import SlaveBackend, SlaveReading
from telesurg.services.slave_control.factory import make_backend
from telesurg.services.slave_control.serial_backend import SerialBackendConfig
from telesurg.shared import robots
from telesurg.shared.authority import AuthorityConfig
from telesurg.shared.bus import BusConfig, Node, only
from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import ConfigError
from telesurg.shared.kinematics.work_frame import CameraWorkFrame, ConfiguredWorkFrame
from telesurg.shared.messages import CartesianPose, SceneState
from telesurg.shared.robots import arms_of
from telesurg.shared.robots.api import MotionContext, ViewFrameUser
from telesurg.shared.timing import CycleTimer, check_rt_priority, start_loop

log = logging.getLogger(__name__)


@dataclass
class SlaveControlConfig:
    """slave_control config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "slave_control"  # instance id (liveliness alive/<service>, header src)
    arm: str = "arm1"  # slave arm id in keys slave/<arm>/...
    backend: str = "mujoco"  # valid: mujoco, serial (a real arm's servo controller, docs/robots.md, Hardware)
    # robot model, a name in the robot registry (shared/robots/<model>): mh3f (one forceps arm,
    # trocar modes); plas, vip: two joint-space arms arm1/arm2 in one process (one arm core each)
    model: str = "mh3f"
    # MuJoCo: another scene of the robot, a scene_*.xml file in its folder ("" = its own scene.xml;
    # e.g. the MH3F's "scene_trocar_task.xml": tissue under the trocar for the study's trocar tasks)
    scene: str = ""
    # the robot's own knobs (its config dataclass, shared/robots/<model>/config.py; e.g.
    # --set robot.jog_speed_mm_s=20): checked against the robot's config at start
    robot: dict[str, Any] = field(default_factory=dict)
    # rad / m: MuJoCo start pose, every joint of the model ([] = the model's "home" keyframe, else
    # each arm's home: the MH3F's tip at (835, 0, 301) mm, forceps pitched 29° down)
    q_home: tuple[float, ...] = ()
    publish_hz: float = 250.0  # Hz: measured_js and measured_cp
    wrench_hz: float = 50.0  # Hz: measured_cf from the external-torque estimate (MuJoCo without contacts)
    # Hz: measured_cf when the backend measures the contact forces on the instrument (the MH3F scene's
    # tissue): a haptic master's force stream (docs/haptics.md) needs ≥ 500 Hz
    contact_wrench_hz: float = 500.0
    state_hz: float = 20.0  # Hz: operating_state (also sent on every change)
    # Hz: slave/<arm>/scene, a MuJoCo scene's loose objects (who holds them) and the instruments'
    # collisions (scenes with loose objects or jaws only; collisions are sampled at this rate)
    scene_hz: float = 20.0
    # Hz: setpoint_js, the commanded joints while a slave-side motion drives the arm (PTP, jog,
    # playback, insert/remove, direct teach), checked by the watchdog; the watchdog checks the
    # joint path between two samples at fine steps, so this rate only sets its reaction time
    setpoint_js_hz: float = 100.0
    setpoint_timeout_ms: float = 100.0  # ms: an older setpoint is stale → hold
    # ms: a setpoint whose header stamp is further than this from this host's wall clock is
    # refused (stale, or the hosts' clocks disagree); > the longest scheduling stall, so a
    # stalled slave does not refuse what waited in its queue
    setpoint_max_age_ms: float = 1000.0
    # ms: a lease is honoured at most its valid_for_ms + this after its own header stamp (this
    # host's wall clock, the watchdog's too): a thawed slave never acts on old leases
    lease_stamp_slack_ms: float = 50.0
    # ms: every arm interpolates its setpoints over their period (delay 1.5 periods), at most this long
    interpolation_max_ms: float = 100.0
    # ms: while following, the setpoint timeline may run this far behind the master (stalls of the
    # loop or of the stream not yet made up by the catch-up); further behind, the arm holds. A
    # backstop against a host that stalls the slave more than it makes up: a single stall of the
    # whole host (which neither the watchdog nor the slave holds on: docs/safety.md) is made up at
    # 2x; at most 1000 (what the interpolator keeps)
    follow_max_lag_ms: float = 1000.0
    engage_tolerance_rad: float = 0.02  # rad: first followed setpoint must be this close to the arm
    # rad: while following, a setpoint farther than this from the previous one is refused (a jump)
    max_setpoint_step_rad: float = 0.1
    setpoint_source: str = "mapping"  # only this service may publish servo_jp for this arm
    # deg, roll/pitch/yaw of the work jog frame (the laparoscope's view: x image right, y image
    # down, z into the image) in the base frame; default: looking down, patient's head (+x) up
    work_frame_rpy_deg: tuple[float, float, float] = (180.0, 0.0, -90.0)
    # camera id: `work` jogs in its view (camera/<cam>/measured_cp: the endoscope's optical frame
    # is the laparoscope's view frame; work_frame_rpy_deg until its first pose) ("" = always
    # work_frame_rpy_deg; telesurg up sets it when a camera runs)
    camera: str = ""
    camera_source: str = "camera"  # the only publisher accepted on camera/<cam>/measured_cp
    # mm, base frame: the patient's body (the mh3f scene's torso under the drape). Every slave-side
    # motion of the trocar arm is refused / stopped where the forceps would cross it outside the
    # trocar, and every followed servo_jp step is clamped at its surface
    # (shared/robots/mh3f/keepout.py); the entry must be within 5 mm of the trocar
    # (default: the torso (260, -170, 136)-(740, 170, 196) mm with 5 mm on every side and 6 mm below,
    # and the top 2 mm under the trocar: the arm lags its command (a PTP within 0.8 mrad of its
    # joint line, docs/trocar.md), and a path is checked at 0.005 rad steps)
    patient_box_min_mm: tuple[float, float, float] = (255.0, -175.0, 130.0)
    patient_box_max_mm: tuple[float, float, float] = (745.0, 175.0, 198.0)
    # .npy written at exit: one row per setpoint the control loop applied (origin_ns of the master
    # sample, the setpoint's stamp, the wall time the loop first used it, the wall time the backend
    # stepped that period's command, the master time its interpolated reference played, ns; 0 =
    # none) — for telesurg bench latency
    latency_log: str = ""
    command_sources: list[str] = field(default_factory=list)  # who may send commands ([] = anyone)
    # who may send which operator command, e-stop or reset, and the confirmation of motion-starting
    # commands (shared/authority.py; set once for the site in [site.authority])
    authority: AuthorityConfig = field(default_factory=AuthorityConfig)
    # The watchdog's liveliness token is watched too: its death revokes the lease at once
    # (in ms), instead of after the lease lifetime.
    watchdog_service: str = "watchdog"
    # backend = "serial": the joint-servo controller (shared/servo_protocol.py), the [slave_control.serial]
    # table: port, baud, rate, timeouts, bring-up switches (telesurg slave-control --help lists them)
    serial: SerialBackendConfig = field(default_factory=SerialBackendConfig)
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


def make_arms(cfg: SlaveControlConfig, backend: SlaveBackend) -> list[ArmCore]:
    """One arm core per arm of ``cfg.model`` on ``backend`` (after it was entered)."""
    spec = robots.get(cfg.model)
    spec.make_config(cfg.robot)  # the robot's knobs, checked before anything moves
    names = list(backend.joint_names)
    cores = []
    for p in arms_of(cfg.model, cfg.arm):
        missing = [j for j in p.model_joints if j not in names]
        if missing:
            raise ConfigError(f"model {cfg.model} has no joints {missing} for arm {p.arm}")
        motion: MotionSource | None = None
        if spec.motions is not None:  # the robot's slave-side motions (shared/robots/<model>)
            motion = spec.motions(MotionContext(cfg, p, getattr(backend, "push", None)))
        idx = [names.index(j) for j in p.model_joints]
        contiguous = idx == list(range(idx[0], idx[0] + len(idx)))
        index = slice(idx[0], idx[0] + len(idx)) if contiguous else np.array(idx)
        # every arm interpolates its setpoints (the trocar arm too: its servos must never see a
        # step, see arm.ServoFollow); a robot with catch_up (the MH3F) makes up stalls
        # (arm.CATCHUP): the joint-space arms keep their timeline (with the catch-up the PLAS
        # slave left its commanded path)
        catchup = CATCHUP if spec.catch_up else 1.0
        core = ArmCore(p, index, cfg, backend.dt, motion=motion, interpolate=True, catchup=catchup)
        tool = f"{p.arm}_jaw"
        if tool in getattr(backend, "tool_names", ()):  # the arm's jaws: open at the start
            core.tool, core.grip = tool, 0.0
            getattr(backend, "command_tool")(tool, 0.0)  # noqa: B009 (a MuJoCo backend's)
        cores.append(core)
    return cores


class ScenePublisher:
    """``slave/<arm>/scene`` of every arm (:class:`~telesurg.shared.messages.SceneState`): the
    scene's loose objects and who holds them, each arm's jaws, and the instruments' collisions (an
    ``instrument_collision`` event at each new one)."""

    def __init__(self, node: Node, backend: Any, arms: list[ArmCore]) -> None:
        self.node, self.backend, self.arms = node, backend, arms
        self.outlets = [node.outlet(node.keys.slave(a.arm, "scene"), control=False) for a in arms]
        self.collisions = 0
        self.touching = False

    @staticmethod
    def wanted(backend: Any) -> bool:
        """The backend has a scene worth publishing: loose objects or jaws."""
        if not hasattr(backend, "read_scene"):
            return False
        r = backend.read_scene()
        return bool(r.objects) or bool(r.tools)

    def publish(self) -> None:
        r = self.backend.read_scene()
        if r.instrument_contact and not self.touching:
            self.collisions += 1
            self.node.event("instrument_collision", "the instruments of two arms collide", severity="warning")
        self.touching = bool(r.instrument_contact)
        jaws = tuple(round(float(r.tools[a.tool]), 3) for a in self.arms if a.tool in r.tools)
        held = tuple("+".join(h) for h in r.held_by)
        pos = np.round(np.asarray(r.positions, dtype=float).reshape(-1, 3), 5)
        x, y, z = (tuple(float(v) for v in pos[:, i]) for i in range(3))
        for out in self.outlets:
            out.put(
                SceneState(
                    out.header(), tuple(r.objects), x, y, z, held, jaws, self.touching, self.collisions
                )
            )


def follow_camera(node: Node, cfg: SlaveControlConfig, motion: ViewFrameUser) -> None:
    """``work`` jogs of ``motion`` in the view of camera ``cfg.camera`` (its pose stream, read at
    the loop's poll); ``work_frame_rpy_deg`` until its first pose. The last pose holds however old
    (as in the mapping): the camera's pose changes only when it is moved, and a move is published
    at once — a lagging pose stream (the camera runs at idle priority) must not turn a running jog
    back to the configured frame."""
    frame = CameraWorkFrame(ConfiguredWorkFrame(cfg.work_frame_rpy_deg), max_age_s=math.inf)
    motion.work_frame = frame

    def on_pose(msg: CartesianPose, key: str) -> None:
        frame.on_pose(msg.orientation)

    node.subscribe(
        node.keys.camera(cfg.camera, "measured_cp"),
        CartesianPose,
        on_pose,
        sources=only(cfg.camera_source),
        polled=True,
    )


def run(cfg: SlaveControlConfig, stop: threading.Event) -> None:
    """Run the slave until ``stop``."""
    check_rt_priority(cfg.rt_priority)
    if not 10.0 <= cfg.setpoint_js_hz <= 1000.0:  # the watchdog needs them at least every 100 ms
        raise ConfigError(f"setpoint_js_hz={cfg.setpoint_js_hz} outside [10, 1000]")
    if not 0.0 < cfg.follow_max_lag_ms <= 1000.0:  # the interpolator keeps 1.2 s of setpoints
        raise ConfigError(f"follow_max_lag_ms={cfg.follow_max_lag_ms} outside (0, 1000]")
    if cfg.scene and cfg.backend != "mujoco":
        raise ConfigError(f'scene={cfg.scene!r} is a MuJoCo scene: it needs backend = "mujoco"')
    robots.get(cfg.model).scene_file(cfg.scene)  # (ConfigError naming the robot's scenes)
    profiles = arms_of(cfg.model, cfg.arm)
    home = tuple(v for p in profiles for v in p.home)
    sites = tuple(p.tip_site for p in profiles)
    backend = make_backend(cfg.backend, cfg.model, cfg.q_home, sites, cfg, home)
    with backend, Node(cfg.bus, cfg.site, cfg.service) as node:
        k = node.keys
        arms = make_arms(cfg, backend)
        for a in arms:
            a.connect(node)
            if cfg.camera and isinstance(a.motion, ViewFrameUser):
                follow_camera(node, cfg, a.motion)
        servo_streams = [node.streams.get(k.slave(a.arm, "servo_jp")) for a in arms]
        # Sub-rate tasks run in different cycles where they can (phases 0-3 below: with periods of
        # 4, 10 and 50 cycles these three never share one), so no cycle carries the sum of their
        # work: measured_js/cp at phase 0, motion sources' measurements 1, operating_state 3;
        # measured_cf at phase 2 (with contacts every 2nd cycle at 500 Hz: a few µs, one small message).
        dt = backend.dt
        timer = CycleTimer(1.0 / dt)
        pub_every = max(1, round(1.0 / (dt * cfg.publish_hz)))
        measure_every = max(1, round(0.01 / dt))  # 100 Hz
        state_every = max(1, round(1.0 / (dt * cfg.state_hz)))
        commanded_every = max(1, round(1.0 / (dt * cfg.setpoint_js_hz)))
        shadow_every = max(1, round(cfg.shadow_report_s / dt))
        reading = backend.read()
        wrench_hz = cfg.contact_wrench_hz if reading.contact_wrench is not None else cfg.wrench_hz
        wrench_every = max(1, round(1.0 / (dt * wrench_hz)))
        scene = ScenePublisher(node, backend, arms) if ScenePublisher.wanted(backend) else None
        scene_every = max(1, round(1.0 / (dt * cfg.scene_hz)))
        # out of contact the contact wrench is sent at wrench_hz only (nothing to feel: the
        # receivers' load, two arms × 500 Hz on the PLAS and VIP, goes to what matters)
        quiet_every = max(1, round(wrench_hz / cfg.wrench_hz))
        for a in arms:  # the first operating_state already carries the measurements
            a.start(a.arm_reading(reading))
        q_cmd = reading.position.copy()
        sent_grip = {a.tool: a.grip for a in arms if a.tool}
        command_tool: Any = getattr(backend, "command_tool", None)  # (the arms' jaws, MuJoCo)

        def command(now: float, reading: SlaveReading) -> None:
            """Every arm's command for the period at ``now``, sent to the backend."""
            for a in arms:
                q_cmd[a.index] = a.control(now, a.arm_reading(reading))
                if a.tool and a.grip != sent_grip.get(a.tool):
                    command_tool(a.tool, a.grip)
                    sent_grip[a.tool] = a.grip
            backend.command(q_cmd)

        def stepped() -> None:
            """The backend stepped: the latency log's "acts" time (latency_log only)."""
            if cfg.latency_log:
                t = wall_ns()
                for a in arms:
                    a.stepped(t)

        log.info(
            "slave %s (%s/%s, arms %s) running at %.0f Hz",
            cfg.service,
            cfg.backend,
            cfg.model,
            ", ".join(a.arm for a in arms),
            1 / dt,
        )
        start_loop(cfg.rt_priority)
        cycle = 0
        while not stop.is_set():
            # the period's inputs are read and its command computed right at its deadline, just
            # before the step that sends it: a setpoint that came while the loop slept acts in
            # this step, not one period later (the command is never older than the poll)
            missed = timer.wait()
            node.poll()
            now = time.monotonic()
            if backend.realtime or not missed:
                # a real arm held its last command through the stall by itself; its MuJoCo shadow
                # is stepped by the periods it missed, so it stays in real time too
                command(now, reading)
                backend.step(1 + missed)
                stepped()
                for a in arms:
                    a.stalled(missed * dt)
            else:
                # a simulation woke late: replay the missed periods, each with its own command
                # computed at its own time (the catch-up rule, arm.py): the physics stays in real
                # time and the arm on its commanded path, never a jump. The first command drives
                # the first missed period, at that period's time; only the last
                # REPLAY_MAX_PERIODS are replayed (bounded work before the next publication); the
                # arm held that first command through the earlier ones, as a real arm would have.
                # Every one of them judges the newest lease and setpoint (polled above: by
                # arrival, cycles and their own stamps, on this host's wall clock now), never
                # the ones from before the stall (a thawed slave acts on no old permission).
                now -= missed * dt
                command(now, reading)
                held = max(0, missed - REPLAY_MAX_PERIODS)
                backend.step(1 + held)
                stepped()
                for a in arms:  # the arm held its command through them: its timeline pauses
                    a.stalled(held * dt)
                # each replayed period at its own time on the loop's schedule: right after the
                # 1 + held periods the command above drove
                for period in range(held + 1, missed + 1):
                    command(now + period * dt, backend.read())
                    backend.step(1)
                    stepped()
            reading = backend.read()
            cycle += 1
            arm_readings = [a.arm_reading(reading) for a in arms]
            for a, r in zip(arms, arm_readings, strict=True):
                a.after_period(cycle, r)
            if timer.every(measure_every, 1):
                for a, r in zip(arms, arm_readings, strict=True):
                    a.measure(r)
            if reading.divergence is not None and timer.every(shadow_every):
                node.event("shadow", f"shadow divergence {reading.divergence.describe()}")
            if timer.every(pub_every):
                for a, r in zip(arms, arm_readings, strict=True):
                    a.publish_measured(r)
            if timer.every(wrench_every, 2):
                for a, r in zip(arms, arm_readings, strict=True):
                    a.publish_wrench(r, quiet_every)
            if timer.every(commanded_every, 5):  # (phase 5: with 10 periods, never with 0-3 above)
                for a in arms:
                    a.publish_commanded()
            if scene is not None and timer.every(scene_every, 7):  # (never with phases 0-5 above)
                scene.publish()
            force_state = timer.every(state_every, 3)
            for a, s in zip(arms, servo_streams, strict=True):
                a.publish_state(force_state, s.rejected)
        for a in arms:
            a.close()
        log.info(
            "stopped after %d cycles: %d overruns, %d periods caught up",
            cycle,
            timer.overruns,
            timer.periods - timer.cycles,
        )


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg slave-control``."""
    return service_main("slave-control", SlaveControlConfig, run, argv, __doc__ or "")
