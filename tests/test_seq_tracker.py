"""The one sequence tracker (streams.SeqTracker) of the bus, the recorder and the serial links."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from telesurg.services.record import SeqCheck
from telesurg.shared.serial_link import SEQ_MODULUS, frame_seq_tracker, seq_delta
from telesurg.shared.streams import (
    DUPLICATE,
    FIRST,
    GAP,
    LATE,
    NEXT,
    RESTART,
    SeqTracker,
    StreamStats,
    seq_distance,
)


def _run(t: SeqTracker, seqs: list[int]) -> list[str]:
    return [t.add(s) for s in seqs]


def test_every_verdict_and_its_counts() -> None:
    t = SeqTracker()
    assert _run(t, [3, 4, 7, 5, 5, 2, 8, 0, 1]) == [
        FIRST,
        NEXT,
        GAP,
        LATE,
        DUPLICATE,
        LATE,
        NEXT,
        RESTART,
        NEXT,
    ]
    # 7 skips 5 and 6; 5 comes late (6 stays lost); 5 again is a duplicate; 2 is older than the
    # first seen (3): late; 0 after 8: the publisher restarted
    assert t.counts() == {"messages": 9, "gaps": 1, "lost": 1, "reordered": 2, "duplicates": 1, "restarts": 1}
    assert t.skipped == 2 and t.top == 1


def test_zero_after_zero_is_a_duplicate_and_a_new_source_a_restart() -> None:
    t = SeqTracker()
    assert _run(t, [0, 0]) == [FIRST, DUPLICATE]
    t.restart()
    assert _run(t, [500, 501]) == [FIRST, NEXT]
    assert (t.restarts, t.gaps, t.duplicates) == (1, 0, 1)


def test_reset_keeps_the_counts() -> None:
    t = SeqTracker()
    _run(t, [0, 2])
    t.reset()
    assert _run(t, [9, 10]) == [FIRST, NEXT]
    assert (t.gaps, t.lost, t.restarts, t.messages) == (1, 1, 0, 4)


def test_serial_links_wrap_and_a_step_back_is_a_restart() -> None:
    t = frame_seq_tracker()
    assert _run(t, [65534, 65535, 0, 3]) == [FIRST, NEXT, NEXT, GAP]
    assert (t.gaps, t.lost) == (1, 2)
    assert t.add(1) == RESTART  # a byte stream cannot reorder: the sender started over
    assert t.add(1) == RESTART  # nor repeat a frame
    assert t.add(0) == RESTART and t.add(1) == NEXT
    assert (t.restarts, t.reordered, t.duplicates) == (3, 0, 0)


def test_late_numbers_across_a_wrap() -> None:
    t = SeqTracker(modulus=SEQ_MODULUS)
    assert _run(t, [65533, 1, 65535, 0, 65534]) == [FIRST, GAP, LATE, LATE, LATE]
    assert (t.gaps, t.lost, t.reordered) == (1, 0, 3)


def test_holes_are_bounded() -> None:
    t = SeqTracker(max_holes=10)
    _run(t, [0, 100])  # 99 skipped: counted, not remembered
    assert t.lost == 99 and not t.holes
    assert t.add(50) == DUPLICATE  # without the memory a late one cannot be told from a repeat


@pytest.mark.parametrize(("a", "b", "m", "d"), [(5, 3, 0, -2), (65535, 0, 2**16, 1), (0, 65535, 2**16, -1)])
def test_seq_distance(a: int, b: int, m: int, d: int) -> None:
    assert seq_distance(a, b, m) == d


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_serial_seq_delta_is_the_tracker_distance(a: int, b: int) -> None:
    assert seq_delta(a, b) == seq_distance(a, b, SEQ_MODULUS)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 60), max_size=40))
def test_bus_and_recorder_count_one_way(seqs: list[int]) -> None:
    """The bus delivers exactly the NEXT / GAP / FIRST / RESTART messages of the recorder's tracker."""
    bus, rec = StreamStats(), SeqCheck()
    delivered = [s for s in seqs if bus.accept("pub", s)]
    kept = [s for s, v in zip(seqs, _run(rec, seqs), strict=True) if v not in (LATE, DUPLICATE)]
    assert delivered == kept
    assert bus.received == len(delivered)
    assert (bus.gaps, bus.restarts) == (rec.gaps, rec.restarts)
    assert bus.reordered == rec.reordered + rec.duplicates == len(seqs) - len(delivered)
    assert bus.lost == rec.skipped  # a late message is dropped by the bus: still lost to its callback
