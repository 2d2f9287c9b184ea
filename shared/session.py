"""Run a command in a session (so a scheduler autogroup) of its own, behind a small parent.

Linux shares the CPU between autogroups (one per session) before it shares it between the
threads of a group. A launcher started from a shell that also runs busy jobs (``make -j2 &``)
would share their autogroup, and with it their CPU share: on this project's VM, with the demo
launcher in its busy loops' session a watchdog thread was left ~120 ms runnable without a CPU and
the watchdog held the slave on a stale control stream in about half the demos; in a session of
its own, in none (docs/performance.md, "The launcher in a session of its own by default").
``setsid`` itself would cut the process off from the terminal's Ctrl-C and from a kill of its
process group, so :func:`run_in_own_session` keeps the caller as a parent that forwards those
signals to a child in a new session and passes its exit code back.

Example::

    code = run_in_own_session(["demo", "--headless", "--seconds", "20"])
    if code is not None:      # the command ran in the child
        sys.exit(code)
    ...                       # already on its own (or autogroups off): run it here
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

#: ``0`` runs the command in the caller's session (no parent/child pair).
OWN_SESSION_ENV = "TELESURG_OWN_SESSION"
#: What the parent passes on to the child (Ctrl-C, a stop, a hang-up, the stack-dump request).
FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR1)
AUTOGROUP_SYSCTL = Path("/proc/sys/kernel/sched_autogroup_enabled")


def autogroups_on() -> bool:
    """True where the kernel groups the CPU by session (``kernel.sched_autogroup_enabled=1``)."""
    try:
        return AUTOGROUP_SYSCTL.read_text().strip() == "1"
    except OSError:
        return False


def needs_own_session() -> bool:
    """True when this process shares its session's autogroup with others and may leave it: not
    already a session leader, autogroups on, and ``$TELESURG_OWN_SESSION`` not ``0``."""
    if os.environ.get(OWN_SESSION_ENV, "").strip() == "0":
        return False
    return os.getsid(0) != os.getpid() and autogroups_on()


def die_with_parent(sig: int) -> None:
    """``preexec_fn``: have the kernel send this process ``sig`` when its parent ends, however it
    ends (``PR_SET_PDEATHSIG``; a parent killed with SIGKILL forwards nothing). Linux only;
    harmless elsewhere."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, sig)  # PR_SET_PDEATHSIG


def run_in_own_session(argv: Sequence[str]) -> int | None:
    """Run ``telesurg ARGV`` in a child in a session of its own and return its exit code (128 +
    the signal's number when a signal ended it), or None when :func:`needs_own_session` says no
    (the caller then runs the command itself)."""
    if not needs_own_session():
        return None
    cmd = [sys.executable, "-m", "telesurg.services.cli", *argv]
    child: subprocess.Popen[bytes] | None = None
    pending: list[int] = []  # a signal taken before the child existed

    def forward(signum: int, _frame: object) -> None:
        if child is None:
            pending.append(signum)
            return
        with contextlib.suppress(ProcessLookupError):
            child.send_signal(signum)

    for sig in FORWARDED:  # (a child's exec puts them back to their defaults)
        signal.signal(sig, forward)
    # SIGTERM when the parent dies: the child still stops the services it started, in order
    stop_with_parent = functools.partial(die_with_parent, signal.SIGTERM)
    child = subprocess.Popen(cmd, start_new_session=True, preexec_fn=stop_with_parent)
    for signum in pending:
        child.send_signal(signum)
    rc = child.wait()
    return rc if rc >= 0 else 128 - rc
