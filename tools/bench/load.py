"""Background load for the benches (``telesurg bench latency | soak --load SPEC``).

A spec names what else runs on the host while the control path is measured:

* ``cpu:N`` — N busy-loop processes at normal priority (nice 0, SCHED_OTHER): other programs
  on the same cores, e.g. a package install or a compiler, each in a session (so a scheduler
  autogroup) of its own as a program started elsewhere on the host is — not in the bench's, whose
  CPU share they would otherwise split (the bench, like the launcher, runs in a session of its
  own: telesurg.shared.session);
* ``idle:N`` — N busy-loop processes under ``SCHED_IDLE``, the class the launcher gives the
  camera and the mirror: best-effort work that gets only the CPU the control path leaves. What it
  still costs the control path is what the host's shared cores cost (caches, memory bandwidth,
  a hypervisor's sibling threads), not the scheduler's choice;
* ``record`` — the recorder (``telesurg record``) on the site's bus: every message of the site
  decoded and written to an MCAP file;
* ``stalled`` — a subscriber that stops reading: a plain zenoh client on the site's ``**`` whose
  handler is a FIFO of one sample it never takes, so its zenoh stops reading its socket — a hung
  viewer, recorder or console, or a hostile process (the router must not wait for it: services/router
  ``congestion_rules``);
* ``viewer`` — the rerun mirror serving the web viewer, and Debian's headless Chromium showing it
  (software WebGL), as a researcher watching the session on the console host; both at the lowest
  priority, each in a scheduler autogroup of nice 19 (as the launcher runs the mirror).

Each :class:`Load` is started after the pipeline it loads (it needs the router's endpoint) and
stopped with it; every process it starts is its own and is ended by PID.

Example::

    with Load.parse("cpu:2").running(endpoint, tmp):
        ...  # measure
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from telesurg.shared.session import die_with_parent

#: The kinds a ``--load`` spec can name.
KINDS = ("cpu", "idle", "record", "stalled", "viewer")
CHROMIUM = ("chromium", "chromium-browser", "google-chrome")


@dataclass(frozen=True)
class Load:
    """One kind of background load (see the module)."""

    kind: str
    n: int = 1  # cpu / idle: how many busy processes

    @classmethod
    def parse(cls, spec: str) -> Load:
        """``cpu:2`` / ``idle:1`` / ``record`` / ``stalled`` / ``viewer``; ValueError naming the valid
        forms."""
        kind, _, arg = spec.partition(":")
        if kind not in KINDS:
            raise ValueError(f"--load {spec!r}: unknown kind; valid: cpu:N, idle:N, record, stalled, viewer")
        if kind in ("cpu", "idle"):
            if not arg.isdigit() or not 1 <= int(arg) <= 16:
                raise ValueError(f"--load {spec!r}: {kind}:N needs N in 1..16")
            return cls(kind, int(arg))
        if arg:
            raise ValueError(f"--load {spec!r}: {kind} takes no argument")
        return cls(kind)

    @property
    def name(self) -> str:
        """The spec as given (``cpu:2``)."""
        return f"{self.kind}:{self.n}" if self.kind in ("cpu", "idle") else self.kind

    def available(self) -> str:
        """ "" if this load can run here, else why not."""
        if self.kind == "viewer" and not any(shutil.which(c) for c in CHROMIUM):
            return "no Chromium on this host (Debian: apt-get install chromium)"
        return ""

    @contextlib.contextmanager
    def running(self, endpoint: str, tmp: Path) -> Iterator[list[int]]:
        """Start the load against the router at ``endpoint``; yields the PIDs; stops them on exit."""
        procs: list[subprocess.Popen[bytes]] = []
        try:
            if self.kind == "cpu":
                for _ in range(self.n):
                    procs.append(_spawn([sys.executable, "-c", "while True: pass"], session=True))
            elif self.kind == "idle":
                for _ in range(self.n):
                    procs.append(_spawn([sys.executable, "-c", _IDLE_HOG], session=True))
            elif self.kind == "record":
                out = tmp / f"load-record-{time.monotonic_ns()}.mcap"
                argv = [sys.executable, "-m", "telesurg.services.record", "--out", str(out)]
                procs.append(_spawn([*argv, "--connect", endpoint]))
            elif self.kind == "stalled":
                procs.append(_spawn([sys.executable, "-c", _STALLED, endpoint]))
            elif self.kind == "viewer":
                procs += _viewer(endpoint, tmp)
            yield [p.pid for p in procs]
        finally:
            hard = self.kind in ("cpu", "idle", "stalled")  # nothing of theirs to save
            for p in procs:
                if p.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        p.send_signal(signal.SIGKILL if hard else signal.SIGINT)
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(30)
                if self.kind == "viewer":  # its own process group: a browser's children too
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(p.pid, signal.SIGKILL)


#: A busy loop under SCHED_IDLE (nice 19 where that is refused), set before it starts spinning.
_IDLE_HOG = """
import os
try:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
except (AttributeError, OSError):
    os.nice(19)
while True:
    pass
"""


#: A zenoh client on everything that never reads what it receives (its FIFO of one stays full).
_STALLED = """
import sys, time, zenoh
c = zenoh.Config()
c.insert_json5("mode", '"client"')
c.insert_json5("connect/endpoints", '["' + sys.argv[1] + '"]')
s = zenoh.open(c)
sub = s.declare_subscriber("**", zenoh.handlers.FifoChannel(1))
while True:
    time.sleep(3600)
"""


def _die_with_parent() -> None:
    """preexec_fn: SIGKILL this process when the bench that started it ends, however it ends (a
    bench killed by SIGTERM runs none of its clean-up, and a busy loop left behind would load
    every later run; nothing of a load's needs saving). Linux only; harmless elsewhere."""
    die_with_parent(signal.SIGKILL)


def _spawn(argv: list[str], lowest: bool = False, session: bool = False) -> subprocess.Popen[bytes]:
    """``argv`` with its output discarded, ended with the bench (:func:`_die_with_parent`);
    ``session``: in a session of its own; ``lowest``: that, at the lowest priority
    (:func:`telesurg.tools.bench.browser.lowest_priority`)."""
    if not lowest:
        return subprocess.Popen(
            argv,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=session,
            preexec_fn=_die_with_parent,
        )
    from telesurg.tools.bench.browser import lowest_priority

    def pre() -> None:
        _die_with_parent()
        lowest_priority()

    return subprocess.Popen(
        argv,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=pre,
    )


def _viewer(endpoint: str, tmp: Path) -> list[subprocess.Popen[bytes]]:
    """The mirror serving the web viewer + headless Chromium on it (software WebGL)."""
    from telesurg.services.launcher import free_port
    from telesurg.shared.viewer import viewer_url

    web, grpc = free_port(), free_port()
    argv = [sys.executable, "-m", "telesurg.services.mirror", "--connect", endpoint, "--serve"]
    argv += ["--set", f"web_port={web}", "--set", f"grpc_port={grpc}"]
    mirror = _spawn(argv, lowest=True)
    time.sleep(3.0)  # the viewer's files are served once the mirror is up
    browser = next(c for c in CHROMIUM if shutil.which(c))
    url = viewer_url(f"rerun+http://127.0.0.1:{grpc}/proxy", web)
    profile = tmp / f"chromium-{os.getpid()}-{time.monotonic_ns()}"
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--enable-unsafe-swiftshader",  # software WebGL, as on a console without a GPU
        "--no-first-run",
        "--disable-background-networking",
        # a headless page may count as hidden: keep drawing as a visible viewer does
        "--disable-renderer-backgrounding",
        "--disable-background-timer-throttling",
        "--disable-backgrounding-occluded-windows",
        "--window-size=1600,900",
        f"--user-data-dir={profile}",
        "--remote-debugging-port=0",  # keeps the headless browser (and the page) alive
    ]
    chrome = _spawn([browser, *flags, url], lowest=True)
    return [chrome, mirror]
