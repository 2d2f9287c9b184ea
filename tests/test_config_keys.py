"""Config loading, key layout, cycle timer and stream bookkeeping."""

from __future__ import annotations

from pathlib import Path

import pytest
from telesurg.services.mapping import MappingConfig
from telesurg.services.master_capture import MasterCaptureConfig
from telesurg.shared.config import load_config
from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import Keys
from telesurg.shared.streams import StreamStats


def test_toml_and_overrides(tmp_path: Path) -> None:
    f = tmp_path / "m.toml"
    f.write_text('arm = "left"\nrate_hz = 250\n[scripted]\nradius = 0.02\n')
    cfg = load_config(MasterCaptureConfig, f, ["scripted.period_s=4", "bus.connect=['tcp/127.0.0.1:1']"])
    assert cfg.arm == "left" and cfg.rate_hz == 250.0
    assert cfg.scripted.radius == 0.02 and cfg.scripted.period_s == 4.0
    assert cfg.bus.connect == ["tcp/127.0.0.1:1"]


def test_config_errors_name_valid_options(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"valid: .*rate_hz"):
        load_config(MasterCaptureConfig, None, ["rat_hz=3"])
    with pytest.raises(ConfigError, match="must be a number"):
        load_config(MasterCaptureConfig, None, ["rate_hz=fast"])
    with pytest.raises(ConfigError, match="not found"):
        load_config(MasterCaptureConfig, tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="valid: follow, fixed"):
        load_config(MappingConfig, None, ["orientation=loose"]).validate()
    with pytest.raises(ConfigError, match="master_arm:slave_arm"):
        load_config(MappingConfig, None, ["pairs=['m1']"]).validate()


def test_keys() -> None:
    k = Keys("lab")
    assert k.master("m1", "measured_cp") == "telesurg/lab/master/m1/measured_cp"
    assert k.slave("arm2", "servo_jp") == "telesurg/lab/slave/arm2/servo_jp"
    assert k.safety("arm1", "lease") == "telesurg/lab/safety/arm1/lease"
    assert k.alive("mapping") == "telesurg/lab/alive/mapping/*"
    assert k.alive() == "telesurg/lab/alive/*/*"
    token = k.alive_token("mapping", "00ff12")
    assert token == "telesurg/lab/alive/mapping/00ff12"
    assert k.parse_alive(token) == ("mapping", "00ff12") and k.service_of_alive(token) == "mapping"
    with pytest.raises(ConfigError, match="hex digits"):
        k.alive_token("mapping", "*")
    assert k.all == "telesurg/lab/**"
    with pytest.raises(ConfigError, match="valid: servo_jp"):
        k.slave("arm1", "servo_cp")
    with pytest.raises(ConfigError, match="arm id"):
        k.slave("arm/1", "servo_jp")
    with pytest.raises(ConfigError, match="site id"):
        Keys("a b")


def test_stream_stats_gaps_reorder_restart() -> None:
    s = StreamStats()
    for seq in (0, 1, 2, 5, 4, 5, 6):
        s.accept("a", seq)
    assert (s.received, s.gaps, s.lost, s.reordered) == (5, 1, 2, 2)
    assert s.accept("b", 100)  # new source: restart, no gap
    assert s.accept("b", 0)  # same source restarted from 0
    assert s.restarts == 2 and s.gaps == 1
