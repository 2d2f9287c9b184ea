"""Teleoperation in the camera frame: the rotation from the surgeon's view to the slave base.

The master frame of a camera-frame mapping is the view the surgeon looks at (dVRK: the stereo
viewer): x to the right of the picture, y up, z toward the surgeon. The camera publishes its
optical frame (OpenCV: x right, y down, z into the scene) in the slave base frame, so

``R_ms = R_base_optical · diag(1, −1, −1)``

maps a master increment into the base frame: a hand motion to the right moves the tip to the
right in the image whatever the endoscope's pose.
"""

from __future__ import annotations

import numpy as np
from telesurg.shared.kinematics import matrix_from_quat
from telesurg.shared.messages import CartesianPose

#: Surgeon's view frame (x right, y up, z toward the viewer) → the camera's optical frame.
VIEW_TO_OPTICAL = np.diag([1.0, -1.0, -1.0])


def view_rotation(camera_pose: CartesianPose) -> np.ndarray:
    """``(3, 3)`` rotation of the surgeon's view frame in the slave base frame."""
    r_base_optical = matrix_from_quat(np.array(camera_pose.orientation))
    out: np.ndarray = r_base_optical @ VIEW_TO_OPTICAL
    return out


def project(
    point: tuple[float, float, float] | np.ndarray,
    camera_pose: CartesianPose,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    baseline_m: float = 0.0,
) -> tuple[float, float] | None:
    """Pixel ``(u, v)`` of a base-frame point in the picture of the camera at ``camera_pose``
    (its optical frame, pinhole intrinsics of :class:`~telesurg.shared.messages.CameraImage`);
    ``baseline_m``: the right eye of a stereo pair, that far along the optical x (its pixel in that
    eye's own image). None when the point is not in front of the camera."""
    R = matrix_from_quat(np.array(camera_pose.orientation))
    p = R.T @ (np.asarray(point, dtype=float) - np.array(camera_pose.position))
    p[0] -= baseline_m
    if p[2] <= 1e-6:
        return None
    return float(fx * p[0] / p[2] + cx), float(fy * p[1] / p[2] + cy)
