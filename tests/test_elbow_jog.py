"""The elbow (null-space) jog of the VIP arms (issue #20, acceptance 4), below the bus.

* ``shared/kinematics/elbow.py``: moving the elbow keeps the wrist where it is, the elbow leaves
  the VIP line, a joint limit refuses a move and names the joint, and the mid-range search raises
  the smallest joint margin.
* ``services/slave_control/elbow_jog.py`` through an :class:`ArmCore` (no bus, no process): the
  commanded joints move the elbow at the jog speed while the wrist of every commanded pose stays
  put, only under a valid lease (a lost lease stops the jog for good), with clear refusals.
* The Fig. 9 case of Jang 2014 in kinematics: the wrist stalls on its way to the target under the
  paper's VIP; the mid-range elbow search at the stall and ``select_vip`` of the result make the
  target reachable (what the process test ``test_vip_realloc_process.py`` does through the
  services).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import ArmCore
from telesurg.services.slave_control.control import Lease
from telesurg.shared.errors import IKError
from telesurg.shared.kinematics.elbow import (
    elbow_move,
    limit_margin,
    midrange_direction,
    off_line,
    tangent,
)
from telesurg.shared.messages import Command, Header
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.api import ArmReading
from telesurg.shared.robots.vip import kinematics as vip
from telesurg.shared.robots.vip.elbow_jog import ElbowJog
from telesurg.tools.experiment.jang import FIG9_TARGET_OFFSET_M, paper_vip

G = vip.VIP_ARM1
PROFILE = arm_profile("vip", "arm1")
CHAIN = PROFILE.elbow
assert CHAIN is not None


def _stall() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(target T, paper VIP V, stall wrist P, joints there): the last wrist on the straight way
    from the initial wrist to the Fig. 9 target that VIP IK with the paper's VIP reaches."""
    w0 = vip.fk(G.home_q, G).wrist
    T = w0 + np.array(FIG9_TARGET_OFFSET_M)
    V = paper_vip(G)
    last = None
    for s in np.linspace(0.0, 1.0, 1201):
        try:
            last = (w0 + s * (T - w0), vip.vip_ik(w0 + s * (T - w0), V, G))
        except vip.JointLimitError:
            break
    assert last is not None
    return T, V, last[0], last[1]


def test_elbow_move_keeps_the_wrist_and_leaves_the_vip_line() -> None:
    q = G.home_q
    W = vip.fk(q, G).wrist
    V = vip.select_vip(q, 0.05, G)
    assert off_line(vip.fk(q, G).elbow, W, V) < 1e-9
    for axis in range(3):
        d = np.zeros(3)
        d[axis] = 1.0
        t = tangent(CHAIN, q, W, d)
        q2 = elbow_move(CHAIN, q, W, 0.005 * t)
        pose = vip.fk(q2, G)
        assert np.linalg.norm(pose.wrist - W) < 1e-9  # the wrist stays
        assert abs(np.linalg.norm(pose.elbow - W) - G.forearm) < 1e-9
        moved = np.linalg.norm(pose.elbow - vip.fk(q, G).elbow)
        assert 0.0049 < moved < 0.0051  # a 5 mm move perpendicular to the forearm
        assert off_line(pose.elbow, W, V) > 0.004  # off the VIP line
    along = vip.fk(q, G).elbow - W
    with pytest.raises(ValueError, match="along the forearm"):
        tangent(CHAIN, q, W, along)


def test_a_joint_limit_refuses_an_elbow_move_and_names_the_joint() -> None:
    _, _, P, q = _stall()  # q2 on its 50° limit
    with pytest.raises(IKError, match="q2"):
        elbow_move(CHAIN, q, P, 0.0005 * tangent(CHAIN, q, P, np.array([-1.0, 0.0, 0.0])))


def test_fig9_midrange_elbow_then_reallocation_reaches_the_target() -> None:
    T, V, P, q = _stall()
    assert np.linalg.norm(T - P) > 0.015  # the wrist stalls > 15 mm short of the target
    with pytest.raises(vip.JointLimitError):
        vip.vip_ik(T, V, G)
    m0 = limit_margin(q, CHAIN.lower, CHAIN.upper)
    travelled = 0.0
    while (d := midrange_direction(CHAIN, q, P, 0.001)) is not None and travelled < 0.1:
        q = elbow_move(CHAIN, q, P, 0.0001 * d)
        travelled += 0.0001
    m1 = limit_margin(q, CHAIN.lower, CHAIN.upper)
    print(f"margin {m0:.3f} -> {m1:.3f} after {travelled * 1e3:.1f} mm of elbow travel")
    assert m1 > m0 + 0.1
    assert np.linalg.norm(vip.fk(q, G).wrist - P) < 1e-9
    V2 = vip.select_vip(q, 0.05, G)
    assert off_line(vip.fk(q, G).elbow, P, V) > 0.005  # the elbow left the first VIP's line
    for s in np.linspace(0.0, 1.0, 50):  # the whole way on to the target, within Table I
        vip.vip_ik(P + s * (T - P), V2, G)


def _jog_core() -> tuple[ArmCore, ElbowJog]:
    cfg = SlaveControlConfig(model="vip")
    motion = ElbowJog(cfg, PROFILE)
    core = ArmCore(PROFILE, np.arange(5), cfg, 0.001, motion=motion, interpolate=True)
    q = np.array(PROFILE.home)
    core.start(ArmReading(q, np.zeros(5), np.zeros(5), PROFILE))
    return core, motion


def _cmd(name: str, *args: str) -> Command:
    return Command(Header("console", 0, time.time_ns()), "arm1", name, args)


def _run(core: ArmCore, lease: Lease, periods: int, t0: float) -> float:
    q = core.q_cmd
    for i in range(periods):
        now = t0 + i * 0.001
        core.lease = lease
        q = core.control(now, ArmReading(q.copy(), np.zeros(5), np.zeros(5), PROFILE))
        core.after_period(core.cycle + 1, ArmReading(q.copy(), np.zeros(5), np.zeros(5), PROFILE))
    return t0 + periods * 0.001


def test_elbow_jog_moves_the_elbow_under_the_lease_and_holds_the_wrist() -> None:
    core, motion = _jog_core()
    q0 = core.q_cmd.copy()
    W0, E0 = vip.fk(q0, G).wrist, vip.fk(q0, G).elbow
    ok, why = motion.command(_cmd("elbow_jog", "axis=z", "direction=1", "mm=2"))
    assert not ok and "may not move" in why  # no lease yet
    t = time.monotonic()
    t = _run(core, Lease(True, t + 10.0, "", 0, 10_000), 5, t)  # the loop judges the lease valid
    ok, why = motion.command(_cmd("elbow_jog", "axis=w"))
    assert not ok and "valid: x, y, z, midrange" in why
    ok, why = motion.command(_cmd("elbow_jog", "axis=z", "direction=1", "mm=2"))
    assert ok, why
    walls = []
    for _ in range(30):  # 300 ms at 10 mm/s: 2 mm then done
        t = _run(core, Lease(True, t + 10.0, "", core.cycle, 10_000), 10, t)
        walls.append(np.linalg.norm(vip.fk(core.q_cmd, G).wrist - W0))
    assert not motion.active()
    E = vip.fk(core.q_cmd, G).elbow
    assert 1.9e-3 < np.linalg.norm(E - E0) < 2.1e-3 and E[2] > E0[2]  # 2 mm, upward
    assert max(walls) < 1e-9  # the wrist of every commanded pose stayed put
    # a lost lease stops a running jog for good
    ok, why = motion.command(_cmd("elbow_jog", "axis=z", "direction=-1", "mm=5"))
    assert ok, why
    t = _run(core, Lease(True, t + 10.0, "", core.cycle, 10_000), 50, t)
    q_mid = core.q_cmd.copy()
    t = _run(core, Lease(False, 0.0, "watchdog HOLD"), 5, t)
    assert not motion.active()
    t = _run(core, Lease(True, t + 10.0, "", core.cycle, 10_000), 100, t)
    assert np.allclose(core.q_cmd, q_mid)  # nothing moved after the lease came back
