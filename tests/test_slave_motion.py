"""Slave-side motion sources (telesurg.shared.robots.mh3f.motion): PTP and jog, pure kinematics."""

from __future__ import annotations

import numpy as np
import pytest
from telesurg.shared.errors import IKError
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
from telesurg.shared.robots.mh3f.motion import PtpMotion, jog_step, ptp_duration
from telesurg.shared.robots.mh3f.trocar import forceps_roll, posture_adjust, rcm_error, trocar_ik

TROCAR = np.array([0.5, 0.0, 0.2])
Q0 = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])


def test_ptp_is_synchronous_and_ends_exactly() -> None:
    q_to = posture_adjust(Q0, TROCAR)
    m = PtpMotion(Q0.copy(), q_to, ptp_duration(Q0, q_to, 0.2))
    halfway = None
    while not m.done:
        q = m.next(0.001)
        if halfway is None and m.elapsed_s >= m.duration_s / 2:
            halfway = q
    np.testing.assert_allclose(q, q_to, atol=1e-12)
    assert halfway is not None
    delta = q_to - Q0
    moving = np.abs(delta) > 1e-6
    assert moving[4] and not moving[:3].any()
    moved = (halfway - Q0)[moving] / delta[moving]  # every moving joint half-way at the same time
    np.testing.assert_allclose(moved, 0.5, atol=2e-3)
    np.testing.assert_allclose(q[:3], Q0[:3], atol=0)  # J1–J3 untouched


def test_cartesian_jog_moves_the_tip_at_the_jog_speed() -> None:
    q = Q0.copy()
    p0 = fk(q, MH3F)[:3, 3]
    for _ in range(100):
        q = jog_step(q, "base", "z", -1, 0.001, speed_m_s=0.02, joint_speed_rad_s=0.1, trocar=None)
    p1 = fk(q, MH3F)[:3, 3]
    np.testing.assert_allclose(p1 - p0, [0.0, 0.0, -0.002], atol=1e-9)  # 20 mm/s for 0.1 s
    np.testing.assert_allclose(fk(q, MH3F)[:3, :3], fk(Q0, MH3F)[:3, :3], atol=1e-9)  # no rotation


def test_jog_in_trocar_mode_pivots_about_the_trocar() -> None:
    qa = posture_adjust(Q0, TROCAR)
    d = fk(qa, MH3F)[:3, 0]
    q = trocar_ik(TROCAR + 0.06 * d, TROCAR, qa)
    for _ in range(300):  # 15 mm sideways: the forceps tilts about the trocar
        q = jog_step(q, "base", "y", 1, 0.001, speed_m_s=0.05, joint_speed_rad_s=0.1, trocar=TROCAR)
        assert rcm_error(q, TROCAR) < 1e-9


def test_joint_jog_and_unsupported_axes() -> None:
    q = jog_step(Q0, "joint", "j6", -1, 0.5, speed_m_s=0.01, joint_speed_rad_s=0.2, trocar=None)
    np.testing.assert_allclose(q - Q0, [0, 0, 0, 0, 0, -0.1], atol=1e-15)
    with pytest.raises(IKError, match="jog about q7 is not implemented"):
        jog_step(Q0, "forceps", "q7", 1, 0.001, speed_m_s=0.01, joint_speed_rad_s=0.1, trocar=None)


def test_rotation_jogs_turn_about_the_tip() -> None:
    T0 = fk(Q0, MH3F)
    for frame, axis in (("base", "rz"), ("forceps", "ry"), ("world", "rx")):
        q = Q0.copy()
        for _ in range(100):  # 0.1 rad/s for 0.1 s: 0.01 rad
            q = jog_step(q, frame, axis, 1, 0.001, speed_m_s=0.01, joint_speed_rad_s=0.1, trocar=None)
        T = fk(q, MH3F)
        np.testing.assert_allclose(T[:3, 3], T0[:3, 3], atol=1e-9)  # the tip stays put
        d_rot = T[:3, :3] @ T0[:3, :3].T
        angle = np.arccos(np.clip((np.trace(d_rot) - 1) / 2, -1, 1))
        assert abs(angle - 0.01) < 1e-9


def test_trocar_mode_rotation_is_the_roll_only() -> None:
    qa = posture_adjust(Q0, TROCAR)
    d = fk(qa, MH3F)[:3, 0]
    q0 = trocar_ik(TROCAR + 0.06 * d, TROCAR, qa)
    q = q0.copy()
    for _ in range(100):
        q = jog_step(q, "forceps", "rx", 1, 0.001, speed_m_s=0.01, joint_speed_rad_s=0.1, trocar=TROCAR)
    np.testing.assert_allclose(fk(q, MH3F)[:3, 3], fk(q0, MH3F)[:3, 3], atol=1e-9)
    assert rcm_error(q, TROCAR) < 1e-9
    assert abs(forceps_roll(q, MH3F) - forceps_roll(q0, MH3F) - 0.01) < 1e-9
    with pytest.raises(IKError, match="only rotation is the roll"):
        jog_step(q, "base", "rz", 1, 0.001, speed_m_s=0.01, joint_speed_rad_s=0.1, trocar=TROCAR)
