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
import urllib.request
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
    """``telesurg console --web`` connected to ``ep``: (base URL, monotonic time it was started)."""
    port = free_port()
    argv = [sys.executable, "-m", "telesurg.services.cli", "console", "--web", "--port", str(port)]
    argv += ["--connect", ep, "--log-file", str(tmp / "web.log"), *extra]
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}/"
    try:
        assert wait_until(lambda: get(url + "api/stats") is not None, 30.0), "no page within 30 s"
        yield url, t0
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = proc.wait()
        assert code == 0, f"web console exit code {code}"


def get(url: str) -> Any:
    try:
        with urllib.request.urlopen(url, timeout=2) as r:
            return json.loads(r.read())
    except OSError:
        return None


NAN = '{"type": "sample", "master": "m1", "t": 1, "p": [NaN, 0, 0], "q": [0, 0, 0, 1], "clutch": true}'
INF = '{"type": "sample", "master": "m1", "t": 1, "p": [0, 0, 0], "q": [0, 0, 0, Infinity], "clutch": true}'
GOOD = {"type": "sample", "master": "m1", "t": 1.0, "p": [0, 0, 0], "q": [0, 0, 0, 1], "clutch": True}


async def attack(url: str) -> dict[str, Any]:
    """Send each kind of bad frame on one connection (then a flood on a second, and a frame past
    aiohttp's own cap on a third); what the server said and how each connection ended."""
    import aiohttp

    ws_url = url.replace("http", "ws") + "ws"
    out: dict[str, Any] = {}
    async with aiohttp.ClientSession() as http:
        async with http.ws_connect(ws_url) as ws:
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
        async with http.ws_connect(ws_url) as ws:
            for _ in range(2000):
                await ws.send_str('{"type": "ping"}')
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["flood_close"] = ws.close_code
        async with http.ws_connect(ws_url) as ws:  # well-formed frames with bad values, repeated
            for _ in range(60):
                await ws.send_str(json.dumps({**GOOD, "p": [0, 0, 9.0]}))
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["values_close"] = ws.close_code
        async with http.ws_connect(ws_url, max_msg_size=0) as ws:
            await ws.send_str("y" * (1 << 20))
            msg = await ws.receive(timeout=10)
            while msg.type == aiohttp.WSMsgType.TEXT:
                msg = await ws.receive(timeout=10)
            out["huge_close"] = ws.close_code
    return out


def test_bad_socket_input_is_refused_counted_and_never_reaches_the_bus(endpoint: str, tmp_path: Path) -> None:
    seen: list[str] = []
    lock = threading.Lock()
    session = open_session(BusConfig(connect=[endpoint]))
    try:

        def on_sample(s: Any) -> None:
            with lock:
                seen.append(str(s.key_expr))

        sub = session.declare_subscriber("telesurg/local/master/**", on_sample)
        with web_console(endpoint, tmp_path) as (url, _):
            result = asyncio.run(attack(url))
            stats = get(url + "api/stats")
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


async def first_state(url: str) -> tuple[float, dict[str, Any]]:
    import aiohttp

    async with aiohttp.ClientSession() as http, http.ws_connect(url.replace("http", "ws") + "ws") as ws:
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
