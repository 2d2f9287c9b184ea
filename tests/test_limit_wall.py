"""The slave's nearest joint limit as a wall in the master's frame (shared/teleop/limit_wall.py):
the master moved to the wall brings the joint to its margin; the guidance renders it
(shared/haptics/guidance.py's plane_force)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from telesurg.shared.haptics.guidance import Guidance, GuidanceSettings, plane_force
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.teleop.limit_wall import NO_WALL, limit_wall

LOWER, UPPER = np.array(MH3F.lower), np.array(MH3F.upper)
MARGIN = math.radians(5.0)


def _wall(q: np.ndarray, a: np.ndarray) -> tuple[tuple[float, float, float, float], np.ndarray]:
    t0 = fk(q, MH3F)

    def solve(p: np.ndarray) -> np.ndarray:
        t = t0.copy()
        t[:3, 3] = p
        return ik(t, q, MH3F)

    return limit_wall(solve, t0[:3, 3], q, LOWER, UPPER, MARGIN, a, np.zeros(3)), solve(t0[:3, 3])


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_the_master_at_the_wall_brings_the_nearest_joint_to_its_margin(scale: float) -> None:
    q = np.array([0.0, 0.2, 0.3, 0.0, math.radians(120.0 - 8.0), 0.0])  # J5 8° from its upper limit
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # master x → slave y
    a = scale * rot
    wall, _ = _wall(q, a)
    n, d = np.array(wall[:3]), wall[3]
    assert np.linalg.norm(n) == pytest.approx(1.0) and 0.0 < d < 0.05
    # move the master to the wall: the slave (through A = scale R) brings J5 to 5° from its limit
    t = fk(q, MH3F)
    t[:3, 3] += a @ (d * n)
    q_at = ik(t, q, MH3F)
    print(
        f"scale {scale}: wall {d * 1e3:.1f} mm along {np.round(n, 3)}; J5 there {math.degrees(q_at[4]):.2f}°"
    )
    assert math.degrees(UPPER[4] - q_at[4]) == pytest.approx(5.0, abs=0.3)
    # the wall is in the master's motion: half the scale, twice the master distance
    if scale == 0.5:
        assert d == pytest.approx(2 * _wall(q, rot)[0][3], rel=0.02)


def test_far_from_every_limit_there_is_no_wall() -> None:
    home = np.array([0.0, 0.2, 0.3, 0.0, -0.6, 0.0])
    wall, _ = _wall(home, 0.1 * np.eye(3))  # at 1:10 every limit is far in master motion
    assert wall == NO_WALL


def test_a_solver_with_no_answer_gives_no_wall() -> None:
    def solve(p: np.ndarray) -> np.ndarray:
        raise ValueError("out of reach")

    assert (
        limit_wall(solve, np.zeros(3), np.zeros(6), LOWER, UPPER, MARGIN, np.eye(3), np.zeros(3)) == NO_WALL
    )


def test_the_wall_pushes_only_from_beyond_it_and_more_as_it_goes_deeper() -> None:
    n = np.array([0.0, 0.0, 1.0])
    assert np.allclose(plane_force(np.array([0.0, 0.0, 0.009]), np.zeros(3), n, 0.01, 1000.0, 2.0), 0.0)
    f = plane_force(np.array([0.0, 0.0, 0.012]), np.array([0.0, 0.0, 0.1]), n, 0.01, 1000.0, 2.0)
    assert f == pytest.approx((0.0, 0.0, -(1000.0 * 0.002 + 2.0 * 0.1)))
    g = Guidance(GuidanceSettings())
    assert not g.on
    g.limit_wall = (n, 0.01)
    assert g.on and g.force(np.array([0.0, 0.0, 0.012]), np.zeros(3))[2] == pytest.approx(-2.0)


def test_the_mh3f_mapping_publishes_the_wall_while_following(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The MH3F's cartesian mapping (a real zenoh session) puts the wall in its teleop state while
    the pair follows near a joint limit, and none once it stops following."""
    import threading
    import time

    from helpers import feed_master
    from telesurg.services.launcher import free_port
    from telesurg.services.mapping import MappingConfig, Pair
    from telesurg.shared.bus import BusConfig, Node, open_session
    from telesurg.shared.messages import Header, JointState, OperatingState, TeleopState

    h = Header("test", 0, 0)
    q = (0.0, 0.2, 0.3, 0.0, -0.6, math.radians(360.0 - 8.0))  # the home tip, J6 8° from its limit
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    states: list[TeleopState] = []
    try:
        bus = BusConfig(connect=[ep])
        with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
            probe.subscribe(
                probe.keys.mapping("arm1", "teleop_state"), TeleopState, lambda m, k: states.append(m)
            )
            time.sleep(0.3)
            cfg = MappingConfig(mode="cartesian", model="mh3f", scale=1.0)
            cfg.validate()
            arm = Pair(cfg, node, "m1", "arm1", threading.Event())
            arm.on_slave_js(JointState(h, MH3F.joint_names, q), "")
            arm.on_slave_state(OperatingState(h, "PAUSED", "non_trocar", False, True, "", 0), "")
            feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
            for _ in range(3):
                feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
            assert arm.following
            # the subscriber's declaration may reach the mapping's session late on a loaded host:
            # publish until the probe hears the mapping, then start over with what follows
            deadline = time.monotonic() + 5.0
            while not states and time.monotonic() < deadline:
                arm._publish_state()
                time.sleep(0.05)
            time.sleep(0.2)
            states.clear()
            arm._publish_state()
            feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
            arm._publish_state()
            deadline = time.monotonic() + 3.0
            while not (states and states[-1].state != "ENABLED") and time.monotonic() < deadline:
                time.sleep(0.05)
    finally:
        router.close()  # type: ignore[no-untyped-call]
    engaged = [s for s in states if s.state == "ENABLED"]
    assert engaged, [s.state for s in states]
    n = np.array(engaged[-1].limit_wall[:3])
    print(f"teleop state while following: limit_wall {engaged[-1].limit_wall}")
    assert np.linalg.norm(n) == pytest.approx(1.0) and 0.0 < engaged[-1].limit_wall[3] < 0.05
    assert states[-1].state != "ENABLED" and states[-1].limit_wall == NO_WALL
