"""The benches' browser cannot take CPU from the control path: every Chromium process runs in a
scheduler autogroup of nice 19.

With autogroups (Linux's default, ``kernel.sched_autogroup_enabled``) the CPU is shared between
sessions first; a process's own nice counts only inside its session. The launcher runs the control
processes in autogroups of nice −10, the mirror and the camera at 19; ``telesurg bench viewer``
and ``bench … --load viewer`` start Chromium (browser, zygotes, renderer, GPU process) in a
session whose autogroup is at 19 too. Read from ``/proc/<pid>/autogroup`` of the real processes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import autogroup
from telesurg.tools.bench.browser import CHROMIUM, autogroups, chromium, lowest_priority

pytestmark = pytest.mark.process

AUTOGROUPS = Path("/proc/self/autogroup").exists()


@pytest.mark.skipif(not AUTOGROUPS, reason="no scheduler autogroups on this kernel")
@pytest.mark.timeout(180)
def test_every_chromium_process_runs_in_one_autogroup_at_nice_19(tmp_path: Path) -> None:
    if not CHROMIUM.exists():
        pytest.skip("needs Debian chromium at /usr/bin/chromium: apt-get install -y chromium")
    profile = str(tmp_path / "chromium-profile")
    mine = autogroup("self")
    with chromium("about:blank", tmp_path, autogroup_nice=19) as (cdp, session):
        assert cdp.call("Runtime.evaluate", {"expression": "1 + 1", "returnByValue": True}, session)
        groups = autogroups(profile)
    print(groups)
    assert len(groups) >= 3, groups  # the browser, its zygote(s), the renderer, the GPU process, ...
    names = {g.split()[0] for g in groups.values()}
    assert len(names) == 1 and mine not in names, (groups, mine)  # one group: its own session
    assert all(g.endswith(" nice 19") for g in groups.values()), groups
    assert autogroups(profile) == {}  # every process ended


@pytest.mark.skipif(not AUTOGROUPS, reason="no scheduler autogroups on this kernel")
def test_lowest_priority_puts_a_new_session_at_nice_19() -> None:
    p = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(30)"],
        start_new_session=True,
        preexec_fn=lowest_priority,
    )
    try:
        group = Path(f"/proc/{p.pid}/autogroup").read_text().strip()
        assert group.endswith(" nice 19"), group
        assert os.getpriority(os.PRIO_PROCESS, p.pid) == 19
    finally:
        p.kill()
        p.wait(timeout=10)
