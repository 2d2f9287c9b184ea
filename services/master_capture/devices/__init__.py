"""Master devices: one registered class per device, one file each, chosen by master_capture's
``device`` key.

A device subclasses :class:`MasterDevice`, names itself (``name``), says where its settings are
(``config``: a dataclass; ``table``: the master_capture config table holding them, by default the
free-form ``[master_capture.device_options]``) and is registered with :func:`register`. A plugin
file (``--plugin FILE``) registers its own the same way. ``docs/extending.md``, "Add a master
device". A device that reads the bus (the ``policy`` device: the slave's measurements) has a
``connect(node)`` method; master_capture calls it with its node once the node is open.

Example::

    @register
    class Still(MasterDevice):
        name = "still"
        config = StillConfig  # settings from [master_capture.device_options]

        def __init__(self, cfg: StillConfig) -> None:
            self.cfg = cfg

        def read(self, t: float) -> DeviceSample:
            return DeviceSample(self.cfg.position, (0.0, 0.0, 0.0, 1.0), True, True)
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import TracebackType
from typing import Any, ClassVar, TypeVar

from telesurg.shared.config import from_dict
from telesurg.shared.errors import ConfigError


@dataclass(frozen=True)
class DeviceSample:
    """One master reading.

    Attributes:
        position: tip position in the master frame, m, shape (3,).
        orientation: unit quaternion (x, y, z, w) in the master frame.
        clutch: clutch pedal pressed.
        operator_present: operator detected at the console.
        joints: master joint positions (rad / m) if the device has joints, else empty.
        valid: the reading is fresh. False while a device is unplugged, silent for longer than
            its staleness limit or refused; the other fields then hold the last reading (or
            zeros) and must not be published.
        joint1_switch: the all-joints master's joint-1 (shoulder slide) switch is pressed;
            False on devices without one.
        grip: the gripper, 0 open … 1 closed (an omega.7's grip; 0 on devices without one).
    """

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    clutch: bool
    operator_present: bool
    joints: tuple[float, ...] = ()
    valid: bool = True
    joint1_switch: bool = False
    grip: float = 0.0


class MasterDevice:
    """What master_capture needs from a device: open (``with``), :meth:`read`, close.

    Class attributes: ``name`` (the ``device`` value), ``config`` (its settings dataclass, built
    from the master_capture table ``table``), ``joint_names`` (``measured_js`` names; empty: no
    joints published). The constructor takes one ``config`` instance.
    """

    name: ClassVar[str]
    config: ClassVar[type[Any]]
    table: ClassVar[str] = "device_options"
    joint_names: tuple[str, ...] = ()

    def read(self, t: float) -> DeviceSample:
        """Sample the device; ``t`` is seconds since capture started."""
        raise NotImplementedError

    def __enter__(self) -> MasterDevice:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        return None


D = TypeVar("D", bound=type[MasterDevice])
_DEVICES: dict[str, type[MasterDevice]] = {}


def register(cls: D) -> D:
    """Register a device class under ``cls.name`` (a class decorator); a second class with the
    same name is an error."""
    name = getattr(cls, "name", "")
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f"master device class {cls.__name__}: name {name!r} must be an identifier")
    if not isinstance(getattr(cls, "config", None), type):
        raise ConfigError(f"master device {name!r}: config must be its settings dataclass")
    old = _DEVICES.get(name)
    if old is not None and old is not cls:
        raise ConfigError(f"master device {name!r} already registered by {old.__module__}.{old.__name__}")
    _DEVICES[name] = cls
    return cls


def names() -> tuple[str, ...]:
    """The registered device names: the built-in ones, then the plugins' in registration order."""
    return tuple(_DEVICES)


def get(name: str) -> type[MasterDevice]:
    """The device class registered as ``name``; ConfigError listing the known names if none."""
    try:
        return _DEVICES[name]
    except KeyError:
        raise ConfigError(
            f"master device {name!r} unknown; valid: {', '.join(names())} (more from --plugin FILE)"
        ) from None


def device_config(name: str, settings: object | None = None) -> Any:
    """The settings of device ``name`` from ``settings`` (a master_capture config: its
    ``table`` attribute; a dict there is type-checked into the device's ``config``), or the
    device's defaults when ``settings`` is None."""
    cls = get(name)
    if settings is None:
        return cls.config()
    value = getattr(settings, cls.table, None)
    if isinstance(value, dict):
        return from_dict(cls.config, value, cls.table)
    if not isinstance(value, cls.config):
        raise ConfigError(f"master device {name!r}: no {cls.table!r} settings of type {cls.config.__name__}")
    return value


def open_device(name: str, settings: object | None = None) -> MasterDevice:
    """Make (not yet open) device ``name`` from its settings (see :func:`device_config`)."""
    return get(name)(device_config(name, settings))  # type: ignore[call-arg]


#: the built-in devices, one module each (importing one registers it), in the order names() lists them
BUILT_IN = ("scripted", "serial", "spacemouse", "touch", "omega7", "gamepad", "policy", "touch_sim")
for _module in BUILT_IN:
    importlib.import_module(f"{__name__}.{_module}")
