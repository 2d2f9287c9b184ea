"""Tests for shared.kinematics.vip (Jang et al. 2014 SPA arm, VIP control) and the MuJoCo model vip."""

from __future__ import annotations

import math
import pathlib
from dataclasses import replace

import mujoco
import numpy as np
import pytest
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.vip.kinematics import (
    EV_MAX,
    EV_MIN,
    VIP_ARM,
    VIP_ARM1,
    VIP_ARM2,
    JointLimitError,
    VipArmGeometry,
    check_limits,
    elbow_jacobian,
    fk,
    ik,
    jacobian,
    pinv_step,
    select_vip,
    vip_elbow,
    vip_ik,
    within_limits,
)

TOL = 1e-9
GEOMS = [VIP_ARM, VIP_ARM1, VIP_ARM2]
GEOM_IDS = ["base", "arm1", "arm2"]
MODEL_DIR = pathlib.Path(__file__).resolve().parent.parent / "shared" / "robots" / "vip"


def _random_q(rng: np.random.Generator, n: int, geom: VipArmGeometry = VIP_ARM) -> list[FloatArray]:
    """Random joints within the Table I limits, with the forearm bent (q5 >= 0.01 rad: q4 defined)."""
    lo, hi = geom.lower_limits.copy(), geom.upper_limits
    lo[4] = 0.01
    return [rng.uniform(lo, hi) for _ in range(n)]


def _off_line(point: FloatArray, a: FloatArray, b: FloatArray) -> float:
    """Distance [m] of ``point`` from the straight line through ``a`` and ``b``."""
    d = (b - a) / np.linalg.norm(b - a)
    r = point - a
    return float(np.linalg.norm(r - (r @ d) * d))


# --------------------------------------------------------------------------------------------
# Geometry of the arm (checked against the paper's definitions, not against the chain code)
# --------------------------------------------------------------------------------------------


def test_table1_limits_and_home() -> None:
    deg = math.radians
    np.testing.assert_allclose(VIP_ARM.lower, [deg(-20), deg(5), -0.195, deg(-90), 0.0])
    np.testing.assert_allclose(VIP_ARM.upper, [deg(60), deg(50), -0.02, deg(90), deg(90)])
    np.testing.assert_allclose(VIP_ARM.home, [deg(20), deg(30), -0.14, deg(30), deg(45)])
    assert 0.0 < VIP_ARM.alpha < math.pi / 2 and 0.0 < VIP_ARM.beta < math.pi / 2  # eq. 1


@pytest.mark.parametrize("geom", GEOMS, ids=GEOM_IDS)
def test_fk_matches_the_papers_definitions(geom: VipArmGeometry) -> None:
    """R fixed, |RE| = -q3, E on the cone of half-angle β about z2 (elevation α, azimuth q1),
    |EW| = forearm and angle(RE, EW) = q5 (eqs. 18-19)."""
    rng = np.random.default_rng(6)
    Rb = geom.base_rotation
    for q in _random_q(rng, 200, geom):
        p = fk(q, geom)
        np.testing.assert_allclose(p.rcm, geom.base_position, atol=TOL)
        re, ew = p.elbow - p.rcm, p.wrist - p.elbow
        assert np.linalg.norm(re) == pytest.approx(-q[2], abs=TOL)
        assert np.linalg.norm(ew) == pytest.approx(geom.forearm, abs=TOL)
        ca, sa = math.cos(geom.alpha), math.sin(geom.alpha)
        z2 = Rb @ np.array([ca * math.cos(q[0]), ca * math.sin(q[0]), sa])  # the q2 axis
        z3 = -re / np.linalg.norm(re)  # the shaft goes in along -z3
        assert float(z3 @ z2) == pytest.approx(math.cos(geom.beta), abs=TOL)
        cos_q5 = float(re @ ew) / (np.linalg.norm(re) * np.linalg.norm(ew))
        assert cos_q5 == pytest.approx(math.cos(q[4]), abs=TOL)
        # Wrist frame: z5 points from W back to E.
        np.testing.assert_allclose(p.wrist_frame[:3, 2], -ew / geom.forearm, atol=TOL)
        np.testing.assert_allclose(p.wrist_frame[:3, 3], p.wrist, atol=0.0)


def test_shaft_is_vertical_at_q2_zero_and_tilts_as_documented() -> None:
    """α + β = π/2: q2 = 0 puts the shaft on -z1; cos θ = sin²α + cos²α cos q2 otherwise."""
    q = VIP_ARM.home_q.copy()
    for q2_deg, theta_deg in [(0.0, 0.0), (5.0, 2.5), (30.0, 14.9), (50.0, 24.4)]:
        q[1] = math.radians(q2_deg)
        e = fk(q).elbow
        theta = math.degrees(math.acos(-e[2] / np.linalg.norm(e)))
        assert theta == pytest.approx(theta_deg, abs=0.05)


def test_two_arm_placement() -> None:
    """The model's arms: RCMs 12 mm apart across the port, wrists right (arm1) and left (arm2)."""
    q = VIP_ARM.home_q
    w1, w2 = fk(q, VIP_ARM1).wrist, fk(q, VIP_ARM2).wrist
    assert w1[1] < -0.03 and w2[1] > 0.03
    np.testing.assert_allclose(w1, -w2 * np.array([1.0, 1.0, -1.0]), atol=TOL)  # 180° about z
    assert -0.20 < w1[2] < -0.17  # ~0.18 m below the skin


# --------------------------------------------------------------------------------------------
# Inverse kinematics (eqs. 3-19)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("geom", GEOMS, ids=GEOM_IDS)
def test_fk_ik_round_trip(geom: VipArmGeometry) -> None:
    rng = np.random.default_rng(2014)
    for q in _random_q(rng, 500, geom):
        p = fk(q, geom)
        q_ik = ik(p.elbow, p.wrist, geom)
        np.testing.assert_allclose(q_ik, q, atol=TOL, rtol=0.0)
        p2 = fk(q_ik, geom)
        np.testing.assert_allclose(p2.elbow, p.elbow, atol=TOL, rtol=0.0)
        np.testing.assert_allclose(p2.wrist, p.wrist, atol=TOL, rtol=0.0)


def test_ik_at_the_limits_and_straight_forearm() -> None:
    g = VIP_ARM
    for q in (g.lower_limits, g.upper_limits):
        q = q.copy()
        q[3] = 0.3  # q5 = 0 at the lower corner leaves q4 free: pass it as the reference
        p = fk(q, g)
        np.testing.assert_allclose(ik(p.elbow, p.wrist, g, q4_ref=0.3), q, atol=TOL)
    q = g.home_q.copy()
    q[4] = 0.0  # straight forearm: q4 undetermined, kept at q4_ref
    p = fk(q, g)
    assert ik(p.elbow, p.wrist, g, q4_ref=-0.7)[3] == -0.7
    np.testing.assert_allclose(fk(ik(p.elbow, p.wrist, g, q4_ref=-0.7), g).wrist, p.wrist, atol=TOL)


@pytest.mark.parametrize(
    ("joint", "value", "message"),
    [
        (0, math.radians(70.0), "q1 = 70.0° (1.2217 rad) exceeds its upper limit 60.0° by 10.0°"),
        (0, math.radians(-32.5), "q1 = -32.5° (-0.5672 rad) is below its lower limit -20.0° by 12.5°"),
        (1, math.radians(57.0), "q2 = 57.0° (0.9948 rad) exceeds its upper limit 50.0° by 7.0°"),
        (1, math.radians(2.0), "q2 = 2.0° (0.0349 rad) is below its lower limit 5.0° by 3.0°"),
        (2, -0.012, "q3 = -0.012 m exceeds its upper limit -0.020 m by 0.008 m"),
        (2, -0.232, "q3 = -0.232 m is below its lower limit -0.195 m by 0.037 m"),
        (3, math.radians(100.0), "q4 = 100.0° (1.7453 rad) exceeds its upper limit 90.0° by 10.0°"),
        (3, math.radians(-95.0), "q4 = -95.0° (-1.6581 rad) is below its lower limit -90.0° by 5.0°"),
        (4, math.radians(120.0), "q5 = 120.0° (2.0944 rad) exceeds its upper limit 90.0° by 30.0°"),
    ],
)
def test_ik_outside_limits_names_the_joint(joint: int, value: float, message: str) -> None:
    q = VIP_ARM.home_q.copy()
    q[joint] = value
    p = fk(q)
    with pytest.raises(JointLimitError) as info:
        ik(p.elbow, p.wrist)
    assert message in str(info.value)
    assert [v.joint for v in info.value.violations] == [f"q{joint + 1}"]
    assert isinstance(info.value, IKError)
    # Without the limits (the paper's simulation) the same point is solved exactly.
    np.testing.assert_allclose(ik(p.elbow, p.wrist, enforce_limits=False), q, atol=TOL)
    assert not within_limits(q)
    with pytest.raises(JointLimitError, match=f"q{joint + 1}"):
        check_limits(q)


def test_ik_reports_every_violated_joint() -> None:
    q = VIP_ARM.home_q.copy()
    q[0], q[2] = math.radians(65.0), -0.21
    p = fk(q)
    with pytest.raises(JointLimitError) as info:
        ik(p.elbow, p.wrist)
    assert [v.joint for v in info.value.violations] == ["q1", "q3"]
    assert [v.excess for v in info.value.violations] == pytest.approx([math.radians(5.0), 0.015])


def test_ik_rejects_unreachable_targets() -> None:
    p = fk(VIP_ARM.home_q)
    with pytest.raises(IKError, match="forearm"):
        ik(p.elbow, p.wrist + np.array([0.0, 0.0, 0.01]))  # |EW| != 0.060
    with pytest.raises(IKError, match="q1 axis"):
        ik([0.0, 0.0, -0.1], [0.0, 0.06, -0.1])  # assumption (2)
    with pytest.raises(IKError, match="RCM point"):
        ik([0.0, 0.0, 0.0], [0.0, 0.0, -0.06])
    with pytest.raises(IKError, match="cone"):
        ik([0.1, 0.0, -0.01], [0.1, 0.0, -0.07])  # shaft 84° from vertical: beyond the 60° cone
    with pytest.raises(KinematicsError, match="shape"):
        ik([0.0, 0.1], p.wrist)


def test_geometry_validation() -> None:
    with pytest.raises(KinematicsError, match="alpha"):
        replace(VIP_ARM, alpha=math.pi / 2)
    with pytest.raises(KinematicsError, match="beta"):
        replace(VIP_ARM, beta=0.0)
    with pytest.raises(KinematicsError, match="home"):
        replace(VIP_ARM, home=(0.0, 0.0, -0.1, 0.0, 0.1))
    with pytest.raises(KinematicsError, match="unit quaternion"):
        replace(VIP_ARM, base_quat=(0.0, 0.0, 0.0, 2.0))


# --------------------------------------------------------------------------------------------
# Jacobians
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("geom", GEOMS, ids=GEOM_IDS)
def test_jacobians_match_finite_differences(geom: VipArmGeometry) -> None:
    rng = np.random.default_rng(7)
    h = 1e-6
    for q in _random_q(rng, 50, geom):
        Jw, Je = jacobian(q, geom), elbow_jacobian(q, geom)
        assert Jw.shape == Je.shape == (3, 5)
        for i in range(5):
            dq = np.zeros(5)
            dq[i] = h
            plus, minus = fk(q + dq, geom), fk(q - dq, geom)
            np.testing.assert_allclose(Jw[:, i], (plus.wrist - minus.wrist) / (2 * h), atol=1e-8)
            np.testing.assert_allclose(Je[:, i], (plus.elbow - minus.elbow) / (2 * h), atol=1e-8)


# --------------------------------------------------------------------------------------------
# Virtual Incision Port (eqs. 20-23)
# --------------------------------------------------------------------------------------------


def test_vip_elbow_is_on_the_line_at_forearm_length() -> None:
    rng = np.random.default_rng(20)
    for _ in range(200):
        W = rng.uniform(-0.1, 0.1, 3)
        V = W + rng.uniform(-0.15, 0.15, 3)
        E = vip_elbow(W, V)
        assert np.linalg.norm(E - W) == pytest.approx(VIP_ARM.forearm, abs=TOL)
        assert _off_line(E, W, V) < TOL
        assert float((E - W) @ (V - W)) > 0.0  # toward V, not away from it
    with pytest.raises(KinematicsError, match="coincides"):
        vip_elbow([0.0, 0.0, -0.1], [0.0, 0.0, -0.1])


@pytest.mark.parametrize("ev", [EV_MIN, 0.035, EV_MAX])
@pytest.mark.parametrize("geom", GEOMS, ids=GEOM_IDS)
def test_select_vip_reproduces_the_configuration(geom: VipArmGeometry, ev: float) -> None:
    """The VIP chosen from the joint readings makes vip_ik return those readings (Steps 3-6)."""
    rng = np.random.default_rng(23)
    for q in _random_q(rng, 100, geom):
        p = fk(q, geom)
        V = select_vip(q, ev, geom)
        assert np.linalg.norm(V - p.elbow) == pytest.approx(ev, abs=TOL)  # |EV|
        assert np.linalg.norm(V - p.wrist) == pytest.approx(geom.forearm + ev, abs=TOL)
        assert _off_line(p.elbow, p.wrist, V) < TOL  # V, E, W collinear, E between
        np.testing.assert_allclose(vip_elbow(p.wrist, V, geom), p.elbow, atol=TOL)
        np.testing.assert_allclose(vip_ik(p.wrist, V, geom), q, atol=TOL, rtol=0.0)


def test_select_vip_default_is_the_experiments_005_m() -> None:
    q = VIP_ARM.home_q
    V = select_vip(q)
    assert np.linalg.norm(V - fk(q).elbow) == pytest.approx(0.05, abs=TOL)


@pytest.mark.parametrize("ev", [0.0, 0.019, 0.051, 0.2, -0.03, math.nan, math.inf])
def test_select_vip_rejects_ev_outside_the_procedure_range(ev: float) -> None:
    with pytest.raises(ValueError, match=r"ev_distance.*\[0\.02, 0\.05\] m"):
        select_vip(VIP_ARM.home_q, ev)


def test_vip_moves_keep_the_elbow_on_the_virtual_instrument() -> None:
    """Wrist moves under a fixed VIP: E stays on W-V at |EV| = |WV| - forearm, within limits."""
    g = VIP_ARM1
    q0 = g.home_q
    V = select_vip(q0, 0.05, g)
    W0 = fk(q0, g).wrist
    for offset in ([0.02, 0.0, 0.0], [0.0, -0.02, 0.01], [-0.01, 0.015, -0.015]):
        W = W0 + np.array(offset)
        q = vip_ik(W, V, g)
        p = fk(q, g)
        np.testing.assert_allclose(p.wrist, W, atol=TOL)
        assert _off_line(p.elbow, W, V) < TOL
        assert np.linalg.norm(p.elbow - V) == pytest.approx(np.linalg.norm(W - V) - g.forearm, abs=TOL)


def _circle(W0: FloatArray, k: int, n: int, radius: float = 0.02) -> FloatArray:
    t = 2.0 * math.pi * k / n
    return W0 + radius * np.array([math.cos(t) - 1.0, math.sin(t), 0.3 * math.sin(2.0 * t)])


def test_pseudo_inverse_elbow_wanders_vip_elbow_does_not() -> None:
    """Same closed wrist path (20 mm circle): the pinv elbow leaves the line W-V and does not come
    back; the VIP elbow stays on it and returns to its start (deterministic elbow)."""
    g = VIP_ARM1
    q0 = g.home_q
    start = fk(q0, g)
    V = select_vip(q0, 0.05, g)
    n = 200
    q_pinv = q0.copy()
    pinv_off = pinv_err = vip_off = 0.0
    q_vip = q0
    for k in range(1, n + 1):
        W = _circle(start.wrist, k, n)
        for _ in range(3):  # closed-loop resolved rate: a few pinv steps per waypoint
            q_pinv = pinv_step(q_pinv, W - fk(q_pinv, g).wrist, g)
        p = fk(q_pinv, g)
        pinv_err = max(pinv_err, float(np.linalg.norm(p.wrist - W)))
        pinv_off = max(pinv_off, _off_line(p.elbow, W, V))
        q_vip = vip_ik(W, V, g)
        vip_off = max(vip_off, _off_line(fk(q_vip, g).elbow, W, V))
    assert pinv_err < 1e-6  # the pinv wrist follows the path too: a fair comparison
    assert vip_off < TOL
    assert pinv_off > 5e-3  # measured 26 mm
    assert np.linalg.norm(fk(q_pinv, g).elbow - start.elbow) > 5e-3  # measured 25 mm
    np.testing.assert_allclose(fk(q_vip, g).elbow, start.elbow, atol=TOL)


# --------------------------------------------------------------------------------------------
# MuJoCo model shared/robots/vip
# --------------------------------------------------------------------------------------------

ARMS = (("arm1", VIP_ARM1), ("arm2", VIP_ARM2))


@pytest.fixture(scope="module")
def vip_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(MODEL_DIR / "scene.xml"))


def _warnings(data: mujoco.MjData) -> dict[int, int]:
    return {i: int(w.number) for i, w in enumerate(data.warning) if w.number}


#: the arm joints (arm1 q1..q5, arm2 q1..q5) and each arm's jaw fingers (robot.xml "jaws")
ARM_JOINTS = [f"{arm}_q{i}" for arm, _ in ARMS for i in range(1, 6)]
JAWS = [f"{arm}_jaw" for arm, _ in ARMS]


def _arm_qadr(m: mujoco.MjModel) -> np.ndarray:
    """qpos addresses of the ten arm joints (each arm's fingers follow its q5 in qpos)."""
    return np.array([m.jnt_qposadr[m.joint(n).id] for n in ARM_JOINTS])


def test_model_names_limits_and_home(vip_model: mujoco.MjModel) -> None:
    m = vip_model
    names = ARM_JOINTS
    # each arm's five joints, then its two jaw fingers; the scene's other joints are the tissue's
    # indentations, unactuated (not the robot's)
    tissue = [f"tissue_{arm}_indent" for arm, _ in ARMS]
    per_arm = [[*(f"{arm}_q{i}" for i in range(1, 6)), f"{arm}_jaw_a", f"{arm}_jaw_b"] for arm, _ in ARMS]
    assert [m.joint(i).name for i in range(m.njnt)] == [*per_arm[0], *per_arm[1], *tissue]
    # the ten arm servos first, in joint order, then the jaws (actuator group 2: tools), each on
    # its finger a
    assert [m.actuator(i).name for i in range(m.nu)] == names + JAWS
    assert [m.joint(m.actuator(i).trnid[0]).name for i in range(m.nu)] == names + [f"{j}_a" for j in JAWS]
    assert list(m.actuator_group) == [0] * 10 + [2, 2]
    for arm, _ in ARMS:
        for site in ("rcm", "elbow", "wrist", "grasp"):
            m.site(f"{arm}_{site}")  # raises KeyError if missing
    m.camera("endoscope")
    limits = np.column_stack([VIP_ARM.lower_limits, VIP_ARM.upper_limits])
    arm_ids = [m.joint(n).id for n in names]
    np.testing.assert_allclose(m.jnt_range[arm_ids], np.vstack([limits, limits]), atol=1e-9)
    np.testing.assert_allclose(m.actuator_ctrlrange[:10], np.vstack([limits, limits]), atol=1e-9)
    np.testing.assert_allclose(m.actuator_ctrlrange[10:], [[0.0, 0.0045]] * 2, atol=1e-12)  # open .. closed
    assert all(m.jnt_limited) and all(m.actuator_ctrllimited)
    home = np.concatenate([VIP_ARM.home_q, VIP_ARM.home_q])
    key = m.key("home")
    adr = _arm_qadr(m)
    np.testing.assert_allclose(key.qpos[adr], home, atol=1e-9)
    np.testing.assert_array_equal(np.delete(key.qpos, adr), 0.0)  # the jaws open, the tissue at rest
    np.testing.assert_allclose(key.ctrl, np.r_[home, 0, 0], atol=1e-9)  # the jaws commanded open
    np.testing.assert_allclose(m.qpos0[adr], home, atol=1e-9)
    np.testing.assert_array_equal(np.delete(m.qpos0, adr), 0.0)


def test_model_sites_match_fk(vip_model: mujoco.MjModel) -> None:
    m = vip_model
    data = mujoco.MjData(m)
    rng = np.random.default_rng(9)
    qs = [np.concatenate([a, b]) for a, b in zip(_random_q(rng, 20), _random_q(rng, 20), strict=True)]
    qs.append(np.concatenate([VIP_ARM.lower_limits, VIP_ARM.upper_limits]))
    adr = _arm_qadr(m)
    fingers = np.setdiff1d(np.arange(10 + 4), adr)  # the four jaw fingers (before the tissue)
    for q in qs:
        data.qpos[adr] = q
        data.qpos[fingers] = rng.uniform(0.0, 0.0045, 4)  # the jaws do not move the wrist
        mujoco.mj_forward(m, data)
        for j, (arm, geom) in enumerate(ARMS):
            p = fk(q[5 * j : 5 * j + 5], geom)
            np.testing.assert_allclose(data.site(f"{arm}_rcm").xpos, p.rcm, atol=1e-6)
            np.testing.assert_allclose(data.site(f"{arm}_elbow").xpos, p.elbow, atol=1e-6)
            np.testing.assert_allclose(data.site(f"{arm}_wrist").xpos, p.wrist, atol=1e-6)
            np.testing.assert_allclose(
                data.site(f"{arm}_wrist").xmat.reshape(3, 3), p.wrist_frame[:3, :3], atol=1e-6
            )


def test_model_tracks_vip_setpoints(vip_model: mujoco.MjModel) -> None:
    """Both arms follow a 15 mm wrist circle (≤ 37 mm/s) from vip_ik setpoints within 0.5 mm,
    with the elbows on their virtual instruments within 0.5 mm and no MuJoCo warnings."""
    m = vip_model
    data = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, data, m.key("home").id)
    vips = [select_vip(VIP_ARM.home_q, 0.05, g) for _, g in ARMS]
    w0 = [fk(VIP_ARM.home_q, g).wrist for _, g in ARMS]
    duration, dt = 4.0, m.opt.timestep
    worst_wrist = worst_elbow = 0.0
    for k in range(1, round(duration / dt) + 1):
        s = math.pi * (1.0 - math.cos(math.pi * k * dt / duration))  # 0 → 2π, smooth start/stop
        offset = 0.015 * np.array([math.cos(s) - 1.0, math.sin(s), 0.0])
        targets = [w0[0] + offset, w0[1] - offset]
        for j, (_, g) in enumerate(ARMS):
            data.ctrl[5 * j : 5 * j + 5] = vip_ik(targets[j], vips[j], g)
        mujoco.mj_step(m, data)
        if k % 10 == 0:
            for j, (arm, _) in enumerate(ARMS):
                wrist = data.site(f"{arm}_wrist").xpos
                worst_wrist = max(worst_wrist, float(np.linalg.norm(wrist - targets[j])))
                worst_elbow = max(worst_elbow, _off_line(data.site(f"{arm}_elbow").xpos, wrist, vips[j]))
    assert worst_wrist < 5e-4
    assert worst_elbow < 5e-4
    assert _warnings(data) == {}


def test_model_robot_xml_alone_steps_cleanly() -> None:
    m = mujoco.MjModel.from_xml_path(str(MODEL_DIR / "robot.xml"))
    assert m.opt.timestep == pytest.approx(0.001)
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    data = mujoco.MjData(m)
    driven = m.jnt_qposadr[m.actuator_trnid[:, 0]]  # each servo's joint (the jaws: finger a)
    for k in range(1000):
        if k == 500:
            data.ctrl[:] = np.clip(
                data.qpos[driven] + 0.05, m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
            )
        mujoco.mj_step(m, data)
    assert _warnings(data) == {}
    assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
