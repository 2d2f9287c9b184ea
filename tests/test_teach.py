"""Direct teach (admittance) and teaching playback, pure parts: services/slave_control/teach.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared.errors import ConfigError, IKError
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk
from telesurg.shared.robots.mh3f.teach import (
    MAX_POINTS,
    Playback,
    TaughtPoint,
    TeachConfig,
    TeachStore,
    admittance,
    direct_teach_step,
    playback_problem,
)
from telesurg.shared.robots.mh3f.trocar import insertion_depth, posture_adjust, rcm_error, trocar_ik

TROCAR = np.array([0.5, 0.0, 0.2])
START = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])
CFG = TeachConfig()


def inserted(depth: float = 0.06) -> np.ndarray:
    """Joints with the forceps ``depth`` m through the trocar."""
    q = posture_adjust(START, TROCAR)
    tip = fk(q, MH3F)[:3, 3]
    d = (TROCAR - tip) / np.linalg.norm(TROCAR - tip)
    return trocar_ik(TROCAR + depth * d, TROCAR, q)


def point(q: np.ndarray, mode: str) -> TaughtPoint:
    tip = fk(q, MH3F)[:3, 3]
    return TaughtPoint(tuple(q.tolist()), (float(tip[0]), float(tip[1]), float(tip[2])), mode)


def test_admittance_deadband_gain_and_cap() -> None:
    tau = np.array([0.2, -0.2, 10.0, -10.0, 1.3, 1000.0])
    v = admittance(tau, CFG)
    assert v[0] == 0.0 and v[1] == 0.0  # inside the deadband
    assert v[2] == pytest.approx(CFG.gain_arm * (10.0 - CFG.deadband_nm))
    assert v[3] == pytest.approx(-CFG.gain_wrist * (10.0 - CFG.deadband_nm))
    assert v[5] == CFG.max_speed_rad_s


def test_non_trocar_every_joint_follows_the_push() -> None:
    tau = np.array([5.0, -5.0, 5.0, -5.0, 5.0, -5.0])
    out = direct_teach_step(START, tau, 0.01, "non_trocar", CFG)
    assert np.all(np.sign(out - START) == np.sign(tau))


def test_trocar_j1_to_j3_follow_and_the_rcm_holds() -> None:
    q = inserted()
    tau = np.array([8.0, 3.0, 0.0, 5.0, 5.0, 5.0])  # wrist torques are ignored in trocar mode
    for _ in range(200):
        q_next = direct_teach_step(q, tau, 0.001, "trocar", CFG, trocar=TROCAR)
        assert rcm_error(q_next, TROCAR) < 1e-9
        assert q_next[5] == q[5]  # J6 kept
        q = q_next
    assert q[0] - inserted()[0] > 0.01  # J1 moved with the push
    assert insertion_depth(q, TROCAR) > 0.005


def test_trocar_push_that_pulls_the_tip_out_is_not_followed() -> None:
    q = inserted(0.0055)  # just inside
    tau = np.zeros(6)
    # find a J2/J3 push that makes the tip shallower, then check it is refused
    for sign in (1.0, -1.0):
        tau[1] = sign * 20.0
        q_try = q.copy()
        q_try[:3] += admittance(tau, CFG)[:3] * 0.01
        if insertion_depth(posture_adjust(q_try, TROCAR), TROCAR) < insertion_depth(q, TROCAR):
            break
    with pytest.raises(IKError, match="out of the trocar"):
        for _ in range(100):
            q = direct_teach_step(q, tau, 0.01, "trocar", CFG, trocar=TROCAR)


def test_posture_only_j4_j5_toward_the_target_never_past_it() -> None:
    target = posture_adjust(START, TROCAR)
    togo = target - START
    away = -np.sign(togo) * 20.0
    away[:3] = 50.0
    out = direct_teach_step(START, away, 0.01, "posture", CFG, posture_target=target)
    assert np.array_equal(out, START)  # pushing away from the target (or J1–J3) moves nothing
    toward = np.sign(togo) * 20.0
    toward[[0, 1, 2, 5]] = 50.0
    q = START.copy()
    for _ in range(3000):
        q = direct_teach_step(q, toward, 0.01, "posture", CFG, posture_target=target)
    assert np.array_equal(q[[0, 1, 2, 5]], START[[0, 1, 2, 5]])
    assert np.allclose(q[3:5], target[3:5], atol=1e-12)  # arrived and stopped there


def test_playback_joint_ptp_passes_every_point_exactly() -> None:
    pts = [point(START + d, "non_trocar") for d in (np.full(6, 0.05), np.full(6, -0.05), np.zeros(6))]
    pb = Playback(pts, "non_trocar", None, np.array(MH3F.max_velocity) * 0.2, 0.02, dwell_s=0.05)
    q = START + 0.1
    path = []
    for _ in range(20000):
        q = pb.next(q, 0.001)
        path.append(q)
        if pb.done:
            break
    assert pb.done and pb.reached == [0, 1, 2]
    for p in pts:
        assert min(float(np.max(np.abs(x - np.array(p.q)))) for x in path) < 1e-12
    steps = np.abs(np.diff(np.array(path), axis=0)).max()
    assert steps < 0.2 * max(MH3F.max_velocity) * 0.001 * 1.6  # smooth: no jumps


def test_trocar_playback_keeps_the_rcm_between_points() -> None:
    q0 = inserted(0.06)
    q1 = trocar_ik(fk(q0, MH3F)[:3, 3] + [0.0, 0.02, 0.01], TROCAR, q0)
    pts = [point(q1, "trocar"), point(q0, "trocar")]
    pb = Playback(pts, "trocar", TROCAR, np.array(MH3F.max_velocity) * 0.2, 0.02, dwell_s=0.0)
    q = q0.copy()
    worst = 0.0
    while not pb.done:
        q = pb.next(q, 0.001)
        worst = max(worst, rcm_error(q, TROCAR))
    assert worst < 1e-9
    assert np.linalg.norm(fk(q, MH3F)[:3, 3] - np.array(pts[-1].tip)) < 1e-9


def test_playback_refuses_programs_that_cross_the_trocar() -> None:
    outside = [point(START, "non_trocar")]
    inside = [point(inserted(), "trocar")]
    assert "not on the trocar" in playback_problem(outside, "trocar", TROCAR)
    assert "inside the trocar" in playback_problem(inside, "non_trocar", TROCAR)
    assert playback_problem(outside, "non_trocar", TROCAR) == ""
    assert playback_problem(inside, "trocar", TROCAR) == ""
    assert playback_problem([], "non_trocar", TROCAR) == "the program has no points"


def test_store_round_trip_and_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "arm1.json"
    s = TeachStore(path, "arm1")
    s.trocars["port1"] = (0.5, 0.0, 0.2)
    s.current_trocar = "port1"
    assert s.add_point("home", point(START, "non_trocar")) == ""
    s.save()
    again = TeachStore(path, "arm1")
    assert again.trocars == s.trocars and again.current_trocar == "port1"
    assert again.programs == s.programs
    with pytest.raises(ConfigError, match="belongs to arm 'arm1'"):
        TeachStore(path, "arm2")
    assert "invalid program name" in s.add_point("Bad Name", point(START, "non_trocar"))
    for _ in range(MAX_POINTS - 1):
        s.add_point("home", point(START, "non_trocar"))
    assert "already has 64 points" in s.add_point("home", point(START, "non_trocar"))
    path.write_text("{not json")
    with pytest.raises(ConfigError, match=str(path)):
        TeachStore(path, "arm1")
    data = {
        "version": 1,
        "arm": "arm1",
        "programs": {"x": [{"q": [0.0, "a"], "tip": [0, 0, 0], "mode": "n"}]},
    }
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="bad joints"):
        TeachStore(path, "arm1")
    assert TeachStore(None, "arm1").programs == {}  # memory only
