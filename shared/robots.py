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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache

import numpy as np
from telesurg.shared.errors import ConfigError


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
        tip: joints → controlled point (m, model world frame).
    """

    arm: str
    joint_names: tuple[str, ...]
    model_joints: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_velocity: tuple[float, ...]
    home: tuple[float, ...]
    tip_site: str
    tip: Callable[[np.ndarray], np.ndarray]


def _mh3f(arm: str) -> tuple[ArmProfile, ...]:
    from telesurg.shared.kinematics import MH3F, fk

    def tip(q: np.ndarray) -> np.ndarray:
        out: np.ndarray = fk(q, MH3F)[:3, 3]
        return out

    home = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    names = MH3F.joint_names
    return (ArmProfile(arm, names, names, MH3F.lower, MH3F.upper, MH3F.max_velocity, home, "tip", tip),)


#: PLAS joint speeds (the thesis gives none): 50 mm/s for the slides, 2 rad/s for the joints.
PLAS_MAX_VELOCITY = (0.05, 2.0, 2.0, 2.0, 0.05, 2.0)
#: VIP arm joint speeds (the paper gives none): 2 rad/s, 0.1 m/s for the prismatic q3.
VIP_MAX_VELOCITY = (2.0, 2.0, 0.1, 2.0, 2.0)


def _plas(arm: str) -> ArmProfile:
    from telesurg.shared.kinematics.plas import PLAS_SLAVE
    from telesurg.shared.kinematics.plas_layout import arm_tip

    def tip(q: np.ndarray) -> np.ndarray:
        return arm_tip(arm, q)

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
        tip,
    )


def _vip(arm: str) -> ArmProfile:
    from telesurg.shared.kinematics import vip

    geom = vip.VIP_ARM1 if arm == "arm1" else vip.VIP_ARM2

    def tip(q: np.ndarray) -> np.ndarray:
        out: np.ndarray = vip.fk(q, geom).wrist
        return out

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
        tip,
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
