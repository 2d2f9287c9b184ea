"""The mapping's engage/clutch/IK-failure behaviour, driven in-process over real zenoh sessions."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from conftest import wait_until
from helpers import feed_master
from telesurg.services.mapping import MappingConfig, Pair
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import (
    CartesianPose,
    Command,
    Header,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
    TeleopState,
)
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
from telesurg.shared.teleop.master import master_point

Q0 = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
H = Header("test", 0, 0)


@pytest.fixture
def rig(endpoint: str) -> Iterator[tuple[Pair, list[JointSetpoint], list[SafetyEvent]]]:
    bus = BusConfig(connect=[endpoint])
    setpoints: list[JointSetpoint] = []
    events: list[SafetyEvent] = []
    with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
        probe.subscribe(probe.keys.slave("arm1", "servo_jp"), JointSetpoint, lambda m, k: setpoints.append(m))
        probe.subscribe(probe.keys.events(), SafetyEvent, lambda m, k: events.append(m))
        time.sleep(0.3)
        arm = Pair(MappingConfig(scale=0.5), node, "m1", "arm1", threading.Event())
        arm.on_slave_js(JointState(H, MH3F.joint_names, Q0), "")
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, True, "", 0), "")
        yield arm, setpoints, events


def test_engage_needs_press_edge_then_scaled_motion_without_jump(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, setpoints, _ = rig
    feed_master(arm, (0.3, 0.0, 0.0), clutch=True)  # pedal already down at start: not an engage
    assert not arm.following
    feed_master(arm, (0.3, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.3, 0.0, 0.0), clutch=True)  # press edge → engage
    assert arm.following
    feed_master(arm, (0.31, 0.0, 0.0), clutch=True)  # master +10 mm in x → slave +5 mm
    wait_until(lambda: len(setpoints) >= 4, 3.0)
    first, moved = np.array(setpoints[2].position), np.array(setpoints[3].position)
    tip0, tip1 = fk(np.array(Q0))[:3, 3], fk(moved)[:3, 3]
    assert np.allclose(first, Q0, atol=1e-9)  # engage: first setpoint is where the arm is
    np.testing.assert_allclose(tip1 - tip0, (0.005, 0.0, 0.0), atol=1e-9)
    assert [s.follow for s in setpoints] == [False, False, True, True]


def test_ik_failure_holds_last_setpoint_and_reports(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, setpoints, events = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    feed_master(arm, (2.0, 0.0, 0.0), clutch=True)  # slave target 1 m away: unreachable
    feed_master(arm, (2.0, 0.0, 0.0), clutch=True)
    wait_until(lambda: len(setpoints) >= 4, 3.0)
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
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]], state: OperatingState, why: str
) -> None:
    arm, _, events = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    arm.on_slave_state(state, "")
    assert not arm.following
    arm.on_slave_state(OperatingState(H, "PAUSED", state.control_mode, False, True, "", 2), "")
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)  # pedal still down: no re-engage
    assert not arm.following
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    deadline = time.monotonic() + 3
    while not any(why in e.text for e in events if e.kind == "disengage") and time.monotonic() < deadline:
        time.sleep(0.01)
    assert any(why in e.text for e in events if e.kind == "disengage"), [e.text for e in events]


def test_a_press_released_before_the_next_sample_does_not_engage(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    # polled buttons: a stalled loop may read a press and its release before mapping a sample
    arm, setpoints, _ = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    arm.on_buttons(MasterButtons(H, True, True), "")
    arm.on_buttons(MasterButtons(H, False, True), "")
    arm.on_master(CartesianPose(H, "master", (0.0, 0.0, 0.0)), "")
    arm.process()
    assert not arm.following
    wait_until(lambda: len(setpoints) >= 2, 3.0)
    assert [s.follow for s in setpoints] == [False, False]
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)  # the next press engages
    assert arm.following


def plas_pair(arm0: Pair) -> Pair:
    """A PLAS all-joints pair on ``arm0``'s node, its slave at zero, allowed to move, not following."""
    cfg = MappingConfig(mode="all_joints", model="plas")
    cfg.validate()
    arm = Pair(cfg, arm0.node, "m1", "arm1", threading.Event())
    names = arm.strategy.profile.joint_names
    arm.on_slave_js(JointState(H, names, tuple(0.0 for _ in names)), "")
    arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")
    return arm


def test_joint_space_mapping_follows_the_same_engage_rules(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    # the PLAS all-joints mapping shares the clutch rules (services/mapping/engage.py)
    arm = plas_pair(rig[0])

    def sample(clutch: bool | None) -> None:
        if clutch is not None:
            arm.on_buttons(MasterButtons(H, clutch, True), "")
        arm.on_master(JointState(H, tuple(f"m{i}" for i in range(6)), (0.0,) * 6), "")
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


def test_a_slave_that_stops_following_on_its_own_disengages_the_pair(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    """The slave held on a stale setpoint stream (its lease intact) and waits for a new press: the
    pair goes HOLDING naming why, not ENABLED while the arm stands still; the slave's own start
    (not yet following, just after the engage) does not."""
    from telesurg.shared.messages import now_ns

    arm = plas_pair(rig[0])

    def sample(clutch: bool) -> None:
        arm.on_buttons(MasterButtons(H, clutch, True), "")
        arm.on_master(JointState(H, tuple(f"m{i}" for i in range(6)), (0.0,) * 6), "")
        arm.process()

    def slave(follow: bool, reason: str, after_engage_ms: float) -> None:
        h = Header("slave_control", 1, arm.since_ns + int(after_engage_ms * 1e6))
        arm.on_slave_state(OperatingState(h, "ENABLED", "joint", follow, True, reason, 1), "")

    sample(False)
    sample(True)
    assert arm.following
    slave(False, "waiting for engage", 50)  # its start: armed, the first setpoint on its way
    slave(False, "waiting for a new engage (clutch)", 100)  # (inside the start's grace)
    assert arm.following
    slave(True, "", 120)
    slave(False, "setpoint stream stale", 2000)
    assert not arm.following and arm.state == "HOLDING"
    assert arm.reason == "slave not following: setpoint stream stale"
    sample(True)  # the pedal still down: no engage
    assert not arm.following
    sample(False)
    sample(True)  # a new press engages again
    assert arm.following and arm.since_ns <= now_ns()


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
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, _, _ = rig
    assert arm.strategy.on_command(Command(H, "arm1", "scale_up", ())).reason == "scale 0.5 → 0.7"
    assert arm.strategy.on_command(Command(H, "arm1", "scale_down", ())).reason == "scale 0.7 → 0.5"
    bad = arm.strategy.on_command(Command(H, "arm1", "set_scale", ("value=5",)))
    assert not bad.accepted and "(0, 2]" in bad.reason and arm.scale == 0.5
    assert not arm.strategy.on_command(Command(H, "arm2", "scale_up", ())).accepted


def states_seen(probe: Node, arm: str) -> tuple[list[TeleopState], Callable[[], list[str]]]:
    got: list[TeleopState] = []
    probe.subscribe(probe.keys.mapping(arm, "teleop_state"), TeleopState, lambda m, k: got.append(m))

    def states() -> list[str]:
        return [m.state for i, m in enumerate(got) if i == 0 or m.state != got[i - 1].state]

    return got, states


def test_the_teleop_state_machine_is_published_on_every_change(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]], endpoint: str
) -> None:
    arm, _, _ = rig
    with Node(BusConfig(connect=[endpoint]), "t", "probe2") as probe:
        got, states = states_seen(probe, "arm1")
        # the probe's subscription is in place once a periodic state reaches it
        assert wait_until(lambda: arm.publish_state() is None and bool(got)), "no teleop state"

        def press(clutch: bool) -> None:
            arm.on_slave_js(JointState(H, MH3F.joint_names, Q0), "")  # fresh slave joints
            feed_master(arm, (0.0, 0.0, 0.0), clutch)

        press(True)  # pedal down at start
        assert arm.state == "HOLDING" and "at start" in arm.reason
        press(False)
        assert arm.state == "IDLE"
        arm.on_buttons(MasterButtons(H, True, True), "")
        assert arm.state == "ENGAGING"  # the engage is tried at the next master sample
        arm.on_master(CartesianPose(H, "master", (0.0, 0.0, 0.0)), "")
        arm.process()
        assert arm.state == "ENABLED" and arm.following
        # a watchdog hold: the slave loses its lease → HOLDING, a new press needed
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, False, "lease expired", 1), "")
        assert (arm.state, arm.previous) == ("HOLDING", "ENABLED") and "lease expired" in arm.reason
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, True, "", 1), "")
        press(True)
        assert arm.state == "HOLDING"  # lease back, pedal still down: still holding
        press(False)
        assert arm.state == "IDLE"
        press(True)
        assert arm.state == "ENABLED"
        press(False)  # the operator's release
        assert (arm.state, arm.reason) == ("IDLE", "clutch released")
        # not allowed to move while released: DISABLED with the reason; a press is refused
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, False, "estop", 2), "")
        arm.check_timeouts()
        assert arm.state == "DISABLED" and "estop" in arm.reason
        since = arm.since_ns  # a new reason within the state: published, entered at the same time
        arm.on_slave_state(OperatingState(H, "PAUSED", "non_trocar", False, False, "lease expired", 2), "")
        arm.check_timeouts()
        assert (arm.state, arm.previous, arm.since_ns) == ("DISABLED", "IDLE", since), arm.reason
        assert "lease expired" in arm.reason
        assert wait_until(lambda: "lease expired" in got[-1].reason and got[-1].since_ns == since), got[-1]
        press(True)
        assert arm.state == "HOLDING" and arm.reason.startswith("engage refused")
        want = ["HOLDING", "IDLE", "ENGAGING", "ENABLED", "HOLDING", "IDLE", "ENGAGING", "ENABLED", "IDLE"]
        want += ["DISABLED", "ENGAGING", "HOLDING"]
        assert wait_until(lambda: states()[-len(want) :] == want), states()
        last = got[-1]
        assert (last.master, last.slave, last.previous, last.mode) == ("m1", "arm1", "ENGAGING", "cartesian")
        assert last.scale == 0.5 and last.safety_scale == 1.0 and last.since_ns > 0


def test_a_late_joiner_gets_the_current_teleop_state_at_once(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]], endpoint: str
) -> None:
    # nobody calls publish_state here (the 10 Hz re-send): the last publication is before the
    # joiner subscribes, so only the mapping's answer to the joiner's query can bring the state
    # (the 0.5 s figure is checked against real processes in tests/test_teleop_state.py)
    arm, _, _ = rig
    arm.on_slave_js(JointState(H, MH3F.joint_names, Q0), "")  # fresh slave joints
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.state == "ENABLED"
    arm.strategy.on_command(Command(H, "arm1", "set_scale", ("value=0.3",)))
    with Node(BusConfig(connect=[endpoint]), "t", "late") as late:
        got: list[TeleopState] = []
        late.subscribe(
            late.keys.mapping("arm1", "teleop_state"),
            TeleopState,
            lambda m, k: got.append(m),
            sources=["mapping"],
            latest=True,
        )
        assert wait_until(lambda: bool(got)), "no teleop state: the query was not answered"
        assert got[0].state == "ENABLED" and got[0].scale == 0.3


def test_a_joint_space_mapping_publishes_the_controlled_point_of_its_setpoint(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]], endpoint: str
) -> None:
    # setpoint_cp of the PLAS all-joints mapping: the profile's tip of what servo_jp commands, in
    # the frame of the slave's measured_cp (the demo report's tracking reference)
    arm0, setpoints, _ = rig
    cfg = MappingConfig(mode="all_joints", model="plas")
    with Node(BusConfig(connect=[endpoint]), "t", "probe2") as probe:
        targets: list[CartesianPose] = []
        probe.subscribe(
            probe.keys.slave("arm1", "setpoint_cp"), CartesianPose, lambda m, k: targets.append(m)
        )
        got, _ = states_seen(probe, "arm1")  # declared after setpoint_cp: in place once one arrives
        assert wait_until(lambda: arm0.publish_state() is None and bool(got)), "probe not subscribed"
        arm = Pair(cfg, arm0.node, "m1", "arm1", threading.Event())
        names = arm.strategy.profile.joint_names
        q0 = (0.0, 0.1, 0.2, 0.3, 0.0, 0.0)
        arm.on_slave_js(JointState(H, names, q0), "")
        arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")

        def sample(clutch: bool, qm: float) -> None:
            arm.on_slave_js(JointState(H, names, q0), "")  # fresh slave joints
            arm.on_buttons(MasterButtons(H, clutch, True), "")
            arm.on_master(JointState(H, tuple(f"m{i}" for i in range(6)), (0.0, qm, 0.0, 0.0, 0.0, 0.0)), "")
            arm.process()

        sample(False, 0.0)
        sample(True, 0.0)
        assert arm.following
        time.sleep(0.02)  # one target period (target_hz = 100)
        sample(True, 0.05)
        assert wait_until(lambda: len(targets) >= 2), targets
        assert wait_until(lambda: any(s.follow and s.position != q0 for s in setpoints)), setpoints
        last = [s for s in setpoints if s.follow][-1]
        tip = arm.strategy.profile.tip(np.array(last.position))
        assert targets[-1].frame == "base"  # the frame of the slave's measured_cp
        np.testing.assert_allclose(targets[-1].position, tip, atol=1e-12)
        assert np.linalg.norm(np.subtract(targets[-1].position, targets[0].position)) > 1e-4  # it moved


def test_the_jaws_follow_the_grip_only_once_it_has_come_to_them_after_an_engage(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    """An engage never opens the jaws on what they hold nor snaps them shut: the setpoints carry
    no grip (-1, the jaws keep theirs) until the master's grip comes within 0.1 of the jaws', then
    the grip; not engaged, none; an arm without jaws, none."""
    arm, setpoints, events = rig
    arm = plas_pair(arm)

    def slave_jaws(grip: float) -> None:
        arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0, grip=grip), "")

    def sample(clutch: bool, grip: float) -> float:
        arm.on_buttons(MasterButtons(H, clutch, True, grip), "")
        arm.on_master(JointState(H, tuple(f"m{i}" for i in range(6)), (0.0,) * 6), "")
        arm.process()
        wait_until(lambda: len(setpoints) >= n + 1, 3.0)
        return setpoints[-1].grip

    n = 0
    slave_jaws(1.0)  # the jaws hold something (closed)
    assert sample(False, 0.0) == -1.0  # not engaged: none
    n = len(setpoints)
    assert sample(True, 0.0) == -1.0 and arm.following  # engaged, the grip open: the jaws stay shut
    n = len(setpoints)
    assert sample(True, 0.5) == -1.0
    n = len(setpoints)
    assert sample(True, 0.95) == 0.95  # came to the jaws' closure: followed from now on
    n = len(setpoints)
    assert sample(True, 0.2) == 0.2
    assert wait_until(lambda: any(e.kind == "grip" for e in events), 2.0)
    n = len(setpoints)
    slave_jaws(-1.0)  # an arm without jaws: never a grip
    assert sample(True, 0.2) == -1.0
