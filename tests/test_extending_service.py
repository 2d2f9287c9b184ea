"""docs/extending.md, "Add a service", run as written: its row goes into a copy of the service
table (shared/service_table.py), its package next to the copied services, and ``telesurg up`` (on
loopback, a free port) starts the router and the new service from that copy (the copy shadows
the checkout's ``telesurg.shared`` and ``telesurg.services`` through ``PYTHONPATH``).
Safety events published on the site reach it; Ctrl-C stops the site cleanly and its log counts
exactly the events it logged."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from telesurg.services.launcher import free_port
from telesurg.shared.bus import BusConfig, Node

pytestmark = pytest.mark.process

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "extending.md"
SITE = "extend"


def section(title: str) -> str:
    """The text of the page's ``## title`` section."""
    text = PAGE.read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else len(text)]


def python_blocks(text: str) -> list[str]:
    """The ``python`` fenced blocks of ``text``, dedented."""
    return [textwrap.dedent(b) for b in re.findall(r"```python\n(.*?)\n\s*```", text, re.S)]


def overlay(tmp: Path, row: str, package: str) -> Path:
    """``tmp/telesurg/{shared,services}``: the checkout's, with the row and the package added."""
    for folder in ("shared", "services"):
        shutil.copytree(
            ROOT / folder, tmp / "telesurg" / folder, ignore=shutil.ignore_patterns("__pycache__")
        )
    services = tmp / "telesurg" / "services"
    table = tmp / "telesurg" / "shared" / "service_table.py"
    text = table.read_text()
    start = text.index("SERVICES: tuple[Service, ...] = (")
    end = text.index("\n)\n", start)
    table.write_text(text[:end] + "\n" + textwrap.indent(row.strip(), "    ") + text[end:])
    (services / "event_count").mkdir()
    (services / "event_count" / "__init__.py").write_text(package)
    return tmp


def test_the_page_has_the_example() -> None:
    row, package = python_blocks(section("Add a service"))
    assert row.startswith('Service("event_count"') and "def main(" in package


def test_a_service_added_by_one_row_and_its_package_runs(tmp_path: Path) -> None:
    row, package = python_blocks(section("Add a service"))
    path = overlay(tmp_path / "src", row, package)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(path), os.environ.get("PYTHONPATH", "")])}
    logs, keys, port = tmp_path / "logs", tmp_path / "keys", free_port()
    # the copy's CLI knows the command, and its help comes from the config class
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "event-count", "--help"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0 and "service" in r.stdout, r.stderr
    up = [sys.executable, "-m", "telesurg.services.cli", "up", "--site", SITE, "--port", str(port)]
    up += ["--services", "event_count", "--log-dir", str(logs), "--keys", str(keys)]
    proc = subprocess.Popen(up, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log = logs / "event_count.log"
    try:
        deadline = time.monotonic() + 60
        while not (logs / "pids.json").exists():  # written once every service is on the bus
            assert proc.poll() is None, proc.communicate()[0][-3000:]
            assert time.monotonic() < deadline, "the site did not come up in 60 s"
            time.sleep(0.2)
        bus = BusConfig(connect=[f"tcp/127.0.0.1:{port}"], keys_dir=str(keys))
        with Node(bus, SITE, "watchdog") as node:  # the watchdog is not running: its identity
            deadline = time.monotonic() + 30
            sent = 0
            while log.read_text().count("safety event ") < 3:
                assert time.monotonic() < deadline, log.read_text()[-2000:]
                sent += 1
                node.event("drill", f"drill {sent}", severity="warning")
                time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out[-3000:]
    assert "all processes stopped cleanly" in out and " ERROR " not in out, out[-3000:]
    text = log.read_text()
    logged = re.findall(r"safety event (\d+): watchdog drill \(warning\): drill \d+", text)
    assert len(logged) >= 3 and logged == [str(i + 1) for i in range(len(logged))], text[-2000:]
    assert f"counted {len(logged)} safety events: {{'watchdog/drill': {len(logged)}}}" in text, text[-2000:]
    assert " ERROR " not in text, text
