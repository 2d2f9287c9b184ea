"""The rerun web viewer of ``telesurg demo``, rendered in headless Debian chromium.

A demo session (``telesurg demo --headless --seconds 15``: router and every service) is mirrored
by ``telesurg mirror --serve`` (gRPC + the web viewer on loopback), which outlives the session.
Chromium then opens the viewer URL and is driven over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: NUL-terminated JSON on fds 3 and 4; no websocket, no extra
package). Screenshots are taken every 3 s until the viewer has drawn the session (software
WebGL: 20 s or more); the last one is saved and its pixels checked: not blank, not the loading
page, the arm and the plots drawn in colour.

Needs ``/usr/bin/chromium`` (Debian: ``apt-get install -y chromium``); skipped without it.

Also a script, to refresh the screenshot of ``docs/console.md`` (a 20 s session, the time
cursor put at 60 % of it)::

    .venv/bin/python tests/test_viewer_browser.py docs/img/viewer.png 0.6
"""

from __future__ import annotations

import contextlib
import io
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import CHROMIUM, WINDOW, DevTools, chromium, clutch_flags, hue_pixels, screenshot
from telesurg.shared import robots

pytestmark = pytest.mark.process

#: the MH3F's casting blue (its MJCF material ``mh3f_blue``, rgba 0.11 0.33 0.66)
ARM_BLUE = (28, 84, 168)

ROOT = Path(__file__).resolve().parents[1]
# --------------------------------------------------------------------------- pixels


def _near(img: np.ndarray, color: tuple[int, int, int], tol: int) -> np.ndarray:
    return np.asarray(np.abs(img - np.asarray(color)).max(axis=2) <= tol)


def pixel_stats(png: bytes) -> dict[str, float]:
    """Figures of a screenshot: ``std`` (grey level, 0–255), ``colors`` (distinct colours after
    quantising to 4 bits a channel), ``arm`` (pixels of the MH3F's casting blue in the lean
    layout's 3D view, the left three fifths: the robot's bodies are drawn), ``joints`` (pixels of
    the joint plot colours: the plots are drawn),
    ``width``/``height``."""
    from PIL import Image
    from telesurg.services.mirror.view import JOINT_COLORS

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int32)
    h, w, _ = img.shape
    q = (img >> 4).reshape(-1, 3)
    joints = np.zeros((h, w), dtype=bool)
    for color in JOINT_COLORS[:6]:
        joints |= _near(img, color, 24)
    return {
        "std": float(img.mean(axis=2).std()),
        "colors": float(np.unique(q[:, 0] << 8 | q[:, 1] << 4 | q[:, 2]).size),
        "arm": float(hue_pixels(png, ARM_BLUE, (0, 40, w * 3 // 5, h - 20))),
        "joints": float(joints.sum()),
        "width": w,
        "height": h,
    }


def rendered(stats: dict[str, float]) -> bool:
    """The viewer has drawn the session: the robot's bodies, joint plots, a varied picture (the
    loading page is a near-uniform dark page; an empty viewer has none of these colours)."""
    # rendered: the joint plots 800-3000+ px, fewer where the plot's legend covers its lines; the
    # arm's blue as in tests/test_viewer_geometry.py (an empty viewer, or the loading page, has
    # neither colour)
    drawn = stats["arm"] >= 2000 and stats["joints"] >= 500
    return drawn and stats["colors"] >= 150 and stats["std"] >= 8


_FPS_JS = """new Promise(done => {
  let n = 0; const t0 = performance.now();
  const tick = () => {
    n++;
    if (performance.now() - t0 < 2000) requestAnimationFrame(tick); else done(n / 2);
  };
  requestAnimationFrame(tick);
})"""


def frame_rate(cdp: DevTools, session: str) -> float:
    """Animation frames per second of the page over 2 s: ~1 while the viewer ingests a backlog
    (one software-rendered frame a second), tens once it has everything."""
    try:
        r = cdp.call(
            "Runtime.evaluate", {"expression": _FPS_JS, "awaitPromise": True, "returnByValue": True}, session
        )
    except RuntimeError:  # the page is (re)loading
        return 0.0
    return float(r.get("result", {}).get("value") or 0.0)


# --------------------------------------------------------------------------- the demo


@contextlib.contextmanager
def served_demo(
    workdir: Path, session_s: float, mirror_set: Sequence[str] = ()
) -> Iterator[tuple[str, Path, subprocess.Popen[bytes]]]:
    """A demo session seen by a mirror that serves the web viewer: (viewer URL, .rrd, mirror).

    ``telesurg demo --headless --seconds session_s`` runs the router and every service; the
    mirror (``telesurg mirror --serve --save``, the demo's own mirror command line) joins its
    router and outlives the session, so the browser then renders a finished session: no
    simulation competes with software WebGL for the CPU. On exit the mirror is stopped with
    SIGINT (which completes the .rrd).
    """
    from telesurg.services.launcher import free_port, wait_port
    from telesurg.shared.viewer import viewer_url

    port, web, grpc = free_port(), free_port(), free_port()
    rrd = workdir / "session.rrd"
    cli = [sys.executable, "-m", "telesurg.services.cli"]
    demo_argv = [*cli, "demo", "--headless", "--seconds", str(session_s), "--port", str(port)]
    demo_argv += ["--log-dir", str(workdir / "logs"), "--report", str(workdir / "report.json")]
    # the operator re-clutches every 4 s: a watchdog hold on this busy host ends one
    # engagement, not the session the viewer shows
    demo_argv += clutch_flags()
    mirror_argv = [*cli, "mirror", "--connect", f"tcp/127.0.0.1:{port}", "--serve", "--save", str(rrd)]
    mirror_argv += ["--set", f"web_port={web}", "--set", f"grpc_port={grpc}"]
    # the viewer opens after the session and shows all of it: the server keeps the whole session
    # (a live viewer gets only the recent history_mb, tests/test_viewer_history.py)
    mirror_argv += ["--set", "history_mb=0"]
    for item in mirror_set:
        mirror_argv += ["--set", item]
    procs: list[subprocess.Popen[bytes]] = []
    logs: list[Any] = []
    try:
        logs.append((workdir / "demo.out").open("wb"))
        procs.append(subprocess.Popen(demo_argv, cwd=ROOT, stdout=logs[-1], stderr=subprocess.STDOUT))
        assert wait_port("127.0.0.1", port, 60.0), "the demo's router did not open its port"
        logs.append((workdir / "mirror.out").open("wb"))
        procs.append(subprocess.Popen(mirror_argv, cwd=ROOT, stdout=logs[-1], stderr=subprocess.STDOUT))
        demo_proc, mirror = procs
        assert demo_proc.wait(timeout=session_s + 180.0) == 0, (workdir / "demo.out").read_text()[-3000:]
        assert mirror.poll() is None, (workdir / "mirror.out").read_text()[-3000:]
        assert wait_port("127.0.0.1", web, 30.0), "the mirror serves no web viewer"
        yield viewer_url(f"rerun+http://127.0.0.1:{grpc}/proxy", web), rrd, mirror
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(timeout=10)
        for f in logs:
            f.close()


def capture(
    url: str, workdir: Path, png_out: Path, timeout_s: float = 240.0
) -> tuple[dict[str, float], list[dict[str, float]]]:
    """Open ``url`` in chromium and screenshot it every 3 s until two shots in a row look
    rendered, or ``timeout_s``; the last shot is saved to ``png_out``. Returns its stats and
    every shot's."""
    history: list[dict[str, float]] = []
    with chromium(url, workdir) as (cdp, session):
        deadline = time.monotonic() + timeout_s
        ok_before = False
        while True:
            time.sleep(3.0)
            png = screenshot(cdp, session)
            stats = pixel_stats(png)
            history.append(stats)
            png_out.write_bytes(png)
            ok = rendered(stats)
            if (ok and ok_before) or time.monotonic() > deadline:
                return stats, history
            ok_before = ok


# --------------------------------------------------------------------------- test


@pytest.mark.timeout(900)
def test_web_viewer_renders_the_demo_session(tmp_path: Path) -> None:
    from telesurg.services.mirror import LIVE_PLOT_HZ

    if not CHROMIUM.exists():
        pytest.skip("needs Debian chromium at /usr/bin/chromium: apt-get install -y chromium")
    if shutil.which("bash") is None:
        pytest.skip("needs bash to hand chromium its DevTools pipe")
    from helpers import drawn_body_poses, entity_paths, scalar_counts

    png = tmp_path / "viewer.png"
    with served_demo(tmp_path, session_s=15.0) as (url, rrd, mirror):
        stats, history = capture(url, tmp_path, png)
        mirror.send_signal(signal.SIGINT)
        assert mirror.wait(timeout=30) == 0
    print(f"screenshot {png}: {stats}")
    for i, s in enumerate(history):
        print(f"  shot {i}: " + ", ".join(f"{k} {v:.0f}" for k, v in s.items()))
    # a real picture of the viewer with the session drawn: the loading page ("Loading
    # Application Bundle…" on a dark page) and an empty viewer have no robot and no joint plots
    assert png.stat().st_size > 20_000
    assert (stats["width"], stats["height"]) == WINDOW
    assert rendered(stats), f"the viewer never drew the session: {history}"
    # what the viewer was given: the robot's bodies, the trocar, the trails, the errors
    paths = entity_paths(rrd)
    assert {"link1", "forceps"} <= set(drawn_body_poses(rrd, robots.get("mh3f"))), sorted(paths)
    for p in ("trocar", "tip", "target", "tip_error_mm", "state"):
        assert f"/slave/arm1/{p}" in paths, p
    assert {"/master/m1/tip", "/safety/arm1/state", "/safety/arm1/latency_ms", "/events"} <= paths
    counts = scalar_counts(rrd)
    # a serving mirror thins the joint series to LIVE_PLOT_HZ: over 10 s of the 15 s session
    assert counts["/slave/arm1/joints/measured"] > 10 * LIVE_PLOT_HZ, counts
    assert counts["/slave/arm1/tip_error_mm"] > 50, counts


def _click(cdp: DevTools, session: str, x: float, y: float) -> None:
    for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
        button = "none" if kind == "mouseMoved" else "left"
        event = {"type": kind, "x": x, "y": y, "button": button, "clickCount": int(button == "left")}
        cdp.call("Input.dispatchMouseEvent", event, session)
        time.sleep(0.4)  # one software-rendered frame per event at least


def docs_screenshot(out: Path, at: float) -> None:
    """The screenshot of ``docs/console.md``: a 20 s demo session, fully loaded, with the time
    cursor at ``at`` (fraction of the recording: mid-session rather than its shutdown)."""
    with tempfile.TemporaryDirectory() as tmp, served_demo(Path(tmp), session_s=20.0) as (url, _rrd, _mirror):
        history: list[dict[str, float]] = []
        with chromium(url, Path(tmp)) as (cdp, session):
            deadline = time.monotonic() + 900.0
            while time.monotonic() < deadline:  # rendered, and the whole session ingested
                time.sleep(3.0)
                history.append(pixel_stats(screenshot(cdp, session)))
                if rendered(history[-1]) and frame_rate(cdp, session) > 20.0:
                    break
            # the time panel's stream area spans x = 192…1568 px at this window size
            x = 192 + at * (1568 - 192)
            for _ in range(2):  # the first click focuses the panel
                _click(cdp, session, x, 850)
            time.sleep(2.0)
            png = screenshot(cdp, session)
        out.write_bytes(png)
        print(f"wrote {out}: {pixel_stats(png)} after {len(history)} shots")


if __name__ == "__main__":
    docs_screenshot(
        Path(sys.argv[1] if len(sys.argv) > 1 else "viewer.png").resolve(),
        float(sys.argv[2]) if len(sys.argv) > 2 else 0.6,
    )
