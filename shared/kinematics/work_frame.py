"""The ``work`` jog frame (Jinno 2014): the laparoscope's view frame, distinct from ``base``/``world``.

A jog in ``work`` moves the tip along the axes the surgeon sees on the laparoscope image: x to the
image's right, y down the image, z into the image (the camera's optical axis), the usual camera
convention. Where the frame comes from is a seam (:class:`WorkFrame`):

* :class:`ConfiguredWorkFrame` — a fixed rotation from the site config
  (``work_frame_rpy_deg``, base frame); the default is a laparoscope looking straight down on
  the patient with the patient's head (+x) up in the image.
* :class:`CameraWorkFrame` — follows a camera pose (e.g. the endoscope camera's
  ``camera/<cam>/measured_cp`` stream of the video service) fed to :meth:`CameraWorkFrame.on_pose`;
  until a first pose arrives, and whenever the last one is older than ``max_age_s``, it falls back
  to the configured frame.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

import numpy as np
from telesurg.shared.kinematics import matrix_from_quat
from telesurg.shared.kinematics.transforms import rpy_matrix

#: roll, pitch, yaw [deg] of a laparoscope looking down (-z) with the patient's head (+x) up.
LAPAROSCOPE_DOWN_RPY_DEG = (180.0, 0.0, -90.0)


class WorkFrame(Protocol):
    """Source of the work frame's rotation in the arm's base frame."""

    def rotation(self) -> np.ndarray:
        """Columns: the work frame's x, y, z axes in the base frame, ``(3, 3)``."""
        ...


class ConfiguredWorkFrame:
    """A fixed work frame from ``roll, pitch, yaw`` [deg] (``R = Rz Ry Rx``, base frame)."""

    def __init__(self, rpy_deg: tuple[float, float, float] = LAPAROSCOPE_DOWN_RPY_DEG) -> None:
        self._r = rpy_matrix(rpy_deg)

    def rotation(self) -> np.ndarray:
        return self._r


class CameraWorkFrame:
    """The work frame of a camera whose pose (base frame, quaternion x, y, z, w) is fed in."""

    def __init__(self, fallback: WorkFrame, max_age_s: float = 0.5) -> None:
        self.fallback, self.max_age_s = fallback, max_age_s
        self._lock = threading.Lock()
        self._r: np.ndarray | None = None
        self._t = 0.0

    def on_pose(self, orientation: tuple[float, float, float, float]) -> None:
        """A new camera orientation (from the camera pose stream's callback)."""
        r = matrix_from_quat(np.array(orientation, dtype=np.float64))
        with self._lock:
            self._r, self._t = r, time.monotonic()

    def rotation(self) -> np.ndarray:
        with self._lock:
            if self._r is not None and time.monotonic() - self._t <= self.max_age_s:
                return self._r
        return self.fallback.rotation()
