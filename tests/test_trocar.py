"""Tests for shared.kinematics.trocar: RCM measures, trocar-mode IK and the J4/J5 posture adjustment."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics import FloatArray, rot_x, rot_y, rot_z
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik, ik_all, within_limits, wrist_center
from telesurg.shared.robots.mh3f.trocar import (
    STRAIGHT_FORCEPS,
    TROCAR_MODE_DEPTH,
    Forceps,
    _tcp_frame,
    axis_angle_to_trocar,
    forceps_roll,
    insertion_depth,
    interpolate_posture,
    posture_adjust,
    posture_duration,
    rcm_error,
    roll_reference,
    trocar_ik,
)

TOL = 1e-9
TROCAR = np.array([0.5, 0.0, 0.2])  # the paper's experiment: (x0, y0, z0) = (500, 0, 200) mm
Q_HOME = np.array([0.0, 0.2, 0.3, 0.0, -0.6, 0.0])
# A comfortable insertion direction through TROCAR: 60° below horizontal, in the x-z plane. The
# wrist centre is then 0.43-0.48 m from the shoulder for depths of 0-120 mm (reach 0.532 m) and
# 0.2-0.3 m from the J1 axis (away from the shoulder singularity).
AXIS_IN = np.array([math.cos(math.radians(-60.0)), 0.0, math.sin(math.radians(-60.0))])


def _unit(v: FloatArray) -> FloatArray:
    return v / np.linalg.norm(v)


def _cone_direction(rng: np.random.Generator, axis: FloatArray, half_angle: float) -> FloatArray:
    """Uniformly random unit vector within ``half_angle`` [rad] of the unit ``axis``."""
    cos_t = rng.uniform(math.cos(half_angle), 1.0)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    e1 = _unit(np.cross(axis, [0.0, 1.0, 0.0]))
    e2 = np.cross(axis, e1)
    sin_t = math.sqrt(1.0 - cos_t * cos_t)
    return cos_t * axis + sin_t * (math.cos(phi) * e1 + math.sin(phi) * e2)


def _wrapped(a: float) -> float:
    return math.remainder(a, 2.0 * math.pi)


def _home_axis() -> FloatArray:
    """Unit direction from the home-pose wrist centre to the trocar."""
    return _unit(TROCAR - wrist_center(Q_HOME))


# ---------------------------------------------------------------------------- derivation


def test_tool_axis_in_frame3_formula() -> None:
    """The posture-adjust derivation: R36 e_x = (cos q5, -sin q4 sin q5, cos q4 sin q5) in frame 3."""
    rng = np.random.default_rng(11)
    for _ in range(200):
        q1, q2, q3, q4, q5, q6 = rng.uniform(-3.0, 3.0, 6)
        R03 = rot_z(q1) @ rot_y(q2 - q3)
        v = [math.cos(q5), -math.sin(q4) * math.sin(q5), math.cos(q4) * math.sin(q5)]
        np.testing.assert_allclose(R03 @ v, fk([q1, q2, q3, q4, q5, q6])[:3, 0], atol=1e-15)
        R36 = rot_x(q4) @ rot_y(-q5) @ rot_x(q6)
        np.testing.assert_allclose(R36[:, 0], v, atol=1e-15)


# ---------------------------------------------------------------------------- measures


def test_insertion_depth_sign_and_value() -> None:
    q = np.array([0.1, 0.3, 0.2, 0.4, -0.7, 0.5])
    T = fk(q)
    tip, x = T[:3, 3], T[:3, 0]
    assert insertion_depth(q, tip) == pytest.approx(0.0, abs=1e-15)
    assert insertion_depth(q, tip - 0.05 * x) == pytest.approx(0.05, abs=1e-15)  # 50 mm in
    assert insertion_depth(q, tip + 0.03 * x) == pytest.approx(-0.03, abs=1e-15)  # 30 mm short
    # A lateral offset of the trocar does not change the depth along the axis.
    n = _unit(np.cross(x, [0.0, 0.0, 1.0]))
    assert insertion_depth(q, tip - 0.05 * x + 0.01 * n) == pytest.approx(0.05, abs=1e-15)


def test_rcm_error_equals_a_deliberate_offset() -> None:
    rng = np.random.default_rng(3)
    q = np.array([-0.2, 0.1, 0.4, -0.3, 0.8, 1.0])
    T = fk(q)
    tip, x = T[:3, 3], T[:3, 0]
    for offset in (0.0, 1e-6, 0.001, 0.0234):
        n = _unit(np.cross(x, rng.normal(size=3)))  # random direction perpendicular to the axis
        along = rng.uniform(-0.6, 0.3)  # anywhere along the (infinite) axis line
        trocar = tip - along * x + offset * n
        assert rcm_error(q, trocar) == pytest.approx(offset, abs=1e-14)
    # The wrist centre lies on the axis line.
    assert rcm_error(q, wrist_center(q)) < 1e-15


def test_axis_angle_to_trocar() -> None:
    q = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # axis +x from W = (0.27, 0, 0.562)
    W = wrist_center(q)
    assert axis_angle_to_trocar(q, W + np.array([0.3, 0.0, 0.0])) == pytest.approx(0.0, abs=1e-15)
    assert axis_angle_to_trocar(q, W + np.array([0.3, 0.0, -0.3])) == pytest.approx(math.pi / 4, abs=1e-15)
    assert axis_angle_to_trocar(q, W + np.array([0.0, 0.2, 0.0])) == pytest.approx(math.pi / 2, abs=1e-15)
    assert axis_angle_to_trocar(q, W - np.array([0.1, 0.0, 0.0])) == pytest.approx(math.pi, abs=1e-15)
    with pytest.raises(KinematicsError, match="coincides with the wrist centre"):
        axis_angle_to_trocar(q, W)


def test_measures_reject_bad_input() -> None:
    with pytest.raises(KinematicsError, match=r"trocar must have shape \(3,\)"):
        rcm_error(Q_HOME, [0.5, 0.0])
    with pytest.raises(KinematicsError, match="trocar must be finite"):
        insertion_depth(Q_HOME, [0.5, np.nan, 0.2])
    with pytest.raises(KinematicsError, match=r"shape \(6,\)"):
        rcm_error(np.zeros(5), TROCAR)


# ---------------------------------------------------------------------------- roll convention


def test_roll_reference_convention() -> None:
    # q = 0: axis +x, y_ref = ẑ × x̂ = +y, so roll 0 is the identity orientation.
    np.testing.assert_allclose(roll_reference([1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)
    assert forceps_roll(np.zeros(6)) == pytest.approx(0.0, abs=1e-15)
    # Horizontal and perpendicular to the axis for a tilted axis.
    d = _unit(np.array([0.3, -0.4, -0.8]))
    r = roll_reference(d)
    assert abs(r[2]) < 1e-15 and abs(r @ d) < 1e-15 and np.linalg.norm(r) == pytest.approx(1.0)
    # Degenerate: vertical axis -> base +y.
    np.testing.assert_allclose(roll_reference([0.0, 0.0, -1.0]), [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(roll_reference([0.0, 0.0, 2.0]), [0.0, 1.0, 0.0], atol=1e-15)
    r = roll_reference([1e-8, 2e-8, -1.0])  # within 1e-6 of vertical: +y projected ⟂ d
    assert r[1] > 0.999999 and abs(r @ _unit(np.array([1e-8, 2e-8, -1.0]))) < 1e-15
    with pytest.raises(KinematicsError, match="non-zero"):
        roll_reference([0.0, 0.0, 0.0])


def test_roll_is_honoured_and_right_handed() -> None:
    tip = TROCAR + 0.06 * AXIS_IN
    q0 = trocar_ik(tip, TROCAR, Q_HOME, roll=0.0)
    for roll in (0.0, 0.4, -1.3, 2.9, math.pi):
        q = trocar_ik(tip, TROCAR, Q_HOME, roll=roll)
        assert _wrapped(forceps_roll(q) - roll) == pytest.approx(0.0, abs=1e-12)
        # Right-handed about the axis: the TCP frame is the roll-0 frame turned by Rx(roll).
        np.testing.assert_allclose(fk(q)[:3, :3], fk(q0)[:3, :3] @ rot_x(roll), atol=1e-12)


def test_roll_with_vertical_axis() -> None:
    trocar = np.array([0.30, 0.0, 0.05])
    tip = trocar + np.array([0.0, 0.0, -0.05])  # forceps straight down: the degenerate roll reference
    q_cur = Q_HOME
    for roll in (0.0, 0.7):
        q = trocar_ik(tip, trocar, q_cur, roll=roll)
        T = fk(q)
        np.testing.assert_allclose(T[:3, 3], tip, atol=TOL)
        np.testing.assert_allclose(T[:3, 0], [0.0, 0.0, -1.0], atol=TOL)
        y_expected = [math.sin(roll), math.cos(roll), 0.0]  # +y turned about d = -z by roll
        np.testing.assert_allclose(T[:3, 1], y_expected, atol=1e-12)


# ---------------------------------------------------------------------------- trocar IK


def test_trocar_ik_round_trip_random_cone(capsys: pytest.CaptureFixture[str]) -> None:
    """Tips 20-120 mm beyond the trocar within ±30° of home-wrist → trocar; keep the solvable ones."""
    rng = np.random.default_rng(2014)
    axis = _home_axis()
    n_total, solved, unreachable = 600, 0, 0
    worst_tip = worst_rcm = worst_roll = 0.0
    for i in range(n_total):
        d = _cone_direction(rng, axis, math.radians(30.0))
        assert math.degrees(math.acos(min(1.0, float(d @ axis)))) <= 30.0 + 1e-9
        tip = TROCAR + rng.uniform(0.020, 0.120) * d
        roll = float(rng.uniform(-math.pi, math.pi)) if i % 2 == 0 else None
        try:
            q = trocar_ik(tip, TROCAR, Q_HOME, roll=roll)
        except IKError as exc:
            assert "reach" in str(exc) or "joint limits" in str(exc), str(exc)
            unreachable += 1
            continue
        solved += 1
        assert within_limits(q)
        T = fk(q)
        worst_tip = max(worst_tip, float(np.linalg.norm(T[:3, 3] - tip)))
        worst_rcm = max(worst_rcm, rcm_error(q, TROCAR))
        np.testing.assert_allclose(T[:3, 0], d, atol=1e-12)  # axis = trocar → tip
        assert insertion_depth(q, TROCAR) == pytest.approx(np.linalg.norm(tip - TROCAR), abs=1e-12)
        if roll is not None:
            worst_roll = max(worst_roll, abs(_wrapped(forceps_roll(q) - roll)))
        # Nearest branch: no other within-limit solution of this pose is closer to the start.
        cost = float(np.sum((q - Q_HOME) ** 2))
        assert all(float(np.sum((s - Q_HOME) ** 2)) >= cost - 1e-12 for s in ik_all(T))
    with capsys.disabled():
        print(
            f"\ntrocar IK round trip: {solved}/{n_total} cone targets solved ({unreachable} out of reach); "
            f"worst tip {worst_tip:.1e} m, rcm {worst_rcm:.1e} m, roll {worst_roll:.1e} rad"
        )
    assert solved >= 200
    assert worst_tip <= TOL and worst_rcm <= TOL and worst_roll <= 1e-12


def test_trocar_ik_none_roll_keeps_current_y_axis() -> None:
    rng = np.random.default_rng(8)
    q_cur = trocar_ik(TROCAR + 0.06 * AXIS_IN, TROCAR, Q_HOME, roll=0.5)
    y_cur = fk(q_cur)[:3, 1]
    for _ in range(20):
        d = _cone_direction(rng, AXIS_IN, math.radians(10.0))
        tip = TROCAR + 0.07 * d
        q = trocar_ik(tip, TROCAR, q_cur)
        kept = float(fk(q)[:3, 1] @ y_cur)
        # No roll about the new axis brings the y axis closer to the current one.
        q_roll = forceps_roll(q)
        for delta in np.linspace(-0.3, 0.3, 61):
            other = fk(trocar_ik(tip, TROCAR, q_cur, roll=q_roll + delta))[:3, 1]
            assert float(other @ y_cur) <= kept + 1e-12


def test_none_roll_when_the_axis_turns_onto_the_old_y_axis() -> None:
    """Degenerate continuity case: the old y axis is the new forceps axis; the old z axis is kept."""
    T = fk(np.array([0.2, 0.1, 0.4, 0.3, -0.8, 0.5]))
    d = (float(T[0, 1]), float(T[1, 1]), float(T[2, 1]))
    y, z = _tcp_frame(d, None, T)
    np.testing.assert_allclose(z, T[:3, 2], atol=1e-15)
    np.testing.assert_allclose(y, -T[:3, 0], atol=1e-15)  # right-handed: y = z × d


def test_trocar_ik_continuity_along_path() -> None:
    """~1 mm tip steps on a circle, then in and out: joints continuous, no branch flip."""
    e1 = _unit(np.cross(AXIS_IN, [0.0, 1.0, 0.0]))
    e2 = np.cross(AXIS_IN, e1)
    radius, depth, n = 0.015, 0.100, 95  # 2π × 15 mm ≈ 94 mm of circle at 100 mm depth
    circle = [
        TROCAR + depth * AXIS_IN + radius * (math.cos(t) * e1 + math.sin(t) * e2)
        for t in np.linspace(0.0, 2.0 * math.pi, n + 1)
    ]
    d_end = _unit(circle[-1] - TROCAR)  # in and out along the forceps axis at the loop's end
    plunge = [circle[-1] + (0.001 * k) * d_end for k in (*range(1, 31), *range(29, -1, -1))]

    def follow(q: FloatArray, path: list[FloatArray]) -> tuple[FloatArray, float]:
        max_step = 0.0
        for tip in path:
            q_next = trocar_ik(tip, TROCAR, q)
            max_step = max(max_step, float(np.abs(q_next - q).max()))
            assert np.sign(q_next[4]) == np.sign(q_start[4])  # same wrist branch
            assert abs(q_next[0] - q_start[0]) < math.pi / 2  # same J1 (front) branch
            np.testing.assert_allclose(fk(q_next)[:3, 3], tip, atol=TOL)
            assert rcm_error(q_next, TROCAR) <= TOL
            q = q_next
        return q, max_step

    q_start = trocar_ik(circle[0], TROCAR, Q_HOME)
    q_loop, step_circle = follow(q_start, circle[1:])
    q_end, step_plunge = follow(q_loop, plunge)
    # Tip steps of ~1 mm with the wrist centre ~5x further from the trocar: small joint steps.
    assert step_circle < 0.05 and step_plunge < 0.01, (step_circle, step_plunge)
    # Around the closed loop only the roll (J6) differs, by the solid angle the axis swept
    # (the holonomy of keeping the y axis closest, i.e. parallel transport): 2π (1 - cos θ).
    solid_angle = 2.0 * math.pi * (1.0 - math.cos(math.atan2(radius, depth)))
    np.testing.assert_allclose(q_loop[:5], q_start[:5], atol=1e-9, rtol=0)
    assert _wrapped(forceps_roll(q_loop) - forceps_roll(q_start)) == pytest.approx(solid_angle, abs=1e-3)
    assert q_loop[5] - q_start[5] == pytest.approx(solid_angle, abs=1e-3)
    # In and back out along the same axis: the very same joints.
    np.testing.assert_allclose(q_end, q_loop, atol=1e-9, rtol=0)


def test_trocar_ik_tip_at_or_behind_trocar() -> None:
    axis = _home_axis()
    with pytest.raises(IKError, match=r"only 0\.00 mm beyond the trocar"):
        trocar_ik(TROCAR, TROCAR, Q_HOME)
    with pytest.raises(IKError, match=r"only 3\.00 mm beyond the trocar .* at least 5\.00 mm"):
        trocar_ik(TROCAR + 0.003 * axis, TROCAR, Q_HOME)
    with pytest.raises(IKError, match=r"20\.00 mm behind the trocar"):
        trocar_ik(TROCAR - 0.02 * axis, TROCAR, Q_HOME)
    # Beside the trocar: 40 mm away but perpendicular to the approach direction.
    side = _unit(np.cross(axis, [0.0, 1.0, 0.0]))
    with pytest.raises(IKError, match=r"0\.00 mm (behind|beyond) the trocar"):
        trocar_ik(TROCAR + 0.04 * side, TROCAR, Q_HOME)
    # A smaller minimum is honoured.
    q = trocar_ik(TROCAR + 0.003 * axis, TROCAR, Q_HOME, min_depth=0.001)
    assert rcm_error(q, TROCAR) <= TOL


def test_trocar_ik_unreachable_and_too_deep() -> None:
    far = np.array([1.2, 0.0, 0.2])  # the wrist centre would have to be beyond the arm's reach
    tip = far + 0.05 * _unit(far - wrist_center(Q_HOME))
    with pytest.raises(IKError, match=r"trocar IK: tip .* 50\.0 mm beyond the trocar .*beyond the reach"):
        trocar_ik(tip, far, Q_HOME)
    with pytest.raises(IKError, match=r"more than the 0\.5000 m forceps length .* by 0\.0200 m"):
        trocar_ik(TROCAR + 0.52 * _home_axis(), TROCAR, Q_HOME)


def test_trocar_ik_rejects_bad_arguments() -> None:
    tip = TROCAR + 0.05 * AXIS_IN
    with pytest.raises(KinematicsError, match="min_depth"):
        trocar_ik(tip, TROCAR, Q_HOME, min_depth=0.0)
    with pytest.raises(KinematicsError, match="roll must be finite"):
        trocar_ik(tip, TROCAR, Q_HOME, roll=math.nan)
    with pytest.raises(KinematicsError, match=r"tip must have shape \(3,\)"):
        trocar_ik(np.zeros(4), TROCAR, Q_HOME)


def test_trocar_ik_benchmark(capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(99)
    tips = [TROCAR + 0.08 * _cone_direction(rng, AXIS_IN, math.radians(10.0)) for _ in range(200)]
    q = trocar_ik(tips[0], TROCAR, Q_HOME)
    for roll in (None, 0.3):
        t0 = time.perf_counter()
        n = 0
        for _ in range(5):
            for tip in tips:
                trocar_ik(tip, TROCAR, q, roll=roll)
                n += 1
        us = (time.perf_counter() - t0) / n * 1e6
        with capsys.disabled():
            print(f"\ntrocar_ik (roll={roll}): {us:.1f} µs per call over {n} calls")


# ---------------------------------------------------------------------------- posture adjustment


def _random_starts(rng: np.random.Generator, n: int) -> list[FloatArray]:
    """Random arm poses whose wrist centre is 0.15-0.75 m from the trocar, on the arm's side."""
    out: list[FloatArray] = []
    while len(out) < n:
        q = rng.uniform(MH3F.lower_limits, MH3F.upper_limits)
        q[0] = rng.uniform(-1.0, 1.0)
        q[1] = rng.uniform(-0.5, 0.8)
        q[2] = rng.uniform(-0.5, 1.0)
        if 0.15 < float(np.linalg.norm(TROCAR - wrist_center(q))) < 0.75:
            out.append(q)
    return out


def test_posture_adjust_moves_j4_j5_only_and_aligns() -> None:
    rng = np.random.default_rng(21)
    adjusted = 0
    for q in _random_starts(rng, 300):
        try:
            qa = posture_adjust(q, TROCAR)
        except IKError as exc:
            assert "violate the joint limits" in str(exc)
            continue
        adjusted += 1
        np.testing.assert_allclose(qa[[0, 1, 2, 5]], q[[0, 1, 2, 5]], atol=1e-12, rtol=0)
        assert within_limits(qa)
        assert axis_angle_to_trocar(qa, TROCAR) <= TOL
        assert rcm_error(qa, TROCAR) <= TOL
        # Nearest of the two wrist solutions (the flip is (q4 ± π, -q5), any in-limit wrap).
        flip4 = qa[3] + math.pi if qa[3] < 0 else qa[3] - math.pi
        flip = qa.copy()
        flip[3], flip[4] = flip4, -qa[4]
        assert axis_angle_to_trocar(flip, TROCAR) <= TOL  # the other solution is a solution too
        if within_limits(flip):
            assert np.sum((qa[3:5] - q[3:5]) ** 2) <= np.sum((flip[3:5] - q[3:5]) ** 2) + 1e-12
    assert adjusted >= 200, adjusted


def test_posture_adjust_from_paper_like_starts() -> None:
    """Three different starts outside the patient (paper, Fig. 10), then insert into trocar mode."""
    starts = [
        np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0]),
        np.array([0.4, -0.3, 0.5, 0.8, -0.5, 1.0]),
        np.array([-0.4, -0.2, 0.7, -1.2, 0.9, -0.4]),
    ]
    for q in starts:
        assert axis_angle_to_trocar(q, TROCAR) > 0.1  # not aligned yet
        qa = posture_adjust(q, TROCAR)
        assert axis_angle_to_trocar(qa, TROCAR) <= TOL and rcm_error(qa, TROCAR) <= TOL
        depth = insertion_depth(qa, TROCAR)
        assert depth < -0.05  # tip still outside: ready for the insert motion
        # Insert motion (jog along the aligned axis, orientation kept): the RCM holds throughout.
        T = fk(qa)
        d = T[:3, 0]
        q_cur = qa
        for target_depth in np.linspace(depth, 0.0, 10):
            T_step = T.copy()
            T_step[:3, 3] = TROCAR + target_depth * d
            q_cur = ik(T_step, q_cur)
            assert rcm_error(q_cur, TROCAR) <= TOL
        # Past the trocar: trocar-mode IK up to the paper's 50 mm switch-over depth.
        for target_depth in np.linspace(0.005, TROCAR_MODE_DEPTH, 10):
            q_next = trocar_ik(TROCAR + target_depth * d, TROCAR, q_cur)
            assert float(np.abs(q_next - q_cur).max()) < 0.05  # no jump when entering trocar mode
            assert rcm_error(q_next, TROCAR) <= TOL
            q_cur = q_next
        assert insertion_depth(q_cur, TROCAR) == pytest.approx(TROCAR_MODE_DEPTH, abs=1e-12)


def test_posture_adjust_already_aligned_and_singular() -> None:
    q = np.array([0.1, 0.2, 0.5, 0.4, -0.7, 0.3])
    T = fk(q)
    trocar = T[:3, 3] + 0.1 * T[:3, 0]  # straight ahead: already aligned
    np.testing.assert_allclose(posture_adjust(q, trocar), q, atol=1e-12, rtol=0)
    # Trocar on the upper-arm axis direction: q5 = 0 (singular wrist), J4 kept.
    q_s = np.array([0.1, 0.2, 0.5, 0.4, 0.0, 0.3])
    T_s = fk(q_s)
    qa = posture_adjust(np.array([0.1, 0.2, 0.5, 0.4, 0.6, 0.3]), T_s[:3, 3] + 0.2 * T_s[:3, 0])
    assert qa[3] == pytest.approx(0.4) and abs(qa[4]) < 1e-7


def test_posture_adjust_out_of_limits_and_degenerate() -> None:
    q = np.array([0.0, 0.0, 0.0, 0.0, 0.5, 0.0])  # upper arm along +x, W = (0.27, 0, 0.562)
    W = wrist_center(q)
    behind = W + np.array([-0.3, 0.0, -0.05])  # 170.5° from the upper-arm axis: |q5| > 120° on both flips
    with pytest.raises(IKError, match=r"both wrist solutions violate .* j5 by 50\.5°"):
        posture_adjust(q, behind)
    with pytest.raises(IKError, match="coincides with the wrist centre"):
        posture_adjust(q, W)


def test_interpolate_posture_is_synchronous() -> None:
    q_from = np.array([0.0, 0.0, 0.5, 0.0, -0.3, 0.2])
    q_to = posture_adjust(q_from, TROCAR)
    np.testing.assert_array_equal(interpolate_posture(q_from, q_to, 0.0), q_from)
    np.testing.assert_array_equal(interpolate_posture(q_from, q_to, 1.0), q_to)
    mid = interpolate_posture(q_from, q_to, 0.25)
    np.testing.assert_allclose(mid[3:5], q_from[3:5] + 0.25 * (q_to[3:5] - q_from[3:5]), atol=1e-15)
    np.testing.assert_array_equal(mid[[0, 1, 2, 5]], q_from[[0, 1, 2, 5]])
    with pytest.raises(KinematicsError, match=r"s must be in \[0, 1\]"):
        interpolate_posture(q_from, q_to, 1.5)
    other = q_to.copy()
    other[1] += 0.01
    with pytest.raises(KinematicsError, match=r"J4 and J5 only, but joint 2 differs by 1\.000e-02"):
        interpolate_posture(q_from, other, 0.5)
    # Duration: the slower joint (largest |Δq| / speed) sets the time.
    dt = posture_duration(q_from, q_to)
    expected = max(abs(q_to[3] - q_from[3]) / 5.24, abs(q_to[4] - q_from[4]) / 5.24)
    assert dt == pytest.approx(expected)
    assert posture_duration(q_from, q_to, speed_fraction=0.5) == pytest.approx(2.0 * expected)


# ---------------------------------------------------------------------------- forceps


def test_forceps_description() -> None:
    geom = STRAIGHT_FORCEPS.arm_geometry()
    assert geom == MH3F  # the default arm already carries the paper's 500 mm dummy forceps
    short = Forceps(length_m=0.35).arm_geometry()
    assert short.tool == 0.35 and short.wrist_to_tcp == pytest.approx(0.44)
    # The shorter tool is honoured by the trocar IK.
    tip = TROCAR + 0.05 * AXIS_IN
    q = trocar_ik(tip, TROCAR, Q_HOME, geom=short)
    np.testing.assert_allclose(fk(q, short)[:3, 3], tip, atol=TOL)
    assert rcm_error(q, TROCAR, short) <= TOL
    articulated = Forceps(length_m=0.45, wrist_joints=2)
    assert articulated.articulated
    with pytest.raises(NotImplementedError, match=r"articulated forceps \(2 tip joints, J7/J8"):
        articulated.arm_geometry()
    with pytest.raises(KinematicsError, match="length_m"):
        Forceps(length_m=0.0)
    with pytest.raises(KinematicsError, match="wrist_joints"):
        Forceps(wrist_joints=-1)


def test_pose_to_trocar_matches_the_kinematic_measures() -> None:
    from telesurg.shared.robots.mh3f.trocar import pose_to_trocar

    rng = np.random.default_rng(5)
    trocar = np.array([0.5, 0.0, 0.2])
    for _ in range(50):
        q = rng.uniform(np.array(MH3F.lower) * 0.5, np.array(MH3F.upper) * 0.5)
        T = fk(q, MH3F)
        rcm, depth = pose_to_trocar(T[:3, 3], 3.0 * T[:3, 0], trocar)  # axis length is ignored
        assert rcm == pytest.approx(rcm_error(q, trocar), abs=1e-12)
        assert depth == pytest.approx(insertion_depth(q, trocar), abs=1e-12)


def test_mujoco_arm_through_the_trocar_has_sub_mm_rcm_error() -> None:
    """Measured from MuJoCo's tip site (not from the command): a trocar-IK pose 60 mm deep."""
    from telesurg.services.slave_control.factory import make_backend
    from telesurg.shared.kinematics import matrix_from_quat
    from telesurg.shared.robots.mh3f.trocar import pose_to_trocar

    trocar = np.array([0.5, 0.0, 0.2])
    q_start = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])  # a paper-like start (Fig. 10)
    q_aligned = posture_adjust(q_start, trocar)
    axis = fk(q_aligned, MH3F)[:3, 0]
    q_in = trocar_ik(trocar + 0.06 * axis, trocar, q_aligned)
    with make_backend("mujoco", "mh3f", tuple(q_in.tolist())) as sim:
        sim.command(q_in)
        sim.step(500)  # 0.5 s to settle under gravity
        r = sim.read()
    rcm, depth = pose_to_trocar(r.tip_position, matrix_from_quat(r.tip_quat)[:, 0], trocar)
    print(f"MuJoCo at rest: RCM error {rcm * 1e3:.4f} mm, depth {depth * 1e3:.2f} mm")
    assert rcm < 1e-3 and depth == pytest.approx(0.06, abs=1e-3)
