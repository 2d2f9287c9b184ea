"""PLAS Y-type single-port slave arm, its all-joints ergonomic master, and the Table-6 mapping.

Source: S. Shim, *All Joints Controlling Master Device for Y-Type Single Port Laparoscopic
Surgery Robot*, MS thesis, DGIST 2015 (Tables 1, 3, 4, 5, 6, eqs. 22-29, Section 4).

Units: metres and radians everywhere (the thesis quotes mm and degrees; converted here).

Joints (``q`` is always ``(6,)``, in this order)
------------------------------------------------
==  ===========  =====================================  ======================================
i   slave        what it does (Table 1, Section 2.1)    master (Table 3, Section 2.2)
==  ===========  =====================================  ======================================
1   ``d1``       slide of the arm along the shaft [m]   ``d1``: shoulder slide [m] — an on/off
                                                        switch on the real device
2   ``theta2``   first yaw (triangulation)              ``theta2``: elbow yaw (armrest)
3   ``theta3``   second yaw                             ``theta3``: wrist yaw
4   ``theta4``   pitch                                  ``theta4``: wrist pitch
5   ``d5``       pillar extension [m]                   ``theta5``: wrist roll
6   ``theta6``   roll of the forceps                    ``d6``: finger slide [m]
==  ===========  =====================================  ======================================

Slave joint ``i`` is driven by master joint :data:`MASTER_FOR_SLAVE` ``[i]``: the master's
roll is its joint 5 and its finger slide joint 6, the other way round from the slave.

Reconstructed models (Tables 4, 5) and why the FK follows them
--------------------------------------------------------------
Tables 4 and 5 are modified (Craig) DH tables, row ``i`` = ``Rx(α_{i-1}) Tx(a_{i-1}) Rz(θ_i)
Tz(d_i)``, of the arm from joint 2 to the end effector ("pillar" of the slave, handle of the
master, thesis Fig. 17). They give, in the *arm frame* (origin on the joint-2 axis, ``z`` along
it, ``x`` along the first link at ``θ2 = 0``; the base of Tables 4-5)::

    slave  (eq. 22): p = (C23 (a3 + d5 C4) + a2 C2,  S23 (a3 + d5 C4) + a2 S2,  d5 S4)
    master (Tab. 5): p = (C23 d6 C4 + a2' C2,        S23 d6 C4 + a2' S2,        d6 S4)

with a2 = 50 mm, a3 = 15 mm, d5 = 30 mm, a2' = 138 mm, d6 = 60 mm. Section 4's numbers
(62.5°, 40°, 60°, arcs of 103.6 and 31.4 mm) follow from exactly these formulas, with ``θ = 0``
meaning "the link continues straight".

The full 6-joint FK below is these chains extended by the joints the reconstruction leaves out:

* slave: Table 1 row 1 (``Tz(d1) Rx(π/2)``: the arm slides along the shaft ``z0``, the yaw
  axes are perpendicular to it), Table 4 with the pillar ``d5 + q5`` (Table 1 makes d5 a
  variable; q5 = 0 is the reconstructed 30 mm pillar), then the roll ``Rz(θ6) Tz(d6)``::

      T = Tz(q1) Rx(π/2) Rz(θ2) Tx(a2) Rz(θ3) Rx(π/2) Tx(a3) Rz(θ4 + π/2) Rx(π/2) Tz(d5 + q5)
          Rz(θ6) Tz(d6)

  Table 1 itself (standard DH, ``θ4`` without offset) points the pillar along the yaw axis at
  ``θ4 = 0``; Table 4's ``θ4 + 90°`` offset makes it continue the link. The thesis uses Table
  4's zero, and so does this module (Table 1's ``θ4`` = 90° - this ``θ4``).
* master: Table 3 row 1 (``Tz(d1')``, slide along the joint-2 axis, α1 = 0), Table 5, and
  Table 3 row 6 (handle ``d6 + d6'``)::

      T = Tz(q1) Rz(θ2) Tx(a2') Rz(θ3) Rx(π/2) Rz(θ4 + π/2) Rx(π/2) Rz(θ5) Tz(d6 + q6)

  Table 3 as printed cannot be used as it stands: its twists make joint 3 perpendicular to
  joint 2 (α2 = -π/2), and eq. 5, said to follow from it, puts the wrist pitch before the wrist
  yaw and drops d1', a1 and a5, whose values are never given. Table 5, the text ("joint 2 and
  3 ... elbow and wrist" yaws, "joint 4 as a pitch rotation of wrist") and the Section 4
  numbers agree with each other, so the master is Table 5 (a1 = a5 = 0).

Mapping factors (Table 6, eqs. 27-28)
-------------------------------------
Equating the slave and master tip velocities of eqs. 25 and 26 joint by joint gives
``θ'_slave = f θ'_master`` with ``f2 = (C23 d6 C4 + a2' C2) / (C23 (a3 + d5 C4) + a2 C2)``
(the ratio of the two tips' ``x`` coordinates), ``f3 = d6 C4 / (a3 + d5 C4)``,
``f4 = d6 / d5``; joint 1 is an on/off switch driving d1 at a set speed, joints 5 and 6 are
1:1. The thesis writes one set of angles for both arms; :func:`mapping_factors` evaluates the
angles of the *master* (the operator's input) and the current lengths ``d5 + q5 + d6`` (slave)
and ``d6 + q6`` (master), which at q5 = q6 = 0 is Table 6 verbatim. With equal angles on both
arms, ``v_y`` and ``v_z`` of the two tips then agree and ``v_x`` differs by eq. 29 per unit
``θ'2`` (:func:`eq29_vx_error`); the ``tip_exact`` mode instead solves the slave Jacobian for
the master's tip displacement (damped least squares), which couples the slave joints.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray, rot_x

__all__ = [
    "DEFAULT_D1_SPEED",
    "DEFAULT_DAMPING",
    "DEFAULT_MAX_FACTOR",
    "MASTER_FOR_SLAVE",
    "PLAS_MASTER",
    "PLAS_SLAVE",
    "DHRow",
    "Followed",
    "MappingConfig",
    "MappingMode",
    "MappingStep",
    "PlasMasterGeometry",
    "PlasSlaveGeometry",
    "eq29_vx_error",
    "follow",
    "map_step",
    "mapping_factors",
    "master_arm_jacobian",
    "master_fk",
    "master_jacobian",
    "master_tip_arm",
    "slave_arm_jacobian",
    "slave_fk",
    "slave_jacobian",
    "slave_tip_arm",
    "tip_velocity_error",
]

HALF_PI = 0.5 * math.pi

MASTER_FOR_SLAVE: tuple[int, ...] = (0, 1, 2, 3, 5, 4)
"""Index of the master joint that drives slave joint ``i`` (slave d5 ← master d6', θ6 ← θ5)."""

DEFAULT_D1_SPEED = 0.010
"""Speed [m/s] at which the joint-1 switch drives the slave's d1. The thesis gives no value."""

DEFAULT_MAX_FACTOR = 5.0
"""Bound on |mapping factor|. f2 is a ratio of tip ``x`` coordinates and grows without bound
where the slave's vanishes (its tip crossing the arm frame's y axis, e.g. θ2 = θ3 = 60°); 5 keeps
a slave joint within 5× the speed of its master joint."""

DEFAULT_DAMPING = 1e-3
"""Damping λ [m] of the tip_exact least squares; the arm Jacobian's singular values are
~0.03-0.1 m/rad, so λ = 1 mm only matters near a singularity."""

_CLAMP_TOL = 1e-12  # [m or rad] a requested value further than this beyond a limit counts as clamped
_NEWTON_ITERATIONS = 3  # tip_exact: Newton steps per mapping step (residual ~1e-12 m after 2-3)


def _deg(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(math.radians(v) for v in values)


@dataclass(frozen=True)
class DHRow:
    """One modified (Craig) DH row: ``Rx(alpha) Tx(a) Rz(theta + q) Tz(d)`` or ``… Tz(d + q)``.

    Attributes:
        alpha: twist α_{i-1} [rad] about the previous x axis.
        a: length a_{i-1} [m] along the previous x axis.
        d: offset d_i [m] along the joint axis (the value at q = 0 for a prismatic joint).
        theta: offset θ_i [rad] about the joint axis (added to q for a revolute joint).
        prismatic: True if q is added to ``d`` [m], False if to ``theta`` [rad].
    """

    alpha: float
    a: float
    d: float
    theta: float
    prismatic: bool = False

    def pre(self) -> FloatArray:
        """``Rx(alpha) Tx(a)`` ``(4, 4)``: from the previous frame to a frame on the joint axis."""
        T = np.eye(4, dtype=np.float64)
        T[:3, :3] = rot_x(self.alpha)
        T[0, 3] = self.a
        return T

    def joint(self, q: float) -> FloatArray:
        """``Rz(theta [+ q]) Tz(d [+ q])`` ``(4, 4)``: the motion along / about the joint axis."""
        th = self.theta if self.prismatic else self.theta + q
        d = self.d + q if self.prismatic else self.d
        c, s = math.cos(th), math.sin(th)
        return np.array(
            [[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, d], [0.0, 0.0, 0.0, 1.0]],
            dtype=np.float64,
        )

    def transform(self, q: float) -> FloatArray:
        """The whole row ``(4, 4)`` for joint value ``q`` [rad or m]."""
        return self.pre() @ self.joint(q)


def _check_geometry(name: str, lengths: dict[str, float], positive: tuple[str, ...], geom: _Limits) -> None:
    for key, value in lengths.items():
        if not math.isfinite(value) or value < 0.0:
            raise KinematicsError(f"{name}.{key} must be finite and >= 0, got {value}")
    for key in positive:
        if lengths[key] <= 0.0:
            raise KinematicsError(f"{name}.{key} must be > 0, got {lengths[key]}")
    for attr in ("joint_names", "lower", "upper"):
        if len(getattr(geom, attr)) != 6:
            raise KinematicsError(f"{name}.{attr} must have 6 entries")
    for n, lo, hi in zip(geom.joint_names, geom.lower, geom.upper, strict=True):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise KinematicsError(f"{name} joint {n}: need finite lower < upper, got {lo}, {hi}")


class _Limits:
    """Joint names and limits shared by both geometries (a mixin; attributes set by the dataclass)."""

    joint_names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]

    @property
    def lower_limits(self) -> FloatArray:
        """Lower joint limits ``(6,)`` [m or rad]."""
        return np.array(self.lower, dtype=np.float64)

    @property
    def upper_limits(self) -> FloatArray:
        """Upper joint limits ``(6,)`` [m or rad]."""
        return np.array(self.upper, dtype=np.float64)


@dataclass(frozen=True)
class PlasSlaveGeometry(_Limits):
    """Dimensions [m] and joint limits [m / rad] of one PLAS arm (Tables 1 and 4).

    Attributes:
        a2: first yaw axis to second yaw axis (Table 4: 50 mm).
        a3: second yaw axis to the pitch axis (Table 4: 15 mm).
        d5: pitch axis to the end effector ("pillar") with the joint-5 slide at q5 = 0
            (Table 4: 30 mm). The prismatic joint 5 adds ``q5`` to it.
        d6: roll joint to the tip along the pillar (Table 1 d6; no value in the thesis, and its
            reconstruction puts the end effector at the roll joint, so 0).
        joint_names: 6 names, used in messages and clamp reports.
        lower, upper: joint limits. d1 in [0, 215] mm is the thesis's (Section 2.1.1); it gives
            none for the others, so these are chosen: ±90° for the yaws and the pitch (the
            Section 4 motions reach 62.5°, 40° and 60°), a ±15 mm pillar stroke around the
            reconstructed 30 mm (the master's finger slide drives it 1:1) and ±180° roll.
    """

    a2: float = 0.050
    a3: float = 0.015
    d5: float = 0.030
    d6: float = 0.0
    joint_names: tuple[str, ...] = ("d1", "theta2", "theta3", "theta4", "d5", "theta6")
    lower: tuple[float, ...] = (0.0, *_deg((-90.0, -90.0, -90.0)), -0.015, math.radians(-180.0))
    upper: tuple[float, ...] = (0.215, *_deg((90.0, 90.0, 90.0)), 0.015, math.radians(180.0))

    def __post_init__(self) -> None:
        lengths = {"a2": self.a2, "a3": self.a3, "d5": self.d5, "d6": self.d6}
        _check_geometry("PlasSlaveGeometry", lengths, ("a2", "d5"), self)

    @property
    def dh(self) -> tuple[DHRow, ...]:
        """The 6 modified-DH rows of :func:`slave_fk` (see the module docstring)."""
        return (
            DHRow(0.0, 0.0, 0.0, 0.0, prismatic=True),
            DHRow(HALF_PI, 0.0, 0.0, 0.0),
            DHRow(0.0, self.a2, 0.0, 0.0),
            DHRow(HALF_PI, self.a3, 0.0, HALF_PI),
            DHRow(HALF_PI, 0.0, self.d5, 0.0, prismatic=True),
            DHRow(0.0, 0.0, self.d6, 0.0),
        )

    @property
    def arm_rotation(self) -> FloatArray:
        """Rotation ``(3, 3)`` of the arm frame (Table 4 base) in the base frame: ``Rx(π/2)``."""
        return rot_x(HALF_PI)

    def pillar(self, d5_extension: float) -> float:
        """Pitch axis to the tip [m] for joint 5 at ``d5_extension`` [m]: ``d5 + q5 + d6``."""
        return self.d5 + d5_extension + self.d6


@dataclass(frozen=True)
class PlasMasterGeometry(_Limits):
    """Dimensions [m] and joint limits [m / rad] of the ergonomic master (Tables 3 and 5).

    Attributes:
        a2: elbow yaw axis to the wrist (Table 5 a2': 138 mm, a forearm).
        d6: wrist centre to the handle point with the finger slide at q6 = 0 (Table 5: 60 mm).
            The prismatic joint 6 adds ``q6`` to it (Table 3: ``d6 + d6'``).
        joint_names: 6 names.
        lower, upper: joint limits; informative (the master is read, never commanded). The
            thesis gives none for the device, so: shoulder slide 0-50 mm (read as a switch);
            elbow yaw ±60°; wrist yaw ±60° (human abduction/adduction is -20..30° [thesis
            Section 2.2], but Fig. 24 turns this joint to 60°); wrist pitch -70..60° and roll
            -80..90° (the human wrist ranges of Section 2.2); finger slide ±15 mm.
    """

    a2: float = 0.138
    d6: float = 0.060
    joint_names: tuple[str, ...] = ("d1", "theta2", "theta3", "theta4", "theta5", "d6")
    lower: tuple[float, ...] = (0.0, *_deg((-60.0, -60.0, -70.0, -80.0)), -0.015)
    upper: tuple[float, ...] = (0.050, *_deg((60.0, 60.0, 60.0, 90.0)), 0.015)

    def __post_init__(self) -> None:
        _check_geometry("PlasMasterGeometry", {"a2": self.a2, "d6": self.d6}, ("a2", "d6"), self)

    @property
    def dh(self) -> tuple[DHRow, ...]:
        """The 6 modified-DH rows of :func:`master_fk` (see the module docstring)."""
        return (
            DHRow(0.0, 0.0, 0.0, 0.0, prismatic=True),
            DHRow(0.0, 0.0, 0.0, 0.0),
            DHRow(0.0, self.a2, 0.0, 0.0),
            DHRow(HALF_PI, 0.0, 0.0, HALF_PI),
            DHRow(HALF_PI, 0.0, 0.0, 0.0),
            DHRow(0.0, 0.0, self.d6, 0.0, prismatic=True),
        )

    @property
    def arm_rotation(self) -> FloatArray:
        """Rotation ``(3, 3)`` of the arm frame (Table 5 base) in the base frame: identity."""
        return np.eye(3, dtype=np.float64)

    def handle(self, d6_extension: float) -> float:
        """Wrist centre to the handle point [m] for the finger slide at ``d6_extension`` [m]."""
        return self.d6 + d6_extension


PLAS_SLAVE = PlasSlaveGeometry()
"""The PLAS arm with the thesis's dimensions (Table 4)."""

PLAS_MASTER = PlasMasterGeometry()
"""The ergonomic master with the thesis's dimensions (Table 5)."""


# --------------------------------------------------------------------------------------------
# Forward kinematics and Jacobians
# --------------------------------------------------------------------------------------------


def _q6(q: npt.ArrayLike, what: str = "q") -> FloatArray:
    """``q`` checked to be 6 finite joint values [m or rad]."""
    try:
        arr = np.array(q, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be 6 joint values: {exc}") from exc
    if arr.shape != (6,):
        raise KinematicsError(f"{what} must have shape (6,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError(f"{what} must be finite, got {arr.tolist()}")
    return arr


@functools.lru_cache(maxsize=32)
def _prepared(geom: PlasSlaveGeometry | PlasMasterGeometry) -> tuple[tuple[DHRow, ...], FloatArray]:
    """(DH rows, their constant ``Rx(alpha) Tx(a)`` parts ``(6, 4, 4)``) of a (frozen) geometry."""
    rows = geom.dh
    return rows, np.stack([row.pre() for row in rows])


def _chain(
    geom: PlasSlaveGeometry | PlasMasterGeometry, q: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(joint axes ``(6, 3)``, points on them ``(6, 3)``, tip pose ``(4, 4)``) in the base frame."""
    rows, pre = _prepared(geom)
    T = pre[0]
    axes = np.empty((6, 3), dtype=np.float64)
    points = np.empty((6, 3), dtype=np.float64)
    for i, row in enumerate(rows):
        if i:
            T = T @ pre[i]
        axes[i] = T[:3, 2]
        points[i] = T[:3, 3]
        T = T @ row.joint(float(q[i]))
    return axes, points, T


def _jacobian(geom: PlasSlaveGeometry | PlasMasterGeometry, q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(geometric Jacobian ``(6, 6)``, tip pose ``(4, 4)``), both in the base frame."""
    axes, points, T = _chain(geom, q)
    revolute = np.array([not row.prismatic for row in _prepared(geom)[0]])
    J = np.zeros((6, 6), dtype=np.float64)
    J[:3] = np.where(revolute, np.cross(axes, T[:3, 3] - points).T, axes.T)
    J[3:] = np.where(revolute, axes.T, 0.0)
    return J, T


def slave_fk(q: npt.ArrayLike, geom: PlasSlaveGeometry = PLAS_SLAVE) -> FloatArray:
    """Slave tip pose ``(4, 4)`` in the slave base frame (``z0`` along the shaft).

    Args:
        q: ``(6,)`` = (d1 [m], θ2, θ3, θ4 [rad], d5 extension [m], θ6 [rad]).
        geom: arm dimensions.
    """
    return _chain(geom, _q6(q))[2]


def master_fk(q: npt.ArrayLike, geom: PlasMasterGeometry = PLAS_MASTER) -> FloatArray:
    """Master handle pose ``(4, 4)`` in the master base frame (``z0`` along the elbow axis).

    Args:
        q: ``(6,)`` = (d1' [m], θ2, θ3, θ4, θ5 [rad], d6' finger slide [m]).
        geom: device dimensions.
    """
    return _chain(geom, _q6(q))[2]


def slave_jacobian(q: npt.ArrayLike, geom: PlasSlaveGeometry = PLAS_SLAVE) -> FloatArray:
    """Geometric Jacobian ``(6, 6)`` of the slave tip in the base frame.

    ``[v; ω] = J @ qdot`` with ``v`` [m/s], ``ω`` [rad/s] and ``qdot`` in m/s (joints 1, 5) and
    rad/s. Rows 0-2 are the positional Jacobian.
    """
    return _jacobian(geom, _q6(q))[0]


def master_jacobian(q: npt.ArrayLike, geom: PlasMasterGeometry = PLAS_MASTER) -> FloatArray:
    """Geometric Jacobian ``(6, 6)`` of the master handle in the base frame (as :func:`slave_jacobian`)."""
    return _jacobian(geom, _q6(q))[0]


def _slave_arm(q: FloatArray, geom: PlasSlaveGeometry) -> tuple[FloatArray, FloatArray]:
    """Eq. 22 and its Jacobian (eq. 25 plus the d1, d5 and θ6 columns), in the arm frame."""
    c2, s2 = math.cos(q[1]), math.sin(q[1])
    c23, s23 = math.cos(q[1] + q[2]), math.sin(q[1] + q[2])
    c4, s4 = math.cos(q[3]), math.sin(q[3])
    length = geom.pillar(float(q[4]))
    reach = geom.a3 + length * c4  # distance of the tip from the θ3 axis, in the yaw plane
    p = np.array([c23 * reach + geom.a2 * c2, s23 * reach + geom.a2 * s2, length * s4])
    J = np.array(
        [
            [0.0, -p[1], -s23 * reach, -c23 * length * s4, c23 * c4, 0.0],
            [1.0, p[0], c23 * reach, -s23 * length * s4, s23 * c4, 0.0],
            [0.0, 0.0, 0.0, length * c4, s4, 0.0],
        ]
    )
    return p, J


def _master_arm(q: FloatArray, geom: PlasMasterGeometry) -> tuple[FloatArray, FloatArray]:
    """Table 5's handle point and its Jacobian (eq. 26 plus the d1', θ5 and d6' columns)."""
    c2, s2 = math.cos(q[1]), math.sin(q[1])
    c23, s23 = math.cos(q[1] + q[2]), math.sin(q[1] + q[2])
    c4, s4 = math.cos(q[3]), math.sin(q[3])
    length = geom.handle(float(q[5]))
    reach = length * c4
    p = np.array([c23 * reach + geom.a2 * c2, s23 * reach + geom.a2 * s2, length * s4])
    J = np.array(
        [
            [0.0, -p[1], -s23 * reach, -c23 * length * s4, 0.0, c23 * c4],
            [0.0, p[0], c23 * reach, -s23 * length * s4, 0.0, s23 * c4],
            [1.0, 0.0, 0.0, length * c4, 0.0, s4],
        ]
    )
    return p, J


def slave_tip_arm(q: npt.ArrayLike, geom: PlasSlaveGeometry = PLAS_SLAVE) -> FloatArray:
    """Slave tip ``(3,)`` [m] in the arm frame: eq. 22 with the pillar ``d5 + q5 + d6``.

    The arm frame is the base of Table 4: origin on the θ2 axis at the current d1, ``z`` along
    that axis, ``x`` along the first link at θ2 = 0 (``Rx(π/2)`` from the base frame).
    """
    return _slave_arm(_q6(q), geom)[0]


def master_tip_arm(q: npt.ArrayLike, geom: PlasMasterGeometry = PLAS_MASTER) -> FloatArray:
    """Master handle point ``(3,)`` [m] in the arm frame (the base of Table 5, at the current d1')."""
    return _master_arm(_q6(q), geom)[0]


def slave_arm_jacobian(q: npt.ArrayLike, geom: PlasSlaveGeometry = PLAS_SLAVE) -> FloatArray:
    """Positional Jacobian ``(3, 6)``: the tip's base-frame velocity along the arm-frame axes.

    Column 0 is d1 moving the whole arm along the shaft (+y of the arm frame; :func:`slave_tip_arm`,
    measured from the sliding arm origin, does not change); columns 1-3 are eq. 25; column 4 is
    the pillar direction; column 5 (roll) is zero. Equals ``Rx(π/2)ᵀ slave_jacobian(q)[:3]``.
    """
    return _slave_arm(_q6(q), geom)[1]


def master_arm_jacobian(q: npt.ArrayLike, geom: PlasMasterGeometry = PLAS_MASTER) -> FloatArray:
    """Positional Jacobian ``(3, 6)`` of the handle point along the arm-frame axes (eq. 26, extended).

    Column 0 is d1' (+z of the arm frame), column 4 (roll) is zero, column 5 the handle axis.
    Equals ``master_jacobian(q)[:3]`` (the arm frame is parallel to the base frame).
    """
    return _master_arm(_q6(q), geom)[1]


# --------------------------------------------------------------------------------------------
# Mapping factors (Table 6) and the all-joints mapping step
# --------------------------------------------------------------------------------------------

MappingMode = Literal["factor", "tip_exact"]


def _ratio(num: float, den: float, limit: float) -> float:
    """``num / den`` bounded to ``±limit`` (``den = 0`` gives ``±limit``; ``0 / 0`` gives 0)."""
    if num == 0.0:
        return 0.0
    if abs(num) >= limit * abs(den):
        sign = 1.0 if den >= 0.0 else -1.0
        return math.copysign(limit, num) * sign
    return num / den


def mapping_factors(
    q_master: npt.ArrayLike,
    q_slave: npt.ArrayLike,
    slave: PlasSlaveGeometry = PLAS_SLAVE,
    master: PlasMasterGeometry = PLAS_MASTER,
    *,
    max_factor: float = DEFAULT_MAX_FACTOR,
) -> FloatArray:
    """Table-6 factors ``(6,)``: ``θ'_slave[i] = f[i] θ'_master[MASTER_FOR_SLAVE[i]]``.

    ``f[0] = 0``: joint 1 is not proportional, an on/off switch drives it (:func:`map_step`).
    ``f[1:4]`` are eq. 28 at the master's θ2, θ3, θ4 with the current slave pillar
    ``d5 + q_slave[4] + d6`` and master handle ``d6 + q_master[5]``; each is bounded to
    ``±max_factor``. ``f[4] = f[5] = 1`` (d5 ← finger slide, θ6 ← wrist roll).

    Args:
        q_master: master joints ``(6,)`` [m, rad].
        q_slave: slave joints ``(6,)`` [m, rad] (only its pillar extension q5 is used).
        slave, master: geometries.
        max_factor: bound on each |factor| (>= 1).
    """
    qm, qs = _q6(q_master, "q_master"), _q6(q_slave, "q_slave")
    if not (math.isfinite(max_factor) and max_factor >= 1.0):
        raise KinematicsError(f"max_factor must be finite and >= 1, got {max_factor}")
    c2, c23, c4 = math.cos(qm[1]), math.cos(qm[1] + qm[2]), math.cos(qm[3])
    ls, lm = slave.pillar(float(qs[4])), master.handle(float(qm[5]))
    f2 = _ratio(c23 * lm * c4 + master.a2 * c2, c23 * (slave.a3 + ls * c4) + slave.a2 * c2, max_factor)
    f3 = _ratio(lm * c4, slave.a3 + ls * c4, max_factor)
    f4 = _ratio(lm, ls, max_factor)
    return np.array([0.0, f2, f3, f4, 1.0, 1.0], dtype=np.float64)


def eq29_vx_error(
    theta2: float,
    theta3: float,
    theta4: float = 0.0,
    slave: PlasSlaveGeometry = PLAS_SLAVE,
    master: PlasMasterGeometry = PLAS_MASTER,
) -> float:
    """Eq. 29: ``(v_x,slave - v_x,master) / θ'2,master`` [m/rad] with both arms at θ2, θ3, θ4 [rad].

    Uses the retracted pillar / handle (q5 = q6 = 0). Zero at θ3 = 0; the thesis's claim is that
    this is the only tip-velocity error of the factor mapping when the arms share their angles.
    """
    s2, s23, c4 = math.sin(theta2), math.sin(theta2 + theta3), math.cos(theta4)
    ls, lm = slave.pillar(0.0), master.handle(0.0)
    f2 = float(mapping_factors([0.0, theta2, theta3, theta4, 0.0, 0.0], np.zeros(6), slave, master)[1])
    return (s23 * lm * c4 + master.a2 * s2) - f2 * (s23 * (slave.a3 + ls * c4) + slave.a2 * s2)


@dataclass(frozen=True)
class MappingConfig:
    """How master joint motion becomes slave joint motion.

    Attributes:
        mode: ``"factor"`` — Table 6, every slave joint follows its own master joint;
            ``"tip_exact"`` — slave θ2, θ3, θ4, d5 solve the slave Jacobian for the master
            handle's displacement (damped least squares), d1 and θ6 as in ``"factor"``.
        d1_speed: [m/s] speed of slave d1 while the joint-1 switch is on (thesis: no value).
        max_factor: bound on each |Table-6 factor| (see :data:`DEFAULT_MAX_FACTOR`).
        damping: λ [m] of the tip_exact damped least squares.
        slave, master: geometries.
    """

    mode: MappingMode = "factor"
    d1_speed: float = DEFAULT_D1_SPEED
    max_factor: float = DEFAULT_MAX_FACTOR
    damping: float = DEFAULT_DAMPING
    slave: PlasSlaveGeometry = PLAS_SLAVE
    master: PlasMasterGeometry = PLAS_MASTER

    def __post_init__(self) -> None:
        if self.mode not in ("factor", "tip_exact"):
            raise KinematicsError(f"mode must be 'factor' or 'tip_exact', got {self.mode!r}")
        if not (math.isfinite(self.d1_speed) and self.d1_speed > 0.0):
            raise KinematicsError(f"d1_speed must be finite and > 0 m/s, got {self.d1_speed}")
        if not (math.isfinite(self.max_factor) and self.max_factor >= 1.0):
            raise KinematicsError(f"max_factor must be finite and >= 1, got {self.max_factor}")
        if not (math.isfinite(self.damping) and self.damping > 0.0):
            raise KinematicsError(f"damping must be finite and > 0 m, got {self.damping}")


@dataclass(frozen=True)
class MappingStep:
    """Result of one :func:`map_step`.

    Attributes:
        q: new slave joints ``(6,)``, within the limits.
        dq: increment actually applied, ``q - q_slave`` ``(6,)``.
        dq_requested: increment the mapping asked for before clamping ``(6,)``.
        clamped: names of the joints held at a limit this step (empty if none).
    """

    q: FloatArray
    dq: FloatArray
    dq_requested: FloatArray
    clamped: tuple[str, ...]


def _dls(J: FloatArray, r: FloatArray, damping: float) -> FloatArray:
    """Damped least squares ``Jᵀ (J Jᵀ + λ² I)⁻¹ r``."""
    A = J @ J.T + (damping * damping) * np.eye(J.shape[0])
    return J.T @ np.linalg.solve(A, r)


def _tip_exact_increment(q_s: FloatArray, dp: FloatArray, config: MappingConfig) -> FloatArray:
    """Increment ``(4,)`` of slave θ2, θ3, θ4, d5 moving its tip by ``dp`` ``(3,)`` [m] (arm frame)."""
    geom = config.slave
    p, J = _slave_arm(q_s, geom)
    target = p + dp
    q = q_s.copy()
    for i in range(_NEWTON_ITERATIONS):
        if i:
            p, J = _slave_arm(q, geom)
        r = target - p
        if float(np.linalg.norm(r)) < 1e-13:
            break
        q[1:5] += _dls(J[:, 1:5], r, config.damping)
    return q[1:5] - q_s[1:5]


def _check_switch(switch: int) -> None:
    if switch not in (-1, 0, 1):
        raise KinematicsError(f"switch must be -1 (retract), 0 (off) or +1 (advance), got {switch!r}")


def map_step(
    q_slave: npt.ArrayLike,
    q_master: npt.ArrayLike,
    dq_master: npt.ArrayLike,
    *,
    dt: float,
    switch: int = 0,
    config: MappingConfig = MappingConfig(),
) -> MappingStep:
    """Advance the slave by one step of master motion, clamped to the slave's joint limits.

    Args:
        q_slave: current slave joints ``(6,)`` [m, rad].
        q_master: master joints ``(6,)`` at the start of the step [m, rad].
        dq_master: master joint increment over the step ``(6,)`` [m, rad]; its joint-1 entry
            is ignored (the real device reads that joint as a switch).
        dt: step duration [s], used by the joint-1 switch only.
        switch: joint-1 switch: +1 drives d1 forward, -1 back, 0 holds it, at
            ``config.d1_speed`` (the thesis's on/off switch is +1 / 0).
        config: mode and parameters.

    In ``"factor"`` mode the factors are evaluated at the step's midpoint ``q_master +
    dq_master / 2`` (second-order accurate; exact when they are constant, as in Section 4's
    single-joint sweeps). In ``"tip_exact"`` mode the master handle's exact displacement
    ``master_tip_arm(q_master + dq_master) - master_tip_arm(q_master)`` is reproduced at the
    slave tip by a few damped Newton steps (no drift from step to step, apart from clamping).
    """
    qs = _q6(q_slave, "q_slave")
    qm = _q6(q_master, "q_master")
    dqm = _q6(dq_master, "dq_master")
    if not (math.isfinite(dt) and dt >= 0.0):
        raise KinematicsError(f"dt must be finite and >= 0 s, got {dt}")
    _check_switch(switch)
    geom = config.slave
    dq = np.zeros(6, dtype=np.float64)
    dq[0] = switch * config.d1_speed * dt
    if config.mode == "factor":
        f = mapping_factors(qm + 0.5 * dqm, qs, geom, config.master, max_factor=config.max_factor)
        for i in range(1, 6):
            dq[i] = f[i] * dqm[MASTER_FOR_SLAVE[i]]
    else:
        qm_end = qm.copy()
        qm_end[1:] += dqm[1:]
        dp = master_tip_arm(qm_end, config.master) - master_tip_arm(qm, config.master)
        dq[1:5] = _tip_exact_increment(qs, dp, config)
        dq[5] = dqm[MASTER_FOR_SLAVE[5]]
    requested = qs + dq
    q_new = np.clip(requested, geom.lower_limits, geom.upper_limits)
    over = np.abs(requested - q_new) > _CLAMP_TOL
    clamped = tuple(n for n, o in zip(geom.joint_names, over, strict=True) if o)
    return MappingStep(q=q_new, dq=q_new - qs, dq_requested=dq, clamped=clamped)


class Followed(NamedTuple):
    """Result of :func:`follow`."""

    q: FloatArray
    """Slave joints ``(T, 6)``; row 0 is the start, row k follows master row k."""
    clamp_counts: dict[str, int]
    """Per slave joint name, the number of steps in which it was clamped (only non-zero ones)."""


def follow(
    q_master: npt.ArrayLike,
    q_slave0: npt.ArrayLike,
    *,
    dt: float,
    switch: npt.ArrayLike | int = 0,
    config: MappingConfig = MappingConfig(),
) -> Followed:
    """Replay a master joint trajectory ``(T, 6)`` through :func:`map_step`.

    Args:
        q_master: master joints ``(T, 6)`` [m, rad] sampled every ``dt`` [s].
        q_slave0: slave joints ``(6,)`` at row 0.
        dt: sample period [s].
        switch: joint-1 switch, one value for every step or ``(T - 1,)`` values (step k goes
            from row k to row k + 1).
        config: mode and parameters.
    """
    try:
        qm = np.array(q_master, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"q_master must be a (T, 6) array: {exc}") from exc
    if qm.ndim != 2 or qm.shape[1] != 6 or qm.shape[0] < 1:
        raise KinematicsError(f"q_master must have shape (T, 6) with T >= 1, got {qm.shape}")
    n = qm.shape[0]
    try:
        sw = np.broadcast_to(np.asarray(switch), (n - 1,))
    except ValueError as exc:
        raise KinematicsError(f"switch must be one value or {n - 1} values (one per step): {exc}") from exc
    out = np.empty((n, 6), dtype=np.float64)
    out[0] = _q6(q_slave0, "q_slave0")
    counts: dict[str, int] = {}
    for k in range(n - 1):
        step = map_step(out[k], qm[k], qm[k + 1] - qm[k], dt=dt, switch=int(sw[k]), config=config)
        out[k + 1] = step.q
        for name in step.clamped:
            counts[name] = counts.get(name, 0) + 1
    return Followed(out, counts)


def tip_velocity_error(
    q_master: npt.ArrayLike,
    qd_master: npt.ArrayLike,
    q_slave: npt.ArrayLike,
    config: MappingConfig = MappingConfig(),
) -> FloatArray:
    """Tip velocity error ``v_slave - v_master`` ``(3,)`` [m/s] in the arm frame (eq. 29, generalised).

    ``v_master = J_m qd_master`` and ``v_slave = J_s qd_slave`` with the slave rates the mapping
    of ``config.mode`` produces from ``qd_master`` at these configurations. Joint 1 is left out
    on both sides (the switch moves the slave's d1 independently of the master). With both arms
    at the same angles and only master θ2 moving at 1 rad/s, the ``"factor"`` result is
    ``(eq29_vx_error(...), 0, 0)``; the ``"tip_exact"`` result is only the damping's residual.
    """
    qm, qs = _q6(q_master, "q_master"), _q6(q_slave, "q_slave")
    qdm = _q6(qd_master, "qd_master")
    qdm[0] = 0.0
    v_m = master_arm_jacobian(qm, config.master) @ qdm
    Js = slave_arm_jacobian(qs, config.slave)
    qds = np.zeros(6, dtype=np.float64)
    if config.mode == "factor":
        f = mapping_factors(qm, qs, config.slave, config.master, max_factor=config.max_factor)
        for i in range(1, 6):
            qds[i] = f[i] * qdm[MASTER_FOR_SLAVE[i]]
    else:
        qds[1:5] = _dls(Js[:, 1:5], v_m, config.damping)
        qds[5] = qdm[MASTER_FOR_SLAVE[5]]
    return Js @ qds - v_m
