"""``telesurg experiment jinno-insertion --quick`` end to end (issue #4, acceptance 3): the real
services, MuJoCo, every insertion through the trocar, RCM error from MuJoCo below the paper's 1 mm.
The short protocol runs each posture method once (jog and direct teach from start b, PTP from
start c), then the trace from start a; the full protocol is the command without ``--quick``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from telesurg.tools.experiment.jinno import QUICK_PLAN

pytestmark = pytest.mark.process


def test_jinno_insertion_experiment(tmp_path: Path) -> None:
    out = tmp_path / "jinno"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "telesurg.services.cli",
            "experiment",
            "jinno-insertion",
            "--out",
            str(out),
            "--quick",
        ],
        capture_output=True,
        text=True,
        timeout=400,
    )
    print(r.stdout, r.stderr[-3000:])
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((out / "metrics.json").read_text())
    for key in ("rcm_error_max_mm", "rcm_error_mean_mm", "insertions_succeeded", "mode_transitions"):
        assert key in m
    assert m["rcm_error_samples"] > 100  # the trace was measured, many states
    assert m["rcm_error_max_mm"] < 1.0 and m["rcm_error_max_all_trocar_mm"] < 1.0
    # from the measured joints at their full rate, over all of trocar mode (master–slave included):
    # issue #20 asks < 1 mm there too (the slave interpolates its setpoints: no step reaches the servos)
    full_max, full_n = m["rcm_full_rate_max_mm"], m["rcm_full_rate_samples"]
    print(f"full-rate RCM over trocar mode: max {full_max} mm over {full_n} samples")
    print("per run:", {r["name"]: r["rcm_full_rate_max_mm"] for r in m["runs"]})
    assert m["rcm_full_rate_samples"] > 1000
    assert full_max < 1.0
    runs = len(QUICK_PLAN)
    assert {r[2] for r in QUICK_PLAN} == {"ptp", "jog", "direct_teach"} and QUICK_PLAN[-1][3]
    assert m["insertions_succeeded"] == m["insertions_attempted"] == runs
    # every run: into trocar mode and out again (5 transitions each)
    assert m["mode_transitions"] >= 5 * runs and m["removals_succeeded"] == runs
    assert all(run["other_joints_moved_deg"] < 0.05 for run in m["runs"])  # posture: J4/J5 only
    # the tip traces the master's path: judged by the distance from it, not by how late the tip
    # got there (a loaded host stalls the slave; its lag is a figure, not a pass/fail limit)
    print(
        f"trace: path error rms/max {m['trace_path_error_rms_mm']}/{m['trace_path_error_max_mm']} mm, "
        f"lag {m['trace_lag_ms']} ms, same-time error rms/max "
        f"{m['trace_tracking_error_rms_mm']}/{m['trace_tracking_error_max_mm']} mm"
    )
    assert m["trace_path_error_max_mm"] < 2.0 and m["trace_attempts"] >= 1
    figures = ("jinno-fig9.png", "jinno-fig10.png", "jinno-trace.png", "jinno-timeline.png", "jinno-rcm.png")
    for name in figures:
        assert (out / name).stat().st_size > 10_000
