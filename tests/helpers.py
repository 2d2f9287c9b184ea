"""Helpers only the tests use (imported as ``from helpers import ...``; ``tests/`` is on the path).

* .rrd readers — what the mirror wrote, read back with rerun's own chunk reader;
* :func:`clutch_flags` — the bench's clutch schedule as ``--set`` flags for a launched site;
* headless Debian chromium driven over the DevTools protocol on a pipe (:func:`chromium`,
  :class:`DevTools`, :func:`screenshot`): the viewer and web console browser tests.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import json
import os
import select
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from telesurg.services.bench.harness import BENCH_CLUTCH
from telesurg.shared.messages import CartesianPose, Header, MasterButtons

#: header of the messages the tests hand to a mapping's callbacks
TEST_HEADER = Header("test", 0, 0)


def clutch_flags() -> list[str]:
    """``--set`` flags for ``telesurg up`` / ``demo`` / ``deploy/console.sh`` that give the
    site's scripted master the bench's clutch schedule (a hold ends one engagement, not a run)."""
    return [arg for item in BENCH_CLUTCH for arg in ("--set", f"master_capture.{item}")]


def _chunks(path: str | Path) -> Any:
    from rerun.chunk import RrdReader

    return RrdReader(str(path)).stream()


def entity_paths(path: str | Path) -> set[str]:
    """Every entity path with data in the first recording of an .rrd (properties excluded)."""
    return {c.entity_path for c in _chunks(path) if not c.entity_path.startswith("/__")}


def scalar_counts(path: str | Path) -> dict[str, int]:
    """Number of Scalars rows per entity path in an .rrd."""
    counts: dict[str, int] = {}
    for c in _chunks(path):
        names = c.to_record_batch().schema.names
        if any(n.startswith("Scalars:") for n in names):
            counts[c.entity_path] = counts.get(c.entity_path, 0) + c.num_rows
    return counts


def text_logs(path: str | Path) -> list[tuple[str, str, str]]:
    """``(entity_path, level, text)`` of every TextLog row in an .rrd, in file order."""
    out: list[tuple[str, str, str]] = []
    for c in _chunks(path):
        batch = c.to_record_batch()
        names = batch.schema.names
        if "TextLog:text" not in names:
            continue
        texts = batch.column("TextLog:text").to_pylist()
        levels = (
            batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(texts)
        )
        for t, lv in zip(texts, levels, strict=True):
            for i, line in enumerate(t or []):
                level = lv[i] if lv and i < len(lv) else ""
                out.append((c.entity_path, str(level or ""), str(line)))
    return out


def feed_master(arm: Any, p: tuple[float, float, float], clutch: bool) -> None:
    """One master sample into a mapping pair (``ArmMapping``, ``PositionMapping``, …) as its
    zenoh callbacks would deliver it: the buttons, then the pose at ``p`` (m), then one
    ``process()`` of the mapping loop."""
    arm.on_buttons(MasterButtons(TEST_HEADER, clutch, True), "")
    arm.on_master_pose(CartesianPose(TEST_HEADER, "master", p), "")
    arm.process()


# --------------------------------------------------------------------------- chromium over DevTools

CHROMIUM = Path("/usr/bin/chromium")
WINDOW = (1600, 900)  # px: viewport of the screenshot
#: Flags for a closed network and a fresh profile (the profile dir is added per run).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",  # software WebGL (no GPU in CI)
    "--disable-quic",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-extensions",
    "--mute-audio",
    # a headless page may count as hidden: keep its animation frames and timers running
    "--disable-renderer-backgrounding",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
    "--hide-scrollbars",
    f"--window-size={WINDOW[0]},{WINDOW[1]}",
    "--remote-debugging-pipe",
)


# --------------------------------------------------------------------------- DevTools over a pipe


class DevTools:
    """Minimal Chrome DevTools Protocol client over ``--remote-debugging-pipe``.

    Chromium reads commands from its fd 3 and writes replies and events to its fd 4, each a JSON
    object followed by a NUL byte. :meth:`call` sends one command and returns its ``result``,
    skipping events; a protocol error raises RuntimeError.
    """

    def __init__(self, to_browser: int, from_browser: int) -> None:
        self._out = to_browser
        self._in = from_browser
        self._buf = b""
        self._id = 0

    def call(
        self, method: str, params: dict[str, Any] | None = None, session: str = "", timeout: float = 120.0
    ) -> dict[str, Any]:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        data = json.dumps(msg).encode() + b"\0"
        while data:
            data = data[os.write(self._out, data) :]
        deadline = time.monotonic() + timeout
        while True:
            reply = self._next(deadline, method)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                result: dict[str, Any] = reply.get("result", {})
                return result

    def _next(self, deadline: float, method: str) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"chromium did not answer {method}")
            ready, _, _ = select.select([self._in], [], [], left)
            if ready:
                chunk = os.read(self._in, 1 << 20)
                if not chunk:
                    raise ConnectionError(f"chromium closed the DevTools pipe during {method}")
                self._buf += chunk
        raw, self._buf = self._buf.split(b"\0", 1)
        out: dict[str, Any] = json.loads(raw)
        return out


def _high_fd(fd: int) -> int:
    """``fd`` moved to a number >= 10 (the original is closed)."""
    high = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return high


@contextlib.contextmanager
def chromium(
    url: str, workdir: Path, window: tuple[int, int] = WINDOW, mobile: bool = False, nice: int = 10
) -> Iterator[tuple[DevTools, str]]:
    """Headless chromium showing ``url``: (DevTools client, page session id); killed on exit.

    ``window``/``mobile``: the emulated viewport (a phone: e.g. (390, 844), mobile, touch on);
    ``nice``: chromium's niceness (10: it yields to the services; 0 where the page is a master)."""
    profile = workdir / "chromium-profile"
    profile.mkdir(parents=True, exist_ok=True)
    cmd_r, cmd_w = os.pipe()  # we write commands → chromium's fd 3
    out_r, out_w = os.pipe()  # chromium's fd 4 → we read replies
    cmd_r, out_w = _high_fd(cmd_r), _high_fd(out_w)  # not 3 or 4 themselves: no clash when moved
    # bash moves the pipe ends to fds 3 and 4 (multi-digit fds: dash cannot), then execs chromium
    argv = [
        "bash",
        "-c",
        f'exec 3<&{cmd_r} 4>&{out_w} {cmd_r}<&- {out_w}>&-; exec nice -n {nice} "$@"',
        "chromium",
        str(CHROMIUM),
        *CHROMIUM_FLAGS,
        f"--user-data-dir={profile}",
        "about:blank",
    ]
    log = (workdir / "chromium.log").open("wb")
    proc = subprocess.Popen(
        argv, pass_fds=(cmd_r, out_w), stdout=log, stderr=subprocess.STDOUT, start_new_session=True
    )
    os.close(cmd_r)
    os.close(out_w)
    try:
        cdp = DevTools(cmd_w, out_r)
        target = cdp.call("Target.createTarget", {"url": url})["targetId"]
        session = cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            {"width": window[0], "height": window[1], "deviceScaleFactor": 1, "mobile": mobile},
            session,
        )
        if mobile:
            cdp.call("Emulation.setTouchEmulationEnabled", {"enabled": True, "maxTouchPoints": 5}, session)
        cdp.call("Emulation.setFocusEmulationEnabled", {"enabled": True}, session)
        cdp.call("Page.bringToFront", {}, session)
        yield cdp, session
    finally:
        _stop_group(proc)
        os.close(cmd_w)
        os.close(out_r)
        log.close()


def _stop_group(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM chromium's process group (its own session: browser, zygote, renderers, GPU
    process), wait until every member is gone; SIGKILL after 10 s."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if proc.poll() is None:
                time.sleep(0.1)
                continue
            try:
                os.killpg(proc.pid, 0)  # any member left?
            except ProcessLookupError:
                return
            time.sleep(0.1)
    proc.wait(timeout=10)


def screenshot(cdp: DevTools, session: str) -> bytes:
    """PNG of the page's viewport."""
    return base64.b64decode(cdp.call("Page.captureScreenshot", {"format": "png"}, session)["data"])


_operator_seq: dict[str, Any] = {}


def operator_command(node: Any, key: str, arm: str, name: str, *args: str, confirm: bool = True) -> Any:
    """Send one operator command as ``node``'s service id (open it as ``console``: only the
    operator console may command, shared/authority.py) and return the reply; ``confirm``: answer a
    ``confirm required`` reply with its token, as an operator who says yes."""
    from telesurg.shared.messages import Command, CommandReply, Sequencer

    seq = _operator_seq.setdefault(node.service, Sequencer(node.service))
    r = node.request(key, Command(seq.next(), arm, name, args), CommandReply, 5.0)
    if confirm and r.confirm:
        r = node.request(
            key, Command(seq.next(), arm, name, (*args, f"confirm={r.confirm}")), CommandReply, 5.0
        )
    return r
