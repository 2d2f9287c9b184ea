"""A shorter fair-scheduler slice for the control processes' threads (Linux ≥ 6.12), on request.

Under CPU hogs a thread that wakes up may wait for the running hog's slice to end (~1.4 ms
here); with a shorter slice of its own it preempts it sooner. ``$TELESURG_CONTROL_SLICE_US``
makes the launcher ask for one in each control process before it starts, so every thread it
makes (zenoh's runtime threads, the Python threads that take samples) inherits it. It is off by
default: on this project's VM it changed no latency figure (docs/performance.md). These tests
check the request reaches every thread of the control path and nothing else, and needs no
privilege; what it buys on a host is for ``telesurg bench wakeup`` and ``bench latency``.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest
from helpers import run_unprivileged
from telesurg.services.launcher import CONTROL_SLICE_US, Site, SiteSpec, control_slice_us, free_port
from telesurg.shared.errors import ConfigError
from telesurg.shared.timing import check_slice_us, fair_slice_us, set_fair_slice, set_realtime
from telesurg.tools.bench.perf import slice_threads


def _in_thread(fn):  # type: ignore[no-untyped-def]
    out: list[object] = []
    th = threading.Thread(target=lambda: out.append(fn()))
    th.start()
    th.join()
    return out[0]


needs_slices = pytest.mark.skipif(
    _in_thread(lambda: set_fair_slice(300)) != "", reason="this kernel takes no fair slice (Linux < 6.12)"
)


def test_slice_bounds_are_checked() -> None:
    for bad in (-1, 50, 100_001, True, "100", float("nan")):
        with pytest.raises(ConfigError, match=r"0 \(the kernel's default\) or 100\.\.100000 µs"):
            check_slice_us(bad)  # type: ignore[arg-type]
    for good in (0, 100, 2500.0, 100_000):
        check_slice_us(good)


def test_the_environment_sets_the_control_slice(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TELESURG_CONTROL_SLICE_US", raising=False)
    assert control_slice_us() == CONTROL_SLICE_US == 0  # the kernel's, unless asked
    monkeypatch.setenv("TELESURG_CONTROL_SLICE_US", "100")
    assert control_slice_us() == 100
    for bad in ("fast", "20"):
        monkeypatch.setenv("TELESURG_CONTROL_SLICE_US", bad)
        with pytest.raises(ConfigError, match=r"TELESURG_CONTROL_SLICE_US|100\.\.100000"):
            control_slice_us()


@needs_slices
def test_a_slice_is_set_read_back_and_inherited_by_new_threads() -> None:
    before = fair_slice_us()

    def body() -> tuple[str, float | None, float | None, float | None]:
        untouched = _in_thread(lambda: (set_fair_slice(0), fair_slice_us()))
        why = set_fair_slice(250)
        return why, untouched[1], fair_slice_us(), _in_thread(fair_slice_us)

    why, after_zero, mine, child = _in_thread(body)
    assert why == "" and mine == 250.0 and child == 250.0  # later threads inherit it
    assert after_zero == before  # 0 leaves the kernel's slice
    assert fair_slice_us() == before  # the calling thread only


@needs_slices
def test_a_realtime_thread_is_left_alone() -> None:
    def body() -> tuple[str, str, float | None, int]:
        rt = set_realtime(7)
        return rt, set_fair_slice(100), fair_slice_us(), os.sched_getscheduler(0)

    rt, why, got, policy = _in_thread(body)
    if rt:
        pytest.skip(f"no SCHED_FIFO here: {rt}")
    assert why == "" and got is None  # not under the fair scheduler: nothing to read or set
    assert policy & ~getattr(os, "SCHED_RESET_ON_FORK", 0) == os.SCHED_FIFO


@needs_slices
def test_no_privilege_is_needed() -> None:
    r = run_unprivileged(  # (root drops to "nobody", and with it every capability)
        "from telesurg.shared.timing import fair_slice_us, set_fair_slice",
        "why = set_fair_slice(100)\n"
        "print(repr(why), fair_slice_us()); sys.exit(0 if not why and fair_slice_us() == 100 else 1)\n",
    )
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.process
@needs_slices
def test_every_thread_of_the_control_processes_has_the_slice_and_the_mirror_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("TELESURG_CONTROL_SLICE_US", "100")
    spec = SiteSpec(
        site="slice",
        port=free_port(),
        services=("watchdog", "slave_control", "mirror"),
        overrides={"mirror": [f"save={json.dumps(str(tmp_path / 'run.rrd'))}"]},
        log_dir=tmp_path,
    )
    with Site(spec) as site:
        mirror_pid = site.pid("mirror")
        deadline = time.monotonic() + 20  # the mirror steps down once it is set up
        while time.monotonic() < deadline and os.sched_getscheduler(mirror_pid) != os.SCHED_IDLE:
            time.sleep(0.1)
        got = {name: slice_threads(p.pid) for name, p in site.procs.items()}
        mirror = [fair_slice_us(int(t)) for t in os.listdir(f"/proc/{mirror_pid}/task")]
        zenoh = {  # zenoh's runtime threads (named by tokio) of the watchdog, with their slice
            (Path(f"/proc/{site.pid('watchdog')}/task/{t}/comm").read_text().strip(), fair_slice_us(int(t)))
            for t in os.listdir(f"/proc/{site.pid('watchdog')}/task")
        }
    for name in ("router", "watchdog", "slave_control"):
        k, n = map(int, got[name].split("/"))
        assert k == n >= 5, f"{name}: {got[name]} threads with the control slice"
    assert any(c.startswith(("rx-", "tx-", "app-", "net-")) and s == 100.0 for c, s in zenoh), zenoh
    assert got["mirror"] == "0/0" and set(mirror) == {None}, mirror  # SCHED_IDLE: below every slice
