"""Redundant single-port (SPA) arm of Jang et al. 2014 and its Virtual Incision Port (VIP) control.

Source: J. Jang, H. Choi, H. Kim, H. Kwak, *Kinematic Control of Redundant Arms based on the
Virtual Incision Ports for Robotic Single-Port Access Surgery*, ICRA 2014: Section II (the arm,
eqs. 1-19), Section III (the VIP, eqs. 20-23) and Table I (joint limits and initial angles).
The text of the paper lost its minus signs and Greek letters; every sign restored here is
stated below with the reason. Units: metres and radians everywhere.

Arm
---
Five joints place the wrist W (the three wrist-orientation joints and the gripper after W are not
modelled, as in the paper). q1, q2 and q3 form a conically shaped remote-centre-of-motion (RCM)
mechanism: their axes all pass through the RCM point R, the incision. q3 slides the instrument
shaft along its own axis z3 and sets the elbow E = q3·z3 (q3 < 0: Table I gives -0.195..-0.02 m,
so z3 points out of the patient and the shaft goes in along -z3). q4 rolls the shaft about z3 and
q5 bends the forearm at E; the forearm E→W has the fixed length ``forearm``.

Base frame (the paper's "base coordinates"): origin at R, z1 up, out of the patient.

====  ==========  ==========================================================  ===============
q     type        axis                                                        through
====  ==========  ==========================================================  ===============
q1    revolute    z1 = base z                                                 R
q2    revolute    z2: elevation α above the x1y1 plane, azimuth q1            R
q3    prismatic   z3: at angle β from z2 (and from the y2z2 plane)            R (E = q3·z3)
q4    revolute    z3, the shaft axis (roll)                                   E
q5    revolute    -y4 (elbow bend; the forearm leaves the shaft at angle q5)  E
====  ==========  ==========================================================  ===============

The chain, in rotation matrices (``W`` is then ``forearm`` along ``-z5``, like ``E`` along z3)::

    R1 = Rz(q1)
    R2 = R1 · Ry(π/2 - α) · Rz(π) · Rz(q2)     # columns x2, y2, z2
    R3 = R2 · Ry(β)                            # z3 = sin β · x2 + cos β · z2
    E  = q3 · R3[:, 2]
    R4 = R3 · Rz(q4)
    R5 = R4 · Ry(-q5)
    W  = E - forearm · R5[:, 2]                # = E + forearm · (sin q5 · x4 - cos q5 · z3)

At q2 = 0 the frame-2 axes are x2 = u = (-sin α cos q1, -sin α sin q1, cos α) (perpendicular to
z2, upward), y2 = -y1 and z2 = (cos α cos q1, cos α sin q1, sin α). Frame 3 is frame 2 tilted by β
about y2, so q4 = 0 bends the forearm in the plane of z2 and z3, away from z2. Points and frames
are finally mapped into the world by the arm's base transform (:attr:`VipArmGeometry.base_transform`).

Inverse kinematics (eqs. 3-19)
------------------------------
Given E (the paper's E(xe, ye, ze)) and W, with ``(a, b, c) = -E/|E|`` (eq. 3: the minus is
restored, since with q3 < 0 this is the unit vector z3):

* **q1** (eqs. 5-11): T, the projection of (a, b, c) on the q2 axis, is ``cos β · z2``, so
  ``xp² + yp² = A = cos²β sin²α / tan²α = cos²β cos²α`` (eq. 7, which pins the geometry: z3 is
  at β from z2) and ``a·xp + b·yp = cos β (cos β - c sin α)`` (the line of eqs. 6 and 8-10).
  Eq. 5 intersects that line with that circle and eq. 11 takes ``atan2(yp, xp)``. The same two
  intersections in polar form are ``q1 = atan2(b, a) ± arccos((cos β - c sin α) / (cos α ·
  hypot(a, b)))``. The ``+`` root gives ``sin q2 ≥ 0`` (q2 in [0, π], which holds Table I's
  5°..50°); the ``-`` root is its mirror with q2 < 0, outside Table I, and is not returned.
  ``hypot(a, b) = 0`` is excluded by assumption (2); an argument of arccos beyond ±1 means the
  shaft direction is outside the cone the RCM can reach.
* **q2** (eqs. 12-14): ``q2 = atan2(a⊥, b⊥)`` with ``a⊥ = a sin q1 - b cos q1 = z3·(-y1)`` and
  ``b⊥ = -a sin α cos q1 - b sin α sin q1 + c cos α = z3·u`` (eqs. 13-14 with their minus signs
  restored; these are the components of z3 along y2 and x2, which is what fixes frame 2 above).
* **q3** (eq. 15): ``q3 = -|E|`` (minus restored: Table I's range is negative).
* **q4** (eqs. 16-17): ``W⊥`` = W in the frame of q4 (frame 3, origin E); ``q4 = atan2(y⊥, x⊥)``.
  At q5 = 0 (forearm straight) q4 is undetermined and the caller's ``q4_ref`` is kept.
* **q5** (eqs. 18-19): the angle between ``u = (W - E)/|W - E|`` and ``v = E/|E|``, computed as
  ``atan2(|u × v|, u·v)`` (the same angle as ``arccos(u·v)``, but accurate near 0).

Design parameters chosen here (the paper gives neither value)
-------------------------------------------------------------
* **α = 60°, β = 30°.** Eq. 1 only bounds them (0 < α, β < π/2). Assumption (2) (E off the z1
  axis) is needed only if the cone z3 sweeps about z2 reaches z1, i.e. if α + β ≥ π/2, and
  Table I stops q2 at 5° rather than 0: both point to α + β = π/2, where q2 = 0 puts the shaft
  exactly on z1 (the q1 singularity) and the 5° stop is the margin from it. Then the shaft's
  angle θ from z1 obeys ``cos θ = sin²α + cos²α cos q2``; α = 60° gives θ = 2.5° / 14.9° / 24.4°
  at q2 = 5° / 30° (Table I initial) / 50°, a ±24° cone about the port axis: a moderate pivot
  for rigid shafts sharing one incision (α = 45° would need ±35°). Without joint limits the RCM
  reaches shaft directions up to 2β = 60° from z1.
* **forearm |EW| = 0.060 m.** Not in the paper. With it the Table I initial pose puts W
  0.184 m below the incision, the depth of the operating field in an insufflated abdomen, and the
  forearm is ~40% of the initial insertion |q3| = 0.14 m, as on articulated SPA instruments.

VIP (eqs. 20-23)
----------------
:func:`vip_elbow` puts E on the line from W to the virtual port V, ``forearm`` from W (eqs.
20-21); :func:`vip_ik` then applies :func:`ik`. :func:`select_vip` is the paper's procedure
(Steps 3-6): V on the line W→E extended beyond E by |EV| (0.02-0.05 m, default 0.05 m as in the
experiment), from the current joint readings. :func:`pinv_step` is the pseudo-inverse-Jacobian
resolution the paper compares against, with the analytic wrist :func:`jacobian`.

Example::

    import numpy as np
    from telesurg.shared.robots.vip.kinematics import VIP_ARM, fk, select_vip, vip_ik

    q = VIP_ARM.home_q                            # joint readings (Table I initial pose)
    V = select_vip(q)                             # VIP from the readings, |EV| = 0.05 m
    W = fk(q).wrist + np.array([0.01, 0.0, 0.0])  # move the wrist 10 mm along x
    q_next = vip_ik(W, V)                         # E stays on the line W-V
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray, matrix_from_quat, rot_y, rot_z

__all__ = [
    "EV_DEFAULT",
    "EV_MAX",
    "EV_MIN",
    "LENGTH_TOL",
    "LIMIT_TOL",
    "VIP_ARM",
    "VIP_ARM1",
    "VIP_ARM2",
    "WRIST_SINGULAR_TOL",
    "JointLimitError",
    "LimitViolation",
    "VipArmGeometry",
    "VipPose",
    "check_limits",
    "elbow_jacobian",
    "fk",
    "ik",
    "jacobian",
    "pinv_step",
    "select_vip",
    "vip_elbow",
    "vip_ik",
    "within_limits",
    "wrist_jacobian",
]

EV_MIN = 0.02
"""Smallest |EV| [m] of the VIP selection procedure (Section III-C, Step 5: "0.02-0.05 m")."""

EV_MAX = 0.05
"""Largest |EV| [m] of the VIP selection procedure (Section III-C, Step 5)."""

EV_DEFAULT = 0.05
"""|EV| [m] used in the paper's experiment (Section V-B)."""

LIMIT_TOL = 1e-9
"""Joint-limit tolerance [rad or m]: IK values this close outside a limit are put onto it."""

LENGTH_TOL = 1e-9
"""Largest accepted mismatch [m] between |W - E| and the forearm length in :func:`ik`."""

WRIST_SINGULAR_TOL = 1e-10
"""Distance [m] of W from the shaft axis below which q4 is undetermined (q5 ≈ 0; q4_ref is kept)."""

_REVOLUTE = (True, True, False, True, True)  # q3 is the prismatic joint
_AXIS_TOL = 1e-12  # [m / unit] E this close to the z1 axis violates assumption (2)
_CONE_TOL = 1e-12  # slack on |arccos argument| <= 1 for q1 (rounding of a reachable E)


def _table1(q1: float, q2: float, q3: float, q4: float, q5: float) -> tuple[float, ...]:
    """Table I row: q1, q2, q4, q5 in degrees, q3 in metres; returned in radians / metres."""
    return (math.radians(q1), math.radians(q2), q3, math.radians(q4), math.radians(q5))


@dataclass(frozen=True)
class VipArmGeometry:
    """Design parameters, joint limits and placement of one arm.

    Attributes:
        alpha: elevation [rad] of the q2 axis z2 above the x1y1 plane (0 < alpha < π/2, eq. 1).
        beta: angle [rad] of the shaft axis z3 from the y2z2 plane, which is also its angle from
            z2, i.e. the half-angle of the cone q2 sweeps the shaft on (0 < beta < π/2, eq. 1).
        forearm: elbow-to-wrist length |EW| [m].
        joint_names: 5 names, used in error messages.
        lower, upper: joint limits (Table I) [rad; q3 in m].
        home: initial joint values (Table I) [rad; q3 in m].
        base_position: R in the world frame [m].
        base_quat: orientation of the base frame in the world, [x, y, z, w] (unit).
    """

    alpha: float = math.radians(60.0)
    beta: float = math.radians(30.0)
    forearm: float = 0.060
    joint_names: tuple[str, ...] = ("q1", "q2", "q3", "q4", "q5")
    lower: tuple[float, ...] = _table1(-20.0, 5.0, -0.195, -90.0, 0.0)
    upper: tuple[float, ...] = _table1(60.0, 50.0, -0.02, 90.0, 90.0)
    home: tuple[float, ...] = _table1(20.0, 30.0, -0.14, 30.0, 45.0)
    base_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_quat: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        for name in ("alpha", "beta"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value < 0.5 * math.pi):
                raise KinematicsError(f"VipArmGeometry.{name} must be in (0, π/2) rad (eq. 1), got {value}")
        if not (math.isfinite(self.forearm) and self.forearm > 0.0):
            raise KinematicsError(f"VipArmGeometry.forearm must be finite and > 0 m, got {self.forearm}")
        for name in ("joint_names", "lower", "upper", "home"):
            if len(getattr(self, name)) != 5:
                raise KinematicsError(f"VipArmGeometry.{name} must have 5 entries (q1..q5)")
        for n, lo, hi, h in zip(self.joint_names, self.lower, self.upper, self.home, strict=True):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise KinematicsError(f"joint {n}: need finite lower < upper, got {lo}, {hi}")
            if not lo <= h <= hi:
                raise KinematicsError(f"joint {n}: home value {h} is outside [{lo}, {hi}]")
        if self.upper[2] >= 0.0:
            raise KinematicsError(f"q3 must stay < 0 (E = q3·z3 inside the patient), upper = {self.upper[2]}")
        if len(self.base_position) != 3 or not all(map(math.isfinite, self.base_position)):
            raise KinematicsError(f"base_position must be 3 finite numbers [m], got {self.base_position}")
        if len(self.base_quat) != 4 or not all(map(math.isfinite, self.base_quat)):
            raise KinematicsError(f"base_quat must be 4 finite numbers [x, y, z, w], got {self.base_quat}")
        if abs(math.sqrt(sum(v * v for v in self.base_quat)) - 1.0) > 1e-9:
            raise KinematicsError(f"base_quat must be a unit quaternion [x, y, z, w], got {self.base_quat}")

    @property
    def lower_limits(self) -> FloatArray:
        """Lower joint limits ``(5,)`` [rad; q3 in m]."""
        return np.array(self.lower, dtype=np.float64)

    @property
    def upper_limits(self) -> FloatArray:
        """Upper joint limits ``(5,)`` [rad; q3 in m]."""
        return np.array(self.upper, dtype=np.float64)

    @property
    def home_q(self) -> FloatArray:
        """Table I initial joint values ``(5,)`` [rad; q3 in m]."""
        return np.array(self.home, dtype=np.float64)

    @property
    def base_rotation(self) -> FloatArray:
        """Rotation ``(3, 3)`` of the base frame in the world."""
        return matrix_from_quat(self.base_quat)

    @property
    def base_transform(self) -> FloatArray:
        """Pose ``(4, 4)`` of the base frame (origin R) in the world [m]."""
        T = np.eye(4, dtype=np.float64)
        T[:3, :3] = self.base_rotation
        T[:3, 3] = self.base_position
        return T


def _yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


VIP_ARM = VipArmGeometry()
"""One arm in the paper's base coordinates (R at the origin, identity base)."""

VIP_ARM1 = replace(VIP_ARM, base_position=(0.0, -0.006, 0.0), base_quat=_yaw_quat(0.5 * math.pi))
"""Arm 1 of the two-arm MuJoCo model (``models/vip``): port frame origin at the incision centre,
z up, x toward the patient's head; R 6 mm to the right (-y), base turned +90° about z. Its
wrist is on the right (-y) at the Table I initial pose."""

VIP_ARM2 = replace(VIP_ARM, base_position=(0.0, 0.006, 0.0), base_quat=_yaw_quat(-0.5 * math.pi))
"""Arm 2 of the two-arm MuJoCo model: the same arm turned 180° about the port axis, R 6 mm to
the left (+y). Its wrist is on the left (+y) at the Table I initial pose."""


class VipPose(NamedTuple):
    """Forward kinematics of one arm, in the world frame.

    Attributes:
        rcm: R ``(3,)`` [m].
        elbow: E ``(3,)`` [m].
        wrist: W ``(3,)`` [m].
        wrist_frame: ``(4, 4)`` pose at W, rotation R5: z5 along the forearm pointing from W
            back to E (the instrument continues along -z5), x5 the bending direction rotated by
            q5, y5 = y4.
    """

    rcm: FloatArray
    elbow: FloatArray
    wrist: FloatArray
    wrist_frame: FloatArray


class LimitViolation(NamedTuple):
    """One joint outside its limit: ``excess`` = how far [rad, or m for q3], always > 0."""

    joint_index: int
    joint: str
    value: float
    limit: float
    excess: float
    upper: bool


class JointLimitError(IKError):
    """An IK solution exists but violates Table I limits; ``violations`` names each joint."""

    def __init__(self, violations: tuple[LimitViolation, ...], context: str = "") -> None:
        self.violations = violations
        text = "; ".join(_describe(v) for v in violations)
        super().__init__(f"{context}{text}")


def _amount(x: float, decimals: int) -> str:
    """``x`` with ``decimals`` decimals, or in scientific notation if that would round to 0."""
    return f"{x:.{decimals}f}" if abs(x) >= 0.5 * 10.0**-decimals else f"{x:.1e}"


def _describe(v: LimitViolation) -> str:
    side = "exceeds its upper" if v.upper else "is below its lower"
    if not _REVOLUTE[v.joint_index]:
        return f"{v.joint} = {v.value:.3f} m {side} limit {v.limit:.3f} m by {_amount(v.excess, 3)} m"
    deg = math.degrees
    return (
        f"{v.joint} = {deg(v.value):.1f}° ({v.value:.4f} rad) {side} limit {deg(v.limit):.1f}° "
        f"by {_amount(deg(v.excess), 1)}°"
    )


class _Frames(NamedTuple):
    """World-frame joint frames and points of one configuration."""

    R1: FloatArray
    R2: FloatArray
    R3: FloatArray
    R4: FloatArray
    R5: FloatArray
    rcm: FloatArray
    elbow: FloatArray
    wrist: FloatArray


def _vec(x: npt.ArrayLike, n: int, what: str) -> FloatArray:
    """``x`` as a finite float64 array of shape ``(n,)``, else KinematicsError naming ``what``."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be {n} numbers: {exc}") from exc
    if arr.shape != (n,):
        raise KinematicsError(f"{what} must have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def _q2_frame(alpha: float) -> FloatArray:
    """``Ry(π/2 - α) Rz(π)``: columns u, -y1, z2 of frame 2 at q1 = q2 = 0."""
    return rot_y(0.5 * math.pi - alpha) @ rot_z(math.pi)


def _frames(q: npt.ArrayLike, geom: VipArmGeometry) -> _Frames:
    q1, q2, q3, q4, q5 = _vec(q, 5, "q").tolist()
    Rb = geom.base_rotation
    pb = np.array(geom.base_position, dtype=np.float64)
    R1 = Rb @ rot_z(q1)
    R2 = R1 @ _q2_frame(geom.alpha) @ rot_z(q2)
    R3 = R2 @ rot_y(geom.beta)
    R4 = R3 @ rot_z(q4)
    R5 = R4 @ rot_y(-q5)
    elbow = pb + q3 * R3[:, 2]
    wrist = elbow - geom.forearm * R5[:, 2]
    return _Frames(R1, R2, R3, R4, R5, pb, elbow, wrist)


def fk(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> VipPose:
    """R, E, W and the wrist frame, in the world, for joints ``q`` ``(5,)`` [rad; q3 in m]."""
    f = _frames(q, geom)
    T = np.eye(4, dtype=np.float64)
    T[:3, :3] = f.R5
    T[:3, 3] = f.wrist
    return VipPose(rcm=f.rcm, elbow=f.elbow, wrist=f.wrist, wrist_frame=T)


def jacobian(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """Wrist-position Jacobian ``(3, 5)``: ``dW = J @ dq`` [m per rad; column 3 m per m].

    Columns, all in the world frame: ``z1 × (W - R)``, ``z2 × (W - R)``, ``z3``,
    ``z3 × (W - E)``, ``-y4 × (W - E)``.
    """
    f = _frames(q, geom)
    rw, ew = f.wrist - f.rcm, f.wrist - f.elbow
    z3 = f.R3[:, 2]
    cols = (
        np.cross(f.R1[:, 2], rw),
        np.cross(f.R2[:, 2], rw),
        z3,
        np.cross(z3, ew),
        np.cross(-f.R4[:, 1], ew),
    )
    return np.asarray(np.column_stack(cols), dtype=np.float64)


def wrist_jacobian(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """Geometric Jacobian ``(6, 5)`` of the wrist frame (:attr:`VipPose.wrist_frame`), world frame.

    ``[v; ω] = J @ qdot``: rows 0-2 are :func:`jacobian` (the velocity of W), rows 3-5 the angular
    velocity of the wrist frame: ``z1``, ``z2``, ``0`` (q3 slides), ``z3``, ``-y4``.
    """
    f = _frames(q, geom)
    rw, ew = f.wrist - f.rcm, f.wrist - f.elbow
    z3, y4 = f.R3[:, 2], -f.R4[:, 1]
    axes = (f.R1[:, 2], f.R2[:, 2], np.zeros(3), z3, y4)
    linear = (np.cross(axes[0], rw), np.cross(axes[1], rw), z3, np.cross(z3, ew), np.cross(y4, ew))
    return np.asarray(np.vstack([np.column_stack(linear), np.column_stack(axes)]), dtype=np.float64)


def elbow_jacobian(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """Elbow-position Jacobian ``(3, 5)``: ``dE = J @ dq`` (q4 and q5 do not move E)."""
    f = _frames(q, geom)
    re = f.elbow - f.rcm
    cols = (np.cross(f.R1[:, 2], re), np.cross(f.R2[:, 2], re), f.R3[:, 2], np.zeros(3), np.zeros(3))
    return np.asarray(np.column_stack(cols), dtype=np.float64)


def _violations(q: FloatArray, geom: VipArmGeometry, tol: float) -> tuple[LimitViolation, ...]:
    out = []
    for i, (name, v, lo, hi) in enumerate(
        zip(geom.joint_names, q.tolist(), geom.lower, geom.upper, strict=True)
    ):
        if v > hi + tol:
            out.append(LimitViolation(i, name, v, hi, v - hi, True))
        elif v < lo - tol:
            out.append(LimitViolation(i, name, v, lo, lo - v, False))
    return tuple(out)


def within_limits(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM, tol: float = 0.0) -> bool:
    """True if every joint of ``q`` ``(5,)`` is within its Table I limits (± ``tol``)."""
    return not _violations(_vec(q, 5, "q"), geom, tol)


def check_limits(q: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> None:
    """Raise :class:`JointLimitError` naming every joint of ``q`` ``(5,)`` outside its limits."""
    bad = _violations(_vec(q, 5, "q"), geom, LIMIT_TOL)
    if bad:
        raise JointLimitError(bad, "joints outside the Table I limits: ")


def ik(
    E: npt.ArrayLike,
    W: npt.ArrayLike,
    geom: VipArmGeometry = VIP_ARM,
    *,
    q4_ref: float = 0.0,
    enforce_limits: bool = True,
) -> FloatArray:
    """Analytic IK (eqs. 3-19): joints ``(5,)`` [rad; q3 in m] placing the elbow at E and wrist at W.

    Args:
        E: elbow position ``(3,)`` in the world [m].
        W: wrist position ``(3,)`` in the world [m]; must be ``forearm`` from E.
        geom: arm geometry and placement.
        q4_ref: q4 [rad] kept when the forearm is straight (q5 ≈ 0), where q4 is undetermined.
        enforce_limits: check Table I limits (the paper's simulation ran without them).

    Returns:
        ``q`` with q1 in (-π, π], q2 in [0, π] (the root holding Table I's range), q3 = -|RE|,
        q4 in (-π, π], q5 in [0, π]. Values within :data:`LIMIT_TOL` outside a limit are put
        onto it.

    Raises:
        IKError: E at R or on the z1 axis (assumption 2), the shaft direction RE outside the
            RCM cone, or |W - E| not equal to the forearm length.
        JointLimitError: the solution violates Table I; the message names each joint, its value,
            the limit and by how much.
    """
    Rb = geom.base_rotation
    pb = np.array(geom.base_position, dtype=np.float64)
    e = Rb.T @ (_vec(E, 3, "E") - pb)
    w = Rb.T @ (_vec(W, 3, "W") - pb)
    n = float(np.linalg.norm(e))
    if n < _AXIS_TOL:
        raise IKError("E coincides with the RCM point R: the shaft direction is undefined")
    a, b, c = (-e / n).tolist()  # eq. 3: the unit vector z3
    rho = math.hypot(a, b)
    if rho < _AXIS_TOL:
        raise IKError("E lies on the q1 axis z1 (assumption 2 of the paper): q1 is undetermined")
    sa, ca = math.sin(geom.alpha), math.cos(geom.alpha)
    cb = math.cos(geom.beta)
    kappa = (cb - c * sa) / (ca * rho)
    if abs(kappa) > 1.0 + _CONE_TOL:
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, c))))
        lo = math.degrees(abs(0.5 * math.pi - geom.alpha - geom.beta))
        hi = math.degrees(0.5 * math.pi - geom.alpha + geom.beta)
        raise IKError(
            f"E is outside the cone the RCM reaches: the shaft R→E would be {tilt:.1f}° from the "
            f"-z1 axis, the mechanism reaches {lo:.1f}°..{hi:.1f}°"
        )
    q1 = math.atan2(b, a) + math.acos(max(-1.0, min(1.0, kappa)))  # eqs. 5-11, the sin q2 >= 0 root
    if q1 > math.pi:
        q1 -= 2.0 * math.pi
    s1, c1 = math.sin(q1), math.cos(q1)
    a_perp = a * s1 - b * c1  # eq. 13: z3 · y2
    b_perp = -a * sa * c1 - b * sa * s1 + c * ca  # eq. 14: z3 · x2
    q2 = math.atan2(a_perp, b_perp)  # eq. 12
    q3 = -n  # eq. 15
    R3 = rot_z(q1) @ _q2_frame(geom.alpha) @ rot_z(q2) @ rot_y(geom.beta)
    w_perp = R3.T @ (w - e)  # eq. 17: W in the frame of q4 (origin E)
    length = float(np.linalg.norm(w_perp))
    if abs(length - geom.forearm) > LENGTH_TOL:
        raise IKError(
            f"|W - E| = {length:.6f} m but the forearm is {geom.forearm:.6f} m: "
            "W is not reachable from this E"
        )
    xw, yw, zw = w_perp.tolist()
    radial = math.hypot(xw, yw)
    q4 = math.atan2(yw, xw) if radial > WRIST_SINGULAR_TOL else float(q4_ref)  # eq. 16
    q5 = math.atan2(radial, -zw)  # eqs. 18-19: angle between E→W and R→E (= -z3)
    q = np.array([q1, q2, q3, q4, q5], dtype=np.float64)
    if enforce_limits:
        bad = _violations(q, geom, LIMIT_TOL)
        if bad:
            raise JointLimitError(bad, "IK solution outside the Table I limits: ")
        q = np.clip(q, geom.lower_limits, geom.upper_limits)
    return q


def vip_elbow(W: npt.ArrayLike, V: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """Elbow ``(3,)`` [m] on the line from W toward the VIP V, ``forearm`` from W (eqs. 20-21).

    Raises:
        KinematicsError: V coincides with W (the line is undefined).
    """
    w = _vec(W, 3, "W")
    wv = _vec(V, 3, "V") - w
    d = float(np.linalg.norm(wv))
    if d < _AXIS_TOL:
        raise KinematicsError("the VIP V coincides with the wrist W: the line W-V is undefined")
    return np.asarray(w + (geom.forearm / d) * wv, dtype=np.float64)


def vip_ik(
    W: npt.ArrayLike,
    V: npt.ArrayLike,
    geom: VipArmGeometry = VIP_ARM,
    *,
    q4_ref: float = 0.0,
    enforce_limits: bool = True,
) -> FloatArray:
    """Joints ``(5,)`` for wrist W with the elbow on the line W-V: :func:`vip_elbow` then :func:`ik`."""
    return ik(vip_elbow(W, V, geom), W, geom, q4_ref=q4_ref, enforce_limits=enforce_limits)


def select_vip(
    q: npt.ArrayLike, ev_distance: float = EV_DEFAULT, geom: VipArmGeometry = VIP_ARM
) -> FloatArray:
    """The VIP ``(3,)`` [m] of the paper's selection procedure (eqs. 22-23) from joint readings.

    E and W come from :func:`fk` of the current joints ``q`` ``(5,)`` (Step 3); V lies on the
    line W→E extended ``ev_distance`` beyond E (Steps 4-6): ``V = W + (E - W)/|E - W| ·
    (|WE| + |EV|)``. Then :func:`vip_ik` of the current W and this V returns ``q`` again
    (while q5 > 0).

    Raises:
        KinematicsError: ``ev_distance`` outside [:data:`EV_MIN`, :data:`EV_MAX`] m (Step 5).
    """
    ev = float(ev_distance)
    if not (math.isfinite(ev) and EV_MIN <= ev <= EV_MAX):
        raise KinematicsError(
            f"ev_distance = {ev_distance!r} m is outside the range of the VIP selection procedure, "
            f"[{EV_MIN}, {EV_MAX}] m (Section III-C, Step 5)"
        )
    pose = fk(q, geom)
    we = pose.elbow - pose.wrist
    return np.asarray(pose.wrist + we * ((geom.forearm + ev) / float(np.linalg.norm(we))), dtype=np.float64)


def pinv_step(
    q: npt.ArrayLike, dW: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM, *, rcond: float = 1e-10
) -> FloatArray:
    """One pseudo-inverse-Jacobian step: ``q + pinv(J(q)) @ dW`` ``(5,)`` (the paper's comparison).

    The minimum-norm joint change (q3 in metres weighs like the angles in radians) that moves
    the wrist by ``dW`` ``(3,)`` [m] to first order. The redundancy is left to the pseudo-inverse,
    so the elbow drifts. Joint limits are not applied.
    """
    qv = _vec(q, 5, "q")
    step = np.linalg.pinv(jacobian(qv, geom), rcond=rcond) @ _vec(dW, 3, "dW")
    return np.asarray(qv + step, dtype=np.float64)
