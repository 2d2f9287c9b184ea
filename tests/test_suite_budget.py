"""The suite's own honesty: more process-test reruns than the budget fail the run, and the
summary lists each rerun with its first failure and the unit/process split of the run's time."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

CONFTEST = Path(__file__).resolve().parent / "conftest.py"

FLAKY = """
import pathlib
import pytest

@pytest.mark.process
@pytest.mark.parametrize("i", range({n}))
def test_fails_once(i, tmp_path_factory):
    mark = pathlib.Path(__file__).with_name(f"ran-{{i}}")
    if not mark.exists():
        mark.write_text("once")
        raise AssertionError(f"first attempt of {{i}} fails")

def test_unit_passes():
    pass
"""


def run_suite(tmp_path: Path, flaky: int, *args: str) -> subprocess.CompletedProcess[str]:
    (tmp_path / "conftest.py").write_text(CONFTEST.read_text())
    (tmp_path / "test_flaky.py").write_text(FLAKY.format(n=flaky))
    (tmp_path / "pytest.ini").write_text("[pytest]\nmarkers =\n    process: real services\n")
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", *args, str(tmp_path)],
        cwd=tmp_path,
        # as from a shell, also when this test runs in a pytest-xdist worker
        env={k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_XDIST", "PYTEST_CURRENT"))},
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.slow
@pytest.mark.parametrize("flaky", [1, 6])
def test_reruns_over_the_budget_fail_the_run_and_are_listed(tmp_path: Path, flaky: int) -> None:
    r = run_suite(tmp_path, flaky)
    over = flaky > 5
    assert (r.returncode != 0) == over, r.stdout[-3000:]
    assert f"reruns: {flaky} of a budget of 5" in r.stdout, r.stdout[-3000:]
    assert ("over the budget: the run fails" in r.stdout) == over
    for i in range(flaky):
        assert f"rerun test_flaky.py::test_fails_once[{i}] (call), first failure:" in r.stdout
        assert f"first attempt of {i} fails" in r.stdout
    assert "unit tests: 1 in" in r.stdout and f"process tests: {flaky} in" in r.stdout, r.stdout[-3000:]


@pytest.mark.slow
def test_in_parallel_the_controller_alone_counts_and_records_and_the_parts_add_up(tmp_path: Path) -> None:
    """make test runs the unit part, then the process part; with ``-n 2`` (pytest-xdist) a run
    has the same verdict and list, and one record; the second part names both and their sum."""
    unit = run_suite(tmp_path, 6, "-m", "not process")
    assert unit.returncode == 0 and "this run: -m 'not process'" in unit.stdout, unit.stdout[-3000:]
    r = run_suite(tmp_path, 6, "-m", "process", "-n", "2")
    assert r.returncode != 0 and "reruns: 6 of a budget of 5" in r.stdout, r.stdout[-3000:]
    for i in range(6):
        assert f"rerun test_flaky.py::test_fails_once[{i}] (call), first failure:" in r.stdout
    assert "unit tests: 0 in" in r.stdout and "process tests: 6 in" in r.stdout, r.stdout[-3000:]
    assert "2 workers" in r.stdout and "make test: unit part " in r.stdout, r.stdout[-3000:]
    assert " s wall (budget 900 s)" in r.stdout, r.stdout[-3000:]
    runs = json.loads((tmp_path / ".pytest_cache/v/telesurg/runs").read_text())
    assert [(run["marks"], run["workers"]) for run in runs] == [("not process", 0), ("process", 2)], runs
    assert runs[1]["process"]["tests"] == 6 and len(runs[1]["reruns"]) == 6, runs
