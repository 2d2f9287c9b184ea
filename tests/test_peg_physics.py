"""Peg transfer with the two-arm robots' graspers: real friction grasps in MuJoCo.

The ``vip`` and ``plas`` robots carry jaws (robot.xml: two fingers on slide joints, one position
servo per arm, ``armN_jaw``, actuator group 2) and ship a peg-transfer scene, ``scene_pegs.xml``: a
peg (a 6 mm x 15 mm cylinder of 2 g, a free body) on a start pad on arm1's side, a target pad on
arm2's side, and the handover point between them (sites ``peg_start``, ``peg_target``,
``peg_handover``). Everything here goes through :class:`MujocoBackend` as an operator's script
would: joint commands from a damped-least-squares IK on each arm's jaw centre (the controlled
point's :class:`~telesurg.shared.robots.registry.ArmProfile` pose and Jacobian, the jaw centre a
fixed offset along the tool), ``command_tool`` for the jaws, and ``read_scene`` for what the
operator sees: where the peg is, who holds it, whether the instruments touch. Nothing attaches the
peg to a jaw: it is held by the fingers' friction or falls.

What a user notices, and the tests check: arm1 picks the peg up, lifts it and carries it at a
human speed without losing it; arm2 takes it over (both hold it, then only arm2); arm2 sets it
down upright on the target and lets go; the instruments never touch each other on the way, and
when driven into each other they do (and it is reported); opening the jaws mid-carry drops the
peg onto the board.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import mujoco
import numpy as np
import pytest
from telesurg.services.slave_control.backends import MujocoBackend, SceneReading
from telesurg.services.slave_control.models import model_path
from telesurg.shared import robots
from telesurg.shared.errors import ConfigError

SCENE = "scene_pegs.xml"
HALF_HEIGHT = 0.0075  # m, the peg's half height (15 mm tall)
TOP_GRIP = 0.002  # m, arm1 grips with its jaw centre this far below the peg's top
LOW_GRIP = 0.004  # m, arm2 grips with its jaw centre this far above the peg's bottom
ABOVE = 0.025  # m, arm1's approach: its jaw centre this high above the grasp
LIFT = 0.020  # m, arm1 lifts the peg this much before the carry (and the handover is this high)
CARRY = 0.030  # m/s, mean jaw speed of a carry (minimum-jerk: the peak is 1.875 x this)
TICK = 2  # physics steps (1 ms) per operator command
EZ = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Layout:
    """How an operator moves one robot's jaws in its pegs scene (README, "The pegs scene").

    ``jaw_offset``: the jaw centre is this far from the controlled point along −z of its site's
    frame (``armN_wrist`` / ``armN_tip``); ``vip``: the tool points along −z of that frame and
    the jaws close along its y (plas: along +z, closing along x). ``tilt1``/``tilt2``: each arm's
    tool angle from straight down (deg) while it holds the peg: constant, with the closing
    direction horizontal, so the held peg stays upright. ``seed1``: arm1's joints above the peg;
    ``seed2``: arm2's joints at its grasp on the handover.
    """

    robot: str
    jaw_offset: float
    vip: bool
    tilt1: float
    tilt2: float
    seed1: tuple[float, ...]
    seed2: tuple[float, ...]


LAYOUTS = {
    "vip": Layout(
        robot="vip",
        jaw_offset=0.012,
        vip=True,
        tilt1=5.0,
        tilt2=62.0,
        seed1=(0.3426, 0.7962, -0.1030, 1.2215, 0.3029),
        seed2=(0.5177, 0.4164, -0.1504, 1.3898, 1.2892),
    ),
    "plas": Layout(
        robot="plas",
        jaw_offset=0.0045,
        vip=False,
        tilt1=40.0,
        tilt2=70.0,
        seed1=(0.0558, 0.6979, 0.7282, 0.6855, 0.0061, -1.3446),
        seed2=(0.0744, 1.4235, 1.2427, -0.7268, 0.0046, -0.3295),
    ),
}


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class Operator:
    """A scripted operator of both arms of one robot in its pegs scene."""

    def __init__(self, layout: Layout, backend: MujocoBackend) -> None:
        self.lay, self.b = layout, backend
        spec = robots.get(layout.robot)
        self.arms = {a: spec.arm(a) for a in ("arm1", "arm2")}
        names = backend.joint_names
        self.idx = {a: np.array([names.index(j) for j in p.model_joints]) for a, p in self.arms.items()}
        self.q_cmd = backend.read().position.copy()
        self.contact_seen = False  # instrument_contact ever True
        self.ticks = 0
        self.scene = backend.read_scene()
        self.track: list[tuple[float, SceneReading]] = []  # (sim time, reading) of every tick

    # -- kinematics of the jaws
    def q(self, arm: str) -> np.ndarray:
        out: np.ndarray = self.q_cmd[self.idx[arm]]
        return out

    def jaw(self, arm: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Jaw centre (m), tool direction and closing direction (unit) at the commanded joints."""
        T = self.arms[arm].pose(self.q(arm))
        R = T[:3, :3]
        a = -R[:, 2] if self.lay.vip else R[:, 2]
        c = R[:, 1] if self.lay.vip else R[:, 0]
        return T[:3, 3] - self.lay.jaw_offset * R[:, 2], a, c

    def measured_jaw(self, arm: str) -> np.ndarray:
        """Jaw centre (m) at the measured joints."""
        T = self.arms[arm].pose(self.b.read().position[self.idx[arm]])
        out: np.ndarray = T[:3, 3] - self.lay.jaw_offset * T[:3, 2]
        return out

    def ik(self, arm: str, target: np.ndarray, tilt_deg: float, iters: int = 1) -> None:
        """Damped least squares on the jaw centre (3), the tool's tilt from straight down (1) and a
        horizontal closing direction (1); the redundancy (plas) keeps the joints off their limits."""
        prof, q = self.arms[arm], self.q(arm).copy()
        lo, hi = np.array(prof.lower), np.array(prof.upper)
        cos_t, w = math.cos(math.radians(tilt_deg)), 0.02  # w: m per unit of the direction rows
        for _ in range(iters):
            T, J = prof.pose(q), prof.jacobian(q)
            R, Jv, Jw = T[:3, :3], J[:3], J[3:]
            r = -self.lay.jaw_offset * R[:, 2]  # site → jaw centre
            a = -R[:, 2] if self.lay.vip else R[:, 2]
            c = R[:, 1] if self.lay.vip else R[:, 0]
            # d(cos tilt)/dt = -(ω × a)·z = -ω·(a × z); d(c_z)/dt = ω·(c × z); (v × z = (v_y, -v_x, 0))
            a_z, c_z = np.array([a[1], -a[0], 0.0]), np.array([c[1], -c[0], 0.0])
            A = np.vstack([Jv - _skew(r) @ Jw, -w * (a_z @ Jw), w * (c_z @ Jw)])
            e = np.concatenate([target - (T[:3, 3] + r), [w * (cos_t + a[2]), -w * c[2]]])
            pinv = A.T @ np.linalg.inv(A @ A.T + 1e-8 * np.eye(len(e)))
            # the redundancy (plas: 6 joints, 5 tasks) pushes the joints within 20 % of a limit back
            span = hi - lo
            near = np.clip(0.2 - np.minimum(q - lo, hi - q) / span, 0.0, None)
            dq = pinv @ e + (np.eye(len(q)) - pinv @ A) @ (near * np.sign((lo + hi) / 2 - q) * span)
            q = np.clip(q + dq, lo, hi)
        self.q_cmd[self.idx[arm]] = q

    # -- time
    def tick(self) -> SceneReading:
        self.b.command(self.q_cmd)
        self.b.step(TICK)
        s = self.b.read_scene()
        self.contact_seen |= s.instrument_contact
        self.ticks += 1
        self.track.append((self.ticks * TICK * self.b.dt, s))
        self.scene = s
        return s

    def wait(self, seconds: float) -> SceneReading:
        for _ in range(round(seconds / (TICK * self.b.dt))):
            self.tick()
        return self.scene

    def move(self, arm: str, goal: np.ndarray, tilt_deg: float, speed: float = CARRY) -> SceneReading:
        """The jaw centre to ``goal`` on a straight minimum-jerk path, mean ``speed`` m/s."""
        start = self.jaw(arm)[0]
        n = max(10, round(float(np.linalg.norm(goal - start)) / speed / (TICK * self.b.dt)))
        for k in range(1, n + 1):
            s = k / n
            self.ik(arm, start + (10 * s**3 - 15 * s**4 + 6 * s**5) * (goal - start), tilt_deg)
            self.tick()
        return self.scene

    def joint_move(self, arm: str, q_goal: tuple[float, ...], seconds: float) -> None:
        q0 = self.q(arm).copy()
        n = round(seconds / (TICK * self.b.dt))
        for k in range(1, n + 1):
            s = k / n
            self.q_cmd[self.idx[arm]] = q0 + (10 * s**3 - 15 * s**4 + 6 * s**5) * (np.array(q_goal) - q0)
            self.tick()

    # -- the task's steps
    def peg(self) -> np.ndarray:
        out: np.ndarray = self.scene.positions[0].copy()
        return out

    def ready_arm2(self) -> None:
        """arm2 to its grasp of the handover, held back 15 mm along its tool, jaws open."""
        lay = self.lay
        self.joint_move("arm2", lay.seed2, 0.8)
        grasp, tool, _ = self.jaw("arm2")
        self.move("arm2", grasp - 0.015 * tool, lay.tilt2)

    def pick(self) -> np.ndarray:
        """arm1 over the peg, down, jaws closed, peg lifted by LIFT; returns the peg's start."""
        lay, start = self.lay, self.peg()
        grasp = start + (HALF_HEIGHT - TOP_GRIP) * EZ
        self.joint_move("arm1", lay.seed1, 0.8)
        self.ik("arm1", grasp + ABOVE * EZ, lay.tilt1, iters=10)
        self.move("arm1", grasp, lay.tilt1)
        self.b.command_tool("arm1_jaw", 1.0)
        self.wait(0.3)
        self.move("arm1", grasp + LIFT * EZ, lay.tilt1)
        return start


def _upright(quat_xyzw: np.ndarray) -> float:
    """Angle (deg) of the peg's axis from vertical."""
    x, y, _, _ = quat_xyzw
    return math.degrees(math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (x * x + y * y)))))


@pytest.fixture(params=sorted(LAYOUTS))
def operator(request: pytest.FixtureRequest) -> Iterator[Operator]:
    lay = LAYOUTS[request.param]
    sites = tuple(p.tip_site for p in robots.arms_of(lay.robot))
    with MujocoBackend(lay.robot, (), sites, scene=SCENE) as b:
        yield Operator(lay, b)


@functools.cache
def _marks(robot: str) -> dict[str, np.ndarray]:
    """The scene's marks (sites on the world body): the pads' centres on the board, the handover."""
    m = mujoco.MjModel.from_xml_path(str(model_path(robot, SCENE)))
    return {n: np.array(m.site(n).pos) for n in ("peg_start", "peg_target", "peg_handover")}


def _site(op: Operator, name: str) -> np.ndarray:
    return _marks(op.lay.robot)[name].copy()


# ----------------------------------------------------------------------------------------------
# The backend's tool API
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("robot", sorted(LAYOUTS))
def test_the_jaws_are_tools_not_arm_joints(robot: str) -> None:
    """The graspers are tools (their own commands, their closure in read_scene); the arm's joints,
    its commands and its reading are the arm joints only, in the registry's order."""
    arms = robots.arms_of(robot)
    with MujocoBackend(robot, (), tuple(p.tip_site for p in arms), scene=SCENE) as b:
        assert b.tool_names == ("arm1_jaw", "arm2_jaw")
        assert b.joint_names == tuple(j for p in arms for j in p.model_joints)
        r = b.read()
        assert r.position.shape == r.velocity.shape == r.effort.shape == (len(b.joint_names),)
        s = b.read_scene()
        assert s.objects == ("peg",) and s.held_by == ((),) and s.tools == {"arm1_jaw": 0.0, "arm2_jaw": 0.0}
        b.command_tool("arm2_jaw", 7.0)  # clipped: fully closed
        b.command(r.position)  # an arm command leaves the jaws as they are
        b.step(150)
        s = b.read_scene()
        assert s.tools["arm2_jaw"] == pytest.approx(1.0, abs=1e-3)
        assert s.tools["arm1_jaw"] == pytest.approx(0.0, abs=1e-6)
        b.command_tool("arm2_jaw", 0.5)  # half closed: half the stroke
        b.step(150)
        assert b.read_scene().tools["arm2_jaw"] == pytest.approx(0.5, abs=1e-3)
        with pytest.raises(ConfigError, match=r"no tool 'arm3_jaw'; valid: arm1_jaw, arm2_jaw"):
            b.command_tool("arm3_jaw", 1.0)
        with pytest.raises(ConfigError, match="grip"):
            b.command_tool("arm1_jaw", float("nan"))


def test_a_robot_without_tools_has_none() -> None:
    profile = robots.arm_profile("mh3f", "arm1")
    with MujocoBackend("mh3f", profile.home) as b:
        assert b.tool_names == ()
        assert b.joint_names == profile.model_joints
        s = b.read_scene()
        assert s.objects == () and s.positions.shape == (0, 3) and s.tools == {}
        assert not s.instrument_contact
        with pytest.raises(ConfigError, match="valid: none"):
            b.command_tool("arm1_jaw", 1.0)


def test_the_peg_rests_still_until_touched(operator: Operator) -> None:
    start = operator.peg()
    np.testing.assert_allclose(start[:2], _site(operator, "peg_start")[:2], atol=1e-9)
    operator.wait(1.0)
    s = operator.scene
    assert np.linalg.norm(s.positions[0] - start) < 5e-5  # settled on the board, no drift
    assert _upright(s.quats[0]) < 0.01 and s.held_by == ((),)
    later = operator.wait(0.5).positions[0]
    assert np.linalg.norm(later - s.positions[0]) < 1e-7  # no jitter


# ----------------------------------------------------------------------------------------------
# The peg transfer
# ----------------------------------------------------------------------------------------------


def test_peg_transfer_hand_over_and_place(operator: Operator) -> None:
    """arm1 picks the peg, carries it to the handover at a human speed, arm2 takes it, arm1 lets go
    and withdraws, arm2 sets it down upright on the target and lets go; the instruments never
    touch each other."""
    op, lay = operator, operator.lay
    handover, target = _site(op, "peg_handover"), _site(op, "peg_target")

    op.ready_arm2()
    start = op.pick()
    s = op.scene
    assert s.held_by == (("arm1",),)
    assert 0.2 < s.tools["arm1_jaw"] < 0.6  # the jaws stopped on the peg (0.33: a 6 mm peg in 9 mm)
    assert op.peg()[2] - start[2] >= 0.015  # lifted

    # the carry to the handover: held all the way, at a human speed, without slipping
    grip = op.peg() - op.jaw("arm1")[0]
    n0 = len(op.track)
    op.move("arm1", handover + (HALF_HEIGHT - TOP_GRIP) * EZ, lay.tilt1)
    op.wait(0.2)
    carry = op.track[n0:]
    assert all(r.held_by == (("arm1",),) for _, r in carry)
    times = np.array([t for t, _ in carry])
    path = np.array([r.positions[0] for _, r in carry])
    speed = np.linalg.norm(np.diff(path, axis=0), axis=1) / np.diff(times)
    assert 0.04 < speed.max() < 0.08  # m/s: a human hand's pace (mean 30 mm/s)
    assert np.linalg.norm(op.peg() - op.jaw("arm1")[0] - grip) < 5e-4  # slipped < 0.5 mm
    assert np.linalg.norm(op.peg() - handover) < 1e-3

    # arm2 takes it: into its grasp along its own tool axis, jaws closed: both hold it
    grasp2 = op.peg() - (HALF_HEIGHT - LOW_GRIP) * EZ
    op.move("arm2", grasp2, lay.tilt2, speed=0.02)
    op.b.command_tool("arm2_jaw", 1.0)
    assert op.wait(0.3).held_by == (("arm1", "arm2"),)
    # arm1 lets go and withdraws upwards: arm2 alone holds it, where it was
    before = op.peg()
    op.b.command_tool("arm1_jaw", 0.0)
    assert op.wait(0.3).held_by == (("arm2",),)
    op.move("arm1", op.jaw("arm1")[0] + 0.015 * EZ, lay.tilt1)
    assert op.scene.held_by == (("arm2",),) and op.scene.tools["arm1_jaw"] < 0.02
    assert np.linalg.norm(op.peg() - before) < 1e-3

    # arm2 carries it to the target and sets it down on the board
    place = target + (HALF_HEIGHT + 0.0005 - (HALF_HEIGHT - LOW_GRIP)) * EZ  # 0.5 mm above the board
    n0 = len(op.track)
    op.move("arm2", place + LIFT * EZ, lay.tilt2)
    carry = op.track[n0:]
    assert all(r.held_by == (("arm2",),) for _, r in carry)
    assert max(_upright(r.quats[0]) for _, r in carry) < 2.0  # carried upright
    op.move("arm2", place, lay.tilt2, speed=0.02)
    op.wait(0.1)
    op.b.command_tool("arm2_jaw", 0.0)
    op.wait(0.3)
    op.move("arm2", op.jaw("arm2")[0] - 0.010 * op.jaw("arm2")[1] + 0.010 * EZ, lay.tilt2)
    s = op.wait(0.5)

    assert s.held_by == ((),)
    assert np.linalg.norm((s.positions[0] - target)[:2]) < 0.005  # on the target
    assert abs(s.positions[0][2] - (target[2] + HALF_HEIGHT)) < 2e-4  # standing on the board
    assert _upright(s.quats[0]) < 5.0
    assert not op.contact_seen  # the instruments never touched each other


def test_opening_the_jaws_mid_carry_drops_the_peg(operator: Operator) -> None:
    op, lay = operator, operator.lay
    start = op.pick()
    mid = (op.peg() + _site(op, "peg_handover")) / 2 + (HALF_HEIGHT - TOP_GRIP) * EZ
    op.move("arm1", mid, lay.tilt1)
    held = op.peg()
    assert op.scene.held_by == (("arm1",),) and held[2] - start[2] > 0.015
    op.b.command_tool("arm1_jaw", 0.0)
    assert op.wait(0.1).held_by == ((),)
    s = op.wait(0.5)
    assert s.held_by == ((),)
    assert s.positions[0][2] < held[2] - 0.01  # it fell (onto the board, maybe on its side)
    assert s.positions[0][2] < start[2] + 0.002
    # and it stays where it fell: no rolling away across the board (rolling friction)
    later = op.wait(1.0).positions[0]
    assert np.linalg.norm(later - s.positions[0]) < 1e-3


def test_instruments_driven_into_each_other_touch(operator: Operator) -> None:
    """arm2 waits at the handover; arm1's jaws driven through the place where arm2's are run into
    them: the contact is reported (never before) and arm2's instrument holds arm1's back."""
    op, lay = operator, operator.lay
    op.joint_move("arm2", lay.seed2, 0.8)
    op.joint_move("arm1", lay.seed1, 0.8)
    assert not op.contact_seen
    path = op.jaw("arm2")[0] - op.jaw("arm1")[0]
    op.move("arm1", op.jaw("arm1")[0] + 1.3 * path, lay.tilt1, speed=0.04)
    op.wait(0.2)
    assert op.contact_seen and op.scene.instrument_contact
    # physical: arm1's jaws stop short of where they are commanded (free, they track to < 0.01 mm)
    assert np.linalg.norm(op.measured_jaw("arm1") - op.jaw("arm1")[0]) > 3e-4
    assert op.scene.positions[0][2] < _site(op, "peg_start")[2] + HALF_HEIGHT + 1e-3  # the peg untouched
    # both instruments feel the push, equal and opposite: the pressing arm is stopped by the same
    # force limit as the arm it presses
    w = op.b.read().site_wrenches
    assert w is not None
    f1, f2 = (w[p.tip_site][:3] for p in op.arms.values())
    assert np.linalg.norm(f1) > 0.5, (f1, f2)
    np.testing.assert_allclose(f1, -f2, atol=0.05 * np.linalg.norm(f1))
