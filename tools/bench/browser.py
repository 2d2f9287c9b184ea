"""Headless Debian Chromium driven over the DevTools protocol on a pipe: the benches' and the
tests' browser (the rerun web viewer, the web console).

``--remote-debugging-pipe``: Chromium reads NUL-terminated JSON commands on its fd 3 and writes
replies and events on its fd 4 — no websocket, no extra package. :func:`chromium` starts it on a
URL in its own process group (ended on exit), :class:`DevTools` sends commands,
:func:`screenshot` takes the viewport as PNG.

Example::

    with chromium("http://127.0.0.1:9090/", Path("/tmp/x")) as (cdp, session):
        png = screenshot(cdp, session)
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
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

# --------------------------------------------------------------------------- chromium over DevTools

CHROMIUM = Path("/usr/bin/chromium")
WINDOW = (1600, 900)  # px: viewport of the screenshot
#: Flags for a closed network and a fresh profile (the profile dir is added per run).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
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
#: Software WebGL (there is no GPU in CI) by rasteriser: ``swiftshader`` (Chromium's own, what it
#: falls back to without a usable GPU) or ``llvmpipe`` (Mesa's, through ANGLE on EGL; needs
#: libegl1 + libgl1-mesa-dri; 1.7–2.4× the frames/s of SwiftShader on pages of the viewer,
#: docs/performance.md).
GL_FLAGS = {
    "swiftshader": ("--disable-gpu", "--enable-unsafe-swiftshader"),
    "llvmpipe": ("--use-angle=gl-egl", "--ignore-gpu-blocklist"),
}


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
    url: str,
    workdir: Path,
    window: tuple[int, int] = WINDOW,
    mobile: bool = False,
    nice: int = 10,
    autogroup_nice: int | None = None,
    flags: Sequence[str] = (),
    gl: str = "swiftshader",
    browser: Path = CHROMIUM,
) -> Iterator[tuple[DevTools, str]]:
    """Headless chromium showing ``url``: (DevTools client, page session id); killed on exit.

    ``window``/``mobile``: the emulated viewport (a phone: e.g. (390, 844), mobile, touch on);
    ``nice``: chromium's niceness (10: it yields to the services; 0 where the page is a master);
    ``autogroup_nice``: the nice value of the scheduler autogroup chromium runs in (its own
    session: every chromium process — browser, renderer, GPU process — is in it), None to leave
    it at 0. With autogroups (Linux's default) a process's own nice counts only inside its group;
    19 puts the whole browser below every other session's work, the control path's included
    (see :func:`autogroups`); ``flags``: extra chromium flags; ``gl``: the software WebGL
    rasteriser, a key of :data:`GL_FLAGS`; ``browser``: the Chromium executable (another build, e.g.
    one unpacked from an older package, to compare builds)."""
    profile = workdir / "chromium-profile"
    profile.mkdir(parents=True, exist_ok=True)
    cmd_r, cmd_w = os.pipe()  # we write commands → chromium's fd 3
    out_r, out_w = os.pipe()  # chromium's fd 4 → we read replies
    cmd_r, out_w = _high_fd(cmd_r), _high_fd(out_w)  # not 3 or 4 themselves: no clash when moved
    # bash moves the pipe ends to fds 3 and 4 (multi-digit fds: dash cannot), then execs chromium
    # a session is an autogroup: its nice value is set from inside, before chromium starts
    group = (
        f"echo {int(autogroup_nice)} > /proc/self/autogroup 2>/dev/null; "
        if autogroup_nice is not None
        else ""
    )
    argv = [
        "bash",
        "-c",
        f'{group}exec 3<&{cmd_r} 4>&{out_w} {cmd_r}<&- {out_w}>&-; exec nice -n {nice} "$@"',
        "chromium",
        str(browser),
        *_flags(flags, gl),
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


def _flags(extra: Sequence[str], gl: str = "swiftshader") -> list[str]:
    """:data:`CHROMIUM_FLAGS` and the ``gl`` rasteriser's :data:`GL_FLAGS` with ``extra`` added (an
    extra ``--name=value`` replaces the default flag of that name)."""
    if gl not in GL_FLAGS:
        raise ValueError(f"gl={gl!r}: one of {', '.join(GL_FLAGS)}")
    names = {f.split("=", 1)[0] for f in extra}
    base = (*CHROMIUM_FLAGS, *GL_FLAGS[gl])
    return [*(f for f in base if f.split("=", 1)[0] not in names), *extra]


def lowest_priority() -> None:
    """``preexec_fn`` of a process started in a session of its own (``start_new_session``): nice 19
    and its session's scheduler autogroup at nice 19, so neither it nor anything it starts (a
    browser's renderer and GPU processes) takes CPU from another session's work — the control
    path's processes run in autogroups of nice −10 (the launcher) or 0."""
    with contextlib.suppress(OSError):
        os.nice(19)
    with contextlib.suppress(OSError):
        Path("/proc/self/autogroup").write_text("19\n")


def autogroups(marker: str) -> dict[int, str]:
    """pid → ``/proc/<pid>/autogroup`` (e.g. ``/autogroup-123 nice 19``) of every live process whose
    command line holds ``marker`` (one chromium's profile directory: all its processes)."""
    out: dict[int, str] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if marker.encode() not in (d / "cmdline").read_bytes():
                continue
            out[int(d.name)] = (d / "autogroup").read_text().strip()
        except OSError:
            continue
    return out


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
    proc.wait(timeout=60)  # a starved host (a browser at autogroup nice 19) reaps slowly


def screenshot(cdp: DevTools, session: str) -> bytes:
    """PNG of the page's viewport."""
    return base64.b64decode(cdp.call("Page.captureScreenshot", {"format": "png"}, session)["data"])
