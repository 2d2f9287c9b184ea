"""The mapping's engage/clutch/IK-failure behaviour, driven in-process over real zenoh sessions."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from telesurg.services.launcher import free_port
from telesurg.services.mapping import ArmMapping, MappingConfig, master_point
from telesurg.services.mapping.joints import AllJointsMapping
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.errors import ConfigError
from telesurg.shared.kinematics.mh3f import MH3F, fk
from telesurg.shared.messages import (
    CartesianPose,
    Header,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
)

Q0 = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
H = Header("test", 0, 0)


@pytest.fixture
def rig() -> Iterator[tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    bus = BusConfig(connect=[ep])
    setpoints: list[JointSetpoint] = []
    events: list[SafetyEvent] = []
    try:
        with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
            probe.subscribe(
                probe.keys.slave("arm1", "servo_jp"), JointSetpoint, lambda m, k: setpoints.append(m)
            )
            probe.subscribe(probe.keys.events(), SafetyEvent, lambda m, k: events.append(m))
            time.sleep(0.3)
            arm = ArmMapping(MappingConfig(scale=0.5), node, "m1", "arm1", threading.Event())
            arm.on_slave_js(JointState(H, MH3F.joint_names, Q0), "")
            arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, True, "", 0), "")
            yield arm, setpoints, events
    finally:
        router.close()  # type: ignore[no-untyped-call]


def feed(arm: ArmMapping, p: tuple[float, float, float], clutch: bool) -> None:
    arm.on_buttons(MasterButtons(H, clutch, True), "")
    arm.on_master_pose(CartesianPose(H, "master", p), "")
    arm.process()


def settle(n: int, store: list[JointSetpoint]) -> None:
    deadline = time.monotonic() + 3
    while len(store) < n and time.monotonic() < deadline:
        time.sleep(0.01)


def test_engage_needs_press_edge_then_scaled_motion_without_jump(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, setpoints, _ = rig
    feed(arm, (0.3, 0.0, 0.0), clutch=True)  # pedal already down at start: not an engage
    assert not arm.following
    feed(arm, (0.3, 0.0, 0.0), clutch=False)
    feed(arm, (0.3, 0.0, 0.0), clutch=True)  # press edge → engage
    assert arm.following
    feed(arm, (0.31, 0.0, 0.0), clutch=True)  # master +10 mm in x → slave +5 mm
    settle(4, setpoints)
    first, moved = np.array(setpoints[2].position), np.array(setpoints[3].position)
    tip0, tip1 = fk(np.array(Q0))[:3, 3], fk(moved)[:3, 3]
    assert np.allclose(first, Q0, atol=1e-9)  # engage: first setpoint is where the arm is
    np.testing.assert_allclose(tip1 - tip0, (0.005, 0.0, 0.0), atol=1e-9)
    assert [s.follow for s in setpoints] == [False, False, True, True]


def test_ik_failure_holds_last_setpoint_and_reports(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, setpoints, events = rig
    feed(arm, (0.0, 0.0, 0.0), clutch=False)
    feed(arm, (0.0, 0.0, 0.0), clutch=True)
    feed(arm, (2.0, 0.0, 0.0), clutch=True)  # slave target 1 m away: unreachable
    feed(arm, (2.0, 0.0, 0.0), clutch=True)
    settle(4, setpoints)
    assert all(np.allclose(s.position, Q0) for s in setpoints[1:])
    assert arm.ik_failures == 2
    deadline = time.monotonic() + 3
    while not any(e.kind == "ik_failure" for e in events) and time.monotonic() < deadline:
        time.sleep(0.01)
    failures = [e for e in events if e.kind == "ik_failure"]
    assert len(failures) == 1 and "holding last valid setpoint" in failures[0].text


@pytest.mark.parametrize(
    ("state", "why"),
    [
        (OperatingState(H, "PAUSED", "non_trocar", False, False, "lease expired", 1), "slave holding"),
        (OperatingState(H, "ENABLED", "transitional", True, True, "", 1), "non_trocar → transitional"),
    ],
    ids=["slave holding", "control mode change"],
)
def test_a_slave_hold_or_mode_change_disengages_and_needs_a_new_press(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]], state: OperatingState, why: str
) -> None:
    arm, _, events = rig
    feed(arm, (0.0, 0.0, 0.0), clutch=False)
    feed(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    arm.on_slave_state(state, "")
    assert not arm.following
    arm.on_slave_state(OperatingState(H, "PAUSED", state.control_mode, False, True, "", 2), "")
    feed(arm, (0.0, 0.0, 0.0), clutch=True)  # pedal still down: no re-engage
    assert not arm.following
    feed(arm, (0.0, 0.0, 0.0), clutch=False)
    feed(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    deadline = time.monotonic() + 3
    while not any(why in e.text for e in events if e.kind == "disengage") and time.monotonic() < deadline:
        time.sleep(0.01)
    assert any(why in e.text for e in events if e.kind == "disengage"), [e.text for e in events]


def test_a_press_released_before_the_next_sample_does_not_engage(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    # polled buttons: a stalled loop may read a press and its release before mapping a sample
    arm, setpoints, _ = rig
    feed(arm, (0.0, 0.0, 0.0), clutch=False)
    arm.on_buttons(MasterButtons(H, True, True), "")
    arm.on_buttons(MasterButtons(H, False, True), "")
    arm.on_master_pose(CartesianPose(H, "master", (0.0, 0.0, 0.0)), "")
    arm.process()
    assert not arm.following
    settle(2, setpoints)
    assert [s.follow for s in setpoints] == [False, False]
    feed(arm, (0.0, 0.0, 0.0), clutch=True)  # the next press engages
    assert arm.following


def test_joint_space_mapping_follows_the_same_engage_rules(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    # the PLAS all-joints mapping shares the clutch rules (services/mapping/engage.py)
    arm0, _, _ = rig
    cfg = MappingConfig(mode="all_joints", model="plas")
    cfg.validate()
    arm = AllJointsMapping(cfg, arm0.node, "m1", "arm1", threading.Event())
    names = arm.profile.joint_names
    arm.on_slave_js(JointState(H, names, tuple(0.0 for _ in names)), "")
    arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")

    def sample(clutch: bool | None) -> None:
        if clutch is not None:
            arm.on_buttons(MasterButtons(H, clutch, True), "")
        arm.on_master_js(JointState(H, tuple(f"m{i}" for i in range(6)), (0.0,) * 6), "")
        arm.process()

    sample(True)  # pedal down at start: not an engage
    assert not arm.following
    sample(False)
    arm.on_buttons(MasterButtons(H, True, True), "")  # a press and its release in one poll
    arm.on_buttons(MasterButtons(H, False, True), "")
    sample(None)
    assert not arm.following
    sample(True)
    assert arm.following
    arm.on_slave_state(OperatingState(H, "ENABLED", "joint", True, False, "lease expired", 1), "")
    assert not arm.following
    arm.on_slave_state(OperatingState(H, "ENABLED", "joint", False, True, "", 2), "")
    sample(True)  # pedal still down: no re-engage
    assert not arm.following
    sample(False)
    sample(True)
    assert arm.following


def test_virtual_trocar_master_maps_the_dummy_tip_with_the_fulcrum_effect() -> None:
    cfg = MappingConfig(
        master_mode="virtual_trocar", virtual_trocar_mm=(0.0, 0.0, 0.0), dummy_forceps_mm=200.0
    )
    cfg.validate()
    h0 = (0.0, 0.0, 0.1)  # handle 100 mm above the virtual trocar: dummy tip 100 mm below it
    np.testing.assert_allclose(master_point(cfg, h0), (0.0, 0.0, -0.1), atol=1e-12)
    side = master_point(cfg, (0.01, 0.0, 0.1)) - master_point(cfg, h0)
    assert side[0] < -0.009  # handle +10 mm sideways → tip ~10 mm the other way (1:1 at mid-shaft)
    deeper = master_point(cfg, (0.0, 0.0, 0.09)) - master_point(cfg, h0)
    np.testing.assert_allclose(deeper, (0.0, 0.0, -0.01), atol=1e-12)  # pushed in → tip deeper
    pen = MappingConfig()
    np.testing.assert_allclose(master_point(pen, (0.01, 0.0, 0.1)), (0.01, 0.0, 0.1))
    with pytest.raises(ConfigError, match="master_mode"):
        MappingConfig(master_mode="joystick").validate()


def test_operator_scale_commands_step_and_refuse_clearly(
    rig: tuple[ArmMapping, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    from telesurg.shared.messages import Command

    arm, _, _ = rig
    assert arm.on_command(Command(H, "arm1", "scale_up", ())).reason == "scale 0.5 → 0.7"
    assert arm.on_command(Command(H, "arm1", "scale_down", ())).reason == "scale 0.7 → 0.5"
    bad = arm.on_command(Command(H, "arm1", "set_scale", ("value=5",)))
    assert not bad.accepted and "(0, 2]" in bad.reason and arm.scale == 0.5
    assert not arm.on_command(Command(H, "arm2", "scale_up", ())).accepted
