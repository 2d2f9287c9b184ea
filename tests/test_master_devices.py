"""The scripted master device: paths, clutch schedule, CSV playback and its errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from telesurg.services.master_capture.devices import ScriptedConfig, ScriptedDevice, make_device
from telesurg.shared.errors import ConfigError


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
    with make_device("scripted", ScriptedConfig(trajectory="csv", csv_path=str(f), clutch=[[0, 1e9]])) as dev:
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
        make_device("phantom", ScriptedConfig())
