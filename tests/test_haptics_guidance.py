"""Haptic guidance rendered on the console (issue #42): the master's workspace walls and the
virtual trocar, felt at once and without the slave or the network."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
from telesurg.shared.bus import BusConfig
from telesurg.shared.errors import ConfigError
from telesurg.shared.haptics.guidance import AXIS, Guidance, GuidanceSettings, trocar_force, wall_force

LO, HI = np.array([-0.08, -0.06, -0.05]), np.array([0.08, 0.06, 0.05])
STILL = np.zeros(3)


def test_walls_push_back_only_beyond_them() -> None:
    for x in (np.zeros(3), LO + 1e-4, HI - 1e-4):
        assert np.all(wall_force(x, STILL, LO, HI, 1000.0, 2.0) == 0.0)
    # 5 mm beyond +x: 5 N back along −x, nothing else
    f = wall_force(np.array([0.085, 0.0, 0.0]), STILL, LO, HI, 1000.0, 2.0)
    assert f == pytest.approx([-5.0, 0.0, 0.0])
    # 3 mm below the floor and 2 mm beyond −y (a corner): each wall its own push
    f = wall_force(np.array([0.0, -0.062, -0.053]), STILL, LO, HI, 1000.0, 2.0)
    assert f == pytest.approx([0.0, 2.0, 3.0])
    # moving further in: the damper adds; moving back out: the spring alone
    f_in = wall_force(np.array([0.0, 0.0, -0.053]), np.array([0.0, 0.0, -0.1]), LO, HI, 1000.0, 2.0)
    f_out = wall_force(np.array([0.0, 0.0, -0.053]), np.array([0.0, 0.0, 0.1]), LO, HI, 1000.0, 2.0)
    assert f_in[2] == pytest.approx(3.2) and f_out[2] == pytest.approx(3.0)


def _trocar(**kw: float) -> GuidanceSettings:
    return GuidanceSettings(trocar=(0.0, 0.0, 0.0), forceps_m=0.2, handle_min_m=0.04, **kw)  # type: ignore[arg-type]


def test_virtual_trocar_keeps_the_dummy_forceps_in_reach_and_in_its_cone() -> None:
    s = _trocar(tilt_max_deg=45.0)
    # straight up the axis, 100 mm from the fulcrum: free
    assert np.all(trocar_force(np.array([0.0, 0.0, 0.1]), STILL, s) == 0.0)
    # 210 mm away: the dummy tip would leave the trocar; 10 mm → 10 N towards the fulcrum
    assert trocar_force(np.array([0.0, 0.0, 0.21]), STILL, s) == pytest.approx([0.0, 0.0, -10.0])
    # 30 mm away: the handle against the trocar; pushed out 10 N
    assert trocar_force(np.array([0.0, 0.0, 0.03]), STILL, s) == pytest.approx([0.0, 0.0, 10.0])
    # tilted 60° (past 45°) at 100 mm: pushed back towards the axis, along the sphere round the
    # fulcrum; a small step along the push lowers the tilt and keeps the distance
    x = 0.1 * np.array([math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))])
    f = trocar_force(x, STILL, s)
    assert np.linalg.norm(f) == pytest.approx(1000.0 * 0.1 * math.radians(15), rel=1e-6)
    assert abs(f @ x) < 1e-9  # tangential

    def tilt(p: np.ndarray) -> float:
        u = -p / np.linalg.norm(p)
        return math.degrees(math.acos(float(u @ AXIS)))

    step = x + 1e-4 * f / np.linalg.norm(f)
    assert tilt(step) < tilt(x) and np.linalg.norm(step) == pytest.approx(0.1, abs=1e-6)
    # within the cone at 40°: no push
    x40 = 0.1 * np.array([0.0, math.sin(math.radians(40)), math.cos(math.radians(40))])
    assert np.all(trocar_force(x40, STILL, s) == 0.0)


def test_bad_guidance_settings_are_refused_with_the_reason() -> None:
    from telesurg.services.master_capture import HapticsConfig, guidance_settings

    assert not Guidance(guidance_settings(HapticsConfig())).on  # off by default
    for kw, words in (
        ({"walls_min_mm": (-80.0, -60.0, -50.0)}, "both corners"),
        ({"walls_min_mm": (-80.0, 60.0, -50.0), "walls_max_mm": (80.0, 60.0, 50.0)}, "below"),
        ({"trocar_handle_min_mm": 250.0}, "trocar_handle_min_mm"),
        ({"trocar_tilt_max_deg": 0.0}, "trocar_tilt_max_deg"),
        ({"guidance_stiffness_n_per_m": -1.0}, "guidance_stiffness"),
    ):
        with pytest.raises(ConfigError, match=words):
            guidance_settings(HapticsConfig(**kw))  # type: ignore[arg-type]


def test_the_hand_meets_the_floor_of_the_workspace_without_a_slave(
    endpoint: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """master_capture with touch_sim and only walls (no slave arm, no network force): the simulated
    hand reaches 31 mm down; the handle stops near the floor at −10 mm, pushed up, the device's
    force never past its limit."""
    from telesurg.services import master_capture
    from telesurg.services.master_capture import devices
    from telesurg.services.master_capture.devices.touch_sim import TouchSim, TouchSimConfig

    dev = TouchSim(TouchSimConfig(surface_mm=-20.0, press_mm=11.0))  # intent: down to −31 mm
    monkeypatch.setattr(devices, "open_device", lambda name, settings=None: dev)
    cfg = master_capture.MasterCaptureConfig(
        device="touch_sim", rate_hz=1000.0, bus=BusConfig(connect=[endpoint])
    )
    cfg.haptics.walls_min_mm = (-80.0, -60.0, -10.0)
    cfg.haptics.walls_max_mm = (80.0, 60.0, 50.0)
    stop = threading.Event()
    thread = threading.Thread(target=master_capture.run, args=(cfg, stop), daemon=True)
    lowest, pushes = 0.0, []
    thread.start()
    try:
        end = time.monotonic() + 4.0  # the script's press ends at 2.3 s of device time, holds to 3.8
        while time.monotonic() < end:
            lowest = min(lowest, float(dev.sim.x[2]))
            pushes.append(dev.sim.motor.copy())
            time.sleep(0.005)
    finally:
        stop.set()
        thread.join(timeout=5)
    assert not thread.is_alive()
    f = np.array(pushes)
    print(
        f"lowest {lowest * 1e3:.1f} mm (intent −31 mm); largest push {np.linalg.norm(f, axis=1).max():.2f} N"
    )
    assert dev.sim.t > 2.5, "the script did not reach its press"
    assert -0.016 < lowest < -0.010  # held at the floor, a few mm into it (hand 200 N/m, wall 1000)
    assert f[:, 2].max() > 2.0 and np.all(np.abs(f[:, :2]) < 1e-9)  # straight up
    assert np.linalg.norm(f, axis=1).max() <= 3.3 + 1e-9  # the device's limit
