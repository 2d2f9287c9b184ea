"""``telesurg bench ingest``: each kind sends what the mirror sends for it, at the rate asked.

The browser run itself is a benchmark (its figures are in docs/performance.md); here the feeder
writes to a file instead of the web viewer, and the file is read back.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from telesurg.tools.bench.ingest import KINDS, Feeder


@pytest.mark.parametrize("kind", KINDS)
def test_each_kind_sends_its_entity_at_the_rate_asked(kind: str, tmp_path: Path) -> None:
    from rerun.chunk import RrdReader
    from telesurg.services.mirror.view import BODY_POSES, RerunView, geometry_path

    out = tmp_path / f"{kind}.rrd"
    view = RerunView("test", save=str(out))
    t0 = time.monotonic()
    with Feeder(view, kind, rate=20.0).running() as feeder:
        deadline = t0 + 30.0  # (a loaded host may starve the feeder's thread: its figure, not a fault)
        while feeder.sent < 20 and time.monotonic() < deadline:
            time.sleep(0.01)
    elapsed = time.monotonic() - t0
    sent = feeder.sent
    view.close()
    entity = {
        "poses": BODY_POSES,
        "primitives": geometry_path("mh3f"),
        "series": "/slave/arm1/joints/measured",
        "trail": "/slave/arm1/tip",
    }[kind]
    rows = 0
    for c in RrdReader(str(out)).stream():
        if c.entity_path == entity and not c.is_static:
            rows += c.num_rows
    # paced at the rate asked: frame k + 1 goes out no earlier than k / 20 s after the first (how
    # fast a starved host keeps up is the bench's figure: telesurg bench ingest)
    assert 20 <= sent <= 20.0 * elapsed + 1, (sent, elapsed)
    # a Transform3D row per body of the MH3F scene the mirror draws; a 10-row joint block; one row
    # otherwise
    per_frame = {"poses": len(feeder.geo.bodies), "series": 10}.get(kind, 1)
    assert rows == sent * per_frame, (rows, sent)


def test_an_unknown_kind_is_refused() -> None:
    from telesurg.services.mirror.view import RerunView

    view = RerunView("test")
    with pytest.raises(ValueError, match="kind 'meshes': valid: poses, primitives, series, trail"):
        Feeder(view, "meshes", 10.0)
    view.close()
