"""The peg transfer through the real services (docs/study.md): on the VIP and PLAS sites, two
masters (the synthetic operator's two hands, each a ``policy`` master_capture through the link
impairer) drive the two arms; slave_control's MuJoCo jaws grasp the peg by friction, hand it over
and place it. What a user notices: the trial completes with the peg on its target after a real
hand-over (the recording's scene shows it held by arm1, then by both, then by arm2, then resting
on the target), and a peg dropped on the way is scored as a drop.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared import tasks
from telesurg.tools import study
from telesurg.tools.study import runner
from telesurg.tools.study.protocol import load, schedule

PROTOCOL = """\
[study]
name = "pegs"
seed = 11
tasks = ["{task}"]
repetitions = 1
host_margin_ms = 500

[[condition]]
name = "0 ms"
delay_ms = 0
"""


def holders_seen(obj: np.ndarray) -> list[int]:
    """The object's holders (bits) in the order they changed."""
    out: list[int] = []
    for bits in obj[:, 4].astype(int):
        if not out or out[-1] != bits:
            out.append(int(bits))
    return out


def in_order(seen: list[int], wanted: list[int]) -> bool:
    """``wanted`` occurs in ``seen`` in this order (other values between them allowed)."""
    it = iter(seen)
    return all(w in it for w in wanted)


@pytest.mark.process
@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", ["vip-pegs", "plas-pegs"])
def test_the_peg_is_handed_over_and_placed_by_real_grasps(tmp_path: Path, name: str) -> None:
    """Issue #44 acceptance 1, the two-arm peg transfer on the VIP and on the PLAS (its position
    mapping keeping the forceps' tilt): grasp, hand over, place, in MuJoCo, with no drop and no
    collision of the instruments."""
    task = tasks.get(name)
    proto = tmp_path / "pegs.toml"
    proto.write_text(PROTOCOL.format(task=task.name))
    out = tmp_path / "out"
    assert study.main([str(proto), "--out", str(out)]) == 0
    (r,) = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    print(
        f"{r['task']}: done={r['completed']} in {r['completion_time_s']} s (held {r['time_held_s']:.1f} s), "
        f"paths {r['path_lengths_mm']} mm (ideal {r['ideal_length_mm']:.0f}), errors {r['errors']}, "
        f"peak force {r['peak_force_n']:.2f} N"
    )
    assert r["completed"] and r["goals_reached"] == 3, r
    assert r["errors"]["drop"] == 0 and r["errors"]["collision"] == 0, r
    s = runner.streams_from_mcap(out / r["recording"], task)
    # held by arm1 (1), by both (3) in the hand-over, by arm2 alone (2), then let go (0)
    seen = holders_seen(s.obj)
    print("holders seen:", seen)
    assert seen[0] == 0 and in_order(seen, [1, 3, 2]) and seen[-1] == 0, seen
    place = task.goals[2].position
    end = s.obj[-1, 1:4]
    assert np.hypot(end[0] - place[0], end[1] - place[1]) <= task.goals[2].radius_m, end  # on its target
    assert all(v > 0 for v in r["path_lengths_mm"].values()), r  # both arms moved


@pytest.mark.process
@pytest.mark.timeout(600)
def test_a_peg_dropped_on_the_way_is_scored_as_a_drop(tmp_path: Path) -> None:
    """The first hand opens its grip once it has lifted the peg: the peg falls, the trial scores a
    drop; the operator picks it up again where it lies."""
    proto = tmp_path / "pegs.toml"
    proto.write_text(PROTOCOL.format(task="vip-pegs"))
    (trial,) = schedule(load(proto), "p01")
    where = runner.Where(tmp_path / "out")
    row = runner.run_trial(trial, where, 500.0, knobs={"drop_after_lift": True})
    print({k: row[k] for k in ("completed", "completion_time_s", "errors", "goals_reached", "path_exits")})
    assert row["errors"]["drop"] >= 1, row
    s = runner.streams_from_mcap(where.mcap(trial.index), tasks.get("vip-pegs"))
    z = s.obj[:, 3]
    assert z.max() - z[np.argmax(z) :].min() > 0.01, "the peg fell"
