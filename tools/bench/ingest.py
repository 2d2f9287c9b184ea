"""``telesurg bench ingest``: how many messages of one kind a second the rerun web viewer takes in.

The web viewer takes in incoming messages only while it draws a frame, for about 10 ms a frame
(rerun's ``receive_messages``), and under software WebGL a large page draws 1–2 frames a second:
what a message costs it decides whether the viewer keeps up with live. This bench serves the
viewer from a :class:`~telesurg.services.mirror.view.RerunView` (the mirror's own drawing code)
that sends one kind of message ``--rate`` times a second, opens it in headless Chromium
(software WebGL, its autogroup at nice 19 as in ``bench viewer``) beside a headless demo (the
control services loading the host as in a session; ``--no-demo`` for an idle host), and probes
the viewer's time cursor once a second (:func:`telesurg.tools.bench.viewer.probe`). A viewer
that keeps up stays near a constant lag; one that does not falls behind at a constant rate (the
``slope`` of lag over time, s per s): it takes in ``rate × (1 − slope)`` frames a second.

Kinds (one "frame" each; the MH3F's model, :class:`~telesurg.services.mirror.geometry.RobotGeometry`):

* ``poses`` — a ``Transform3D`` row per robot body (9), each naming its body's frame: how the
  mirror posed every body until 2026-12-05 (now only bodies with meshes);
* ``primitives`` — every primitive geom of the robot posed in the world frame, one row of one
  entity (how the mirror draws a robot now);
* ``series`` — a block of 10 rows × 6 joints (``send_columns``), as a joint plot's;
* ``trail`` — a 50-point trail and its head, as the tip's.

Example::

    telesurg bench ingest --kind poses --rate 10 --json docs/data/perf/ingest-poses.json
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio, robots
from telesurg.tools.bench.browser import CHROMIUM, chromium
from telesurg.tools.bench.machine import machine, now
from telesurg.tools.bench.viewer import AUTOGROUP_NICE, demo_process, frame_rate, probe, window_size

KINDS = ("poses", "primitives", "series", "trail")
#: s before the lag is fitted (the viewer's start and first catch-up)
WARMUP_S = 20.0


class Feeder:
    """Sends ``rate`` frames a second of one ``kind`` to ``view`` on a thread of its own."""

    def __init__(self, view: Any, kind: str, rate: float) -> None:
        from telesurg.services.mirror.geometry import RobotGeometry

        if kind not in KINDS:
            raise ValueError(f"kind {kind!r}: valid: {', '.join(KINDS)}")
        self.view, self.kind, self.rate = view, kind, rate
        spec = robots.get("mh3f")
        self.geo = RobotGeometry.load(spec)
        self.profile = spec.arms("arm1")[0]
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)
        if kind == "primitives":
            view.robot("mh3f", self.geo.primitives, ())

    def _frame(self, k: int) -> None:
        stamp = time.time_ns()
        q = np.asarray(self.profile.home, np.float64) + 0.2 * np.sin(k / 20.0)
        arms = {"arm1": (self.profile, q)}
        if self.kind == "poses":
            for body, (x, quat) in self.geo.pose(arms).items():
                self.view.body_pose("mh3f", body, stamp, stamp, x, quat)
        elif self.kind == "primitives":
            self.view.primitive_poses("mh3f", stamp, stamp, self.geo.primitive_poses(arms))
        elif self.kind == "series":
            t = stamp - np.arange(9, -1, -1, dtype=np.int64) * 100_000_000
            self.view.series("/slave/arm1/joints/measured", t, t, np.sin(np.outer(t / 1e9, np.arange(1, 7))))
        else:
            pts = np.column_stack([np.cos(np.arange(50) / 8), np.sin(np.arange(50) / 8), np.ones(50)]) * 0.1
            self.view.trail("/slave/arm1/tip", stamp, stamp, np.roll(pts, k, axis=0), (40, 90, 220))
        self.view.send_now()
        self.sent += 1

    def _run(self) -> None:
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set():
            self._frame(k)
            k += 1
            self._stop.wait(max(0.0, t0 + k / self.rate - time.monotonic()))

    @contextlib.contextmanager
    def running(self) -> Iterator[Feeder]:
        self._thread.start()
        try:
            yield self
        finally:
            self._stop.set()
            self._thread.join(timeout=5)


def run(
    kind: str, rate: float, seconds: float, window: tuple[int, int], demo: bool, workdir: Path
) -> dict[str, Any]:
    """The viewer fed ``rate`` frames a second of ``kind`` for ``seconds``; the figures."""
    from telesurg.services.launcher import free_port
    from telesurg.services.mirror.view import RerunView
    from telesurg.shared.viewer import viewer_url

    web, grpc = free_port(), free_port()
    samples: list[tuple[float, float]] = []
    fps: list[float] = []
    with contextlib.ExitStack() as stack:
        if demo:  # headless (router, control services, camera; no mirror): the load of a session
            argv = [sys.executable, "-m", "telesurg.services.cli", "demo", "--headless"]
            argv += ["--seconds", f"{seconds + 60.0:g}", "--port", "0", "--console-port", "0"]
            stack.enter_context(demo_process(argv, workdir / "demo.out"))
            time.sleep(15.0)  # its services up and running
        view = RerunView(
            "telesurg-ingest", serve=True, web_port=web, grpc_port=grpc, history_mb=0.15, flush_s=0.25
        )
        stack.callback(view.close)
        feeder = stack.enter_context(Feeder(view, kind, rate).running())
        url = viewer_url(f"rerun+http://127.0.0.1:{grpc}/proxy", web)
        cdp, session = stack.enter_context(
            chromium(
                url,
                workdir,
                window=window,
                nice=0,
                autogroup_nice=AUTOGROUP_NICE,
                flags=[f"--window-size={window[0]},{window[1]}"],
            )
        )
        t0 = time.monotonic()
        next_fps = t0 + WARMUP_S
        while time.monotonic() - t0 < seconds:
            time.sleep(1.0)
            p = probe(cdp, session)
            if p is not None and p["cursor_ns"] is not None:
                samples.append((round(time.monotonic() - t0, 2), (p["page_ns"] - p["cursor_ns"]) / 1e9))
            if time.monotonic() >= next_fps:
                f = frame_rate(cdp, session)
                if f is not None:
                    fps.append(f)
                next_fps = time.monotonic() + 15.0
        sent = feeder.sent
    after = [(t, lag) for t, lag in samples if t >= WARMUP_S]
    slope = (
        float(np.polyfit([t for t, _ in after], [lag for _, lag in after], 1)[0]) if len(after) >= 5 else None
    )
    return {
        "kind": kind,
        "rate_hz": rate,
        "frames_sent": sent,
        "seconds": seconds,
        "window": list(window),
        "demo": demo,
        "lag_p50_s": float(np.median([lag for _, lag in after])) if after else None,
        "lag_last_s": after[-1][1] if after else None,
        "slope_s_per_s": slope,
        # frames a second the viewer took in (a slope above 0: it falls behind)
        "taken_in_hz": rate * (1.0 - max(0.0, slope)) if slope is not None else None,
        "fps": fps,
        "fps_median": float(np.median(fps)) if fps else None,
        "date": now(),
        "machine": machine(),
        "samples": samples,
    }


def main(argv: list[str] | None = None) -> int:
    """``telesurg bench ingest``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench ingest",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--kind", choices=KINDS, required=True, help="what each frame sends")
    ap.add_argument("--rate", type=float, default=10.0, help="frames a second (default 10)")
    ap.add_argument("--seconds", type=float, default=70.0, help="viewer open this long, s (default 70)")
    ap.add_argument(
        "--window", type=window_size, default=(1280, 720), metavar="WxH", help="the page (default 1280x720)"
    )
    ap.add_argument("--no-demo", action="store_true", help="no headless demo beside it (an idle host)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args(argv)
    if not 0.1 <= args.rate <= 200.0:
        ap.error(f"--rate {args.rate:g}: 0.1..200 frames a second")
    if not CHROMIUM.is_file():
        print(f"telesurg bench ingest: needs Chromium at {CHROMIUM} (Debian: apt-get install chromium)")
        return 2
    with tempfile.TemporaryDirectory(prefix="bench-ingest-") as tmp:
        res = run(args.kind, args.rate, args.seconds, args.window, not args.no_demo, Path(tmp))

    def f(x: float | None, fmt: str) -> str:
        return "—" if x is None else format(x, fmt)

    where = "beside a headless demo" if res["demo"] else "idle host"
    print(
        f"{args.kind} at {args.rate:g} frames/s, {args.window[0]}x{args.window[1]}, {where}: "
        f"lag after {WARMUP_S:g} s p50 {f(res['lag_p50_s'], '.2f')} s, "
        f"slope {f(res['slope_s_per_s'], '+.3f')} s/s, taken in {f(res['taken_in_hz'], '.1f')} frames/s; "
        f"viewer frames/s {f(res['fps_median'], '.1f')}"
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(jsonio.dumps(res, indent=1) + "\n")
    return 0
