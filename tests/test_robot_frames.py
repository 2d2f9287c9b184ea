"""Every arm's pose() and jacobian() (shared/robots.py) in the one documented frame convention.

pose(q) is the MuJoCo tip site's pose (position and orientation) in the scene's world frame, and
jacobian(q) is the geometric Jacobian of that pose (rows v then ω, world coordinates).
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.models import model_path
from telesurg.shared.robots import MODELS, ArmProfile, arms_of


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


@pytest.mark.parametrize("model", MODELS)
def test_pose_is_the_tip_site_and_jacobian_its_derivative(model: str) -> None:
    m = mujoco.MjModel.from_xml_path(str(model_path(model)))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(7)
    for p in arms_of(model):
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
