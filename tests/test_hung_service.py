"""A service that does not stop says where it is stuck.

Every service writes each thread's Python stack to its log on ``SIGUSR1`` and goes on running;
the launcher asks for those stacks before it kills a service that did not stop in time, and its
error line says where to read them. A real router and watchdog, started by the launcher.
"""

from __future__ import annotations

import logging
import signal
import time
from pathlib import Path

import pytest
from telesurg.services.common import STACKS_SIGNAL
from telesurg.services.launcher import Site, SiteSpec, free_port

pytestmark = pytest.mark.process


def _dump(path: Path, count: int, timeout: float = 5.0) -> str:
    """The log once it holds ``count`` stack dumps and has stopped growing (a dump is written
    thread by thread)."""
    deadline = time.monotonic() + timeout
    last = ""
    while time.monotonic() < deadline:
        time.sleep(0.2)
        got = path.read_text(errors="replace")
        if got.count("most recent call first") >= count and got == last:
            return got
        last = got
    return last


def test_a_service_writes_its_stacks_and_goes_on(tmp_path: Path) -> None:
    spec = SiteSpec(site="stacks", port=free_port(), services=("watchdog",), log_dir=tmp_path)
    log = tmp_path / "watchdog.log"
    with Site(spec) as site:
        p = site.procs["watchdog"]
        p.send_signal(STACKS_SIGNAL)
        text = _dump(log, 1)
        assert p.poll() is None, "the watchdog died on the stack-dump signal"
    assert STACKS_SIGNAL == signal.SIGUSR1
    assert "most recent call first" in text, text[-2000:]
    # the main thread is in the watchdog's loop (its wait for the next tick)
    assert "services/watchdog/__init__.py" in text and " in run" in text, text[-2000:]
    assert p.returncode == 0, "the watchdog did not stop cleanly after the dump"


def test_the_launcher_asks_a_straggler_for_its_stacks_before_killing_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    spec = SiteSpec(site="straggler", port=free_port(), services=("watchdog",), log_dir=tmp_path)
    site = Site(spec)
    site.start()
    try:
        before = (tmp_path / "watchdog.log").read_text(errors="replace")
        assert "most recent call first" not in before
        with caplog.at_level(logging.ERROR, logger="telesurg"):
            codes = site.stop(timeout=0.0)  # nothing stops in 0 s: every service is a straggler
    finally:
        site.stop()
    lines = [r.getMessage() for r in caplog.records if "did not stop" in r.getMessage()]
    wd = [m for m in lines if m.startswith("watchdog")]
    assert wd and f"its threads' stacks are in {tmp_path / 'watchdog.log'}" in wd[0], lines
    text = _dump(tmp_path / "watchdog.log", 1)
    assert "most recent call first" in text and "services/watchdog/__init__.py" in text, text[-2000:]
    assert set(codes) == {"watchdog", "router"}
    assert all(p.poll() is not None for p in site.procs.values()), "a straggler outlived stop()"
