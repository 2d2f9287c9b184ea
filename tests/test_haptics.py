"""Bilateral force feedback: the tissue you can touch, the force renderer, the controllers.

The slave is the real MuJoCo MH3F scene (``MujocoBackend``; the PLAS and VIP scenes for their
tissue); the master is the simulated Touch and hand (``touch_sim``); the controllers and the
renderer are ``shared/haptics``. Delay-sweep figures are ``telesurg bench haptics``'s; here only
what a user would notice.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import mujoco
import numpy as np
import pytest
from telesurg.services.master_capture.devices import open_device
from telesurg.services.master_capture.devices.touch_sim.model import HeldDevice, TouchModel, press_and_slide
from telesurg.services.slave_control import SlaveControlConfig, make_arms
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.models import model_path
from telesurg.shared.errors import ConfigError, MessageError
from telesurg.shared.haptics import BilateralConfig, ForceRenderer, RenderConfig, SlavePortWork, check_force
from telesurg.shared.haptics.tdpa import MasterPacket, make_bilateral
from telesurg.shared.robots import registry
from telesurg.tools.bench.haptics import TipFollower, contact_height, run_one

DT = 0.001


@pytest.fixture(scope="module")
def slave() -> tuple[MujocoBackend, TipFollower, float]:
    with MujocoBackend("mh3f", registry.arm_profile("mh3f", "arm1").home) as backend:
        follower = TipFollower(backend)
        yield backend, follower, contact_height(backend, follower)


def test_tissue_pushes_back_with_its_published_stiffness(
    slave: tuple[MujocoBackend, TipFollower, float],
) -> None:
    """Pressing the forceps tip 3 then 6 mm into the tissue: the contact force on the instrument
    points up, out of the tissue, and grows at the scene's 0.4 N/mm (the spring) within 20 %
    (the hard contact's own give in series); nothing sideways."""
    backend, follower, z_c = slave
    x0 = follower.tip().copy()
    forces, depths = [], []
    for mm in (3.0, 6.0):
        for _ in range(500):
            follower.follow(np.array([x0[0], x0[1], z_c - mm / 1e3]))
        r = backend.read()
        assert r.contact_wrench is not None
        forces.append(r.contact_wrench[:3].copy())
        depths.append(z_c - r.tip_position[2])
    k = (forces[1][2] - forces[0][2]) / (depths[1] - depths[0])
    assert 0.8 * 400 <= k <= 1.2 * 400, f"tissue stiffness {k:.0f} N/m"
    assert forces[1][2] > 1.5
    assert abs(forces[1][0]) < 0.2 * forces[1][2] and abs(forces[1][1]) < 0.2 * forces[1][2]
    for _ in range(800):  # lifted off: no force
        follower.follow(np.array([x0[0], x0[1], z_c + 0.01]))
    assert np.linalg.norm(backend.read().contact_wrench[:3]) < 1e-6  # type: ignore[index]


@pytest.mark.parametrize("model", ["mh3f", "plas", "vip"])
def test_scene_joint_is_not_the_robots(model: str) -> None:
    """The tissue's indentation joints are the scene's: the backend reports the arms' joints."""
    arms = registry.arms_of(model)
    joints = tuple(j for p in arms for j in p.model_joints)
    home, tips = tuple(v for p in arms for v in p.home), tuple(p.tip_site for p in arms)
    with MujocoBackend(model, home, tips) as backend:
        assert backend.joint_names == joints
        assert backend.read().position.shape == (len(joints),)
        assert mujoco.MjModel.from_xml_path(str(backend.scene)).njnt > len(joints)  # it has a tissue


#: Where a two-arm robot starts a press: the PLAS in its working "Y" (keyframe y_shape; its home
#: holds the arms straight out to the sides), the VIP at home (Table I).
START_KEY = {"plas": "y_shape", "vip": "home"}


@pytest.fixture(scope="module", params=sorted(START_KEY))
def two_arm_slave(request: pytest.FixtureRequest) -> Iterator[tuple[str, MujocoBackend]]:
    """A two-arm slave, both tips reported (as slave_control runs it), at its working pose."""
    model = request.param
    arms = registry.arms_of(model)
    m = mujoco.MjModel.from_xml_path(str(model_path(model)))
    key = m.key(START_KEY[model])
    adr = [m.jnt_qposadr[m.joint(j).id] for p in arms for j in p.model_joints]  # (jaw fingers between)
    with MujocoBackend(model, tuple(key.qpos[adr]), tuple(p.tip_site for p in arms)) as backend:
        yield model, backend


@pytest.mark.parametrize("arm", ["arm1", "arm2"])
def test_each_arm_presses_its_own_tissue_with_the_published_stiffness(
    two_arm_slave: tuple[str, MujocoBackend], arm: str
) -> None:
    """Each arm of the PLAS and the VIP lowers its tip from free space (no force) onto the tissue
    under it, presses 3 then 6 mm: the force on its instrument points up and grows at 0.4 N/mm
    within 20 %, nothing sideways; slave_control's other arm feels none of it; lifted, the force
    is zero."""
    model, backend = two_arm_slave
    cores = {c.profile.arm: c for c in make_arms(SlaveControlConfig(model=model), backend)}
    follower = TipFollower(backend, model, arm)
    other = next(a for a in cores if a != arm)
    start, w = follower.measured()
    assert w is not None and np.linalg.norm(w[:3]) < 1e-6  # free space
    z_c = contact_height(backend, follower)
    assert start[2] - z_c > 0.01  # the working pose is clear of the tissue
    x0 = follower.tip().copy()
    forces, depths = [], []
    for mm in (3.0, 6.0):
        for _ in range(500):
            follower.follow(np.array([x0[0], x0[1], z_c - mm / 1e3]))
        tip, w = follower.measured()
        assert w is not None
        forces.append(w[:3].copy())
        depths.append(z_c - tip[2])
        r = backend.read()  # what each arm's measured_cf carries
        published = {a: core.arm_reading(r).contact_wrench for a, core in cores.items()}
        np.testing.assert_array_equal(published[arm], w)
        assert np.linalg.norm(published[other][:3]) < 1e-6  # type: ignore[index]
    k = (forces[1][2] - forces[0][2]) / (depths[1] - depths[0])
    assert 0.8 * 400 <= k <= 1.2 * 400, f"{model} {arm}: tissue stiffness {k:.0f} N/m"
    assert forces[1][2] > 1.5
    assert abs(forces[1][0]) < 0.1 * forces[1][2] and abs(forces[1][1]) < 0.1 * forces[1][2]
    for _ in range(800):  # lifted off: no force
        follower.follow(np.array([x0[0], x0[1], z_c + 0.01]))
    assert np.linalg.norm(follower.measured()[1][:3]) < 1e-6  # type: ignore[index]


def test_bad_forces_are_refused_counted_and_never_reach_the_device() -> None:
    device = HeldDevice(TouchModel(), press_and_slide())
    r = ForceRenderer(RenderConfig())
    assert r.offer((0.0, 0.0, 1.0), 0.0)
    for bad in ((math.nan, 0, 0), (0, math.inf, 0), (0, 0, 1e6), (1, 2), "three", None):
        assert not r.offer(bad, 0.001)
    assert r.rejected == 6
    outs = [device.write_force(r.step(0.001 * k, DT)) for k in range(1, 30)]
    assert np.all(np.isfinite(outs)) and max(np.linalg.norm(outs, axis=1)) <= 1.0 + 1e-9
    with pytest.raises(MessageError, match="not finite"):
        check_force((math.nan, 0.0, 0.0), 100.0)


def test_device_force_never_exceeds_its_limit() -> None:
    """However large the force asked (within what a message may carry), the renderer and the
    device's amplifier keep it within 3.3 N, rising at the rate limit."""
    device = HeldDevice(TouchModel(), press_and_slide())
    r = ForceRenderer(RenderConfig(limit_n=3.3, rate_n_per_s=200.0))
    outs = []
    for k in range(200):
        r.offer((0.0, 60.0, 80.0), k * DT)
        outs.append(np.linalg.norm(device.write_force(r.step(k * DT, DT))))
    assert max(outs) <= 3.3 + 1e-9 and max(np.diff(outs)) <= 200.0 * DT + 1e-9
    assert r.clipped > 0
    assert np.linalg.norm(device.write_force(np.array([0.0, 0.0, 50.0]))) == pytest.approx(3.3)


def test_stale_stream_and_hold_fade_the_force_to_zero_at_a_bounded_rate() -> None:
    r = ForceRenderer(RenderConfig(fade_n_per_s=10.0, stale_ms=20.0))
    for k in range(100):  # a steady 2 N, fresh
        r.offer((0.0, 0.0, 2.0), k * DT)
        r.step(k * DT, DT)
    out = [np.linalg.norm(r.step(0.1 + k * DT, DT)) for k in range(400)]  # the stream stops
    assert out[0] == pytest.approx(2.0)  # not before it is stale
    assert max(abs(np.diff(out))) <= 10.0 * DT + 1e-9  # never a step
    assert out[-1] == 0.0
    r.offer((0.0, 0.0, 2.0), 0.6)  # fresh again, but the watchdog holds
    held = [np.linalg.norm(r.step(0.6 + k * DT, DT, hold=True)) for k in range(10)]
    assert max(held) == 0.0


def test_unknown_controller_is_refused_with_the_valid_ones() -> None:
    with pytest.raises(ConfigError, match="valid: none, naive, tdpa, wave"):
        BilateralConfig(controller="magic")
    with pytest.raises(ConfigError, match="force_scale"):
        BilateralConfig(force_scale=math.nan)


def test_touch_sim_is_a_master_device_that_takes_a_force() -> None:
    dev = open_device("touch_sim")
    first = dev.read(0.0)
    assert first.clutch and first.operator_present
    applied = dev.write_force(np.array([0.0, 0.0, 10.0]))  # type: ignore[attr-defined]
    assert np.linalg.norm(applied) == pytest.approx(3.3)
    assert dev.read(0.5).position[2] > first.position[2]  # pushed up, against a hand at rest


def test_the_slave_port_counts_only_the_work_the_tissue_gives_back() -> None:
    """E_in_s (the slave's half of the observers, sent on measured_cf): pressing into the tissue
    puts energy into it (not counted), the tissue pushing the instrument back returns it."""
    port, up = SlavePortWork(), np.array([0.0, 0.0, 2.0])  # the tissue pushes up with 2 N
    port.add(up, np.array([0.0, 0.0, 0.0]))
    assert port.add(up, np.array([0.0, 0.0, -0.005])) == 0.0  # pressed 5 mm in: work into the tissue
    assert port.add(up, np.array([0.0, 0.0, -0.002])) == pytest.approx(0.006)  # 3 mm back: 6 mJ out
    assert port.add(np.zeros(3), np.array([0.01, 0.0, 0.0])) == pytest.approx(0.006)  # free space


def test_touch_sim_as_an_operator_at_a_site_presses_when_ready_and_moves_while_engaged() -> None:
    from telesurg.services.master_capture.devices.touch_sim import TouchSim, TouchSimConfig

    with pytest.raises(ConfigError, match="valid: script, site"):
        TouchSimConfig(operator="robot")
    dev = TouchSim(TouchSimConfig(operator="site", surface_mm=-10.0))
    assert not dev.read(0.0).clutch  # no teleop state yet: the pedal stays up
    for state in ("DISABLED", "IDLE", "ENGAGING"):
        dev._teleop = state
        assert dev.read(1.0).clutch == (state != "DISABLED")
        assert dev.read(2.0).position == (0.0, 0.0, 0.0)  # not engaged: the hand keeps still
    dev._teleop = "ENABLED"
    z = [dev.read(2.0 + 0.1 * k).position[2] for k in range(25)]  # the script: reach down
    assert z[-1] < -0.003  # it moved down towards the tissue
    dev._teleop = "HOLDING"  # held: the pedal goes up and the script pauses
    sample = dev.read(5.0)
    assert not sample.clutch
    assert dev.read(9.0).position[2] == pytest.approx(sample.position[2], abs=1e-4)


def test_touch_sim_at_a_site_makes_up_for_the_motion_the_slave_did_not_take() -> None:
    """Engaged again after a hold, the simulated operator aims where the slave's tip should be:
    the motion lost while the slave held is added to its hand's goal (as a surgeon would, looking
    at the video)."""
    from telesurg.services.master_capture.devices.touch_sim import TouchSim, TouchSimConfig

    dev = TouchSim(TouchSimConfig(operator="site", surface_mm=-10.0))
    s0 = np.array([0.8, 0.0, 0.3])
    dev._teleop, dev._scale, dev._tip = "ENABLED", 0.5, s0.copy()
    dev.read(0.0)
    for k in range(1, 9):
        dev.read(0.1 * k)  # 0.8 s of the script: the hand reaches down
    x_hold = np.array(dev.sim.x)
    dev._teleop = "HOLDING"
    dev.read(1.0)
    # the slave took none of the master's way down before it held (a hold at once)
    dev._tip = s0.copy()
    dev._teleop = "ENABLED"
    dev.read(1.1)
    # its goal now: the script plus the whole way the slave did not take
    assert x_hold[2] < -0.001
    assert dev._aim == pytest.approx(x_hold, abs=1e-6)
    dev.read(2.5)  # the hand blends its goal there over a few hundred ms (a correction, not a jump)
    assert dev.sim.offset == pytest.approx(x_hold, abs=1e-4)
    # had the slave taken it all (0.5 × the master's way), nothing would be added
    dev._teleop = "HOLDING"
    dev.read(2.6)
    x_now = np.array(dev.sim.x)
    dev._tip, dev._teleop = s0 + 0.5 * x_now, "ENABLED"
    dev.read(2.7)
    assert dev._aim == pytest.approx(np.zeros(3), abs=1e-6)


@pytest.mark.slow
def test_zero_delay_feels_the_tissue_and_nothing_in_free_space() -> None:
    """Acceptance 1: at zero delay the stiffness felt at the master is the tissue's × the scales
    within 20 %; in free space the master force is < 0.1 N."""
    row = run_one("tdpa", 0.0)
    assert row["felt_stiffness_n_per_mm"] == pytest.approx(row["expected_stiffness_n_per_mm"], rel=0.2)
    assert row["free_space_force_n"] < 0.1
    assert row["max_device_force_n"] <= row["device_limit_n"]


@pytest.mark.slow
def test_naive_goes_unstable_where_tdpa_stays_passive() -> None:
    """Acceptance 2 at two points: the naive loop at 100 ms round trip generates energy and
    oscillates; TDPA at 200 ms with ±20 % jitter and 5 % loss stays passive and settles."""
    naive = run_one("naive", 100.0)
    tdpa = run_one("tdpa", 200.0, 0.2, 0.05)
    assert naive["verdict"] == "unstable", naive
    assert min(naive["min_observed_master_mj"], naive["min_observed_slave_mj"]) < -10.0
    assert tdpa["verdict"] == "stable", tdpa
    assert min(tdpa["min_observed_master_mj"], tdpa["min_observed_slave_mj"]) >= -1.0
    assert tdpa["overshoot"] <= 1.5


def _slave_port(controller: str, energy_in_m: float, seconds: float = 1.0) -> tuple[float, float, float]:
    """The slave half alone: master packets command a descent at 10 mm/s into a 400 N/m tissue
    (top at 0), carrying ``energy_in_m`` as the master's input energy (0: none arrived — the
    master's energy is late, or forged low). Returns (lowest W_s J, depth reached m, energy the
    slave passivity controller dissipated J)."""
    b = make_bilateral(BilateralConfig(controller=controller))
    k_tissue, w_min, depth = 400.0, math.inf, 0.0
    for i in range(1, int(seconds / DT) + 1):
        x_m = np.array([0.0, 0.0, -0.010 * i * DT])
        z = float(b.x_s[2])
        f_e = np.array([0.0, 0.0, k_tissue * max(0.0, -z)])  # the tissue pushes up when indented
        b.slave_step(MasterPacket(i, x_m, energy_in_m), f_e, DT)
        w_min, depth = min(w_min, b.observed_slave), min(depth, float(b.x_s[2]))
    return w_min, depth, b.dissipated_s


def test_slave_passivity_controller_keeps_the_slave_port_passive() -> None:
    """The slave half of TDPA (position channel): with no master energy to spend, pressing into
    the tissue would take energy out of the network at the slave port; the slave PC backs the
    instrument off just enough that W_s never goes below zero (naive: −10 mJ at 10 mm deep);
    with the master's energy in hand it follows the master exactly and dissipates nothing."""
    w_naive, depth_naive, _ = _slave_port("naive", 0.0)
    w_tdpa, depth_tdpa, dissipated = _slave_port("tdpa", 0.0)
    print(
        f"no master energy: naive W_s ≥ {w_naive * 1e3:.3f} mJ, {depth_naive * 1e3:.1f} mm deep; "
        f"tdpa W_s ≥ {w_tdpa * 1e3:.4f} mJ, {depth_tdpa * 1e3:.2f} mm deep, "
        f"PC dissipated {dissipated * 1e3:.3f} mJ"
    )
    assert w_naive < -0.5e-3 and depth_naive == pytest.approx(-0.010, abs=1e-4)
    assert w_tdpa >= -1e-6  # passive: never more out than the master put in
    assert depth_tdpa > depth_naive + 0.005  # it backed off
    assert dissipated > 0.0
    w_fed, depth_fed, dissipated_fed = _slave_port("tdpa", 1.0)  # 1 J from the master: ample
    assert w_fed > 0.99 and depth_fed == pytest.approx(depth_naive, abs=1e-6) and dissipated_fed == 0.0
