"""Trocar mode of the forceps-holding 6-axis arm: RCM kinematics and the J4/J5 posture adjustment.

After M. Jinno, "Master–slave manipulator for laparoscopic surgery using a 6-axis vertical
articulated robot", ROBOMECH Journal 1:23 (2014). Units: metres and radians.

The forceps axis is the TCP x axis of :func:`telesurg.shared.robots.mh3f.kinematics.fk`; it passes through the
wrist centre W (J4, J5 and J6 intersect there, the paper's condition 1) and coincides with J6
(condition 2). The trocar (the entry point into the abdominal wall) is a fixed point ``c`` in the
base frame; in trocar mode the forceps axis must pass through it (remote centre of motion).

Trocar-mode IK (paper, Fig. 3, five steps)
------------------------------------------
1. Forceps wrist from the TCP pose: the identity for the straight forceps used here (J7/J8 of an
   articulated forceps are not implemented, see :class:`Forceps`).
2. Manipulator wrist from the tip and the trocar: the axis direction is ``d = unit(tip - c)`` and
   ``W = tip - (d6 + tool) d``.
3. J1-J3 from W, 4. J4-J5 from the trocar direction, 5. J6 from the roll about ``d``.

Steps 3-5 are exactly the decoupled analytic IK of :func:`~telesurg.shared.robots.mh3f.kinematics.ik`
applied to
the TCP pose ``[R, tip]`` with ``R[:, 0] = d``; :func:`trocar_ik` builds that pose (choosing the
roll) and calls it, so the nearest branch to the current joints is kept.

Roll convention
---------------
The roll about the forceps axis ``d`` is the angle from a reference axis ``y_ref`` to the TCP y
axis, right-handed about ``d``: ``y = cos(roll) y_ref + sin(roll) (d × y_ref)``, ``z = d × y``.
``y_ref = unit(ẑ × d)`` with ẑ the base +z (up): the horizontal direction perpendicular to the
axis. At ``q = 0`` (``d = +x``) this gives ``y_ref = +y`` and roll 0 is the identity orientation.
When ``d`` is within :data:`ROLL_REF_SINGULAR_TOL` of vertical, ``ẑ × d`` is undefined and
``y_ref`` is the base +y axis projected onto the plane normal to ``d``. Near vertical the
reference turns quickly with ``d`` (any fixed-reference convention must, somewhere); for smooth
master-slave motion pass ``roll=None``, which keeps the current TCP y axis as close as possible.

Posture adjustment (transitional mode)
--------------------------------------
With J1-J3 fixed, W is fixed; J4/J5 turn the forceps axis to point from W at the trocar. The axis
in frame 3 (``R03 = Rz(q1) Ry(q2 - q3)``, ``R36 = Rx(q4) Ry(-q5) Rx(q6)``) is
``R36 e_x = Rx(q4) (cos q5, 0, sin q5) = (cos q5, -sin q4 sin q5, cos q4 sin q5)``. Setting it to
``v = R03ᵀ unit(c - W)`` gives ``q5 = atan2(hypot(v1, v2), v0)``, ``q4 = atan2(-v1, v2)`` or the
wrist flip ``(q4 + π, -q5)``; see :func:`posture_adjust`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.mh3f.kinematics import (
    LIMIT_TOL,
    MH3F,
    WRIST_SINGULAR_TOL,
    ArmGeometry,
    _q_values,
    fk,
    ik,
    wrist_center,
)

__all__ = [
    "MIN_TIP_DEPTH",
    "ROLL_REF_SINGULAR_TOL",
    "STRAIGHT_FORCEPS",
    "TROCAR_MODE_DEPTH",
    "Forceps",
    "axis_angle_to_trocar",
    "forceps_roll",
    "insertion_depth",
    "interpolate_posture",
    "posture_adjust",
    "posture_duration",
    "rcm_error",
    "roll_reference",
    "trocar_ik",
]

MIN_TIP_DEPTH = 0.005
"""Default minimum distance [m] of the tip target beyond the trocar in :func:`trocar_ik`.

Closer than this the axis ``trocar → tip`` is ill defined (0.1 mm of tip noise at 5 mm is 1.1°).
"""

TROCAR_MODE_DEPTH = 0.050
"""Insertion depth [m] past the trocar from which the paper switches to trocar mode."""

ROLL_REF_SINGULAR_TOL = 1e-6
"""``|ẑ × d|`` (sine of the axis tilt from vertical) below which the roll reference is base +y."""

_POINT_TOL = 1e-9  # [m] two points closer than this are treated as coincident
_Vec3 = tuple[float, float, float]


# ------------------------------------------------------------------------------------------
# Tool description
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Forceps:
    """Description of the forceps held by the arm (the tool on the flange).

    The straight forceps (``wrist_joints=0``: a laparoscope, a conventional forceps or the
    paper's 500 mm dummy forceps) is fully described by its length; its tip is the TCP on the
    flange x axis. An articulated forceps (paper, Fig. 2: J7 and J8 at the distal end, crossing
    the J6 axis at one point) is accepted as a description, but its kinematics (steps 1 and 5
    of the trocar-mode IK) are not implemented: :meth:`arm_geometry` refuses it.

    Attributes:
        length_m: flange (mechanical interface) to tip along the J6 axis [m]; for an articulated
            forceps, flange to the forceps wrist point.
        wrist_joints: number of joints at the forceps tip (0: straight; 2: J7/J8 of Fig. 2).
    """

    length_m: float = 0.500
    wrist_joints: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.length_m) and self.length_m > 0.0):
            raise KinematicsError(f"Forceps.length_m must be finite and > 0, got {self.length_m}")
        if self.wrist_joints < 0:
            raise KinematicsError(f"Forceps.wrist_joints must be >= 0, got {self.wrist_joints}")

    @property
    def articulated(self) -> bool:
        """True if the forceps has joints at its tip (J7, J8, ...)."""
        return self.wrist_joints > 0

    def arm_geometry(self, base: ArmGeometry = MH3F) -> ArmGeometry:
        """``base`` with ``tool = length_m``: the geometry every function of this module takes.

        Build it once and reuse it (the kinematics cache derived constants per geometry object).

        Raises:
            NotImplementedError: for an articulated forceps (``wrist_joints > 0``).
        """
        if self.articulated:
            raise NotImplementedError(
                f"articulated forceps ({self.wrist_joints} tip joints, J7/J8 of the paper's Fig. 2) "
                "are not implemented: trocar-mode IK steps 1 and 5 (forceps wrist and J7/J8) are "
                "missing; only the straight forceps (wrist_joints=0) is supported"
            )
        return replace(base, tool=self.length_m)


STRAIGHT_FORCEPS = Forceps()
"""The paper's dummy forceps: straight, Ø5 mm, 350 mm shaft, 500 mm from flange to tip."""


# ------------------------------------------------------------------------------------------
# Small scalar helpers (numpy is slow on 3-vectors)
# ------------------------------------------------------------------------------------------


def _point(x: npt.ArrayLike, what: str) -> _Vec3:
    """``x`` checked to be a finite 3-vector [m]; returned as Python floats."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be a 3-vector [m]: {exc}") from exc
    if arr.shape != (3,):
        raise KinematicsError(f"{what} must have shape (3,), got {arr.shape}")
    a, b, c = arr.tolist()
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(c)):
        raise KinematicsError(f"{what} must be finite, got {[a, b, c]}")
    return a, b, c


def _sub(a: _Vec3, b: _Vec3) -> _Vec3:
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _dot(a: _Vec3, b: _Vec3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: _Vec3, b: _Vec3) -> _Vec3:
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _norm(a: _Vec3) -> float:
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def _scaled(a: _Vec3, k: float) -> _Vec3:
    return a[0] * k, a[1] * k, a[2] * k


def _fmt(p: _Vec3) -> str:
    return f"({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f})"


def _tool_line(q: npt.ArrayLike, geom: ArmGeometry) -> tuple[_Vec3, _Vec3, FloatArray]:
    """``(tip [m], unit forceps axis, TCP pose (4, 4))`` of the arm at ``q`` (from :func:`fk`)."""
    T = fk(q, geom)
    rows: list[list[float]] = T[:3].tolist()
    tip = (rows[0][3], rows[1][3], rows[2][3])
    axis = (rows[0][0], rows[1][0], rows[2][0])
    return tip, axis, T


# ------------------------------------------------------------------------------------------
# Measures of a pose relative to the trocar
# ------------------------------------------------------------------------------------------


def rcm_error(q: npt.ArrayLike, trocar: npt.ArrayLike, geom: ArmGeometry = MH3F) -> float:
    """Distance [m] from the trocar point to the forceps axis line of the arm at ``q``.

    The line is the whole infinite TCP x axis (through W and the tip), as in the paper's Fig. 13.

    Args:
        q: joint angles ``(6,)`` [rad].
        trocar: trocar point ``(3,)`` [m], base frame.
        geom: arm geometry (``tool`` = forceps length).
    """
    tip, axis, _ = _tool_line(q, geom)
    return pose_to_trocar(tip, axis, trocar)[0]


def pose_to_trocar(tip: npt.ArrayLike, axis: npt.ArrayLike, trocar: npt.ArrayLike) -> tuple[float, float]:
    """``(rcm_error, insertion_depth)`` [m] of a *measured* forceps pose relative to the trocar.

    For a slave that measures its tip (e.g. MuJoCo's tip site, or a real arm's own forward
    kinematics): the forceps axis is the line through ``tip`` along ``axis`` (the TCP x axis,
    normalised here).

    Args:
        tip: forceps tip ``(3,)`` [m], base frame.
        axis: forceps axis direction ``(3,)``, toward the tip (any length > 0).
        trocar: trocar point ``(3,)`` [m], base frame.
    """
    t = _point(tip, "tip")
    a = _point(axis, "axis")
    n = _norm(a)
    if n < _POINT_TOL:
        raise KinematicsError("forceps axis direction has zero length")
    d = _scaled(a, 1.0 / n)
    c = _point(trocar, "trocar")
    rel = _sub(c, t)
    return _norm(_cross(rel, d)), -_dot(rel, d)


def insertion_depth(q: npt.ArrayLike, trocar: npt.ArrayLike, geom: ArmGeometry = MH3F) -> float:
    """Signed distance [m] along the forceps axis from the trocar to the tip.

    ``(tip - trocar) · x_tcp``: positive when the tip is past the trocar (inside the patient),
    0 with the tip at the trocar, negative while the tip is still outside. Measured along the
    axis, so it ignores a lateral :func:`rcm_error`.

    Args:
        q: joint angles ``(6,)`` [rad].
        trocar: trocar point ``(3,)`` [m], base frame.
        geom: arm geometry (``tool`` = forceps length).
    """
    tip, axis, _ = _tool_line(q, geom)
    return pose_to_trocar(tip, axis, trocar)[1]


def axis_angle_to_trocar(q: npt.ArrayLike, trocar: npt.ArrayLike, geom: ArmGeometry = MH3F) -> float:
    """Angle [rad] in [0, π] between the forceps axis and the direction wrist centre → trocar.

    0 means the forceps points at the trocar (the condition to allow the insert motion).

    Args:
        q: joint angles ``(6,)`` [rad].
        trocar: trocar point ``(3,)`` [m], base frame.
        geom: arm geometry.

    Raises:
        KinematicsError: if the trocar coincides with the wrist centre (no direction).
    """
    c = _point(trocar, "trocar")
    tip, axis, _ = _tool_line(q, geom)
    w = _sub(tip, _scaled(axis, geom.wrist_to_tcp))
    u = _sub(c, w)
    if _norm(u) < _POINT_TOL:
        raise KinematicsError(f"trocar {_fmt(c)} coincides with the wrist centre: no direction to it")
    return math.atan2(_norm(_cross(axis, u)), _dot(axis, u))


# ------------------------------------------------------------------------------------------
# Roll about the forceps axis
# ------------------------------------------------------------------------------------------


def _roll_reference(d: _Vec3) -> _Vec3:
    """Unit roll reference ``y_ref`` ⟂ unit axis ``d`` (see the module docstring)."""
    r = (-d[1], d[0], 0.0)  # ẑ × d
    n = math.hypot(r[0], r[1])
    if n < ROLL_REF_SINGULAR_TOL:
        r = (-d[1] * d[0], 1.0 - d[1] * d[1], -d[1] * d[2])  # ŷ - (ŷ·d) d
        n = _norm(r)
    return _scaled(r, 1.0 / n)


def roll_reference(axis: npt.ArrayLike) -> FloatArray:
    """Roll reference ``y_ref`` ``(3,)`` for a forceps axis direction ``axis`` ``(3,)``.

    ``unit(ẑ × d)`` (horizontal, ⟂ the axis), or base +y projected ⟂ ``d`` when the axis is
    within :data:`ROLL_REF_SINGULAR_TOL` of vertical. ``axis`` need not be unit length.

    Raises:
        KinematicsError: if ``axis`` is (near) zero.
    """
    a = _point(axis, "axis")
    n = _norm(a)
    if n < 1e-12:
        raise KinematicsError(f"axis must be non-zero, got {list(a)}")
    return np.array(_roll_reference(_scaled(a, 1.0 / n)), dtype=np.float64)


def forceps_roll(q: npt.ArrayLike, geom: ArmGeometry = MH3F) -> float:
    """Roll [rad] in (-π, π] of the TCP y axis about the forceps axis, from :func:`roll_reference`.

    The inverse of the ``roll`` argument of :func:`trocar_ik`.
    """
    _, d, T = _tool_line(q, geom)
    y = (float(T[0, 1]), float(T[1, 1]), float(T[2, 1]))
    y_ref = _roll_reference(d)
    return math.atan2(_dot(y, _cross(d, y_ref)), _dot(y, y_ref))


def _tcp_frame(d: _Vec3, roll: float | None, T_current: FloatArray) -> tuple[_Vec3, _Vec3]:
    """TCP ``(y, z)`` axes for the forceps axis ``d`` (unit): given ``roll``, or nearest current y."""
    if roll is not None:
        y_ref = _roll_reference(d)
        e = _cross(d, y_ref)
        c, s = math.cos(roll), math.sin(roll)
        y = (c * y_ref[0] + s * e[0], c * y_ref[1] + s * e[1], c * y_ref[2] + s * e[2])
    else:
        # Projecting the current y onto the plane ⟂ d maximises y · y_current.
        y_cur = (float(T_current[0, 1]), float(T_current[1, 1]), float(T_current[2, 1]))
        y = _sub(y_cur, _scaled(d, _dot(y_cur, d)))
        n = _norm(y)
        if n < 1e-6:  # the axis turned onto the old y axis: keep the old z axis instead
            z_cur = (float(T_current[0, 2]), float(T_current[1, 2]), float(T_current[2, 2]))
            z = _sub(z_cur, _scaled(d, _dot(z_cur, d)))
            z = _scaled(z, 1.0 / _norm(z))
            return _cross(z, d), z
        y = _scaled(y, 1.0 / n)
    return y, _cross(d, y)


# ------------------------------------------------------------------------------------------
# Trocar-mode inverse kinematics
# ------------------------------------------------------------------------------------------


def trocar_ik(
    tip: npt.ArrayLike,
    trocar: npt.ArrayLike,
    q_current: npt.ArrayLike,
    roll: float | None = None,
    geom: ArmGeometry = MH3F,
    *,
    min_depth: float = MIN_TIP_DEPTH,
) -> FloatArray:
    """Joint angles putting the forceps tip at ``tip`` with the forceps axis through ``trocar``.

    The forceps axis is the line trocar → tip (``d = unit(tip - trocar)``, the TCP x axis), the
    roll about it is ``roll`` (see the module docstring) or, if None, the one keeping the current
    TCP y axis closest; the 6-axis analytic :func:`~telesurg.shared.robots.mh3f.kinematics.ik` then returns
    the
    solution nearest ``q_current``.

    The tip must lie at least ``min_depth`` beyond the trocar as seen from the current wrist
    centre, i.e. ``(tip - trocar) · unit(trocar - W(q_current)) >= min_depth``; that refuses a
    tip at, beside or behind the trocar (which would swing the arm through the patient). It must
    also be at most ``geom.tool`` beyond it (the flange cannot pass the trocar).

    Args:
        tip: tip target ``(3,)`` [m], base frame.
        trocar: trocar point ``(3,)`` [m], base frame.
        q_current: current joint angles ``(6,)`` [rad]: branch choice and continuity reference.
        roll: roll [rad] about the forceps axis, or None for continuity with ``q_current``.
        geom: arm geometry (``tool`` = forceps length, see :meth:`Forceps.arm_geometry`).
        min_depth: minimum tip distance beyond the trocar [m], > 0.

    Returns:
        Joint angles ``(6,)`` [rad]; their kinematic RCM error is at rounding level (~1e-15 m).

    Raises:
        IKError: tip too close to / behind the trocar, deeper than the forceps length, out of
            reach or only reachable outside the joint limits (the message says by how much).
        KinematicsError: malformed inputs.
    """
    p = _point(tip, "tip")
    c = _point(trocar, "trocar")
    if not (math.isfinite(min_depth) and min_depth > 0.0):
        raise KinematicsError(f"min_depth must be finite and > 0 [m], got {min_depth}")
    if roll is not None and not math.isfinite(roll):
        raise KinematicsError(f"roll must be finite [rad] or None, got {roll}")
    tip_cur, axis_cur, T_cur = _tool_line(q_current, geom)
    w_cur = _sub(tip_cur, _scaled(axis_cur, geom.wrist_to_tcp))

    # Step 2 of the paper: the axis direction, checked against the side of the trocar.
    u = _sub(c, w_cur)
    u_norm = _norm(u)
    if u_norm < _POINT_TOL:
        raise IKError(f"trocar IK: the current wrist centre coincides with the trocar {_fmt(c)}")
    v = _sub(p, c)
    dist = _norm(v)
    depth = _dot(v, u) / u_norm
    if depth < min_depth - _POINT_TOL:  # 1 nm slack: a tip exactly at min_depth passes
        side = f"{-depth * 1e3:.2f} mm behind" if depth < 0.0 else f"only {depth * 1e3:.2f} mm beyond"
        raise IKError(
            f"trocar IK: tip {_fmt(p)} is {side} the trocar {_fmt(c)} (seen from the current wrist "
            f"centre); it must be at least {min_depth * 1e3:.2f} mm beyond it, or the forceps axis "
            "(trocar → tip) is undefined or would swing through the patient"
        )
    if dist > geom.tool:
        raise IKError(
            f"trocar IK: tip {_fmt(p)} is {dist:.4f} m beyond the trocar {_fmt(c)}, more than the "
            f"{geom.tool:.4f} m forceps length (flange to tip) by {dist - geom.tool:.4f} m"
        )
    d = _scaled(v, 1.0 / dist)

    # Steps 3-5: the analytic 6-axis IK of the pose [d, y, z | tip].
    y, z = _tcp_frame(d, roll, T_cur)
    T = np.array(
        [
            [d[0], y[0], z[0], p[0]],
            [d[1], y[1], z[1], p[1]],
            [d[2], y[2], z[2], p[2]],
            [0.0, 0.0, 0.0, 1.0],
        ],
        dtype=np.float64,
    )
    try:
        return ik(T, q_current, geom)
    except IKError as exc:
        raise IKError(
            f"trocar IK: tip {_fmt(p)} {dist * 1e3:.1f} mm beyond the trocar {_fmt(c)} "
            f"(axis {_fmt(d)}): {exc}"
        ) from exc


# ------------------------------------------------------------------------------------------
# Posture adjustment by J4 and J5 (transitional mode)
# ------------------------------------------------------------------------------------------


def _wraps(value: float, lo: float, hi: float) -> list[float]:
    """Every ``value + 2πk`` within ``[lo - LIMIT_TOL, hi + LIMIT_TOL]``, clipped onto ``[lo, hi]``."""
    two_pi = 2.0 * math.pi
    k_min = math.ceil((lo - LIMIT_TOL - value) / two_pi)
    k_max = math.floor((hi + LIMIT_TOL - value) / two_pi)
    return [min(hi, max(lo, value + k * two_pi)) for k in range(k_min, k_max + 1)]


def _violation(value: float, lo: float, hi: float) -> tuple[float, float]:
    """``(smallest limit violation [rad], that wrap of value)`` over ``value + 2πk``."""
    options = [math.remainder(value, 2.0 * math.pi) + k * 2.0 * math.pi for k in (-1, 0, 1)]
    return min((max(lo - o, o - hi, 0.0), o) for o in options)


def posture_adjust(q: npt.ArrayLike, trocar: npt.ArrayLike, geom: ArmGeometry = MH3F) -> FloatArray:
    """J4/J5 that point the forceps axis from the wrist centre at the trocar (J1-J3, J6 kept).

    The paper's posture adjustment: W depends on J1-J3 only, so turning J4/J5 aligns the axis
    with W → trocar and the axis then passes through the trocar (``rcm_error = 0``). With
    ``v = R03ᵀ unit(trocar - W)`` (frame 3 after J1-J3) and the tool axis in frame 3
    ``(cos q5, -sin q4 sin q5, cos q4 sin q5)``, the solutions are
    ``(atan2(-v1, v2), atan2(hypot(v1, v2), v0))`` and its wrist flip ``(q4 + π, -q5)``; the
    one within the limits nearest ``q`` (L2 over J4, J5, all 2π wraps) is returned. With the
    trocar straight ahead (``q5 = 0``, singular) J4 stays at its current value.

    The same computation gives the J4/J5 set-points in trocar mode under direct teach. In the
    transitional mode check :func:`insertion_depth` afterwards: a negative value means the tip
    is still outside, as it must be before the insert motion.

    Args:
        q: current joint angles ``(6,)`` [rad].
        trocar: trocar point ``(3,)`` [m], base frame.
        geom: arm geometry.

    Returns:
        ``q`` with J4 and J5 replaced, ``(6,)`` [rad].

    Raises:
        IKError: the trocar coincides with the wrist centre, or both wrist solutions violate
            the J4/J5 limits (the message names the nearest violation).
    """
    qv = _q_values(q, "q")
    c = _point(trocar, "trocar")
    w = wrist_center(qv, geom).tolist()
    u = _sub(c, (w[0], w[1], w[2]))
    n = _norm(u)
    if n < _POINT_TOL:
        raise IKError(f"posture adjustment: the trocar {_fmt(c)} coincides with the wrist centre")
    ux, uy, uz = _scaled(u, 1.0 / n)
    q1, q2, q3, q4_cur, q5_cur, _ = qv
    c1, s1 = math.cos(q1), math.sin(q1)
    c23, s23 = math.cos(q2 - q3), math.sin(q2 - q3)
    # v = R03ᵀ u with R03 = Rz(q1) Ry(q2 - q3) = [x3, y1, z3].
    v0 = c1 * c23 * ux + s1 * c23 * uy - s23 * uz
    v1 = -s1 * ux + c1 * uy
    v2 = c1 * s23 * ux + s1 * s23 * uy + c23 * uz
    sin5 = math.hypot(v1, v2)
    q5 = math.atan2(sin5, v0)
    if sin5 > WRIST_SINGULAR_TOL:
        q4 = math.atan2(-v1, v2)
        cands = [(q4, q5), (q4 + math.pi, -q5)]
    else:
        cands = [(q4_cur, q5)]  # q5 = 0 (axis already aligned) or π (trocar straight behind)

    (lo4, lo5), (hi4, hi5) = geom.lower[3:5], geom.upper[3:5]
    best: tuple[float, float] | None = None
    best_cost = math.inf
    for a4, a5 in cands:
        for w4 in _wraps(a4, lo4, hi4):
            for w5 in _wraps(a5, lo5, hi5):
                cost = (w4 - q4_cur) ** 2 + (w5 - q5_cur) ** 2
                if cost < best_cost:
                    best, best_cost = (w4, w5), cost
    if best is None:
        raise IKError(_posture_limit_message(cands, c, geom))
    out = np.array(qv, dtype=np.float64)
    out[3], out[4] = best
    return out


def _posture_limit_message(cands: list[tuple[float, float]], c: _Vec3, geom: ArmGeometry) -> str:
    """Name the J4/J5 limit violation of the wrist solution that comes closest."""
    worst_per_cand = []
    for a4, a5 in cands:
        v4 = (*_violation(a4, geom.lower[3], geom.upper[3]), 3)
        v5 = (*_violation(a5, geom.lower[4], geom.upper[4]), 4)
        worst_per_cand.append(max(v4, v5))
    viol, angle, j = min(worst_per_cand)
    name = geom.joint_names[j]
    return (
        f"posture adjustment toward the trocar {_fmt(c)}: both wrist solutions violate the joint "
        f"limits; the nearest violates {name} by {math.degrees(viol):.1f}° ({name} = "
        f"{math.degrees(angle):.1f}°, limits [{math.degrees(geom.lower[j]):.1f}°, "
        f"{math.degrees(geom.upper[j]):.1f}°])"
    )


def _posture_pair(q_from: npt.ArrayLike, q_to: npt.ArrayLike) -> tuple[list[float], list[float]]:
    """Both joint vectors, checked to differ in J4/J5 only (by at most 1e-12 rad elsewhere)."""
    a = _q_values(q_from, "q_from")
    b = _q_values(q_to, "q_to")
    for j in (0, 1, 2, 5):
        if abs(a[j] - b[j]) > 1e-12:
            raise KinematicsError(
                f"posture motion moves J4 and J5 only, but joint {j + 1} differs by "
                f"{abs(a[j] - b[j]):.3e} rad ({a[j]:.6f} → {b[j]:.6f})"
            )
    return a, b


def interpolate_posture(q_from: npt.ArrayLike, q_to: npt.ArrayLike, s: float) -> FloatArray:
    """Synchronous point-to-point J4/J5 motion: the pose at fraction ``s`` in [0, 1].

    Linear in joint space with one common ``s``, so J4 and J5 start and arrive together:
    ``q4(s) = (1 - s) q4_from + s q4_to`` (likewise q5; exact at s = 0 and s = 1). The other
    joints are those of ``q_from``. Time-scale ``s`` with :func:`posture_duration`.

    Args:
        q_from: start joints ``(6,)`` [rad].
        q_to: goal joints ``(6,)`` [rad], e.g. :func:`posture_adjust` of ``q_from``.
        s: path fraction in [0, 1].

    Raises:
        KinematicsError: ``s`` outside [0, 1], or the poses differ in J1-J3 or J6.
    """
    if not (0.0 <= s <= 1.0):
        raise KinematicsError(f"posture interpolation fraction s must be in [0, 1], got {s}")
    a, b = _posture_pair(q_from, q_to)
    out = np.array(a, dtype=np.float64)
    out[3] = (1.0 - s) * a[3] + s * b[3]
    out[4] = (1.0 - s) * a[4] + s * b[4]
    return out


def posture_duration(
    q_from: npt.ArrayLike, q_to: npt.ArrayLike, geom: ArmGeometry = MH3F, speed_fraction: float = 1.0
) -> float:
    """Shortest time [s] of the synchronous J4/J5 move at ``speed_fraction`` of the joint speeds.

    ``max(|Δq4| / v4, |Δq5| / v5) / speed_fraction`` with the speed limits of ``geom``
    [rad/s]: the slower joint sets the time and the other one is slowed to arrive with it.

    Raises:
        KinematicsError: ``speed_fraction`` not in (0, 1], or the poses differ in J1-J3 or J6.
    """
    if not (0.0 < speed_fraction <= 1.0):
        raise KinematicsError(f"speed_fraction must be in (0, 1], got {speed_fraction}")
    a, b = _posture_pair(q_from, q_to)
    v4, v5 = geom.max_velocity[3:5]
    return max(abs(b[3] - a[3]) / v4, abs(b[4] - a[4]) / v5) / speed_fraction
