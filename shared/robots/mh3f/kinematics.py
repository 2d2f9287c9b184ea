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
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray, rot_x, rot_y, rot_z

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


_Vec3 = tuple[float, float, float]


class _Params(NamedTuple):
    """Constants of one geometry used on the hot paths, derived once (see :func:`_params`)."""

    d1: float
    a2: float
    a3: float
    d4: float
    d6: float
    tool: float
    wrist_to_tcp: float
    upper_arm_length: float
    upper_arm_angle: float
    a2_sq: float  # a2 * a2
    upper_arm_length_sq: float  # L * L
    two_a2_l: float  # 2 * a2 * L
    reach_max: float  # reach + _REACH_TOL
    reach_min: float  # min_reach - _REACH_TOL
    bounds: tuple[tuple[float, float, float, float], ...]  # (lo, hi, lo - LIMIT_TOL, hi + LIMIT_TOL)


# id(geom) -> (geom, params). The geometry is frozen, and holding it keeps its id unique while cached.
_PARAMS_CACHE: dict[int, tuple[ArmGeometry, _Params]] = {}
_PARAMS_CACHE_MAX = 32


def _params(geom: ArmGeometry) -> _Params:
    """The cached :class:`_Params` of ``geom``."""
    entry = _PARAMS_CACHE.get(id(geom))
    if entry is not None and entry[0] is geom:
        return entry[1]
    a2, length = geom.a2, geom.upper_arm_length
    params = _Params(
        d1=geom.d1,
        a2=a2,
        a3=geom.a3,
        d4=geom.d4,
        d6=geom.d6,
        tool=geom.tool,
        wrist_to_tcp=geom.wrist_to_tcp,
        upper_arm_length=length,
        upper_arm_angle=geom.upper_arm_angle,
        a2_sq=a2 * a2,
        upper_arm_length_sq=length * length,
        two_a2_l=2.0 * a2 * length,
        reach_max=geom.reach + _REACH_TOL,
        reach_min=geom.min_reach - _REACH_TOL,
        bounds=tuple(
            (lo, hi, lo - LIMIT_TOL, hi + LIMIT_TOL) for lo, hi in zip(geom.lower, geom.upper, strict=True)
        ),
    )
    if len(_PARAMS_CACHE) >= _PARAMS_CACHE_MAX:
        _PARAMS_CACHE.clear()
    _PARAMS_CACHE[id(geom)] = (geom, params)
    return params


class _Chain(NamedTuple):
    """Joint-axis directions and link points of the serial chain (base frame, Python floats)."""

    y1: _Vec3  # R1[:, 1] (= R2[:, 1])
    x3: _Vec3  # R3[:, 0] (= R4[:, 0])
    y4: _Vec3  # R4[:, 1] (= R5[:, 1])
    x6: _Vec3  # R6[:, 0] (= R5[:, 0]), the tool axis
    y6: _Vec3  # R6[:, 1]
    z6: _Vec3  # R6[:, 2]
    p_j2: _Vec3
    p_j3: _Vec3
    p_j4: _Vec3
    p_wrist: _Vec3
    p_flange: _Vec3
    p_tcp: _Vec3


def _q_values(q: npt.ArrayLike, what: str = "q") -> list[float]:
    """``q`` checked to be 6 finite joint angles [rad]; returned as Python floats."""
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be 6 joint angles [rad]: {exc}") from exc
    if arr.shape != (6,):
        raise KinematicsError(f"{what} must have shape (6,), got {arr.shape}")
    values: list[float] = arr.tolist()
    # A finite sum implies finite terms (nan / inf propagate); only an overflow needs the full test.
    if not math.isfinite(sum(values)) and not all(map(math.isfinite, values)):
        raise KinematicsError(f"{what} must be finite, got {values}")
    return values


def _chain(q: npt.ArrayLike, geom: ArmGeometry) -> _Chain:
    """``R1 = Rz(q1)``, ``R3 = R1 Ry(q2 - q3)``, ``R4 = R3 Rx(q4)``, ``R5 = R4 Ry(-q5)``, ``R6 = R5 Rx(q6)``.

    Written out column by column in scalar arithmetic (numpy is slow on 3-vectors).
    """
    q1, q2, q3, q4, q5, q6 = _q_values(q)
    prm = _params(geom)
    cos, sin = math.cos, math.sin
    c1, s1 = cos(q1), sin(q1)
    c2, s2 = cos(q2), sin(q2)
    q23 = q2 - q3
    c23, s23 = cos(q23), sin(q23)
    c4, s4 = cos(q4), sin(q4)
    c5, s5 = cos(q5), sin(q5)
    c6, s6 = cos(q6), sin(q6)
    # R3 = Rz(q1) Ry(q23): columns x3, y1, z3.
    x3x, x3y, x3z = c1 * c23, s1 * c23, -s23
    z3x, z3y, z3z = c1 * s23, s1 * s23, c23
    # R4 = R3 Rx(q4): y4 = c4 y1 + s4 z3, z4 = -s4 y1 + c4 z3.
    y4x, y4y, y4z = c4 * -s1 + s4 * z3x, c4 * c1 + s4 * z3y, s4 * z3z
    z4x, z4y, z4z = -s4 * -s1 + c4 * z3x, -s4 * c1 + c4 * z3y, c4 * z3z
    # R5 = R4 Ry(-q5): x5 = c5 x3 + s5 z4, z5 = -s5 x3 + c5 z4 (y5 = y4).
    x5x, x5y, x5z = c5 * x3x + s5 * z4x, c5 * x3y + s5 * z4y, c5 * x3z + s5 * z4z
    z5x, z5y, z5z = -s5 * x3x + c5 * z4x, -s5 * x3y + c5 * z4y, -s5 * x3z + c5 * z4z
    # R6 = R5 Rx(q6): x6 = x5, y6 = c6 y4 + s6 z5, z6 = -s6 y4 + c6 z5.
    y6 = (c6 * y4x + s6 * z5x, c6 * y4y + s6 * z5y, c6 * y4z + s6 * z5z)
    z6 = (-s6 * y4x + c6 * z5x, -s6 * y4y + c6 * z5y, -s6 * y4z + c6 * z5z)
    a2, a3, d4, d6, tool = prm.a2, prm.a3, prm.d4, prm.d6, prm.tool
    d1 = prm.d1
    # Link points; R2[:, 2] = (c1 s2, s1 s2, c2).
    j3x, j3y, j3z = a2 * (c1 * s2), a2 * (s1 * s2), d1 + a2 * c2
    j4x, j4y, j4z = j3x + a3 * z3x, j3y + a3 * z3y, j3z + a3 * z3z
    wx, wy, wz = j4x + d4 * x3x, j4y + d4 * x3y, j4z + d4 * x3z
    fx, fy, fz = wx + d6 * x5x, wy + d6 * x5y, wz + d6 * x5z
    return _Chain(
        y1=(-s1, c1, 0.0),
        x3=(x3x, x3y, x3z),
        y4=(y4x, y4y, y4z),
        x6=(x5x, x5y, x5z),
        y6=y6,
        z6=z6,
        p_j2=(0.0, 0.0, d1),
        p_j3=(j3x, j3y, j3z),
        p_j4=(j4x, j4y, j4z),
        p_wrist=(wx, wy, wz),
        p_flange=(fx, fy, fz),
        p_tcp=(fx + tool * x5x, fy + tool * x5y, fz + tool * x5z),
    )


def fk(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """TCP pose ``(4, 4)`` in the base frame for joint angles ``q`` ``(6,)`` [rad]."""
    c = _chain(q, geom)
    x, y, z, p = c.x6, c.y6, c.z6, c.p_tcp
    return np.array(
        [
            [x[0], y[0], z[0], p[0]],
            [x[1], y[1], z[1], p[1]],
            [x[2], y[2], z[2], p[2]],
            [0.0, 0.0, 0.0, 1.0],
        ],
        dtype=np.float64,
    )


def fk_frames(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Link points ``(7, 3)`` [m] in the base frame, for drawing the arm.

    Rows: base origin, J2 (shoulder), J3 (elbow), J4 point (end of the A3 offset), wrist
    centre, flange, TCP (tool tip).
    """
    c = _chain(q, geom)
    return np.array(
        [(0.0, 0.0, 0.0), c.p_j2, c.p_j3, c.p_j4, c.p_wrist, c.p_flange, c.p_tcp], dtype=np.float64
    )


def wrist_center(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Wrist centre (intersection of J4, J5, J6) ``(3,)`` [m] in the base frame."""
    return np.array(_chain(q, geom).p_wrist, dtype=np.float64)


def jacobian(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """Geometric Jacobian ``(6, 6)`` of the TCP in the base frame.

    ``[v; ω] = J @ qdot`` with ``v`` the TCP linear velocity [m/s], ``ω`` the angular velocity
    [rad/s] (both in base coordinates) and ``qdot`` [rad/s]. Column i is
    ``[z_i × (p_tcp - p_i); z_i]`` for joint axis ``z_i`` through point ``p_i``.
    """
    c = _chain(q, geom)
    y1, y4 = c.y1, c.y4
    axes = (
        (0.0, 0.0, 1.0),
        y1,
        (-y1[0], -y1[1], -y1[2]),
        c.x3,
        (-y4[0], -y4[1], -y4[2]),
        c.x6,
    )
    points = ((0.0, 0.0, 0.0), c.p_j2, c.p_j3, c.p_j4, c.p_wrist, c.p_wrist)
    tx, ty, tz = c.p_tcp
    columns = []
    for (ax, ay, az), (px, py, pz) in zip(axes, points, strict=True):
        dx, dy, dz = tx - px, ty - py, tz - pz
        columns.append((ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx, ax, ay, az))
    return np.array(list(zip(*columns, strict=True)), dtype=np.float64)


def within_limits(q: npt.ArrayLike, geom: ArmGeometry = MH3F, tol: float = 0.0) -> bool:
    """True if every joint of ``q`` ``(6,)`` [rad] is within its limits (± ``tol`` [rad])."""
    values = _q_values(q)
    return all(v >= lo - tol for v, lo in zip(values, geom.lower, strict=True)) and all(
        v <= hi + tol for v, hi in zip(values, geom.upper, strict=True)
    )


# --------------------------------------------------------------------------------------------
# Inverse kinematics
# --------------------------------------------------------------------------------------------


def _as_pose(T: npt.ArrayLike) -> list[list[float]]:
    """``T`` checked to be a finite 4x4 with a proper rotation block; its rows as Python floats."""
    try:
        arr = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise IKError(f"target pose must be a numeric 4x4 transform: {exc}") from exc
    if arr.shape != (4, 4):
        raise IKError(f"target pose must have shape (4, 4), got {arr.shape}")
    rows: list[list[float]] = arr.tolist()
    r0, r1, r2, r3 = rows
    # A finite sum implies finite terms (nan / inf propagate); only an overflow needs the full test.
    if not math.isfinite(sum(r0) + sum(r1) + sum(r2) + sum(r3)) and not all(
        math.isfinite(v) for row in rows for v in row
    ):
        raise IKError("target pose contains non-finite values")
    a, b, c = r0[0], r0[1], r0[2]
    d, e, f = r1[0], r1[1], r1[2]
    g, h, i = r2[0], r2[1], r2[2]
    # |RᵀR - I| (RᵀR is symmetric) and det(R), in scalars: the fast test for a proper rotation.
    err = max(
        abs(a * a + d * d + g * g - 1.0),
        abs(b * b + e * e + h * h - 1.0),
        abs(c * c + f * f + i * i - 1.0),
        abs(a * b + d * e + g * h),
        abs(a * c + d * f + g * i),
        abs(b * c + e * f + h * i),
    )
    det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    if not (err <= 1e-6 and det >= 0.0):
        # Rejected (or undecided): the reference test in numpy decides and gives the message.
        R = arr[:3, :3]
        err = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if err > 1e-6 or np.linalg.det(R) < 0.0:
            raise IKError(f"target rotation is not a proper rotation matrix (|RᵀR - I| = {err:.2e})")
    return rows


def _wrist_reference(q1: float, q23: float, R: FloatArray, q4_ref: float) -> list[tuple[float, float, float]]:
    """``(q4, q5, q6)`` of one arm branch from 3x3 numpy products (the reference arithmetic).

    The scalar code in :func:`_ik_candidates` is the same formula, but BLAS (with FMA) rounds
    differently in the last bit. That only decides exact ties such as the mirrored limit
    violations of two wrist-flip branches, so the error message is built from these values.
    """
    R36 = (rot_z(q1) @ rot_y(q23)).T @ R
    sin_b = math.hypot(float(R36[1, 0]), float(R36[2, 0]))
    if sin_b > WRIST_SINGULAR_TOL:
        a0 = math.atan2(float(R36[1, 0]), float(-R36[2, 0]))
        q4s: tuple[float, ...] = (a0, a0 + math.pi)
    else:
        q4s = (q4_ref,)
    out = []
    for q4 in q4s:
        M = rot_x(q4).T @ R36  # = Ry(-q5) Rx(q6)
        q5 = -math.atan2(float(-M[2, 0]), float(M[0, 0]))
        q6 = math.atan2(float(-M[1, 2]), float(M[1, 1]))
        out.append((q4, q5, q6))
    return out


def _ik_candidates(
    T: npt.ArrayLike, geom: ArmGeometry, q_ref: list[float] | None, *, reference: bool = False
) -> tuple[list[tuple[float, ...]], str | None]:
    """All analytic IK branches (up to 8 of 6 angles) with every angle wrapped to [-π, π], limits ignored.

    Returns ``([], reason)`` when the wrist centre is out of reach. Raises IKError for a
    malformed pose. ``reference=True`` takes the wrist angles from :func:`_wrist_reference`.
    """
    rows = _as_pose(T)
    R_ref = np.asarray(T, dtype=np.float64)[:3, :3] if reference else None
    r00, r01, r02, px = rows[0]
    r10, r11, r12, py = rows[1]
    r20, r21, r22, pz = rows[2]
    prm = _params(geom)
    k = prm.wrist_to_tcp
    wx, wy, wz = px - k * r00, py - k * r10, pz - k * r20  # W = p - (d6 + tool) R[:, 0]
    rxy = math.hypot(wx, wy)
    z = wz - prm.d1
    dist = math.hypot(rxy, z)

    if dist > prm.reach_max:
        return [], (
            f"target wrist centre is {dist:.3f} m from the shoulder (J2 axis), beyond the "
            f"reach of {geom.reach:.3f} m (tip {geom.wrist_to_tcp:.3f} m from the wrist centre)"
        )
    if dist < prm.reach_min:
        return [], (
            f"target wrist centre is {dist:.4f} m from the shoulder (J2 axis), inside the "
            f"minimum reach of {geom.min_reach:.4f} m"
        )

    cos, sin, atan2, rem = math.cos, math.sin, math.atan2, math.remainder

    # J1: front and back branch; on the J1 axis q1 is free, so keep the reference.
    q1_ref = q_ref[0] if q_ref is not None else 0.0
    q1_front = q1_ref if rxy < SHOULDER_SINGULAR_TOL else atan2(wy, wx)

    # J3: elbow up / down from the law of cosines on (a2, L); q3 and the second atan2 of q2
    # depend on the elbow branch only.
    L, a2 = prm.upper_arm_length, prm.a2
    s = (dist * dist - prm.a2_sq - prm.upper_arm_length_sq) / prm.two_a2_l
    psi0 = math.asin(min(1.0, max(-1.0, s)))
    elbows = [
        (psi - prm.upper_arm_angle, atan2(L * cos(psi), a2 + L * sin(psi))) for psi in (psi0, math.pi - psi0)
    ]

    q4_ref = q_ref[3] if q_ref is not None else 0.0
    out: list[tuple[float, ...]] = []
    for q1, x in ((q1_front, rxy), (q1_front + math.pi, -rxy)):
        c1, s1 = cos(q1), sin(q1)
        # R36 = R3ᵀ R with R3 = Rz(q1) Ry(q2 - q3) = [x3, y1, z3]; its row 1 is y1ᵀ R, y1 = (-s1, c1, 0).
        b10 = -s1 * r00 + c1 * r10
        b11 = -s1 * r01 + c1 * r11
        b12 = -s1 * r02 + c1 * r12
        q2_plane = atan2(x, z)
        w1 = rem(q1, TWO_PI)
        for q3, elbow_term in elbows:
            q2 = q2_plane - elbow_term
            q23 = q2 - q3
            c23, s23 = cos(q23), sin(q23)
            x3x, x3y = c1 * c23, s1 * c23
            z3x, z3y = c1 * s23, s1 * s23
            b00 = x3x * r00 + x3y * r10 + -s23 * r20
            b20 = z3x * r00 + z3y * r10 + c23 * r20
            b21 = z3x * r01 + z3y * r11 + c23 * r21
            b22 = z3x * r02 + z3y * r12 + c23 * r22
            w2, w3 = rem(q2, TWO_PI), rem(q3, TWO_PI)
            if R_ref is not None:
                for q4, q5, q6 in _wrist_reference(q1, q23, R_ref, q4_ref):
                    out.append((w1, w2, w3, rem(q4, TWO_PI), rem(q5, TWO_PI), rem(q6, TWO_PI)))
                continue
            if math.hypot(b10, b20) > WRIST_SINGULAR_TOL:  # |sin q5|
                a0 = atan2(b10, -b20)
                q4s: tuple[float, ...] = (a0, a0 + math.pi)
            else:
                q4s = (q4_ref,)
            for q4 in q4s:
                # M = Rx(q4)ᵀ R36 = Ry(-q5) Rx(q6)
                c4, s4 = cos(q4), sin(q4)
                q5 = -atan2(-(-s4 * b10 + c4 * b20), b00)
                q6 = atan2(-(c4 * b12 + s4 * b22), c4 * b11 + s4 * b21)
                out.append((w1, w2, w3, rem(q4, TWO_PI), rem(q5, TWO_PI), rem(q6, TWO_PI)))
    return out, None


def _within_limit_solutions(
    cands: list[tuple[float, ...]], bounds: tuple[tuple[float, float, float, float], ...]
) -> list[tuple[float, ...]]:
    """Every distinct within-limit solution: each joint's ``value + 2πk`` in [lo - LIMIT_TOL,
    hi + LIMIT_TOL], clipped onto [lo, hi], combined over the joints, in candidate order.

    ``bounds`` are the per-joint ``(lo, hi, lo - LIMIT_TOL, hi + LIMIT_TOL)`` of :func:`_params`.
    """
    ceil, floor = math.ceil, math.floor
    sols: list[tuple[float, ...]] = []
    for cand in cands:
        options: list[tuple[float, ...]] = []
        several = False
        for v, (lo, hi, lo_tol, hi_tol) in zip(cand, bounds, strict=True):
            k_min = ceil((lo_tol - v) / TWO_PI)
            k_max = floor((hi_tol - v) / TWO_PI)
            if k_min == k_max:
                options.append((min(hi, max(lo, v + k_min * TWO_PI)),))
            elif k_min > k_max:
                break  # no variant of this joint within its limits: the branch yields nothing
            else:
                several = True
                options.append(tuple(min(hi, max(lo, v + k * TWO_PI)) for k in range(k_min, k_max + 1)))
        else:
            combos = itertools.product(*options) if several else (tuple([o[0] for o in options]),)
            for combo in combos:
                c0, c1, c2, c3, c4, c5 = combo
                for s in sols:  # duplicate if every joint is within 1e-9 rad
                    if (
                        abs(c0 - s[0]) < 1e-9
                        and abs(c1 - s[1]) < 1e-9
                        and abs(c2 - s[2]) < 1e-9
                        and abs(c3 - s[3]) < 1e-9
                        and abs(c4 - s[4]) < 1e-9
                        and abs(c5 - s[5]) < 1e-9
                    ):
                        break
                else:
                    sols.append(combo)
    return sols


def _nearest(sols: list[tuple[float, ...]], qc: list[float], w: list[float] | None) -> int:
    """Index of the first solution with the smallest ``sum(w * (s - qc)²)`` (like ``np.argmin``)."""
    q0, q1, q2, q3, q4, q5 = qc
    best_i, best = 0, math.inf
    for i, (s0, s1, s2, s3, s4, s5) in enumerate(sols):
        d0, d1, d2, d3, d4, d5 = s0 - q0, s1 - q1, s2 - q2, s3 - q3, s4 - q4, s5 - q5
        if w is None:
            cost = d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3 + d4 * d4 + d5 * d5
        else:
            cost = (
                w[0] * (d0 * d0)
                + w[1] * (d1 * d1)
                + w[2] * (d2 * d2)
                + w[3] * (d3 * d3)
                + w[4] * (d4 * d4)
                + w[5] * (d5 * d5)
            )
        if cost < best:
            best_i, best = i, cost
        elif cost != cost:  # nan (0 weight times an overflowed square): argmin takes the first nan
            return i
    return best_i


def _limit_violation_message(cands: list[tuple[float, ...]], geom: ArmGeometry) -> str:
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
    ref = None if q_ref is None else _q_values(q_ref, "q_ref")
    cands, _ = _ik_candidates(T, geom, ref)
    return [np.array(s, dtype=np.float64) for s in _within_limit_solutions(cands, _params(geom).bounds)]


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
    qc = _q_values(q_current, "q_current")
    w = None
    if weights is not None:
        w = _q_values(weights, "weights")
        if any(v < 0.0 for v in w):
            raise KinematicsError(f"weights must be >= 0, got {w}")
    cands, reason = _ik_candidates(T, geom, qc)
    if reason is not None:
        raise IKError(reason)
    sols = _within_limit_solutions(cands, _params(geom).bounds)
    if not sols:
        cands, _ = _ik_candidates(T, geom, qc, reference=True)
        raise IKError(_limit_violation_message(cands, geom))
    return np.array(sols[_nearest(sols, qc, w)], dtype=np.float64)
