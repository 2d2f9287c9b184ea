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


def test_the_rates_are_the_live_viewer_s_while_serving_and_the_file_s_otherwise() -> None:
    from telesurg.services.mirror import FILE_DRAW_HZ, LIVE_DRAW_HZ, LIVE_PLOT_HZ

    saving = MirrorConfig(save="x.rrd")
    saving.validate()
    assert (saving.effective_draw_hz(), saving.effective_plot_hz()) == (FILE_DRAW_HZ, 0.0)  # every sample
    serving = MirrorConfig(save="x.rrd", serve=True)
    serving.validate()
    assert (serving.effective_draw_hz(), serving.effective_plot_hz()) == (LIVE_DRAW_HZ, LIVE_PLOT_HZ)
    assert LIVE_DRAW_HZ < FILE_DRAW_HZ and serving.flush_s == 0.25
    chosen = MirrorConfig(serve=True, draw_hz=15.0, plot_hz=0.0)  # a user's rates win
    chosen.validate()
    assert (chosen.effective_draw_hz(), chosen.effective_plot_hz()) == (15.0, 0.0)
    # what the lean layout does not show (the camera too): LIVE_OFFVIEW_HZ while serving it, else as set
    from telesurg.services.mirror import LIVE_OFFVIEW_HZ

    assert (serving.layout, serving.effective_offview_hz(), serving.effective_image_hz()) == (
        "lean",
        LIVE_OFFVIEW_HZ,
        min(serving.image_hz, LIVE_OFFVIEW_HZ),
    )
    assert (saving.effective_offview_hz(), saving.effective_image_hz()) == (0.0, saving.image_hz)
    full = MirrorConfig(serve=True, layout="full")
    assert (full.effective_offview_hz(), full.effective_image_hz()) == (0.0, full.image_hz)
    # the joint blocks and the trails: the live viewer's rates while serving, the file's otherwise
    from telesurg.services.mirror import FILE_SERIES_HZ, LIVE_SERIES_HZ, LIVE_TRAIL_DRAW_HZ

    assert (serving.effective_series_hz(), serving.effective_trail_draw_hz()) == (
        LIVE_SERIES_HZ,
        LIVE_TRAIL_DRAW_HZ,
    )
    assert (saving.effective_series_hz(), saving.effective_trail_draw_hz()) == (FILE_SERIES_HZ, FILE_DRAW_HZ)
    mine = MirrorConfig(serve=True, series_hz=4.0, trail_draw_hz=10.0)
    assert (mine.effective_series_hz(), mine.effective_trail_draw_hz()) == (4.0, 10.0)
    bads = ({"draw_hz": 0.5}, {"draw_hz": -0.5}, {"plot_hz": -0.5}, {"plot_hz": -2.0}, {"series_hz": 0.0})
    for bad in (*bads, {"trail_draw_hz": 0.2}, {"series_hz": -2.0}):
        with pytest.raises(ConfigError, match=rf"{next(iter(bad))}="):
            MirrorConfig(save="x.rrd", **bad).validate()  # type: ignore[arg-type]


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
