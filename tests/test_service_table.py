"""The service table (shared/service_table.py) is the one list of services: the CLI's commands,
the launcher's start / stop order and priorities and the site file's tables come from it, and
every row names a real package with a ``main`` and its config class."""

from __future__ import annotations

import importlib
import inspect

import pytest
from telesurg.services import cli, launcher
from telesurg.shared import config
from telesurg.shared.service_table import ROUTER, SERVICES, Service


def kept(order: tuple[str, ...], names: tuple[str, ...]) -> tuple[str, ...]:
    """``order`` without the services not in ``names`` (a row added later does not matter)."""
    return tuple(n for n in order if n in names)


def test_rows_are_unique_and_ordered() -> None:
    names = [s.name for s in SERVICES]
    assert len(set(names)) == len(names)
    assert len({s.stop for s in SERVICES}) == len(SERVICES), "two rows share a stop position"
    (router,) = [s for s in SERVICES if s.name == ROUTER]
    assert router.stop == max(s.stop for s in SERVICES)
    # start stages: the router alone first; the master once the services it drives listen
    stage = {s.name: s.start for s in SERVICES}
    assert [n for n, k in stage.items() if k <= stage[ROUTER]] == [ROUTER]
    assert stage["master_capture"] > max(stage[n] for n in ("watchdog", "slave_control", "mapping"))
    assert all(s.start > stage["master_capture"] for s in SERVICES if s.on_request)


@pytest.mark.parametrize("row", SERVICES, ids=lambda s: s.name)
def test_each_row_names_its_package_main_and_config(row: Service) -> None:
    module = importlib.import_module(row.module)
    assert list(inspect.signature(module.main).parameters) == ["argv"]
    cfg = getattr(module, row.config)()
    assert cfg.service == row.name


def test_the_cli_the_launcher_and_the_site_file_follow_the_table() -> None:
    for s in SERVICES:
        assert cli.COMMANDS[s.cli] == (s.module, s.help)
        assert launcher.CLI_NAME[s.name] == s.cli and launcher.CONFIG_CLASSES[s.name] == (s.module, s.config)
        assert s.name in launcher.STOP_ORDER and s.name in config.SERVICE_TABLES
        started = s.name in (*launcher.SERVICES, *launcher.ON_REQUEST)
        assert started == (s.name != ROUTER)
    assert set(cli.COMMANDS) >= {"up", "demo", "bench", "experiment", "device"}
    # the orders a site starts and stops in: the watchdog stops right after the console (its last
    # word revokes every lease: an orderly stop is no fault), the mirror after the others, the router last
    start = ("watchdog", "slave_control", "mapping", "mirror", "master_capture", "camera")
    stop = ("console", "watchdog", "master_capture", "mapping", "slave_control", "camera", "mirror", "router")
    assert kept(launcher.SERVICES, start) == start and kept(launcher.STOP_ORDER, stop) == stop
    control = ("router", "watchdog", "slave_control", "mapping", "master_capture")
    assert kept(launcher.CONTROL, stop) == control and kept(launcher.ZID_SERVICES, stop) == control[1:]
    assert kept(launcher.NICE, stop) == ("mirror", "camera") and kept(launcher.OPTIONAL, stop) == ("camera",)
    assert kept(launcher.ON_REQUEST, stop) == ("console",)


def test_a_row_flag_reaches_the_command_line() -> None:
    """A row's ``args`` are on its command line (the console's ``--web``), no one else's."""
    spec = launcher.SiteSpec(port=7999, services=("watchdog", "console"))
    assert "--web" in launcher.service_argv(spec, "console")
    assert "--web" not in launcher.service_argv(spec, "watchdog")
    argv = launcher.service_argv(spec, "slave_control")
    assert argv[argv.index("telesurg.services.cli") + 1] == "slave-control"


def test_a_tool_without_its_extra_says_what_to_install(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cli, "missing_extra", lambda extra: ["matplotlib"] if extra == "lab" else [])
    assert cli.main(["bench", "faults"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [
        "telesurg bench needs the 'lab' extra (matplotlib not installed): pip install 'telesurg[lab]' "
        "(in a checkout: pip install -e '.[lab]')"
    ]
    assert cli.missing_extra("no-such-extra") == []
