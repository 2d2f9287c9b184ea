"""Per-stream receive bookkeeping: sequence gaps, reordering, duplicates, rejections, staleness."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class StreamStats:
    """Counts for one incoming stream (one key, one source).

    ``accept(seq)`` returns False for a duplicate or out-of-order message, which the caller then
    drops. A jump forward is accepted and counted in ``gaps`` / ``lost``. A new source id (a
    restarted publisher) resets the expected sequence.
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

    def accept(self, source: str, seq: int) -> bool:
        """Account one decoded message; False means drop it (old or duplicate)."""
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
        self.last_rx_ns = time.monotonic_ns()
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
