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
#: True in a pytest-xdist worker (``-n 2``): the controller alone counts the run and records it
#: (it receives every worker's reports)
_WORKER: list[bool] = [False]


def pytest_configure(config: pytest.Config) -> None:
    """Every Node of the tests (in-process or a started service) signs and verifies with one
    throw-away keyring with the site's identities; any other adds its own key on first use."""
    _WORKER[0] = hasattr(config, "workerinput")
    d = tempfile.mkdtemp(prefix="telesurg-test-keys-")
    init_keyring(os.path.join(d, "keys"), IDENTITIES)
    os.environ[KEYS_ENV] = os.path.join(d, "keys")
    _KEYRING.append(d)


#: A process test (real services on this 2-core VM) runs once more after a failure: a stall of
#: the host can make the watchdog hold mid-test (its stream deadlines are tens of ms), which is the
#: system doing its job, not the behaviour under test. A test that fails twice fails.
PROCESS_RERUNS = 1
#: More reruns than this in one run fail the run: a rerun hides a flake, many reruns hide a defect.
#: Every rerun is listed with its first failure; the last runs' reruns are counted across runs.
RERUN_BUDGET = 5
#: Seconds the unit tests (``make test-fast``: ``-m "not process and not slow" -n 2``) may take,
#: and the whole run (``make test``: the unit part, then the process part).
FAST_BUDGET_S = 90.0
SUITE_BUDGET_S = 15 * 60.0
_HISTORY = "telesurg/runs"  # pytest's cache key of the per-run records (.pytest_cache)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("process") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=PROCESS_RERUNS, reruns_delay=1))


_RERUNS: list[pytest.TestReport] = []
_SECONDS = {"unit": 0.0, "process": 0.0}
_COUNT = {"unit": 0, "process": 0}
_START = time.monotonic()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if _WORKER[0]:
        return
    kind = "process" if "process" in report.keywords else "unit"
    _SECONDS[kind] += report.duration
    if report.outcome != "rerun" and (
        report.when == "call" or (report.when == "setup" and report.outcome != "passed")
    ):
        _COUNT[kind] += 1
    if report.outcome == "rerun":  # (pytest-rerunfailures' outcome for a first failure)
        _RERUNS.append(report)


def _rerun_ids() -> list[str]:
    return sorted({r.nodeid for r in _RERUNS})


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Over the rerun budget → the run fails; the run's record goes to pytest's cache."""
    if _WORKER[0]:
        return
    if len(_rerun_ids()) > RERUN_BUDGET and exitstatus == pytest.ExitCode.OK:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
    cache = getattr(session.config, "cache", None)  # absent under -p no:cacheprovider
    if cache is not None and _COUNT["unit"] + _COUNT["process"] > 0:
        runs = cache.get(_HISTORY, [])
        runs.append(
            {
                "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
                "wall_s": round(time.monotonic() - _START, 1),
                "marks": session.config.option.markexpr or "",
                "workers": _workers(session.config),
                "unit": {"tests": _COUNT["unit"], "s": round(_SECONDS["unit"], 1)},
                "process": {"tests": _COUNT["process"], "s": round(_SECONDS["process"], 1)},
                "reruns": _rerun_ids(),
            }
        )
        cache.set(_HISTORY, runs[-20:])


def _workers(config: pytest.Config) -> int:
    """pytest-xdist's worker count (``-n``), 0 without it."""
    n = getattr(config.option, "numprocesses", None)
    return int(n) if isinstance(n, int) else 0


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The run's split (unit / process seconds against their budgets), its reruns against the
    budget with why each failed the first time, and the reruns of the last recorded runs."""
    tr = terminalreporter
    if _WORKER[0]:
        return
    tr.section("telesurg suite")
    unit, proc = _SECONDS["unit"], _SECONDS["process"]
    n = _workers(tr.config)
    tr.write_line(
        f"unit tests: {_COUNT['unit']} in {unit:.0f} s (make test-fast budget {FAST_BUDGET_S:.0f} s); "
        f"process tests: {_COUNT['process']} in {proc:.0f} s; "
        f"total {unit + proc:.0f} s (budget {SUITE_BUDGET_S:.0f} s)"
    )
    tr.write_line(
        f"this run: -m {tr.config.option.markexpr or '(all)'!r}, "
        + (f"{n} workers (test seconds summed over them), " if n else "")
        + f"{time.monotonic() - _START:.0f} s wall"
    )
    ids = _rerun_ids()
    verdict = "over the budget: the run fails" if len(ids) > RERUN_BUDGET else "within the budget"
    tr.write_line(f"reruns: {len(ids)} of a budget of {RERUN_BUDGET} ({verdict})")
    for r in _RERUNS:
        lines = r.longreprtext.strip().splitlines()
        tr.write_line(f"  rerun {r.nodeid} ({r.when}), first failure:")
        for line in lines[-25:]:
            tr.write_line(f"      {line}")
    cache = getattr(tr.config, "cache", None)
    runs = cache.get(_HISTORY, []) if cache is not None else []
    if len(runs) > 1 and runs[-1].get("marks") == "process" and runs[-2].get("marks") == "not process":
        # make test: the unit part (in parallel), then the process part (serial), one after the other
        w_unit, w_proc = runs[-2]["wall_s"], runs[-1]["wall_s"]
        tr.write_line(
            f"make test: unit part {w_unit:.0f} s + process part {w_proc:.0f} s = "
            f"{w_unit + w_proc:.0f} s wall (budget {SUITE_BUDGET_S:.0f} s)"
        )
    if len(runs) > 1:
        counts: dict[str, int] = {}
        for run in runs:
            for nodeid in run["reruns"]:
                counts[nodeid] = counts.get(nodeid, 0) + 1
        worst = sorted(counts.items(), key=lambda kv: -kv[1])[:10]
        tr.write_line(f"reruns over the last {len(runs)} recorded runs (.pytest_cache): {len(counts)} tests")
        for nodeid, n in worst:
            tr.write_line(f"  {n:3d}× {nodeid}")


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
