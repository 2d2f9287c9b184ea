"""The watchdog's checks of the slave's commanded joints of slave-side motions (``setpoint_js``).

Issue #20: the slave's own keep-out is one check; the watchdog checks the commanded joints too, as
it checks followed ``servo_jp`` — joint limits, jumps, the workspace and the patient keep-out. The
paths below are straight base-frame tip lines solved by the arm's IK (a base jog) and an insertion
along the forceps axis through the trocar; each sample is a ``setpoint_js`` 10 ms apart (100 Hz).
"""

from __future__ import annotations

import numpy as np
from telesurg.services.watchdog import WatchdogConfig
from telesurg.services.watchdog.commanded import CommandedCheck
from telesurg.services.watchdog.logic import ArmSafety
from telesurg.shared.messages import Header, JointState, OperatingState
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.mh3f.keepout import PatientBox, pose_problem, shaft_inside_m
from telesurg.shared.robots.mh3f.kinematics import fk, ik
from telesurg.shared.robots.mh3f.trocar import posture_adjust, rcm_error
from telesurg.tools.experiment.jinno import STARTS

PROFILE = arm_profile("mh3f", "arm1")
TROCAR = (0.5, 0.0, 0.2)
CFG = WatchdogConfig()
BOX = PatientBox(
    tuple(v / 1e3 for v in CFG.patient_box_min_mm),  # type: ignore[arg-type]
    tuple(v / 1e3 for v in CFG.patient_box_max_mm),  # type: ignore[arg-type]
    TROCAR,
)


def check() -> CommandedCheck:
    safety = ArmSafety("arm1", CFG.policy("arm1"), PROFILE.joint_names, tip_of=PROFILE.tip)
    c = CommandedCheck(safety, CFG.patient_box_min_mm, CFG.patient_box_max_mm, tip_of=PROFILE.tip)
    c.on_slave_state(OperatingState(Header("slave_control", 0, 1), trocar=TROCAR), 0.0)
    return c


def feed(c: CommandedCheck, path: list[np.ndarray], t0_ns: int = 10**18) -> list[str]:
    """Feed ``path`` as 100 Hz samples; the fault text of each ("" = none)."""
    out = []
    for i, q in enumerate(path):
        ts = t0_ns + i * 10_000_000
        msg = JointState(Header("slave_control", i, ts), PROFILE.joint_names, tuple(float(v) for v in q))
        out.append(c.on_setpoint_js(msg, i * 0.01))
    return out


def base_line(q0: np.ndarray, d_m: np.ndarray, steps: int) -> list[np.ndarray]:
    """The joints of a base-frame tip line from ``q0`` (orientation kept), one per step."""
    t0 = fk(q0)
    path, q = [q0], q0
    for i in range(1, steps + 1):
        t = t0.copy()
        t[:3, 3] += d_m * i / steps
        q = ik(t, q)
        path.append(q)
    return path


def test_a_jog_down_through_the_patient_holds_with_the_reason_where_it_would_cross() -> None:
    # from the home pose (tip at (835, 0, 301) mm) straight down 200 mm at 40 mm/s: the shaft
    # crosses the torso's top ~150 mm down, 230 mm from the trocar
    path = base_line(np.array(PROFILE.home), np.array([0.0, 0.0, -0.2]), 500)
    c = check()
    faults = feed(c, path)
    first = next(i for i, f in enumerate(faults) if f)
    assert pose_problem(path[first - 1], BOX) is None  # the first sample whose path crosses
    assert "patient keep-out" in faults[first] and "outside the trocar" in faults[first]
    v = c.safety.evaluate(first * 0.01)
    assert v.state == "HOLD" and not v.allow
    assert any("patient keep-out" in cause for cause in v.causes), v.causes
    assert c.safety.counters["keepout"] >= 1


def test_the_same_line_above_the_patient_is_allowed() -> None:
    path = base_line(np.array(PROFILE.home), np.array([0.0, 0.05, 0.05]), 200)
    c = check()
    assert not any(feed(c, path))
    assert c.safety.evaluate(2.0).state == "OK"
    assert c.checked == len(path)


def test_a_sweep_between_two_samples_is_found_on_the_path() -> None:
    # two samples far apart (a fast motion or a decimated stream): both ends are clear (the tip
    # beside the torso at either side), the joint path between them sweeps through it
    low = base_line(np.array(PROFILE.home), np.array([0.0, 0.0, -0.17]), 60)[-1]
    assert pose_problem(low, BOX)  # in front of the arm: in the patient
    a, b = low.copy(), low.copy()
    a[0], b[0] = 0.8, -0.8  # J1 swings it to either side, clear of the torso
    assert pose_problem(a, BOX) is None and pose_problem(b, BOX) is None
    c = check()
    faults = feed(c, [a, b])
    assert faults[0] == "" and "patient keep-out" in faults[1] and "along the path" in faults[1]


def test_insertion_through_the_trocar_is_allowed_and_a_tilt_out_of_it_is_not() -> None:
    q = posture_adjust(np.array(STARTS["start_a"]), np.array(TROCAR))  # aligned, tip 74 mm outside
    t = fk(q)
    axis = t[:3, 0]
    depth_now = float(np.dot(t[:3, 3] - np.array(TROCAR), axis))
    assert depth_now < -0.05 and pose_problem(q, BOX) is None
    insert = base_line(q, axis * (0.08 - depth_now), 400)  # to 80 mm beyond the trocar
    assert max(rcm_error(v, TROCAR) for v in insert) < 1e-6
    c = check()
    assert not any(feed(c, insert)), "an insertion through the trocar was held"
    assert shaft_inside_m(insert[-1], BOX) > 0.05
    # in the patient, a base-x line (not about the trocar) drags the shaft out of the trocar
    drag = base_line(insert[-1], np.array([0.03, 0.0, 0.0]), 60)
    faults = feed(c, drag, t0_ns=10**18 + 401 * 10_000_000)
    assert any("patient keep-out" in f for f in faults)


def test_a_motion_starting_in_the_patient_may_get_out_but_not_go_deeper() -> None:
    down = base_line(np.array(PROFILE.home), np.array([0.0, 0.0, -0.17]), 100)
    start = down[-1]
    assert pose_problem(start, BOX)  # an arm started in the patient (outside the trocar)
    up = base_line(start, np.array([0.0, 0.0, 0.05]), 50)
    c = check()
    assert not any(feed(c, up)), "getting out was held"
    deeper = base_line(start, np.array([0.0, 0.0, -0.03]), 30)
    c = check()
    faults = feed(c, deeper)
    assert faults[0] == "" and any("deeper into the patient" in f for f in faults)


def test_joint_limits_jumps_and_the_workspace_hold_like_servo_jp() -> None:
    c = check()
    q = np.array(PROFILE.home)
    bad = q.copy()
    bad[0] = PROFILE.upper[0] + 0.1
    assert "outside joint limits" in feed(c, [bad])[0]
    c = check()
    far = q.copy()
    far[0] += 0.5  # 0.5 rad in 10 ms
    out = feed(c, [q, q, q, far])
    assert "a jump" in out[-1]
    low_ceiling = WatchdogConfig(workspace_max_mm=(1100.0, 600.0, 320.0))
    safety = ArmSafety("arm1", low_ceiling.policy("arm1"), PROFILE.joint_names, tip_of=PROFILE.tip)
    c = CommandedCheck(safety, CFG.patient_box_min_mm, CFG.patient_box_max_mm, tip_of=PROFILE.tip)
    high = base_line(q, np.array([0.0, 0.0, 0.05]), 50)  # tip z 301 → 351 mm, ceiling 320 mm
    assert any(feed(c, high))
    assert any("outside the workspace" in cause for cause in c.safety.evaluate(0.6).causes)


def test_a_robot_without_the_trocar_family_has_no_keep_out() -> None:
    c = check()
    c.box_min_mm = c.box_max_mm = None
    path = base_line(np.array(PROFILE.home), np.array([0.0, 0.0, -0.2]), 100)
    assert not any(feed(c, path))


def test_no_trocar_reported_means_no_entry_anywhere() -> None:
    c = check()
    c.on_slave_state(OperatingState(Header("slave_control", 1, 2), trocar=(0.0, 0.0, 0.0)), 0.0)
    q = posture_adjust(np.array(STARTS["start_a"]), np.array(TROCAR))
    t = fk(q)
    depth_now = float(np.dot(t[:3, 3] - np.array(TROCAR), t[:3, 0]))
    insert = base_line(q, t[:3, 0] * (0.08 - depth_now), 400)
    assert any("patient keep-out" in f for f in feed(c, insert))


def test_a_motion_starting_above_the_workspace_may_come_back_in_but_not_go_further_out() -> None:
    # the trocar process tests' start: the tip at z = 1,024 mm, above the local site's 800 mm
    start = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])
    assert fk(start)[2, 3] > 0.8
    adjust = [start + (posture_adjust(start, np.array(TROCAR)) - start) * s for s in np.linspace(0, 1, 100)]
    c = check()
    assert not any(feed(c, adjust)), "the posture adjustment from above the workspace was held"
    c = check()
    up = base_line(start, np.array([0.0, 0.0, 0.02]), 20)
    faults = feed(c, up)
    assert faults[0] == "" and any("outside the workspace" in f for f in faults)


def test_a_slave_side_motion_reported_by_the_slave_starts_the_freshness_clock() -> None:
    """``motion_since``: set while the slave reports ENABLED without following (a slave-side
    motion: the service then needs setpoint_js fresh), cleared otherwise."""
    c = check()
    assert c.motion_since is None
    c.on_slave_state(OperatingState(Header("slave_control", 1, 2), "ENABLED", follow=False), 5.0)
    c.on_slave_state(OperatingState(Header("slave_control", 2, 3), "ENABLED", follow=False), 6.0)
    assert c.motion_since == 5.0  # from the motion's start
    c.on_slave_state(OperatingState(Header("slave_control", 3, 4), "ENABLED", follow=True), 7.0)
    assert c.motion_since is None  # following servo_jp: not a slave-side motion
    c.on_slave_state(OperatingState(Header("slave_control", 4, 5), "PAUSED", follow=False), 8.0)
    assert c.motion_since is None
