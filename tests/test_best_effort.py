"""The best-effort services (mirror, camera) start at normal priority and step down once up.

At the lowest priority from the start, the mirror's imports and set-up got ~2 % of a CPU on a
host whose two cores other programs kept busy: ``telesurg demo`` then failed with "mirror did not
come up within 30 s". Now it starts like any program, steps down (``SCHED_IDLE``, its autogroup
at nice 19) once it is set up, and the launcher lifts it back before it asks it to stop so it
can save its recording. Real launcher, router, mirror and CPU hogs (processes in sessions of
their own, as other programs on the host).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import wait_until
from telesurg.services.launcher import BEST_EFFORT_NICE, Site, SiteSpec, best_effort_nice, free_port
from telesurg.shared.errors import ConfigError
from telesurg.shared.timing import BEST_EFFORT_ENV

AUTOGROUPS = Path("/proc/self/autogroup").exists()


def _autogroup_nice(pid: int) -> int | None:
    if not AUTOGROUPS:
        return None
    return int(Path(f"/proc/{pid}/autogroup").read_text().split()[-1])  # "/autogroup-123 nice 19"


def _policies(pid: int) -> set[int]:
    out = set()
    for t in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(OSError):  # a thread that just ended
            out.add(os.sched_getscheduler(int(t)))
    return out


@contextmanager
def _hogs(n: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``n`` busy loops at normal priority, each in a session (an autogroup) of its own."""
    procs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True) for _ in range(n)
    ]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _mirror_site(tmp_path: Path) -> SiteSpec:
    return SiteSpec(
        site="besteffort",
        port=free_port(),
        services=("mirror",),
        overrides={"mirror": [f"save={json.dumps(str(tmp_path / 'run.rrd'))}"]},
        log_dir=tmp_path,
    )


def test_the_nice_value_is_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(BEST_EFFORT_ENV, raising=False)
    assert best_effort_nice() == BEST_EFFORT_NICE == 19
    monkeypatch.setenv(BEST_EFFORT_ENV, "7")
    assert best_effort_nice() == 7
    for bad in ("-5", "20", "low"):
        monkeypatch.setenv(BEST_EFFORT_ENV, bad)
        with pytest.raises(ConfigError, match=r"0\.\.19"):
            best_effort_nice()
        with pytest.raises(ConfigError, match=r"0\.\.19"):  # the launcher starts nothing
            Site(SiteSpec(port=free_port(), services=())).start()


@pytest.mark.process
def test_the_mirror_comes_up_on_a_busy_host_and_then_steps_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(BEST_EFFORT_ENV, raising=False)
    with _hogs(2) as hogs, Site(_mirror_site(tmp_path)) as site:  # raised before: not up in 30 s
        pid = site.pid("mirror")
        stepped = wait_until(lambda: _policies(pid) == {os.SCHED_IDLE}, 20)
        policies, group = _policies(pid), _autogroup_nice(pid)
        assert all(h.poll() is None for h in hogs)
        codes = site.stop()
    assert stepped, f"the mirror's threads have policies {policies}, not SCHED_IDLE alone"
    assert group in (None, 19), group
    assert codes["mirror"] == 0, (tmp_path / "mirror.log").read_text()[-2000:]
    log = (tmp_path / "mirror.log").read_text()
    assert "best-effort from now on" in log and "recording to" in log, log[-2000:]
    assert (tmp_path / "run.rrd").stat().st_size > 0


@pytest.mark.process
def test_nice_0_keeps_the_mirror_at_normal_priority(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(BEST_EFFORT_ENV, "0")
    with Site(_mirror_site(tmp_path)) as site:
        pid = site.pid("mirror")
        said = wait_until(lambda: "at normal priority" in (tmp_path / "mirror.log").read_text(), 20)
        policies, group = _policies(pid), _autogroup_nice(pid)
    assert said, (tmp_path / "mirror.log").read_text()[-2000:]
    assert policies == {os.SCHED_OTHER}, policies
    assert group in (None, 0), group
