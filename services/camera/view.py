"""``telesurg view``: the live endoscope picture in a small web page (until the web console lands).

Subscribes to ``camera/<cam>/image`` and serves, on 127.0.0.1 only, a page (``/``) with the
picture as an MJPEG stream (``/stream.mjpg``: each frame's JPEG as it arrives, no re-encoding)
and the frame's age, sequence and size (``/status.json``). Any browser shows it — once logged in:
like the web console, the page is served only with the session cookie that the one-time login URL
printed at start gives (:mod:`telesurg.shared.door`: Host and Origin checked, sessions
expire after 8 h); another local user or another page in the browser gets a one-line refusal.

Example::

    telesurg view --connect tcp/127.0.0.1:7447 --port 8088    # open the login URL it prints
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading
import time
from collections.abc import Sequence
from http.cookies import SimpleCookie
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs

from telesurg.services.common import duration_s, install_stop_handlers, setup_logging, tcp_port
from telesurg.shared import mjpeg
from telesurg.shared.bus import Node, add_bus_args, bus_from_args
from telesurg.shared.clock import wall_ns
from telesurg.shared.door import Door
from telesurg.shared.errors import TelesurgError
from telesurg.shared.messages import CameraImage

log = logging.getLogger("telesurg.view")

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>telesurg endoscope</title>
<style>body{background:#111;color:#ddd;font:14px sans-serif;margin:1em}img{width:min(96vw,960px);
image-rendering:auto;border:1px solid #444}</style></head><body>
<div id="s">waiting for frames…</div><img src="/stream.mjpg" alt="endoscope">
<script>setInterval(async()=>{try{const s=await (await fetch('/status.json')).json();
document.getElementById('s').textContent=`camera ${s.camera}  seq ${s.seq}  ${s.width}x${s.height}  `+
`age at arrival ${s.age_ms.toFixed(1)} ms  ${s.fps.toFixed(1)} fps`;}catch(e){}},500);</script>
</body></html>"""


class Latest:
    """The newest frame and its arrival, shared by the zenoh callback and the HTTP threads."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.msg: CameraImage | None = None
        self.age_ms = 0.0
        self.arrivals: list[float] = []

    def on_frame(self, msg: CameraImage, key: str) -> None:
        now = time.monotonic()
        with self.cond:
            self.msg = msg
            self.age_ms = (wall_ns() - msg.capture_ns) / 1e6
            self.arrivals = [t for t in self.arrivals if now - t < 2.0] + [now]
            self.cond.notify_all()

    def status(self) -> dict[str, Any]:
        with self.cond:
            m = self.msg
            if m is None:
                return {"camera": "", "seq": -1, "width": 0, "height": 0, "age_ms": 0.0, "fps": 0.0}
            return {
                "camera": m.camera,
                "seq": m.header.seq,
                "width": m.width,
                "height": m.height,
                "age_ms": self.age_ms,
                "fps": len(self.arrivals) / 2.0,
            }


def make_server(latest: Latest, port: int, stop: threading.Event, door: Door) -> ThreadingHTTPServer:
    """The page, the MJPEG stream and the status on 127.0.0.1:``port``, behind ``door``."""

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt: str, *args: Any) -> None:
            log.debug(fmt, *args)

        def _admitted(self, method: str) -> bool:
            path, _, query = self.path.partition("?")
            cookies = {k: m.value for k, m in SimpleCookie(self.headers.get("Cookie", "")).items()}
            headers = {h: v for h in ("Host", "Origin") if (v := self.headers.get(h)) is not None}
            verdict = door.admit(method, path, headers, cookies, websocket=False)
            if not verdict.ok:
                log.warning("%s (from %s)", verdict.reason, self.client_address[0])
                self._send(verdict.reason.encode() + b"\n", "text/plain; charset=utf-8", verdict.status)
                return False
            if path == "/login":
                got = door.login(parse_qs(query).get("token", [""])[0])
                if got is None:
                    reason = b"refused: this login link is not valid (already used or mistyped)\n"
                    log.warning("refused login from %s", self.client_address[0])
                    self._send(reason, "text/plain; charset=utf-8", 401)
                    return False
                self.send_response(303)
                self.send_header("Location", "/")
                self.send_header("Set-Cookie", door.cookie_header(got[0]))
                self.send_header("Cache-Control", "no-store")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return False
            return True

        def do_POST(self) -> None:
            if self._admitted("POST"):
                self.send_error(405)

        def do_GET(self) -> None:
            if not self._admitted("GET"):
                return
            if self.path == "/":
                self._send(PAGE.encode(), "text/html; charset=utf-8")
            elif self.path == "/status.json":
                self._send(json.dumps(latest.status()).encode(), "application/json")
            elif self.path == "/stream.mjpg":
                self._stream()
            else:
                self.send_error(404)

        def _send(self, body: bytes, ctype: str, status: int = 200) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _stream(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", mjpeg.CONTENT_TYPE)
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            try:
                self.wfile.write(mjpeg.START)
            except OSError:
                return
            last = -1
            while not stop.is_set():
                with latest.cond:
                    latest.cond.wait_for(
                        lambda last=last: (
                            stop.is_set()  # type: ignore[misc]
                            or (latest.msg is not None and latest.msg.header.seq != last)
                        ),
                        timeout=1.0,
                    )
                    m = latest.msg
                if m is None or m.header.seq == last:
                    continue
                last = m.header.seq
                try:
                    self.wfile.write(mjpeg.part(m.data))  # (shown on arrival: shared/mjpeg.py)
                except OSError:  # the browser went away
                    return

    server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    server.daemon_threads = True
    return server


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg view``."""
    ap = argparse.ArgumentParser(prog="telesurg view", description=__doc__)
    ap.add_argument("--site", default="local", help="site id (default: local)")
    ap.add_argument("--camera", default="endo", help="camera id (default: endo)")
    ap.add_argument("--port", type=tcp_port, default=8088, help="HTTP port on 127.0.0.1 (default 8088)")
    ap.add_argument("--seconds", type=duration_s, default=0.0, help="stop after this long (0: Ctrl-C)")
    add_bus_args(ap)
    a = ap.parse_args(argv)
    bus = bus_from_args(a)
    if not bus.connect and bus.mode == "client":
        bus.connect = ["tcp/127.0.0.1:7447"]
    setup_logging("INFO", "view")
    stop = threading.Event()
    install_stop_handlers(stop)
    latest = Latest()
    door = Door("127.0.0.1", a.port, cookie="telesurg_view")
    try:  # the page's port first: a taken one is said before anything joins the site
        server = make_server(latest, a.port, stop, door)
    except OSError as exc:
        print(
            f"telesurg view: port {a.port} on 127.0.0.1: {exc.strerror or exc} (--port picks another)",
            file=sys.stderr,
        )
        return 1
    try:
        with Node(bus, a.site, f"view_{a.port}") as node:
            node.subscribe(
                node.keys.camera(a.camera, "image"), CameraImage, latest.on_frame, sources=["camera"]
            )
            threading.Thread(target=server.serve_forever, daemon=True).start()
            log.info("endoscope view: http://127.0.0.1:%d/ (log in with the login URL)", a.port)
            # (stdout only, never the log: the one-time login token is the page's secret)
            print(f"endoscope view: {door.login_url(door.mint())}", flush=True)
            stop.wait(a.seconds or None)
            stop.set()
            with latest.cond:
                latest.cond.notify_all()
            server.shutdown()
    except (ConnectionError, TelesurgError) as exc:  # no router there, a bad keyring
        print(f"telesurg view: {exc}", file=sys.stderr)
        return 1
    finally:
        server.server_close()
    return 0
