"""``telesurg bench arms``: a robot of N identical arms through the real services, and what each
arm costs (tools/bench/arms.py, tools/bench/arms_robot.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.shared.robots import registry
from telesurg.tools.bench import arms
from telesurg.tools.bench.arms_robot import register_arms


def test_the_robot_of_n_arms_is_n_mh3f_each_with_its_own_joints_and_tip(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # registered for this test only: the other tests see the registry they expect
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    name = register_arms(3, tmp_path)
    spec = registry.get(name)
    profiles = spec.arms("arm1")
    assert [p.arm for p in profiles] == ["arm1", "arm2", "arm3"]
    joints = [j for p in profiles for j in p.model_joints]
    assert len(set(joints)) == 18 and profiles[1].tip_site == "arm2_tip"
    home = tuple(x for p in profiles for x in p.home)
    with MujocoBackend(name, home, sites=tuple(p.tip_site for p in profiles)) as b:
        assert b.joint_names == tuple(joints)
        b.step(10)
        r = b.read()
        assert r.site_positions is not None
        # every arm at the MH3F's home tip (one base)
        want = registry.get("mh3f").arm("arm1").pose(np.array(profiles[0].home))[:3, 3]
        assert np.allclose(r.site_positions, want, atol=1e-3)


@pytest.mark.parametrize("bad", ["0", "1,x", "17", ""])
def test_bad_arm_counts_are_refused(bad: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=r"arm counts|in \[1, 16\]"):
        arms._arms_arg(bad)


@pytest.mark.process
@pytest.mark.timeout(300)
def test_one_and_two_arms_run_through_the_real_services(tmp_path: Path) -> None:
    out = tmp_path / "arms.json"
    from telesurg.tools.bench import main

    code = main(["arms", "--arms", "1,2", "--rate", "250", "--seconds", "3", "--json", str(out)])
    assert code == 0
    res = json.loads(out.read_text())
    rows = {r["arms"]: r for r in res["rows"]}
    print(json.dumps({n: (r["cpu_total_pct"], r["arms_followed"]) for n, r in rows.items()}))
    assert set(rows) == {1, 2}
    for n, r in rows.items():
        # every arm of the robot followed the master: the slave used its setpoints
        assert r["arms_followed"] == n, r
        assert set(r["cpu_pct"]) >= {"router", "watchdog", "slave_control", "mapping", "master_capture"}
        assert r["end_to_end_ms"]["n"] > 100 and r["relay_end_to_end_ms"]["n"] > 100
    # the CPU an added arm costs, where the host has room for both (else None: saturated)
    assert res["cpu_per_added_arm_pct"] is None or np.isfinite(res["cpu_per_added_arm_pct"])


def test_the_summary_reads_the_slope_where_the_host_has_room() -> None:
    def row(n: int, cpu: float, runs: bool) -> dict[str, object]:
        return {"arms": n, "cpu_total_pct": cpu, "runs": runs}

    free = arms.summary([row(1, 60.0, True), row(2, 90.0, True), row(3, 120.0, False)], 2)
    assert free == {
        "cpu_per_added_arm_pct": 30.0,
        "saturated_from_arms": None,
        "largest_arms_without_misses": 2,
    }
    full = arms.summary([row(1, 186.0, False), row(2, 194.0, False)], 2)
    assert full == {"cpu_per_added_arm_pct": None, "saturated_from_arms": 1, "largest_arms_without_misses": 0}
