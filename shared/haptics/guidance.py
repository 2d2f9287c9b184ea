"""Haptic guidance rendered on the console, without the network: the master's workspace walls, the
virtual trocar (Jinno 2014's virtual-trocar master) as a physical constraint of the handle, and the
slave's nearest joint limit as a wall (the mapping's ``limit_wall``, shared/teleop/limit_wall.py).

A wall is a spring and a damper normal to it, acting only while the handle is beyond it (the
damper only while it moves further in): ``f = k · depth − b · v_in``. The virtual trocar is the
fulcrum ``c`` of a dummy forceps of length ``L`` whose handle is the device: the handle stays
between ``r_min`` of the fulcrum (the handle's body against the trocar) and ``L`` (the dummy tip
back at the trocar), and the shaft within ``tilt_max`` of straight down (the trocar's cone in the
body wall); beyond either, the same spring and damper push it back along the shortest way in.

Units: m, m/s, N; vectors are (3,) arrays in the master frame.

Example::

    g = Guidance(GuidanceSettings(walls=((-0.08, -0.06, -0.05), (0.08, 0.06, 0.05))))
    g.force(x, v)   # N: the push back into the workspace (zero inside it)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

AXIS = np.array([0.0, 0.0, -1.0])  # the virtual trocar's axis: from the handle down through the fulcrum


@dataclass(frozen=True)
class GuidanceSettings:
    """What to render (``None``: that constraint off); see the module doc."""

    walls: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # (min, max), m
    trocar: tuple[float, float, float] | None = None  # the fulcrum c, m
    forceps_m: float = 0.2  # L: the dummy forceps' length
    handle_min_m: float = 0.04  # r_min: the handle's closest approach to the fulcrum
    tilt_max_deg: float = 60.0  # the shaft's largest tilt from straight down
    stiffness: float = 1000.0  # N/m
    damping: float = 2.0  # N·s/m


def wall_force(
    x: np.ndarray, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, k: float, b: float
) -> np.ndarray:
    """N: the walls of the box ``lo``–``hi`` pushing a handle at ``x`` (moving at ``v``) back in."""
    below, above = x < lo, x > hi
    f = np.zeros(3)
    f[below] = k * (lo - x)[below] - b * np.minimum(v, 0.0)[below]
    f[above] = k * (hi - x)[above] - b * np.maximum(v, 0.0)[above]
    return f


def trocar_force(x: np.ndarray, v: np.ndarray, s: GuidanceSettings) -> np.ndarray:
    """N: the virtual trocar's push on a handle at ``x`` (moving at ``v``); zero where the dummy
    forceps is within its reach and its cone."""
    assert s.trocar is not None
    c = np.asarray(s.trocar, dtype=float)
    d = c - x
    r = float(np.linalg.norm(d))
    u = d / r if r > 1e-9 else AXIS.copy()  # from the handle to the fulcrum
    k, b = s.stiffness, s.damping
    f = np.zeros(3)
    v_out = float(-v @ u)  # speed away from the fulcrum
    if r > s.forceps_m:  # the dummy tip would leave the trocar: pull the handle back towards it
        f += (k * (r - s.forceps_m) + b * max(v_out, 0.0)) * u
    elif r < s.handle_min_m:  # the handle against the trocar: push it out
        f -= (k * (s.handle_min_m - r) + b * max(-v_out, 0.0)) * u
    tilt = math.acos(float(np.clip(u @ AXIS, -1.0, 1.0)))
    excess = tilt - math.radians(s.tilt_max_deg)
    if excess > 0.0:
        # the handle moves on the sphere round c: towards the axis is along −(AXIS − (AXIS·u) u)
        t = AXIS - (AXIS @ u) * u
        n = float(np.linalg.norm(t))
        if n > 1e-9:
            back = -t / n  # the direction that brings the shaft back into the cone
            v_away = float(-v @ back)
            f += (k * r * excess + b * max(v_away, 0.0)) * back
    return f


def plane_force(x: np.ndarray, v: np.ndarray, n: np.ndarray, d: float, k: float, b: float) -> np.ndarray:
    """N: the wall ``n·x = d`` (``n`` a unit vector) pushing a handle at ``x`` beyond it (``n·x > d``,
    moving at ``v``) back; zero on the free side."""
    depth = float(n @ x) - d
    if depth <= 0.0:
        return np.zeros(3)
    out: np.ndarray = -(k * depth + b * max(float(n @ v), 0.0)) * n
    return out


class Guidance:
    """The sum of the configured constraints' forces (:meth:`force`); ``limit_wall`` (``(n, d)``
    or None) is the slave's joint-limit wall, set from the mapping's teleop state while engaged."""

    def __init__(self, settings: GuidanceSettings) -> None:
        self.s = settings
        self.lo = np.asarray(settings.walls[0], dtype=float) if settings.walls else None
        self.hi = np.asarray(settings.walls[1], dtype=float) if settings.walls else None
        self.limit_wall: tuple[np.ndarray, float] | None = None

    @property
    def on(self) -> bool:
        return self.lo is not None or self.s.trocar is not None or self.limit_wall is not None

    def force(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        f = np.zeros(3)
        if (wall := self.limit_wall) is not None:
            f += plane_force(x, v, wall[0], wall[1], self.s.stiffness, self.s.damping)
        if self.lo is not None and self.hi is not None:
            f += wall_force(x, v, self.lo, self.hi, self.s.stiffness, self.s.damping)
        if self.s.trocar is not None:
            f += trocar_force(x, v, self.s)
        return f
