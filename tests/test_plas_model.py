"""MuJoCo models plas (two-arm PLAS slave) and plas_master: load, step, match plas.py, track steps."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.models import model_names, model_path
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.plas.kinematics import PLAS_MASTER, PLAS_SLAVE, master_fk, slave_fk
from telesurg.shared.robots.plas.layout import (
    ARM_BASES,
    ARM_NAMES,
    SHAFT_AXIS,
    arm_base,
    arm_tip,
    arm_tip_pose,
)

TOL = 1e-6  # [m] site vs analytic kinematics (they agree to ~1e-15)
SETTLE_STEPS = 300  # 0.3 s at dt = 1 ms
REVOLUTE_STEP = 0.2  # [rad]
PRISMATIC_STEP = 0.010  # [m]


def _warnings(data: mujoco.MjData) -> dict[int, int]:
    return {i: int(w.number) for i, w in enumerate(data.warning) if w.number}


@pytest.fixture(scope="module")
def slave() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(model_path("plas")))


@pytest.fixture(scope="module")
def master() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(model_path("plas_master")))


def _names(model: mujoco.MjModel, obj: mujoco.mjtObj, n: int) -> list[str]:
    return [mujoco.mj_id2name(model, obj, i) for i in range(n)]


def _random_q(rng: np.random.Generator, lower: FloatArray, upper: FloatArray) -> FloatArray:
    return rng.uniform(lower, upper)


def _arm_qadr(model: mujoco.MjModel, arm: str) -> np.ndarray:
    """qpos addresses of an arm's six joints (its two jaw fingers follow theta6 in qpos)."""
    return np.array([model.jnt_qposadr[model.joint(f"{arm}_{n}").id] for n in PLAS_SLAVE.joint_names])


# --------------------------------------------------------------------------------------------
# Registry, names, limits
# --------------------------------------------------------------------------------------------


def test_registered() -> None:
    assert {"plas", "plas_master"} <= set(model_names())
    assert model_path("plas").parent.name == "plas"
    assert model_path("plas_master").parent.name == "plas_master"


def test_slave_names_and_limits(slave: mujoco.MjModel) -> None:
    expected = [f"{arm}_{n}" for arm in ARM_NAMES for n in PLAS_SLAVE.joint_names]
    # each arm's six joints, then its two jaw fingers; the scene's other joints are the tissue's
    # indentations, unactuated (not the robot's)
    tissue = [f"tissue_{arm}_indent" for arm in ARM_NAMES]
    per_arm = [
        [*expected[6 * k : 6 * k + 6], f"{arm}_jaw_a", f"{arm}_jaw_b"] for k, arm in enumerate(ARM_NAMES)
    ]
    assert _names(slave, mujoco.mjtObj.mjOBJ_JOINT, slave.njnt) == [*per_arm[0], *per_arm[1], *tissue]
    # the twelve arm servos first, in joint order, then the jaws (actuator group 2: tools), each
    # on its finger a
    jaws = [f"{arm}_jaw" for arm in ARM_NAMES]
    assert _names(slave, mujoco.mjtObj.mjOBJ_ACTUATOR, slave.nu) == expected + jaws
    assert [slave.joint(slave.actuator(i).trnid[0]).name for i in range(slave.nu)] == expected + [
        f"{j}_a" for j in jaws
    ]
    assert list(slave.actuator_group) == [0] * 12 + [2, 2]
    assert slave.nu == 14 and slave.nq == slave.nv == 18
    for arm in ARM_NAMES:
        slave.site(f"{arm}_tip")  # raises KeyError if missing
        slave.site(f"{arm}_grasp")
    limits = np.column_stack([PLAS_SLAVE.lower_limits, PLAS_SLAVE.upper_limits])
    expected_range = np.vstack([limits, limits])
    arm_ids = [slave.joint(n).id for n in expected]
    np.testing.assert_allclose(slave.jnt_range[arm_ids], expected_range, rtol=0, atol=1e-9)
    np.testing.assert_allclose(slave.actuator_ctrlrange[:12], expected_range, rtol=0, atol=1e-9)
    np.testing.assert_allclose(slave.actuator_ctrlrange[12:], [[0.0, 0.0045]] * 2, rtol=0, atol=1e-12)
    assert all(slave.jnt_limited)
    prismatic = [n in ("d1", "d5") for n in PLAS_SLAVE.joint_names] * 2
    assert [t == mujoco.mjtJoint.mjJNT_SLIDE for t in slave.jnt_type[arm_ids]] == prismatic


def test_master_names_and_limits(master: mujoco.MjModel) -> None:
    expected = list(PLAS_MASTER.joint_names)
    assert _names(master, mujoco.mjtObj.mjOBJ_JOINT, master.njnt) == expected
    assert _names(master, mujoco.mjtObj.mjOBJ_ACTUATOR, master.nu) == expected
    master.site("tip")
    expected_range = np.column_stack([PLAS_MASTER.lower_limits, PLAS_MASTER.upper_limits])
    np.testing.assert_allclose(master.jnt_range, expected_range, rtol=0, atol=1e-9)
    np.testing.assert_allclose(master.actuator_ctrlrange, expected_range, rtol=0, atol=1e-9)
    assert all(master.jnt_limited)
    prismatic = [n in ("d1", "d6") for n in PLAS_MASTER.joint_names]
    assert [t == mujoco.mjtJoint.mjJNT_SLIDE for t in master.jnt_type] == prismatic


# --------------------------------------------------------------------------------------------
# Kinematics: sites vs plas.py / plas_layout.py
# --------------------------------------------------------------------------------------------


def test_layout_helpers() -> None:
    q = np.array([0.05, 0.3, -0.2, 0.4, 0.01, 0.5])
    for arm in ARM_NAMES:
        base = ARM_BASES[arm]
        assert not base.flags.writeable
        np.testing.assert_allclose(base[:3, :3] @ base[:3, :3].T, np.eye(3), atol=1e-15)
        assert np.linalg.det(base[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_allclose(base[:3, 2], SHAFT_AXIS)  # z0 runs down the port
        np.testing.assert_allclose(arm_tip_pose(arm, q), base @ slave_fk(q), atol=1e-15)
        deeper = arm_tip(arm, q, insertion=0.03)
        np.testing.assert_allclose(deeper - arm_tip(arm, q), 0.03 * SHAFT_AXIS, atol=1e-15)
        np.testing.assert_allclose(arm_base(arm, 0.03)[:3, 3], base[:3, 3] + 0.03 * SHAFT_AXIS)
    # arm2 = arm1 turned by pi about the port axis; mirror image with theta4, theta6 negated.
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    np.testing.assert_allclose(ARM_BASES["arm2"], turn @ ARM_BASES["arm1"], atol=1e-15)
    mirrored = q * np.array([1, 1, 1, -1, 1, -1])
    np.testing.assert_allclose(arm_tip("arm2", mirrored), arm_tip("arm1", q) * [1, -1, 1], atol=1e-15)
    with pytest.raises(KinematicsError, match="arm3"):
        arm_tip("arm3", q)
    with pytest.raises(KinematicsError, match="insertion"):
        arm_tip("arm1", q, insertion=float("nan"))


def test_slave_zero_pose(slave: mujoco.MjModel) -> None:
    data = mujoco.MjData(slave)
    mujoco.mj_forward(slave, data)
    reach = PLAS_SLAVE.a2 + PLAS_SLAVE.a3 + PLAS_SLAVE.d5
    np.testing.assert_allclose(data.site("arm1_tip").xpos, [0.0, -0.006 - reach, -0.04], atol=1e-12)
    np.testing.assert_allclose(data.site("arm2_tip").xpos, [0.0, 0.006 + reach, -0.04], atol=1e-12)
    np.testing.assert_allclose(data.site("port").xpos, [0.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("arm", ARM_NAMES)
def test_slave_tip_matches_layout(slave: mujoco.MjModel, arm: str) -> None:
    data = mujoco.MjData(slave)
    rng = np.random.default_rng(2015 + ARM_NAMES.index(arm))
    adr = _arm_qadr(slave, arm)
    other = _arm_qadr(slave, ARM_NAMES[1 - ARM_NAMES.index(arm)])
    fingers = np.setdiff1d(np.arange(16), np.r_[adr, other])  # the four jaw fingers (before the tissue)
    for _ in range(20):
        q = _random_q(rng, PLAS_SLAVE.lower_limits, PLAS_SLAVE.upper_limits)
        data.qpos[adr] = q
        data.qpos[other] = _random_q(rng, PLAS_SLAVE.lower_limits, PLAS_SLAVE.upper_limits)
        data.qpos[fingers] = rng.uniform(0.0, 0.0045, 4)  # the jaws do not move the tip
        mujoco.mj_forward(slave, data)
        site = data.site(f"{arm}_tip")
        np.testing.assert_allclose(site.xpos, arm_tip(arm, q), rtol=0, atol=TOL)
        pose = arm_tip_pose(arm, q)
        np.testing.assert_allclose(site.xmat.reshape(3, 3), pose[:3, :3], rtol=0, atol=1e-9)
        np.testing.assert_allclose(data.sensor(f"{arm}_tip_pos").data, pose[:3, 3], rtol=0, atol=TOL)


def test_slave_insertion_is_the_common_body() -> None:
    """Moving the body insertion_part down the port by ``insertion`` is arm_tip(..., insertion)."""
    model = mujoco.MjModel.from_xml_path(str(model_path("plas")))
    data = mujoco.MjData(model)
    body = model.body("insertion_part").id
    rng = np.random.default_rng(7)
    for insertion in (0.02, -0.01):
        model.body_pos[body] = insertion * SHAFT_AXIS
        q = np.concatenate(
            [_random_q(rng, PLAS_SLAVE.lower_limits, PLAS_SLAVE.upper_limits) for _ in range(2)]
        )
        data.qpos[np.r_[_arm_qadr(model, "arm1"), _arm_qadr(model, "arm2")]] = q
        mujoco.mj_forward(model, data)
        for k, arm in enumerate(ARM_NAMES):
            expected = arm_tip(arm, q[6 * k : 6 * k + 6], insertion=insertion)
            np.testing.assert_allclose(data.site(f"{arm}_tip").xpos, expected, rtol=0, atol=TOL)


def test_master_tip_matches_fk(master: mujoco.MjModel) -> None:
    data = mujoco.MjData(master)
    mujoco.mj_forward(master, data)
    np.testing.assert_allclose(data.site("tip").xpos, [PLAS_MASTER.a2 + PLAS_MASTER.d6, 0, 0], atol=1e-12)
    rng = np.random.default_rng(2016)
    for _ in range(20):
        q = _random_q(rng, PLAS_MASTER.lower_limits, PLAS_MASTER.upper_limits)
        data.qpos[:] = q
        mujoco.mj_forward(master, data)
        T = master_fk(q)
        np.testing.assert_allclose(data.site("tip").xpos, T[:3, 3], rtol=0, atol=TOL)
        np.testing.assert_allclose(data.site("tip").xmat.reshape(3, 3), T[:3, :3], rtol=0, atol=1e-9)


def test_keyframes(slave: mujoco.MjModel, master: mujoco.MjModel) -> None:
    for model, key in ((slave, "home"), (master, "home")):
        np.testing.assert_array_equal(model.key(key).qpos, np.zeros(model.nq))
        np.testing.assert_array_equal(model.key(key).ctrl, np.zeros(model.nu))
    data = mujoco.MjData(slave)
    mujoco.mj_resetDataKeyframe(slave, data, slave.key("y_shape").id)
    mujoco.mj_forward(slave, data)
    tip1, tip2 = data.site("arm1_tip").xpos, data.site("arm2_tip").xpos
    np.testing.assert_allclose(tip2, tip1 * [1, -1, 1], atol=1e-12)  # mirror images
    assert tip1[1] < 0.0 < tip2[1]
    adr = np.r_[_arm_qadr(slave, "arm1"), _arm_qadr(slave, "arm2")]
    for key in ("y_shape", "insert"):  # the arms' joints; the jaws open, the tissue at rest
        np.testing.assert_allclose(slave.key(key).ctrl[:12], slave.key(key).qpos[adr])
        np.testing.assert_array_equal(slave.key(key).ctrl[12:], 0.0)
        np.testing.assert_array_equal(np.delete(slave.key(key).qpos, adr), 0.0)
    np.testing.assert_allclose(master.key("rest").ctrl, master.key("rest").qpos)


# --------------------------------------------------------------------------------------------
# Dynamics: clean stepping, servo steps
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["plas", "plas_master"])
def test_steps_one_second_cleanly(name: str) -> None:
    model = mujoco.MjModel.from_xml_path(str(model_path(name)))
    assert model.opt.timestep == pytest.approx(0.001)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for key in range(model.nkey):
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, key)
        q0 = data.qpos.copy()
        for _ in range(1000):
            mujoco.mj_step(model, data)
        assert _warnings(data) == {}
        assert np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))
        np.testing.assert_allclose(data.qpos, q0, rtol=0, atol=1e-9)  # gravcomp: no sag, no drift
        assert float(np.max(np.abs(data.qvel))) < 1e-9


@pytest.mark.parametrize("name", ["plas", "plas_master"])
def test_servo_steps(name: str) -> None:
    """A 0.2 rad (revolute) / 10 mm (prismatic) step on one joint is within 2 % after 0.3 s."""
    model = mujoco.MjModel.from_xml_path(str(model_path(name)))
    lo, hi = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    q0 = lo + 0.4 * (hi - lo)  # away from every limit, with room for the step (ranges >= 30 mm, 2 rad)
    adr = model.jnt_qposadr[model.actuator_trnid[:, 0]]  # each servo's joint (a jaw's: its finger a)
    arm = np.flatnonzero(model.actuator_group != 2)  # the joint servos (group 2: the jaws)
    for i in arm:
        slide = model.jnt_type[model.actuator(i).trnid[0]] == mujoco.mjtJoint.mjJNT_SLIDE
        step = PRISMATIC_STEP if slide else REVOLUTE_STEP
        data = mujoco.MjData(model)
        data.qpos[adr] = q0
        data.ctrl[:] = q0
        data.ctrl[i] = q0[i] + step
        assert lo[i] <= data.ctrl[i] <= hi[i]
        for _ in range(SETTLE_STEPS):
            mujoco.mj_step(model, data)
        err = abs(data.qpos[adr[i]] - data.ctrl[i])
        assert err <= 0.02 * step, f"{model.actuator(i).name}: {err:.3g} after 0.3 s"
        others = np.delete(np.abs(data.qpos[adr[arm]] - q0[arm]), np.flatnonzero(arm == i))
        assert float(np.max(others)) < 0.02 * step
        assert _warnings(data) == {}


def test_jaws_close_and_open_together(slave: mujoco.MjModel) -> None:
    """Each arm's jaw servo (group 2) closes both fingers fully within 0.1 s and opens them again,
    the two fingers mirroring each other, the arm's joints unmoved."""
    data = mujoco.MjData(slave)
    mujoco.mj_resetDataKeyframe(slave, data, slave.key("y_shape").id)
    arms = np.r_[_arm_qadr(slave, "arm1"), _arm_qadr(slave, "arm2")]
    q_arms = data.qpos[arms].copy()
    for arm in ARM_NAMES:
        act = slave.actuator(f"{arm}_jaw").id
        a, b = (slave.jnt_qposadr[slave.joint(f"{arm}_jaw_{f}").id] for f in "ab")
        for target in (0.0045, 0.0):  # closed, then open again
            data.ctrl[act] = target
            for _ in range(100):
                mujoco.mj_step(slave, data)
            assert data.qpos[a] == pytest.approx(target, abs=2e-5)
            assert data.qpos[b] == pytest.approx(data.qpos[a], abs=2e-5)
    np.testing.assert_allclose(data.qpos[arms], q_arms, rtol=0, atol=1e-6)
    assert _warnings(data) == {}
