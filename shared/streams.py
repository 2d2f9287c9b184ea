"""Per-stream receive bookkeeping: sequence gaps, reordering, duplicates, rejections, staleness."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

#: A forward sequence jump larger than this is implausible (at 1 kHz: over 100 s of loss without
#: the link dropping); it is rejected unless the next message confirms the new numbering.
MAX_SEQ_JUMP = 100_000


@dataclass
class StreamStats:
    """Counts for one incoming stream (one key, one source).

    ``accept(seq)`` returns False for a duplicate or out-of-order message, which the caller then
    drops. A jump forward is accepted and counted in ``gaps`` / ``lost``; a jump of more than
    :data:`MAX_SEQ_JUMP` is accepted only once the next message continues it (one forged message
    cannot make the genuine stream look old). A new source id (a restarted publisher) resets the
    expected sequence. ``rejected`` counts what the strict decoder refused, messages from a source
    that may not publish on this key (also in ``foreign``) and unconfirmed jumps.
    """

    received: int = 0
    gaps: int = 0
    lost: int = 0
    reordered: int = 0
    rejected: int = 0
    last_seq: int = -1
    source: str = ""
    last_rx_ns: int = 0
    restarts: int = 0
    foreign: int = 0
    jumps: int = 0
    _jump_to: int = -1

    def accept(self, source: str, seq: int, rx_ns: int = 0) -> bool:
        """Account one decoded message; False means drop it (old, duplicate or implausible).

        ``rx_ns``: when it arrived (monotonic ns; 0 = now), for a message read from a buffer."""
        if source == self.source and self.last_seq >= 0 and seq > self.last_seq + MAX_SEQ_JUMP:
            if seq != self._jump_to + 1:
                self._jump_to = seq
                self.rejected += 1
                return False
            self.jumps += 1
        self._jump_to = -1
        if source != self.source:
            if self.source:
                self.restarts += 1
            self.source = source
            self.last_seq = seq - 1
        elif seq == 0 and self.last_seq > 0:
            # Same source id restarted (process restart keeps its id): start over.
            self.restarts += 1
            self.last_seq = -1
        if seq <= self.last_seq:
            self.reordered += 1
            return False
        if seq > self.last_seq + 1 and self.last_seq >= 0:
            self.gaps += 1
            self.lost += seq - self.last_seq - 1
        self.last_seq = seq
        self.received += 1
        self.last_rx_ns = rx_ns or time.monotonic_ns()
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
