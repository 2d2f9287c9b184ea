"""Smoke runs of the benchmark commands users run (`telesurg bench faults|fuzz`): exit code, JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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
