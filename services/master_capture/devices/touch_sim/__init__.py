"""The ``touch_sim`` master device: a simulated Touch-like haptic device held by a simulated hand.

It never met hardware: the device (mass, friction, force limit from the Touch data sheet) and the
operator's hand (a spring-damper following a scripted intent: reach, press, slide, release) are
:mod:`.model`. Unlike the other devices it takes a force: :meth:`TouchSim.write_force` (clamped to
the device's limit, as a real amplifier would). The haptic loop (``docs/haptics.md``) reads its
pose and writes its force every period; ``telesurg bench haptics`` drives it against the MuJoCo
slave.

Who works the pedal (``operator``): ``"script"`` (the bench's) presses it throughout and plays
the script from the device's start; ``"site"`` plays an operator at a running site: it watches the
mapping's teleop state of ``arm`` (``mapping/<arm>/teleop_state``, what the console shows), presses
the pedal when the arm is ready to engage (IDLE) and keeps it down while engaging and engaged,
releases it when the mapping holds or refuses (a new press then engages again), and plays the
script only while engaged: the hand keeps still otherwise. It watches the slave's tip too, as a
surgeon watches the video: the script says where the slave's tip should go (from where it was at
the first engage, × the mapping's scale), and at every new engage (and change of scale: the mapping
re-anchors then) in free space the hand adds what the slave did not take while it held to where it
means to go; in contact (a force on the hand) it goes on by feel.

Example: ``telesurg master-capture --set device=touch_sim --set device_options.press_mm=8``.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.services.master_capture.devices.touch_sim.model import (
    HeldDevice,
    TouchModel,
    press_and_slide,
)
from telesurg.shared.bus import Node
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CartesianPose, TeleopState

#: Who works the pedal (module doc).
OPERATORS = ("script", "site")
#: The teleop states in which an operator at the site keeps the pedal down (IDLE: ready to engage).
PEDAL_DOWN = frozenset({"IDLE", "ENGAGING", "ENABLED"})
#: N: a force on the hand above this is contact: the operator then goes by feel, not by the video
FEEL_N = 0.1
#: s: the time constant of the operator's correction after a new engage (a hand's corrective
#: sub-movement takes a few hundred ms)
REAIM_S = 0.3


@dataclass
class TouchSimConfig:
    """``[master_capture.device_options]`` of the touch_sim device."""

    force_limit_n: float = 3.3  # N: the device's force limit (Touch data sheet: 3.3 N peak)
    friction_n: float = 0.1  # N: Coulomb friction (Touch: backdrive friction < 0.26 N)
    hand_stiffness: float = 200.0  # N/m: the simulated hand's grasp stiffness
    hand_damping: float = 3.0  # N·s/m: the simulated hand's grasp damping
    surface_mm: float = -20.0  # mm: where the script expects the tissue (below the start)
    press_mm: float = 11.0  # mm: how far the hand means to press beyond the surface
    slide_mm: float = 20.0  # mm: how far it slides along x while pressing
    step_s: float = 0.001  # s: simulation step (the device's servo period)
    # who works the pedal: "script" (pressed throughout, the script from the start) or "site"
    # (presses when the mapping says the arm is ready; the script plays while engaged)
    operator: str = "script"
    arm: str = "arm1"  # operator "site": the slave arm whose teleop state and tip it watches
    mapping_source: str = "mapping"  # operator "site": the only sender of that teleop state taken
    slave_source: str = "slave_control"  # operator "site": the only sender of that tip taken

    def __post_init__(self) -> None:
        if self.operator not in OPERATORS:
            raise ConfigError(f"touch_sim: operator {self.operator!r} invalid; valid: {', '.join(OPERATORS)}")


@register
class TouchSim(MasterDevice):
    """Simulated Touch + hand; the pedal pressed throughout."""

    name = "touch_sim"
    config = TouchSimConfig

    def __init__(self, cfg: TouchSimConfig) -> None:
        self.cfg = cfg
        model = TouchModel(
            force_limit_n=cfg.force_limit_n,
            friction_n=cfg.friction_n,
            hand_stiffness=cfg.hand_stiffness,
            hand_damping=cfg.hand_damping,
        )
        self.sim = HeldDevice(model, press_and_slide(cfg.surface_mm, cfg.press_mm, cfg.slide_mm))
        self._teleop = ""  # operator "site": the mapping's last teleop state of cfg.arm
        self._scale = 0.0  # and its motion scale (the operator's × the watchdog's)
        self._tip: np.ndarray | None = None  # the slave's last tip seen (m, base frame)
        self._lock = threading.Lock()
        self._last_t: float | None = None  # device time of the previous read
        self._played = 0.0  # s of device time the script has played (operator "site")
        self._engaged: tuple[float, ...] | None = None  # (scale,) of the engagement being played
        self._s0: np.ndarray | None = None  # the slave's tip at the first engage
        self._aim = np.zeros(3)  # the offset the hand's goal is blended towards (m)

    def connect(self, node: Node) -> None:
        """Operator "site": watch the mapping's teleop state and the slave's tip (master_capture
        calls this)."""
        if self.cfg.operator == "site":
            k = node.keys
            teleop = k.mapping(self.cfg.arm, "teleop_state")
            node.subscribe(
                teleop, TeleopState, self._on_teleop, sources=[self.cfg.mapping_source], latest=True
            )
            tip = k.slave(self.cfg.arm, "measured_cp")
            node.subscribe(tip, CartesianPose, self._on_tip, sources=[self.cfg.slave_source])

    def _on_teleop(self, m: TeleopState, key: str) -> None:
        with self._lock:
            self._teleop, self._scale = m.state, m.scale * m.safety_scale

    def _on_tip(self, m: CartesianPose, key: str) -> None:
        with self._lock:
            self._tip = np.array(m.position)

    def _reanchor(self, scale: float, tip: np.ndarray | None) -> None:
        """A new engagement (or scale) from the mapping: aim the hand so that the slave's tip goes
        where the script meant it to (module doc)."""
        if tip is None or scale <= 0.0:
            return
        if self._s0 is None:
            self._s0 = tip.copy()
            return
        if float(np.linalg.norm(self.sim.motor)) > FEEL_N:
            return  # in contact the operator presses by feel, not to a place on the video
        # engaged now: slave = tip + scale (x − x_now); the script wants s0 + scale · script(t),
        # so the hand goes to script(t) + x_now + (s0 − tip) / scale (blended in over REAIM_S, as
        # a hand corrects a movement, not in a jump)
        self._aim = self.sim.x + (self._s0 - tip) / scale

    def read(self, t: float) -> DeviceSample:
        pedal = True
        if self.cfg.operator == "site":
            with self._lock:
                state, scale, tip = self._teleop, self._scale, self._tip
            pedal = state in PEDAL_DOWN
            engaged = (scale,) if state == "ENABLED" else None
            if engaged is not None and engaged != self._engaged:
                self._reanchor(scale, tip)
            self._engaged = engaged
            # the script's clock runs while engaged only: the hand keeps still otherwise
            if state == "ENABLED" and self._last_t is not None:
                self._played += max(0.0, t - self._last_t)
            self._last_t = t
            t = self._played
        blend = self.cfg.step_s / REAIM_S
        while self.sim.t + self.cfg.step_s <= t:  # catch the simulation up to t
            if self.cfg.operator == "site":
                self.sim.offset += blend * (self._aim - self.sim.offset)
            self.sim.step(self.cfg.step_s)
        x = self.sim.x
        return DeviceSample((float(x[0]), float(x[1]), float(x[2])), (0.0, 0.0, 0.0, 1.0), pedal, True)

    def write_force(self, force: np.ndarray) -> np.ndarray:
        """Command the device's force (N, master frame); returns the force applied (≤ the limit)."""
        return self.sim.write_force(force)
