"""Sequence tracking of one stream (:class:`SeqTracker`), and the bus's per-key receive bookkeeping.

:class:`SeqTracker` is the one place that says what a sequence number means, for every counter of
the project: the bus (:class:`StreamStats`, per key), the recorder (per key and publisher) and the
serial links (16-bit frame counters, ``shared/serial_link.py``, the devices and the servo
controller). Given the newest number seen so far (``top``):

=========================================== ============ =========================================
new number                                  verdict      counters
=========================================== ============ =========================================
the first one (or the first after reset())  ``FIRST``    —
``top + 1``                                 ``NEXT``     —
``0`` after a higher one                    ``RESTART``  ``restarts`` (the publisher started over)
``top + 1 + k``, k ≥ 1                      ``GAP``      ``gaps`` += 1, ``skipped`` and ``lost`` += k
``≤ top``, one of the skipped numbers       ``LATE``     ``reordered`` += 1, ``lost`` −= 1
``≤ top``, older than the first one seen    ``LATE``     ``reordered`` += 1
``≤ top`` otherwise (seen before)           ``DUPLICATE`` ``duplicates`` += 1
=========================================== ============ =========================================

With ``modulus`` (a serial link's 2**16) distances wrap (65535 → 0 is ``NEXT``). A transport
that cannot reorder or duplicate (``reorders=False``: a serial byte stream) turns every step back
into a ``RESTART``: there, a number going back can only be the sender starting over. Skipped
numbers are remembered (up to ``max_holes``) so that a late one is told from a duplicate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from telesurg.shared.fresh import SenderWindow

#: A forward sequence jump larger than this is implausible (at 1 kHz: over 100 s of loss without
#: the link dropping); it is rejected unless the next message confirms the new numbering.
MAX_SEQ_JUMP = 100_000
#: Most skipped sequence numbers a tracker remembers (to tell a late message from a duplicate).
MAX_HOLES = 100_000

FIRST, NEXT, GAP, LATE, DUPLICATE, RESTART = "first", "next", "gap", "late", "duplicate", "restart"


def seq_distance(a: int, b: int, modulus: int = 0) -> int:
    """Signed distance from sequence number ``a`` to ``b``; with a modulus, in [-modulus/2, modulus/2).

    1 is the next number, ``d > 1`` skips ``d - 1``, ``d <= 0`` goes back. Wraps:
    ``seq_distance(65535, 0, 2**16) == 1``."""
    if modulus:
        half = modulus // 2
        return (b - a + half) % modulus - half
    return b - a


@dataclass(slots=True)
class SeqTracker:
    """Gaps, losses, late and duplicate messages and restarts of one numbered stream (see the module).

    ``add(seq)`` returns the verdict; the counters accumulate over :meth:`reset` (a new link or
    publisher: its numbering may start anywhere)."""

    modulus: int = 0  # 0: unbounded integers >= 0 (bus, recorder); 2**16: serial frames
    reorders: bool = True  # False: an in-order transport, a step back is a restart
    max_holes: int = MAX_HOLES
    messages: int = 0
    gaps: int = 0
    skipped: int = 0  # numbers jumped over by gaps, late or not
    lost: int = 0  # numbers jumped over and not (yet) seen
    reordered: int = 0
    duplicates: int = 0
    restarts: int = 0
    # False: seq 0 after a higher number is *not* a restart (a stream whose restarts are known
    # by other means, e.g. an authenticated session id): it is a late or duplicate number
    zero_restarts: bool = True
    top: int = -1  # newest number (-1: none yet)
    first: int = -1
    holes: set[int] = field(default_factory=set)

    def reset(self) -> None:
        """Forget the position (a new link or publisher); the counters stay."""
        self.top = self.first = -1
        self.holes.clear()

    def restart(self) -> None:
        """Count a restart seen by other means (e.g. a new source id); the next number is FIRST."""
        self.restarts += 1
        self.reset()

    def add(self, seq: int) -> str:
        """Account one number; returns FIRST, NEXT, GAP, LATE, DUPLICATE or RESTART."""
        self.messages += 1
        top = self.top
        if seq == top + 1 and top >= 0:  # in order: the common case, first
            self.top = seq
            return NEXT
        if top < 0:
            self.top = self.first = seq
            return FIRST
        d = seq - top if not self.modulus else seq_distance(top, seq, self.modulus)
        if d == 1:
            self.top = seq
            return NEXT
        if (seq == 0 and top > 0 and self.zero_restarts and seq not in self.holes) or (
            d <= 0 and not self.reorders
        ):
            self.restarts += 1
            self.holes.clear()
            self.top = self.first = seq
            return RESTART
        if d > 1:
            missing = d - 1
            self.gaps += 1
            self.skipped += missing
            self.lost += missing
            if len(self.holes) + missing <= self.max_holes:
                m = self.modulus
                self.holes.update(((top + i) % m if m else top + i) for i in range(1, d))
            self.top = seq
            return GAP
        if seq in self.holes:
            self.holes.discard(seq)
            self.lost -= 1
            self.reordered += 1
            return LATE
        if (
            seq_distance(self.first, seq, self.modulus) < 0
        ):  # older than anything seen: came after its successors
            self.reordered += 1
            return LATE
        self.duplicates += 1
        return DUPLICATE

    def counts(self) -> dict[str, int]:
        """Counters for reports."""
        return {
            "messages": self.messages,
            "gaps": self.gaps,
            "lost": self.lost,
            "reordered": self.reordered,
            "duplicates": self.duplicates,
            "restarts": self.restarts,
        }


#: Skipped numbers a bus stream remembers: its verdicts drop late and duplicate messages alike, so
#: a small memory is enough (and a large gap costs no time in the receive path).
BUS_MAX_HOLES = 1024


@dataclass
class StreamStats:
    """Counts for one incoming stream (one key, one source), on a :class:`SeqTracker`.

    ``accept(seq)`` returns False for a duplicate or late (out-of-order) message, which the caller
    then drops: a subscriber sees every stream only move forward. A jump forward is accepted and
    counted in ``gaps`` / ``lost``; a jump of more than :data:`MAX_SEQ_JUMP` is accepted only once
    the next message continues it (one forged message cannot make the genuine stream look old). A
    new source id (a restarted publisher) is a restart, like ``seq`` 0 after a higher one.
    ``rejected`` counts what the strict decoder refused, messages from a source that may not
    publish on this key (also in ``foreign``), messages that failed authentication (also in
    ``unauthenticated``; the bus rejects them before decoding, so they change nothing else here),
    messages the freshness rules refused (also in ``replayed``: too old, or not newer than what
    their signer sent before, :mod:`telesurg.shared.fresh`) and unconfirmed jumps.

    With an authenticated session id (``accept(..., sid=...)``, the bus's case) a restart is a new
    ``sid`` only — ``seq`` 0 in the same session is an old or duplicate number, dropped — and a new
    ``sid`` is taken only with a header stamp newer than the last accepted message's (a recorded
    message of an earlier session, sent again, is refused and counted in ``stale_sessions``).

    Because late messages are dropped, ``lost`` counts every number jumped over (a late one never
    reaches the callback: the tracker's ``skipped``) and ``reordered`` every message dropped as not
    newer (the tracker's ``reordered`` + ``duplicates``); ``seq`` has the finer counts.
    """

    received: int = 0
    rejected: int = 0
    source: str = ""
    last_rx_ns: int = 0
    foreign: int = 0
    jumps: int = 0
    unauthenticated: int = 0  # failed authentication (also in rejected)
    stale_sessions: int = 0  # a session id change with an older stamp (also in rejected)
    replayed: int = 0  # refused by the freshness rules, shared/fresh.py (also in rejected)
    # signer -> what was taken from it on this key (shared/fresh.py; the bus keeps them)
    senders: dict[str, SenderWindow] = field(default_factory=dict)
    sid: bytes = b""  # authenticated session id of the source ("" = none seen / not tracked)
    last_stamp_ns: int = 0  # header stamp of the last accepted message (with a sid)
    seq: SeqTracker = field(default_factory=lambda: SeqTracker(max_holes=BUS_MAX_HOLES))
    _jump_to: int = -1

    @property
    def gaps(self) -> int:
        """Forward jumps of the sequence number."""
        return self.seq.gaps

    @property
    def lost(self) -> int:
        """Sequence numbers jumped over: messages the callback never got."""
        return self.seq.skipped

    @property
    def reordered(self) -> int:
        """Messages dropped as not newer than the last one delivered (late or duplicate)."""
        return self.seq.reordered + self.seq.duplicates

    @property
    def restarts(self) -> int:
        """Publisher restarts: a new source id, or ``seq`` 0 after a higher one."""
        return self.seq.restarts

    @property
    def last_seq(self) -> int:
        """Newest sequence number delivered (-1: none yet)."""
        return self.seq.top

    def accept(self, source: str, seq: int, rx_ns: int = 0, sid: bytes = b"", stamp_ns: int = 0) -> bool:
        """Account one decoded message; False means drop it (old, duplicate or implausible).

        ``rx_ns``: when it arrived (monotonic ns; 0 = now), for a message read from a buffer.
        ``sid`` / ``stamp_ns``: its authenticated session id and header stamp (see the class)."""
        t = self.seq
        if sid:
            if self.sid != sid and source == self.source:
                if stamp_ns <= self.last_stamp_ns:
                    self.rejected += 1
                    self.stale_sessions += 1
                    return False
                if self.sid:
                    t.restart()
                self._jump_to = -1
            self.sid = sid
            t.zero_restarts = False
        if seq > t.top + MAX_SEQ_JUMP and t.top >= 0 and source == self.source:
            if seq != self._jump_to + 1:
                self._jump_to = seq
                self.rejected += 1
                return False
            self.jumps += 1
        if self._jump_to >= 0:
            self._jump_to = -1
        if source != self.source:
            if self.source:
                t.restart()
            self.source = source
        verdict = t.add(seq)
        if verdict is LATE or verdict is DUPLICATE:
            return False
        self.received += 1
        self.last_rx_ns = rx_ns or time.monotonic_ns()
        if stamp_ns > self.last_stamp_ns:
            self.last_stamp_ns = stamp_ns
        return True

    def age_s(self) -> float:
        """Seconds since the last accepted message (inf if none yet)."""
        if not self.last_rx_ns:
            return float("inf")
        return (time.monotonic_ns() - self.last_rx_ns) / 1e9

    def as_dict(self) -> dict[str, Any]:
        """Counters for reports."""
        return {
            "received": self.received,
            "gaps": self.gaps,
            "lost": self.lost,
            "reordered": self.reordered,
            "rejected": self.rejected,
            "restarts": self.restarts,
            "foreign": self.foreign,
            "unauthenticated": self.unauthenticated,
            "replayed": self.replayed,
        }


@dataclass
class StreamTable:
    """StreamStats by key."""

    streams: dict[str, StreamStats] = field(default_factory=dict)

    def get(self, key: str) -> StreamStats:
        """Stats of ``key`` (created on first use)."""
        s = self.streams.get(key)
        if s is None:
            s = self.streams[key] = StreamStats()
        return s

    @property
    def rejected(self) -> int:
        """Total rejected messages over all streams."""
        return sum(s.rejected for s in self.streams.values())

    @property
    def replayed(self) -> int:
        """Total messages the freshness rules refused (also in :attr:`rejected`), over all streams."""
        return sum(s.replayed for s in self.streams.values())

    @property
    def lost(self) -> int:
        """Total numbers jumped over and not seen, over all streams."""
        return sum(s.lost for s in self.streams.values())
