"""``telesurg bench viewer``: how far behind live the rerun web viewer is, with the demo running.

Runs ``telesurg demo`` (router, every service, the mirror serving the web viewer, the camera and
the web console, as a user starts it) for ``--seconds``, opens the viewer in headless Debian
Chromium (software WebGL, as on a console without a GPU; in a session whose scheduler autogroup
runs at nice 19, below the control path — ``--autogroup-nice 0`` for a browser at a user's normal
priority; every Chromium process's ``/proc/<pid>/autogroup`` is reported) driven over the
DevTools protocol (:mod:`telesurg.tools.bench.browser`), and once a second asks the page what
the viewer shows:

* the viewer's own state (``window._handle.viewer_state()``, the encoded ``GetStateResponse`` of
  rerun's Viewer Control API, computed at once from the viewer's last frame): the time cursor of
  the active timeline (``source_time``, the publisher's stamp) — in follow mode (a live stream)
  the newest time the viewer has ingested and draws — and the page's wall clock (``Date.now()``)
  in the same evaluation. **Lag** = page clock − cursor: how old the newest thing on screen is;
* every 10 s the page's animation frame rate over 2 s (software WebGL frames a second).

The viewer's first seconds (loading its WebAssembly bundle, the first blueprint) are reported
apart (``first_cursor_s``) and the lag figures are taken after ``--warmup`` s. The demo's report
gives the watchdog's transitions into HOLD / DEGRADED over the same run (the goal: 0 HOLD).
Prints a table and writes JSON (``--json``; docs/performance.md keeps the figures).

Examples::

    telesurg bench viewer --seconds 100 --json docs/data/perf/viewer.json
    telesurg bench viewer --seconds 60 --set mirror.layout=\\"full\\"    # the full layout
    telesurg bench viewer --seconds 100 --window 1280x720            # a smaller page
    telesurg bench viewer --seconds 100 --gl llvmpipe                # Mesa's rasteriser
    telesurg bench viewer --seconds 100 --browser /opt/chromium-155/usr/lib/chromium/chromium
    telesurg bench viewer --plot lag.png --from before=a.json after=b.json   # saved runs, no run
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.tools.bench.browser import (
    CHROMIUM,
    GL_FLAGS,
    WINDOW,
    DevTools,
    autogroups,
    chromium,
    screenshot,
)
from telesurg.tools.bench.machine import machine, now
from telesurg.tools.bench.plots import plot_viewer_lag

#: s a probe waits for the page to answer.
PROBE_TIMEOUT_S = 20.0
#: Chromium's scheduler autogroup runs at this nice value: below every other session's work
#: (the control processes' autogroups are at −10 or 0), as the launcher runs the mirror and camera.
AUTOGROUP_NICE = 19
#: Timelines the mirror logs on (what the cursor can be on).
TIMELINES = ("source_time", "receive_time")

_STATE_JS = (
    "(() => { const h = window._handle; if (!h || h.has_panicked()) return [Date.now(), null];"
    " return [Date.now(), Array.from(h.viewer_state())]; })()"
)
_FPS_JS = """new Promise(done => {
  let n = 0; const t0 = performance.now();
  const tick = () => {
    n++;
    const dt = performance.now() - t0;
    if (dt < 2000) requestAnimationFrame(tick); else done(n / (dt / 1000));
  };
  requestAnimationFrame(tick);
})"""


# --------------------------------------------------------------------------- the viewer's state


def _varint(b: bytes, i: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        if i >= len(b):
            raise ValueError("truncated varint")
        c = b[i]
        i += 1
        out |= (c & 0x7F) << shift
        shift += 7
        if c < 0x80:
            return out, i


def fields(b: bytes) -> list[tuple[int, int | bytes]]:
    """The fields of one protobuf message, in order: (number, varint value or raw bytes of a
    length-delimited / fixed field). ValueError if ``b`` is not a message."""
    out: list[tuple[int, int | bytes]] = []
    i = 0
    while i < len(b):
        key, i = _varint(b, i)
        num, wire = key >> 3, key & 7
        if num == 0:
            raise ValueError("field number 0")
        if wire == 0:
            v, i = _varint(b, i)
            out.append((num, v))
        elif wire == 2:
            n, i = _varint(b, i)
            if i + n > len(b):
                raise ValueError("truncated field")
            out.append((num, b[i : i + n]))
            i += n
        elif wire in (1, 5):
            n = 8 if wire == 1 else 4
            out.append((num, b[i : i + n]))
            i += n
        else:
            raise ValueError(f"wire type {wire}")
    return out


def _sub(b: bytes, num: int) -> list[bytes]:
    return [v for n, v in fields(b) if n == num and isinstance(v, bytes)]


def _ints(b: bytes, num: int) -> list[int]:
    return [v for n, v in fields(b) if n == num and isinstance(v, int)]


def _named(b: bytes) -> str | None:
    return next((t for t in TIMELINES if t.encode() in b), None)


def viewer_times(state: bytes) -> dict[str, Any]:
    """What the viewer state says about time: ``{"active": timeline or None, "cursor_ns": the time
    cursor on it or None, "newest_ns": {timeline: newest time ingested}}``.

    ``state``: ``viewer_state()`` bytes (rerun 0.41 ``GetStateResponse``: field 3 the active
    recording — its field 2 per timeline (name, type, range {min, max}), its field 3 the active
    timeline (name, type, {time})). Raises ValueError if the bytes do not parse that way.
    """
    out: dict[str, Any] = {"active": None, "cursor_ns": None, "newest_ns": {}}
    for rec in _sub(state, 3):
        for tl in _sub(rec, 2):
            name = _named(b"".join(_sub(tl, 1)))
            ranges = _sub(tl, 3)
            if name and ranges:
                hi = _ints(ranges[0], 2)
                if hi:
                    out["newest_ns"][name] = hi[0]
        for cur in _sub(rec, 3):
            name = _named(b"".join(_sub(cur, 1)))
            times = _sub(cur, 3)
            if name and times and _ints(times[0], 1):
                out["active"], out["cursor_ns"] = name, _ints(times[0], 1)[0]
    return out


def probe(cdp: DevTools, session: str) -> dict[str, Any] | None:
    """One look at the viewer: the page's clock (ns) and :func:`viewer_times` (``"viewer": False``
    while the page is up but the viewer application in it has not started); None if the page does
    not answer within :data:`PROBE_TIMEOUT_S`."""
    try:
        r = cdp.call(
            "Runtime.evaluate",
            {"expression": _STATE_JS, "returnByValue": True},
            session,
            timeout=PROBE_TIMEOUT_S,
        )
    except (RuntimeError, TimeoutError):
        return None
    value = r.get("result", {}).get("value")
    if not value:
        return None
    page_ms, raw = value
    if raw is None:
        return {"page_ns": int(page_ms * 1e6), "viewer": False, "cursor_ns": None, "newest_ns": {}}
    try:
        times = viewer_times(bytes(raw))
    except ValueError:
        return None
    return {"page_ns": int(page_ms * 1e6), "viewer": True, **times}


#: JS: the WebGL renderer a page of this browser gets (the rasteriser that draws the viewer).
_RENDERER_JS = (
    "(() => { const gl = document.createElement('canvas').getContext('webgl2');"
    " if (!gl) return null; const e = gl.getExtension('WEBGL_debug_renderer_info');"
    " return e ? gl.getParameter(e.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER); })()"
)


def webgl_renderer(cdp: DevTools, session: str) -> str | None:
    """The WebGL renderer string the page reports (e.g. "ANGLE (…SwiftShader…)"), None without
    WebGL 2."""
    r = cdp.call("Runtime.evaluate", {"expression": _RENDERER_JS, "returnByValue": True}, session)
    value = r.get("result", {}).get("value")
    return str(value) if value else None


def browser_version(cdp: DevTools) -> str:
    """The browser's product and version (``Chrome/156.0.8078.114``): a figure of the viewer is
    a figure of one build of its rasteriser and compositor."""
    return str(cdp.call("Browser.getVersion").get("product", ""))


def frame_rate(cdp: DevTools, session: str) -> float | None:
    """Animation frames a second of the page over 2 s or its first frame after that (None if the
    page does not answer within a minute)."""
    try:
        r = cdp.call(
            "Runtime.evaluate",
            {"expression": _FPS_JS, "awaitPromise": True, "returnByValue": True},
            session,
            timeout=60,
        )
    except (RuntimeError, TimeoutError):
        return None
    v = r.get("result", {}).get("value")
    return float(v) if v is not None else None


# --------------------------------------------------------------------------- the run


def cpu_seconds(marker: str) -> float:
    """CPU time (user + system, s) of the live processes whose command line holds ``marker``
    (this run's Chromium: its profile directory), read from /proc."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if marker.encode() not in (d / "cmdline").read_bytes():
                continue
            stat = (d / "stat").read_text()
        except OSError:
            continue
        parts = stat.rsplit(")", 1)[1].split()
        total += (int(parts[11]) + int(parts[12])) / tick  # utime, stime (fields 14, 15)
    return total


@contextlib.contextmanager
def demo_process(argv: list[str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``argv`` (a ``telesurg demo`` command line) running with its output in ``log``; stopped with
    SIGINT (killed after 60 s) on exit."""
    with log.open("wb") as out:
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT)
        try:
            yield proc
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=10)


def _count(values: Iterable[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for v in values:
        out[v] = out.get(v, 0) + 1
    return out


def _pct(xs: Sequence[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(xs), q)) if xs else None


def run(
    seconds: float,
    warmup: float,
    sets: Sequence[str],
    workdir: Path,
    png: Path | None = None,
    *,
    window: tuple[int, int] = WINDOW,
    autogroup_nice: int | None = AUTOGROUP_NICE,
    flags: Sequence[str] = (),
    gl: str = "swiftshader",
    browser: Path = CHROMIUM,
) -> dict[str, Any]:
    """The demo for ``seconds`` with the viewer open; the figures (module docstring).
    ``window``: the page's viewport (px); ``autogroup_nice``: the nice value of Chromium's
    scheduler autogroup (None: 0); ``flags``: extra Chromium flags; ``gl``: the software WebGL
    rasteriser (:data:`~telesurg.tools.bench.browser.GL_FLAGS`); ``browser``: the Chromium
    executable."""
    from telesurg.services.launcher import free_port, wait_port
    from telesurg.shared.viewer import viewer_url

    port, web, grpc = free_port(), free_port(), free_port()
    report = workdir / "report.json"
    argv = [sys.executable, "-m", "telesurg.services.cli", "demo", "--seconds", str(seconds)]
    argv += ["--port", str(port), "--web-port", str(web), "--grpc-port", str(grpc), "--console-port", "0"]
    argv += ["--report", str(report), "--log-dir", str(workdir / "logs")]
    for s in sets:
        argv += ["--set", s]
    samples: list[dict[str, Any]] = []
    fps: list[dict[str, float]] = []
    t_open = load_open = browser_cpu = browser_wall = 0.0
    with demo_process(argv, workdir / "demo.out") as demo:
        if not wait_port("127.0.0.1", web, 120.0):
            raise RuntimeError(f"the demo served no viewer: {(workdir / 'demo.out').read_text()[-2000:]}")
        url = viewer_url(f"rerun+http://127.0.0.1:{grpc}/proxy", web)
        profile = str(workdir / "chromium-profile")
        groups: dict[int, str] = {}
        with chromium(
            url,
            workdir,
            window=window,
            nice=0,
            autogroup_nice=autogroup_nice,
            flags=[f"--window-size={window[0]},{window[1]}", *flags],
            gl=gl,
            browser=browser,
        ) as (cdp, session):
            renderer = webgl_renderer(cdp, session)
            version = browser_version(cdp)
            t_open = time.monotonic()
            load_open = os.getloadavg()[0]
            next_fps = t_open + warmup
            shot: bytes | None = None  # the screenshot, taken live ~8 s before the demo ends
            while demo.poll() is None:
                time.sleep(1.0)
                t = time.monotonic() - t_open
                p = probe(cdp, session)
                took = time.monotonic() - t_open - t
                sample: dict[str, Any] = {
                    "t_s": round(t, 2),
                    "answered": p is not None,
                    "probe_s": round(took, 2),
                }
                if p is not None:
                    sample["viewer"] = p["viewer"]
                    lag = (p["page_ns"] - p["cursor_ns"]) / 1e9 if p["cursor_ns"] is not None else None
                    newest = p["newest_ns"].get("source_time")
                    sample["lag_s"] = lag
                    sample["ingest_lag_s"] = (p["page_ns"] - newest) / 1e9 if newest is not None else None
                samples.append(sample)
                if png is not None and shot is None and t >= seconds - 8.0:
                    with contextlib.suppress(RuntimeError, TimeoutError):  # tried again at the end
                        shot = screenshot(cdp, session)
                groups.update(autogroups(profile))  # every Chromium process seen
                if time.monotonic() >= next_fps and demo.poll() is None:
                    f = frame_rate(cdp, session)
                    if f is not None:
                        fps.append({"t_s": round(time.monotonic() - t_open, 2), "fps": f})
                    next_fps = time.monotonic() + 10.0
            browser_cpu = cpu_seconds(profile)
            browser_wall = time.monotonic() - t_open
            if png is not None:
                try:
                    png.write_bytes(shot if shot is not None else screenshot(cdp, session))
                except (RuntimeError, TimeoutError) as exc:  # a page that no longer answers
                    print(f"no screenshot: {exc}", file=sys.stderr)
    rep = json.loads(report.read_text()) if report.is_file() else {}
    if not rep:  # the demo ended without its report: say why
        print(f"the demo wrote no report:\n{(workdir / 'demo.out').read_text()[-3000:]}", file=sys.stderr)
    counted = [s for s in samples if s["t_s"] >= warmup]
    lags = [s["lag_s"] for s in counted if s.get("lag_s") is not None]
    first = next((s["t_s"] for s in samples if s.get("lag_s") is not None), None)
    wd = rep.get("watchdog", {})
    return {
        "seconds": seconds,
        "warmup_s": warmup,
        "set": list(sets),
        "first_cursor_s": first,
        "lag_s": {
            "n": len(lags),
            "p50": _pct(lags, 50),
            "p90": _pct(lags, 90),
            "p99": _pct(lags, 99),
            "max": max(lags) if lags else None,
            "share_under_1s": (sum(x < 1.0 for x in lags) / len(lags)) if lags else None,
            # probes the page did not answer within PROBE_TIMEOUT_S (its JS thread busy in a frame
            # the whole time: what it shows is at least that old)
            "unanswered": sum(not s["answered"] for s in counted),
            "viewer_not_started": sum(s.get("viewer") is False for s in counted),
            "probes": len(counted),
        },
        "fps": {"median": _pct([f["fps"] for f in fps], 50), "samples": fps},
        "watchdog": {arm: w.get("entered") for arm, w in wd.items()} if isinstance(wd, dict) else wd,
        "summary": rep.get("summary"),
        "engagements": rep.get("engagements"),
        # Chromium's processes (browser, renderer, GPU process with SwiftShader): CPU they got
        "browser_cpu_s": round(browser_cpu, 2),
        "window": list(window),
        "chromium_flags": list(flags),
        "gl": gl,
        "webgl_renderer": renderer,
        "browser_version": version,
        "browser": str(browser),
        # /proc/<pid>/autogroup of every Chromium process seen: (group, nice) → processes
        "chromium_autogroups": _count(groups.values()),
        "browser_cpu_share": round(browser_cpu / browser_wall, 3) if browser_wall > 0 else None,
        "load_average_at_open": load_open,
        "load_average": list(os.getloadavg()),
        "cpus": os.cpu_count(),
        "date": now(),
        "machine": machine(),
        "samples": samples,
    }


def window_size(text: str) -> tuple[int, int]:
    """argparse type of a page size ``WxH`` (px, 100..8000 each)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WxH, e.g. 1600x900") from None
    if not (100 <= w <= 8000 and 100 <= h <= 8000):
        raise argparse.ArgumentTypeError(f"{text!r}: width and height in [100, 8000] px")
    return w, h


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg bench viewer``."""
    ap = argparse.ArgumentParser(
        prog="telesurg bench viewer",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--seconds", type=float, default=100.0, help="demo length, s (default 100)")
    ap.add_argument(
        "--warmup", type=float, default=20.0, help="s after the page opens not counted (default 20)"
    )
    ap.add_argument(
        "--set", action="append", default=[], metavar="SERVICE.KEY=VALUE", help="passed to the demo"
    )
    ap.add_argument(
        "--window",
        type=window_size,
        default=WINDOW,
        metavar="WxH",
        help=f"the page's viewport, px (default {WINDOW[0]}x{WINDOW[1]})",
    )
    ap.add_argument(
        "--autogroup-nice",
        type=int,
        default=AUTOGROUP_NICE,
        help=f"nice value of Chromium's scheduler autogroup (default {AUTOGROUP_NICE}: below the services)",
    )
    ap.add_argument(
        "--chromium-flag",
        action="append",
        default=[],
        metavar="FLAG",
        help="extra Chromium flag, e.g. --chromium-flag=--force-device-scale-factor=0.5 (repeatable)",
    )
    ap.add_argument(
        "--gl",
        choices=sorted(GL_FLAGS),
        default="swiftshader",
        help="software WebGL rasteriser: swiftshader (Chromium's fallback, default) or llvmpipe (Mesa)",
    )
    ap.add_argument(
        "--browser",
        type=Path,
        default=CHROMIUM,
        metavar="PATH",
        help=f"the Chromium executable (default {CHROMIUM}); e.g. an older build unpacked with dpkg-deb -x",
    )
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--png", type=Path, help="save a screenshot here (taken ~8 s before the session ends)")
    ap.add_argument(
        "--plot",
        type=Path,
        help="a PNG of the lag over time: of this run, or with --from of saved runs (no run then)",
    )
    ap.add_argument(
        "--from",
        dest="runs",
        nargs="+",
        default=[],
        metavar="LABEL=JSON",
        help="saved runs (--json files) to plot with --plot instead of running",
    )
    args = ap.parse_args(argv)
    if args.runs:
        if args.plot is None:
            ap.error("--from needs --plot")
        runs = []
        for item in args.runs:
            label, sep, path = item.partition("=")
            if not sep:
                ap.error(f"--from {item!r}: LABEL=JSON")
            runs.append((label, json.loads(Path(path).read_text())))
        plot_viewer_lag(runs, args.plot)
        print(f"plot written to {args.plot}")
        return 0
    if not args.browser.is_file() or not os.access(args.browser, os.X_OK):
        if args.browser == CHROMIUM:
            print(f"telesurg bench viewer: needs Chromium at {CHROMIUM} (Debian: apt-get install chromium)")
        else:
            print(f"telesurg bench viewer: --browser {args.browser}: no executable there")
        return 2
    with tempfile.TemporaryDirectory(prefix="bench-viewer-") as tmp:
        res = run(
            args.seconds,
            args.warmup,
            args.set,
            Path(tmp),
            args.png,
            window=args.window,
            autogroup_nice=args.autogroup_nice,
            flags=args.chromium_flag,
            gl=args.gl,
            browser=args.browser,
        )
    lag = res["lag_s"]

    def f(x: float | None, fmt: str = ".2f") -> str:
        return "—" if x is None else format(x, fmt)

    print(f"viewer open {args.seconds:g} s (first picture after {f(res['first_cursor_s'], '.1f')} s)")
    print(
        f"lag behind live after {args.warmup:g} s: p50 {f(lag['p50'])} s, p90 {f(lag['p90'])} s, "
        f"max {f(lag['max'])} s over {lag['n']} samples; under 1 s: {f(lag['share_under_1s'], '.0%')}; "
        f"{lag['unanswered']} of {lag['probes']} probes unanswered within {PROBE_TIMEOUT_S:g} s, "
        f"{lag['viewer_not_started']} before the viewer application started"
    )
    print(
        f"viewer frames/s (median): {f(res['fps']['median'], '.1f')}; Chromium got "
        f"{f(res['browser_cpu_share'])} of a core; load average {res['load_average_at_open']:.1f} at open, "
        f"{res['load_average'][0]:.1f} at the end on {res['cpus']} CPUs"
    )
    print(f"demo: {res['summary']}; engagements {res['engagements']}")
    print(
        f"viewport {res['window'][0]}x{res['window'][1]}; {res['browser_version']}; "
        f"WebGL: {res['webgl_renderer']}; "
        "Chromium's processes by autogroup: "
        + ", ".join(f"{g}: {n}" for g, n in res["chromium_autogroups"].items())
    )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(jsonio.dumps(res, indent=1) + "\n")
    if args.plot:
        plot_viewer_lag([(f"this run, {args.window[0]}x{args.window[1]}", res)], args.plot)
    return 0
