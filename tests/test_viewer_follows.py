"""The web viewer follows live: its time cursor stays at the newest data, it does not play back.

The real mirror (``telesurg mirror --serve``) is fed MH3F joint states over zenoh as
slave_control publishes them, for :data:`PREROLL_S` before the viewer opens; its gRPC server keeps
the whole session (``history_mb = 0``), so a new viewer is replayed it from its start. Headless
Chromium then opens the web viewer and, once a second, the test reads the viewer's own state (the
bench's probe, :func:`telesurg.tools.bench.viewer.probe`): the time cursor on ``source_time``,
the newest time the viewer has ingested, and the page's clock.

A *following* viewer (the blueprint's time panel, :func:`telesurg.services.mirror.view.blueprint`)
puts its cursor on the newest data it has, which moves with live. A viewer that *plays* starts at
the replay's first sample and moves at most 0.1 s of data per frame (rerun caps a frame's step):
with software WebGL's 1–2 frames a second it falls behind its own data and behind live at nearly
the clock's rate. Checked with the blueprint set to ``play_state="playing"`` (2026-12-02, load
average 10): the cursor moved 0.8 s in 15.6 s, 4.4–6.3 s behind its own newest data, 30–34 s
behind live — this test failed; with ``following`` it passed (lag 0.8–1.8 s once caught up). The
bounds are generous (the cursor within 2 s of its data and :data:`LAG_S` of live, advancing at
half the clock's rate at least): they tell following from playing, not how fast the viewer is
(``telesurg bench viewer`` measures that, docs/performance.md). Needs ``/usr/bin/chromium``;
skipped without it.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import CHROMIUM, SwingingArm, chromium

pytestmark = pytest.mark.process

ROOT = Path(__file__).resolve().parents[1]
#: s of data the mirror has sent before the viewer opens (a playing viewer starts that far back).
PREROLL_S = 5.0
#: s the viewer application may take to show a first time cursor (software WebGL start-up).
START_S = 45.0
#: s behind live (median of the probes) a following viewer stays within here; a playing one falls
#: behind by the time its frames take (docs/performance.md: 28–81 s on a loaded host).
LAG_S = 10.0
#: s of probes judged after the first cursor.
WINDOW_S = 15.0


@pytest.mark.timeout(240)
def test_the_web_viewer_follows_the_live_end_of_the_stream(tmp_path: Path) -> None:
    if not CHROMIUM.exists():
        pytest.skip("needs Debian chromium at /usr/bin/chromium: apt-get install -y chromium")
    from telesurg.services.launcher import free_port, wait_port
    from telesurg.shared import robots
    from telesurg.shared.bus import BusConfig, Node, open_session
    from telesurg.shared.viewer import viewer_url
    from telesurg.tools.bench.viewer import probe

    profile = robots.get("mh3f").arm("arm1")
    ep = f"tcp/127.0.0.1:{free_port()}"
    web, grpc = free_port(), free_port()
    router = open_session(BusConfig(mode="router", listen=[ep]))
    argv = [sys.executable, "-m", "telesurg.services.cli", "mirror", "--connect", ep, "--serve"]
    argv += ["--set", f"web_port={web}", "--set", f"grpc_port={grpc}"]
    # the server replays the whole session to the viewer (a playing viewer would start at its
    # first sample); no robot bodies: the stick figure and the joint plots are enough here
    argv += ["--set", "history_mb=0", "--set", "geometry=false", "--set", "draw_hz=5", "--set", "series_hz=2"]
    log = (tmp_path / "mirror.out").open("wb")
    mirror = subprocess.Popen(argv, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    stop = threading.Event()
    samples: list[dict[str, Any]] = []
    try:
        assert wait_port("127.0.0.1", web, 60.0), (tmp_path / "mirror.out").read_text()[-2000:]
        with Node(BusConfig(connect=[ep]), "local", "slave_control") as node:
            thread = SwingingArm(node, profile)  # the slave's measured joints at 100 Hz
            thread.stop = stop
            thread.start()
            time.sleep(PREROLL_S)
            url = viewer_url(f"rerun+http://127.0.0.1:{grpc}/proxy", web)
            with chromium(url, tmp_path, window=(800, 450)) as (cdp, session):
                t_open = time.monotonic()
                first: float | None = None
                while True:
                    time.sleep(1.0)
                    p = probe(cdp, session)
                    now = time.monotonic() - t_open  # after the answer: a busy page answers late
                    if p is not None and p["cursor_ns"] is not None:
                        first = now if first is None else first
                        newest = p["newest_ns"].get("source_time", p["cursor_ns"])
                        samples.append(
                            {
                                "t_s": round(now, 2),
                                "lag_s": (p["page_ns"] - p["cursor_ns"]) / 1e9,  # behind live
                                "behind_newest_s": (newest - p["cursor_ns"]) / 1e9,  # behind its data
                                "cursor_ns": p["cursor_ns"],
                            }
                        )
                    if first is None and now > START_S:
                        pytest.fail(f"the viewer showed no time cursor within {START_S:g} s: {p}")
                    if first is not None and now - first >= WINDOW_S:
                        break
            stop.set()
            thread.join(timeout=5)
    finally:
        stop.set()
        if mirror.poll() is None:
            mirror.send_signal(signal.SIGINT)
            try:
                mirror.wait(timeout=30)
            except subprocess.TimeoutExpired:
                mirror.kill()
                mirror.wait(timeout=10)
        log.close()
        router.close()  # type: ignore[no-untyped-call]
    for s in samples:
        print(f"  t {s['t_s']:6.1f} s: lag {s['lag_s']:6.2f} s, behind its data {s['behind_newest_s']:.2f} s")
    assert len(samples) >= 3, f"too few probes answered: {samples}"
    behind = float(np.median([s["behind_newest_s"] for s in samples]))
    lag = float(np.median([s["lag_s"] for s in samples]))
    # following: the cursor sits on the newest data the viewer has (a playing one: ~PREROLL_S back)
    assert behind <= 2.0, f"the cursor is {behind:.1f} s behind the viewer's own newest data: it plays"
    # ... and that is within seconds of live (generous: how close is the bench's question)
    assert lag <= LAG_S, f"the viewer is {lag:.1f} s behind live (median), not following it"
    # ... and it moves with live (not paused): over the window it advanced at least half the clock
    moved = (samples[-1]["cursor_ns"] - samples[0]["cursor_ns"]) / 1e9
    span = samples[-1]["t_s"] - samples[0]["t_s"]
    assert moved >= 0.5 * span, f"the cursor moved {moved:.1f} s in {span:.1f} s of wall clock"
