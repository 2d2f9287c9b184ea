"""The ``touch`` master device: Geomagic Touch / PHANTOM Omni (absolute) through ``pyopenhaptics``;
settings in ``[master_capture.desk]``.

Example: ``telesurg master-capture --set device=touch``.
"""

from __future__ import annotations

import time

from telesurg.services.master_capture.devices import register
from telesurg.services.master_capture.devices.desk import (
    DeskConfig,
    DeskDevice,
    Reading,
    need_library,
    quat_of_columns,
)


class TouchBinding:
    """Geomagic Touch / PHANTOM Omni through ``pyopenhaptics`` (OpenHaptics HD API): the stylus
    tip position (mm → m) and orientation from its transform, the two stylus buttons."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._dev: object | None = None
        self._hd: object | None = None

    def open(self) -> None:
        hd = need_library(TouchDevice, "pyOpenHaptics.hd")
        dev_mod = need_library(TouchDevice, "pyOpenHaptics.hd_device")
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
            orientation=quat_of_columns(m),
            buttons=(bool(b & 1), bool(b & 2)),
        )

    def close(self) -> None:
        if self._dev is not None:
            self._dev.close()  # type: ignore[attr-defined]


@register
class TouchDevice(DeskDevice):
    """Geomagic Touch / PHANTOM Omni (absolute) through ``pyopenhaptics``."""

    name = "touch"
    binding_class = TouchBinding
    library = ("pyopenhaptics", "the 3D Systems OpenHaptics SDK and Touch device drivers")
    absolute = True
