"""Tests for telesurg.shared.kinematics: SO(3)/SE(3) helpers and the MH3F forward/inverse kinematics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics import (
    FloatArray,
    make_transform,
    matrix_from_quat,
    matrix_from_rotvec,
    quat_from_matrix,
    quat_normalize,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle_between,
    rotvec_from_matrix,
)
from telesurg.shared.robots.mh3f.kinematics import (
    MH3F,
    MH3F_NO_TOOL,
    ArmGeometry,
    fk,
    fk_frames,
    ik,
    ik_all,
    jacobian,
    within_limits,
    wrist_center,
)

TOL = 1e-9


def _pose_error(T1: FloatArray, T2: FloatArray) -> tuple[float, float]:
    """(position error [m], rotation error [rad]) between two poses."""
    dp = float(np.linalg.norm(T1[:3, 3] - T2[:3, 3]))
    return dp, rotation_angle_between(T1[:3, :3], T2[:3, :3])


def _random_regular_q(rng: np.random.Generator, n: int) -> list[FloatArray]:
    """Random joint vectors within limits, away from the wrist, shoulder and elbow singularities."""
    geom = MH3F
    out: list[FloatArray] = []
    while len(out) < n:
        q = rng.uniform(geom.lower_limits, geom.upper_limits)
        if abs(q[4]) < 0.05:
            continue  # wrist singularity (q5 = 0): q4 + q6 only
        W = wrist_center(q)
        if math.hypot(W[0], W[1]) < 0.02:
            continue  # shoulder singularity: wrist centre on the J1 axis
        if abs(math.cos(q[2] + geom.upper_arm_angle)) < 0.05:
            continue  # elbow stretched / folded: the two elbow branches merge
        out.append(q)
    return out


def _chain_product(q: FloatArray, geom: ArmGeometry) -> FloatArray:
    """The FK definition from the spec, written out as a product of 4x4 transforms."""

    def rot(R: FloatArray) -> FloatArray:
        return make_transform(R, np.zeros(3))

    def trans(x: float, y: float, z: float) -> FloatArray:
        return make_transform(np.eye(3), [x, y, z])

    q1, q2, q3, q4, q5, q6 = q
    return (
        rot(rot_z(q1))
        @ trans(0, 0, geom.d1)
        @ rot(rot_y(q2))
        @ trans(0, 0, geom.a2)
        @ rot(rot_y(-q3))
        @ trans(0, 0, geom.a3)
        @ rot(rot_x(q4))
        @ trans(geom.d4, 0, 0)
        @ rot(rot_y(-q5))
        @ rot(rot_x(q6))
        @ trans(geom.d6 + geom.tool, 0, 0)
    )


# ---------------------------------------------------------------------------- transforms


def test_elementary_rotations_are_right_handed() -> None:
    a = math.pi / 2
    np.testing.assert_allclose(rot_x(a) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot_y(a) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(rot_z(a) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_quat_order_is_xyzw() -> None:
    s = math.sqrt(0.5)
    np.testing.assert_allclose(quat_from_matrix(np.eye(3)), [0, 0, 0, 1])
    np.testing.assert_allclose(quat_from_matrix(rot_z(math.pi / 2)), [0, 0, s, s], atol=1e-15)
    np.testing.assert_allclose(quat_from_matrix(rot_x(math.pi)), [1, 0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(matrix_from_quat([0, s, 0, s]), rot_y(math.pi / 2), atol=1e-15)


def test_quat_round_trips() -> None:
    rng = np.random.default_rng(1)
    quats = [quat_normalize(rng.normal(size=4)) for _ in range(500)]
    # Near-180° rotations exercise every Shepperd branch.
    quats += [quat_normalize([*axis, w]) for axis in np.eye(3) for w in (0.0, 1e-9, -1e-9)]
    for q in quats:
        canonical = q if q[3] >= 0 else -q
        back = quat_from_matrix(matrix_from_quat(q))
        assert back[3] >= 0
        assert min(np.abs(back - canonical).max(), np.abs(back + canonical).max()) < 1e-12
        R = matrix_from_quat(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
        assert rotation_angle_between(matrix_from_quat(back), R) < 1e-12


def test_quat_normalize_rejects_zero_and_bad_shape() -> None:
    np.testing.assert_allclose(quat_normalize([0, 0, 0, 2]), [0, 0, 0, 1])
    with pytest.raises(KinematicsError, match="zero"):
        quat_normalize([0, 0, 0, 0])
    with pytest.raises(KinematicsError, match="shape"):
        quat_from_matrix(np.eye(4))


def test_rotvec_log_exp_and_small_angles() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.0, math.pi)
        v = angle * axis
        np.testing.assert_allclose(rotvec_from_matrix(matrix_from_rotvec(v)), v, atol=1e-12)
    assert rotation_angle_between(np.eye(3), rot_x(1e-10)) == pytest.approx(1e-10, rel=1e-6)
    assert rotation_angle_between(np.eye(3), rot_y(math.pi)) == pytest.approx(math.pi)
    np.testing.assert_allclose(rotvec_from_matrix(rot_z(1e-13)), [0, 0, 1e-13], atol=1e-25)


# ---------------------------------------------------------------------------- geometry / FK


def test_geometry_constants() -> None:
    assert MH3F.d1 + MH3F.reach == pytest.approx(0.804, abs=1e-3)  # vertical reach 804 mm
    assert MH3F.reach == pytest.approx(0.532, abs=1e-3)
    assert MH3F.wrist_to_tcp == pytest.approx(0.590)
    np.testing.assert_allclose(np.degrees(MH3F.lower_limits), [-160, -85, -105, -170, -120, -360], atol=1e-12)
    np.testing.assert_allclose(np.degrees(MH3F.upper_limits), [160, 90, 260, 170, 120, 360])
    np.testing.assert_allclose(MH3F.velocity_limits, [3.49, 2.62, 3.32, 5.24, 5.24, 7.33])
    assert MH3F_NO_TOOL.tool == 0.0
    with pytest.raises(KinematicsError):
        ArmGeometry(lower=(0.0,) * 5)
    with pytest.raises(KinematicsError):
        ArmGeometry(d4=-1.0)


def test_fk_at_zero() -> None:
    T = fk(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [0.860, 0.0, 0.562], atol=1e-15)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-15)
    expected = np.array(
        [
            [0, 0, 0],
            [0, 0, 0.272],
            [0, 0, 0.532],
            [0, 0, 0.562],
            [0.270, 0, 0.562],
            [0.360, 0, 0.562],
            [0.860, 0, 0.562],
        ]
    )
    np.testing.assert_allclose(fk_frames(np.zeros(6)), expected, atol=1e-15)
    np.testing.assert_allclose(fk(np.zeros(6), MH3F_NO_TOOL)[:3, 3], [0.36, 0, 0.562])


def test_fk_matches_spec_product_and_frames() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        q = rng.uniform(MH3F.lower_limits, MH3F.upper_limits)
        T = fk(q)
        np.testing.assert_allclose(T, _chain_product(q, MH3F), atol=1e-14)
        frames = fk_frames(q)
        np.testing.assert_allclose(frames[-1], T[:3, 3], atol=1e-14)
        np.testing.assert_allclose(frames[4], wrist_center(q), atol=1e-14)
        np.testing.assert_allclose(frames[4] + 0.590 * T[:3, 0], T[:3, 3], atol=1e-14)
        lengths = np.linalg.norm(np.diff(frames, axis=0), axis=1)
        np.testing.assert_allclose(lengths, [0.272, 0.260, 0.030, 0.270, 0.090, 0.500])


def test_joint_directions() -> None:
    d = 0.3
    # J1 positive turns the arm toward +y.
    assert fk([d, 0, 0, 0, 0, 0])[1, 3] > 0
    # J2 positive tilts the lower arm toward +x.
    assert fk_frames([0, d, 0, 0, 0, 0])[2, 0] > 0
    # J3 positive raises the upper arm.
    assert wrist_center([0, 0, d, 0, 0, 0])[2] > wrist_center(np.zeros(6))[2]
    # J5 positive pitches the flange up.
    T = fk([0, 0, 0, 0, d, 0])
    assert T[2, 0] > 0 and T[2, 3] > 0.562


def test_bad_joint_vector_rejected() -> None:
    with pytest.raises(KinematicsError, match="shape"):
        fk(np.zeros(5))
    with pytest.raises(KinematicsError, match="finite"):
        fk([0, 0, math.nan, 0, 0, 0])


def test_within_limits() -> None:
    assert within_limits(np.zeros(6))
    assert not within_limits(np.radians([0, 0, 0, 0, 121, 0]))
    assert within_limits(np.radians([0, 0, 260, 0, 0, 360]))


# ---------------------------------------------------------------------------- Jacobian


def test_jacobian_matches_numerical_derivative() -> None:
    rng = np.random.default_rng(4)
    h = 1e-6
    for _ in range(30):
        q = rng.uniform(MH3F.lower_limits, MH3F.upper_limits)
        J = jacobian(q)
        J_num = np.empty((6, 6))
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = h
            Tp, Tm = fk(q + dq), fk(q - dq)
            J_num[:3, i] = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
            # R(q+h) R(q-h)ᵀ = exp(2h [ω]) with ω in the base frame.
            J_num[3:, i] = rotvec_from_matrix(Tp[:3, :3] @ Tm[:3, :3].T) / (2 * h)
        np.testing.assert_allclose(J, J_num, atol=1e-6)


def test_jacobian_at_zero() -> None:
    J = jacobian(np.zeros(6))
    # J1 about +z at 0.86 m forward: tip moves +y at 0.86 m/s per rad/s.
    np.testing.assert_allclose(J[:, 0], [0, 0.86, 0, 0, 0, 1], atol=1e-15)
    # J6 rolls about the tool axis, which passes through the tip: pure rotation about +x.
    np.testing.assert_allclose(J[:, 5], [0, 0, 0, 1, 0, 0], atol=1e-15)


# ---------------------------------------------------------------------------- IK


def test_ik_round_trip_all_branches() -> None:
    rng = np.random.default_rng(5)
    counts = []
    for q in _random_regular_q(rng, 250):
        T = fk(q)
        sols = ik_all(T)
        counts.append(len(sols))
        assert sols, f"no IK solution for fk({q.tolist()})"
        for s in sols:
            assert within_limits(s)
            dp, dr = _pose_error(fk(s), T)
            assert dp <= TOL and dr <= TOL, (q.tolist(), s.tolist(), dp, dr)
        assert min(float(np.abs(s - q).max()) for s in sols) < TOL
        # Distinct solutions only.
        for i, a in enumerate(sols):
            for b in sols[i + 1 :]:
                assert np.abs(a - b).max() > 1e-9
        # The nearest solution to q is q itself.
        np.testing.assert_allclose(ik(T, q), q, atol=TOL, rtol=0)
    # Several branches exist in general (J1 front/back x elbow x wrist flip, plus J3/J6 wraps).
    assert max(counts) >= 8


def test_ik_all_finds_multiple_wraps_of_j6() -> None:
    q = np.radians([20, 10, 30, 40, 50, 100])
    sols = ik_all(fk(q))
    j6 = sorted(round(math.degrees(s[5]), 6) for s in sols if np.allclose(s[:5], q[:5]))
    assert j6 == [-260.0, 100.0]


def test_ik_all_finds_j3_wrap() -> None:
    q = np.radians([0, 20, 255, 10, 40, 0])  # J3 = 255° is the same as -105°: both are in range
    sols = ik_all(fk(q))
    j3 = {round(math.degrees(s[2]), 6) for s in sols if np.allclose(s[[0, 1, 3, 4, 5]], q[[0, 1, 3, 4, 5]])}
    assert j3 == {255.0, -105.0}


def test_ik_singular_wrist_keeps_current_q4() -> None:
    q = np.array([0.3, 0.2, 0.4, 0.0, 0.0, 0.5])  # q5 = 0: only q4 + q6 matters
    T = fk(q)
    q_cur = np.array([0.3, 0.2, 0.4, 0.7, 0.0, 0.0])
    sol = ik(T, q_cur)
    assert sol[3] == pytest.approx(0.7)
    assert sol[3] + sol[5] == pytest.approx(0.5)
    dp, dr = _pose_error(fk(sol), T)
    assert dp <= TOL and dr <= TOL


def test_ik_shoulder_singularity() -> None:
    # Upper arm tilted so the wrist centre lies on the J1 axis: q1 is free.
    q3 = math.atan2(MH3F.d4, MH3F.a3)
    q = np.array([0.0, 0.0, q3, 0.3, 0.6, 0.2])
    assert np.linalg.norm(wrist_center(q)[:2]) < 1e-12
    T = fk(q)
    q_cur = np.array([0.4, 0.0, q3, 0.0, 0.5, 0.0])
    sol = ik(T, q_cur)
    assert sol[0] == pytest.approx(0.4)
    dp, dr = _pose_error(fk(sol), T)
    assert dp <= TOL and dr <= TOL


def test_ik_weights_change_the_choice() -> None:
    q = np.radians([20, 10, 30, 40, 50, 100])
    T = fk(q)
    # Current J6 is 180° from the solution's J6, but matches the wrist-flip branch exactly.
    q_cur = np.radians([20, 10, 30, 40, 50, -80])
    flip = np.radians([20, 10, 30, -140, -50, -80])
    plain = ik(T, q_cur)
    assert np.abs(plain - flip).max() > 1.0  # L2 prefers another branch
    weighted = ik(T, q_cur, weights=[1, 1, 1, 0, 0, 1])  # q4, q5 free: the flip costs nothing
    np.testing.assert_allclose(weighted, flip, atol=TOL)
    for sol in (plain, weighted):
        dp, dr = _pose_error(fk(sol), T)
        assert dp <= TOL and dr <= TOL


def test_ik_unreachable_raises() -> None:
    T = make_transform(np.eye(3), [1.5, 0.0, 0.5])
    with pytest.raises(IKError, match=r"beyond the reach of 0\.532 m"):
        ik(T, np.zeros(6))
    assert ik_all(T) == []


def test_ik_out_of_limits_raises() -> None:
    T = fk(np.radians([0, 0, 0, 0, -125, 0]))  # J5 beyond -120° on every branch
    with pytest.raises(IKError, match=r"violate joint limits: nearest violates j5 by 5\.0°"):
        ik(T, np.zeros(6))
    assert ik_all(T) == []


def test_ik_rejects_malformed_pose() -> None:
    with pytest.raises(IKError, match="shape"):
        ik(np.eye(3), np.zeros(6))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(IKError, match="rotation"):
        ik(bad, np.zeros(6))
    with pytest.raises(IKError, match="finite"):
        ik_all(np.full((4, 4), np.nan))
