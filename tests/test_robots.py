"""Robot profiles (shared/robots.py) agree with the MuJoCo models and the kinematics."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.models import model_path
from telesurg.shared.errors import ConfigError
from telesurg.shared.robots import MODELS, arm_profile, arms_of


@pytest.mark.parametrize("model", MODELS)
def test_profiles_match_the_model(model: str) -> None:
    m = mujoco.MjModel.from_xml_path(str(model_path(model)))
    d = mujoco.MjData(m)
    rng = np.random.default_rng(1)
    for p in arms_of(model):
        ids = [m.joint(j).id for j in p.model_joints]
        np.testing.assert_allclose(m.jnt_range[ids, 0], p.lower, atol=1e-6)
        np.testing.assert_allclose(m.jnt_range[ids, 1], p.upper, atol=1e-6)
        for _ in range(5):  # the profile's tip function is the model's tip site
            q = rng.uniform(p.lower, p.upper)
            d.qpos[[m.jnt_qposadr[i] for i in ids]] = q
            mujoco.mj_forward(m, d)
            np.testing.assert_allclose(d.site(p.tip_site).xpos, p.tip(q), atol=1e-6)
        assert len(p.joint_names) == len(p.max_velocity) == len(p.home)


def test_unknown_model_or_arm_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="valid: mh3f, plas, vip"):
        arms_of("ur5")
    with pytest.raises(ConfigError, match="no arm 'arm3'"):
        arm_profile("plas", "arm3")
    assert arm_profile("mh3f", "left").arm == "left"  # a single-arm model takes any id
