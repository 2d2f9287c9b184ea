"""MuJoCo slave-arm models: compile, step cleanly, match the analytic chain, track setpoints."""

from __future__ import annotations

import pathlib

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.models import model_names, model_path

MODELS_DIR = pathlib.Path(model_path("mh3f")).parent.parent  # shared/robots
SCENES = sorted(MODELS_DIR.glob("*/scene.xml")) + sorted(MODELS_DIR.glob("*/*/scene.xml"))

# Bent working pose (forceps pointing down-forward, towards the trocar).
Q_BENT = np.array([0.0, 0.3, 0.2, 0.0, -0.8, 0.0])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _tr(x: float, y: float, z: float) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def mh3f_tip(q: np.ndarray) -> np.ndarray:
    """Tip pose (4x4) of the MH3F + 500 mm forceps, from the documented chain."""
    return (
        _rz(q[0])
        @ _tr(0, 0, 0.272)
        @ _ry(q[1])
        @ _tr(0, 0, 0.260)
        @ _ry(-q[2])
        @ _tr(0, 0, 0.030)
        @ _rx(q[3])
        @ _tr(0.270, 0, 0)
        @ _ry(-q[4])
        @ _rx(q[5])
        @ _tr(0.590, 0, 0)
    )


def _warnings(data: mujoco.MjData) -> dict[int, int]:
    return {i: int(w.number) for i, w in enumerate(data.warning) if w.number}


@pytest.fixture(scope="module")
def mh3f() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(model_path("mh3f")))


def test_model_path() -> None:
    assert "mh3f" in model_names()
    assert model_path("mh3f").name == "scene.xml"
    assert model_path("mh3f").is_file()
    with pytest.raises(ValueError, match="mh3f"):
        model_path("puma560")


def test_every_scene_is_registered() -> None:
    assert SCENES, "no scene.xml found"
    # every folder here is a model name and every model name of this folder has a folder (a
    # plugin's robot, e.g. tests/robots/tri3 once loaded, keeps its scene elsewhere)
    here = {n for n in model_names() if MODELS_DIR in model_path(n).parents}
    assert {p.parent.name for p in SCENES} == here
    assert all(model_path(n).is_file() for n in model_names())


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.parent.name)
def test_scene_steps_cleanly(scene: pathlib.Path) -> None:
    model = mujoco.MjModel.from_xml_path(str(scene))
    assert model.opt.timestep == pytest.approx(0.001)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    data = mujoco.MjData(model)
    # Hold the zero pose, then move every position servo towards a nearby target.
    for k in range(1000):
        if k == 500:
            data.ctrl[:] = np.clip(
                data.qpos[: model.nu] + 0.05,
                model.actuator_ctrlrange[:, 0],
                model.actuator_ctrlrange[:, 1],
            )
        mujoco.mj_step(model, data)
    assert _warnings(data) == {}
    assert np.all(np.isfinite(data.qpos))
    assert np.all(np.isfinite(data.qvel))
    assert np.all(np.isfinite(data.act))


#: the MH3F arm's joints in the scene's qpos (the tissue's indentation joint follows them)
ARM = slice(0, 6)


def test_mh3f_tip_at_zero(mh3f: mujoco.MjModel) -> None:
    data = mujoco.MjData(mh3f)
    mujoco.mj_kinematics(mh3f, data)
    np.testing.assert_allclose(data.site("tip").xpos, [0.860, 0.0, 0.562], atol=1e-9)
    np.testing.assert_allclose(data.site("flange").xpos, [0.360, 0.0, 0.562], atol=1e-9)
    np.testing.assert_allclose(data.site("wrist_center").xpos, [0.270, 0.0, 0.562], atol=1e-9)
    np.testing.assert_allclose(data.site("trocar").xpos, [0.5, 0.0, 0.2], atol=1e-12)


def test_mh3f_fk_matches_chain(mh3f: mujoco.MjModel) -> None:
    data = mujoco.MjData(mh3f)
    rng = np.random.default_rng(2014)
    lo, hi = mh3f.jnt_range[ARM, 0], mh3f.jnt_range[ARM, 1]
    for _ in range(100):
        q = rng.uniform(lo, hi)
        data.qpos[ARM] = q
        mujoco.mj_kinematics(mh3f, data)
        expected = mh3f_tip(q)
        np.testing.assert_allclose(data.site("tip").xpos, expected[:3, 3], atol=1e-9)
        np.testing.assert_allclose(data.site("tip").xmat.reshape(3, 3), expected[:3, :3], atol=1e-9)


def test_mh3f_limits_and_actuators(mh3f: mujoco.MjModel) -> None:
    deg = np.deg2rad
    expected = deg([[-160, 160], [-85, 90], [-105, 260], [-170, 170], [-120, 120], [-360, 360]])
    np.testing.assert_allclose(mh3f.jnt_range[ARM], expected, atol=1e-6)
    np.testing.assert_allclose(mh3f.actuator_ctrlrange, expected, atol=1e-6)
    names = [mh3f.actuator(i).name for i in range(mh3f.nu)]
    assert names == [f"j{i}" for i in range(1, 7)]
    assert all(mh3f.jnt_limited)
    # the scene's one other joint is the tissue's indentation, unactuated (not the robot's)
    assert [mh3f.joint(j).name for j in range(6, mh3f.njnt)] == ["tissue_indent"]


def test_mh3f_static_setpoint(mh3f: mujoco.MjModel) -> None:
    data = mujoco.MjData(mh3f)
    data.qpos[ARM] = Q_BENT + np.array([0.02, -0.02, 0.02, 0.03, -0.03, 0.05])
    data.ctrl[:] = Q_BENT
    for _ in range(500):
        mujoco.mj_step(mh3f, data)
    err = np.linalg.norm(data.site("tip").xpos - mh3f_tip(Q_BENT)[:3, 3])
    assert err < 1e-4
    assert _warnings(data) == {}


def test_mh3f_tracks_smooth_setpoints(mh3f: mujoco.MjModel) -> None:
    """A smooth setpoint stream (tip speed up to ~50 mm/s) is tracked within 0.5 mm."""
    data = mujoco.MjData(mh3f)
    amp = 0.4 * np.array([0.06, 0.05, 0.05, 0.15, 0.08, 0.2])
    freq = np.array([0.13, 0.17, 0.11, 0.19, 0.23, 0.29])
    data.qpos[ARM] = Q_BENT
    data.ctrl[:] = Q_BENT
    worst = 0.0
    dt = mh3f.opt.timestep
    for k in range(1, 3001):
        target = Q_BENT + amp * (1.0 - np.cos(2.0 * np.pi * freq * k * dt))
        data.ctrl[:] = target
        mujoco.mj_step(mh3f, data)
        if k % 10 == 0:
            err = np.linalg.norm(data.site("tip").xpos - mh3f_tip(target)[:3, 3])
            worst = max(worst, float(err))
    assert worst < 5e-4
    assert _warnings(data) == {}
