"""The master frame of the mapping: fixed, or the work frame (the laparoscope's view, Jinno 2014).

``master_frame = "fixed"`` (default): the master frame's axes in the slave base frame are the
rotation ``master_to_slave_rpy_deg``. ``master_frame = "work"``: master motion is expressed in the
**work frame** — the laparoscope's view frame, as the slave's ``work`` jogs use it (x to the
image's right, y down the image, z into the image; ``work_frame_rpy_deg`` in the base frame, the
default a laparoscope looking straight down with the patient's head up in the image). The master
is held in front of the picture, so as for the camera frame
(:mod:`telesurg.shared.teleop.camera_frame`) the master's axes are the surgeon's view of that
frame: master +x = work +x (image right), master +y = work −y (image up), master +z = work −z
(toward the surgeon), i.e. ``R_ms = R_work · diag(1, −1, −1)``. Where the site has an endoscope
camera (``camera`` set), its published pose replaces the configured work frame as soon as it
arrives (the camera's optical frame *is* the laparoscope's view frame).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.kinematics.transforms import quat_from_matrix, rpy_matrix
from telesurg.shared.teleop.camera_frame import VIEW_TO_OPTICAL

if TYPE_CHECKING:
    from telesurg.shared.teleop.settings import MappingSettings

#: Valid ``master_frame`` values.
MASTER_FRAMES = ("fixed", "work")


def rotation_of(r_ms: np.ndarray) -> tuple[float, float, float, float]:
    """``R_ms`` as the teleop state's quaternion ``[x, y, z, w]``."""
    q = quat_from_matrix(r_ms)
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def master_rotation(cfg: MappingSettings) -> np.ndarray:
    """``(3, 3)`` the master frame's axes in the slave base frame (columns), before any camera pose."""
    if cfg.master_frame == "work":
        out: np.ndarray = rpy_matrix(cfg.work_frame_rpy_deg) @ VIEW_TO_OPTICAL
        return out
    return rpy_matrix(cfg.master_to_slave_rpy_deg)
