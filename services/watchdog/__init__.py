"""watchdog: grants each slave arm a short lease to move, only while everything is healthy.

Per arm it combines into OK / DEGRADED / HOLD / ESTOP (:mod:`telesurg.services.watchdog.logic`,
``docs/safety.md``):

* its own measurements: the liveliness tokens ``alive/<service>`` of ``required_services``; the
  staleness of each control stream against its deadline (``*_deadline_ms``); lost and reordered
  control messages per second; the command-path latency (p50/p90/p99: ``servo_jp``'s age since
  its master sample, the master host's clock offset taken out — :mod:`telesurg.shared.clock`,
  probed over the bus —, or half the round trip to the master's echo queryable); with
  ``video_camera`` set, the endoscope video's freshness (:mod:`telesurg.services.watchdog.video`);
* the safety rules (:mod:`telesurg.services.watchdog.rules`, one file each; plugins add more) on
  ``servo_jp``, the slave's ``operating_state`` and the master's buttons;
* the slave's commanded joints of slave-side motions (``slave/<arm>/setpoint_js``) and the patient
  keep-out (:mod:`telesurg.services.watchdog.commanded`);
* e-stop commands on ``estop`` (latched until an explicit reset).

Every ``1/lease_hz`` s, and at once on a liveliness loss, an e-stop or a commanded fault, it
publishes ``safety/<arm>/lease`` (``allow``, ``valid_for_ms``, ``reason``); the slave holds when the
lease says hold or expires. ``safety/<arm>/state`` goes out on change and at ``state_hz``; every
transition is an event with its causes.

Example::

    telesurg watchdog --connect tcp/127.0.0.1:7447 --set 'pairs=["m1:arm1"]'
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from telesurg.services.common import service_main
from telesurg.services.watchdog import rules as safety_rules
from telesurg.services.watchdog.commanded import CommandedCheck
from telesurg.services.watchdog.logic import ArmSafety, Policy, Verdict
from telesurg.services.watchdog.video import VideoPolicy, VideoWatch
from telesurg.shared.authority import Authority, AuthorityConfig
from telesurg.shared.bus import BusConfig, Node, Outlet, only
from telesurg.shared.clock import ClockFilter, ClockSample, offset_text, wall_ns
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import (
    CameraImage,
    CartesianPose,
    CartesianWrench,
    EStop,
    JointSetpoint,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    SafetyLease,
    SafetyState,
    VideoState,
)
from telesurg.shared.pairs import parse_pair
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots import get as robot_spec
from telesurg.shared.timing import settle_gc

log = logging.getLogger(__name__)
LATENCY_SOURCES = ("clock", "echo")


@dataclass
class WatchdogConfig:
    """watchdog config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "watchdog"  # instance id (liveliness alive/<service>, header src)
    pairs: list[str] = field(default_factory=lambda: ["m1:arm1"])  # "master_arm:slave_arm"
    model: str = "mh3f"  # slave robot model (shared/robots.py): joint names, limits, tip for the workspace
    # services whose liveliness token must be present for any arm to move
    required_services: list[str] = field(
        default_factory=lambda: ["master_capture", "mapping", "slave_control"]
    )
    lease_hz: float = 50.0  # Hz: lease publish rate (also at once on any liveliness loss)
    # ms: lease lifetime at the slave. Covers a *frozen* watchdog; a dead one is seen by the
    # slave through liveliness in ms. Long enough to ride out the VM's scheduling stalls.
    lease_valid_ms: float = 250.0
    # Deadlines leave room for one lease tick (20 ms) so a silent stream holds within 100 ms.
    master_deadline_ms: float = 80.0  # ms: master measured_cp older than this → HOLD
    buttons_deadline_ms: float = 200.0  # ms: master buttons older than this → HOLD
    servo_deadline_ms: float = 80.0  # ms: servo_jp older than this → HOLD
    slave_deadline_ms: float = 100.0  # ms: slave measured_js older than this → HOLD
    slave_state_deadline_ms: float = 250.0  # ms: slave operating_state (20 Hz) older → HOLD
    # ms: while the slave reports a slave-side motion, its commanded joints (setpoint_js, 100 Hz)
    # older than this → HOLD (counted from the motion's start at the earliest)
    setpoint_js_deadline_ms: float = 100.0
    max_loss_per_s: int = 10  # lost + reordered control messages per second above this → DEGRADED
    # the master's pose: more than this % of its samples lost or reordered in the last second →
    # DEGRADED. Counted apart: over the datagram link (shared/bus.py) a WAN loses a few, each
    # superseded by the next sample; its staleness is master_deadline_ms's
    max_master_loss_pct: float = 10.0
    # clock: servo_jp's age since its master sample's stamp, on this host's clock (the master
    # host's offset, from the clock probes, taken out); echo: half the probes' round trip
    latency_source: str = "clock"
    echo_service: str = "master_capture"  # whose clock / round trip the probes measure
    echo_hz: float = 20.0  # Hz: clock probes (signed queries to echo/<echo_service>)
    latency_budget_ms: float = 100.0  # ms: p90 above → DEGRADED, motion scale × degraded_scale
    latency_limit_ms: float = 250.0  # ms: p50 above → HOLD (out of follow until re-engage)
    latency_window_s: float = 1.0  # s: window of the latency percentiles
    degraded_scale: float = 0.5  # motion-scale factor while DEGRADED
    velocity_hold_factor: float = 2.0  # setpoint speed above this × joint limit → HOLD (a jump)
    workspace_min_mm: tuple[float, float, float] = (150.0, -600.0, -200.0)  # target box, base frame
    workspace_max_mm: tuple[float, float, float] = (1100.0, 600.0, 800.0)
    rcm_limit_mm: float = 2.0  # mm: RCM error above this in trocar mode → HOLD
    # mm, base frame: the patient's body for a trocar-family robot (the MH3F): the slave's
    # commanded joints of slave-side motions (setpoint_js) may take the forceps into it only
    # through the trocar the slave reports, else → HOLD; the default is slave_control's (the mh3f
    # scene's torso with its margin)
    patient_box_min_mm: tuple[float, float, float] = (255.0, -175.0, 130.0)
    patient_box_max_mm: tuple[float, float, float] = (745.0, 175.0, 198.0)
    fault_latch_ms: float = 500.0  # ms: a message-level fault holds at least this long
    min_hold_ms: float = 250.0  # ms: a HOLD outlasts its causes by this much (no flapping lease)
    require_operator: bool = True  # HOLD while the master reports no operator present
    # settings of the safety rules (services/watchdog/rules/, one file each; plugins add more):
    # rule name → its keys, e.g. [watchdog.rules.rcm] modes = ["trocar"]
    rules: dict[str, dict[str, Any]] = field(default_factory=dict)
    state_hz: float = 5.0  # Hz: safety state republish rate (also sent on every change)
    # Only these services may publish the watched streams (others are rejected and counted, and
    # cannot keep a stream looking fresh; "" = anyone; several comma-separated: a site with two
    # masters, "master_capture,master_capture_2"). E-stops are accepted from anyone.
    master_source: str = "master_capture"
    mapping_source: str = "mapping"
    slave_source: str = "slave_control"
    # The endoscope video (docs/console.md). camera id whose camera/<cam>/image every arm needs
    # fresh ("" = no video watched; a site without a camera)
    video_camera: str = ""
    video_service: str = "camera"  # the camera's service id: its frames only, its liveliness token
    video_stale_ms: float = 250.0  # ms: no frame for this long → DEGRADED (3 frames at 12 fps)
    video_hold_ms: float = 1000.0  # ms: no frame (or camera not alive) for this long → HOLD
    video_age_budget_ms: float = 150.0  # ms: a frame older than this at arrival → DEGRADED
    video_age_limit_ms: float = 500.0  # ms: a frame older than this at arrival → HOLD
    video_fresh_frames: int = 3  # fresh frames in a row needed before OK again
    video_window_s: float = 2.0  # s: window of the frame-age percentiles and fps
    # who may send an e-stop and who may reset one (shared/authority.py; set once for the site in
    # [site.authority]): a reset only from the operator console
    authority: AuthorityConfig = field(default_factory=AuthorityConfig)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session

    def video_policy(self) -> VideoPolicy:
        """The video limits of this config."""
        return VideoPolicy(
            self.video_stale_ms,
            self.video_hold_ms,
            self.video_age_budget_ms,
            self.video_age_limit_ms,
            self.video_fresh_frames,
            self.video_window_s,
        )

    def validate(self) -> None:
        """Raise ConfigError on inconsistent settings."""
        if self.video_camera and not (
            0 < self.video_stale_ms < self.video_hold_ms
            and 0 < self.video_age_budget_ms < self.video_age_limit_ms
        ):
            raise ConfigError(
                "need 0 < video_stale_ms < video_hold_ms and 0 < video_age_budget_ms < video_age_limit_ms"
            )
        if self.video_fresh_frames < 1 or self.video_window_s <= 0:
            raise ConfigError("video_fresh_frames must be >= 1 and video_window_s > 0")
        if self.lease_hz <= 0 or self.lease_valid_ms * self.lease_hz / 1e3 < 2.0:
            raise ConfigError("lease_valid_ms must cover at least 2 lease periods")
        if self.latency_source not in LATENCY_SOURCES:
            raise ConfigError(
                f"latency_source {self.latency_source!r} invalid; valid: {', '.join(LATENCY_SOURCES)}"
            )
        if not 0.0 < self.max_master_loss_pct <= 100.0:
            raise ConfigError(f"max_master_loss_pct={self.max_master_loss_pct} outside (0, 100]")
        if not 0 < self.latency_budget_ms < self.latency_limit_ms:
            raise ConfigError("need 0 < latency_budget_ms < latency_limit_ms")
        if not 0.0 < self.degraded_scale <= 1.0:
            raise ConfigError(f"degraded_scale={self.degraded_scale} outside (0, 1]")
        if self.velocity_hold_factor < 1.0:
            raise ConfigError("velocity_hold_factor must be >= 1")
        if any(a >= b for a, b in zip(self.workspace_min_mm, self.workspace_max_mm, strict=True)):
            raise ConfigError("workspace_min_mm must be below workspace_max_mm on every axis")
        if any(a >= b for a, b in zip(self.patient_box_min_mm, self.patient_box_max_mm, strict=True)):
            raise ConfigError("patient_box_min_mm must be below patient_box_max_mm on every axis")
        for p in self.pairs:
            arm_profile(self.model, parse_pair(p)[1])
        safety_rules.check_settings(self.rules)

    def policy(self, arm: str = "arm1") -> Policy:
        """Per-arm limits: this config plus the robot model's joint limits for ``arm``."""
        p = arm_profile(self.model, arm)
        return Policy(
            lower=np.array(p.lower),
            upper=np.array(p.upper),
            max_velocity=np.array(p.max_velocity),
            velocity_hold_factor=self.velocity_hold_factor,
            workspace_min_mm=self.workspace_min_mm,
            workspace_max_mm=self.workspace_max_mm,
            rcm_limit_mm=self.rcm_limit_mm,
            latency_budget_ms=self.latency_budget_ms,
            latency_limit_ms=self.latency_limit_ms,
            latency_window_s=self.latency_window_s,
            # echo probes are few (echo_hz per second): judge on half a window's worth of them
            latency_min_samples=(
                max(3, int(0.5 * self.echo_hz * self.latency_window_s))
                if self.latency_source == "echo"
                else 20
            ),
            degraded_scale=self.degraded_scale,
            fault_latch_ms=self.fault_latch_ms,
            min_hold_ms=self.min_hold_ms,
            require_operator=self.require_operator,
        )


class ArmWatch:
    """One arm: its streams and deadlines, its safety logic, its outlets."""

    def __init__(self, node: Node, cfg: WatchdogConfig, master: str, arm: str) -> None:
        k = node.keys
        self.arm, self.master = arm, master
        self.deadlines = {
            k.master(master, "measured_cp"): cfg.master_deadline_ms,
            k.master(master, "buttons"): cfg.buttons_deadline_ms,
            k.slave(arm, "servo_jp"): cfg.servo_deadline_ms,
            k.slave(arm, "measured_js"): cfg.slave_deadline_ms,
            k.slave(arm, "operating_state"): cfg.slave_state_deadline_ms,
        }
        self.control = [k.slave(arm, "servo_jp"), k.slave(arm, "measured_js")]  # max_loss_per_s
        self.master_pose = k.master(master, "measured_cp")  # max_master_loss_pct
        profile = arm_profile(cfg.model, arm)
        self.safety = ArmSafety(
            arm, cfg.policy(arm), profile.joint_names, tip_of=profile.tip, rule_settings=cfg.rules
        )
        keepout = robot_spec(cfg.model).patient_keepout  # the forceps arm and its patient
        self.commanded = CommandedCheck(
            self.safety,
            cfg.patient_box_min_mm if keepout else None,
            cfg.patient_box_max_mm if keepout else None,
            tip_of=profile.tip,
        )
        # (mono s, lost + reordered so far on the control streams, on the master pose, master
        # poses received so far)
        self.loss: deque[tuple[float, int, int, int]] = deque()
        self.lease_out: Outlet = node.outlet(k.safety(arm, "lease"))
        self.state_out: Outlet = node.outlet(k.safety(arm, "state"), control=False)
        self.video_out: Outlet | None = (
            node.outlet(k.safety(arm, "video"), control=False) if cfg.video_camera else None
        )
        self.verdict = Verdict("HOLD", ("starting",), 1.0, 0.0, 0.0, 0.0, 0)
        self.ever_ok = False  # the arm has been OK once: a HOLD from now on is an error, not start-up
        self.commanded_key = k.slave(arm, "setpoint_js")
        self.motion_tick: int | None = None  # the tick at which the slave began a slave-side motion


class Watchdog:
    """Combines every signal into per-arm leases."""

    def __init__(self, cfg: WatchdogConfig, node: Node) -> None:
        self.cfg, self.node = cfg, node
        self.lock = threading.Lock()  # guards alive and every ArmSafety
        self.alive: set[str] = set()
        self.authority = Authority(cfg.authority)
        # Ticks executed, and the tick at which each stream last delivered. A stream is stale
        # only when it is old by wall time *and* by ticks: after the watchdog's own stall
        # (descheduled), queued messages get a chance to arrive before anything is judged stale.
        self.ticks = 0
        self.tick_lock = threading.Lock()
        # Set by an input that must revoke a lease now (liveliness loss, e-stop, a commanded
        # fault): the loop (:meth:`serve`) wakes and ticks at once. The callbacks never tick
        # themselves: a tick puts the leases (CongestionControl.BLOCK), and a zenoh delivery
        # thread blocked in a put — or waiting for ``tick_lock`` while the loop is in one — stops
        # reading from the router, whose queue towards this process then holds up the very
        # transport the loop's put needs (a deadlock; zenoh advises no blocking call in a callback).
        self.urgent = threading.Event()
        self.last_tick: dict[str, int] = {}
        self.clock = ClockFilter()  # the clock probes of the echo_service
        self.arms = [ArmWatch(node, cfg, *parse_pair(p)) for p in cfg.pairs]
        k = node.keys
        m, mp, sl = only(cfg.master_source), only(cfg.mapping_source), only(cfg.slave_source)
        for a in self.arms:
            sub = node.subscribe
            # staleness-only streams are read at the tick (Node.poll), not woken for per message
            sub(k.master(a.master, "measured_cp"), CartesianPose, self._on_stream, sources=m, polled=True)
            sub(k.master(a.master, "buttons"), MasterButtons, self._bind(a, self._on_buttons), sources=m)
            sub(k.slave(a.arm, "servo_jp"), JointSetpoint, self._bind(a, self._on_servo), sources=mp)
            sub(k.slave(a.arm, "measured_js"), JointState, self._on_stream, sources=sl, polled=True)
            sub(k.slave(a.arm, "operating_state"), OperatingState, self._bind(a, self._on_slave), sources=sl)
            sub(k.slave(a.arm, "setpoint_js"), JointState, self._bind(a, self._on_commanded), sources=sl)
            sub(
                k.slave(a.arm, "measured_cf"),
                CartesianWrench,
                self._bind(a, self._on_wrench),
                sources=sl,
                polled=True,
            )
        node.subscribe(k.estop, EStop, self._on_estop)
        self.video: VideoWatch | None = None
        if cfg.video_camera:
            self.video = VideoWatch(cfg.video_policy(), time.monotonic())
            node.subscribe(
                k.camera(cfg.video_camera, "image"),
                CameraImage,
                self._on_frame,
                sources=only(cfg.video_service),
            )
        node.watch_liveliness(k.alive(), self._on_alive)

    @staticmethod
    def _bind(a: ArmWatch, fn):  # type: ignore[no-untyped-def]
        def cb(msg: Message, key: str) -> None:
            fn(a, msg, key)

        return cb

    # -- inputs (zenoh threads) -------------------------------------------------------------
    def _on_stream(self, msg: Message, key: str) -> None:
        self.last_tick[key] = self.ticks  # receive time is tracked by Node.streams

    def _on_buttons(self, a: ArmWatch, msg: MasterButtons, key: str) -> None:
        self.last_tick[key] = self.ticks
        with self.lock:
            a.safety.on_buttons(msg, time.monotonic())

    def _on_servo(self, a: ArmWatch, msg: JointSetpoint, key: str) -> None:
        self.last_tick[key] = self.ticks
        # the master's stamp on this host's clock: its host's offset taken out (the clock probes)
        wall = wall_ns() + self.clock_offset_ns if self.cfg.latency_source == "clock" else None
        with self.lock:
            a.safety.on_servo(msg, time.monotonic(), wall)

    def _on_wrench(self, a: ArmWatch, msg: CartesianWrench, key: str) -> None:
        with self.lock:
            a.safety.on_wrench(msg, time.monotonic())

    def _on_slave(self, a: ArmWatch, msg: OperatingState, key: str) -> None:
        self.last_tick[key] = self.ticks
        with self.lock:
            a.safety.on_slave_state(msg, time.monotonic())
            a.commanded.on_slave_state(msg, time.monotonic())
            if a.commanded.motion_since is not None and a.motion_tick is None:
                a.motion_tick = self.ticks
            elif a.commanded.motion_since is None:
                a.motion_tick = None

    def _on_commanded(self, a: ArmWatch, msg: JointState, key: str) -> None:
        """The slave's commanded joints of a slave-side motion: a violation holds at once."""
        self.last_tick[key] = self.ticks
        with self.lock:
            fault = a.commanded.on_setpoint_js(msg, time.monotonic())
        if fault:
            self.urgent.set()  # revoke the lease now, not at the next period

    def _on_frame(self, msg: CameraImage, key: str) -> None:
        now = time.monotonic()
        if self.cfg.latency_source == "clock":  # one host, one clock: arrival − capture
            age_ms = (wall_ns() - msg.capture_ns) / 1e6
        else:  # across hosts: the camera's own time + the command path's one-way estimate
            with self.lock:
                one_way = self.arms[0].verdict.latency_p50_ms if self.arms else 0.0
            age_ms = msg.render_ms + msg.encode_ms + one_way
        with self.lock:
            assert self.video is not None
            self.video.on_frame(msg.header.seq, age_ms, now)

    def _on_estop(self, msg: EStop, key: str) -> None:
        if problem := self.authority.estop_problem(msg.header.source, msg.action):
            self.node.event(
                "estop_refused", problem, arm="" if msg.arm == "*" else msg.arm, severity="warning"
            )
            return
        stamp = self.node.fresh.local_ns(msg.header.source, msg.header.stamp_ns)
        if stale := self.authority.estop_order(msg.action, stamp):
            self.node.replayed(key, msg.header.source, stale)
            return
        with self.lock:
            changed = [a.safety.on_estop(msg) for a in self.arms]
        if any(changed):
            self.urgent.set()

    def _on_alive(self, service: str, alive: bool) -> None:
        with self.lock:
            if alive:
                self.alive.add(service)
            else:
                self.alive.discard(service)
            if self.video is not None and service == self.cfg.video_service:
                self.video.on_alive(alive, time.monotonic())
        if not alive and (
            service in self.cfg.required_services
            or (self.video is not None and service == self.cfg.video_service)
        ):
            self.urgent.set()  # do not wait for the next period

    def add_echo_latency(self, rtt_s: float | None) -> None:
        """Account one echo round trip (None: no reply) as a latency sample of every arm."""
        now = time.monotonic()
        with self.lock:
            for a in self.arms:
                a.safety.add_latency(rtt_s * 500.0 if rtt_s is not None else 1e4, now)

    @property
    def clock_offset_ns(self) -> int:
        """The echo_service's host clock minus this one's, ns, as the clock probes estimate it
        (0 before the first probe)."""
        return self.node.fresh.offset_ns(self.cfg.echo_service)

    def add_clock_sample(self, sample: ClockSample | None) -> None:
        """Take one clock probe of the echo_service: its latency (echo) or its host's offset
        (clock: the servo_jp origin stamps are moved onto this host's clock by it)."""
        if self.cfg.latency_source == "echo":
            self.add_echo_latency(None if sample is None else sample.delay_ns / 1e9)
            return
        if sample is None or not self.clock.add(sample, time.monotonic()):
            return
        theta = self.clock.offset_ns(time.monotonic())
        if theta is None:
            return
        first = self.clock.samples == 1
        # one place for it: the latency and the freshness rules both read it from there
        self.node.fresh.offsets[self.cfg.echo_service] = round(theta)
        if first or (self.clock.samples % 600 == 0 and abs(theta) > 1e6):
            log.info(
                "%s's clock: %s",
                self.cfg.echo_service,
                offset_text(theta, self.clock.delay_ns()),
            )

    # -- decision ---------------------------------------------------------------------------
    def hold_causes(self, a: ArmWatch) -> list[str]:
        """Liveliness and staleness causes of ``a`` (empty: healthy)."""
        with self.lock:
            alive = set(self.alive)
        out = [f"{s} not alive" for s in self.cfg.required_services if s not in alive]
        if (since := a.commanded.motion_since) is not None:  # a slave-side motion: setpoint_js fresh
            key, deadline = a.commanded_key, self.cfg.setpoint_js_deadline_ms
            age_ms = min(self.node.streams.get(key).age_s(), time.monotonic() - since) * 1e3
            ticks = self.ticks - max(self.last_tick.get(key, -(10**9)), a.motion_tick or 0)
            if age_ms > deadline and ticks * 1e3 / self.cfg.lease_hz >= deadline:
                why = f"({age_ms:.0f} ms > {deadline:.0f} ms)"
                out.append(f"slave/{a.arm}/setpoint_js stale during a slave-side motion {why}")
        for key, deadline in a.deadlines.items():
            age_ms = self.node.streams.get(key).age_s() * 1e3
            ticks = self.ticks - self.last_tick.get(key, -(10**9))
            if age_ms > deadline and ticks * 1e3 / self.cfg.lease_hz >= deadline:
                stream = key.split("/", 2)[-1]
                out.append(
                    f"{stream} never received"
                    if age_ms == float("inf")
                    else f"{stream} stale ({age_ms:.0f} ms > {deadline:.0f} ms)"
                )
        return out

    def degraded_causes(self, a: ArmWatch, now: float) -> list[str]:
        """Lost / reordered control messages over the last second."""
        total = 0
        for key in a.control:
            st = self.node.streams.get(key)
            total += st.lost + st.reordered
        m = self.node.streams.get(a.master_pose)
        a.loss.append((now, total, m.lost + m.reordered, m.received))
        while len(a.loss) > 1 and now - a.loss[1][0] >= 1.0:
            a.loss.popleft()
        first = a.loss[0]
        out = []
        lost = total - first[1]
        if lost > self.cfg.max_loss_per_s:
            out.append(f"{lost} control messages lost or reordered in the last second")
        m_lost, m_rx = m.lost + m.reordered - first[2], m.received - first[3]
        pct = 100.0 * m_lost / (m_lost + m_rx) if m_lost else 0.0
        if pct > self.cfg.max_master_loss_pct:
            out.append(f"{pct:.0f} % of the master's poses lost or reordered in the last second")
        return out

    def tick(self, *, force_state: bool = False) -> None:
        """Evaluate every arm, publish leases (and states on change or when forced)."""
        with self.tick_lock:  # the loop's periodic and urgent ticks, and a test's
            self._tick(force_state)

    def _tick(self, force_state: bool) -> None:
        self.ticks += 1
        self.node.poll()  # the polled streams, counted as seen at this tick
        now = time.monotonic()
        video = ("OK", "")
        if self.video is not None:
            with self.lock:
                video = self.video.evaluate(now)
        for a in self.arms:
            hold = self.hold_causes(a)
            degraded = self.degraded_causes(a, now)
            if video[0] == "HOLD":
                hold.append(video[1])
            elif video[0] == "DEGRADED":
                degraded.append(video[1])
            with self.lock:
                v = a.safety.evaluate(now, hold, degraded)
            a.lease_out.put(
                SafetyLease(
                    a.lease_out.header(),
                    a.arm,
                    v.allow,
                    self.cfg.lease_valid_ms,
                    "" if v.allow else f"{v.state}: " + "; ".join(v.causes)[:480],
                )
            )
            old = a.verdict
            a.verdict = v
            changed = v.state != old.state
            if changed:
                # (before the arm was first OK, the services and the camera are still coming up:
                # their HOLDs are the start-up's, not an error; an e-stop always is)
                if v.state == "OK" or not (a.ever_ok or v.state == "ESTOP"):
                    severity = "info"
                else:
                    severity = "warning" if v.state == "DEGRADED" else "error"
                self.node.event(
                    "safety_transition",
                    f"{old.state} → {v.state}" + (f": {'; '.join(v.causes)}" if v.causes else ""),
                    arm=a.arm,
                    severity=severity,
                )
                a.ever_ok |= v.state == "OK"
            if changed or force_state or v.causes != old.causes:
                self.publish_state(a)

    def serve(self, stop: threading.Event) -> None:
        """Tick every ``1/lease_hz`` s, and at once when an input asks (:attr:`urgent`), until
        ``stop``. The only thread that ticks, so the only one that puts leases and states."""
        period = 1.0 / self.cfg.lease_hz
        state_every = max(1, round(self.cfg.lease_hz / self.cfg.state_hz))
        n = 0
        next_t = time.monotonic()
        while not stop.is_set():
            if self.urgent.wait(max(0.0, next_t - time.monotonic())):
                self.urgent.clear()  # (an input's state is set before it asks: this tick sees it)
                self.tick(force_state=True)
                continue
            self.tick()
            n += 1
            if n % state_every == 0:
                with self.tick_lock:
                    for a in self.arms:
                        self.publish_state(a)
            next_t += period
            now = time.monotonic()
            if next_t < now:  # we were descheduled: skip the missed ticks instead of bursting
                next_t = now + period  # through them (a burst would age every stream in ticks too)

    def publish_state(self, a: ArmWatch) -> None:
        """Send the current safety state of ``a``."""
        v = a.verdict
        a.state_out.put(
            SafetyState(
                a.state_out.header(),
                a.arm,
                v.state,
                v.causes,
                v.scale,
                round(v.latency_p50_ms, 3),
                round(v.latency_p90_ms, 3),
                round(v.latency_p99_ms, 3),
                v.latency_samples,
                round(self.clock_offset_ns / 1e6, 3),
            )
        )
        if a.video_out is not None and self.video is not None:
            now = time.monotonic()
            with self.lock:
                w = self.video
                p50, p99, fps, _ = w.ages(now)
                since = w.since_frame_ms(now) if w.last_rx is not None else 0.0
                msg = VideoState(
                    a.video_out.header(),
                    a.arm,
                    self.cfg.video_camera,
                    w.state,
                    round(since, 3),
                    round(w.last_age_ms, 3),
                    round(p50, 3),
                    round(p99, 3),
                    round(fps, 3),
                    w.frames,
                    w.gaps,
                )
            a.video_out.put(msg)


def _probe_loop(wd: Watchdog, cfg: WatchdogConfig, stop: threading.Event) -> None:
    """Probe the echo_service's clock at ``echo_hz`` on a fixed schedule (the time an answer
    takes is not added to the period, so the window gets its samples at any round trip below it)."""
    period = 1.0 / cfg.echo_hz
    next_t = time.monotonic() + period
    while not stop.wait(max(0.0, next_t - time.monotonic())):
        next_t = max(next_t + period, time.monotonic())
        try:
            sample = wd.node.clock_probe(cfg.echo_service, timeout=cfg.latency_limit_ms / 1e3)
        except Exception:  # session closing
            return
        wd.add_clock_sample(sample)


def run(cfg: WatchdogConfig, stop: threading.Event) -> None:
    """Watch until ``stop``; leases stop with the process (fail-safe)."""
    cfg.validate()
    with Node(cfg.bus, cfg.site, cfg.service) as node:
        wd = Watchdog(cfg, node)
        threading.Thread(target=_probe_loop, args=(wd, cfg, stop), daemon=True).start()
        log.info("watching %s; required services: %s", cfg.pairs, cfg.required_services)
        settle_gc()
        wd.serve(stop)
        # Last word: revoke every lease explicitly before going away.
        for a in wd.arms:
            a.lease_out.put(
                SafetyLease(a.lease_out.header(), a.arm, False, cfg.lease_valid_ms, "watchdog stopped")
            )
        for a in wd.arms:
            log.info("%s: message-level faults %s", a.arm, a.safety.counters or "none")


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg watchdog``."""
    return service_main("watchdog", WatchdogConfig, run, argv, __doc__ or "")
