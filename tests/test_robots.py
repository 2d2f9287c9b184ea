"""Robot profiles (shared/robots.py) agree with the MuJoCo models and the kinematics."""

from __future__ import annotations

import dataclasses
import pathlib

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.models import model_path
from telesurg.shared import robots
from telesurg.shared.errors import ConfigError, IKError
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
    with pytest.raises(ConfigError, match="valid: " + ", ".join(robots.names())):  # mh3f, plas, vip …
        arms_of("ur5")
    with pytest.raises(ConfigError, match="no arm 'arm3'"):
        arm_profile("plas", "arm3")
    assert arm_profile("mh3f", "left").arm == "left"  # a single-arm model takes any id


def test_registry_names_and_lookup() -> None:
    assert set(MODELS) <= set(robots.names())
    spec = robots.get("plas")
    assert spec.slave_family == "joint" and "all_joints" in spec.mapping_modes
    assert robots.get("mh3f").slave_family == "trocar"
    assert spec.scene == model_path("plas")
    assert [a.arm for a in spec.arms("x")] == ["arm1", "arm2"]
    with pytest.raises(ConfigError, match=r"robot model 'ur5' unknown; valid: " + ", ".join(robots.names())):
        robots.get("ur5")


def test_register_refuses_a_bad_spec() -> None:
    vip = robots.get("vip")
    with pytest.raises(ConfigError, match="registered already"):
        robots.register(dataclasses.replace(vip, description="another vip"))
    with pytest.raises(ConfigError, match="slave_family 'wheels' invalid; valid: trocar, joint"):
        dataclasses.replace(vip, name="rover", slave_family="wheels")
    with pytest.raises(ConfigError, match="is not a file"):
        dataclasses.replace(vip, name="rover", scene=model_path("vip").parent / "missing.xml")
    with pytest.raises(ConfigError, match="must match"):
        dataclasses.replace(vip, name="Bad Name")
    p = arm_profile("vip", "arm1")
    with pytest.raises(ConfigError, match=r"home 9\.0 outside"):
        dataclasses.replace(p, home=(9.0, *p.home[1:]))
    with pytest.raises(ConfigError, match="lower has 4 values, not 5"):
        dataclasses.replace(p, lower=p.lower[:4])


def test_load_plugin_errors_name_the_file(tmp_path: pathlib.Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        robots.load_plugin(str(tmp_path / "none.py"))
    bad = tmp_path / "bad_robot.py"
    bad.write_text("raise RuntimeError('broken on purpose')\n")
    with pytest.raises(ConfigError, match=r"bad_robot.py' failed to load: RuntimeError: broken on purpose"):
        robots.load_plugin(str(bad))
    assert "bad_robot" not in " ".join(robots.names())


def test_only_mh3f_has_an_analytic_pose_ik() -> None:
    p = arm_profile("mh3f", "arm1")
    q = np.array(p.home)
    np.testing.assert_allclose(p.ik(p.pose(q), q + 0.01), q, atol=1e-9)
    with pytest.raises(IKError, match="no analytic IK"):
        arm_profile("plas", "arm1").ik(np.eye(4), np.zeros(6))


def test_recognise_an_arm_by_its_joint_names() -> None:
    vip = arm_profile("vip", "arm2")
    found = robots.recognise("arm2", vip.joint_names)
    assert found is not None and found[0].name == "vip" and found[1] == vip
    assert robots.recognise("arm3", vip.joint_names) is None  # vip has no arm3
    found = robots.recognise("left", arm_profile("mh3f", "arm1").joint_names)
    assert found is not None and found[0].name == "mh3f" and found[1].arm == "left"
    assert robots.recognise("arm1", ("a", "b")) is None
