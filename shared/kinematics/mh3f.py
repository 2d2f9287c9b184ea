"""Forward / inverse kinematics and Jacobian of a 6-axis Yaskawa MOTOMAN-MH3F class arm.

Units: metres and radians everywhere (limits in the data sheet are degrees; converted here).

Frames
------
Base frame: origin on the floor on the J1 axis, +z up, +x forward, +y = z × x (left).
At ``q = 0`` the lower arm is vertical and the upper arm horizontal, pointing +x.

====  ======  ================================================  ==============================
axis  about   through (at q = 0)                                positive motion
====  ======  ================================================  ==============================
J1    +z      (0, 0, 0)                                         turns the arm toward +y
J2    +y      (0, 0, D1)                                        tilts the lower arm toward +x
J3    -y      (0, 0, D1 + A2)                                   raises the upper arm
J4    +x      (0, 0, D1 + A2 + A3)  (the upper-arm axis)        rolls the forearm
J5    -y      wrist centre W = (D4, 0, D1 + A2 + A3)            pitches the flange up
J6    +x      W (the flange / tool axis)                        rolls the flange
====  ======  ================================================  ==============================

Dimensions (:data:`MH3F`): D1 = 0.272 (base height; chosen so that the 804 mm vertical reach
equals D1 + the 532 mm horizontal reach of the wrist centre), A2 = 0.260 (lower arm),
A3 = 0.030 (upper-arm offset, perpendicular to the upper arm), D4 = 0.270 (upper arm, J4 point to
W), D6 = 0.090 (W to flange) and TOOL = 0.500 (straight dummy forceps on the flange x axis:
350 mm × Ø5 mm shaft, 500 mm from flange to tip). Wrist centre to tip: D6 + TOOL = 0.590.

Each joint is a rotation about its axis expressed in the previous moving frame, so the TCP pose
is the product (this *is* the forward-kinematics definition used below)::

    T = Rz(q1) Tz(D1) Ry(q2) Tz(A2) Ry(-q3) Tz(A3) Rx(q4) Tx(D4) Ry(-q5) Rx(q6) Tx(D6 + TOOL)

At q = 0 this puts the tip at (D4 + D6 + TOOL, 0, D1 + A2 + A3) = (0.860, 0, 0.562) with the
identity orientation. The TCP frame has the flange orientation; its x axis is the forceps axis,
pointing toward the tip.

Inverse kinematics (derivation, briefly)
----------------------------------------
J4, J5, J6 intersect at W, so the problem decouples:

1. **Wrist centre**: ``W = p - (D6 + TOOL) R[:, 0]``.
2. **J1**: the arm has no lateral offset, so W lies in the vertical plane of J1:
   ``q1 = atan2(Wy, Wx)`` (front) or that + π (back, reaching over the top). In that plane let
   ``x = ±hypot(Wx, Wy)`` and ``z = Wz - D1``.
3. **J3 (elbow)**: the upper arm from J3 to W is the vector (D4, A3) rotated by q3, i.e. a link
   of length ``L = hypot(D4, A3)`` at angle ``ψ = q3 + φ`` with ``φ = atan2(A3, D4)``. The
   planar two-link law of cosines gives ``sin ψ = (x² + z² - A2² - L²) / (2 A2 L)``, hence
   ``ψ = asin(·)`` or ``π - asin(·)`` (elbow up / down) and ``q3 = ψ - φ``.
4. **J2**: ``x = a sin q2 + b cos q2``, ``z = a cos q2 - b sin q2`` with ``a = A2 + L sin ψ``,
   ``b = L cos ψ``, so ``q2 = atan2(x, z) - atan2(b, a)``.
5. **Wrist**: ``R36 = (Rz(q1) Ry(q2 - q3))ᵀ R = Rx(q4) Ry(-q5) Rx(q6)`` (an x-y-x Euler set).
   With ``β = -q5``: ``R36[1,0] = sin q4 sin β``, ``R36[2,0] = -cos q4 sin β``, so
   ``q4 = atan2(R36[1,0], -R36[2,0])`` or that + π (wrist flip); then ``Rx(q4)ᵀ R36 = Ry(β) Rx(q6)``
   yields ``β`` and ``q6`` with well-conditioned atan2 calls. When ``sin q5 ≈ 0`` (singular
   wrist) only ``q4 + q6`` is determined: q4 is kept at the reference (current) value and the
   rest goes to q6.
6. **Revolute wrap**: J3 spans 365° and J6 720°, so every ``q ± 2πk`` that stays within the
   limits is a separate solution. Up to 8 branches (J1 front/back × elbow × wrist flip) times
   those wraps are returned.

Limits (data-sheet Table 1, degrees): J1 ±160, J2 -85..+90, J3 -105..+260, J4 ±170, J5 ±120,
J6 ±360. Maximum speeds [rad/s]: 3.49, 2.62, 3.32, 5.24, 5.24, 7.33.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from shared.errors import IKError, KinematicsError
from shared.kinematics.transforms import (
    FloatArray,
    make_transform,
    rot_x,
    rot_y,
    rot_z,
)

__all__ = [
    "LIMIT_TOL",
    "MH3F",
    "MH3F_NO_TOOL",
    "SHOULDER_SINGULAR_TOL",
    "WRIST_SINGULAR_TOL",
    "ArmGeometry",
    "fk",
    "fk_frames",
    "ik",
    "ik_all",
    "jacobian",
    "within_limits",
    "wrist_center",
]

TWO_PI = 2.0 * math.pi

LIMIT_TOL = 1e-9
"""Joint-limit tolerance [rad]: IK solutions this far outside a limit are clipped onto it."""

WRIST_SINGULAR_TOL = 1e-10
"""|sin q5| below which the wrist is treated as singular (q4 kept at the reference value)."""

SHOULDER_SINGULAR_TOL = 1e-10
"""Distance [m] of the wrist centre from the J1 axis below which q1 is kept at the reference."""

_REACH_TOL = 1e-9  # [m] slack on the reach test, so a fully stretched fk(q) stays reachable


def _deg(values: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(math.radians(v) for v in values)


@dataclass(frozen=True)
class ArmGeometry:
    """Link dimensions [m], joint limits [rad] and speed limits [rad/s] of the arm.

    Attributes:
        d1: base height, floor to the J2 axis.
        a2: lower arm, J2 axis to J3 axis.
        a3: upper-arm offset, J3 axis to the J4 axis (perpendicular to the upper arm).
        d4: upper arm, along the J4 axis to the wrist centre.
        d6: wrist centre to the flange, along the J6 axis.
        tool: flange to TCP along the flange x axis (0 gives the flange itself).
        joint_names: 6 names, used in error messages.
        lower, upper: joint limits [rad], 6 each.
        max_velocity: joint speed limits [rad/s], 6.
    """

    d1: float = 0.272
    a2: float = 0.260
    a3: float = 0.030
    d4: float = 0.270
    d6: float = 0.090
    tool: float = 0.500
    joint_names: tuple[str, ...] = ("j1", "j2", "j3", "j4", "j5", "j6")
    lower: tuple[float, ...] = _deg((-160.0, -85.0, -105.0, -170.0, -120.0, -360.0))
    upper: tuple[float, ...] = _deg((160.0, 90.0, 260.0, 170.0, 120.0, 360.0))
    max_velocity: tuple[float, ...] = (3.49, 2.62, 3.32, 5.24, 5.24, 7.33)

    def __post_init__(self) -> None:
        for name in ("d1", "a2", "a3", "d4", "d6", "tool"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0.0:
                raise KinematicsError(f"ArmGeometry.{name} must be finite and >= 0, got {value}")
        if self.a2 <= 0.0 or math.hypot(self.d4, self.a3) <= 0.0:
            raise KinematicsError("ArmGeometry needs a2 > 0 and hypot(d4, a3) > 0")
        for name in ("joint_names", "lower", "upper", "max_velocity"):
            if len(getattr(self, name)) != 6:
                raise KinematicsError(f"ArmGeometry.{name} must have 6 entries")
        for n, lo, hi, v in zip(self.joint_names, self.lower, self.upper, self.max_velocity, strict=True):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise KinematicsError(f"joint {n}: need finite lower < upper, got {lo}, {hi}")
            if not (math.isfinite(v) and v > 0.0):
                raise KinematicsError(f"joint {n}: max_velocity must be > 0, got {v}")

    @property
    def lower_limits(self) -> FloatArray:
        """Lower joint limits ``(6,)`` [rad]."""
        return np.array(self.lower, dtype=np.float64)

    @property
    def upper_limits(self) -> FloatArray:
        """Upper joint limits ``(6,)`` [rad]."""
        return np.array(self.upper, dtype=np.float64)

    @property
    def velocity_limits(self) -> FloatArray:
        """Joint speed limits ``(6,)`` [rad/s]."""
        return np.array(self.max_velocity, dtype=np.float64)

    @property
    def upper_arm_length(self) -> float:
        """Effective upper arm, J3 axis to wrist centre: ``hypot(d4, a3)`` [m]."""
        return math.hypot(self.d4, self.a3)

    @property
    def upper_arm_angle(self) -> float:
        """Angle [rad] of the J3→W vector above the J4 axis: ``atan2(a3, d4)``."""
        return math.atan2(self.a3, self.d4)

    @property
    def reach(self) -> float:
        """Largest distance [m] of the wrist centre from the J2 axis: ``a2 + upper_arm_length``."""
        return self.a2 + self.upper_arm_length

    @property
    def min_reach(self) -> float:
        """Smallest distance [m] of the wrist centre from the J2 axis."""
        return abs(self.a2 - self.upper_arm_length)

    @property
    def wrist_to_tcp(self) -> float:
        """Wrist centre to TCP along the J6 axis: ``d6 + tool`` [m]."""
        return self.d6 + self.tool


MH3F = ArmGeometry()
"""MOTOMAN-MH3F class arm with the 500 mm dummy forceps; the TCP is the forceps tip."""

MH3F_NO_TOOL = replace(MH3F, tool=0.0)
"""Same arm without a tool; the TCP is the flange (mechanical interface)."""


class _Chain(NamedTuple):
    """Intermediate frames of the serial chain (all in the base frame)."""

    R1: FloatArray  # after J1
    R2: FloatArray  # after J2
    R3: FloatArray  # after J3
    R4: FloatArray  # after J4
    R5: FloatArray  # after J5
    R6: FloatArray  # after J6 = flange / TCP orientation
    p_j2: FloatArray
    p_j3: FloatArray
    p_j4: FloatArray
    p_wrist: FloatArray
    p_flange: FloatArray
    p_tcp: FloatArray


def _as_q(q: npt.ArrayLike, what: str = "q") -> FloatArray:
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be 6 joint angles [rad]: {exc}") from exc
    if arr.shape != (6,):
        raise KinematicsError(f"{what} must have shape (6,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def _chain(q: npt.ArrayLike, geom: ArmGeometry) -> _Chain:
    q1, q2, q3, q4, q5, q6 = (float(v) for v in _as_q(q))
    R1 = rot_z(q1)
    R2 = R1 @ rot_y(q2)
    R3 = R2 @ rot_y(-q3)
    R4 = R3 @ rot_x(q4)
    R5 = R4 @ rot_y(-q5)
    R6 = R5 @ rot_x(q6)
    p_j2 = np.array([0.0, 0.0, geom.d1], dtype=np.float64)
    p_j3 = p_j2 + geom.a2 * R2[:, 2]
    p_j4 = p_j3 + geom.a3 * R3[:, 2]
    p_wrist = p_j4 + geom.d4 * R4[:, 0]
    p_flange = p_wrist + geom.d6 * R6[:, 0]
    p_tcp = p_flange + geom.tool * R6[:, 0]
    return _Chain(R1, R2, R3, R4, R5, R6, p_j2, p_j3, p_j4, p_wrist, p_flange, p_tcp)


def fk(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """TCP pose ``(4, 4)`` in the base frame for joint angles ``q`` ``(6,)`` [rad]."""
    c = _chain(q, geom)
    return make_transform(c.R6, c.p_tcp)


def fk_frames(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Link points ``(7, 3)`` [m] in the base frame, for drawing the arm.

    Rows: base origin, J2 (shoulder), J3 (elbow), J4 point (end of the A3 offset), wrist
    centre, flange, TCP (tool tip).
    """
    c = _chain(q, geom)
    return np.stack([np.zeros(3, dtype=np.float64), c.p_j2, c.p_j3, c.p_j4, c.p_wrist, c.p_flange, c.p_tcp])


def wrist_center(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Wrist centre (intersection of J4, J5, J6) ``(3,)`` [m] in the base frame."""
    return _chain(q, geom).p_wrist


def jacobian(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Geometric Jacobian ``(6, 6)`` of the TCP in the base frame.

    ``[v; ω] = J @ qdot`` with ``v`` the TCP linear velocity [m/s], ``ω`` the angular velocity
    [rad/s] (both in base coordinates) and ``qdot`` [rad/s]. Column i is
    ``[z_i × (p_tcp - p_i); z_i]`` for joint axis ``z_i`` through point ``p_i``.
    """
    c = _chain(q, geom)
    axes = (
        np.array([0.0, 0.0, 1.0], dtype=np.float64),
        c.R1[:, 1],
        -c.R2[:, 1],
        c.R3[:, 0],
        -c.R4[:, 1],
        c.R5[:, 0],
    )
    points = (np.zeros(3, dtype=np.float64), c.p_j2, c.p_j3, c.p_j4, c.p_wrist, c.p_wrist)
    J = np.empty((6, 6), dtype=np.float64)
    for i, (z, p) in enumerate(zip(axes, points, strict=True)):
        J[:3, i] = np.cross(z, c.p_tcp - p)
        J[3:, i] = z
    return J


def within_limits(q: npt.ArrayLike, geom: ArmGeometry = MH3F, tol: float = 0.0) -> bool:
    """True if every joint of ``q`` ``(6,)`` [rad] is within its limits (± ``tol`` [rad])."""
    arr = _as_q(q)
    return bool(np.all(arr >= geom.lower_limits - tol) and np.all(arr <= geom.upper_limits + tol))


# --------------------------------------------------------------------------------------------
# Inverse kinematics
# --------------------------------------------------------------------------------------------


def _wrap(a: float) -> float:
    """Angle wrapped to [-π, π]."""
    return math.remainder(a, TWO_PI)


def _as_pose(T: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    try:
        arr = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise IKError(f"target pose must be a numeric 4x4 transform: {exc}") from exc
    if arr.shape != (4, 4):
        raise IKError(f"target pose must have shape (4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise IKError("target pose contains non-finite values")
    R = arr[:3, :3]
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > 1e-6 or np.linalg.det(R) < 0.0:
        raise IKError(f"target rotation is not a proper rotation matrix (|RᵀR - I| = {err:.2e})")
    return R, arr[:3, 3]


def _ik_candidates(
    T: npt.ArrayLike, geom: ArmGeometry, q_ref: FloatArray | None
) -> tuple[FloatArray, str | None]:
    """All analytic IK branches ``(M, 6)`` with every angle wrapped to [-π, π], limits ignored.

    Returns ``(empty, reason)`` when the wrist centre is out of reach. Raises IKError for a
    malformed pose.
    """
    R, p = _as_pose(T)
    W = p - geom.wrist_to_tcp * R[:, 0]
    rxy = math.hypot(float(W[0]), float(W[1]))
    z = float(W[2]) - geom.d1
    dist = math.hypot(rxy, z)
    L, phi, a2 = geom.upper_arm_length, geom.upper_arm_angle, geom.a2

    if dist > geom.reach + _REACH_TOL:
        return np.empty((0, 6)), (
            f"target wrist centre is {dist:.3f} m from the shoulder (J2 axis), beyond the "
            f"reach of {geom.reach:.3f} m (tip {geom.wrist_to_tcp:.3f} m from the wrist centre)"
        )
    if dist < geom.min_reach - _REACH_TOL:
        return np.empty((0, 6)), (
            f"target wrist centre is {dist:.4f} m from the shoulder (J2 axis), inside the "
            f"minimum reach of {geom.min_reach:.4f} m"
        )

    # J1: front and back branch; on the J1 axis q1 is free, so keep the reference.
    if rxy < SHOULDER_SINGULAR_TOL:
        q1_front = float(q_ref[0]) if q_ref is not None else 0.0
    else:
        q1_front = math.atan2(float(W[1]), float(W[0]))
    j1_branches = ((q1_front, rxy), (q1_front + math.pi, -rxy))

    # J3: elbow up / down from the law of cosines on (a2, L).
    s = (dist * dist - a2 * a2 - L * L) / (2.0 * a2 * L)
    psi0 = math.asin(min(1.0, max(-1.0, s)))
    psis = (psi0, math.pi - psi0)

    q4_ref = float(q_ref[3]) if q_ref is not None else 0.0
    out: list[list[float]] = []
    for q1, x in j1_branches:
        for psi in psis:
            q3 = psi - phi
            q2 = math.atan2(x, z) - math.atan2(L * math.cos(psi), a2 + L * math.sin(psi))
            R36 = (rot_z(q1) @ rot_y(q2 - q3)).T @ R
            sin_b = math.hypot(float(R36[1, 0]), float(R36[2, 0]))
            if sin_b > WRIST_SINGULAR_TOL:
                a0 = math.atan2(float(R36[1, 0]), float(-R36[2, 0]))
                q4s: tuple[float, ...] = (a0, a0 + math.pi)
            else:
                q4s = (q4_ref,)
            for q4 in q4s:
                M = rot_x(q4).T @ R36  # = Ry(-q5) Rx(q6)
                q5 = -math.atan2(float(-M[2, 0]), float(M[0, 0]))
                q6 = math.atan2(float(-M[1, 2]), float(M[1, 1]))
                out.append([_wrap(v) for v in (q1, q2, q3, q4, q5, q6)])
    return np.array(out, dtype=np.float64), None


def _wrap_variants(value: float, lo: float, hi: float) -> list[float]:
    """All ``value + 2πk`` in [lo - LIMIT_TOL, hi + LIMIT_TOL], clipped onto [lo, hi]."""
    k_min = math.ceil((lo - LIMIT_TOL - value) / TWO_PI)
    k_max = math.floor((hi + LIMIT_TOL - value) / TWO_PI)
    return [min(hi, max(lo, value + k * TWO_PI)) for k in range(k_min, k_max + 1)]


def _within_limit_solutions(cands: FloatArray, geom: ArmGeometry) -> list[FloatArray]:
    sols: list[FloatArray] = []
    for cand in cands:
        per_joint = [
            _wrap_variants(float(v), lo, hi) for v, lo, hi in zip(cand, geom.lower, geom.upper, strict=True)
        ]
        for combo in itertools.product(*per_joint):
            sol = np.array(combo, dtype=np.float64)
            if not any(np.max(np.abs(sol - s)) < 1e-9 for s in sols):
                sols.append(sol)
    return sols


def _limit_violation_message(cands: FloatArray, geom: ArmGeometry) -> str:
    """Describe the branch that comes closest to the limits (each joint at its best 2π wrap)."""
    best: tuple[float, int, float] | None = None  # (violation [rad], joint index, angle [rad])
    for cand in cands:
        worst = (0.0, 0, float(cand[0]))
        for j, (v, lo, hi) in enumerate(zip(cand, geom.lower, geom.upper, strict=True)):
            options = [float(v) + k * TWO_PI for k in (-2, -1, 0, 1, 2)]
            viol, angle = min((max(lo - o, o - hi, 0.0), o) for o in options)
            if viol > worst[0]:
                worst = (viol, j, angle)
        if best is None or worst[0] < best[0]:
            best = worst
    if best is None:
        return "no IK branch found"
    viol, j, angle = best
    name = geom.joint_names[j]
    return (
        f"all {len(cands)} IK branches violate joint limits: nearest violates {name} by "
        f"{math.degrees(viol):.1f}° ({name} = {math.degrees(angle):.1f}°, limits "
        f"[{math.degrees(geom.lower[j]):.1f}°, {math.degrees(geom.upper[j]):.1f}°])"
    )


def ik_all(
    T: npt.ArrayLike, geom: ArmGeometry = MH3F, *, q_ref: npt.ArrayLike | None = None
) -> list[FloatArray]:
    """Every distinct analytic IK solution of TCP pose ``T`` ``(4, 4)`` within the joint limits.

    Covers J1 front/back × elbow up/down × wrist flip (up to 8 branches) and every ``± 2π``
    variant of a joint that stays within its limits (J3, J6). Each solution is ``(6,)`` [rad].

    Args:
        T: target TCP pose in the base frame, ``(4, 4)``, translation in metres.
        geom: arm geometry.
        q_ref: optional ``(6,)`` reference joints [rad]; at a singular wrist (``q5 ≈ 0``) q4 is
            set to ``q_ref[3]`` (0 if absent), and with the wrist centre on the J1 axis q1 is set
            to ``q_ref[0]``.

    Returns:
        The solutions (possibly empty if the target is out of reach or every branch violates a
        limit — use :func:`ik` for the reason).

    Raises:
        IKError: if ``T`` is not a finite 4x4 rigid transform.
    """
    ref = None if q_ref is None else _as_q(q_ref, "q_ref")
    cands, _ = _ik_candidates(T, geom, ref)
    return _within_limit_solutions(cands, geom)


def ik(
    T: npt.ArrayLike,
    q_current: npt.ArrayLike,
    geom: ArmGeometry = MH3F,
    *,
    weights: npt.ArrayLike | None = None,
) -> FloatArray:
    """The IK solution of pose ``T`` ``(4, 4)`` nearest to ``q_current`` ``(6,)`` [rad].

    Nearest means the smallest ``sum(weights * (q - q_current)²)`` (plain L2 when ``weights``
    is None) over all within-limit solutions of :func:`ik_all`. At a singular wrist q4 stays at
    ``q_current[3]``.

    Returns:
        Joint angles ``(6,)`` [rad].

    Raises:
        IKError: naming the reason — target out of reach, or every branch violates a joint limit
            (and by how much the nearest one does), or a malformed pose.
    """
    qc = _as_q(q_current, "q_current")
    if weights is None:
        w = np.ones(6, dtype=np.float64)
    else:
        w = _as_q(weights, "weights")
        if np.any(w < 0.0):
            raise KinematicsError(f"weights must be >= 0, got {w.tolist()}")
    cands, reason = _ik_candidates(T, geom, qc)
    if reason is not None:
        raise IKError(reason)
    sols = _within_limit_solutions(cands, geom)
    if not sols:
        raise IKError(_limit_violation_message(cands, geom))
    costs = [float(np.sum(w * (s - qc) ** 2)) for s in sols]
    return sols[int(np.argmin(costs))].copy()
