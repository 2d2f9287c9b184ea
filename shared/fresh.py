"""Freshness of authenticated messages: a genuine message is taken once, within a short window.

Authentication (:mod:`telesurg.shared.auth`) says *who* signed a message; these rules say that it
is not an old one sent again (a stranger without the keyring can still capture and resend signed
messages). Every :class:`~telesurg.shared.bus.Node` holds one :class:`Freshness` and applies it
after authentication and decoding, before anything else looks at a message:

* **Age** (puts, queries, replies): the header stamp, moved onto the receiver's clock by the
  signer's clock offset (:meth:`Freshness.offset_ns`, the hook for an offset a site estimates;
  0 today), may be at most ``max_age_ms`` old and at most ``tolerance_ms`` in the future, and not
  older than the receiver's own start minus ``tolerance_ms`` — so nothing captured before a
  receiver (re)started gets in, although the receiver forgot what it had seen. A put is aged when
  its session starts to be followed; the next numbers of that session are not (late, not replayed).
* **Per sender** (puts; a :class:`SenderWindow` per key *and* signer): within one session id the
  sequence number must move forward; a new session id of the signer is taken only with a stamp
  newer than that signer's last accepted one on the key. A message of one identity between
  another's does not reset anything.
* **Single use** (queries): the id ``(signer, sid, seq, stamp)`` of every query taken is kept
  for the age window; the same query again is refused.
* **Replies are bound** to their query: the replier signs with the query's attachment as
  ``bind`` (:meth:`~telesurg.shared.auth.Signer.attach`), the querier verifies with its own, so a
  signed reply to another query does not verify. A ``latest`` value (a reply to the
  subscription's own query) is bound instead of aged: it may be old by design.

Each check returns ``""`` (fresh) or the reason; the bus counts the refusal
(``StreamStats.replayed``, within ``rejected``) and reports it as a ``replayed`` event naming the
signer. Example::

    fresh = Freshness(max_age_ms=5000, tolerance_ms=500)
    win = SenderWindow()
    if not (why := fresh.put_problem("watchdog", win, sid, seq, stamp_ns, wall_ns())):
        fresh.took(win, sid, seq, stamp_ns)
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from telesurg.shared.clock import wall_ns
from telesurg.shared.errors import ConfigError

#: default bound of a message's age, ms (the receiver's wall clock minus the header stamp)
MAX_AGE_MS = 5000
#: default tolerance for the clock offset between two hosts, ms (on one host: scheduling only)
TOLERANCE_MS = 500
#: most query ids kept (a flood of signed queries is refused beyond it, never forgotten early)
MAX_QUERY_IDS = 100_000


@dataclass(slots=True)
class SenderWindow:
    """What one receiver has taken from one signer on one key."""

    sid: bytes = b""  # session id of the last message taken ("" = none yet)
    top: int = -1  # its sequence number
    stamp_ns: int = 0  # newest header stamp taken from this signer on the key (its clock)


@dataclass
class Freshness:
    """The freshness rules of one receiver (a Node); see the module. Thread-safe for queries;
    :meth:`put_problem` / :meth:`took` run under the caller's lock."""

    max_age_ms: float = MAX_AGE_MS
    tolerance_ms: float = TOLERANCE_MS
    clock: Callable[[], int] = wall_ns
    start_ns: int = 0  # when the receiver started, its wall clock (0 = now)
    # signer -> how far its clock runs ahead of ours, ns (the hook for a site's estimate)
    offsets: dict[str, int] = field(default_factory=dict)
    _used: dict[tuple[str, bytes, int, int], int] = field(default_factory=dict)
    _order: deque[tuple[int, tuple[str, bytes, int, int]]] = field(default_factory=deque)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __post_init__(self) -> None:
        if not 100 <= self.max_age_ms <= 600_000:
            raise ConfigError(f"freshness max_age_ms={self.max_age_ms:g} outside [100, 600000]")
        if not 0 <= self.tolerance_ms <= 60_000:
            raise ConfigError(f"freshness tolerance_ms={self.tolerance_ms:g} outside [0, 60000]")
        self._max_ns = round(self.max_age_ms * 1e6)
        self._tol_ns = round(self.tolerance_ms * 1e6)
        self.start_ns = self.start_ns or self.clock()

    def offset_ns(self, signer: str) -> int:
        """How far ``signer``'s clock runs ahead of this receiver's, ns (0 unless set in
        :attr:`offsets`: the one place a measured offset between two hosts goes)."""
        return self.offsets.get(signer, 0)

    def local_ns(self, signer: str, stamp_ns: int) -> int:
        """``signer``'s header stamp on this receiver's clock."""
        return stamp_ns - self.offsets.get(signer, 0) if self.offsets else stamp_ns

    def age_problem(self, signer: str, stamp_ns: int, now_ns: int) -> str:
        """Why a message stamped ``stamp_ns`` by ``signer`` is too old or too new now ("" = not)."""
        t = stamp_ns - self.offsets.get(signer, 0) if self.offsets else stamp_ns
        tol = self._tol_ns
        if t < self.start_ns - tol:
            return f"stamped {(self.start_ns - t) / 1e9:.3f} s before this receiver started"
        age = now_ns - t
        if age > self._max_ns:
            return f"stamped {age / 1e9:.3f} s ago (limit {self._max_ns / 1e9:g} s)"
        if age < -tol:
            return f"stamped {-age / 1e9:.3f} s in the future (tolerance {tol / 1e9:g} s)"
        return ""

    def put_problem(
        self,
        signer: str,
        win: SenderWindow,
        sid: bytes,
        seq: int,
        stamp_ns: int,
        now_ns: int,
        *,
        bound: bool = False,
    ) -> str:
        """Why a put (``bound``: a latest value answering this receiver's own query, not aged) is
        not fresh for ``win``, the window of its key and signer ("" = fresh).

        The next numbers of the session this receiver follows are not aged: each is newer than
        anything it took, so not a replay to it, only late (a receiver that fell behind); how old
        a lease or setpoint may be to be *acted on* is the slave's own stamp-age rule."""
        if sid == win.sid:
            if seq <= win.top:
                return f"seq {seq} not after {win.top} of session {sid.hex()}"
            return ""
        if not bound and (why := self.age_problem(signer, stamp_ns, now_ns)):
            return why
        if win.sid and stamp_ns <= win.stamp_ns:
            return (
                f"session {sid.hex()} stamped {(win.stamp_ns - stamp_ns) / 1e9:.3f} s before "
                f"the signer's last message (session {win.sid.hex()})"
            )
        return ""

    @staticmethod
    def took(win: SenderWindow, sid: bytes, seq: int, stamp_ns: int) -> None:
        """Record a put delivered (after :meth:`put_problem` said fresh)."""
        win.sid = sid
        win.top = seq
        if stamp_ns > win.stamp_ns:
            win.stamp_ns = stamp_ns

    def query_problem(self, signer: str, sid: bytes, seq: int, stamp_ns: int, now_ns: int) -> str:
        """Why a query is not fresh ("" = fresh, and its id is now used up)."""
        if why := self.age_problem(signer, stamp_ns, now_ns):
            return why
        qid = (signer, sid, seq, stamp_ns)
        with self._lock:
            order, used = self._order, self._used
            while order and order[0][0] < now_ns:
                used.pop(order.popleft()[1], None)
            if qid in used:
                return f"replayed query (seq {seq} of session {sid.hex()}, already taken)"
            if len(used) >= MAX_QUERY_IDS:
                return f"more than {MAX_QUERY_IDS} queries within {self._max_ns / 1e9:g} s"
            # kept until no copy of it can pass the age rule any more
            expiry = self.local_ns(signer, stamp_ns) + self._max_ns + self._tol_ns
            used[qid] = expiry
            order.append((expiry, qid))
        return ""

    def reply_problem(self, signer: str, stamp_ns: int, now_ns: int) -> str:
        """Why a reply (already verified as bound to its query) is too old ("" = fresh)."""
        return self.age_problem(signer, stamp_ns, now_ns)
