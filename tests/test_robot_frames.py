"""Every registered robot (the built-in ones and the tri3 test plugin, tests/robots/tri3) against
its own MuJoCo scene, in the one frame convention of shared/robots.py.

The scene compiles; every arm joint is in it with the spec's limits and a position actuator; the
scene's "home" keyframe is the profiles' home; pose(q) is the MuJoCo tip site's pose (position
and orientation) in the scene's world frame and jacobian(q) the geometric Jacobian of that pose
(rows v then ω, world coordinates): against a numerical derivative of pose() and MuJoCo's own.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from telesurg.shared import robots
from telesurg.shared.robots import MODELS, ArmProfile

TRI3 = Path(__file__).resolve().parent / "robots" / "tri3" / "tri3.py"
robots.load_plugin(str(TRI3))
ROBOTS = robots.names()


def numeric_jacobian(p: ArmProfile, q: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Central differences of pose(q): linear velocity of the point, angular velocity of the frame."""
    cols = []
    for i in range(len(q)):
        dq = np.zeros_like(q)
        dq[i] = h
        Tp, Tm = p.pose(q + dq), p.pose(q - dq)
        v = (Tp[:3, 3] - Tm[:3, 3]) / (2 * h)
        W = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ p.pose(q)[:3, :3].T  # dR/dq Rᵀ = [ω]×
        cols.append(np.concatenate([v, [W[2, 1], W[0, 2], W[1, 0]]]))
    return np.column_stack(cols)


def test_the_test_plugin_is_registered_beside_the_built_in_robots() -> None:
    assert set(ROBOTS) >= {*MODELS, "tri3"}


@pytest.mark.parametrize("model", ROBOTS)
def test_scene_has_the_spec_joints_limits_actuators_and_home(model: str) -> None:
    spec = robots.get(model)
    m = mujoco.MjModel.from_xml_path(str(spec.scene))
    actuated = {int(m.actuator_trnid[i, 0]) for i in range(m.nu) if m.actuator_trntype[i] == 0}
    home = {m.key(i).name: m.key(i).qpos for i in range(m.nkey)}.get("home")
    for p in spec.arms("arm1"):
        ids = [m.joint(j).id for j in p.model_joints]  # KeyError: a joint the scene lacks
        np.testing.assert_allclose(m.jnt_range[ids, 0], p.lower, atol=1e-6)
        np.testing.assert_allclose(m.jnt_range[ids, 1], p.upper, atol=1e-6)
        assert set(ids) <= actuated, f"{model} {p.arm}: a joint without an actuator"
        assert p.tip_site in {m.site(i).name for i in range(m.nsite)}
        if home is not None:
            np.testing.assert_allclose(home[[m.jnt_qposadr[i] for i in ids]], p.home, atol=1e-9)
        s = spec.sketch(p.arm, np.array(p.home))
        assert s.links.ndim == 2 and s.links.shape[1] == 3 and len(s.links) >= 2


@pytest.mark.parametrize("model", ROBOTS)
def test_pose_is_the_tip_site_and_jacobian_its_derivative(model: str) -> None:
    spec = robots.get(model)
    m = mujoco.MjModel.from_xml_path(str(spec.scene))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(7)
    for p in spec.arms("arm1"):
        adr = [m.jnt_qposadr[m.joint(j).id] for j in p.model_joints]
        margin = 0.02 * (np.array(p.upper) - np.array(p.lower))  # central differences stay inside
        for _ in range(10):
            q = rng.uniform(np.array(p.lower) + margin, np.array(p.upper) - margin)
            d.qpos[:] = m.qpos0
            d.qpos[adr] = q
            mujoco.mj_kinematics(m, d)
            T = p.pose(q)
            assert T.shape == (4, 4)
            np.testing.assert_allclose(T[:3, 3], d.site(p.tip_site).xpos, atol=1e-9)
            np.testing.assert_allclose(T[:3, :3], d.site(p.tip_site).xmat.reshape(3, 3), atol=1e-9)
            np.testing.assert_allclose(T[3], (0, 0, 0, 1))
            np.testing.assert_allclose(p.tip(q), T[:3, 3])
            J = p.jacobian(q)
            assert J.shape == (6, len(p.joint_names))
            np.testing.assert_allclose(J, numeric_jacobian(p, q), atol=1e-6)
            # and MuJoCo's own site Jacobian agrees (columns of this arm's joints)
            jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
            mujoco.mj_comPos(m, d)
            mujoco.mj_jacSite(m, d, jacp, jacr, m.site(p.tip_site).id)
            dofs = [m.jnt_dofadr[m.joint(j).id] for j in p.model_joints]
            np.testing.assert_allclose(J, np.vstack([jacp[:, dofs], jacr[:, dofs]]), atol=1e-8)
