"""A Touch-like haptic device held by a simulated operator's hand (pure numpy; no I/O).

The device's handle and the hand move as one body (the grip is rigid): mass ``hand_kg +
device_kg``, driven by the hand's muscles (a spring-damper pulling towards the operator's
intent, the usual model of a relaxed grasp: Hogan 1989; Kuchenbecker et al. 2003) and by the
device's motor force, against the device's friction (Coulomb, smoothed). The motor force is
clamped to the device's force limit here, as its amplifier would: whatever a caller writes, the
device never pushes harder than ``force_limit_n``.

Geomagic (3D Systems) Touch data sheet: workspace 160 × 120 × 70 mm, maximum exertable force
3.3 N (nominal position), continuous force ≥ 0.88 N, apparent mass at the tip 45 g, backdrive
friction < 0.26 N, stiffness 1.02–2.31 N/mm.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TouchModel:
    """The device and the hand that holds it."""

    device_kg: float = 0.045  # kg: Touch apparent mass at the tip (data sheet)
    friction_n: float = 0.1  # N: Coulomb friction (data sheet: backdrive friction < 0.26 N)
    friction_speed: float = 0.005  # m/s: the Coulomb friction's smoothing speed (tanh)
    force_limit_n: float = 3.3  # N: the motor's force limit (data sheet: max exertable force)
    hand_kg: float = 0.3  # kg: hand and fingers in a pen grasp
    hand_stiffness: float = 200.0  # N/m: grasp stiffness towards the intent
    hand_damping: float = 3.0  # N·s/m: grasp damping (a light grasp: the delay-critical case)


@dataclass(frozen=True)
class Waypoint:
    """Where the operator means the handle to be from time ``t`` (s): ``position`` (m, master
    frame), reached along a smooth (cosine) blend from the previous waypoint."""

    t: float
    position: tuple[float, float, float]


def press_and_slide(
    surface_mm: float = -20.0, press_mm: float = 11.0, slide_mm: float = 20.0
) -> tuple[Waypoint, ...]:
    """The bench's script: hold still, reach down to the tissue surface (``surface_mm`` below the
    start), press ``press_mm`` further into it, slide ``slide_mm`` along x, hold, release upward."""
    z0, z1 = surface_mm / 1e3 + 0.004, (surface_mm - press_mm) / 1e3
    s = slide_mm / 1e3
    return (
        Waypoint(0.0, (0.0, 0.0, 0.0)),
        Waypoint(0.3, (0.0, 0.0, 0.0)),
        Waypoint(1.3, (0.0, 0.0, z0)),  # reach: just above the surface
        Waypoint(2.3, (0.0, 0.0, z1)),  # press
        Waypoint(3.8, (0.0, 0.0, z1)),  # hold (steady contact force)
        Waypoint(5.3, (s, 0.0, z1)),  # slide
        Waypoint(6.3, (s, 0.0, z1)),  # hold
        Waypoint(7.3, (s, 0.0, 0.0)),  # release
    )


def intent(script: tuple[Waypoint, ...], t: float) -> np.ndarray:
    """The operator's intended handle position at ``t`` (m, (3,))."""
    if t <= script[0].t:
        return np.array(script[0].position)
    for a, b in itertools.pairwise(script):
        if t < b.t:
            s = (t - a.t) / (b.t - a.t)
            w = 0.5 - 0.5 * math.cos(math.pi * s)
            return (1 - w) * np.array(a.position) + w * np.array(b.position)
    return np.array(script[-1].position)


class HeldDevice:
    """The handle and the hand as one body (see the module doc); :meth:`step` integrates one
    period (semi-implicit Euler)."""

    def __init__(self, model: TouchModel, script: tuple[Waypoint, ...]) -> None:
        self.model = model
        self.script = script
        self.x = np.zeros(3)  # m, master frame
        self.v = np.zeros(3)  # m/s
        self.motor = np.zeros(3)  # N: the force the device applies (after its limit)
        self.t = 0.0
        self.largest_motor_n = 0.0  # N: the largest motor force it ever applied
        # m, (3,): added to the script's intent (an operator making up for motion the slave did
        # not take, e.g. while it held: touch_sim's "site" operator)
        self.offset = np.zeros(3)

    def write_force(self, force: np.ndarray) -> np.ndarray:
        """Command the motor force (N); returns what the device applies (within its limit)."""
        f = np.asarray(force, dtype=float)
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            f = np.zeros(3)  # a device amplifier given nonsense applies nothing
        n = float(np.linalg.norm(f))
        if n > self.model.force_limit_n:
            f = f * (self.model.force_limit_n / n)
        self.motor = f
        self.largest_motor_n = max(self.largest_motor_n, float(np.linalg.norm(f)))
        return f.copy()

    def hand_force(self) -> np.ndarray:
        """N: the hand's muscle force this instant."""
        m = self.model
        goal = intent(self.script, self.t) + self.offset
        out: np.ndarray = m.hand_stiffness * (goal - self.x) - m.hand_damping * self.v
        return out

    def step(self, dt: float) -> None:
        m = self.model
        friction = -m.friction_n * np.tanh(self.v / m.friction_speed)
        a = (self.hand_force() + self.motor + friction) / (m.hand_kg + m.device_kg)
        self.v = self.v + a * dt
        self.x = self.x + self.v * dt
        self.t += dt
