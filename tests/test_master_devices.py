"""The scripted master device: paths, clutch schedule, CSV playback and its errors; a refused
engage pressed again (unit, and against the running services)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from telesurg.services.master_capture.devices import open_device
from telesurg.services.master_capture.devices.scripted import ScriptedConfig, ScriptedDevice
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import SafetyState, TeleopState
from telesurg.tools.bench.harness import Pipeline


def test_circle_radius_period_and_clutch_schedule() -> None:
    cfg = ScriptedConfig(radius=0.03, period_s=4.0, center=(0.1, 0.0, 0.2), clutch=[[1.0, 2.0]])
    with ScriptedDevice(cfg) as dev:
        pts = np.array([dev.read(t).position for t in np.linspace(0, 4, 200)])
        assert np.allclose(np.linalg.norm(pts[:, :2] - (0.1, 0.0), axis=1), 0.03)
        assert np.allclose(pts[:, 2], 0.2)
        assert np.allclose(pts[0], pts[-1])
        assert [dev.read(t).clutch for t in (0.5, 1.0, 1.5, 2.0)] == [False, True, True, False]
    with ScriptedDevice(ScriptedConfig(clutch=[[1.0, 2.0]], clutch_repeat_s=3.0)) as dev:
        assert [dev.read(t).clutch for t in (3.5, 4.5, 5.5, 7.5)] == [False, True, False, True]


def test_csv_playback_loops_and_gates_clutch(tmp_path: Path) -> None:
    f = tmp_path / "path.csv"
    f.write_text("t,x,y,z,clutch\n0,0,0,0,1\n1,0.01,0,0,1\n2,0.01,0.01,0,0\n")
    with ScriptedDevice(ScriptedConfig(trajectory="csv", csv_path=str(f), clutch=[[0, 1e9]])) as dev:
        assert math.isclose(dev.read(0.5).position[0], 0.005)
        assert dev.read(0.5).clutch and not dev.read(1.9).clutch
        assert math.isclose(dev.read(2.5).position[0], 0.005)  # looped


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("t,x,y,z\n0,0,0,0\n", ">= 2 rows"),
        ("0,0,0,0\n0,1,1,1\n", "t increasing"),
        ("0,a,0,0\n1,0,0,0\n", "path.csv"),
    ],
)
def test_csv_errors(tmp_path: Path, content: str, needle: str) -> None:
    f = tmp_path / "path.csv"
    f.write_text(content)
    with (
        pytest.raises(ConfigError, match=needle),
        ScriptedDevice(ScriptedConfig(trajectory="csv", csv_path=str(f))),
    ):
        pass


def test_config_errors() -> None:
    with pytest.raises(ConfigError, match="valid: circle, figure8, csv"):
        ScriptedDevice(ScriptedConfig(trajectory="spiral"))
    with pytest.raises(ConfigError, match="t_on <= t_off"):
        ScriptedDevice(ScriptedConfig(clutch=[[2.0, 1.0]]))
    with pytest.raises(ConfigError, match="valid: scripted"):
        open_device("phantom")


def test_a_refused_engage_is_answered_by_a_release_and_a_new_press_within_the_retry_time() -> None:
    # the schedule keeps the pedal down from 1 s on; the mapping refuses the engage at 1.0 s
    with ScriptedDevice(ScriptedConfig(clutch=[[1.0, 1e9]], retry_refused_engage_s=0.5)) as dev:
        retry = dev.engage_retry
        assert retry is not None
        assert dev.read(1.0).clutch
        assert retry.refused(since_ns=111)
        assert not retry.refused(since_ns=111)  # the same refusal re-sent at 10 Hz: not a new one
        released = [dev.read(t).clutch for t in (1.01, 1.2, 1.5)]
        assert released == [False, False, False]  # released at once, for the mapping to see
        assert dev.read(1.51).clutch  # pressed again 0.5 s after: a new press
        # refused again (the slave still not allowed): released again, pressed again
        assert retry.refused(since_ns=222)
        assert not dev.read(1.6).clutch and dev.read(2.11).clutch
        assert retry.retries == 2
    # a refusal while the schedule has the pedal up is dropped: no release later on
    with ScriptedDevice(ScriptedConfig(clutch=[[1.0, 2.0]], clutch_repeat_s=3.0)) as dev:
        assert dev.engage_retry is not None and dev.engage_retry.retry_s == 1.0  # on by default
        dev.read(2.5)
        dev.engage_retry.refused(since_ns=1)
        assert not dev.read(2.6).clutch and dev.read(4.0).clutch and dev.engage_retry.retries == 0
    # off: the pedal stays down however often the mapping refuses
    with ScriptedDevice(ScriptedConfig(clutch=[[1.0, 1e9]], retry_refused_engage_s=0.0)) as dev:
        assert dev.engage_retry is None and all(dev.read(t).clutch for t in (1.0, 1.5, 2.0))
    with pytest.raises(ConfigError, match=r"retry_refused_engage_s=0.01 outside \[0.1, 60\] s \(0: off\)"):
        ScriptedDevice(ScriptedConfig(retry_refused_engage_s=0.01))


@pytest.mark.process
def test_the_scripted_pedal_presses_again_after_a_refused_engage(tmp_path: Path) -> None:
    """The pedal is held down from 0.5 s on and never released by its schedule. The arm is
    e-stopped before master_capture starts, so its first engage is refused for sure; the pedal
    then presses again every second while the refusals go on, and once the e-stop is reset the
    next press engages: within seconds, where a pedal held down would never engage again."""
    held = ["scripted.clutch=[[0.5, 1e9]]", "scripted.clutch_repeat_s=0.0"]
    held.append("scripted.retry_refused_engage_s=1.0")
    ov = {"master_capture": held}
    logs = tmp_path / "logs"
    with Pipeline(logs, mirror=False, impair=False, master=False, probe=False, overrides=ov) as pipe:
        lock = threading.Lock()
        teleop: list[tuple[float, TeleopState]] = []
        safety: list[str] = []

        def on_teleop(m: TeleopState, key: str) -> None:
            with lock:
                teleop.append((time.monotonic(), m))

        def on_safety(m: SafetyState, key: str) -> None:
            with lock:
                safety.append(m.state)

        k = pipe.node.keys
        pipe.node.subscribe(k.mapping("arm1", "teleop_state"), TeleopState, on_teleop, sources=["mapping"])
        pipe.node.subscribe(k.safety("arm1", "state"), SafetyState, on_safety, sources=["watchdog"])
        pipe.estop("estop", "arm1")
        assert pipe.wait(lambda: "ESTOP" in safety, 10.0), safety

        def refusals() -> list[tuple[float, int]]:  # (time received, since_ns) of each refusal
            with lock:
                out = {m.since_ns: t for t, m in teleop if (m.previous, m.state) == ("ENGAGING", "HOLDING")}
            return sorted((t, s) for s, t in out.items())

        def engaged() -> float | None:
            with lock:
                return next((t for t, m in teleop if m.state == "ENABLED"), None)

        pipe.site.restart("master_capture")
        assert pipe.wait(lambda: len(refusals()) >= 1, 30.0), "no engage was refused"  # + start-up
        time.sleep(3.5)
        got = refusals()
        gaps = np.diff([t for t, _ in got])
        print(f"{len(got)} refusals in {got[-1][0] - got[0][0]:.2f} s, gaps {np.round(gaps, 2)} s")
        assert engaged() is None, "engaged while e-stopped"
        # the schedule alone presses once: every further refusal is a press again (about 1 s apart)
        assert len(got) >= 3 and gaps.max() < 2.5, got
        t_reset = time.monotonic()
        pipe.estop("reset", "arm1")
        assert pipe.wait(lambda: engaged() is not None, 10.0), teleop[-1]
        t_engaged = engaged()
        assert t_engaged is not None
        print(f"engaged {t_engaged - t_reset:.2f} s after the e-stop reset (the schedule never released)")
        assert t_engaged - t_reset < 5.0
