"""The web console's door in headless chromium and from plain socket clients (issue #39,
acceptance 2 and 4). One ``telesurg console --web`` on a router serves every case:

* a client without the session (no cookie; also another local user, uid nobody), a foreign
  ``Host`` (``rebind.example``, DNS rebinding: chromium maps the name to 127.0.0.1) and a page
  served from another origin
  (another 127.0.0.1 port) in the same chromium that holds the operator's session cookie cannot
  read the state, drive, confirm, record, reset or take control: each gets a one-line refusal
  (HTTP 401/403, or its websocket closed with the reason) and is counted;
* the printed login URL logs in in one step (cookie HttpOnly, the token gone from the address);
* a second page is a viewer (may e-stop, nothing else) until the controller hands control over;
  the page that lost control says so at once.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import psutil
import pytest
from conftest import wait_until
from helpers import DevTools, chromium, run_unprivileged
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.messages import CartesianPose, EStop, SafetyEvent
from test_web_console import click, js, needs_chromium, text, wait_page
from test_web_console_socket import base_of, web_console

pytestmark = pytest.mark.process

EVIL = """<!doctype html><html><body>evil<script>
window.result = {ws: null, fetch: null, opened: false};
const ws = new WebSocket("ws://127.0.0.1:PORT/ws?page=evil1234");
ws.onopen = () => {
  window.result.opened = true;
  for (const f of [{type: "record", action: "start"}, {type: "reset", arm: "*", confirm: true},
                   {type: "control", action: "take"}, {type: "confirm", yes: true},
                   {type: "sample", master: "m1", t: Date.now(), p: [0.01, 0, 0], q: [0, 0, 0, 1],
                    clutch: true}])
    ws.send(JSON.stringify(f));
};
ws.onclose = (e) => { window.result.ws = [e.code, e.reason]; };
fetch("http://127.0.0.1:PORT/api/state", {credentials: "include"})
  .then((r) => r.text()).then((t) => { window.result.fetch = "read " + t.slice(0, 40); })
  .catch((e) => { window.result.fetch = "failed: " + e; });
</script></body></html>"""


@contextmanager
def evil_site(console_port: int) -> Iterator[str]:
    """A page on another 127.0.0.1 port that tries the console's websocket and API."""
    body = EVIL.replace("PORT", str(console_port)).encode()

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, fmt: str, *args: Any) -> None:
            pass

        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


async def outsiders(base: str) -> dict[str, Any]:
    """A socket client without the session, and one with a foreign Host: what each was told."""
    import aiohttp

    out: dict[str, Any] = {}
    ws_url = base.replace("http", "ws") + "ws"
    origin = base.rstrip("/")
    async with aiohttp.ClientSession() as http:
        for path in ("", "api/state", "static/console.js"):
            async with http.get(base + path) as r:
                out[f"nocookie /{path}"] = (r.status, (await r.text()).strip())
        async with http.ws_connect(ws_url, origin=origin) as ws:
            msg = await ws.receive(timeout=10)
            out["nocookie ws"] = (msg.type.name, ws.close_code, msg.extra)
        foreign = {"Host": f"rebind.example:{base.rsplit(':', 1)[1].strip('/')}"}
        async with http.get(base + "api/state", headers=foreign) as r:
            out["host /api/state"] = (r.status, (await r.text()).strip())
        async with http.ws_connect(ws_url, headers=foreign, origin="http://" + foreign["Host"]) as ws:
            msg = await ws.receive(timeout=10)
            out["host ws"] = (msg.type.name, ws.close_code, msg.extra)
        async with http.get(base + "login?token=guessed") as r:
            out["bad login"] = (r.status, (await r.text()).strip())
    return out


def new_page(cdp: DevTools, url: str) -> str:
    """Open ``url`` in a new tab of the same chromium (same cookies); its session id."""
    target = cdp.call("Target.createTarget", {"url": url})["targetId"]
    s = cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
    cdp.call("Emulation.setFocusEmulationEnabled", {"enabled": True}, s)
    return s


def api_state(cdp: DevTools, s: str) -> dict[str, Any]:
    """The console's state read by the logged-in page itself (its own origin, its cookie)."""
    return dict(js(cdp, s, "fetch('/api/state').then((r) => r.json())"))


@pytest.mark.timeout(600)
def test_outsiders_are_refused_and_control_moves_only_by_handover(endpoint: str, tmp_path: Path) -> None:
    needs_chromium()
    events: list[tuple[str, str]] = []
    estops: list[tuple[str, str]] = []
    lock = threading.Lock()

    def on_event(m: SafetyEvent, key: str) -> None:
        with lock:
            events.append((m.kind, m.text))

    def on_estop(m: EStop, key: str) -> None:
        with lock:
            estops.append((m.header.source, m.action))

    masters: list[float] = []  # |x| of each master pose published (the pages' own stay at 0)

    def on_master(m: CartesianPose, key: str) -> None:
        with lock:
            masters.append(abs(m.position[0]))

    with (
        Node(BusConfig(connect=[endpoint]), "local", "doortest") as node,
        web_console(endpoint, tmp_path) as (login, _),
    ):
        k = node.keys
        node.subscribe(k.events(), SafetyEvent, on_event)
        node.subscribe(k.estop, EStop, on_estop)
        node.subscribe(k.master("m1", "measured_cp"), CartesianPose, on_master)
        base = base_of(login)
        port = int(base.rsplit(":", 1)[1].strip("/"))

        # the page listens on loopback only (web.host's default)
        binds = {
            c.laddr.ip for c in psutil.net_connections("tcp") if c.status == "LISTEN" and c.laddr.port == port
        }
        assert binds == {"127.0.0.1"}, binds

        # -- plain socket clients: no session; a foreign Host ------------------------------------
        told = asyncio.run(outsiders(base))
        print("outsiders:", json.dumps(told, indent=1))
        for path in ("", "api/state", "static/console.js"):
            status, why = told[f"nocookie /{path}"]
            assert status == 401 and why.startswith("refused: not logged in"), (path, status, why)
        assert told["nocookie ws"][:2] == ("CLOSE", 4401) and "not logged in" in told["nocookie ws"][2]
        assert told["host /api/state"][0] == 403 and "rebind.example" in told["host /api/state"][1]
        assert told["host ws"][:2] == ("CLOSE", 4403) and "Host" in told["host ws"][2]
        assert told["bad login"][0] == 401 and "not valid" in told["bad login"][1]
        # another local user (uid nobody when the tests run as root)
        other = run_unprivileged(
            "import encodings.idna, urllib.error, urllib.request",
            f"try:\n    urllib.request.urlopen('{base}api/state', timeout=10)\n    print('served')\n"
            "except urllib.error.HTTPError as e:\n    print(e.code, e.read().decode().strip())",
        )
        assert other.stdout.startswith("401 refused: not logged in"), (other.stdout, other.stderr[-500:])

        flags = ("--host-resolver-rules=MAP rebind.example 127.0.0.1",)
        with chromium(login, tmp_path, nice=0, flags=flags) as (cdp, s1):
            # -- the printed login URL: one step to the page, the token gone, the cookie hidden ------
            wait_page(cdp, s1, "#control", lambda t: t == "this page is in control", 30.0)
            assert js(cdp, s1, "location.href") == base, "the page's address still carries the token"
            assert js(cdp, s1, "document.cookie") == "", "the session cookie is readable by scripts"
            wait_page(cdp, s1, "#link", lambda t: t == "console connected", 10.0)
            # the same login URL a second time: refused (one use)
            s_again = new_page(cdp, login)
            time.sleep(1.0)
            assert "not valid" in str(js(cdp, s_again, "document.body.innerText"))

            # -- a page from another origin, in the same chromium (it holds the session cookie) -----
            with evil_site(port) as evil:
                s_evil = new_page(cdp, evil)
                assert wait_until(lambda: bool((js(cdp, s_evil, "window.result") or {}).get("ws")), 15.0)
                assert wait_until(lambda: bool((js(cdp, s_evil, "window.result") or {}).get("fetch")), 15.0)
                r = js(cdp, s_evil, "window.result")
            print("another origin:", r)
            assert r["ws"][0] == 4403 and "Origin" in r["ws"][1], r
            assert r["fetch"].startswith("failed"), f"another origin read the state: {r}"

            # -- a foreign Host in chromium (DNS rebinding): refused with the reason ----------------
            s_rebind = new_page(cdp, f"http://rebind.example:{port}/")
            time.sleep(1.0)
            body = str(js(cdp, s_rebind, "document.body.innerText"))
            assert body.startswith("refused: Host 'rebind.example"), body

            # -- a second page of the operator's session: a viewer --------------------------------
            s2 = new_page(cdp, base)
            wait_page(cdp, s2, "#control", lambda t: t.startswith("VIEWER"), 30.0)
            st0 = api_state(cdp, s2)
            for frame in (
                {"type": "record", "action": "start"},
                {"type": "reset", "arm": "*", "confirm": True},
                {"type": "confirm", "yes": True},
                {"type": "command", "arm": "arm1", "name": "teach_trocar"},
                {
                    "type": "sample",
                    "master": "m1",
                    "t": time.time() * 1e3,
                    "p": [0.02, 0, 0],
                    "q": [0, 0, 0, 1],
                    "clutch": True,
                },
            ):
                js(cdp, s2, f"ws.send({json.dumps(json.dumps(frame))})")
            time.sleep(1.0)
            log2 = text(cdp, s2, "#log")
            assert "viewer" in log2, log2
            # a viewer's e-stop goes out
            n_estop = len(estops)
            click(cdp, s2, "#estop")
            assert wait_until(lambda: len(estops) > n_estop, 5.0), "the viewer's e-stop was not sent"

            # -- the handover: the viewer asks, the controller grants; the first page is told -------
            click(cdp, s2, "#take")
            wait_page(cdp, s2, "#control", lambda t: "asked for control" in t, 10.0)
            assert js(cdp, s1, "document.querySelector('#handover').hidden") is False
            assert text(cdp, s1, "#control") == "this page is in control", "control moved before the grant"
            t_grant = time.monotonic()
            click(cdp, s1, "#handover-yes")
            wait_page(cdp, s1, "#control", lambda t: t.startswith("VIEWER"), 5.0)
            told_ms = (time.monotonic() - t_grant) * 1e3
            wait_page(cdp, s2, "#control", lambda t: t == "this page is in control", 5.0)
            assert "now a viewer" in text(cdp, s1, "#log")
            st1 = api_state(cdp, s1)
            # the operator's page shows the refusals at its door
            shown = wait_page(cdp, s1, "#door-refused", lambda t: "origin" in t and "host" in t, 5.0)
            print(f"handover: first page told within {told_ms:.0f} ms; the page shows {shown!r}")

        time.sleep(0.5)
        with lock:
            kinds = [k for k, _ in events]
            handed = [t for k, t in events if k == "web_control"]
            actions = [a for src, a in estops if src == "console"]
        refused = st1["door"]["refused"]
        # counted: no session (3 pages + the socket + the other user), foreign Host (socket,
        # chromium), Origin, login
        assert refused.get("session", 0) >= 5 and refused.get("host", 0) >= 2, refused
        assert refused.get("origin", 0) >= 1 and refused.get("login", 0) >= 2, refused
        assert "web_refused" in kinds and "web_login" in kinds, kinds
        assert any("handed control" in t for t in handed), handed
        # nothing the outsiders or the viewer sent was acted on
        assert st0["recording"] is False and st1["recording"] is False
        assert st1["socket"]["rejected"].get("viewer", 0) >= 5, st1["socket"]
        assert "reset" not in actions, f"a reset went out: {actions}"
        assert masters and max(masters) < 1e-3, (
            f"an outsider's or the viewer's sample was published: {max(masters)}"
        )
