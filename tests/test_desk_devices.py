"""Desk master devices (services/master_capture/devices/desk.py, a file per device): the
device-independent parts — rate
integration, deadband, workspace box, button edges, staleness, frames — and the library bindings
where their library is installed (skipped with the reason otherwise: none is installable here and
none has been run against hardware)."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
import time
from dataclasses import dataclass, field

import numpy as np
import pytest
from telesurg.services.master_capture import devices
from telesurg.services.master_capture.devices import open_device
from telesurg.services.master_capture.devices.desk import (
    ButtonEdges,
    DeskConfig,
    DeskDevice,
    RateIntegrator,
    Reading,
    deadband,
    scaled_position,
)
from telesurg.services.master_capture.devices.gamepad import GamepadDevice
from telesurg.services.master_capture.devices.spacemouse import SpaceMouseDevice
from telesurg.services.master_capture.devices.touch import TouchDevice
from telesurg.shared.errors import ConfigError, DeviceConnectionError

#: desk device → (Python package to pip install, what else it needs)
LIBRARIES = {n: cls.library for n in devices.names() if issubclass(cls := devices.get(n), DeskDevice)}


@dataclass
class Played:
    """A binding that plays recorded readings (the library's place in these tests)."""

    readings: list[Reading | None] = field(default_factory=list)
    opened: bool = False

    def open(self) -> None:
        self.opened = True

    def read(self) -> Reading | None:
        return self.readings.pop(0) if self.readings else None

    def close(self) -> None:
        self.opened = False


def test_deadband_removes_rest_noise_and_keeps_full_scale() -> None:
    assert deadband(0.05, 0.1) == 0.0
    assert deadband(-0.1, 0.1) == 0.0
    assert deadband(1.0, 0.1) == pytest.approx(1.0)
    assert deadband(-0.55, 0.1) == pytest.approx(-0.5)
    assert deadband(3.0, 0.1) == 1.0  # out of range: clipped


def test_rate_integration_speed_box_and_stall_cap() -> None:
    cfg = DeskConfig(max_speed_mm_s=50.0, workspace_mm=20.0, max_dt_s=0.05, deadband=0.0)
    r = RateIntegrator(cfg)
    t = 0.0
    for _ in range(101):  # 1 s at full +x: 50 mm/s → 50 mm, held at the 20 mm box
        r.step(t, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        t += 0.01
    assert r.position[0] == pytest.approx(0.020)
    assert r.clamped > 0
    r2 = RateIntegrator(DeskConfig(max_speed_mm_s=50.0, max_dt_s=0.05, deadband=0.0))
    r2.step(0.0, (0.0, 1.0, 0.0), (0, 0, 0))
    r2.step(2.0, (0.0, 1.0, 0.0), (0, 0, 0))  # a 2 s stall integrates only 50 ms
    assert r2.position[1] == pytest.approx(0.0025)


def test_rate_rotation_integrates_about_the_body_axes() -> None:
    r = RateIntegrator(DeskConfig(max_rot_deg_s=90.0, deadband=0.0))
    for i in range(101):  # 1 s at full yaw rate: 90°
        r.step(i * 0.01, (0, 0, 0), (0.0, 0.0, 1.0))
    x, y, z, w = r.orientation
    assert math.degrees(2 * math.atan2(z, w)) == pytest.approx(90.0, abs=0.5)
    assert abs(x) < 1e-9 and abs(y) < 1e-9


def test_button_edges_hold_and_toggle() -> None:
    hold = ButtonEdges("hold")
    assert [hold.update(b) for b in (False, True, True, False)] == [False, True, True, False]
    tog = ButtonEdges("toggle")
    assert [tog.update(b) for b in (True, True, False, True, False)] == [True, True, True, False, False]
    assert tog.presses == 2
    tog.update(True)
    tog.reset()  # the device was lost: released, and held buttons do not count as a press
    assert tog.update(False) is False


def test_absolute_devices_map_their_frame() -> None:
    cfg = DeskConfig(rotation_rpy_deg=(0.0, 0.0, 90.0), offset_mm=(0.0, 0.0, 10.0))
    x, y, z = scaled_position((0.01, 0.0, 0.0), cfg)
    assert (x, y, z) == pytest.approx((0.0, 0.01, 0.01))


def test_desk_device_staleness_and_clutch() -> None:
    now = time.monotonic()
    cfg = DeskConfig(stale_ms=50.0, deadband=0.0, max_speed_mm_s=100.0)
    played = Played(
        [
            Reading(now, trans=(1.0, 0.0, 0.0), buttons=(True,)),
            Reading(now + 0.01, trans=(1.0, 0.0, 0.0), buttons=(True,)),
        ]
    )
    dev = SpaceMouseDevice(cfg, binding=played)
    with dev:
        assert played.opened
        s1 = dev.read(0.0)
        s2 = dev.read(0.01)
        assert s1.valid and s2.valid and s2.clutch
        assert s2.position[0] == pytest.approx(0.001)  # 10 ms at 100 mm/s
        time.sleep(0.08)  # no new reading for longer than stale_ms
        s3 = dev.read(0.1)
        assert not s3.valid and not s3.clutch
    assert not played.opened


def test_absolute_device_reports_its_pose() -> None:
    now = time.monotonic()
    played = Played(
        [Reading(now, position=(0.01, 0.02, 0.03), orientation=(0, 0, 0, 1), buttons=(False, True))]
    )
    dev = TouchDevice(DeskConfig(clutch_button=1), binding=played)
    s = dev.read(0.0)
    assert s.valid and s.clutch and s.position == pytest.approx((0.01, 0.02, 0.03))


def test_config_errors_name_the_problem() -> None:
    with pytest.raises(ConfigError, match="clutch_mode"):
        GamepadDevice(DeskConfig(clutch_mode="latch"), binding=Played())
    with pytest.raises(ConfigError, match="deadband"):
        DeskConfig(deadband=0.95).validate()


@pytest.mark.parametrize("kind", sorted(LIBRARIES))
def test_binding_without_its_library_says_what_to_install(kind: str) -> None:
    module = {"spacemouse": "pyspacemouse", "touch": "pyOpenHaptics", "omega7": "forcedimension_core"}.get(
        kind, "pygame"
    )
    if importlib.util.find_spec(module) is not None:
        pytest.skip(f"{module} is installed: see test_binding_with_its_library")
    dev = open_device(kind)
    with pytest.raises(DeviceConnectionError, match=LIBRARIES[kind][0]), dev:  # type: ignore[attr-defined]
        pass


@pytest.mark.parametrize("kind", sorted(LIBRARIES))
def test_binding_with_its_library(kind: str) -> None:
    module = {"spacemouse": "pyspacemouse", "touch": "pyOpenHaptics", "omega7": "forcedimension_core"}.get(
        kind, "pygame"
    )
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{LIBRARIES[kind][0]} not installed (needs {LIBRARIES[kind][1]}); binding not exercised")
    dev = open_device(kind)
    try:
        with dev:  # type: ignore[attr-defined]
            s = dev.read(0.0)
            assert len(s.position) == 3
    except DeviceConnectionError as exc:  # the library is there, the device is not
        pytest.skip(f"{kind}: {exc}")


def test_device_check_cli_reports_a_missing_library() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "device", "check", "omega7", "--seconds", "0.2"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if importlib.util.find_spec("forcedimension_core") is None:
        assert r.returncode == 1 and "forcedimension-core" in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "device", "check", "scripted", "--seconds", "0.3"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "valid readings" in r.stdout and "clutch" in r.stdout


# --------------------------------------------------------------------------- force output


class ForcePlayed(Played):
    """A haptic binding: what it was told to push (device frame), in order."""

    def __init__(self) -> None:
        super().__init__([])
        self.forces: list[tuple[float, float, float]] = []

    def write_force(self, force: tuple[float, float, float]) -> None:
        self.forces.append(force)


@pytest.mark.parametrize(("kind", "limit"), [("touch", 3.3), ("omega7", 12.0)])
def test_haptic_desk_devices_push_in_their_own_frame_within_their_limit(kind: str, limit: float) -> None:
    cls = devices.get(kind)
    binding = ForcePlayed()
    # the device turned a quarter about z on the desk: its x is the master's y
    dev = cls(DeskConfig(rotation_rpy_deg=(0.0, 0.0, 90.0)), binding=binding)  # type: ignore[call-arg]
    with dev:
        applied = dev.write_force((1.0, 0.0, 0.0))  # type: ignore[attr-defined]
        assert tuple(applied) == pytest.approx((1.0, 0.0, 0.0))
        assert binding.forces[-1] == pytest.approx((0.0, -1.0, 0.0))  # master x = device −y
        big = dev.write_force((0.0, 0.0, 100.0))  # type: ignore[attr-defined]
        assert float(np.linalg.norm(big)) == pytest.approx(limit)  # capped at the device's limit
        assert binding.forces[-1] == pytest.approx((0.0, 0.0, limit))
        dev.write_force((math.nan, 0.0, 0.0))  # type: ignore[attr-defined]
        assert binding.forces[-1] == (0.0, 0.0, 0.0)  # never a non-finite force
        dev.write_force((0.5, 0.0, 0.0))  # type: ignore[attr-defined]
    assert binding.forces[-1] == (0.0, 0.0, 0.0) and not binding.opened  # zeroed, then closed


def test_rate_devices_take_no_force_and_haptics_says_so() -> None:
    from telesurg.services.master_capture import HapticLoop, MasterCaptureConfig

    assert not hasattr(SpaceMouseDevice, "write_force") and not hasattr(GamepadDevice, "write_force")
    cfg = MasterCaptureConfig(device="spacemouse")
    cfg.haptics.slave_arm = "arm1"
    with pytest.raises(ConfigError, match="takes no force"):
        HapticLoop(cfg, SpaceMouseDevice(DeskConfig(), binding=Played()), node=None)  # type: ignore[arg-type]


def test_the_touch_binding_sets_the_force_in_the_hd_servo_callback(monkeypatch: pytest.MonkeyPatch) -> None:
    """pyOpenHaptics stood in for by modules that record the HD calls (no SDK, no device here):
    the force is set inside the scheduler's callback, in the device's frame, zeroed at close."""
    import types

    calls: dict[str, list[object]] = {"set_force": [], "scheduler": [], "close": []}
    hd = types.ModuleType("pyOpenHaptics.hd")
    hd.set_force = lambda f: calls["set_force"].append(tuple(f))  # type: ignore[attr-defined]
    hd_callback = types.ModuleType("pyOpenHaptics.hd_callback")
    hd_callback.hd_callback = lambda fn: fn  # type: ignore[attr-defined]
    hd_device = types.ModuleType("pyOpenHaptics.hd_device")

    class HapticDevice:
        def __init__(self, callback: object, scheduler_type: str = "async") -> None:
            calls["scheduler"].append((callback, scheduler_type))

        def close(self) -> None:
            calls["close"].append(True)

    hd_device.HapticDevice = HapticDevice  # type: ignore[attr-defined]
    for name, mod in (
        ("pyOpenHaptics", types.ModuleType("pyOpenHaptics")),
        ("pyOpenHaptics.hd", hd),
        ("pyOpenHaptics.hd_callback", hd_callback),
        ("pyOpenHaptics.hd_device", hd_device),
    ):
        monkeypatch.setitem(sys.modules, name, mod)
    dev = TouchDevice(DeskConfig(rotation_rpy_deg=(0.0, 0.0, 90.0)))
    with dev:
        ((servo, kind),) = calls["scheduler"]
        assert kind == "async"
        dev.write_force((0.0, 2.0, 0.0))
        servo()  # the HD servo loop's tick
        assert calls["set_force"][-1] == pytest.approx((2.0, 0.0, 0.0))  # master y = device x
    servo()
    assert calls["set_force"][-1] == (0.0, 0.0, 0.0) and calls["close"] == [True]


def test_the_omega7_binding_enables_and_sets_the_force(monkeypatch: pytest.MonkeyPatch) -> None:
    """forcedimension-core stood in for by a module that records the DHD calls."""
    import types

    from telesurg.services.master_capture.devices.omega7 import Omega7Device

    calls: list[tuple[object, ...]] = []

    class Dhd:
        def open(self) -> int:
            calls.append(("open",))
            return 0

        def enableForce(self, on: bool) -> None:
            calls.append(("enableForce", on))

        def setForceAndTorqueAndGripperForce(self, f: list[float], t: list[float], fg: float) -> int:
            calls.append(("force", tuple(f), tuple(t), fg))
            return 0

        def close(self) -> None:
            calls.append(("close",))

    sdk = types.ModuleType("forcedimension_core")
    sdk.dhd = Dhd()  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "forcedimension_core", sdk)
    with Omega7Device(DeskConfig()) as dev:
        dev.write_force((0.0, 0.0, 20.0))
    assert calls[:2] == [("open",), ("enableForce", True)]
    assert calls[2] == ("force", (0.0, 0.0, 12.0), (0.0, 0.0, 0.0), 0.0)  # capped at 12 N
    assert calls[-2:] == [("force", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0), ("close",)]
