"""Robot plugin ``reach3``: a 3-DoF arm with its own Cartesian mapping and a go-home motion.

``--plugin tests/robots/reach3/reach3.py`` registers it; everything it needs is in this folder and
``telesurg.shared`` (tests/test_robot_folder.py drives it through the real services).

* **Arm** ``arm1`` (any arm id): yaw ``q1`` about z, shoulder ``q2`` and elbow ``q3`` about the
  yawed y axis; links ``H`` (base height), ``L2``, ``L3`` [m]; controlled point the forearm's end
  (site ``tip``), frame the scene's world (= base) frame.
* **Mapping** ``reach`` (:class:`ReachMapping`): master tip increments → tip position, solved by
  this arm's closed-form IK (:func:`ik`, elbow-down branch) instead of the generic damped least
  squares; the orientation is not controlled. A target out of reach or limits holds the last
  setpoint (``ik_failure`` event).
* **Motion** ``go_home`` (:class:`GoHome`, command on ``slave/<arm>/command``): with the clutch
  released and the lease valid, the joints move straight to ``HOME`` at ``home_speed_rad_s``; event
  ``go_home_done`` when there.
* **Knobs** (:class:`Reach3Config`, the ``robot`` table): ``home_speed_rad_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
from telesurg.shared import robots
from telesurg.shared.errors import ConfigError, IKError
from telesurg.shared.messages import Command, CommandReply
from telesurg.shared.robots.api import ArmReading, AttachedSource, MotionContext, PairContext
from telesurg.shared.robots.joint_mapping import PoseJointStrategy
from telesurg.shared.robots.registry import ArmProfile, RobotSpec, Sketch

HERE = Path(__file__).resolve().parent
H, L2, L3 = 0.10, 0.20, 0.15  # m
JOINTS = ("q1", "q2", "q3")
LOWER = (-2.5, -1.5, 0.2)
UPPER = (2.5, 1.0, 2.6)
HOME = (0.0, -0.5, 1.2)

F = npt.NDArray[np.float64]


@dataclass
class Reach3Config:
    """reach3 config (the ``robot`` table)."""

    home_speed_rad_s: float = 0.5  # rad/s: joint speed of go_home

    def __post_init__(self) -> None:
        if not 0.0 < self.home_speed_rad_s <= 1.5:
            raise ConfigError(f"home_speed_rad_s={self.home_speed_rad_s} outside (0, 1.5]")


# --------------------------------------------------------------------------- kinematics


def _rz(a: float) -> F:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> F:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def points(q: F) -> tuple[F, F, F, F, F]:
    """(base, shoulder, elbow, tip positions, tip rotation) [m], world frame."""
    if np.shape(q) != (3,):
        raise ValueError(f"reach3 needs 3 joints, got {np.shape(q)}")
    r2 = _rz(float(q[0])) @ _ry(float(q[1]))
    r3 = r2 @ _ry(float(q[2]))
    shoulder = np.array([0.0, 0.0, H])
    elbow = shoulder + L2 * r2[:, 0]
    return np.zeros(3), shoulder, elbow, elbow + L3 * r3[:, 0], r3


def pose(q: F) -> F:
    *_, tip, rot = points(q)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, tip
    return T


def jacobian(q: F) -> F:
    _, shoulder, elbow, tip, _ = points(q)
    z, y = np.array([0.0, 0.0, 1.0]), _rz(float(q[0]))[:, 1]
    axes, through = (z, y, y), (np.zeros(3), shoulder, elbow)
    return np.column_stack(
        [np.concatenate([np.cross(a, tip - p), a]) for a, p in zip(axes, through, strict=True)]
    )


def ik(p: F) -> F:
    """Joints putting the tip at ``p`` [m] (the elbow-down branch, ``q3 > 0``).

    In the yawed plane the tip is ``(L2 cos q2 + L3 cos(q2 + q3), H − L2 sin q2 − L3 sin(q2 + q3))``.

    Raises:
        IKError: out of reach or outside the joint limits.
    """
    x, y, z = (float(v) for v in p)
    q1 = math.atan2(y, x)
    r, h = math.hypot(x, y), H - z  # the planar target, h downward
    c3 = (r * r + h * h - L2 * L2 - L3 * L3) / (2.0 * L2 * L3)
    if not -1.0 <= c3 <= 1.0:
        raise IKError(f"target {np.round(np.asarray(p) * 1e3, 1).tolist()} mm out of reach")
    q3 = math.acos(c3)
    q2 = math.atan2(h, r) - math.atan2(L3 * math.sin(q3), L2 + L3 * c3)
    q = np.array([q1, q2, q3])
    if not all(lo <= v <= hi for v, lo, hi in zip(q.tolist(), LOWER, UPPER, strict=True)):
        raise IKError(f"target needs joints {np.round(q, 3).tolist()} outside the limits")
    return q


def arms(arm: str) -> tuple[ArmProfile, ...]:
    return (ArmProfile(arm, JOINTS, JOINTS, LOWER, UPPER, (1.5, 1.5, 1.5), HOME, "tip", pose, jacobian),)


def sketch(arm: str, q: F) -> Sketch:
    base, shoulder, elbow, tip, _ = points(np.asarray(q, dtype=np.float64))
    return Sketch(np.stack([base, shoulder, elbow, tip]), None, None)


# --------------------------------------------------------------------------- the mapping


class ReachMapping(PoseJointStrategy):
    """Master tip increments → tip position → closed-form IK (see the module docstring)."""

    def on_command(self, cmd: Command) -> CommandReply:
        """``state`` and the operator's scale commands."""
        return self.gate.scale_command(cmd, "reach mapping, ")

    def _engaged(self) -> None:
        self.ref = self.last = None  # anchored at the next master sample

    def process(self) -> None:
        g = self.gate
        with g.lock:
            msg, self.pending = self.pending, None
            if g.want_engage and not g.following:
                self._try_engage()
            if msg is None:
                return
            if g.following and self.q_cmd is not None:
                pm = self.master_point(g.cfg, msg.position)
                if self.ref is None:
                    self.ref = (pm, self.profile.tip(self.q_cmd))
                pm0, p0 = self.ref
                target = p0 + g.scale * g.safety_scale * (self.r_ms @ (pm - pm0))
                try:
                    self.q_cmd = ik(target)
                    self.last = (pm, target)
                except IKError as exc:
                    g.ik_failures += 1
                    if g.ik_failures == 1:
                        g.node.event("ik_failure", f"holding: {exc}", arm=g.slave, severity="warning")
            self._put(msg.header.stamp_ns)


# --------------------------------------------------------------------------- the motion


class GoHome(AttachedSource):
    """``go_home``: the joints straight to :data:`HOME` at ``home_speed_rad_s`` (a motion source)."""

    control_mode = "joint"

    def __init__(self, profile: ArmProfile, speed_rad_s: float) -> None:
        self.profile, self.speed = profile, speed_rad_s
        self.target: F | None = None

    def active(self) -> bool:
        return self.target is not None

    def blocks_following(self) -> str:
        return "going home" if self.target is not None else ""

    def next(self, q_cmd: F, reading: ArmReading, dt: float) -> F:
        target = self.target
        if target is None:
            return q_cmd
        step = target - q_cmd
        n = float(np.max(np.abs(step)))
        limit = self.speed * dt
        return target.copy() if n <= limit else q_cmd + step * (limit / n)

    def reached(self, q_out: F, reading: ArmReading) -> None:
        if self.target is not None and float(np.max(np.abs(q_out - self.target))) < 1e-9:
            self.target = None
            self._core.event("go_home_done", "at home")

    def stop(self, reason: str) -> None:
        self.target = None

    def braking(self, q_cmd: F, dt: float, allowed: bool) -> F | None:
        return None

    def measure(self, reading: ArmReading, q_cmd: F) -> None:
        return None

    def follow_keepout(self, q_from: F, q_to: F) -> tuple[F, str]:
        return q_to, ""

    def command(self, cmd: Command) -> tuple[bool, str]:
        core = self._core
        with core.lock:
            if cmd.name == "state":
                return True, "going home" if self.target is not None else "idle"
            if cmd.name != "go_home":
                return False, f"unknown command {cmd.name!r}; valid: state, go_home"
            if core.estop:
                return False, f"go_home refused: {core.estop}"
            if core.ctl.following:
                return False, "go_home refused: the arm follows the master (release the clutch first)"
            if not core.ctl.lease_valid:
                return False, f"go_home refused: the slave may not move ({core.ctl.reason or 'no lease'})"
            self.target = np.array(HOME)
        return True, "going home"

    def state_fields(self) -> tuple[float, tuple[float, float, float]]:
        return 0.0, (0.0, 0.0, 0.0)


def _mapping(gate: PairContext) -> ReachMapping:
    return ReachMapping(gate)


def _motions(ctx: MotionContext) -> GoHome:
    cfg: Reach3Config = robots.get("reach3").make_config(ctx.cfg.robot)
    return GoHome(ctx.profile, cfg.home_speed_rad_s)


robots.register(
    RobotSpec(
        name="reach3",
        arms=arms,
        scene=HERE / "scene.xml",
        mapping_modes=("reach", "position"),
        slave_family="joint",
        sketch=sketch,
        description="3-DoF test arm with its own closed-form mapping and a go-home motion",
        config=Reach3Config,
        strategies={"reach": _mapping},
        motions=_motions,
    )
)
