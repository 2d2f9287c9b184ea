"""Desk master devices: 3Dconnexion SpaceMouse, Geomagic Touch / PHANTOM Omni, Force Dimension
omega.7 and a gamepad, as ``master_capture`` device types (``device = "spacemouse"`` …).

Everything that does not need the device is here and tested (``tests/test_desk_devices.py``):

* :class:`RateIntegrator` — rate control (SpaceMouse, gamepad): each axis in [-1, 1] through a
  deadband (the rest rescaled to start at 0), times the top speed, integrated over the *reading's*
  time step (capped at ``max_dt_s``, so a stalled reader never makes a jump), kept inside the
  workspace box; rotation integrated as a quaternion (body-fixed increments);
* :class:`ButtonEdges` — the clutch from a button: ``hold`` (pressed while held) or ``toggle``
  (each press flips it), from the rising edges;
* staleness — a reading older than ``stale_ms`` (device time) makes the sample invalid, so
  master_capture publishes nothing and the watchdog holds;
* :func:`scaled_position` — absolute devices (Touch, omega.7): device position (m, in its own
  frame) → master frame, through ``rotation_rpy_deg`` and an optional offset.

The binding layer (:class:`SpaceMouseBinding` on ``pyspacemouse``, :class:`TouchBinding` on
``pyopenhaptics``, :class:`Omega7Binding` on ``forcedimension-core``, :class:`GamepadBinding` on
``pygame``) imports its library when the device is opened; without it the device fails to open
with a :class:`~telesurg.shared.errors.DeviceConnectionError` naming the package and the vendor
SDK it needs. **None of these bindings has been run against hardware** (docs/console.md).

``telesurg device check TYPE`` opens one and prints its readings (services/device).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Protocol

from telesurg.services.master_capture.devices import (
    DESK_DEVICES,
    DeviceSample,
    MasterDevice,
    ScriptedConfig,
    SerialMasterConfig,
    make_device,
)
from telesurg.shared.errors import ConfigError, DeviceConnectionError

#: device type → (Python package to pip install, what else it needs)
LIBRARIES = {
    "spacemouse": ("pyspacemouse", "hidapi (libhidapi) and read access to the HID device"),
    "touch": ("pyopenhaptics", "the 3D Systems OpenHaptics SDK and Touch device drivers"),
    "omega7": ("forcedimension-core", "the Force Dimension SDK (libdhd / libdrd)"),
    "gamepad": ("pygame", "SDL2 joystick support (read access to /dev/input)"),
}


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


def _need(kind: str, module: str) -> object:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        pkg, also = LIBRARIES[kind]
        raise DeviceConnectionError(
            f"{kind}: Python package {pkg!r} not installed ({exc}); it also needs {also}"
        ) from None


class SpaceMouseBinding:
    """3Dconnexion SpaceMouse through ``pyspacemouse`` (HID): six axes in [-1, 1], buttons."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._lib: object | None = None

    def open(self) -> None:
        lib = _need("spacemouse", "pyspacemouse")
        if not lib.open():  # type: ignore[attr-defined]
            raise DeviceConnectionError("spacemouse: no device found (is it plugged in? HID permissions?)")
        self._lib = lib

    def read(self) -> Reading | None:
        s = self._lib.read()  # type: ignore[union-attr]
        if s is None:
            return None
        return Reading(
            time.monotonic(),
            trans=(float(s.x), float(s.y), float(s.z)),
            rot=(float(s.pitch), float(s.roll), float(s.yaw)),
            buttons=tuple(bool(b) for b in s.buttons),
        )

    def close(self) -> None:
        if self._lib is not None:
            self._lib.close()  # type: ignore[attr-defined]


class GamepadBinding:
    """A gamepad through ``pygame``'s joystick module: left stick x/y, right stick y for depth."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._pad: object | None = None
        self._pg: object | None = None

    def open(self) -> None:
        pg = _need("gamepad", "pygame")
        pg.joystick.init()  # type: ignore[attr-defined]
        if pg.joystick.get_count() <= self.cfg.device_index:  # type: ignore[attr-defined]
            raise DeviceConnectionError(f"gamepad: no joystick number {self.cfg.device_index}")
        self._pad = pg.joystick.Joystick(self.cfg.device_index)  # type: ignore[attr-defined]
        self._pg = pg

    def read(self) -> Reading | None:
        pad, pg = self._pad, self._pg
        pg.event.pump()  # type: ignore[union-attr]
        ax = [pad.get_axis(i) for i in range(pad.get_numaxes())]  # type: ignore[union-attr]
        ax += [0.0] * (4 - len(ax))
        buttons = tuple(bool(pad.get_button(i)) for i in range(pad.get_numbuttons()))  # type: ignore[union-attr]
        return Reading(time.monotonic(), trans=(ax[0], -ax[1], -ax[3]), buttons=buttons)

    def close(self) -> None:
        if self._pg is not None:
            self._pg.joystick.quit()  # type: ignore[attr-defined]


class TouchBinding:
    """Geomagic Touch / PHANTOM Omni through ``pyopenhaptics`` (OpenHaptics HD API): the stylus
    tip position (mm → m) and orientation from its transform, the two stylus buttons."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._dev: object | None = None
        self._hd: object | None = None

    def open(self) -> None:
        hd = _need("touch", "pyOpenHaptics.hd")
        dev_mod = _need("touch", "pyOpenHaptics.hd_device")
        self._dev = dev_mod.HapticDevice(callback=lambda: None, scheduler_type="async")  # type: ignore[attr-defined]
        self._hd = hd

    def read(self) -> Reading | None:
        hd = self._hd
        m = hd.get_transform()  # type: ignore[union-attr]  # column-major 4×4, mm
        pos = (m[3][0] / 1e3, m[3][1] / 1e3, m[3][2] / 1e3)
        b = int(hd.get_buttons())  # type: ignore[union-attr]
        return Reading(
            time.monotonic(),
            position=pos,
            orientation=_quat_of_columns(m),
            buttons=(bool(b & 1), bool(b & 2)),
        )

    def close(self) -> None:
        if self._dev is not None:
            self._dev.close()  # type: ignore[attr-defined]


class Omega7Binding:
    """Force Dimension omega.7 through ``forcedimension-core`` (DHD API): position (m), the
    orientation frame, the gripper angle as the grasp axis, the user button."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._dhd: object | None = None

    def open(self) -> None:
        sdk = _need("omega7", "forcedimension_core")
        dhd = sdk.dhd  # type: ignore[attr-defined]
        if dhd.open() < 0:
            raise DeviceConnectionError(f"omega7: dhdOpen failed: {dhd.errorGetLastStr()}")
        self._dhd = dhd

    def read(self) -> Reading | None:
        dhd = self._dhd
        p = [0.0, 0.0, 0.0]
        if dhd.getPosition(out=p) < 0:  # type: ignore[union-attr]
            return None
        frame = [[0.0] * 3 for _ in range(3)]
        dhd.getOrientationFrame(out=frame)  # type: ignore[union-attr]
        angle = float(dhd.getGripperAngleRad())  # type: ignore[union-attr]
        cols = [[frame[r][c] for r in range(3)] for c in range(3)]
        return Reading(
            time.monotonic(),
            position=(p[0], p[1], p[2]),
            orientation=_quat_of_columns(cols),
            buttons=(bool(dhd.getButton(0)),),  # type: ignore[union-attr]
            grasp=max(0.0, min(1.0, 1.0 - angle / 0.52)),  # 0.52 rad ≈ the gripper's open angle
        )

    def close(self) -> None:
        if self._dhd is not None:
            self._dhd.close()  # type: ignore[attr-defined]


def _quat_of_columns(m: object) -> tuple[float, float, float, float]:
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


BINDINGS: dict[str, Callable[[DeskConfig], Binding]] = {
    "spacemouse": SpaceMouseBinding,
    "gamepad": GamepadBinding,
    "touch": TouchBinding,
    "omega7": Omega7Binding,
}


@dataclass
class DeskDevice:
    """A desk device as a :class:`~telesurg.services.master_capture.devices.MasterDevice`.

    Rate devices (spacemouse, gamepad) integrate their axes (:class:`RateIntegrator`); absolute
    ones (touch, omega7) map their pose (:func:`scaled_position`). The clutch comes from
    ``clutch_button`` (:class:`ButtonEdges`); a missing or stale reading makes the sample invalid
    and resets the clutch (a new press is needed).
    """

    kind: str
    cfg: DeskConfig
    binding: Binding | None = None  # None: the type's library binding (opened in __enter__)
    joint_names: tuple[str, ...] = ()
    rate: RateIntegrator = field(init=False)
    edges: ButtonEdges = field(init=False)
    last: Reading | None = None

    def __post_init__(self) -> None:
        if self.kind not in DESK_DEVICES:
            raise ConfigError(f"desk device {self.kind!r} unknown; valid: {', '.join(DESK_DEVICES)}")
        self.cfg.validate()
        self.rate = RateIntegrator(self.cfg)
        self.edges = ButtonEdges(self.cfg.clutch_mode)
        if self.binding is None:
            self.binding = BINDINGS[self.kind](self.cfg)

    @property
    def absolute(self) -> bool:
        """The device reports a pose (touch, omega7), not rates."""
        return self.kind in ("touch", "omega7")

    def __enter__(self) -> DeskDevice:
        assert self.binding is not None
        self.binding.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        assert self.binding is not None
        self.binding.close()

    def read(self, t: float) -> DeviceSample:
        """Sample the device (``t``: s since capture started; staleness uses the reading's time)."""
        assert self.binding is not None
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


def open_device(
    kind: str,
    scripted: ScriptedConfig | None = None,
    serial: SerialMasterConfig | None = None,
    desk: DeskConfig | None = None,
) -> MasterDevice:
    """Any master device type: a desk device here, the others from
    :func:`~telesurg.services.master_capture.devices.make_device` (the library of a desk device is
    imported when it is opened)."""
    if kind in DESK_DEVICES:
        return DeskDevice(kind, desk or DeskConfig())
    return make_device(kind, scripted, serial)
