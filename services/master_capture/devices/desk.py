"""What the desk devices (spacemouse, gamepad: rate control; touch, omega7: absolute) share:
their settings (``[master_capture.desk]``), the device-independent parts and :class:`DeskDevice`,
the base class of each desk device's file (``spacemouse.py`` …).

* :class:`RateIntegrator` — rate control: each axis in [-1, 1] through a deadband, times the top
  speed, integrated over the reading's time step (capped at ``max_dt_s``), kept inside the
  workspace box; rotation integrated as a quaternion (body-fixed increments);
* :class:`ButtonEdges` — the clutch from a button: ``hold`` or ``toggle``;
* staleness — a reading older than ``stale_ms`` makes the sample invalid (nothing is published);
* :func:`scaled_position` — absolute devices: device position (m, its frame) → master frame,
  through ``rotation_rpy_deg`` and an offset.

A device's binding imports its library when the device is opened; without it the open fails with
a :class:`~telesurg.shared.errors.DeviceConnectionError` naming the package and the vendor SDK.
None of the bindings has been run against hardware (docs/console.md, "Desk devices").
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import ClassVar, Protocol

import numpy as np
from telesurg.services.master_capture.devices import DeviceSample, MasterDevice
from telesurg.shared.errors import ConfigError, DeviceConnectionError


@dataclass
class DeskConfig:
    """Desk device settings (``[master_capture.desk]``); which apply depends on the type."""

    # rate control (spacemouse, gamepad)
    deadband: float = 0.1  # fraction of full scale ignored around rest, [0, 0.9]
    max_speed_mm_s: float = 50.0  # mm/s of master motion at full deflection
    max_rot_deg_s: float = 45.0  # deg/s of master rotation at full deflection (0: rotation off)
    workspace_mm: float = 150.0  # mm: the integrated pose stays within ±this on each axis
    max_dt_s: float = 0.05  # s: a longer gap between readings integrates only this long
    # absolute devices (touch, omega7): master = R(rotation_rpy_deg) · device + offset
    rotation_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # buttons
    clutch_button: int = 0  # the device's button number that is the clutch
    clutch_mode: str = "hold"  # hold: pressed while held (a pedal); toggle: each press flips it
    grasp_threshold: float = 0.5  # omega7: gripper closed beyond this fraction (reported, not mapped)
    stale_ms: float = 50.0  # ms: a reading older than this is invalid (nothing is published)
    device_index: int = 0  # which device of that type (first = 0)

    def validate(self) -> None:
        """Raise ConfigError naming the problem."""
        if not 0.0 <= self.deadband <= 0.9:
            raise ConfigError(f"desk deadband={self.deadband} outside [0, 0.9]")
        if not 0.0 < self.max_speed_mm_s <= 1000.0:
            raise ConfigError(f"desk max_speed_mm_s={self.max_speed_mm_s} outside (0, 1000]")
        if not 0.0 <= self.max_rot_deg_s <= 360.0:
            raise ConfigError(f"desk max_rot_deg_s={self.max_rot_deg_s} outside [0, 360]")
        if not 1.0 <= self.workspace_mm <= 1000.0:
            raise ConfigError(f"desk workspace_mm={self.workspace_mm} outside [1, 1000]")
        if not 0.001 <= self.max_dt_s <= 0.5:
            raise ConfigError(f"desk max_dt_s={self.max_dt_s} outside [0.001, 0.5]")
        if self.clutch_mode not in ("hold", "toggle"):
            raise ConfigError(f"desk clutch_mode {self.clutch_mode!r} invalid; valid: hold, toggle")
        if self.clutch_button < 0 or self.device_index < 0:
            raise ConfigError("desk clutch_button and device_index must be >= 0")
        if not 1.0 <= self.stale_ms <= 1000.0:
            raise ConfigError(f"desk stale_ms={self.stale_ms} outside [1, 1000]")


# --------------------------------------------------------------------------- device-independent


def quat_mul(
    a: tuple[float, float, float, float], b: tuple[float, float, float, float]
) -> tuple[float, float, float, float]:
    """Hamilton product of quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    )


def quat_from_rotvec(v: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w) of the rotation vector ``v`` (rad)."""
    ang = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    if ang < 1e-12:
        return (0.0, 0.0, 0.0, 1.0)
    s = math.sin(ang / 2) / ang
    return (v[0] * s, v[1] * s, v[2] * s, math.cos(ang / 2))


def rpy_matrix(rpy_deg: tuple[float, float, float]) -> tuple[tuple[float, float, float], ...]:
    """Rotation matrix Rz(yaw) Ry(pitch) Rx(roll) of roll/pitch/yaw in degrees."""
    r, p, y = (math.radians(a) for a in rpy_deg)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (
        (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
        (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
        (-sp, cp * sr, cp * cr),
    )


def deadband(v: float, band: float) -> float:
    """``v`` in [-1, 1] with ``band`` around 0 removed and the rest rescaled to [-1, 1]."""
    v = max(-1.0, min(1.0, v))
    if abs(v) <= band:
        return 0.0
    return math.copysign((abs(v) - band) / (1.0 - band), v)


@dataclass
class RateIntegrator:
    """Rate control: axes in [-1, 1] → an integrated master pose (m, quaternion x y z w)."""

    cfg: DeskConfig
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    clamped: int = 0  # readings whose integrated position was held at the workspace box
    _t: float | None = None

    def step(self, t: float, trans: tuple[float, float, float], rot: tuple[float, float, float]) -> None:
        """Integrate one reading taken at device time ``t`` (s)."""
        dt = 0.0 if self._t is None else min(max(t - self._t, 0.0), self.cfg.max_dt_s)
        self._t = t
        v = self.cfg.max_speed_mm_s / 1e3
        lim = self.cfg.workspace_mm / 1e3
        p = []
        for x, a in zip(self.position, trans, strict=True):
            nx = x + deadband(a, self.cfg.deadband) * v * dt
            if abs(nx) > lim:
                self.clamped += 1
                nx = math.copysign(lim, nx)
            p.append(nx)
        self.position = (p[0], p[1], p[2])
        w = math.radians(self.cfg.max_rot_deg_s) * dt
        if w > 0:
            inc = quat_from_rotvec(tuple(deadband(a, self.cfg.deadband) * w for a in rot))  # type: ignore[arg-type]
            q = quat_mul(self.orientation, inc)  # body-fixed increment
            n = math.sqrt(sum(c * c for c in q))
            self.orientation = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@dataclass
class ButtonEdges:
    """The clutch from one button: ``hold`` or ``toggle`` (flips on each rising edge)."""

    mode: str = "hold"
    presses: int = 0  # rising edges seen
    _last: bool = False
    _toggled: bool = False

    def update(self, pressed: bool) -> bool:
        """The clutch given the button's state now."""
        rising = pressed and not self._last
        self._last = pressed
        if rising:
            self.presses += 1
            self._toggled = not self._toggled
        return pressed if self.mode == "hold" else self._toggled

    def reset(self) -> None:
        """The device was lost: the clutch is released and a new press is needed."""
        self._last = self._toggled = False


def scaled_position(device_m: tuple[float, float, float], cfg: DeskConfig) -> tuple[float, float, float]:
    """An absolute device's position (m, its own frame) in the master frame."""
    r = rpy_matrix(cfg.rotation_rpy_deg)
    out = [sum(r[i][j] * device_m[j] for j in range(3)) + cfg.offset_mm[i] / 1e3 for i in range(3)]
    return (out[0], out[1], out[2])


# --------------------------------------------------------------------------- bindings


@dataclass(frozen=True)
class Reading:
    """One raw reading of a desk device (what a binding returns)."""

    t: float  # s, the device's (or the reader's monotonic) time of the reading
    trans: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rate devices: axes in [-1, 1]
    rot: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rate devices: axes in [-1, 1]
    position: tuple[float, float, float] | None = None  # absolute devices: m, device frame
    orientation: tuple[float, float, float, float] | None = None  # absolute devices: x y z w
    buttons: tuple[bool, ...] = ()
    grasp: float = 0.0  # omega7 gripper closure, 0 (open) … 1 (closed)


class Binding(Protocol):
    """What a desk device's library gives: open, read, close."""

    def open(self) -> None: ...

    def read(self) -> Reading | None: ...

    def close(self) -> None: ...


class ForceBinding(Binding, Protocol):
    """A haptic desk device's library also takes a force (N, the device's own frame)."""

    def write_force(self, force: tuple[float, float, float]) -> None: ...


def need_library(device: type[DeskDevice], module: str) -> object:
    """Import ``module`` for ``device``; DeviceConnectionError naming its ``library``."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        package, also = device.library
        raise DeviceConnectionError(
            f"{device.name}: Python package {package!r} not installed ({exc}); it also needs {also}"
        ) from None


def quat_of_columns(m: object) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of a rotation given as columns ``m[c][r]`` (the first 3×3)."""
    c = m  # c[col][row]
    r00, r11, r22 = c[0][0], c[1][1], c[2][2]  # type: ignore[index]
    r21, r12 = c[1][2], c[2][1]  # type: ignore[index]
    r02, r20 = c[2][0], c[0][2]  # type: ignore[index]
    r10, r01 = c[0][1], c[1][0]  # type: ignore[index]
    w = math.sqrt(max(0.0, 1.0 + r00 + r11 + r22)) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r00 - r11 - r22)) / 2, r21 - r12)
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r00 + r11 - r22)) / 2, r02 - r20)
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r00 - r11 + r22)) / 2, r10 - r01)
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    return (x / n, y / n, z / n, w / n)


class DeskDevice(MasterDevice):
    """A desk device: its ``binding`` (a library's reader) turned into master samples.

    Rate devices integrate their axes (:class:`RateIntegrator`); absolute ones (``absolute =
    True``) map their pose (:func:`scaled_position`). The clutch comes from ``clutch_button``
    (:class:`ButtonEdges`); a missing or stale reading makes the sample invalid and resets the
    clutch (a new press is needed). A subclass sets ``name``, ``binding_class``, ``library``
    (Python package, what else it needs) and ``absolute``.
    """

    config = DeskConfig
    table = "desk"
    binding_class: ClassVar[type[Binding]]
    library: ClassVar[tuple[str, str]]
    absolute: ClassVar[bool] = False

    def __init__(self, cfg: DeskConfig, binding: Binding | None = None) -> None:
        cfg.validate()
        self.cfg = cfg
        self.rate = RateIntegrator(cfg)
        self.edges = ButtonEdges(cfg.clutch_mode)
        self.last: Reading | None = None
        self.binding: Binding = binding if binding is not None else self.binding_class(cfg)  # type: ignore[call-arg]

    def __enter__(self) -> DeskDevice:
        self.binding.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.binding.close()

    def read(self, t: float) -> DeviceSample:
        """Sample the device (``t``: s since capture started; staleness uses the reading's time)."""
        r = self.binding.read()
        if r is not None:
            self.last = r
        r = self.last
        now = time.monotonic()
        if r is None or (now - r.t) * 1e3 > self.cfg.stale_ms:
            self.edges.reset()
            return DeviceSample(self.rate.position, self.rate.orientation, False, True, valid=False)
        b = self.cfg.clutch_button
        clutch = self.edges.update(b < len(r.buttons) and r.buttons[b])
        if self.absolute and r.position is not None:
            pos = scaled_position(r.position, self.cfg)
            return DeviceSample(pos, r.orientation or (0.0, 0.0, 0.0, 1.0), clutch, True)
        self.rate.step(r.t, r.trans, r.rot)
        return DeviceSample(self.rate.position, self.rate.orientation, clutch, True)


class HapticDeskDevice(DeskDevice):
    """An absolute desk device that also renders a force (the touch, the omega7): the haptic
    loop's force (master frame) turned into the device's frame (``rotation_rpy_deg``ᵀ), its
    magnitude capped at the device's ``force_limit_n``; the force is zeroed before the device is
    closed. A subclass's binding is a :class:`ForceBinding`."""

    absolute = True
    force_limit_n: ClassVar[float]  # N: the device's peak force (its data sheet)

    def write_force(self, force: Sequence[float]) -> np.ndarray:
        """Command ``force`` (N, master frame); returns the force commanded (≤ the limit)."""
        f = np.asarray(force, dtype=float)
        if not np.all(np.isfinite(f)):
            f = np.zeros(3)
        n = float(np.linalg.norm(f))
        if n > self.force_limit_n:
            f = f * (self.force_limit_n / n)
        r = np.array(rpy_matrix(self.cfg.rotation_rpy_deg))
        dev = r.T @ f
        self.binding.write_force((float(dev[0]), float(dev[1]), float(dev[2])))  # type: ignore[attr-defined]
        return f

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            self.binding.write_force((0.0, 0.0, 0.0))  # type: ignore[attr-defined]
        finally:
            super().__exit__(exc_type, exc, tb)
