"""master_capture: samples a master device and publishes its pose, joints and buttons.

Publishes at ``rate_hz`` on ``master/<arm>/measured_cp`` (CartesianPose, m, master frame) and, for
devices with joints, ``master/<arm>/measured_js``; ``master/<arm>/buttons`` (MasterButtons) goes out
before the pose on every change (and in the ``DATAGRAM_REPEAT`` cycles after it, shared/bus.py)
and at least at ``buttons_hz``. All three are datagram streams: with ``--datagram`` they go best effort over
UDP, in one order (shared/bus.py), so a clutch release never arrives after the poses that follow
it, and one lost packet does not lose the release. While the device's reading is not
valid (``DeviceSample.valid``) nothing is published, so the watchdog holds. A device with an
``engage_retry`` (the scripted pedal) is told of the mapping's refused engages of this master
(``mapping/*/teleop_state`` ENGAGING → HOLDING); a device with a ``connect(node)`` (the ``policy``
device) is given the node to subscribe what it observes. Devices: :mod:`.devices`. With
``haptics.slave_arm`` set and a device that takes a force (``touch_sim``), it renders that slave's
``measured_cf`` every period (:class:`HapticLoop`, docs/haptics.md).

Examples::

    telesurg master-capture --connect tcp/127.0.0.1:7447 --set arm=m1 --set scripted.radius=0.03
    telesurg master-capture --set device=serial --set serial.port=/dev/ttyACM0
    telesurg master-capture --set device=touch_sim --set rate_hz=1000 --set haptics.slave_arm=arm1
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
from telesurg.services.master_capture import devices
from telesurg.services.master_capture.devices.desk import DeskConfig
from telesurg.services.master_capture.devices.scripted import EngageRetry, ScriptedConfig
from telesurg.services.master_capture.devices.serial import SerialMasterConfig
from telesurg.shared.bus import BusConfig, Node, Resend
from telesurg.shared.errors import ConfigError
from telesurg.shared.haptics import BilateralConfig, ForceRenderer, RenderConfig, SlavePacket, make_bilateral
from telesurg.shared.haptics.guidance import Guidance, GuidanceSettings
from telesurg.shared.kinematics import matrix_from_quat
from telesurg.shared.messages import (
    CartesianPose,
    CartesianWrench,
    JointState,
    MasterButtons,
    SafetyState,
    TeleopState,
)
from telesurg.shared.timing import CycleTimer, check_rt_priority, start_loop

log = logging.getLogger(__name__)


@dataclass
class HapticsConfig:
    """``[master_capture.haptics]``: force feedback for a device that takes a force (docs/haptics.md)."""

    slave_arm: str = ""  # slave arm whose measured_cf this master renders ("": no force feedback)
    slave_source: str = "slave_control"  # service id: the only sender of measured_cf taken
    watchdog_source: str = "watchdog"  # service id: its safety/<slave_arm>/state HOLD/ESTOP fades the force
    controller: str = "tdpa"  # none / naive / tdpa / wave (master side; shared/haptics/tdpa.py)
    force_scale: float = 0.5  # master force per slave contact force
    limit_n: float = 3.3  # N: the device's force limit (Touch: 3.3 N peak)
    rate_n_per_s: float = 200.0  # N/s: largest change of the force while the stream is fresh
    fade_n_per_s: float = 10.0  # N/s: fade to zero when the stream is stale or the watchdog holds
    stale_ms: float = 20.0  # ms: no measured_cf for this long → fade (slave_control sends at 500 Hz)
    # guidance rendered here, without the network (docs/haptics.md), with or without slave_arm:
    # the master's workspace walls (a box in the master frame, mm; both corners or neither)
    walls_min_mm: tuple[float, float, float] | None = None
    walls_max_mm: tuple[float, float, float] | None = None
    # the virtual trocar (mm, master frame: the mapping's virtual_trocar_mm): the handle is a dummy
    # forceps through this fulcrum, within its length, off the fulcrum and within a tilt
    trocar_mm: tuple[float, float, float] | None = None
    trocar_forceps_mm: float = 200.0  # mm: the dummy forceps' length (the mapping's dummy_forceps_mm)
    trocar_handle_min_mm: float = 40.0  # mm: the handle's closest approach to the fulcrum
    trocar_tilt_max_deg: float = 60.0  # deg: the dummy shaft's largest tilt from straight down
    guidance_stiffness_n_per_m: float = 1000.0  # N/m: of the walls and the trocar
    guidance_damping_ns_per_m: float = 2.0  # N·s/m: of the walls and the trocar, moving further in


def guidance_settings(h: HapticsConfig) -> GuidanceSettings:
    """The guidance of ``[master_capture.haptics]``, checked (a clear error for a bad value)."""
    walls = None
    if (h.walls_min_mm is None) != (h.walls_max_mm is None):
        raise ConfigError("haptics.walls_min_mm and walls_max_mm: set both corners of the box, or neither")
    if h.walls_min_mm is not None and h.walls_max_mm is not None:
        lo, hi = np.array(h.walls_min_mm, dtype=float), np.array(h.walls_max_mm, dtype=float)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise ConfigError(
                f"haptics.walls_min_mm {h.walls_min_mm} must be below walls_max_mm "
                f"{h.walls_max_mm} on every axis"
            )
        walls = (tuple(lo / 1e3), tuple(hi / 1e3))
    if not 0.0 < h.trocar_handle_min_mm < h.trocar_forceps_mm:
        raise ConfigError(
            f"haptics.trocar_handle_min_mm={h.trocar_handle_min_mm} must be in "
            f"(0, trocar_forceps_mm={h.trocar_forceps_mm})"
        )
    if not 0.0 < h.trocar_tilt_max_deg < 180.0:
        raise ConfigError(f"haptics.trocar_tilt_max_deg={h.trocar_tilt_max_deg} outside (0, 180)")
    if not (h.guidance_stiffness_n_per_m > 0.0 and h.guidance_damping_ns_per_m >= 0.0):
        raise ConfigError("haptics.guidance_stiffness_n_per_m must be > 0 and guidance_damping_ns_per_m >= 0")
    return GuidanceSettings(
        walls=walls,
        trocar=None if h.trocar_mm is None else tuple(np.array(h.trocar_mm, dtype=float) / 1e3),
        forceps_m=h.trocar_forceps_mm / 1e3,
        handle_min_m=h.trocar_handle_min_mm / 1e3,
        tilt_max_deg=h.trocar_tilt_max_deg,
        stiffness=h.guidance_stiffness_n_per_m,
        damping=h.guidance_damping_ns_per_m,
    )


@dataclass
class MasterCaptureConfig:
    """master_capture config."""

    site: str = "local"  # key prefix telesurg/<site>
    service: str = "master_capture"  # instance id (liveliness alive/<service>, header src)
    arm: str = "m1"  # master arm id in keys master/<arm>/...
    rate_hz: float = 500.0  # Hz: publish rate of the pose (and joints)
    buttons_hz: float = 50.0  # Hz: buttons are sent on every change and at least this often
    # master device: a registered name (services/master_capture/devices/, one file each; plugins
    # add more; --help lists them)
    device: str = "scripted"
    scripted: ScriptedConfig = field(default_factory=ScriptedConfig)  # scripted device settings
    serial: SerialMasterConfig = field(default_factory=SerialMasterConfig)  # serial encoder-board settings
    desk: DeskConfig = field(default_factory=DeskConfig)  # desk device settings (spacemouse … gamepad)
    # settings of a plugin device (its config dataclass's keys; docs/extending.md)
    device_options: dict[str, Any] = field(default_factory=dict)
    # The operator console's keyboard clutch (console/<arm>/clutch) is ORed with the device's
    # pedal while it is fresh; "" turns it off. A console that dies or is cut off counts as released.
    console_source: str = "console"
    console_clutch_timeout_ms: float = 250.0
    # service id of the mapping: only its teleop states (a refused engage) make the scripted pedal
    # press again (scripted.retry_refused_engage_s)
    mapping_source: str = "mapping"
    # SCHED_FIFO priority of the sampling loop's thread, 1-99 (0: the normal scheduler): a FIFO
    # loop is not preempted by the other processes' threads; needs root or CAP_SYS_NICE (docs/deploy.md)
    rt_priority: int = 0
    haptics: HapticsConfig = field(default_factory=HapticsConfig)  # force feedback (off unless slave_arm)
    bus: BusConfig = field(default_factory=BusConfig)  # zenoh session


def run(cfg: MasterCaptureConfig, stop: threading.Event) -> None:
    """Sample and publish until ``stop``."""
    if not 1.0 <= cfg.rate_hz <= 5000.0:
        raise ConfigError(f"rate_hz={cfg.rate_hz} outside [1, 5000]")
    check_rt_priority(cfg.rt_priority)
    device = devices.open_device(cfg.device, cfg)
    with device, Node(cfg.bus, cfg.site, cfg.service) as node:
        k = node.keys
        connect = getattr(device, "connect", None)
        if callable(connect):  # a device that reads the bus (policy: the slave's measurements)
            connect(node)
        pose_out = node.outlet(k.master(cfg.arm, "measured_cp"), datagram=True)
        buttons_out = node.outlet(k.master(cfg.arm, "buttons"), datagram=True)
        js_out = node.outlet(k.master(cfg.arm, "measured_js"), datagram=True) if device.joint_names else None
        timer = CycleTimer(cfg.rate_hz)
        t0 = time.monotonic()
        resend = Resend(round(cfg.rate_hz / cfg.buttons_hz))
        outages = 0
        console: list[tuple[bool, float]] = [(False, 0.0)]  # (pressed, monotonic time received)

        def on_console(m: MasterButtons, key: str) -> None:
            console[0] = (m.clutch, time.monotonic())

        if cfg.console_source:
            node.subscribe(k.console_clutch(cfg.arm), MasterButtons, on_console, sources=[cfg.console_source])
        console_timeout = cfg.console_clutch_timeout_ms / 1e3
        # a device that answers a refused engage (the scripted pedal) has an engage_retry
        retry = getattr(device, "engage_retry", None)
        if not isinstance(retry, EngageRetry):
            retry = None
        if retry is not None:
            engage_retry = retry

            def on_teleop(m: TeleopState, key: str) -> None:
                # ENGAGING → HOLDING is the refused engage (docs/architecture.md, the teleop state machine)
                refused = m.master == cfg.arm and m.state == "HOLDING" and m.previous == "ENGAGING"
                if refused and engage_retry.refused(m.since_ns):
                    log.info("[%s] %s", m.slave, m.reason)

            mapping = [cfg.mapping_source]
            node.subscribe(k.mapping("*", "teleop_state"), TeleopState, on_teleop, sources=mapping)
        guided = guidance_settings(cfg.haptics)
        haptic = HapticLoop(cfg, device, node) if cfg.haptics.slave_arm or Guidance(guided).on else None
        invalid_since: float | None = None  # time.monotonic() when the reading became invalid
        invalid_kind = ""  # why (the device's status up to its first ':'), said again when it changes
        log.info("publishing master %s at %.0f Hz (%s)", cfg.arm, cfg.rate_hz, cfg.device)
        start_loop(cfg.rt_priority)
        while not stop.is_set():
            s = device.read(time.monotonic() - t0)
            if not s.valid:  # stale / unplugged / refused: publish nothing, the watchdog holds
                why = device_status(device)
                if invalid_since is None or why.split(":", 1)[0] != invalid_kind:
                    # an event, so a launcher waiting for the master's first sample can say why
                    if invalid_since is None:
                        invalid_since = time.monotonic()
                        outages += 1
                        text = f"master {cfg.arm}: no fresh device reading{f' ({why})' if why else ''}"
                        text += "; not publishing until one arrives"
                    else:
                        text = f"master {cfg.arm}: device {why}; still not publishing"
                    invalid_kind = why.split(":", 1)[0]
                    node.event("master_device", text, severity="warning")
                resend.reset()  # buttons go out first thing when readings resume
                timer.wait()
                continue
            if invalid_since is not None:
                log.info(
                    "master %s: device fresh again after %.2f s; publishing",
                    cfg.arm,
                    time.monotonic() - invalid_since,
                )
                invalid_since = None
            pressed, at = console[0]
            console_clutch = pressed and time.monotonic() - at <= console_timeout
            # (the grip to 0.01: a sensor's noise is not a change to send at once)
            buttons = (s.clutch or console_clutch, s.operator_present, round(min(max(s.grip, 0.0), 1.0), 2))
            if resend.due(buttons):
                buttons_out.put(MasterButtons(buttons_out.header(), *buttons))
            energy = haptic.step(s.position, time.monotonic()) if haptic is not None else 0.0
            pose_out.put(CartesianPose(pose_out.header(), "master", s.position, s.orientation, energy))
            if js_out is not None:
                js_out.put(JointState(js_out.header(), device.joint_names, s.joints))
            timer.wait()
        log.info(
            "sent %d samples, %d loop overruns, %d device outages%s",
            pose_out.sent,
            timer.overruns,
            outages,
            f", {retry.retries} presses again after a refused engage" if retry is not None else "",
        )
        if haptic is not None and cfg.haptics.slave_arm:
            log.info(
                "[%s] master passivity: observed W_m min %.3f mJ, dissipated %.3f mJ",
                cfg.haptics.slave_arm,
                haptic.w_min * 1e3,
                haptic.bil.dissipated_m * 1e3,
            )


class HapticLoop:
    """The console side of force feedback, once per sampling period: the newest ``measured_cf`` of
    ``haptics.slave_arm`` (from ``slave_source`` only: forged, replayed and malformed ones never get
    here) through the bilateral controller's master side and the force renderer (check, fade when
    stale, held or not engaged, rate limit, device limit) to the device's ``write_force``. The
    force is rendered only while the mapping says the pair is engaged (teleop ``ENABLED``): a
    master clutched out, or not yet engaged, is not pushed by a slave it does not move. The
    slave's force is rotated into the master frame by the mapping's ``R_ms`` (its teleop
    state's ``rotation``): the surgeon feels it in the frame they move in. Returns the master
    port's input energy for ``measured_cp.energy_in_j``."""

    def __init__(self, cfg: MasterCaptureConfig, device: object, node: Node) -> None:
        h = cfg.haptics
        write = getattr(device, "write_force", None)
        if not callable(write):
            raise ConfigError(
                f"haptics (slave_arm or guidance) is set but device {cfg.device!r} takes no force "
                "(one with write_force, e.g. touch_sim)"
            )
        self.write = write
        self.guidance = Guidance(guidance_settings(h))
        self.bil = make_bilateral(BilateralConfig(controller=h.controller, force_scale=h.force_scale))
        self.renderer = ForceRenderer(RenderConfig(h.limit_n, h.rate_n_per_s, h.fade_n_per_s, h.stale_ms))
        self.lock = threading.Lock()
        self.packet: SlavePacket | None = None
        self.rx_at = -math.inf  # monotonic s: newest measured_cf
        self.hold = False
        self.engaged = False  # the mapping's teleop state is ENABLED
        self.x_prev: np.ndarray | None = None
        self.t_prev = 0.0
        self.w_min = 0.0  # J: the lowest W_m, the master port's observer, after its controller acted
        # E_in_s in master units, summed from this loop's first measured_cf on (as its own
        # E_out_m): each increase of the slave's sum (slave units) × force_scale / position_scale
        # at the time, the position scale being the mapping's (its teleop state: the operator's
        # scale × the watchdog's)
        self.e_in_s_slave: float | None = None  # the slave's last sum, slave units
        self.e_in_s = 0.0
        self.position_scale = 1.0
        # the slave base → master frame rotation, R_msᵀ of the mapping's teleop state (the camera's
        # view or the work frame the master moves the slave in)
        self.r_sm = np.eye(3)
        k = node.keys
        if not h.slave_arm:  # guidance alone: no force from the slave
            return

        def on_wrench(m: CartesianWrench, key: str) -> None:
            with self.lock:
                if self.e_in_s_slave is not None and m.energy_in_j > self.e_in_s_slave:
                    self.e_in_s += h.force_scale / self.position_scale * (m.energy_in_j - self.e_in_s_slave)
                self.e_in_s_slave = m.energy_in_j
                # the slave's force (base frame) in the master's: R_msᵀ F
                self.packet = SlavePacket(m.header.seq, self.r_sm @ np.array(m.force), self.e_in_s)
                self.rx_at = time.monotonic()

        def on_teleop(m: TeleopState, key: str) -> None:
            self.engaged = m.state == "ENABLED"
            n = np.array(m.limit_wall[:3])
            # the slave's nearest joint limit, a wall here while engaged (a unit normal; else none)
            wall = (n, m.limit_wall[3]) if self.engaged and abs(float(n @ n) - 1.0) < 1e-3 else None
            with self.lock:
                self.r_sm = matrix_from_quat(m.rotation).T
                self.guidance.limit_wall = wall
            if m.scale * m.safety_scale > 0.0:
                with self.lock:
                    self.position_scale = m.scale * m.safety_scale

        def on_safety(m: SafetyState, key: str) -> None:
            self.hold = m.state in ("HOLD", "ESTOP")

        node.subscribe(
            k.slave(h.slave_arm, "measured_cf"), CartesianWrench, on_wrench, sources=[h.slave_source]
        )
        node.subscribe(k.safety(h.slave_arm, "state"), SafetyState, on_safety, sources=[h.watchdog_source])
        node.subscribe(
            k.mapping(h.slave_arm, "teleop_state"),
            TeleopState,
            on_teleop,
            sources=[cfg.mapping_source],
            latest=True,
        )

    def step(self, position: tuple[float, float, float], now: float) -> float:
        x = np.array(position)
        dt = max(now - self.t_prev, 1e-4) if self.x_prev is not None else 1e-3
        v = (x - self.x_prev) / dt if self.x_prev is not None else np.zeros(3)
        self.x_prev, self.t_prev = x, now
        with self.lock:
            packet, self.packet, rx_at = self.packet, None, self.rx_at
        force = self.bil.master_step(x, v, packet, dt)
        self.renderer.offer(force, rx_at)
        shaped = self.renderer.step(now, dt, self.hold or not self.engaged)
        if not self.renderer.fading:
            shaped = self.bil.master_passivity(shaped, v, dt)
        if self.guidance.on:  # local: neither faded nor delayed; not the network port's energy
            self.write(shaped + self.guidance.force(x, v))
            self.bil.master_sent(shaped, x, v, dt)
        else:
            applied = np.asarray(self.write(shaped), dtype=float)
            self.bil.master_sent(applied, x, v, dt)
        self.w_min = min(self.w_min, self.bil.observed_master)
        return self.bil.master.e_in


def device_status(device: object) -> str:
    """The device's one-line status (``refused: …``, ``disconnected: …``), "" if it has none."""
    status = getattr(device, "status", None)
    return str(status()) if callable(status) else ""


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg master-capture``."""
    about = f"{__doc__ or ''}\nMaster devices: {', '.join(devices.names())} (more from --plugin FILE).\n"
    return service_main("master-capture", MasterCaptureConfig, run, argv, about)
