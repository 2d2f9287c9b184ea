"""Who controls the master: one page at a time, handed over explicitly (free of I/O).

A *page* is one browser tab of a logged-in session (the page keeps its id across reloads, so a
reload keeps control). The first page to connect while nobody is in control takes it; every
other page is a *viewer* — it sees the state and may e-stop, nothing else. Control moves only by
an explicit act:

* the controller **releases** it (then a viewer may **take** it);
* a viewer **asks** (``take`` while a controller is connected) and the controller **grants**
  (or refuses) it;
* a viewer **takes** it when the controlling page has been gone (no socket) for ``grace_s`` or
  its session expired — the operator's page that closed or crashed cannot block the master forever,
  and a short pause of the operator's page (a reload, a network blip) never hands it on.

Each change returns one line of text for the event the server publishes; the server tells every
page its role at once.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class Control:
    """The controlling page of one web console (thread-safe)."""

    grace_s: float = 10.0  # s: a controller page gone this long may be replaced by a viewer's take
    clock: Callable[[], float] = time.monotonic
    alive: Callable[[str], bool] = lambda page: True  # is the page's session still valid?
    holder: str | None = None  # the controlling page
    request: str | None = None  # the viewer asking for control
    _sockets: dict[str, int] = field(default_factory=dict)  # page → open sockets
    _gone_at: float | None = None  # when the holder's last socket closed
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def is_controller(self, page: str) -> bool:
        with self._lock:
            return self.holder == page

    def join(self, page: str) -> str:
        """A socket of ``page`` opened; the event text if it took control (nobody had it)."""
        with self._lock:
            self._sockets[page] = self._sockets.get(page, 0) + 1
            if self.holder == page:
                self._gone_at = None
                return ""
            if self.holder is None:
                self._set(page)
                return f"control to page {page} (nobody had it)"
            return ""

    def leave(self, page: str) -> str:
        """A socket of ``page`` closed; the event text if a pending request of it was dropped."""
        with self._lock:
            n = self._sockets.get(page, 0) - 1
            if n > 0:
                self._sockets[page] = n
                return ""
            self._sockets.pop(page, None)
            if self.holder == page:
                self._gone_at = self.clock()
            if self.request == page:
                self.request = None
                return f"page {page} left: its request for control dropped"
            return ""

    def release(self, page: str) -> str:
        """The controller gives control up (nobody has it until a viewer takes it)."""
        with self._lock:
            if self.holder != page:
                return ""
            self.holder, self.request, self._gone_at = None, None, None
            return f"page {page} released control"

    def take(self, page: str) -> tuple[bool, str]:
        """A viewer wants control: (granted now, event text). Granted at once when nobody has it,
        or the controller's page is gone (``grace_s``) or logged out; else it is asked."""
        with self._lock:
            if self.holder == page:
                return True, ""
            holder = self.holder
            if holder is None:
                self._set(page)
                return True, f"page {page} took control (nobody had it)"
            gone = self._gone_at is not None and self.clock() - self._gone_at >= self.grace_s
            if gone or not self.alive(holder):
                self._set(page)
                why = "its page was gone" if gone else "its session ended"
                return True, f"page {page} took control from page {holder} ({why})"
            self.request = page
            return False, f"page {page} asks page {holder} for control"

    def answer(self, page: str, yes: bool) -> str:
        """The controller grants (``yes``) or refuses the pending request."""
        with self._lock:
            if self.holder != page or self.request is None:
                return ""
            to, self.request = self.request, None
            if not yes:
                return f"page {page} refused control to page {to}"
            self._set(to)
            return f"page {page} handed control to page {to}"

    def snapshot(self) -> tuple[str | None, str | None]:
        with self._lock:
            return self.holder, self.request

    def _set(self, page: str) -> None:
        self.holder, self.request = page, None
        self._gone_at = None if self._sockets.get(page) else self.clock()
