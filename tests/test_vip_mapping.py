"""The VIP mapping's operator side (issue #20, acceptance 4), with two real zenoh sessions.

* An engage after ``set_vip`` starts where the slave is: the first followed setpoint is the
  slave's joints (the slave refuses an engage whose first setpoint is more than
  ``engage_tolerance_rad`` away), and only then does the elbow move over to the new VIP's line.
* ``reallocate_vip`` is refused while the slave runs a slave-side motion (the elbow jog), and
  afterwards takes the joints the slave measures: the reply says how far the elbow was off the
  previous VIP line.
* The operator's scale commands work in the VIP mode too.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from conftest import wait_until
from helpers import feed_master
from telesurg.services.launcher import free_port
from telesurg.services.mapping import MappingConfig, Pair
from telesurg.shared.bus import BusConfig, Node, open_session
from telesurg.shared.kinematics.elbow import elbow_move, off_line, tangent
from telesurg.shared.messages import Command, Header, JointSetpoint, JointState, OperatingState
from telesurg.shared.robots.vip import kinematics as vip

H = Header("test", 0, 0)
G = vip.VIP_ARM1


def _cmd(name: str, *args: str) -> Command:
    return Command(Header("console", 0, time.time_ns()), "arm1", name, args)


@pytest.fixture
def rig() -> Iterator[tuple[Pair, list[JointSetpoint]]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    bus = BusConfig(connect=[ep])
    setpoints: list[JointSetpoint] = []
    try:
        with Node(bus, "t", "mapping") as node, Node(bus, "t", "probe") as probe:
            probe.subscribe(
                probe.keys.slave("arm1", "servo_jp"), JointSetpoint, lambda m, k: setpoints.append(m)
            )
            time.sleep(0.3)
            cfg = MappingConfig(mode="vip", model="vip", scale=0.5)
            cfg.validate()
            arm = Pair(cfg, node, "m1", "arm1", threading.Event())
            arm.on_slave_js(JointState(H, G.joint_names, G.home), "")
            arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")
            yield arm, setpoints
    finally:
        router.close()  # type: ignore[no-untyped-call]


def test_engage_after_set_vip_starts_at_the_slave(rig: tuple[Pair, list[JointSetpoint]]) -> None:
    arm, setpoints = rig
    home = G.home_q
    V = vip.select_vip(home, 0.05, G) + np.array([0.0, 0.0, 0.01])  # a VIP 10 mm above: the elbow moves
    ok, why = arm.strategy._command(
        _cmd("set_vip", *(f"{c}={v * 1e3}" for c, v in zip("xyz", V, strict=True)))
    )
    assert ok and "the elbow moves" in why, why
    feed_master(arm, (0.0, 0.0, 0.0), clutch=False)
    for i in range(4):
        feed_master(arm, (0.0, 0.0, 0.0), clutch=True)
        time.sleep(0.045)  # 25 Hz samples: the master stamps are 40+ ms apart
        assert i > 0 or arm.following
    wait_until(lambda: sum(s.follow for s in setpoints) >= 4, 3.0)
    followed = [np.array(s.position) for s in setpoints if s.follow]
    np.testing.assert_allclose(followed[0], home, atol=1e-12)  # the first is where the slave is
    # then the elbow moves to the new line (feed_master stamps 0: the 1 ms minimum step, 0.001 rad)
    assert np.max(np.abs(followed[-1] - home)) > 0.002
    w = [vip.fk(q, G).wrist for q in followed]
    assert max(np.linalg.norm(x - w[0]) for x in w) < 5e-5  # the wrist stays (joint-space steps)


def test_reallocate_vip_waits_for_the_elbow_jog_and_takes_the_measured_joints(
    rig: tuple[Pair, list[JointSetpoint]],
) -> None:
    arm, _ = rig
    chain = arm.strategy.profile.elbow
    assert chain is not None
    home = G.home_q
    ok, why = arm.strategy._command(_cmd("reallocate_vip"))
    assert ok, why  # the first VIP, from the home pose
    W = vip.fk(home, G).wrist
    moved = elbow_move(chain, home, W, 0.010 * tangent(chain, home, W, np.array([0.0, 0.0, 1.0])))
    arm.on_slave_state(OperatingState(H, "ENABLED", "joint", False, True, "slave-side motion", 0), "")
    arm.on_slave_js(JointState(H, G.joint_names, tuple(moved)), "")
    ok, why = arm.strategy._command(_cmd("reallocate_vip"))
    assert not ok and "moving" in why
    arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")
    ok, why = arm.strategy._command(_cmd("reallocate_vip"))
    assert ok, why
    m = re.search(r"the elbow was ([0-9.]+) mm off the previous VIP line", why)
    assert m and 9.5 <= float(m.group(1)) <= 10.0, why  # 10 mm swung on the forearm sphere
    assert arm.strategy.V is not None
    np.testing.assert_allclose(arm.strategy.V, vip.select_vip(moved, 0.05, G), atol=1e-12)
    assert off_line(vip.fk(moved, G).elbow, W, arm.strategy.V) < 1e-9


def test_scale_commands_in_vip_mode(rig: tuple[Pair, list[JointSetpoint]]) -> None:
    arm, _ = rig
    r = arm.strategy.on_command(_cmd("set_scale", "value=0.2"))
    assert r.accepted and arm.scale == pytest.approx(0.2)
    r = arm.strategy.on_command(_cmd("set_scale", "value=3"))
    assert not r.accepted and arm.scale == pytest.approx(0.2)


@pytest.mark.parametrize("energy_j", [0.0, 1.0])
def test_vip_slave_passivity_backs_the_wrist_off_a_master_without_energy(energy_j: float) -> None:
    """TDPA's slave port in the VIP mapping (``slave_passivity``): a master that put no energy into
    the network cannot push the tissue (the wrist backs off along the contact force), one with
    energy to spare is followed exactly."""
    from telesurg.shared.messages import CartesianPose, CartesianWrench, MasterButtons

    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    try:
        with Node(BusConfig(connect=[ep]), "t", "mapping") as node:
            cfg = MappingConfig(
                mode="vip", model="vip", scale=1.0, slave_passivity=True, haptics_force_scale=0.5
            )
            cfg.validate()
            arm = Pair(cfg, node, "m1", "arm1", threading.Event())
            arm.on_slave_js(JointState(H, G.joint_names, G.home), "")
            arm.on_slave_state(OperatingState(H, "PAUSED", "joint", False, True, "", 0), "")
            st = arm.strategy
            surface = None
            depth = []
            for i in range(400):  # 2 ms samples: 0.8 s down 8 mm in the master's z, then held
                stamp = 1_000_000_000 + i * 2_000_000
                h = Header("test", i, stamp)
                z = -0.008 * min(1.0, i / 300)
                arm.on_buttons(MasterButtons(h, i > 0, True), "")  # a new press
                # E_in_m counts from the engage (sample 1): 0 there, then what the master put in
                e_in = energy_j if i > 1 else 0.0
                arm.on_master(CartesianPose(h, "master", (0.0, 0.0, z), energy_in_j=e_in), "")
                arm.process()
                if st.q_cmd is None or not arm.following:
                    continue
                w = vip.fk(st.q_cmd, G).wrist
                surface = w[2] if surface is None else surface  # the tissue's top: the engage's wrist
                st.on_contact_force(
                    CartesianWrench(h, "base", (0.0, 0.0, 400.0 * max(0.0, surface - w[2]))), ""
                )
                depth.append(surface - w[2])
    finally:
        router.close()  # type: ignore[no-untyped-call]
    deepest = max(depth)
    print(f"E_in_m {energy_j} J: deepest {deepest * 1e3:.2f} mm; W_s min {st.spc.w_min * 1e3:.3f} mJ")
    if energy_j == 0.0:
        assert deepest < 0.002 and st.spc.w_min > -1e-3 and st.spc.offset_max > 0.004
    else:
        assert deepest == pytest.approx(0.008, abs=2e-4) and st.spc.dissipated == 0.0
