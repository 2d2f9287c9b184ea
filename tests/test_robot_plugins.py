"""``--plugin FILE``: every service, ``telesurg up`` / ``demo`` and ``device emulate-slave`` load a
robot plugin before they validate their config, and the launcher hands it to every service."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
from telesurg.services.launcher import add_site_args, service_argv, spec_from_args
from telesurg.shared import robots
from telesurg.shared.errors import ConfigError
from telesurg.tools import emulate as device

TRI3 = str(Path(__file__).resolve().parent / "robots" / "tri3" / "tri3.py")


def telesurg(*argv: str) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "telesurg.services.cli", *argv]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)


def test_service_loads_the_plugin_before_validating_its_config() -> None:
    # the plugin's robot is known (its modes are checked, not "unknown robot"); still a config
    # error: the cartesian mode does not fit it, so the service stops before touching the bus
    r = telesurg(
        "mapping",
        "--plugin",
        TRI3,
        "--connect",
        "tcp/127.0.0.1:9",
        "--set",
        'model="tri3"',
        "--set",
        'mode="cartesian"',
    )
    assert r.returncode == 1, r.stderr
    assert "mapping mode 'cartesian' does not fit robot model 'tri3'; modes that fit it: position" in r.stderr
    r = telesurg(
        "mapping", "--connect", "tcp/127.0.0.1:9", "--set", 'model="tri3"', "--set", 'mode="position"'
    )
    assert r.returncode == 1  # without the plugin: unknown
    assert "robot model 'tri3' unknown; valid: mh3f, plas, vip" in r.stderr


def test_a_bad_plugin_is_a_clear_error(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    r = telesurg("watchdog", "--plugin", str(tmp_path / "nope.py"))
    assert r.returncode == 2
    assert f"telesurg watchdog: robot plugin '{tmp_path / 'nope.py'}': no such file" in r.stderr
    broken = tmp_path / "broken.py"
    broken.write_text("import not_a_module_anywhere\n")
    assert device.main(["--plugin", str(broken), "emulate-slave", "--model", "mh3f"]) == 2
    assert "failed to load: ModuleNotFoundError" in capsys.readouterr().err


def test_device_emulator_offers_the_plugin_robots(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:  # the model is accepted; only the transport is missing
        device.main(["emulate-slave", "--plugin", TRI3, "--model", "tri3"])
    assert exc.value.code == 2
    assert "emulate-slave needs a transport: --pty" in capsys.readouterr().err
    assert "tri3" in robots.names()


def test_launcher_passes_the_plugins_to_every_service_but_the_router(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_site_args(parser)
    (tmp_path / "site.toml").write_text('[site]\nrobot = "mh3f"\n')
    args = parser.parse_args(["--plugin", TRI3, "--port", "7999", "--config-dir", str(tmp_path)])
    spec = spec_from_args(args, ["watchdog", "mapping"])
    assert spec.plugins == (TRI3,)
    for name in ("watchdog", "slave_control", "mapping", "mirror", "master_capture"):
        argv = service_argv(spec, name)
        assert argv[argv.index("--plugin") + 1] == TRI3
    assert "--plugin" not in service_argv(spec, "router")
    with pytest.raises(ConfigError, match="no such file"):
        spec_from_args(parser.parse_args(["--plugin", str(tmp_path / "x.py")]), ["mapping"])
