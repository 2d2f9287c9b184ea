"""The ``policy`` master device without a bus: what it publishes for what the policy answers.

The live site (the policy drives the slave; a paused policy, an e-stop, the operator's clutch)
is ``tests/test_policy_master_process.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from telesurg.services.master_capture import MasterCaptureConfig
from telesurg.services.master_capture.devices import DeviceSample, open_device
from telesurg.services.master_capture.devices.policy import PolicyDevice, load_policy
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CartesianPose, Header, JointState, OperatingState

REACH = str(Path(__file__).with_name("policies") / "reach.py")
H = Header("slave_control", 0, 0)


def _device(tmp_path: Path, **options: object) -> PolicyDevice:
    cfg = MasterCaptureConfig(
        device="policy",
        device_options={
            "policy": f"{REACH}:make",
            "options": {"pause_file": str(tmp_path / "pause"), **options},
        },
    )
    d = open_device("policy", cfg)
    assert isinstance(d, PolicyDevice)
    return d


def _measure(d: PolicyDevice, following: bool) -> None:
    d._on_js(JointState(H, ("j1",), (0.1,)), "")
    d._on_cp(CartesianPose(H, "base", (0.5, 0.0, 0.2)), "")
    d._on_state(OperatingState(H, "ENABLED", "joint", follow=following), "")


def read(d: PolicyDevice, t: float, following: bool) -> DeviceSample:
    """One read at ``t``, the slave's measurements kept fresh as a live slave's 250 Hz would keep
    them (the staleness rule reads the real clock: a loaded host must not age them)."""
    _measure(d, following)
    return d.read(t)


def test_it_publishes_only_while_the_policy_acts_and_presses_again_after_a_pause(tmp_path: Path) -> None:
    d = _device(tmp_path, speed_mm_s=30.0)
    with d:
        s = d.read(0.0)
        assert not s.valid and "no measurements" in d.status()  # nothing seen yet: nothing published
        _measure(d, following=True)
        samples = [read(d, k / 500, following=True) for k in range(1, 1001)]  # 2 s at 500 Hz
        assert all(s.valid for s in samples[20:])  # from the first call at 30 Hz
        assert not samples[0].clutch and samples[-1].clutch  # pressed from press_at_s (1 s)
        # 30 mm/s along x for 2 s, in 30 Hz steps of 1 mm
        assert samples[-1].position[0] == pytest.approx(0.060, abs=0.0015)
        (tmp_path / "pause").touch()
        paused = [d.read(2 + k / 500) for k in range(1, 101)]
        assert not any(s.valid for s in paused[20:]) and "returned None" in d.status()
        (tmp_path / "pause").unlink()
        _measure(d, following=False)
        again = [read(d, 2.2 + k / 500, following=False) for k in range(1, 501)]
        first = next(i for i, s in enumerate(again) if s.valid)
        # the pedal is released for repress_s (0.5 s) after the policy acts again: a new press
        assert not any(s.clutch for s in again[first : first + 200])
        assert again[-1].clutch


def test_a_step_too_long_is_shortened_and_bad_answers_hold(tmp_path: Path) -> None:
    d = _device(tmp_path, speed_mm_s=3000.0)  # 100 mm a step asked, 5 mm allowed
    with d:
        _measure(d, following=True)
        d.read(0.0)
        d.read(0.04)
        assert d.clipped == 2 and np.linalg.norm(d.position) == pytest.approx(0.010)

        d.policy = lambda obs: (1.0, 2.0)  # not 3 numbers
        assert not d.read(1.0).valid and "not dx dy dz" in d.status()
        d.policy = lambda obs: (0.0, 0.0, 0.0, 1.5)  # a grip outside [0, 1]
        assert not d.read(1.5).valid and "grip 0–1" in d.status()

        def broken(obs: object) -> None:
            raise RuntimeError("no checkpoint")

        d.policy = broken
        assert not d.read(2.0).valid and "RuntimeError: no checkpoint" in d.status()


def test_a_policy_that_cannot_be_loaded_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="module:function"):
        open_device("policy", MasterCaptureConfig(device="policy", device_options={"policy": "nothing"}))
    with pytest.raises(ConfigError, match="not found"):
        load_policy(str(tmp_path / "nope.py") + ":make")
    with pytest.raises(ConfigError, match="no callable 'nope'"):
        load_policy(f"{REACH}:nope")
    with pytest.raises(ConfigError, match="cannot load"):
        load_policy("telesurg.no_such_module:policy")
    with pytest.raises(ConfigError, match="clutch 'foot' invalid; valid: policy, console"):
        open_device(
            "policy",
            MasterCaptureConfig(
                device="policy", device_options={"policy": f"{REACH}:make", "clutch": "foot"}
            ),
        )


def test_a_fourth_value_is_the_grip_and_the_scene_is_seen(tmp_path: Path) -> None:
    """A policy's 4th value sets the master's grip (the slave's jaws follow it); it sees the
    slave's jaws and the scene's objects and who holds them."""
    from telesurg.shared.messages import SceneState

    d = _device(tmp_path)
    seen: list[object] = []

    def grasp(obs: object) -> tuple[float, float, float, float]:
        seen.append(obs)
        return (0.0, 0.0, 0.001, 0.75)

    with d:
        d.policy = grasp
        d._on_scene(SceneState(H, ("peg",), (0.01,), (-0.02,), (-0.2,), ("arm1+arm2",), (0.4, 0.0)), "")
        _measure(d, following=True)
        d._on_state(OperatingState(H, "ENABLED", "joint", follow=True, grip=0.4), "")
        s = d.read(0.0)
        assert s.valid and s.grip == 0.75 and s.position[2] == pytest.approx(0.001)
        obs = seen[-1]
        assert obs.grip == 0.4  # type: ignore[attr-defined]
        assert obs.held_by == {"peg": ("arm1", "arm2")}  # type: ignore[attr-defined]
        np.testing.assert_allclose(obs.objects["peg"], (0.01, -0.02, -0.2))  # type: ignore[attr-defined]
