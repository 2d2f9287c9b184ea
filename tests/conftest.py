"""Shared fixtures: an in-process zenoh router on a free loopback port; one test keyring for the
whole session (``$TELESURG_KEYS``, inherited by every process a test starts)."""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator

import pytest
from telesurg.services.common import gl_backend
from telesurg.services.launcher import free_port
from telesurg.shared.auth import IDENTITIES, KEYS_ENV, init_keyring
from telesurg.shared.bus import BusConfig, open_session

# MuJoCo picks its OpenGL backend when it is first imported: the camera tests render offscreen in
# this process, after other tests imported mujoco (the camera service sets it itself)
os.environ.setdefault("MUJOCO_GL", gl_backend() or "egl")
_KEYRING: list[str] = []


def pytest_configure(config: pytest.Config) -> None:
    """Every Node of the tests (in-process or a started service) signs and verifies with one
    throw-away keyring with the site's identities; any other adds its own key on first use."""
    d = tempfile.mkdtemp(prefix="telesurg-test-keys-")
    init_keyring(os.path.join(d, "keys"), IDENTITIES)
    os.environ[KEYS_ENV] = os.path.join(d, "keys")
    _KEYRING.append(d)


#: A process test (real services on this 2-core VM) runs once more after a failure: a stall of
#: the host can make the watchdog hold mid-test (its stream deadlines are tens of ms), which is the
#: system doing its job, not the behaviour under test. A test that fails twice fails; the rerun
#: shows in the summary (``R``) and in pytest-rerunfailures' report, so flakes stay visible.
PROCESS_RERUNS = 1


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("process") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=PROCESS_RERUNS, reruns_delay=1))


_RERUNS: list[pytest.TestReport] = []


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.outcome == "rerun":  # (pytest-rerunfailures' outcome for a first failure)
        _RERUNS.append(report)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """Why each rerun test failed the first time (pytest-rerunfailures names it, not why): the
    end of its failure text, so a flake can be told from a defect that a rerun hid."""
    if not _RERUNS:
        return
    terminalreporter.section("first failures of the rerun tests")
    for r in _RERUNS:
        lines = r.longreprtext.strip().splitlines()
        terminalreporter.write_line(f"{r.nodeid} ({r.when}):")
        for line in lines[-25:]:
            terminalreporter.write_line(f"    {line}")


def pytest_unconfigure(config: pytest.Config) -> None:
    for d in _KEYRING:
        shutil.rmtree(d, ignore_errors=True)


@pytest.fixture
def endpoint() -> Iterator[str]:
    """``tcp/127.0.0.1:<port>`` of a zenoh router running in this process."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    try:
        yield ep
    finally:
        router.close()  # type: ignore[no-untyped-call]


def wait_until(pred: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll ``pred`` every 10 ms until true or ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()
