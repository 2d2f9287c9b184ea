"""``telesurg up`` runs its site in a session (a scheduler autogroup) of its own, behind a parent
that stays in the shell's process group: Ctrl-C and a kill of that parent still stop everything,
and busy jobs of the same shell no longer share the launcher's CPU share (shared/session.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import wait_until
from helpers import autogroup
from telesurg.services.launcher import free_port, wait_port
from telesurg.shared.session import OWN_SESSION_ENV, autogroups_on

pytestmark = pytest.mark.skipif(
    not autogroups_on(), reason="the kernel has no scheduler autogroups (kernel.sched_autogroup_enabled)"
)


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(c) for c in text.split()]


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.fixture
def site_up(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[bytes], int, Path]]:
    """``telesurg up`` (router + watchdog) started as a shell would: in the test's session."""
    port = free_port()
    log = tmp_path / "up.log"
    argv = [sys.executable, "-m", "telesurg.services.cli", "up", "--port", str(port)]
    argv += ["--log-dir", str(tmp_path / "logs"), "--services", "watchdog"]
    env = {k: v for k, v in os.environ.items() if k != OWN_SESSION_ENV}
    with log.open("wb") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        assert wait_port("127.0.0.1", port, 30), "router did not come up"
        yield proc, port, log
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_the_launcher_runs_in_a_session_of_its_own_and_ctrl_c_stops_it(
    site_up: tuple[subprocess.Popen[bytes], int, Path],
) -> None:
    proc, _, log = site_up
    assert wait_until(lambda: "site 'local' up" in log.read_text(), 30), log.read_text()
    (launcher,) = _children(proc.pid)
    assert os.getsid(launcher) == launcher, "the launcher is not a session leader"
    assert autogroup(launcher) != autogroup("self"), "the launcher shares the shell's autogroup"
    services = _children(launcher)
    assert len(services) == 2, services  # router + watchdog, the launcher's own children
    proc.send_signal(signal.SIGINT)  # Ctrl-C reaches the shell's foreground group: the parent
    assert proc.wait(30) == 0, log.read_text()
    assert "all processes stopped cleanly" in log.read_text()
    assert not any(_alive(p) for p in (launcher, *services))


def test_a_killed_parent_still_stops_the_site(site_up: tuple[subprocess.Popen[bytes], int, Path]) -> None:
    proc, port, log = site_up
    assert wait_until(lambda: "site 'local' up" in log.read_text(), 30), log.read_text()
    (launcher,) = _children(proc.pid)
    services = _children(launcher)
    proc.kill()  # SIGKILL: the parent forwards nothing; the child learns it from the kernel
    proc.wait()
    assert wait_until(lambda: not any(_alive(p) for p in (launcher, *services)), 30), log.read_text()
    assert "all processes stopped cleanly" in log.read_text()  # SIGTERM: an orderly stop
    assert not wait_port("127.0.0.1", port, 0.5), "the router still listens"


def test_the_exit_code_and_errors_come_back_from_the_child(tmp_path: Path) -> None:
    argv = [sys.executable, "-m", "telesurg.services.cli", "up", "--services", "nonesuch"]
    env = {k: v for k, v in os.environ.items() if k != OWN_SESSION_ENV}
    r = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 2
    assert "unknown service(s) ['nonesuch']" in r.stderr


def test_own_session_0_keeps_the_launcher_in_the_callers_process(tmp_path: Path) -> None:
    # port 0: the router picks a free one (a port chosen here could be taken by another test
    # worker before the router binds it)
    argv = [sys.executable, "-m", "telesurg.services.cli", "up", "--port", "0"]
    argv += ["--log-dir", str(tmp_path / "logs"), "--services", "watchdog", "--seconds", "60"]
    err = tmp_path / "stderr.txt"
    with err.open("w") as f:
        proc = subprocess.Popen(argv, env={**os.environ, OWN_SESSION_ENV: "0"}, stderr=f)
    try:
        # the site is up (the watchdog started, not still importing: Ctrl-C then is an orderly stop)
        assert wait_until(lambda: "Ctrl-C stops everything" in err.read_text(), 60), err.read_text()
        # the router is the launcher's own child: no parent/child pair
        assert wait_until(lambda: len(_children(proc.pid)) == 2, 30), _children(proc.pid)
        assert os.getsid(proc.pid) == os.getsid(0)
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0, err.read_text()[-3000:]
