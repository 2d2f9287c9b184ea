"""The ``spacemouse`` master device: 3Dconnexion SpaceMouse (rate control) through ``pyspacemouse``;
settings in ``[master_capture.desk]``.

Example: ``telesurg master-capture --set device=spacemouse``.
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


class SpaceMouseBinding:
    """3Dconnexion SpaceMouse through ``pyspacemouse`` (HID): six axes in [-1, 1], buttons."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._lib: object | None = None

    def open(self) -> None:
        lib = need_library(SpaceMouseDevice, "pyspacemouse")
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


@register
class SpaceMouseDevice(DeskDevice):
    """3Dconnexion SpaceMouse (rate control) through ``pyspacemouse``."""

    name = "spacemouse"
    binding_class = SpaceMouseBinding
    library = ("pyspacemouse", "hidapi (libhidapi) and read access to the HID device")
    absolute = False
