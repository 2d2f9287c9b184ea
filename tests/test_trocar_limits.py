"""Trocar-mode reach, depth and speed clamping, the way out, and the patient keep-out (issue #20).

Pure kinematics: the functions the mapping (``clamped_trocar_ik``) and slave_control
(``remove_step``, the keep-out checks) call for every sample.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from telesurg.shared.errors import IKError
from telesurg.shared.robots.mh3f.keepout import PatientBox, path_problem, pose_problem
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, wrist_center
from telesurg.shared.robots.mh3f.trocar import insertion_depth, posture_adjust, rcm_error, trocar_ik
from telesurg.shared.robots.mh3f.trocar_limits import TROCAR_SPEED_FRACTION, clamped_trocar_ik, remove_step
from telesurg.tools.experiment.jinno import STARTS, TROCAR

DT = 1 / 250
VMAX = np.array(MH3F.max_velocity)
# the mh3f scene's patient torso (shared/robots/mh3f/scene.xml), drape top 0.198 m
BOX = PatientBox((0.26, -0.17, 0.13), (0.74, 0.17, 0.198), tuple(TROCAR.tolist()))


def inserted(start: str, depth: float) -> np.ndarray:
    q = posture_adjust(np.array(STARTS[start]), TROCAR)
    T = fk(q)
    tip = T[:3, 3] + (depth - insertion_depth(q, TROCAR)) * T[:3, 0]
    return trocar_ik(tip, TROCAR, q)


def dummy_tip(h: np.ndarray) -> np.ndarray:
    """The virtual-trocar master point (fulcrum 100 mm below, 250 mm dummy forceps)."""
    d = np.array([0.0, 0.0, -0.1]) - h
    return h + 0.25 * d / np.linalg.norm(d)


@pytest.mark.parametrize("start", sorted(STARTS))
@pytest.mark.parametrize("depth", [0.05, 0.11])
def test_virtual_trocar_circle_never_holds_and_keeps_the_rcm(start: str, depth: float) -> None:
    """A 60 mm master circle at scale 0.5 toward the arm: the slave moves on every sample, within
    the joint speeds, RCM exact; it used to stop at the reach limit ("beyond the reach")."""
    q = inserted(start, depth)
    p0, m0 = fk(q)[:3, 3], dummy_tip(np.zeros(3))
    stalls = longest = 0
    for n in range(1, 1250):
        a = 2 * math.pi * n / 1250
        h = np.array([0.03 * (1 - math.cos(a)), 0.03 * math.sin(a), 0.0])
        r = clamped_trocar_ik(p0 + 0.5 * (dummy_tip(h) - m0), TROCAR, q, DT)
        assert np.all(np.abs(r.q - q) <= VMAX * DT * TROCAR_SPEED_FRACTION + 1e-12)
        assert rcm_error(r.q, TROCAR) < 1e-9
        stalls = stalls + 1 if np.array_equal(r.q, q) else 0
        longest = max(longest, stalls)
        if r.clamped:
            assert r.detail, "a clamp says what it clamped"
        q = r.q
    assert longest * DT <= 0.1


def test_unreachable_target_is_pivoted_to_the_reach_limit_with_a_reason() -> None:
    q = inserted("start_a", 0.05)
    tip = fk(q)[:3, 3]
    with pytest.raises(IKError, match="reach"):
        trocar_ik(tip + np.array([-0.05, 0.0, 0.0]), TROCAR, q)  # toward the arm: the wrist goes out of reach
    r = clamped_trocar_ik(tip + np.array([-0.05, 0.0, 0.0]), TROCAR, q, 1.0)
    assert "reach" in r.clamped and "mm from J2" in r.detail
    assert np.linalg.norm(wrist_center(r.q) - [0, 0, MH3F.d1]) <= MH3F.reach - 0.009
    assert rcm_error(r.q, TROCAR) < 1e-9
    deep = clamped_trocar_ik(TROCAR + 0.6 * (tip - TROCAR) / np.linalg.norm(tip - TROCAR), TROCAR, q, 1.0)
    assert "depth" in deep.clamped and np.linalg.norm(deep.tip - TROCAR) == pytest.approx(0.35)


@pytest.mark.slow
def test_remove_gets_out_where_the_straight_way_leaves_the_reach() -> None:
    """Axis tilted away from the arm: retracting straight would take the wrist out of reach."""
    rng = np.random.default_rng(3)
    pivoted = 0
    q_seed = inserted("start_a", 0.05)
    tried = 0
    while tried < 30:
        th, ph, depth = math.radians(rng.uniform(0, 55)), rng.uniform(0, 2 * math.pi), rng.uniform(0.03, 0.2)
        d = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), -math.cos(th)])
        try:
            q = trocar_ik(TROCAR + depth * d, TROCAR, q_seed)
        except IKError:
            continue
        tried += 1
        did = False
        for _ in range(20000):
            if insertion_depth(q, TROCAR) < -0.002:
                break
            q, p = remove_step(q, TROCAR, 0.04 * DT, pivot_rad=0.25 * DT)
            did |= p
            assert rcm_error(q, TROCAR) < 1e-6 or insertion_depth(q, TROCAR) < 0.002
        assert insertion_depth(q, TROCAR) < -0.002
        pivoted += did
    assert pivoted > 0  # the sample holds poses the straight retraction could not leave


def test_keepout_allows_the_trocar_and_refuses_the_patient_elsewhere() -> None:
    q = inserted("start_a", 0.08)
    assert pose_problem(q, BOX) is None  # through the trocar
    q_off = q.copy()
    q_off[0] += 0.1  # swing J1: the shaft cuts the patient beside the trocar
    problem = pose_problem(q_off, BOX)
    assert problem is not None and "outside the trocar" in problem
    outside = posture_adjust(np.array(STARTS["start_a"]), TROCAR)
    assert path_problem(np.array(STARTS["start_a"]), outside, BOX) is None


@pytest.mark.slow
def test_random_ptp_paths_through_the_patient_are_found() -> None:
    """200 random PTP targets from random postures: the path check refuses every sweep through
    the patient (judged again at 5× finer steps) and names the reason."""
    rng = np.random.default_rng(20)
    lo, hi = np.array(MH3F.lower), np.array(MH3F.upper)
    refused = 0
    for _ in range(200):
        a, b = rng.uniform(lo * 0.6, hi * 0.6), rng.uniform(lo * 0.6, hi * 0.6)
        problem = path_problem(a, b, BOX)
        fine = path_problem(a, b, BOX, max_step_rad=0.001)
        if problem is None:
            assert fine is None, fine
        else:
            refused += 1
            assert "patient" in problem or "trocar" in problem
    assert refused > 0


def test_experiment_starts_lie_inside_the_local_workspace_and_reach_the_trocar_outside_the_patient() -> None:
    """Issue #20: the jinno-insertion starts (tips at z 860–1,225 mm before) lie inside the local
    site's workspace box, their PTP posture adjustments (J4 and J5 both turn) and the playbacks
    between them (from 60 mm behind the trocar) keep the forceps out of the patient."""
    import tomllib
    from pathlib import Path

    from telesurg.shared.robots.mh3f.kinematics import ik

    site = tomllib.loads((Path(__file__).parents[1] / "deploy/local/site.toml").read_text())["site"]
    lo, hi = np.array(site["workspace_min_mm"]) / 1e3, np.array(site["workspace_max_mm"]) / 1e3
    for name, q in STARTS.items():
        tip = fk(np.array(q))[:3, 3]
        assert np.all(tip >= lo) and np.all(tip <= hi), f"{name}: tip {tip * 1e3} mm outside the workspace"
        aligned = posture_adjust(np.array(q), TROCAR)
        turned = np.degrees(np.abs(aligned - q))
        assert np.all(turned[3:5] > 20.0) and np.all(turned[[0, 1, 2, 5]] < 1e-9), (name, turned)
        assert insertion_depth(aligned, TROCAR) < 0.0  # aligned outside: the insertion is left to do
        assert path_problem(np.array(q), aligned, BOX) is None
        T = fk(aligned)
        T[:3, 3] += (-0.062 - insertion_depth(aligned, TROCAR)) * T[:3, 0]  # backed off after removal
        behind = ik(T, aligned)
        for other in STARTS.values():  # the experiment's playback to the next start
            assert path_problem(behind, np.array(other), BOX) is None
