"""The built wheel: imports only as ``telesurg``, ships the site files and deploy scripts, and an
install of it into a fresh venv outside the checkout runs the demo on its packaged site file.

The wheel is built from a copy of the user's folders (so the checkout gets no build/ litter) with
``pip wheel --no-deps``; the fresh venv (``python -m venv``, no system site-packages) installs it
with its pinned dependencies from the same index / pip cache. Measured on the 2-core development
host while other work loaded it: build ~3-6 s, venv + install ~60-70 s, demo ~15 s: ~95 s in all.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from telesurg.tools.bench.harness import OBSERVER_LOSS_MAX

ROOT = Path(__file__).resolve().parents[1]
#: the user's folders and the files the build reads
SOURCES = ("pyproject.toml", "setup.py", "README.md", "shared", "services", "tools", "gym", "deploy")
#: the folders mapped under ``telesurg`` (pyproject.toml [tool.setuptools.package-dir])
FOLDERS = ("shared", "services", "tools", "gym", "deploy")
SITES = ("local", "plas", "vip", "serial", "slave-site", "console")


def source_packages() -> set[str]:
    """``telesurg.<folder>…`` of every folder with an ``__init__.py`` under the mapped folders."""
    return {
        ".".join(("telesurg", *p.parent.relative_to(ROOT).parts))
        for top in FOLDERS
        for p in (ROOT / top).rglob("__init__.py")
        if "__pycache__" not in p.parts
    }


def test_every_folder_is_mapped_under_telesurg() -> None:
    """pyproject maps each user folder to ``telesurg.<folder>`` (setup.py lists the packages
    under them); the service table's packages are among them."""
    from telesurg.shared.service_table import SERVICES

    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert cfg["package-dir"] == {f"telesurg.{f}": f for f in FOLDERS}
    assert "packages" not in cfg  # (a hand-kept list drifts: setup.py finds them)
    assert {s.module for s in SERVICES} <= source_packages()


def _clean_env(venv: Path) -> dict[str, str]:
    """The environment of a user of the installed package: its venv first, nothing of ours."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME") and not k.startswith("PYTEST")
    }
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)
    return env


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCES:
        p = ROOT / name
        if p.is_dir():
            shutil.copytree(p, src / name, ignore=ignore)
        else:
            shutil.copy2(p, src / name)
    out = tmp / "dist"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(src)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    (whl,) = out.glob("telesurg-*.whl")
    return whl


@pytest.mark.process
def test_wheel_is_telesurg_only_and_ships_the_sites(wheel: Path) -> None:
    with zipfile.ZipFile(wheel) as z:
        infos = {i.filename: i for i in z.infolist()}
    top = {n.split("/")[0] for n in infos if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"telesurg"}, top  # no shared/, no services/ at the top
    packaged = {n.removesuffix("/__init__.py").replace("/", ".") for n in infos if n.endswith("/__init__.py")}
    assert packaged == source_packages(), packaged ^ source_packages()
    deploy = {n.removeprefix("telesurg/deploy/") for n in infos if n.startswith("telesurg/deploy/")}
    want = {f"{s}/site.toml" for s in SITES} | {
        "slave-site/acl.json5",
        "local.sh",
        "slave-site.sh",
        "console.sh",
    }
    assert want <= deploy, want - deploy
    for script in ("local.sh", "slave-site.sh", "console.sh"):
        mode = infos[f"telesurg/deploy/{script}"].external_attr >> 16
        assert mode & 0o111, f"{script} is not executable in the wheel"


@pytest.fixture(scope="module")
def fresh_venv(wheel: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    venv = tmp_path_factory.mktemp("venv") / "v"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    r = subprocess.run(
        [str(venv / "bin" / "python"), "-m", "pip", "install", "-q", str(wheel)],
        capture_output=True,
        text=True,
        timeout=900,
        env=_clean_env(venv),
    )
    assert r.returncode == 0, r.stdout + r.stderr
    yield venv
    shutil.rmtree(venv, ignore_errors=True)


@pytest.mark.process
def test_installed_package_imports_from_the_venv_only(fresh_venv: Path, tmp_path: Path) -> None:
    code = (
        "import importlib.util, json, telesurg.services, telesurg.shared, telesurg.deploy\n"
        "print(json.dumps({'paths': [telesurg.services.__file__, telesurg.shared.__file__,"
        " telesurg.deploy.__file__], 'top': [importlib.util.find_spec(n) is not None"
        " for n in ('shared', 'services')]}))"
    )
    r = subprocess.run(
        [str(fresh_venv / "bin" / "python"), "-c", code],
        cwd=tmp_path,
        env=_clean_env(fresh_venv),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for p in out["paths"]:
        assert Path(p).is_relative_to(fresh_venv), p  # the installed wheel, not the checkout
    assert out["top"] == [False, False]


@pytest.mark.process
def test_installed_demo_runs_on_the_packaged_site_file(fresh_venv: Path, tmp_path: Path) -> None:
    """Acceptance 4: ``telesurg demo --headless --seconds 10 --report r.json`` from a temp cwd."""
    env = _clean_env(fresh_venv)
    telesurg = str(fresh_venv / "bin" / "telesurg")
    cmd = [telesurg, "demo", "--headless", "--seconds", "10", "--port", "0", "--report", "r.json"]
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-4000:]
    report = json.loads((tmp_path / "r.json").read_text())
    site_file = Path(report["site_file"])
    assert site_file.is_relative_to(fresh_venv) and site_file.parts[-3:] == ("deploy", "local", "site.toml")
    assert report["streams"], report
    for name, s in report["streams"].items():
        # the report's node is an observer the router drops for when this host leaves it behind
        # (as in tests/test_demo.py): a few samples, never rejections
        assert s["received"] > 0 and s["lost"] <= OBSERVER_LOSS_MAX * s["received"] and s["rejected"] == 0, (
            name,
            s,
        )
    assert set(report["exit_codes"].values()) == {0}
    # --help reads the config keys' help from the installed sources
    r = subprocess.run([telesurg, "mapping", "--help"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 0 and "  master_timeout_ms : float = 100.0 [ms]\n" in r.stdout, r.stdout[-2000:]
    # the site files come out of the package to edit
    r = subprocess.run(
        [telesurg, "site", "init", "sites"], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "sites" / "plas" / "site.toml").read_text() == (
        ROOT / "deploy/plas/site.toml"
    ).read_text()
    assert os.access(tmp_path / "sites" / "local.sh", os.X_OK)


@pytest.mark.process
def test_installed_runtime_needs_no_lab_extra(fresh_venv: Path, tmp_path: Path) -> None:
    """The wheel without extras has no matplotlib (psutil may come with rerun-sdk); a tool that
    needs the lab extra says what to install, in one line, and changes nothing; the tools
    without heavy dependencies run."""
    env = _clean_env(fresh_venv)
    python, telesurg = str(fresh_venv / "bin" / "python"), str(fresh_venv / "bin" / "telesurg")
    code = "import importlib.util as u; print([u.find_spec(n) is None for n in ('matplotlib', 'mink')])"
    r = subprocess.run([python, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.stdout.strip() == "[True, True]", r.stdout + r.stderr
    for cmd in (["bench", "faults"], ["experiment", "shim-mapping", "--out", "x"]):
        r = subprocess.run(
            [telesurg, *cmd], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60
        )
        assert r.returncode == 2, r.stderr
        (line,) = r.stderr.strip().splitlines()
        assert "'lab' extra" in line and "pip install 'telesurg[lab]'" in line and "matplotlib" in line, line
    assert list(tmp_path.iterdir()) == []
    r = subprocess.run(
        [telesurg, "device", "emulate", "--help"], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert r.returncode == 0 and "--pty" in r.stdout, r.stderr
