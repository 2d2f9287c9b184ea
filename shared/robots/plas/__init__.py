"""The PLAS slave (Shim 2015): two Y-type arms in one body, driven joint to joint.

Registers robot ``plas`` (README.md beside this file): arms ``arm1``/``arm2``, joints ``d1 theta2
theta3 theta4 d5 theta6``, controlled point the arm's tip in the port frame. Mapping modes
``all_joints`` (master joints → slave joints, Table 6) and the generic ``position``; no slave-side
motion. Knobs: :class:`~telesurg.shared.robots.plas.config.PlasConfig`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.errors import KinematicsError
from telesurg.shared.robots.plas.config import PlasConfig
from telesurg.shared.robots.registry import ArmProfile, FloatArray, RobotSpec, Sketch, register, two_arms

if TYPE_CHECKING:
    from telesurg.shared.robots.api import MappingStrategy, PairContext

HERE = Path(__file__).resolve().parent

#: PLAS joint speeds (the thesis gives none): 50 mm/s for the slides, 2 rad/s for the joints.
PLAS_MAX_VELOCITY = (0.05, 2.0, 2.0, 2.0, 0.05, 2.0)


def _plas_arm(arm: str) -> ArmProfile:
    from telesurg.shared.robots.plas.kinematics import PLAS_SLAVE
    from telesurg.shared.robots.plas.layout import arm_jacobian, arm_tip_pose

    def pose(q: FloatArray) -> FloatArray:
        return arm_tip_pose(arm, q)

    def jacobian(q: FloatArray) -> FloatArray:
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


def _plas_sketch(arm: str, q: FloatArray) -> Sketch:
    """The DH chain of :class:`~telesurg.shared.robots.plas.kinematics.PlasSlaveGeometry` placed by
    :func:`~telesurg.shared.robots.plas.layout.arm_base`: the shaft channel from the skin down
    to the arm base, the chain up to the pitch axis; the forceps (pillar) from the pitch axis to
    the tip (= :func:`~telesurg.shared.robots.plas.layout.arm_tip`)."""
    from telesurg.shared.robots.plas.kinematics import PLAS_SLAVE
    from telesurg.shared.robots.plas.layout import arm_base

    if len(q) != 6:
        raise KinematicsError(f"plas arm needs 6 joints, got {len(q)}")
    T = arm_base(arm)
    skin = T[:3, 3].copy()
    skin[2] = 0.0  # the channel enters the port at the skin, straight above the arm base
    points = [skin, T[:3, 3].copy()]
    for row, qi in zip(PLAS_SLAVE.dh, q, strict=True):
        T = T @ row.transform(float(qi))
        if np.linalg.norm(T[:3, 3] - points[-1]) > 1e-9:
            points.append(T[:3, 3].copy())
    pts = np.asarray(points)
    return Sketch(pts[:-1], pts[-2:], None)


def _all_joints(gate: PairContext) -> MappingStrategy:
    """The ``all_joints`` mapping (:mod:`.mapping`)."""
    from telesurg.shared.robots.plas.mapping import AllJointsMapping

    return AllJointsMapping(gate)


register(
    RobotSpec(
        "plas",
        two_arms(_plas_arm),
        HERE / "scene.xml",
        ("all_joints", "position"),
        "joint",
        _plas_sketch,
        "two-arm Y-type PLAS slave (Shim 2015)",
        strategies={"all_joints": _all_joints},
        config=PlasConfig,
    )
)
