"""Robot profiles: which arms a slave model has and what the services need to know about each.

One profile per MuJoCo model in ``services/slave_control/models``. slave_control uses it to split
the model's joints into arms (``slave/<arm>/…`` streams carry the arm's own joint names), the
watchdog to check setpoints (joint limits, speed limits, workspace by forward kinematics), the
mapping to pick its IK. Pure and cheap: the kinematics modules are imported on first use.

* ``mh3f`` — one MOTOMAN-MH3F class 6-axis arm with straight forceps (Jinno 2014); the arm id is
  configurable (default ``arm1``), the tip is the forceps tip.
* ``plas`` — the two-arm Y-type PLAS slave (Shim 2015), arms ``arm1``/``arm2`` with joints
  ``d1 theta2 theta3 theta4 d5 theta6``; the tip is the arm's tip in the port frame.
* ``vip`` — two conical-RCM arms with an elbow (Jang 2014), arms ``arm1``/``arm2`` with joints
  ``q1 … q5``; the "tip" is the wrist W (the controlled point), port frame.

Frame convention (one for every robot): :meth:`ArmProfile.pose` is the pose ``(4, 4)`` of the
arm's controlled point in the **world frame of the robot's MuJoCo scene**, equal to the pose of
the MuJoCo site :attr:`ArmProfile.tip_site` (``site_xpos``, ``site_xmat``), with its real
orientation (the site's axes). :meth:`ArmProfile.jacobian` is the geometric Jacobian ``(6, n)``
of that point in the same frame: ``[v; ω] = J @ qdot``, rows ``v`` (the controlled point's
linear velocity, m/s) then ``ω`` (the site frame's angular velocity, rad/s), world coordinates;
``qdot`` in rad/s (m/s for prismatic joints). For ``mh3f`` the world frame is the robot base
frame (the model puts the base at the world origin); for ``plas`` and ``vip`` it is the port frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import ConfigError

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ArmProfile:
    """One arm of a robot model.

    Attributes:
        arm: arm id used in keys (``slave/<arm>/…``).
        joint_names: the arm's joint names in messages.
        model_joints: the same joints' names in the MuJoCo model.
        lower, upper: joint limits (rad, or m for prismatic joints).
        max_velocity: joint speed limits (rad/s or m/s).
        home: start pose.
        tip_site: MuJoCo site of the controlled point.
        pose_of: joints ``(n,)`` → pose ``(4, 4)`` of the controlled point (module docstring).
        jacobian_of: joints ``(n,)`` → geometric Jacobian ``(6, n)`` (module docstring).
    """

    arm: str
    joint_names: tuple[str, ...]
    model_joints: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_velocity: tuple[float, ...]
    home: tuple[float, ...]
    tip_site: str
    pose_of: Callable[[np.ndarray], np.ndarray]
    jacobian_of: Callable[[np.ndarray], np.ndarray]

    def pose(self, q: npt.ArrayLike) -> FloatArray:
        """Pose ``(4, 4)`` of the controlled point (world frame of the scene, = the tip site)."""
        return np.asarray(self.pose_of(np.asarray(q, dtype=np.float64)), dtype=np.float64)

    def jacobian(self, q: npt.ArrayLike) -> FloatArray:
        """Geometric Jacobian ``(6, n)`` of :meth:`pose`: ``[v; ω] = J @ qdot`` (world frame)."""
        return np.asarray(self.jacobian_of(np.asarray(q, dtype=np.float64)), dtype=np.float64)

    def tip(self, q: npt.ArrayLike) -> FloatArray:
        """Position ``(3,)`` [m] of the controlled point (world frame of the scene)."""
        out: FloatArray = self.pose(q)[:3, 3].copy()
        return out


def _mh3f(arm: str) -> tuple[ArmProfile, ...]:
    from telesurg.shared.kinematics import mh3f

    def pose(q: np.ndarray) -> np.ndarray:
        return mh3f.fk(q, mh3f.MH3F)

    def jacobian(q: np.ndarray) -> np.ndarray:
        return mh3f.jacobian(q, mh3f.MH3F)

    home = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    g = mh3f.MH3F
    names = g.joint_names
    return (ArmProfile(arm, names, names, g.lower, g.upper, g.max_velocity, home, "tip", pose, jacobian),)


#: PLAS joint speeds (the thesis gives none): 50 mm/s for the slides, 2 rad/s for the joints.
PLAS_MAX_VELOCITY = (0.05, 2.0, 2.0, 2.0, 0.05, 2.0)
#: VIP arm joint speeds (the paper gives none): 2 rad/s, 0.1 m/s for the prismatic q3.
VIP_MAX_VELOCITY = (2.0, 2.0, 0.1, 2.0, 2.0)


def _plas(arm: str) -> ArmProfile:
    from telesurg.shared.kinematics.plas import PLAS_SLAVE
    from telesurg.shared.kinematics.plas_layout import arm_jacobian, arm_tip_pose

    def pose(q: np.ndarray) -> np.ndarray:
        return arm_tip_pose(arm, q)

    def jacobian(q: np.ndarray) -> np.ndarray:
        return arm_jacobian(arm, q)

    names = PLAS_SLAVE.joint_names
    return ArmProfile(
        arm,
        names,
        tuple(f"{arm}_{n}" for n in names),
        PLAS_SLAVE.lower,
        PLAS_SLAVE.upper,
        PLAS_MAX_VELOCITY,
        (0.0,) * 6,
        f"{arm}_tip",
        pose,
        jacobian,
    )


def _vip(arm: str) -> ArmProfile:
    from telesurg.shared.kinematics import vip

    geom = vip.VIP_ARM1 if arm == "arm1" else vip.VIP_ARM2

    def pose(q: np.ndarray) -> np.ndarray:
        return vip.fk(q, geom).wrist_frame

    def jacobian(q: np.ndarray) -> np.ndarray:
        return vip.wrist_jacobian(q, geom)

    names = geom.joint_names
    return ArmProfile(
        arm,
        names,
        tuple(f"{arm}_{n}" for n in names),
        geom.lower,
        geom.upper,
        VIP_MAX_VELOCITY,
        geom.home,
        f"{arm}_wrist",
        pose,
        jacobian,
    )


MODELS = ("mh3f", "plas", "vip")


@cache
def arms_of(model: str, arm: str = "arm1") -> tuple[ArmProfile, ...]:
    """The arms of ``model`` (``arm``: the id of a single-arm model's arm)."""
    if model == "mh3f":
        return _mh3f(arm)
    if model == "plas":
        return (_plas("arm1"), _plas("arm2"))
    if model == "vip":
        return (_vip("arm1"), _vip("arm2"))
    raise ConfigError(f"robot model {model!r} unknown; valid: {', '.join(MODELS)}")


def arm_profile(model: str, arm: str) -> ArmProfile:
    """The profile of ``arm`` in ``model`` (single-arm models take any arm id)."""
    arms = arms_of(model, arm)
    for a in arms:
        if a.arm == arm:
            return a
    raise ConfigError(f"robot model {model!r} has no arm {arm!r}; arms: {', '.join(a.arm for a in arms)}")
