"""The ``work`` jog frame is the laparoscope's view, distinct from ``base`` (issue #20)."""

from __future__ import annotations

import numpy as np
from telesurg.shared.kinematics.work_frame import CameraWorkFrame, ConfiguredWorkFrame
from telesurg.shared.robots.mh3f.kinematics import fk
from telesurg.shared.robots.mh3f.motion import jog_step

Q = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])


def tip_move(frame: str, axis: str, work: np.ndarray | None) -> np.ndarray:
    q = jog_step(Q, frame, axis, 1, 0.1, speed_m_s=0.01, joint_speed_rad_s=0.1, trocar=None, work=work)
    return (fk(q)[:3, 3] - fk(Q)[:3, 3]) * 1e3


def test_work_z_is_into_the_laparoscope_image_not_base_z() -> None:
    work = ConfiguredWorkFrame().rotation()
    assert np.allclose(tip_move("work", "z", work), [0.0, 0.0, -1.0], atol=1e-9)  # looking down
    assert np.allclose(tip_move("work", "x", work), [0.0, -1.0, 0.0], atol=1e-9)  # image right
    assert np.allclose(tip_move("base", "z", work), [0.0, 0.0, 1.0], atol=1e-9)


def test_camera_pose_replaces_the_configured_frame_while_fresh() -> None:
    cam = CameraWorkFrame(ConfiguredWorkFrame(), max_age_s=60.0)
    assert np.allclose(cam.rotation(), ConfiguredWorkFrame().rotation())
    s = np.sqrt(0.5)
    cam.on_pose((0.0, s, 0.0, s))  # optical axis (z) turned onto base +x
    assert np.allclose(tip_move("work", "z", cam.rotation()), [1.0, 0.0, 0.0], atol=1e-9)
    stale = CameraWorkFrame(ConfiguredWorkFrame(), max_age_s=0.0)
    stale.on_pose((0.0, s, 0.0, s))
    assert np.allclose(stale.rotation(), ConfiguredWorkFrame().rotation())
