"""The web cases of ``telesurg bench attack`` (issue #39): outsiders at the web console's door.

A web console (``telesurg console --web``, the console identity, no browser master of its own:
the bench site's master_capture is the master) is started on the bench site; the bench logs in
with the login URL it printed, as the operator would. Then, per case, an outsider tries the page,
``/api/state`` and the websocket, and over the socket every action (read the state, ``sample``,
``confirm yes``, ``record start``, ``reset``, ``control take``):

=======================  ======================================================================
``web-no-session``       a client without the session cookie (another local user, a script)
``web-foreign-host``     the operator's session cookie, but ``Host: rebind.example`` (DNS
                         rebinding)
``web-cross-origin``     the operator's session cookie and ``Origin: http://127.0.0.1:28999`` (a
                         page served from another origin in the operator's browser)
=======================  ======================================================================

Per case: **sent** (requests and websocket frames), **accepted** (a request served with 200, a
websocket that carried anything but its refusal, a frame the console counted as accepted), the
refusals the console counted (by kind), the one-line reasons the outsider was given, and the slave
tip's motion. Limits: 0 accepted, motion < 0.5 mm.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from telesurg.services.launcher import free_port
from telesurg.tools.bench.harness import now_ns

#: the attack bench's tip motion, mm, of a pipeline between two probe times (None: no data)
Motion = Callable[[Any, int, int], float | None]

#: the frames an outsider tries over the websocket, each an action only the controlling page may do
FRAMES = (
    {"type": "sample", "master": "m1", "t": 0.0, "p": [0.05, 0, 0], "q": [0, 0, 0, 1], "clutch": True},
    {"type": "confirm", "yes": True},
    {"type": "record", "action": "start"},
    {"type": "reset", "arm": "*", "confirm": True},
    {"type": "control", "action": "take"},
)
OTHER_ORIGIN = "http://127.0.0.1:28999"


class WebConsole:
    """A ``telesurg console --web`` on the bench site and the operator's logged-in session."""

    def __init__(self, endpoint: str, site: str) -> None:
        self.port = free_port()
        argv = [sys.executable, "-m", "telesurg.services.cli", "console", "--web", "--port", str(self.port)]
        argv += ["--connect", endpoint, "--site", site, "--set", 'web.master_service=""']
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.lines: list[str] = []
        assert self.proc.stdout is not None
        out = self.proc.stdout
        self._reader = threading.Thread(target=lambda: self.lines.extend(out), daemon=True)
        self._reader.start()
        self.base = f"http://127.0.0.1:{self.port}/"
        self.cookie = ""  # the operator's session cookie (name=value)
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and self.proc.poll() is None:
            login = next((x.split()[-1] for x in self.lines if x.startswith("web console: ")), "")
            if login:
                self.cookie = asyncio.run(self._login(login))
                return
            time.sleep(0.1)
        self.close()
        raise RuntimeError("the web console printed no login URL within 60 s")

    async def _login(self, url: str) -> str:
        import aiohttp

        async with aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True)) as http:
            async with http.get(url) as r:
                if r.status != 200:
                    raise RuntimeError(f"the printed login URL gave HTTP {r.status}")
            cookies = [f"{c.key}={c.value}" for c in http.cookie_jar]
        if not cookies:
            raise RuntimeError("the login set no session cookie")
        return cookies[0]

    def stats(self) -> dict[str, Any]:
        """The console's counters, read by the operator's session."""
        import urllib.request

        req = urllib.request.Request(self.base + "api/stats", headers={"Cookie": self.cookie})
        with urllib.request.urlopen(req, timeout=5) as r:
            out: dict[str, Any] = json.loads(r.read())
        return out

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._reader.join(5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


async def _try(base: str, headers: dict[str, str], origin: str | None) -> dict[str, Any]:
    """Every door of the console with ``headers``: what was served and what was said."""
    import aiohttp

    sent = accepted = 0
    said: list[str] = []
    async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=30)) as http:
        for path in ("", "api/state", "api/stats", "video.mjpg"):
            sent += 1
            # (with its Origin, as a page's fetch sends it; a served MJPEG stream never ends: the
            # first bytes only)
            get_headers = {**headers, **({"Origin": origin} if origin else {})}
            async with http.get(base + path, headers=get_headers) as r:
                accepted += r.status == 200
                said.append(
                    f"/{path}: {r.status} {(await r.content.read(100)).decode(errors='replace').strip()}"
                )
        sent += 1
        ws_url = base.replace("http", "ws") + "ws"
        async with http.ws_connect(ws_url, headers=dict(headers), origin=origin) as ws:
            for f in FRAMES:
                sent += 1
                with contextlib.suppress(ConnectionError, RuntimeError):  # (closed by then)
                    await ws.send_str(json.dumps({**f, "t": time.time() * 1e3} if "t" in f else f))
            got = []
            while True:
                msg = await ws.receive(timeout=5)
                if msg.type != aiohttp.WSMsgType.TEXT:
                    said.append(f"/ws: closed {ws.close_code} {msg.extra or ''}")
                    break
                got.append(msg.data)
            accepted += bool(got)  # anything over the socket but its refusal: the state, a reply
    return {"sent": sent, "served": accepted, "said": said}


def _web_case(how: str, motion: Motion) -> Callable[[Any], dict[str, Any]]:
    """A web case (see the module docstring): ``how`` = no-session | foreign-host | cross-origin."""

    def run(a: Any) -> dict[str, Any]:
        pipe = a.pipe
        web = WebConsole(pipe.spec.endpoint, pipe.spec.site)
        try:
            before = web.stats()
            t0 = now_ns()
            own = web.base.rstrip("/")
            host = f"127.0.0.1:{web.port}"
            if how == "no-session":
                headers, origin = {}, own
            elif how == "foreign-host":
                host = f"rebind.example:{web.port}"
                headers, origin = {"Cookie": web.cookie, "Host": host}, f"http://{host}"
            else:
                headers, origin = {"Cookie": web.cookie}, OTHER_ORIGIN
            tried = asyncio.run(_try(web.base, headers, origin))
            time.sleep(0.5)
            after = web.stats()
        finally:
            web.close()
        frames = after["accepted"] - before["accepted"]
        refused = {
            k: v - before["door"].get(k, 0) for k, v in after["door"].items() if v != before["door"].get(k, 0)
        }
        return {
            "sent": tried["sent"],
            "accepted": tried["served"] + frames,
            "forbidden": True,
            "refused": refused,
            "said": tried["said"],
            "motion_mm": motion(pipe, t0, now_ns()),
        }

    return run


def web_cases(case: Callable[..., Any], motion: Motion) -> list[Any]:
    """The web cases as ``case(name, text, run, fresh=False)`` (the attack bench's ``Case``), each
    on the site the command cases share (a console of its own per case); ``motion(pipe, t0, t1)``
    is the bench's tip motion in mm."""
    what = {
        "no-session": "web console: no session cookie",
        "foreign-host": "web console: Host rebind.example, the cookie",
        "cross-origin": "web console: another page's Origin, the cookie",
    }
    return [case(f"web-{how}", text, _web_case(how, motion), fresh=False) for how, text in what.items()]
