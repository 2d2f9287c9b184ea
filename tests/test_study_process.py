"""``telesurg study`` through the real services (docs/study.md): a protocol of both MH3F tasks at
0 and 300 ms of added delay each way, one repetition, the synthetic operator as the participant.

Each trial is a real site — router, watchdog, slave_control on MuJoCo, mapping, master_capture
with the policy device — whose master reaches it through the link impairer. What a user notices:
every trial completes and has its JSON line and its recording (the slave's tip in it), the report
is written, and the operator is slower at 300 ms than at 0 ms (its time following, without the
time the watchdog held the arm: on a loaded host a hold is the host's, not the delay's).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from telesurg.shared import tasks
from telesurg.tools import study
from telesurg.tools.study.protocol import load, schedule
from telesurg.tools.study.runner import Where, run_trial, streams_from_mcap

PROTOCOL = """\
[study]
name = "ci"
seed = 3
tasks = ["mh3f-targets", "mh3f-wire"]
repetitions = 1
host_margin_ms = 500

[[condition]]
name = "0 ms"
delay_ms = 0

[[condition]]
name = "300 ms"
delay_ms = 300
"""


@pytest.mark.process
@pytest.mark.timeout(1200)
@pytest.mark.skipif(
    not os.environ.get("TELESURG_SLOW"),
    reason="issue #44 acceptance 2 in small, a slow test (4 trials on real sites, 5-10 min; not yet "
    "seen to pass on a loaded host): TELESURG_SLOW=1 runs it",
)
def test_a_study_runs_on_real_sites_and_delay_slows_the_operator(tmp_path: Path) -> None:
    proto = tmp_path / "ci.toml"
    proto.write_text(PROTOCOL)
    out = tmp_path / "out"
    assert study.main([str(proto), "--out", str(out)]) == 0
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert sorted((r["task"], r["condition"]) for r in rows) == [
        ("mh3f-targets", "0 ms"), ("mh3f-targets", "300 ms"), ("mh3f-wire", "0 ms"), ("mh3f-wire", "300 ms"),
    ]  # fmt: skip
    active = {}
    for r in rows:
        print(
            f"{r['task']} {r['condition']}: done={r['completed']} in {r['completion_time_s']} s "
            f"(held {r['time_held_s']:.1f} s), path {r['path_length_mm']:.0f} mm, "
            f"errors {r['errors']}, peak force {r['peak_force_n']:.2f} N, clutch {r['clutch_count']}"
        )
        assert r["completed"], r
        s = streams_from_mcap(out / r["recording"])
        assert len(s.tip) > 250 and len(s.follow) > 20  # the recording holds the trial
        active[(r["task"], r["condition"])] = r["completion_time_s"] - r["time_held_s"]
    assert (out / "report.png").stat().st_size > 10_000
    assert "| mh3f-wire | 300 ms | 1 | 1 |" in (out / "report.md").read_text()
    slow = sum(active[(t, "300 ms")] for t in ("mh3f-targets", "mh3f-wire"))
    fast = sum(active[(t, "0 ms")] for t in ("mh3f-targets", "mh3f-wire"))
    print(f"time following, both tasks: {fast:.1f} s at 0 ms, {slow:.1f} s at 300 ms")
    assert slow > fast


TROCAR_PROTOCOL = """\
[study]
name = "through the trocar"
seed = 5
tasks = ["mh3f-trocar-targets"]
repetitions = 1
host_margin_ms = 500

[[condition]]
name = "0 ms"
delay_ms = 0
"""


@pytest.mark.process
@pytest.mark.timeout(900)
def test_the_trocar_task_is_done_through_the_trocar_on_a_real_site(tmp_path: Path) -> None:
    """Issue #44 acceptance 1, the MH3F target task through the trocar: the harness sets the arm up
    (PTP posture adjustment, insert to trocar mode, master–slave), the synthetic operator touches
    the organ's targets under the trocar in trocar mode, and the RCM error stays within its limit."""
    proto = tmp_path / "trocar.toml"
    proto.write_text(TROCAR_PROTOCOL)
    out = tmp_path / "out"
    assert study.main([str(proto), "--out", str(out)]) == 0
    (r,) = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    print(
        f"{r['task']}: done={r['completed']} in {r['completion_time_s']} s (held {r['time_held_s']:.1f} s), "
        f"path {r['path_length_mm']:.0f} mm (ideal {r['ideal_length_mm']:.0f}), errors {r['errors']}, "
        f"RCM max {r['rcm_error_max_mm']:.3f} mm mean {r['rcm_error_mean_mm']:.3f} mm, "
        f"peak force {r['peak_force_n']:.2f} N, contact {r['contact_time_s']:.1f} s"
    )
    assert r["completed"] and r["goals_reached"] == 4, r
    s = streams_from_mcap(out / r["recording"])
    go = s.follow[s.follow[:, 1] > 0.5, 0][0]
    during = s.rcm[(s.rcm[:, 0] >= go) & (s.rcm[:, 0] <= go + r["completion_time_s"])]
    assert len(during) > 20 and during[:, 2].min() == 1.0  # in trocar mode throughout the trial
    assert r["rcm_error_max_mm"] < 2.0 and r["errors"]["rcm_error"] == 0, r  # the RCM held
    # the forceps touched the organ (each touch presses it), and a press above the 2 N limit is
    # scored as an error (the synthetic operator overshoots into the organ now and then: 2.4-3 N)
    assert r["contact_time_s"] > 0.5 and r["peak_force_n"] > 0.05, r
    assert (r["errors"]["tissue_force"] > 0) == (r["peak_force_n"] > 2.0), r


@pytest.mark.process
@pytest.mark.timeout(600)
@pytest.mark.parametrize(
    ("task", "knobs", "error"),
    [("mh3f-targets", {"press_mm": 9.0}, "tissue_force"), ("mh3f-wire", {"detour_mm": 10.0}, "path_exit")],
)
def test_a_provoked_error_is_detected_and_scored(
    tmp_path: Path, task: str, knobs: dict[str, float], error: str
) -> None:
    """Issue #44 acceptance 1: the synthetic operator errs on purpose through the real services —
    it aims each touch 9 mm into the tissue, or leaves the wire's tube 10 mm to the side
    at the wire's middle — and the trial's row scores it (force above the task's 2 N limit; an
    exit from the 5 mm tube), the recording showing the cause."""
    proto = tmp_path / "p.toml"
    proto.write_text(PROTOCOL.replace('tasks = ["mh3f-targets", "mh3f-wire"]', f'tasks = ["{task}"]'))
    trial = next(t for t in schedule(load(proto), "p01") if t.condition.delay_ms == 0)
    where = Where(tmp_path / "out")
    row = run_trial(trial, where, 500.0, knobs=knobs, time_limit_s=15.0)
    print({k: row[k] for k in ("completed", "completion_time_s", "errors", "peak_force_n", "path_exits")})
    assert row["errors"][error] >= 1, row
    s = streams_from_mcap(where.mcap(trial.index))
    if error == "tissue_force":
        assert row["peak_force_n"] > 2.0 and s.force[:, 1].max() > 2.0, row
    else:
        spec = tasks.get(task)
        far = float(tasks.distance_to_path(s.tip[:, 1:4], spec.path)[0].max())
        assert far > spec.tube_radius_m, far  # the tip was out of the tube
