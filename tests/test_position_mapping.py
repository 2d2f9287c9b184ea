"""The generic position mapping (mode "position"): any registered arm, driven by damped least squares
on its registry pose/Jacobian, with the mapping's clutch rules, joint-limit clamping and step check."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import wait_until
from helpers import feed_master
from telesurg.services.launcher import free_port
from telesurg.services.mapping import MappingConfig, Pair, position
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.errors import ConfigError, KinematicsError
from telesurg.shared.kinematics import solve_position
from telesurg.shared.messages import (
    CartesianPose,
    Command,
    Header,
    JointSetpoint,
    JointState,
    MasterButtons,
    OperatingState,
    SafetyEvent,
)
from telesurg.shared.robots import MODELS, arm_profile, arms_of
from telesurg.shared.robots.plas import tasks as plas_tasks

H = Header("test", 0, 0)


def test_mapping_mode_must_fit_the_robot() -> None:
    with pytest.raises(ConfigError, match="mode 'cartesian' does not fit robot model 'plas'; modes that fit"):
        MappingConfig(mode="cartesian", model="plas").validate()
    with pytest.raises(ConfigError, match="mode 'all_joints' does not fit robot model 'vip'"):
        MappingConfig(mode="all_joints", model="vip", pairs=["m1:arm1"]).validate()
    with pytest.raises(ConfigError, match="robot model 'ur5' unknown; valid: mh3f, plas"):
        MappingConfig(model="ur5").validate()
    with pytest.raises(ConfigError, match="no arm 'arm3'"):
        MappingConfig(mode="position", model="plas", pairs=["m1:arm3"]).validate()
    for model in MODELS:
        MappingConfig(mode="position", model=model).validate()


@pytest.mark.parametrize("model", MODELS)
def test_solve_position_reaches_nearby_targets(model: str) -> None:
    rng = np.random.default_rng(3)
    for p in arms_of(model):
        lo, hi = np.array(p.lower), np.array(p.upper)
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        for _ in range(10):
            q0 = mid + 0.6 * half * rng.uniform(-1, 1, len(lo))
            q_goal = np.clip(q0 + 0.05 * half * rng.uniform(-1, 1, len(lo)), lo, hi)
            target = p.tip(q_goal)
            sol = solve_position(p, q0, target, lo, hi, iterations=20)
            assert sol.error < 1e-6, (p.arm, sol)
            assert np.all(sol.q >= lo) and np.all(sol.q <= hi)


def test_solve_position_clamps_at_the_joint_limits() -> None:
    p = arm_profile("vip", "arm1")
    lo, hi = np.array(p.lower), np.array(p.upper)
    q0 = np.array(p.home)
    far = p.tip(q0) + np.array([0.0, 0.0, 1.0])  # 1 m up the port axis: q3 runs into its limit
    sol = solve_position(p, q0, far, lo, hi, iterations=50)
    assert np.all(sol.q >= lo) and np.all(sol.q <= hi)
    assert 2 in sol.clamped  # q3, the insertion slide
    assert sol.error > 0.5


@contextlib.contextmanager
def _rig(
    cfg: MappingConfig, slave: str = "arm1", q0: tuple[float, ...] | None = None
) -> Iterator[tuple[Pair, list[JointSetpoint], list[SafetyEvent]]]:
    """One mapping pair ``m1:<slave>`` on a router of its own, the slave at ``q0`` (its home) and
    allowed to move; with the setpoints and events it sends."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    bus = BusConfig(connect=[ep])
    setpoints: list[JointSetpoint] = []
    events: list[SafetyEvent] = []
    try:
        with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
            probe.subscribe(
                probe.keys.slave(slave, "servo_jp"), JointSetpoint, lambda m, k: setpoints.append(m)
            )
            probe.subscribe(probe.keys.events(), SafetyEvent, lambda m, k: events.append(m))
            time.sleep(0.3)
            cfg.validate()
            arm = Pair(cfg, node, "m1", slave, threading.Event())
            names = arm.strategy.profile.joint_names
            arm.on_slave_js(JointState(H, names, q0 or arm.strategy.profile.home), "")
            arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")
            yield arm, setpoints, events
    finally:
        router.close()  # type: ignore[no-untyped-call]


@pytest.fixture
def rig() -> Iterator[tuple[Pair, list[JointSetpoint], list[SafetyEvent]]]:
    with _rig(MappingConfig(mode="position", model="vip", scale=0.5, max_joint_step_rad=0.2)) as r:
        yield r


def test_position_mapping_engages_on_a_press_and_moves_the_tip_by_the_scaled_increment(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, setpoints, events = rig
    home = np.array(arm.strategy.profile.home)
    feed_master(arm, (0.1, 0.0, 0.0), clutch=True)  # pedal already down at start: not an engage
    assert not arm.following
    feed_master(arm, (0.1, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.1, 0.0, 0.0), clutch=True)  # press edge → engage, anchored here
    assert arm.following
    tip0 = arm.strategy.profile.tip(home)
    for i in range(1, 11):  # master +1 mm in x and -0.5 mm in z per sample
        feed_master(arm, (0.1 + 0.001 * i, 0.0, -0.0005 * i), clutch=True)
    wait_until(lambda: len(setpoints) >= 13, 3.0)
    assert [s.follow for s in setpoints[:3]] == [False, False, True]
    np.testing.assert_allclose(setpoints[2].position, home, atol=1e-12)  # no jump at engage
    q = np.array(setpoints[12].position)
    np.testing.assert_allclose(arm.strategy.profile.tip(q) - tip0, (0.005, 0.0, -0.0025), atol=1e-5)
    feed_master(arm, (0.2, 0.0, 0.0), clutch=False)  # release: the slave holds where it is
    assert not arm.following
    wait_until(lambda: len(events) >= 2, 3.0)
    assert [e.kind for e in events][:2] == ["engage", "disengage"]


def test_position_mapping_holds_on_a_large_joint_step(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, _, events = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.following
    q_before = arm.strategy.q_cmd.copy() if arm.strategy.q_cmd is not None else None
    feed_master(arm, (0.2, 0.0, 0.0), clutch=True)  # 100 mm of slave motion in one sample
    assert arm.ik_failures == 1
    assert arm.strategy.q_cmd is not None and q_before is not None
    np.testing.assert_allclose(arm.strategy.q_cmd, q_before)  # held the last valid setpoint
    deadline = time.monotonic() + 3
    while not any(e.kind == "ik_failure" for e in events) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert any(e.kind == "ik_failure" and "joint step" in e.text for e in events)


def test_operator_scale_commands_rescale_the_motion_without_a_jump(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]],
) -> None:
    arm, _, _ = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    feed_master(arm, (0.004, 0.0, 0.0), clutch=True)  # anchor at 0, then +4 mm → +2 mm at scale 0.5
    assert arm.strategy.q_cmd is not None
    tip_a = arm.strategy.profile.tip(arm.strategy.q_cmd)
    r = arm.strategy.on_command(Command(H, "arm1", "scale_up", ()))
    assert r.accepted and r.reason == "scale 0.5 → 0.7 while following (re-anchored)"
    feed_master(arm, (0.004, 0.0, 0.0), clutch=True)  # the same master point: no jump at the new scale
    np.testing.assert_allclose(arm.strategy.profile.tip(arm.strategy.q_cmd), tip_a, atol=1e-6)
    feed_master(arm, (0.008, 0.0, 0.0), clutch=True)  # +4 mm more → +2.8 mm at 0.7
    np.testing.assert_allclose(
        arm.strategy.profile.tip(arm.strategy.q_cmd) - tip_a, (0.0028, 0.0, 0.0), atol=1e-6
    )
    assert not arm.strategy.on_command(Command(H, "arm1", "set_scale", ("value=5",))).accepted
    assert not arm.strategy.on_command(Command(H, "arm2", "state", ())).accepted
    assert "scale 0.7" in arm.strategy.on_command(Command(H, "arm1", "state", ())).reason


def test_a_target_that_stays_out_of_a_step_disengages_and_a_new_press_goes_on_from_there(
    rig: tuple[Pair, list[JointSetpoint], list[SafetyEvent]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The master ran ahead while its samples stalled: after holding ``STUCK_S`` the mapping lets
    go (the operator sees HOLDING and why), and the next press re-anchors where the slave stands,
    so it does not jump to the far target."""
    monkeypatch.setattr(position, "STUCK_S", 0.05)
    arm, _, events = rig
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
    assert arm.strategy.q_cmd is not None
    q_held = arm.strategy.q_cmd.copy()
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:  # the master stays 100 mm (slave) away
        feed_master(arm, (0.2, 0.0, 0.0), clutch=True)
        time.sleep(0.01)
    assert not arm.following
    assert arm.state == "HOLDING" and "press again" in arm.reason, arm.reason
    np.testing.assert_allclose(arm.strategy.q_cmd, q_held)  # it never moved toward the far target
    wait_until(lambda: any(e.kind == "disengage" and "out of reach" in e.text for e in events), 3.0)
    arm.on_slave_js(JointState(H, arm.strategy.profile.joint_names, tuple(q_held)), "")  # still there
    feed_master(arm, (0.2, 0.0, 0.0), clutch=False)
    feed_master(arm, (0.2, 0.0, 0.0), clutch=True)  # a new press, where the hand is now
    assert arm.following
    feed_master(arm, (0.202, 0.0, 0.0), clutch=True)  # +2 mm → +1 mm from where the slave stands
    tip = arm.strategy.profile.tip(arm.strategy.q_cmd)
    np.testing.assert_allclose(tip - arm.strategy.profile.tip(q_held), (0.001, 0.0, 0.0), atol=1e-5)


def test_solve_position_keeps_the_tilt_and_turns_only_about_the_vertical() -> None:
    """``keep_up``: the PLAS's forceps reaches targets 30 mm away with its tilt from the vertical
    unchanged (to 0.01°) while the free solve tilts it by degrees; a bad ``keep_up`` is refused."""
    p = arm_profile("plas", "arm2")
    lo, hi = np.array(p.lower), np.array(p.upper)
    q0 = np.array(plas_tasks.Q_ARM2)
    R0 = p.pose(q0)[:3, :3]
    up = R0.T @ np.array([0.0, 0.0, 1.0])
    free_tilts = []
    for d in ((0.0, 0.03, 0.0), (0.0, 0.0, -0.01), (0.01, 0.01, 0.01)):
        target = p.tip(q0) + np.array(d)
        kept = solve_position(p, q0, target, lo, hi, iterations=30, keep_up=up)
        assert kept.error < 1e-5 and kept.tilt_error < np.radians(0.01), (d, kept)
        R = p.pose(kept.q)[:3, :3]
        np.testing.assert_allclose(R @ up, (0.0, 0.0, 1.0), atol=2e-4)  # up is still up
        free = solve_position(p, q0, target, lo, hi, iterations=30)
        free_tilts.append(np.degrees(np.arccos(np.clip((p.pose(free.q)[:3, :3] @ up)[2], -1, 1))))
    assert max(free_tilts) > 2.0, free_tilts  # without it, the same reaches tilt the forceps
    with pytest.raises(KinematicsError, match="keep_up"):
        solve_position(p, q0, p.tip(q0), lo, hi, keep_up=(0.0, 0.0, 0.0))


def test_keep_tilt_carries_the_plas_forceps_without_tilting_it() -> None:
    """The PLAS pair in position mode with ``keep_tilt``: a 60 mm master stroke (30 mm at the tip)
    keeps the forceps' tilt from the engage while the free mapping's tilts it."""
    tilts = {}
    for keep in (True, False):
        cfg = MappingConfig(mode="position", model="plas", pairs=["m1:arm2"], scale=0.5, keep_tilt=keep)
        with _rig(cfg, "arm2", plas_tasks.Q_ARM2) as (arm, _, _):
            prof = arm.strategy.profile
            up = prof.pose(plas_tasks.Q_ARM2)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
            feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
            worst = 0.0
            for i in range(1, 121):  # 0.5 mm of master per sample along y
                feed_master(arm, (0.0, 0.0005 * i, 0.0), clutch=True)
                assert arm.strategy.q_cmd is not None
                R = prof.pose(arm.strategy.q_cmd)[:3, :3]
                worst = max(worst, float(np.degrees(np.arccos(np.clip((R @ up)[2], -1.0, 1.0)))))
            assert arm.ik_failures == 0
            moved = prof.tip(arm.strategy.q_cmd) - prof.tip(plas_tasks.Q_ARM2)
            assert np.linalg.norm(moved) == pytest.approx(0.03, abs=1e-4)
            tilts[keep] = worst
    assert tilts[True] < 0.05 and tilts[False] > 2.0, tilts


def test_a_hand_faster_than_the_arm_is_followed_at_the_arm_s_pace() -> None:
    """A 40 mm master stroke in 40 ms (0.5 m/s at the PLAS's tip, ten times its slide's 50 mm/s):
    the setpoints move no joint faster than 90 % of its speed limit (by the samples' stamps, as the
    watchdog judges them: no "jump" hold), and the tip gets to the target once the hand stops."""
    cfg = MappingConfig(mode="position", model="plas", pairs=["m1:arm2"], scale=0.5, keep_tilt=True)
    with _rig(cfg, "arm2", plas_tasks.Q_ARM2) as (arm, _, _):
        prof = arm.strategy.profile
        vmax = np.array(prof.max_velocity)

        def feed(i: int, p: tuple[float, float, float], clutch: bool = True) -> None:
            h = Header("test", i, 1_000_000_000 + i * 4_000_000)  # a sample every 4 ms
            arm.on_buttons(MasterButtons(h, clutch, True), "")
            arm.on_master(CartesianPose(h, "master", p), "")
            arm.process()

        feed(0, (0.0, 0.0, 0.0), clutch=False)
        feed(1, (0.0, 0.0, 0.0))
        assert arm.strategy.q_cmd is not None
        q_prev = arm.strategy.q_cmd.copy()
        tip0 = prof.tip(q_prev)
        worst = 0.0
        for i in range(2, 400):  # 40 mm down in 10 samples, then the hand holds still
            feed(i, (0.0, 0.0, -0.004 * min(i - 1, 10)))
            q = arm.strategy.q_cmd
            assert q is not None
            worst = max(worst, float(np.max(np.abs(q - q_prev) / (vmax * 0.004))))
            q_prev = q.copy()
        assert worst <= 0.9 + 1e-9, worst
        moved = prof.tip(arm.strategy.q_cmd) - tip0
        np.testing.assert_allclose(moved, (0.0, 0.0, -0.02), atol=1e-4)  # 40 mm × 0.5, at last
        assert arm.ik_failures == 0
