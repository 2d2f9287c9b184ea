"""The router's diagnostics from zenoh's own log: ACL denials only, TLS handshake failures.

zenoh (Rust) logs through ``tracing`` to the process's stdout; its access-control interceptor
logs every decision at ``trace`` level, allowed and denied alike (147 MB in 95 s of
"authorized" lines on a busy site), and a refused TLS handshake is a ``warn`` of the TLS link
module ending in a misleading "Hint: increase the system open file limit". :class:`ZenohLogRelay`
points the process's stdout (fd 1) into a pipe and reads it on a thread:

* ``unauthorized`` / ``authorization error`` lines → one ``WARNING`` "ACL denied: ..." each, at most
  :data:`DENIALS_PER_S` a second (the rest counted and reported once a second, so a flood of
  denied messages cannot flood the log);
* ``authorized`` lines → dropped, unless the mode is ``all`` (then ``DEBUG``);
* TLS accept errors → ``WARNING`` "TLS handshake failed: <peer and reason>";
* anything else zenoh logs → ``INFO`` as is.

Example::

    relay = ZenohLogRelay(acl="denied")
    zenoh.init_log_from_env_or(relay.filter)   # after relay.start()
"""

from __future__ import annotations

import logging
import os
import re
import sys
import threading
import time

log = logging.getLogger("telesurg.router.zenoh")

ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
TLS_TARGET = "zenoh_link_tls"
ACL_MODES = ("off", "denied", "all")
DENIALS_PER_S = 20  # ACL denial lines logged per second at most; the rest are counted
_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_HINT = ". Hint: increase the system open file limit."


class ZenohLogRelay:
    """Reads zenoh's stdout log and re-logs what matters through Python logging."""

    def __init__(self, acl: str = "off", extra: str = "") -> None:
        if acl not in ACL_MODES:
            raise ValueError(f"acl log mode {acl!r}; valid: {', '.join(ACL_MODES)}")
        self.acl = acl
        parts = [f"{TLS_TARGET}=warn"]
        if acl != "off":
            parts.append(f"{ACL_TARGET}=trace")
        if extra:
            parts.append(extra)
        self.filter = ",".join(["warn", *parts])  # the tracing filter for zenoh.init_log_from_env_or
        self.denied = 0  # ACL denials seen
        self.suppressed = 0  # denials not logged (over DENIALS_PER_S)
        self.tls_failures = 0  # refused TLS handshakes seen
        self._window = (0, 0)  # (second, lines logged in it)
        self._caching = ""  # key whose permissions zenoh is computing in advance (not a message)
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Redirect fd 1 into a pipe read by a daemon thread (Python's own stdout goes to the
        original fd 1 through a duplicate)."""
        r, w = os.pipe()
        keep = os.dup(1)
        sys.stdout.flush()
        os.dup2(w, 1)
        os.close(w)
        sys.stdout = os.fdopen(keep, "w", buffering=1)
        self._thread = threading.Thread(target=self._read, args=(r,), name="zenoh-log", daemon=True)
        self._thread.start()

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "r", errors="replace") as f:
            for line in f:
                self.handle(_ANSI.sub("", line).rstrip())

    def handle(self, line: str) -> None:
        """Classify one zenoh log line (public for the tests)."""
        if not line:
            return
        if "caching permissions for `" in line:
            # zenoh computes every message type's permission for a key when it is first used:
            # the decision lines that follow are about no message, until another line comes
            self._caching = line.split("caching permissions for `", 1)[1].split("`", 1)[0]
            return
        if self._caching:
            if ("authorized to" in line or "authorization error" in line) and line.endswith(
                f" on {self._caching}"
            ):
                return
            self._caching = ""
        if "unauthorized to" in line or "authorization error" in line:
            self.denied += 1
            if self.acl == "off":
                return
            sec = int(time.monotonic())
            if self._window[0] != sec:
                if self.suppressed:
                    log.warning("ACL denied: %d more denials in the last second not logged", self.suppressed)
                    self.suppressed = 0
                self._window = (sec, 0)
            if self._window[1] >= DENIALS_PER_S:
                self.suppressed += 1
                return
            self._window = (sec, self._window[1] + 1)
            log.warning("ACL denied: %s", _message(line))
        elif "is authorized to" in line or "Using cached result" in line:
            if self.acl == "all":
                log.debug("ACL: %s", _message(line))
        elif TLS_TARGET in line and _HINT in line:
            self.tls_failures += 1
            log.warning("TLS handshake failed: %s", _message(line).replace(_HINT, ""))
        else:
            log.info("zenoh: %s", line)


def _message(line: str) -> str:
    """The text after zenoh's ``LEVEL target: `` prefix."""
    for marker in (": ", " "):
        _, sep, rest = line.partition(f"{ACL_TARGET}{marker}")
        if sep:
            return rest
    m = re.search(r"zenoh_link_tls[^ ]*: (.*)$", line)
    return m.group(1) if m else line
