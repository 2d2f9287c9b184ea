"""Placement of the two PLAS arms in the world frame of the MuJoCo model ``plas``.

:func:`telesurg.shared.robots.plas.kinematics.slave_fk` gives one arm's tip in *its* base frame (``z0``
along the
shaft, pointing into the patient; ``x0`` the direction the arm points at ``θ2 = 0``). The model
``shared/robots/plas`` puts two such arms side by side on one common body (the
insertion part, thesis Fig. 7) that passes through a single port; this module is the fixed
transform of each arm (:data:`ARM_BASES`) and the world-frame tip (:func:`arm_tip`), which equal
the model's ``armN_base`` bodies and ``armN_tip`` sites. The README of the model derives them.

World frame = port frame (as the ``vip`` model): origin at the centre of the incision on the skin,
``z`` up out of the patient, ``x`` toward the patient's head, ``y`` to the patient's left. The
shaft runs down the port axis (``-z``). Each arm's base frame (its joint-2 axis at ``d1 = 0``) is
:data:`ARM_DEPTH` below the skin and :data:`ARM_OFFSET` to the side of the port axis:

* ``arm1``: origin ``(0, -ARM_OFFSET, -ARM_DEPTH)``, ``x0 = -y`` (spreads to the patient's right),
  ``y0 = -x``, ``z0 = -z``; a half turn about ``(1, -1, 0)/√2``.
* ``arm2``: ``arm1`` turned by π about the port axis: origin ``(0, +ARM_OFFSET, -ARM_DEPTH)``,
  ``x0 = +y`` (spreads to the left), ``y0 = +x``, ``z0 = -z``.

Equal joint values on both arms give mirror images in the spread (``y``-``z``) plane for the yaws
θ2, θ3 and the slides d1, d5; the pitch θ4 and roll θ6 of ``arm2`` act in the opposite world sense
(a turn is not a mirror), so the mirror image of ``arm1`` at ``q`` is ``arm2`` at
``(q1, q2, q3, -q4, q5, -q6)``.

There is no common insertion joint (the thesis's robot has 12 DOF, 6 per arm, each with its own
d1). ``insertion`` in :func:`arm_tip` is the depth by which the common body is pushed further down
the port than in the model (``body_pos`` of the model's body ``insertion_part`` at
``(0, 0, -insertion)``): a setup value, 0 in the model.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.plas.kinematics import PLAS_SLAVE, PlasSlaveGeometry, slave_fk, slave_jacobian

__all__ = [
    "ARM_BASES",
    "ARM_DEPTH",
    "ARM_NAMES",
    "ARM_OFFSET",
    "SHAFT_AXIS",
    "arm_base",
    "arm_jacobian",
    "arm_tip",
    "arm_tip_pose",
]

ARM_NAMES: tuple[str, ...] = ("arm1", "arm2")
"""The arms, in the order of the model's joints and actuators."""

ARM_DEPTH = 0.040
"""[m] depth below the skin of both arms' joint-2 axes at ``d1 = 0`` (the distal end of the
common body: through a 20 mm abdominal wall plus 20 mm of clearance)."""

ARM_OFFSET = 0.006
"""[m] distance of each arm's slide axis from the port axis (12 mm between the two channels of
the ~25 mm common body)."""

SHAFT_AXIS: FloatArray = np.array([0.0, 0.0, -1.0], dtype=np.float64)
"""Unit vector of the shaft / insertion direction in the world frame (down the port)."""
SHAFT_AXIS.flags.writeable = False


def _base(rotation: list[list[float]], y: float) -> FloatArray:
    T = np.eye(4, dtype=np.float64)
    T[:3, :3] = rotation
    T[:3, 3] = (0.0, y, -ARM_DEPTH)
    T.flags.writeable = False
    return T


ARM_BASES: dict[str, FloatArray] = {
    "arm1": _base([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], -ARM_OFFSET),
    "arm2": _base([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]], ARM_OFFSET),
}
"""Pose ``(4, 4)`` of each arm's base frame (that of :func:`slave_fk`) in the world frame, with the
common body at ``insertion = 0`` (read-only arrays)."""


def arm_base(arm: str, insertion: float = 0.0) -> FloatArray:
    """Pose ``(4, 4)`` of ``arm``'s base frame in the world frame [m].

    Args:
        arm: ``"arm1"`` or ``"arm2"``.
        insertion: [m] extra depth of the common body along :data:`SHAFT_AXIS` (0 in the model).

    Raises:
        KinematicsError: unknown ``arm`` or non-finite ``insertion``.
    """
    try:
        base = ARM_BASES[arm]
    except KeyError:
        raise KinematicsError(f"unknown arm {arm!r}; valid: {', '.join(ARM_NAMES)}") from None
    if not math.isfinite(insertion):
        raise KinematicsError(f"insertion must be finite [m], got {insertion}")
    T = base.copy()
    T[:3, 3] += insertion * SHAFT_AXIS
    return T


def arm_tip_pose(
    arm: str, q: npt.ArrayLike, insertion: float = 0.0, geom: PlasSlaveGeometry = PLAS_SLAVE
) -> FloatArray:
    """Tip pose ``(4, 4)`` of ``arm`` in the world frame: ``arm_base(arm, insertion) @ slave_fk(q)``.

    Equals the frame of the model's site ``armN_tip``.

    Args:
        arm: ``"arm1"`` or ``"arm2"``.
        q: that arm's joints ``(6,)`` = (d1 [m], θ2, θ3, θ4 [rad], d5 extension [m], θ6 [rad]).
        insertion: [m] extra depth of the common body (see :func:`arm_base`).
        geom: arm dimensions (the model is built with :data:`PLAS_SLAVE`).
    """
    return arm_base(arm, insertion) @ slave_fk(q, geom)


def arm_tip(
    arm: str, q: npt.ArrayLike, insertion: float = 0.0, geom: PlasSlaveGeometry = PLAS_SLAVE
) -> FloatArray:
    """Tip position ``(3,)`` [m] of ``arm`` in the world frame (the model's site ``armN_tip``).

    Args: as :func:`arm_tip_pose`.
    """
    return arm_tip_pose(arm, q, insertion, geom)[:3, 3].copy()


def arm_jacobian(arm: str, q: npt.ArrayLike, geom: PlasSlaveGeometry = PLAS_SLAVE) -> FloatArray:
    """Geometric Jacobian ``(6, 6)`` of :func:`arm_tip_pose` in the world frame.

    ``[v; ω] = J @ qdot`` (:func:`~telesurg.shared.robots.plas.kinematics.slave_jacobian` turned by the
    arm base's fixed rotation; the common body's insertion does not change it).
    """
    R = arm_base(arm)[:3, :3]
    J = slave_jacobian(q, geom)
    return np.vstack([R @ J[:3], R @ J[3:]])
