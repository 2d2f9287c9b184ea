"""The ``omega7`` master device: Force Dimension omega.7 (absolute) through ``forcedimension-core``;
settings in ``[master_capture.desk]``.

Example: ``telesurg master-capture --set device=omega7``.
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
from telesurg.shared.errors import DeviceConnectionError


class Omega7Binding:
    """Force Dimension omega.7 through ``forcedimension-core`` (DHD API): position (m), the
    orientation frame, the gripper angle as the grasp axis, the user button; the force on x y z
    (N, device frame; no torque, no gripper force: nothing on the bus measures a grasp yet)."""

    def __init__(self, cfg: DeskConfig) -> None:
        self.cfg = cfg
        self._dhd: object | None = None

    def open(self) -> None:
        sdk = need_library(Omega7Device, "forcedimension_core")
        dhd = sdk.dhd  # type: ignore[attr-defined]
        if dhd.open() < 0:
            raise DeviceConnectionError(f"omega7: dhdOpen failed: {dhd.errorGetLastStr()}")
        dhd.enableForce(True)
        self._dhd = dhd

    def write_force(self, force: tuple[float, float, float]) -> None:
        dhd = self._dhd
        if dhd is not None:
            dhd.setForceAndTorqueAndGripperForce(list(force), [0.0, 0.0, 0.0], 0.0)  # type: ignore[attr-defined]

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
            orientation=quat_of_columns(cols),
            buttons=(bool(dhd.getButton(0)),),  # type: ignore[union-attr]
            grasp=max(0.0, min(1.0, 1.0 - angle / 0.52)),  # 0.52 rad ≈ the gripper's open angle
        )

    def close(self) -> None:
        if self._dhd is not None:
            self._dhd.close()  # type: ignore[attr-defined]


@register
class Omega7Device(HapticDeskDevice):
    """Force Dimension omega.7 (absolute, force on x y z) through ``forcedimension-core``."""

    name = "omega7"
    binding_class = Omega7Binding
    library = ("forcedimension-core", "the Force Dimension SDK (libdhd / libdrd)")
    force_limit_n = 12.0  # N: the omega.7's continuous translational force (data sheet)
