"""The web console's websocket against bad input, and a console opened late (issue #19,
acceptance 4 and 5). Real processes: ``telesurg console --web`` on a router (and, for the late
join, a whole site with its scripted master)."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from telesurg.services.launcher import Site, SiteSpec, default_config_dir, free_port
from telesurg.shared.bus import BusConfig, open_session

pytestmark = pytest.mark.process


@contextmanager
def web_console(ep: str, tmp: Path, *extra: str) -> Iterator[tuple[str, float]]:
    """``telesurg console --web`` connected to ``ep``: (the one-time login URL it printed,
    monotonic time it was started)."""
    port = free_port()
    argv = [sys.executable, "-m", "telesurg.services.cli", "console", "--web", "--port", str(port)]
    argv += ["--connect", ep, "--log-file", str(tmp / "web.log"), *extra]
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    lines: list[str] = []
    assert proc.stdout is not None
    out = proc.stdout
    reader = threading.Thread(target=lambda: lines.extend(out), daemon=True)
    reader.start()
    try:
        printed = lambda: next((x.split()[-1] for x in lines if x.startswith("web console: ")), "")  # noqa: E731
        assert wait_until(lambda: bool(printed()), 60.0), f"no login URL printed within 60 s: {lines}"
        login = printed()
        assert login.startswith(f"http://127.0.0.1:{port}/login?token="), login
        yield login, t0
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        reader.join(5)
        out.close()
        assert code == 0, f"web console exit code {code}"


def base_of(login: str) -> str:
    return login.split("login?")[0]


async def logged_in(http: Any, login: str) -> None:
    """Open the printed login URL (one step: the cookie, then the page)."""
    async with http.get(login) as r:
        assert r.status == 200 and str(r.url) == base_of(login), (r.status, r.url)


def client() -> Any:
    import aiohttp

    return aiohttp.ClientSession(cookie_jar=aiohttp.CookieJar(unsafe=True))  # (an IP address host)


NAN = '{"type": "sample", "master": "m1", "t": 1, "p": [NaN, 0, 0], "q": [0, 0, 0, 1], "clutch": true}'
INF = '{"type": "sample", "master": "m1", "t": 1, "p": [0, 0, 0], "q": [0, 0, 0, Infinity], "clutch": true}'
GOOD = {"type": "sample", "master": "m1", "t": 1.0, "p": [0, 0, 0], "q": [0, 0, 0, 1], "clutch": True}


async def attack(login: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """Logged in, send each kind of bad frame on one connection (then a flood on a second, and a
    frame past aiohttp's own cap on a third); what the server said and how each connection ended,
    and the console's counters after."""
    import aiohttp

    url = base_of(login)
    ws_url = url.replace("http", "ws") + "ws?page=tester1"  # one page: the one in control
    origin = url.rstrip("/")
    out: dict[str, Any] = {}
    async with client() as http:
        await logged_in(http, login)
        async with http.ws_connect(ws_url, origin=origin) as ws:
            bad: list[str | bytes] = [
                "{not json",
                "[1, 2, 3]",
                NAN,
                INF,
                json.dumps({**GOOD, "speed": 9}),  # unknown field
                json.dumps({"type": "teleport"}),  # unknown type
                json.dumps({**GOOD, "p": [5.0, 0, 0]}),  # out of range
                json.dumps({**GOOD, "q": [0, 0, 0, 3]}),  # not a unit quaternion
                json.dumps({**GOOD, "pad": "x" * 5000}),  # oversized (under aiohttp's cap)
                b"\x93\x01\x02",  # binary
                json.dumps({"type": "reset", "arm": "*", "confirm": False}),  # reset unconfirmed
            ]
            for f in bad:
                await (ws.send_bytes(f) if isinstance(f, bytes) else ws.send_str(f))
            await asyncio.sleep(0.5)
            out["first_closed"] = ws.closed
        async with http.ws_connect(ws_url, origin=origin) as ws:
            for _ in range(2000):
                await ws.send_str('{"type": "ping"}')
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["flood_close"] = ws.close_code
        async with http.ws_connect(
            ws_url, origin=origin
        ) as ws:  # well-formed frames with bad values, repeated
            for _ in range(60):
                await ws.send_str(json.dumps({**GOOD, "p": [0, 0, 9.0]}))
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["values_close"] = ws.close_code
        async with http.ws_connect(ws_url, origin=origin, max_msg_size=0) as ws:
            await ws.send_str("y" * (1 << 20))
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["huge_close"] = ws.close_code
        async with http.get(url + "api/stats") as r:
            stats = await r.json()
    return out, stats


def test_bad_socket_input_is_refused_counted_and_never_reaches_the_bus(endpoint: str, tmp_path: Path) -> None:
    seen: list[str] = []
    lock = threading.Lock()
    session = open_session(BusConfig(connect=[endpoint]))
    try:

        def on_sample(s: Any) -> None:
            with lock:
                seen.append(str(s.key_expr))

        sub = session.declare_subscriber("telesurg/local/master/**", on_sample)
        with web_console(endpoint, tmp_path) as (login, _):
            result, stats = asyncio.run(attack(login))
            time.sleep(0.3)
        sub.undeclare()
    finally:
        session.close()  # type: ignore[no-untyped-call]
    print("socket:", result, stats)
    r = stats["rejected"]
    assert r.get("malformed", 0) >= 2 and r.get("nonfinite", 0) >= 2
    assert r.get("unknown", 0) >= 2 and r.get("invalid", 0) >= 3 + 50
    assert r.get("oversized", 0) >= 1 and r.get("binary", 0) >= 1
    assert r.get("flood", 0) >= 1
    assert not result["first_closed"], "a few bad frames must not close the connection"
    assert result["flood_close"] == 1008, "the flooding connection is closed (policy violation)"
    assert result["huge_close"] == 1009, "a frame past the cap closes the connection (too big)"
    assert result["values_close"] == 1008, "repeated out-of-range samples close the connection"
    assert stats["closed_abusive"] >= 2
    with lock:
        assert seen == [], f"bad input reached the bus: {seen[:5]}"


async def first_state(login: str) -> tuple[float, dict[str, Any]]:
    url = base_of(login)
    async with client() as http:
        await logged_in(http, login)
        async with http.ws_connect(url.replace("http", "ws") + "ws", origin=url.rstrip("/")) as ws:
            t = time.monotonic()
            msg = await ws.receive(timeout=10)
            return t, json.loads(msg.data)


def test_a_console_opened_after_the_engage_shows_it_at_once(tmp_path: Path) -> None:
    """Acceptance 5: the site's scripted master engages; a web console started afterwards shows
    ENABLED in the first state it sends a page, and within 0.5 s of its session opening."""
    spec = SiteSpec(
        port=free_port(),
        config_dir=default_config_dir(),
        services=("watchdog", "slave_control", "mapping", "master_capture"),
        log_dir=tmp_path / "logs",
    )
    with Site(spec) as site:
        session = open_session(BusConfig(connect=[spec.endpoint]))
        try:
            from telesurg.shared.messages import TeleopState, decode_as

            states: list[tuple[float, str]] = []  # (monotonic s, the mapping's teleop state)

            def on_teleop(s: Any) -> None:
                states.append((time.monotonic(), decode_as(bytes(s.payload), TeleopState).state))

            sub = session.declare_subscriber("telesurg/local/mapping/arm1/teleop_state", on_teleop)
            assert wait_until(lambda: any(st == "ENABLED" for _, st in states), 30.0), "no engage"
            # its own master node under another id: the site's scripted master_capture is running
            extra = ("--set", "web.master_service=web_master")
            with web_console(spec.endpoint, tmp_path, *extra) as (url, t_start):
                t_up = time.monotonic()
                t_ws, state = asyncio.run(first_state(url))
                tp = state["arms"][0]["teleop"]
                print(
                    f"late console: first page state {tp and tp['state']} "
                    f"({(t_ws - t_up) * 1e3:.0f} ms after the page was served, "
                    f"{(t_ws - t_start):.2f} s after the process started); mapping: {states[-3:]}"
                )
                # the truth: what the mapping said last before the page's state, or within 0.5 s
                truth = {st for t, st in states if t_ws - 0.5 <= t <= t_ws + 0.05}
                before = [st for t, st in states if t <= t_ws]
                if before:
                    truth.add(before[-1])
                assert tp is not None and not tp["stale"] and tp["state"] in truth, (tp, truth)
            sub.undeclare()
        finally:
            session.close()  # type: ignore[no-untyped-call]
        assert not site.dead()
