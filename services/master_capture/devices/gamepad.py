"""The ``gamepad`` master device: a gamepad (rate control) through ``pygame``;
settings in ``[master_capture.desk]``.

Example: ``telesurg master-capture --set device=gamepad``.
"""

from __future__ import annotations

import time

from telesurg.services.master_capture.devices import register
from telesurg.services.master_capture.devices.desk import (
    DeskConfig,
    DeskDevice,
    Reading,
    need_library,
)
from telesurg.shared.errors import DeviceConnectionError


class GamepadBinding:
    """A gamepad through ``pygame``'s joystick module: left stick x/y, right stick y for depth."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._pad: object | None = None
        self._pg: object | None = None

    def open(self) -> None:
        pg = need_library(GamepadDevice, "pygame")
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


@register
class GamepadDevice(DeskDevice):
    """A gamepad (rate control) through ``pygame``."""

    name = "gamepad"
    binding_class = GamepadBinding
    library = ("pygame", "SDL2 joystick support (read access to /dev/input)")
    absolute = False
