"""The picture where the surgeon looks and in the record (issue #18): ``telesurg view`` serves the
live frames, the MCAP recording keeps every frame (decoded with its schema), and a replay into
rerun shows them as images."""

from __future__ import annotations

import http.cookiejar
import json
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import psutil
import pytest
from conftest import wait_until
from helpers import entity_paths, held_port
from telesurg.services.launcher import Site, SiteSpec, free_port
from telesurg.services.record import iter_decoded, open_mcap
from telesurg.services.record.replay import to_rerun
from telesurg.shared.messages import CameraImage

pytestmark = pytest.mark.process


def test_view_page_recording_and_replay(tmp_path: Path) -> None:
    spec = SiteSpec(
        site="camv", port=free_port(), services=("camera", "slave_control"), log_dir=tmp_path / "logs"
    )
    out = tmp_path / "run.mcap"
    port = free_port()
    with Site(spec):
        view = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "telesurg.services.cli",
                "view",
                "--site",
                "camv",
                "--connect",
                spec.endpoint,
                "--port",
                str(port),
                "--seconds",
                "60",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        try:
            # the page is served only after the one-time login URL it printed (a session cookie)
            assert view.stdout is not None
            line = view.stdout.readline()
            assert line.startswith(f"endoscope view: http://127.0.0.1:{port}/login?token="), line
            login = line.split()[-1]
            binds = {
                c.laddr.ip
                for c in psutil.net_connections("tcp")
                if c.status == "LISTEN" and c.laddr.port == port
            }
            assert binds == {"127.0.0.1"}, f"telesurg view listens on {binds}"
            jar = urllib.request.HTTPCookieProcessor(http.cookiejar.CookieJar())
            browser = urllib.request.build_opener(jar)
            for url, headers, code in (
                (f"http://127.0.0.1:{port}/", {}, 401),  # another local user: no session
                (f"http://127.0.0.1:{port}/status.json", {}, 401),
                (login, {"Host": "rebind.example"}, 403),  # DNS rebinding
            ):
                with pytest.raises(urllib.error.HTTPError) as refused:
                    urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=5)
                assert refused.value.code == code
                assert refused.value.read().startswith(b"refused: ")
            with browser.open(login, timeout=5) as r:  # one step: the cookie, then the page
                assert r.url == f"http://127.0.0.1:{port}/" and b"/stream.mjpg" in r.read()
            with pytest.raises(urllib.error.HTTPError) as again:
                browser.open(login, timeout=5)
            assert again.value.code == 401, "the login URL worked twice"
            rec = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "telesurg.services.cli",
                    "record",
                    "--out",
                    str(out),
                    "--seconds",
                    "3",
                    "--site",
                    "camv",
                    "--connect",
                    spec.endpoint,
                ],
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert rec.returncode == 0, rec.stderr[-2000:]

            def status() -> dict[str, object]:
                try:
                    with browser.open(f"http://127.0.0.1:{port}/status.json", timeout=2) as r:
                        return dict(json.loads(r.read()))
                except OSError:
                    return {}

            assert wait_until(lambda: int(status().get("seq", -1)) >= 0, 20.0), status()
            s = status()
            assert (s["camera"], s["width"], s["height"]) == ("endo", 320, 240)
            with browser.open(f"http://127.0.0.1:{port}/stream.mjpg", timeout=5) as r:
                head = r.read(4096)
            assert head.startswith(b"--frame\r\nContent-Type: image/jpeg") and b"\xff\xd8" in head
        finally:
            view.terminate()
            view.wait(10)
            if view.stdout is not None:
                view.stdout.close()
    with open_mcap(out) as reader:
        frames = [m for t, _, _, _, m in iter_decoded(reader) if t.endswith("/camera/endo/image")]
    assert len(frames) >= 10 and all(isinstance(m, CameraImage) for m in frames), len(frames)
    counts = to_rerun(out, tmp_path / "run.rrd")
    print(f"{len(frames)} frames recorded; replay into rerun: {counts}")
    assert counts.get("images", 0) >= 3
    assert "/camera/endo/image" in entity_paths(tmp_path / "run.rrd")


def test_view_says_why_it_cannot_start() -> None:
    """A taken port or no router: one line saying so, exit 1, no traceback."""
    view = [sys.executable, "-m", "telesurg.services.cli", "view", "--seconds", "1"]
    with held_port() as port:
        taken = subprocess.run([*view, "--port", str(port)], capture_output=True, text=True, timeout=60)
    dead = free_port()  # nothing listens there
    alone = [*view, "--port", str(free_port()), "--connect", f"tcp/127.0.0.1:{dead}"]
    no_router = subprocess.run(alone, capture_output=True, text=True, timeout=60)
    assert taken.returncode == 1 and "Traceback" not in taken.stderr, taken.stderr
    assert f"telesurg view: port {port} on 127.0.0.1: Address already in use" in taken.stderr
    assert no_router.returncode == 1 and "Traceback" not in no_router.stderr, no_router.stderr
    assert "telesurg view: zenoh session failed" in no_router.stderr
