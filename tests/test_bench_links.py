"""``telesurg bench links``: the bare relay over TCP loopback and a Unix socket, both delivering."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.process


def test_both_links_carry_the_stream_and_the_json_says_what_it_cost(tmp_path: Path) -> None:
    out = tmp_path / "links.json"
    argv = [sys.executable, "-m", "telesurg.services.cli", "bench", "links", "--pairs", "1", "--seconds", "8"]
    proc = subprocess.run(
        [*argv, "--rate", "200", "--json", str(out)], capture_output=True, text=True, timeout=180
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    r = json.loads(out.read_text())
    assert [run["link"] for run in r["runs"]] == ["tcp", "unixsock"]
    tcp, unix = r["runs"]
    assert tcp["endpoint"].startswith("tcp/127.0.0.1:") and unix["endpoint"].startswith("unixsock-stream/")
    for run in r["runs"]:
        # every message of the 200 Hz source arrived (it sends for --seconds), and the four
        # processes used some CPU, split into user and system time
        assert run["received"] >= 0.95 * run["expected"], run
        assert 0 < run["cpu"] == pytest.approx(run["cpu_user"] + run["cpu_system"]), run
        assert 0 < run["p50_ms"] <= run["p99_ms"], run
    assert set(r["median"]) == {"tcp", "unixsock"} and r["machine"]["cpus"] >= 1
    assert "median of 1: tcp CPU" in proc.stdout


def test_links_refuses_a_run_too_short_to_measure() -> None:
    argv = [sys.executable, "-m", "telesurg.services.cli", "bench", "links", "--seconds", "3"]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "--seconds >= 8" in proc.stderr
