"""The ``touch`` master device: Geomagic Touch / PHANTOM Omni (absolute) through ``pyopenhaptics``;
settings in ``[master_capture.desk]``.

Example: ``telesurg master-capture --set device=touch``.
"""

from __future__ import annotations

import time

from telesurg.services.master_capture.devices import register
from telesurg.services.master_capture.devices.desk import (
    DeskConfig,
    HapticDeskDevice,
    Reading,
    need_library,
    quat_of_columns,
)


class TouchBinding:
    """Geomagic Touch / PHANTOM Omni through ``pyopenhaptics`` (OpenHaptics HD API): the stylus
    tip position (mm → m) and orientation from its transform, the two stylus buttons; the force
    (N, device frame) set in the HD servo loop's callback (1 kHz, inside its frame)."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._dev: object | None = None
        self._hd: object | None = None
        self._force = [0.0, 0.0, 0.0]  # the force the servo callback sets, N, device frame

    def open(self) -> None:
        hd = need_library(TouchDevice, "pyOpenHaptics.hd")
        dev_mod = need_library(TouchDevice, "pyOpenHaptics.hd_device")
        cb_mod = need_library(TouchDevice, "pyOpenHaptics.hd_callback")
        force = self._force

        @cb_mod.hd_callback  # type: ignore[attr-defined,untyped-decorator]
        def servo() -> None:
            hd.set_force(list(force))  # type: ignore[attr-defined]

        self._dev = dev_mod.HapticDevice(callback=servo, scheduler_type="async")  # type: ignore[attr-defined]
        self._hd = hd

    def write_force(self, force: tuple[float, float, float]) -> None:
        self._force[:] = force  # (one list, swapped in place: the callback reads it whole)

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
class TouchDevice(HapticDeskDevice):
    """Geomagic Touch / PHANTOM Omni (absolute, force on x y z) through ``pyopenhaptics``."""

    name = "touch"
    binding_class = TouchBinding
    library = ("pyopenhaptics", "the 3D Systems OpenHaptics SDK and Touch device drivers")
    force_limit_n = 3.3  # N: the Touch's peak force (data sheet; the Omni's: 3.3 N)
