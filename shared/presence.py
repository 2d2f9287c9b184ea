"""Who is alive on the bus, judged by the session whose messages are authenticated.

Every :class:`~telesurg.shared.bus.Node` declares its liveliness token under its authenticated
session id, ``alive/<service>/<sid>`` (:meth:`~telesurg.shared.keys.Keys.alive_token`; ``sid``:
the random 64-bit id its messages are signed with, :mod:`telesurg.shared.auth`). zenoh merges the
tokens of one key: a second token on a key keeps the key alive after the first one's owner dies,
and no DELETE arrives while it exists. Keying each token by its session keeps a stranger's token
(any other key) from masking a genuine one; and a receiver that has authenticated messages of a
service knows *which* session is the genuine one:

* a service's **genuine session** is the ``sid`` of the newest message from it that passed
  authentication, decoding and its stream's sequence / session rules
  (:meth:`Presence.authenticated`);
* the service is **alive** while the token of its genuine session is present. The moment that
  token vanishes the service is dead, whatever other tokens for it exist — the watchdog's death is
  seen by the slave as fast as the router drops its session, with a stranger's ``alive/watchdog/…``
  token or not;
* until anything of a service is authenticated (or when its genuine session never declared a
  token this node saw), presence is by any token of it, as before;
* after the genuine session's token vanished, a token that appears *later* counts again (a
  restart: its messages make it the genuine session once they arrive); a token that existed
  before the death never does. Only the death itself acts on safety (the slave revokes its lease
  at once, the watchdog holds); being alive grants nothing — motion still needs fresh
  authenticated leases and streams;
* a session whose token vanished stays dead (:meth:`Presence.vanished`): a message of it still
  queued at a receiver (a polled lease) must not bring it back.

A stranger who copies the genuine token's exact key (it can see it: liveliness keys are visible
to every subscriber) masks it again — that is what the router's ACL refuses on a locked-down site
(only the service's own certificate may declare ``alive/<service>/*``, deploy/slave-site/acl.json5);
on an open site the slave then holds when the last genuine lease expires (docs/security.md).

I/O-free: :class:`~telesurg.shared.bus.Node` feeds it from its liveliness subscribers and its
authenticated subscriptions. Example::

    p = Presence()
    p.watch(lambda s: s == "watchdog", lambda s, alive: print(s, alive))
    p.run(p.token("watchdog", bytes(8), True))        # watchdog True
    p.run(p.authenticated("watchdog", bytes(8)))      # (no change)
    p.run(p.token("watchdog", b"x" * 8, True))        # (a stranger's token: no change)
    p.run(p.token("watchdog", bytes(8), False))       # watchdog False
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

#: vanished sessions remembered per service
GONE_MAX = 32

Call = tuple[Callable[[str, bool], None], str, bool]


@dataclass
class _Watcher:
    match: Callable[[str], bool]
    callback: Callable[[str, bool], None]
    reported: dict[str, bool] = field(default_factory=dict)


class Presence:
    """Tokens and genuine sessions per service; reports changes of :meth:`alive` to watchers.

    The methods that change something return the callbacks to run (``(callback, service,
    alive)``), which the caller runs with :meth:`run` outside any lock."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._tokens: dict[str, dict[bytes, int]] = {}  # service → {sid: order of appearance}
        self._genuine: dict[str, bytes] = {}
        self._gone: dict[str, deque[bytes]] = {}
        self._died: dict[str, int] = {}  # service → order at which its genuine token vanished
        self._order = 0
        self._watchers: list[_Watcher] = []

    # -- what is known -------------------------------------------------------------------------
    def alive(self, service: str) -> bool:
        """Is ``service`` alive (see the module doc)."""
        with self._lock:
            return self._alive(service)

    def _alive(self, service: str) -> bool:
        toks = self._tokens.get(service, {})
        g = self._genuine.get(service)
        if g is None or (g not in toks and g not in self._gone.get(service, ())):
            return bool(toks)
        if g in toks:
            return True
        died = self._died.get(service, 0)
        return any(order > died for order in toks.values())  # a token that came after the death

    def vanished(self, service: str, sid: bytes) -> bool:
        """Did the token of ``service``'s session ``sid`` vanish (that session is dead)?"""
        with self._lock:
            return sid in self._gone.get(service, ())

    def genuine(self, service: str) -> bytes:
        """The genuine session of ``service`` (b"" if nothing of it was authenticated)."""
        return self._genuine.get(service, b"")

    # -- inputs --------------------------------------------------------------------------------
    def token(self, service: str, sid: bytes, present: bool) -> list[Call]:
        """A liveliness token ``alive/<service>/<sid>`` appeared (``present``) or vanished."""
        with self._lock:
            self._order += 1
            toks = self._tokens.setdefault(service, {})
            if present:
                toks.setdefault(sid, self._order)
                gone = self._gone.get(service)
                if gone is not None and sid in gone:
                    gone.remove(sid)  # (a token seen again: zenoh redelivered it)
            else:
                toks.pop(sid, None)
                gone = self._gone.setdefault(service, deque(maxlen=GONE_MAX))
                if sid not in gone:
                    gone.append(sid)
                if sid == self._genuine.get(service):
                    self._died[service] = self._order
            return self._changes(service)

    def authenticated(self, service: str, sid: bytes) -> list[Call]:
        """A message of ``service`` signed in session ``sid`` was accepted. Cheap when nothing
        changes (the 1 kHz path): one dict lookup."""
        if self._genuine.get(service) == sid:
            return []
        with self._lock:
            self._genuine[service] = sid
            return self._changes(service)

    def watch(self, match: Callable[[str], bool], callback: Callable[[str, bool], None]) -> list[Call]:
        """``callback(service, alive)`` on every change of :meth:`alive` of a service ``match``
        accepts (and now for those alive already)."""
        w = _Watcher(match, callback)
        with self._lock:
            self._watchers.append(w)
            return [c for s in list(self._tokens) if match(s) for c in self._report(w, s)]

    @staticmethod
    def run(calls: list[Call]) -> None:
        """Run the callbacks an input returned."""
        for cb, service, alive in calls:
            cb(service, alive)

    # -- internals (under the lock) ------------------------------------------------------------
    def _changes(self, service: str) -> list[Call]:
        return [c for w in self._watchers if w.match(service) for c in self._report(w, service)]

    def _report(self, w: _Watcher, service: str) -> list[Call]:
        alive = self._alive(service)
        was = w.reported.get(service)
        if was == alive or (was is None and not alive):
            return []
        w.reported[service] = alive
        return [(w.callback, service, alive)]
