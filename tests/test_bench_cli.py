"""Smoke runs of the benchmark commands users run (`telesurg bench faults|fuzz`): exit code, JSON."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from rerun.chunk import RrdReader

pytestmark = pytest.mark.process

BENCH = [sys.executable, "-m", "telesurg.services.cli", "bench"]


def test_bench_faults_smoke(tmp_path: Path) -> None:
    out = tmp_path / "faults.json"
    argv = [*BENCH, "faults", "--only", "kill:mapping,garbage:50", "--json", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=240)
    print(proc.stdout[-3000:])
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = json.loads(out.read_text())["rows"]
    assert [r["fault"] for r in rows] == ["SIGKILL mapping", "garbage x50/key"]
    kill, garbage = rows
    assert kill["held"] and kill["reengage_needed"] and kill["causes"] == ["mapping not alive"]
    assert not garbage["held"] and garbage["rejected"] >= 50 * 10
    assert "telesurg bench faults" in proc.stdout


def test_bench_fuzz_smoke(tmp_path: Path) -> None:
    out = tmp_path / "fuzz.json"
    argv = [*BENCH, "fuzz", "--count", "400", "--rate", "400", "--seed", "7", "--json", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=240)
    print(proc.stdout[-3000:])
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    assert r["crashes"] == 0 and r["counts_match"] and r["joint_samples_outside_limits"] == 0
    assert r["sent"] >= 390 and r["rejected"]["mirror"] == r["expected_rejected"]["mirror"]


def test_bench_usage_errors() -> None:
    proc = subprocess.run([*BENCH, "nope"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "usage: telesurg bench" in proc.stderr
    proc = subprocess.run(
        [*BENCH, "faults", "--only", "melt:router"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2 and "unknown fault 'melt:router'" in proc.stderr


def test_bench_memory_smoke(tmp_path: Path) -> None:
    out = tmp_path / "mem.json"
    argv = [*BENCH, "memory", "--seconds", "8", "--every", "2", "--warmup", "0", "--json", str(out)]
    argv += [
        "--set",
        "mirror.rrd_footer=true",
        "--log-dir",
        str(tmp_path / "logs"),
        "--plot",
        str(tmp_path / "m.png"),
    ]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=240)
    print(proc.stdout[-3000:])
    assert proc.returncode == 0, proc.stderr[-3000:]
    r = json.loads(out.read_text())
    procs = r["processes"]
    assert set(procs) == {"router", "watchdog", "mapping", "mirror", "slave_control"}, procs
    # every process sampled from start to end: a slope per process, resident sizes a process has
    assert all(p["slope_mb_s"] is not None and 10 < p["end_mb"] < 2000 for p in procs.values()), procs
    assert len(r["samples"]) >= 5 and r["samples"][-1]["t_s"] >= 8
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the override reached the mirror: its .rrd was closed with a footer (rerun opens it silently)
    assert r["set"] == ["mirror.rrd_footer=true"] and "mirror" in proc.stdout
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        chunks = sum(1 for _ in RrdReader(str(tmp_path / "logs" / "session.rrd")).stream())
    assert chunks > 10 and not [w for w in seen if "footer" in str(w.message)], chunks
    bad = subprocess.run([*BENCH, "memory", "--set", "mirror:geometry=false"], capture_output=True, text=True)
    assert bad.returncode == 1 and "expected SERVICE.KEY=VALUE" in bad.stdout
