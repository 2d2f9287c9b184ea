"""One site file per site: effective configs, shared facts, errors through the real CLI, --help.

``tests/data/site_effective_config.json`` is the effective config of every service of every site
as the per-service files (``deploy/<site>/<service>.toml``) gave it before they became one
``deploy/<site>/site.toml``; the site files must give exactly the same values.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from telesurg.services.cli import main as cli_main
from telesurg.services.launcher import (
    CONFIG_CLASSES,
    SERVICES,
    SiteSpec,
    config_class,
    default_config_dir,
    service_argv,
)
from telesurg.services.launcher.site import init, packaged_files
from telesurg.services.mapping import MappingConfig
from telesurg.services.watchdog import WatchdogConfig
from telesurg.shared.config import SITE_FILE, field_docs, load_config, read_site
from telesurg.shared.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
SITES = ("local", "plas", "vip", "serial", "slave-site", "console")
FIXTURE = json.loads((Path(__file__).parent / "data" / "site_effective_config.json").read_text())


def _telesurg(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """The real CLI in a subprocess (as a user types it)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST")}
    return subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """The CLI's own entry point in this process (exit code, stderr): the same code path as the
    subprocess runs, without another interpreter start."""
    try:
        code = cli_main(list(args))
    except SystemExit as exc:
        code = int(exc.code or 0)
    return code, capsys.readouterr().err


def _site(tmp_path: Path, text: str) -> Path:
    d = tmp_path / "site"
    d.mkdir(exist_ok=True)
    (d / SITE_FILE).write_text(text)
    return d


def test_sites_are_one_file_each() -> None:
    for site in SITES:
        files = sorted(p.name for p in (DEPLOY / site).iterdir())
        assert files == (["acl.json5", SITE_FILE] if site == "slave-site" else [SITE_FILE]), site
    assert sorted(p.relative_to(DEPLOY).as_posix() for p in DEPLOY.glob("*/*.toml")) == sorted(
        f"{s}/{SITE_FILE}" for s in SITES
    )


@pytest.mark.parametrize("site", SITES)
def test_effective_config_equals_the_per_service_files(site: str) -> None:
    """Every service of the site gets exactly the values it had from its own file."""
    assert set(FIXTURE) == set(SITES)
    for name, want in FIXTURE[site].items():
        cfg = load_config(config_class(name), DEPLOY / site / SITE_FILE, table=name)
        got = json.loads(json.dumps(dataclasses.asdict(cfg)))
        assert got == want, f"{site}/{name}: " + ", ".join(
            f"{k}: {got.get(k)!r} != {v!r}" for k, v in want.items() if got.get(k) != v
        )


def _restated(data: dict[str, Any], ref: dict[str, Any], path: str = "") -> list[str]:
    """Keys of ``data`` whose value equals the default in ``ref`` (nested tables walked)."""
    out = []
    for k, v in data.items():
        if isinstance(v, dict):
            out += _restated(v, ref[k], f"{path}{k}.")
        elif v == json.loads(json.dumps(ref[k])):
            out.append(f"{path}{k}")
    return out


def test_site_tables_hold_only_what_differs_from_the_defaults() -> None:
    """No service table restates a default (the [site] facts are stated once, on purpose)."""
    restated = [
        f"{site}: [{table}] {key}"
        for site in SITES
        for table, data in read_site(DEPLOY / site / SITE_FILE).tables.items()
        for key in _restated(data, dataclasses.asdict(config_class(table)()))
    ]
    assert restated == []


def test_shared_facts_fill_every_service_that_has_the_field(tmp_path: Path) -> None:
    d = _site(
        tmp_path,
        '[site]\nrobot = "plas"\npairs = ["m1:arm1", "m1:arm2"]\n'
        "workspace_min_mm = [-1, -2, -3]\nworkspace_max_mm = [1, 2, 3]\n"
        '[mapping]\nmode = "all_joints"\n',
    )
    f = d / SITE_FILE
    m = load_config(MappingConfig, f)  # the table is the service's name
    w = load_config(WatchdogConfig, f, table="watchdog")  # no [watchdog] table: defaults + facts
    for cfg in (m, w):
        assert cfg.model == "plas" and cfg.pairs == ["m1:arm1", "m1:arm2"]
        assert cfg.workspace_min_mm == (-1.0, -2.0, -3.0) and cfg.workspace_max_mm == (1.0, 2.0, 3.0)
    assert m.mode == "all_joints"
    assert load_config(config_class("slave_control"), f, table="slave_control").model == "plas"
    assert load_config(config_class("console"), f, table="console").arms == ["m1:arm1", "m1:arm2"]
    # --set still overrides, after the facts
    assert load_config(MappingConfig, f, ["scale=0.3"]).scale == 0.3


def test_a_table_may_restate_a_fact_only_with_the_same_value(tmp_path: Path) -> None:
    f = _site(tmp_path, '[site]\nrobot = "vip"\n[watchdog]\nmodel = "vip"\n') / SITE_FILE
    assert load_config(WatchdogConfig, f).model == "vip"
    f = _site(tmp_path, '[site]\nrobot = "vip"\n[watchdog]\nmodel = "plas"\n') / SITE_FILE
    with pytest.raises(ConfigError, match=r"\[watchdog\] model = \"plas\" restates .*\[site\] robot"):
        load_config(WatchdogConfig, f)


def test_launcher_gives_each_service_the_site_file_and_its_table() -> None:
    spec = SiteSpec(config_dir=DEPLOY / "plas", overrides={"mapping": ["scale=0.3"]})
    argv = service_argv(spec, "mapping")
    assert argv[argv.index("--config") + 1] == str(DEPLOY / "plas" / SITE_FILE)
    assert argv[argv.index("--table") + 1] == "mapping"
    assert argv[-2:] == ["--set", "scale=0.3"]  # the overrides last: they win
    router = service_argv(spec, "router")
    assert router[router.index("--table") + 1] == "router"


def test_default_site_is_the_packaged_one() -> None:
    """Found through importlib.resources (telesurg.deploy), not a path from the source tree."""
    import importlib.resources

    assert default_config_dir() == Path(str(importlib.resources.files("telesurg.deploy"))) / "local"
    assert (default_config_dir() / SITE_FILE).is_file()


def test_site_init_writes_the_packaged_files(tmp_path: Path) -> None:
    out = tmp_path / "sites"
    written = init(out)
    rel = sorted(p.relative_to(out).as_posix() for p in written)
    assert rel == sorted(p.as_posix() for p in packaged_files())
    assert {f"{s}/{SITE_FILE}" for s in SITES} | {"slave-site/acl.json5", "local.sh", "console.sh"} <= set(
        rel
    )
    assert os.access(out / "slave-site.sh", os.X_OK)
    (out / "local" / SITE_FILE).write_text("# mine\n[site]\n")
    assert init(out) == []  # an existing file is kept
    assert (out / "local" / SITE_FILE).read_text() == "# mine\n[site]\n"
    assert cli_main(["site", "check", str(out / "plas" / SITE_FILE)]) == 0


# -- errors through the real CLI (Acceptance 5) ------------------------------------------------------


def test_up_with_a_missing_site_folder_names_the_path(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    r = _telesurg("up", "--config-dir", str(DEPLOY / "pls"), "--seconds", "1", cwd=tmp_path)
    assert r.returncode != 0
    assert f"{DEPLOY / 'pls' / SITE_FILE} not found" in r.stderr, r.stderr
    code, err = _cli(capsys, "demo", "--headless", "--seconds", "1", "--config-dir", "deploy/pls")
    assert code == 2 and "deploy/pls/site.toml not found" in err, err


def test_unknown_key_names_file_table_and_the_nearest_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = _site(tmp_path, '[site]\nrobot = "mh3f"\n\n[mapping]\nscael = 0.3\n')
    for args in (
        ("up", "--config-dir", str(d), "--seconds", "1"),
        ("mapping", "--config", str(d / SITE_FILE)),
    ):
        r = _telesurg(*args, cwd=tmp_path)
        assert r.returncode == 2, (args, r.stderr)
        assert f"{d / SITE_FILE}: [mapping] unknown key 'scael' (did you mean 'scale'?)" in r.stderr, r.stderr
    code, err = _cli(capsys, "up", "--config-dir", str(DEPLOY / "local"), "--set", "mapping.scael=0.3")
    assert code == 2 and "unknown key 'scael' (did you mean 'scale'?)" in err, err
    d = _site(tmp_path, '[site]\nrobo = "mh3f"\n')
    code, err = _cli(capsys, "up", "--config-dir", str(d))
    assert code == 2 and "[site] unknown key 'robo' (did you mean 'robot'?)" in err, err
    d = _site(tmp_path, "[site]\n[mappnig]\nscale = 0.3\n")
    code, err = _cli(capsys, "up", "--config-dir", str(d))
    assert code == 2 and "unknown table [mappnig] (did you mean 'mapping'?)" in err, err


def test_wrong_type_names_file_table_and_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _site(tmp_path, '[site]\nrobot = "mh3f"\n\n[master_capture.scripted]\nradius = "big"\n')
    r = _telesurg("up", "--config-dir", str(d), cwd=tmp_path)
    assert r.returncode == 2
    assert f"{d / SITE_FILE}: [master_capture] scripted.radius must be a number, got 'big'" in r.stderr
    # a table of a service this run does not start is checked too (the mirror runs later)
    d = _site(tmp_path, '[site]\n[mirror]\ndraw_hz = "fast"\n')
    code, err = _cli(capsys, "up", "--config-dir", str(d), "--no-mirror")
    assert code == 2 and f"{d / SITE_FILE}: [mirror] draw_hz must be a number, got 'fast'" in err, err
    d = _site(tmp_path, "[site]\npairs = 3\n")
    code, err = _cli(capsys, "watchdog", "--config", str(d / SITE_FILE))
    assert code == 2 and f"{d / SITE_FILE}: [site] pairs must be" in err, err


# -- --help: every key with type, default, unit and meaning ------------------------------------------


def _all_configs() -> list[type[Any]]:
    return [config_class(n) for n in CONFIG_CLASSES]


def test_every_config_field_has_help() -> None:
    missing = [
        f"{cls.__name__}.{d.key}" for cls in _all_configs() for d in field_docs(cls) if not d.help.strip()
    ]
    assert missing == []


@pytest.mark.parametrize("service", [*SERVICES, "router", "console"])
def test_service_help_lists_every_key(service: str, capsys: pytest.CaptureFixture[str]) -> None:
    cli = {"slave_control": "slave-control", "master_capture": "master-capture"}.get(service, service)
    with pytest.raises(SystemExit) as exit_:
        cli_main([cli, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert f"table [{service}] of a site file" in out
    for d in field_docs(config_class(service)):
        if d.type != "table":
            unit = f" [{d.unit}]" if d.unit else ""
            assert f"  {d.key} : {d.type} = {d.default}{unit}\n" in out, d.key
        assert d.help.split()[0] in out


def test_mapping_help_shows_units_and_the_site_facts(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli_main(["mapping", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "  master_timeout_ms : float = 100.0 [ms]\n      master stream older than this disengages" in out
    assert "  scale : float = 0.5\n" in out and "(site file: [site] robot)" in out


def test_site_plugins_load_relative_to_the_site_file_before_the_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``[site] plugins`` (contract 1): each service and the launcher load them first."""
    d = _site(tmp_path, '[site]\nplugins = ["robots/mine.py"]\n[mapping]\nscael = 0.3\n')
    (d / "robots").mkdir()
    (d / "robots" / "mine.py").write_text("import sys\nprint('plugin mine loaded', file=sys.stderr)\n")
    r = _telesurg("mapping", "--config", str(d / SITE_FILE), cwd=tmp_path)  # from another folder
    assert r.returncode == 2, r.stderr
    assert r.stderr.index("plugin mine loaded") < r.stderr.index("unknown key 'scael'"), r.stderr
    (d / SITE_FILE).write_text('[site]\nplugins = ["robots/broken.py"]\n')
    (d / "robots" / "broken.py").write_text("raise RuntimeError('broken robot')\n")
    code, err = _cli(capsys, "up", "--config-dir", str(d))
    assert code == 2 and "broken.py" in err and "broken robot" in err, err
