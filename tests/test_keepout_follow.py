"""The patient keep-out for every motion source: followed setpoints (master–slave in every mode,
any ``servo_jp``) clamped at the surface, and the slave-side jog, play and direct teach.

The geometry (:func:`telesurg.shared.robots.mh3f.keepout.clamp_step`), the follow controller that
applies it each period, and the trocar arm's rule (the site's patient box and trocar). The
forceps starts over the torso 150 mm from the trocar, pointing down; the master path goes 90 mm
straight down (through the torso). The depth is judged by sampling the shaft against the box here,
not by the code under test.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.slave_control.arm import ArmCore
from telesurg.services.slave_control.control import FollowController, Lease, Setpoint
from telesurg.shared.messages import Command, Header
from telesurg.shared.robots import arm_profile
from telesurg.shared.robots.api import ArmReading
from telesurg.shared.robots.mh3f.keepout import PatientBox, clamp_step, pose_problem
from telesurg.shared.robots.mh3f.kinematics import MH3F, fk, ik
from telesurg.shared.robots.mh3f.motions import TrocarMotions
from telesurg.shared.robots.mh3f.teach import TaughtPoint
from telesurg.shared.robots.mh3f.trocar import posture_adjust

TROCAR = np.array([0.5, 0.0, 0.2])
BOX = PatientBox((0.255, -0.175, 0.13), (0.745, 0.175, 0.198), (0.5, 0.0, 0.2))
#: joints: the tip at (635, 69, 241) mm over the torso, the forceps pointing down and out (+x)
OVER_TORSO = np.array([0.258, -0.008, 0.397, -0.172, -1.229, -0.435])
HOME = np.array([0.0, -0.2, 0.6, 0.0, -0.3, 0.0])


def depth_in_box(q: np.ndarray) -> float:
    """How deep (m) the shaft (wrist centre → tip) reaches into BOX, sampled at 0.1 mm."""
    T = fk(q)
    tip, axis = T[:3, 3], T[:3, 0]
    s = np.linspace(0.0, MH3F.wrist_to_tcp, 5901)
    p = tip[None, :] - s[:, None] * axis[None, :]
    inside = np.min(np.minimum(p - np.array(BOX.lo), np.array(BOX.hi) - p), axis=1)
    return max(0.0, float(inside.max()))


def gap_to_box(q: np.ndarray) -> float:
    """Distance (m) from the shaft to BOX (0 where it touches)."""
    T = fk(q)
    tip, axis = T[:3, 3], T[:3, 0]
    s = np.linspace(0.0, MH3F.wrist_to_tcp, 5901)
    p = tip[None, :] - s[:, None] * axis[None, :]
    out = np.maximum(np.maximum(np.array(BOX.lo) - p, p - np.array(BOX.hi)), 0.0)
    return float(np.linalg.norm(out, axis=1).min())


def down_path(q0: np.ndarray, metres: float, steps: int) -> list[np.ndarray]:
    """Joints moving the tip straight down by ``metres`` (orientation kept), by IK."""
    T0, out, q = fk(q0), [], q0
    for dz in np.linspace(0.0, -metres, steps + 1)[1:]:
        T = T0.copy()
        T[2, 3] += dz
        q = ik(T, q)
        out.append(q)
    return out


def test_a_step_into_the_torso_is_clamped_at_the_surface() -> None:
    target = down_path(OVER_TORSO, 0.06, 30)[-1]
    assert depth_in_box(target) > 0.015  # the step would put the tip 17 mm into the patient
    q, why = clamp_step(OVER_TORSO, target, BOX)
    assert why is not None and "outside the trocar" in why and "from the trocar" in why
    assert depth_in_box(q) == 0.0
    assert 0.0 < np.linalg.norm(q - OVER_TORSO) < np.linalg.norm(target - OVER_TORSO)
    for _ in range(5):  # the clamp goes on period by period: it closes in on the surface
        q, why = clamp_step(q, target, BOX, explain=False)
        assert why is not None and depth_in_box(q) == 0.0
    assert gap_to_box(q) < 1e-4  # at the surface, not short of it
    free = down_path(OVER_TORSO, 0.02, 10)[-1]  # 20 mm down: still above the patient
    assert clamp_step(OVER_TORSO, free, BOX) == (pytest.approx(free), None)


def test_following_a_master_through_the_torso_stops_at_the_surface() -> None:
    """The follow controller at 1 kHz, its setpoints 90 mm down through the torso (100 mm/s) and
    back up: the command waits at the surface, one event when the clamp starts and one when the
    setpoints are clear again."""
    ctl = FollowController(np.array(arm_profile("mh3f", "arm1").max_velocity))
    ctl.keepout = lambda a, b: (lambda q, why: (q, why or ""))(*clamp_step(a, b, BOX))
    lease = Lease(True, 1e9, "")
    path = down_path(OVER_TORSO, 0.09, 900)
    path += path[::-1] + [OVER_TORSO] * 200
    q_cmd = OVER_TORSO.copy()
    ctl.update(0.0, q_cmd, q_cmd, lease, Setpoint(q_cmd, False, 0.0), 0.001)  # clutch released
    deepest, closest = 0.0, np.inf
    for i, q_ref in enumerate(path):
        now = (i + 1) * 0.001
        q_cmd = ctl.update(now, q_cmd, q_cmd, lease, Setpoint(q_ref, True, now), 0.001)
        assert ctl.following
        deepest, closest = (
            max(deepest, depth_in_box(q_cmd)) if i % 25 == 0 else deepest,
            min(closest, gap_to_box(q_cmd) if i % 25 == 0 else closest),
        )
    assert deepest == 0.0 and closest < 1e-4
    assert np.abs(q_cmd - OVER_TORSO).max() < 1e-9  # followed the way back out
    kinds = [(k, t) for k, t in ctl.events if k == "keepout_clamped"]
    assert len(kinds) == 2, ctl.events
    assert "clamped at the patient's surface" in kinds[0][1] and "clear of the patient" in kinds[1][1]
    assert ctl.keepout_clamped > 500
    assert ctl.clipped == 0  # waiting at the surface is not counted as speed clipping


def test_entry_through_the_trocar_is_allowed_elsewhere_clamped() -> None:
    qa = posture_adjust(HOME, TROCAR)  # the forceps aimed at the trocar, tip outside
    T0 = fk(qa)
    axis = T0[:3, 0]
    depth0 = float((T0[:3, 3] - TROCAR) @ axis)  # < 0: before the trocar
    q = qa
    for d in np.arange(depth0, 0.06, 0.001):  # insert along the axis 60 mm past the trocar
        T = T0.copy()
        T[:3, 3] = TROCAR + d * axis
        nxt = ik(T, q)
        got, why = clamp_step(q, nxt, BOX)
        assert why is None, f"at depth {d * 1e3:.0f} mm: {why}"
        q = got
    assert depth_in_box(q) > 0.02  # in, through the trocar (the tip 49 mm under the trocar)
    # the same insertion 10 mm beside the trocar stops at the surface
    side = np.array([0.0, 0.01, 0.0])
    T = T0.copy()
    T[:3, 3] = TROCAR + side + depth0 * axis
    q = ik(T, qa)
    stopped = None
    for d in np.arange(depth0, 0.06, 0.001):
        T[:3, 3] = TROCAR + side + d * axis
        got, why = clamp_step(q, ik(T, q), BOX)
        q = got
        if why:
            stopped = why
    assert stopped is not None and "outside the trocar" in stopped
    assert depth_in_box(q) == 0.0 and gap_to_box(q) < 1e-4


def test_an_arm_started_inside_may_get_out_not_deeper() -> None:
    path = down_path(OVER_TORSO, 0.08, 40)
    inside, deeper, out = path[30], path[35], path[20]
    assert depth_in_box(inside) > 0.0
    q, why = clamp_step(inside, deeper, BOX)
    assert why is not None and np.array_equal(q, inside)
    q, why = clamp_step(inside, out, BOX)
    assert why is None and np.array_equal(q, out)


def test_the_trocar_arm_clamps_followed_setpoints_with_its_box_and_trocar() -> None:
    """TrocarMotions.follow_keepout: the site's patient box; with no trocar taught no entry."""
    cfg = SlaveControlConfig(model="mh3f")
    motions = TrocarMotions(cfg, arm_profile("mh3f", "arm1"))
    target = down_path(OVER_TORSO, 0.06, 30)[-1]
    q, why = motions.follow_keepout(OVER_TORSO, target)
    assert why.startswith("patient keep-out: ") and pose_problem(q, motions.patient_box()) is None
    qa = posture_adjust(HOME, TROCAR)
    T = fk(qa)
    T[:3, 3] = TROCAR + 0.02 * T[:3, 0]  # 20 mm in through the trocar
    q_in = ik(T, qa)
    T[:3, 3] = TROCAR + 0.021 * T[:3, 0]
    assert motions.follow_keepout(q_in, ik(T, q_in))[1] == ""
    motions.trocar_taught = False
    assert "no trocar taught" in motions.follow_keepout(qa, q_in)[1]


def test_the_fast_check_agrees_with_pose_problem() -> None:
    """clamp_step's message-free check (keepout._allowed) against pose_problem: random poses, and
    poses about the trocar (entering through it, beside it, tilted off it)."""
    from telesurg.shared.robots.mh3f.keepout import _allowed

    rng = np.random.default_rng(7)
    qa = posture_adjust(HOME, TROCAR)
    T0 = fk(qa)
    poses = [
        rng.uniform([-0.8, -0.6, -0.5, -1.5, -2.0, -1.0], [0.8, 0.9, 1.2, 1.5, 0.8, 1.0]) for _ in range(2000)
    ]
    for _ in range(1000):
        T = T0.copy()
        T[:3, 3] = TROCAR + rng.uniform(-0.01, 0.08) * T0[:3, 0] + rng.normal(0.0, 0.004, 3)
        poses.append(ik(T, qa))
    allowed = 0
    for box in (BOX, PatientBox(BOX.lo, BOX.hi, None)):
        for q in poses:
            assert (pose_problem(q, box) is None) == _allowed(q, box, MH3F), q
            allowed += pose_problem(q, box) is None
    assert 0 < allowed < 2 * len(poses)


# --------------------------------------------------------------------------- other motion sources


def _trocar_core() -> tuple[ArmCore, TrocarMotions]:
    cfg = SlaveControlConfig(model="mh3f", robot={"jog_speed_mm_s": 40.0})
    profile = arm_profile("mh3f", "arm1")
    motions = TrocarMotions(cfg, profile)
    core = ArmCore(profile, np.arange(6), cfg, 0.001, motion=motions)
    core.start(_reading(core, OVER_TORSO))
    core.lease = Lease(True, 1e9, "")
    return core, motions


def _reading(core: ArmCore, q: np.ndarray) -> ArmReading:
    """The arm where it was commanded (a perfect servo: the keep-out judges commands)."""
    return ArmReading(np.array(q, dtype=float), np.zeros(6), np.zeros(6), core.profile)


def _cmd(name: str, *args: str) -> Command:
    return Command(Header("console", 0, time.time_ns()), "arm1", name, args)


def test_a_jog_toward_the_torso_stops_before_it() -> None:
    """A base-z jog down from over the torso (non-trocar mode) stops with the keep-out's reason,
    the forceps outside the patient box."""
    core, motions = _trocar_core()
    assert motions.command(_cmd("set_motion_mode", "mode=jog"))[0]
    ok, why = motions.command(_cmd("jog", "frame=base", "axis=z", "direction=-1"))
    assert ok, why
    q = OVER_TORSO.copy()
    for i in range(3000):  # 3 s at 40 mm/s: 120 mm down, were it not stopped
        q = core.control(i * 0.001, _reading(core, q))
        core.after_period(i + 1, _reading(core, q))
        if i % 10 == 0:
            core.measure(_reading(core, q))
    assert motions.modes.jog_command is None  # stopped
    assert depth_in_box(q) == 0.0 and gap_to_box(q) < 0.002  # at the box, one step short at most
    assert fk(OVER_TORSO)[2, 3] - fk(q)[2, 3] > 0.03  # it did go down toward it


def test_a_play_through_the_torso_is_refused() -> None:
    """``play`` of a program whose joint path crosses the torso outside the trocar: refused,
    nothing moves."""
    _, motions = _trocar_core()
    deep = down_path(OVER_TORSO, 0.06, 30)[-1]
    motions.store.programs["deep"] = [
        TaughtPoint(tuple(deep.tolist()), tuple(fk(deep)[:3, 3].tolist()), "non_trocar")
    ]
    assert motions.command(_cmd("set_motion_mode", "mode=playback"))[0]
    ok, why = motions.command(_cmd("play", "program=deep"))
    assert not ok and "patient keep-out" in why and "outside the trocar" in why
    assert motions.playback is None


def test_direct_teach_does_not_follow_a_push_into_the_torso() -> None:
    """Direct teach outside trocar mode: a hand pushing the forceps tip down (40 N) moves it down
    toward the torso, and no further than the patient box."""
    core, motions = _trocar_core()
    assert motions.command(_cmd("set_motion_mode", "mode=direct_teach"))[0]
    q = OVER_TORSO.copy()
    for i in range(4000):
        wrench = np.array([0.0, 0.0, -40.0, 0.0, 0.0, 0.0])  # N at the tip, base frame
        tau = core.profile.jacobian(q).T @ wrench
        r = ArmReading(q.copy(), np.zeros(6), np.zeros(6), core.profile, tau)
        q = core.control(i * 0.001, r)
        core.after_period(i + 1, r)
    assert fk(OVER_TORSO)[2, 3] - fk(q)[2, 3] > 0.02  # the push moved it down
    assert depth_in_box(q) == 0.0
