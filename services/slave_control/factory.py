"""Slave backends by their registered name (``backend = "mujoco"`` or ``"serial"``).

The chooser lives apart from the backends: :mod:`~telesurg.services.slave_control.serial_backend`
builds on :mod:`~telesurg.services.slave_control.backends` (the reading types, the MuJoCo shadow),
and neither imports this module, so there is no import loop. Each backend's heavy imports
(mujoco, pyserial) happen when it is made.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from telesurg.services.slave_control.backends import MujocoBackend, SlaveBackend
from telesurg.shared.errors import ConfigError

if TYPE_CHECKING:
    from telesurg.services.slave_control import SlaveControlConfig

#: Registered backend names.
BACKENDS = ("mujoco", "serial")


def make_backend(
    kind: str,
    model: str,
    q_home: tuple[float, ...],
    sites: tuple[str, ...] = (),
    cfg: SlaveControlConfig | None = None,
    home: tuple[float, ...] = (),
) -> SlaveBackend:
    """The backend registered as ``kind``; ``serial`` takes its ``serial_*`` and ``shadow*`` keys
    from ``cfg`` (the slave_control config). ``home``: the start pose of a MuJoCo model without a
    ``home`` keyframe when ``q_home`` is empty."""
    if cfg is not None and cfg.shadow and kind != "serial":
        raise ConfigError(f'shadow = true needs backend = "serial" (backend is {kind!r})')
    if kind == "mujoco":
        return MujocoBackend(model, q_home, sites, home, scene=cfg.scene if cfg is not None else "")
    if kind == "serial":
        if cfg is None:
            raise ConfigError("the serial backend needs the slave_control config (serial.port, ...)")
        from telesurg.services.slave_control.serial_backend import make_serial_backend

        return make_serial_backend(cfg)
    raise ConfigError(f"slave backend {kind!r} unknown; valid: {', '.join(BACKENDS)}")
