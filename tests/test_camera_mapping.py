"""Teleoperation in the camera frame (issue #18, acceptance 2): the real mapping over real zenoh
sessions, the camera pose from the real MuJoCo endoscope (rotated about its view axis), the tip
projected into the picture with the camera's intrinsics."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import wait_until
from helpers import feed_master
from telesurg.services.camera import pose_matrix, quat_xyzw
from telesurg.services.camera.sources import Intrinsics, MujocoSource
from telesurg.services.mapping import MappingConfig, Pair
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, Header, JointSetpoint, JointState, OperatingState
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk

Q0 = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
H = Header("test", 0, 0)


def _rot_about_view(T: np.ndarray, deg: float) -> np.ndarray:
    """The camera pose turned by ``deg`` about its own view axis (optical z)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out


def _pose_msg(T: np.ndarray) -> CartesianPose:
    return CartesianPose(H, "base", (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), quat_xyzw(T[:3, :3]))


def _pixel(T_cam: np.ndarray, k: Intrinsics, p: np.ndarray) -> np.ndarray:
    pc = T_cam[:3, :3].T @ (p - T_cam[:3, 3])
    return np.array([k.fx * pc[0] / pc[2] + k.cx, k.fy * pc[1] / pc[2] + k.cy])


@pytest.fixture(scope="module")
def endoscope() -> Iterator[MujocoSource]:
    """One simulated endoscope for the module (its GL context takes seconds to make)."""
    src = MujocoSource(robots.get("mh3f").scene, width=320, height=240)
    yield src
    src.close()


@pytest.fixture
def rig(endpoint: str, endoscope: MujocoSource) -> Iterator[tuple[Pair, list[JointSetpoint], MujocoSource]]:
    bus = BusConfig(connect=[endpoint])
    setpoints: list[JointSetpoint] = []
    src = endoscope
    home = src.pose()
    with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
        probe.subscribe(probe.keys.slave("arm1", "servo_jp"), JointSetpoint, lambda m, k: setpoints.append(m))
        time.sleep(0.3)
        arm = Pair(MappingConfig(scale=0.5, camera="endo"), node, "m1", "arm1", threading.Event())
        arm.on_slave_js(JointState(H, MH3F.joint_names, Q0), "")
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, True, "", 0), "")
        yield arm, setpoints, src
    src.move(home)  # the next test starts from the scene's endoscope pose


@pytest.mark.parametrize("roll_deg", [0.0, 90.0])
def test_master_right_moves_the_tip_right_in_the_picture(
    rig: tuple[Pair, list[JointSetpoint], MujocoSource], roll_deg: float
) -> None:
    arm, setpoints, src = rig
    src.move(_rot_about_view(src.pose(), roll_deg))  # the endoscope turned about its axis
    T_cam = src.pose()
    arm.strategy.on_camera_pose(_pose_msg(T_cam), "")
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    feed_master(arm, (0.02, 0.0, 0.0), clutch=True)  # 20 mm to the right of the surgeon's view
    assert wait_until(lambda: len(setpoints) >= 3, 3.0)
    tip0 = fk(np.array(Q0))[:3, 3]
    tip1 = fk(np.array(setpoints[-1].position))[:3, 3]
    assert np.linalg.norm(tip1 - tip0) == pytest.approx(0.01, abs=1e-4)  # scale 0.5
    d = _pixel(T_cam, src.intrinsics, tip1) - _pixel(T_cam, src.intrinsics, tip0)
    angle = math.degrees(math.atan2(d[1], d[0]))  # 0° = right in the image (v grows downward)
    print(f"camera rolled {roll_deg:g}°: tip moved {np.hypot(*d):.1f} px at {angle:+.1f}° in the image")
    assert abs(angle) <= 10.0
    # master "up" (+y of the view) → the tip goes up in the picture (v decreases)
    feed_master(arm, (0.02, 0.02, 0.0), clutch=True)
    assert wait_until(lambda: len(setpoints) >= 4, 3.0)
    tip2 = fk(np.array(setpoints[-1].position))[:3, 3]
    d2 = _pixel(T_cam, src.intrinsics, tip2) - _pixel(T_cam, src.intrinsics, tip1)
    assert abs(math.degrees(math.atan2(-d2[1], d2[0])) - 90.0) <= 10.0


def test_a_camera_turn_while_engaged_does_not_move_the_slave(
    rig: tuple[Pair, list[JointSetpoint], MujocoSource],
) -> None:
    arm, setpoints, src = rig
    T_cam = src.pose()
    arm.strategy.on_camera_pose(_pose_msg(T_cam), "")
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    feed_master(arm, (0.01, 0.005, 0.0), clutch=True)
    assert wait_until(lambda: len(setpoints) >= 3, 3.0)
    before = fk(np.array(setpoints[-1].position))[:3, 3]
    turned = _rot_about_view(T_cam, 90.0)
    src.move(turned)
    arm.strategy.on_camera_pose(_pose_msg(src.pose()), "")  # the camera turns 90° while following
    assert arm.following
    for _ in range(5):  # the master holds still: the slave must not move
        feed_master(arm, (0.01, 0.005, 0.0), clutch=True)
    assert wait_until(lambda: len(setpoints) >= 8, 3.0)
    after = fk(np.array(setpoints[-1].position))[:3, 3]
    moved_mm = float(np.linalg.norm(after - before)) * 1e3
    print(f"slave motion when the camera turned 90° while engaged: {moved_mm:.4f} mm")
    assert moved_mm < 1.0
    # and from here, master right is right in the turned picture
    feed_master(arm, (0.03, 0.005, 0.0), clutch=True)
    assert wait_until(lambda: len(setpoints) >= 9, 3.0)
    tip = fk(np.array(setpoints[-1].position))[:3, 3]
    d = _pixel(turned, src.intrinsics, tip) - _pixel(turned, src.intrinsics, after)
    assert abs(math.degrees(math.atan2(d[1], d[0]))) <= 10.0


def test_pose_message_round_trip() -> None:
    src = MujocoSource(robots.get("mh3f").scene, width=64, height=48)
    T = src.pose()
    np.testing.assert_allclose(pose_matrix(_pose_msg(T)), T, atol=1e-9)
    src.close()


def test_project_lands_where_the_camera_model_says_and_refuses_points_behind() -> None:
    """``project`` (the web console's predictive overlay): a point on the optical axis lands on
    the principal point, one to the right of it to the right; the right eye of a stereo pair sees
    a point shifted left by fx·baseline/z; a point behind the camera has no pixel."""
    from telesurg.shared.teleop.camera_frame import project

    T = np.eye(4)
    T[:3, :3] = _rot_about_view(np.eye(4), 30.0)[:3, :3]  # any orientation
    T[:3, 3] = (0.4, -0.1, 0.8)
    cam = _pose_msg(T)
    k = (300.0, 310.0, 160.0, 120.0)
    ahead = T[:3, :3] @ np.array([0.0, 0.0, 0.2]) + T[:3, 3]
    assert project(ahead, cam, *k) == pytest.approx((160.0, 120.0))
    right = T[:3, :3] @ np.array([0.01, -0.02, 0.2]) + T[:3, 3]
    assert project(right, cam, *k) == pytest.approx((160.0 + 300.0 * 0.05, 120.0 - 310.0 * 0.1))
    assert project(ahead, cam, *k, baseline_m=0.004) == pytest.approx((160.0 - 300.0 * 0.004 / 0.2, 120.0))
    behind = T[:3, :3] @ np.array([0.0, 0.0, -0.2]) + T[:3, 3]
    assert project(behind, cam, *k) is None
    np.testing.assert_allclose(project(right, cam, *k), _pixel(T, Intrinsics(*k), right))
