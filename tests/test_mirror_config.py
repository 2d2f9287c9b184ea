"""The mirror's config refuses what it cannot do, naming the field and its range."""

from __future__ import annotations

import pytest
from telesurg.services.mirror import MirrorConfig
from telesurg.shared.errors import ConfigError


@pytest.mark.parametrize("value", [-0.1, 10.5, float("nan")])
def test_a_batcher_flush_outside_its_range_is_refused(value: float) -> None:
    cfg = MirrorConfig(save="x.rrd", flush_s=value)
    with pytest.raises(ConfigError, match=r"flush_s=.* outside \[0, 10\]"):
        cfg.validate()


def test_the_batcher_flush_defaults_to_rerun_s_own() -> None:
    cfg = MirrorConfig(save="x.rrd")
    cfg.validate()
    assert cfg.flush_s == 0.0  # RerunView: 0 → rerun's default tick (0.2 s)
    MirrorConfig(save="x.rrd", flush_s=0.5).validate()


def test_the_inbox_of_a_starved_mirror_stays_bounded_and_counts_what_it_dropped() -> None:
    from telesurg.services.mirror import Inbox
    from telesurg.shared.messages import Header, Heartbeat

    inbox = Inbox(max_items=100)
    for i in range(250):  # the draw loop got no CPU for a while
        inbox.on_message(Heartbeat(Header("watchdog", i, i), service="watchdog"), "k")
    items = inbox.take()
    assert len(items) == 100 and inbox.dropped == 150 and inbox.received == 250
    assert [m.header.seq for _, _, m in items] == list(range(150, 250))  # the newest kept, in order
    assert inbox.take() == []
    with pytest.raises(ConfigError, match=r"inbox_max=.* outside"):
        MirrorConfig(save="x.rrd", inbox_max=10).validate()
