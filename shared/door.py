"""The door of a local web page onto the bus (the web console, ``telesurg view``): who may in.

Free of I/O and of any web framework: the server asks :meth:`Door.admit` for every request with its
method, path, ``Host``, ``Origin`` and cookies, and serves it only when the answer is "ok".

* **Login.** The operator opens a one-time login URL, ``http://HOST:PORT/login?token=T``, printed by
  the process that started the page. :meth:`Door.login` swaps the token (compared with
  :func:`hmac.compare_digest`; used once) for a session id, which the server sets as a cookie
  (``HttpOnly; SameSite=Strict; Path=/``) before redirecting to the page without the token.
  Sessions expire after ``session_s``. Every other path needs the session cookie.
* **Host.** ``Host`` must be the page's own address: the configured host, ``127.0.0.1``,
  ``localhost`` or ``[::1]`` with the page's port, or a name in ``allowed_hosts`` (a console on
  the LAN). A foreign ``Host`` (``rebind.example``: DNS rebinding) is refused before anything else.
* **Origin.** A websocket and every request that is not ``GET``/``HEAD`` must carry the page's own
  ``Origin``; any request that carries another ``Origin`` is refused (another page in the same
  browser: cookies are not kept apart by port, so a page on another port of this host is
  "same-site" and its requests would carry the session cookie).

Every refusal is counted by kind (``host``, ``origin``, ``login``, ``session``); the server shows
the counts and publishes them as events.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

#: environment variable by which a launcher hands the page server it starts the login token it
#: printed (a process's environment is readable by its own user and root only, its command line
#: by every local user)
LOGIN_ENV = "TELESURG_WEB_LOGIN"
#: paths a page may open without a session: the login itself
OPEN_PATHS = frozenset({"/login"})
SAFE_METHODS = frozenset({"GET", "HEAD"})
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


@dataclass(frozen=True)
class Verdict:
    """What :meth:`Door.admit` says: ``status`` 0 = admitted, else the HTTP status to refuse with,
    ``kind`` the counter and ``reason`` one line for the client."""

    status: int = 0
    kind: str = ""
    reason: str = ""
    session: str = ""  # the session's id (its hash) when admitted with a session

    @property
    def ok(self) -> bool:
        return self.status == 0


@dataclass
class Session:
    """A logged-in browser: its id (the hash of its cookie) and when it expires (monotonic s)."""

    sid: str
    label: str  # short, for the page and the events ("s-1a2b")
    expires: float


@dataclass
class Door:
    """Login tokens, sessions and the Host / Origin rules of one page server (thread-safe)."""

    host: str  # the configured listen host
    port: int  # the bound port (set once bound when configured as 0)
    cookie: str = "telesurg_session"  # cookie name (the server adds the port: cookies ignore ports)
    session_s: float = 8 * 3600.0  # s: a session's lifetime from its login
    allowed_hosts: tuple[str, ...] = ()  # more Host names (no port) the page may be reached by
    clock: Callable[[], float] = time.monotonic
    refused: dict[str, int] = field(default_factory=dict)
    _tokens: dict[str, float] = field(default_factory=dict)  # login token → expiry (inf: until used)
    _sessions: dict[str, Session] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def cookie_name(self) -> str:
        return f"{self.cookie}_{self.port}"

    # -- login ---------------------------------------------------------------------------------
    def mint(self, ttl_s: float = float("inf")) -> str:
        """A new one-time login token (valid until used, or ``ttl_s`` s)."""
        token = secrets.token_urlsafe(32)
        with self._lock:
            self._tokens[token] = self.clock() + ttl_s
        return token

    def add_token(self, token: str) -> None:
        """Accept ``token`` (made by the launcher that started this process) once."""
        with self._lock:
            self._tokens[token] = float("inf")

    def login_url(self, token: str, host: str = "") -> str:
        return f"http://{host or self.host}:{self.port}/login?token={token}"

    def login(self, token: str) -> tuple[str, Session] | None:
        """Swap a login token for (cookie value, session); None (counted) if it is not valid."""
        now = self.clock()
        with self._lock:
            found = ""
            for t, exp in list(self._tokens.items()):
                if exp < now:
                    del self._tokens[t]
                elif hmac.compare_digest(t.encode(), token.encode()):
                    found = t
            if not found:
                self.refused["login"] = self.refused.get("login", 0) + 1
                return None
            del self._tokens[found]  # one use
            value = secrets.token_urlsafe(32)
            sid = _digest(value)
            s = Session(sid, f"s-{sid[:4]}", now + self.session_s)
            self._sessions[sid] = s
            return value, s

    def session(self, cookie_value: str) -> Session | None:
        """The live session of a cookie value, or None (unknown or expired: forgotten)."""
        if not cookie_value:
            return None
        sid = _digest(cookie_value)
        now = self.clock()
        with self._lock:
            s = self._sessions.get(sid)
            if s is not None and s.expires < now:
                del self._sessions[sid]
                return None
            return s

    def alive(self, sid: str) -> bool:
        with self._lock:
            s = self._sessions.get(sid)
            return s is not None and s.expires >= self.clock()

    def logout(self, sid: str) -> None:
        with self._lock:
            self._sessions.pop(sid, None)

    # -- Host and Origin -------------------------------------------------------------------------
    def host_ok(self, host: str) -> bool:
        names = {self.host, *LOOPBACK_NAMES, *self.allowed_hosts}
        return host.lower() in {f"{n}:{self.port}".lower() for n in names}

    def admit(
        self, method: str, path: str, headers: Mapping[str, str], cookies: Mapping[str, str], websocket: bool
    ) -> Verdict:
        """Whether to serve this request (see the module docstring); counts every refusal."""
        host = headers.get("Host", "")
        origin = headers.get("Origin")
        if not self.host_ok(host):
            v = Verdict(403, "host", f"refused: Host {host!r} is not this page's address")
        elif origin is not None and origin != f"http://{host}":
            v = Verdict(403, "origin", f"refused: Origin {origin!r} is not this page's origin")
        elif origin is None and (websocket or method not in SAFE_METHODS):
            v = Verdict(403, "origin", "refused: a websocket or a change needs this page's Origin")
        elif path in OPEN_PATHS:
            return Verdict()
        elif (s := self.session(cookies.get(self.cookie_name, ""))) is None:
            v = Verdict(401, "session", "refused: not logged in (open the login URL the console printed)")
        else:
            return Verdict(session=s.sid)
        self.count(v.kind)
        return v

    def count(self, kind: str) -> None:
        with self._lock:
            self.refused[kind] = self.refused.get(kind, 0) + 1

    def counts(self) -> dict[str, int]:
        with self._lock:
            return dict(self.refused)

    def cookie_header(self, value: str) -> str:
        """The ``Set-Cookie`` value of a session cookie."""
        return f"{self.cookie_name}={value}; HttpOnly; SameSite=Strict; Path=/; Max-Age={int(self.session_s)}"


def _digest(value: str) -> str:
    return hashlib.sha256(value.encode()).hexdigest()
