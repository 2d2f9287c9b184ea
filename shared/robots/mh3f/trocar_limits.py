"""Reach, depth and speed limits of trocar mode: the nearest feasible target, and the way out.

Jinno 2014 runs master–slave in trocar mode with the forceps pivoting about the trocar (the
remote centre of motion, RCM). A master target the arm cannot reach (wrist centre beyond the
arm's reach, a joint limit, deeper than the forceps, at or behind the trocar) or cannot reach in
one sample without exceeding the joint speeds of the paper's Table 1 must not make the slave
hold: :func:`clamped_trocar_ik` returns the nearest feasible target on the way to it, solved by
:func:`~telesurg.shared.robots.mh3f.trocar.trocar_ik` so the RCM stays exact, and says what it
clamped. :func:`remove_step` is one period of the removal (retraction along the forceps axis):
where the straight retraction leaves the arm's reach it pivots the forceps about the trocar
toward the arm while it keeps retracting, so removal never stops at the reach limit.

Units: metres, radians, seconds. Pure (numpy in, numpy out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import IKError, KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.mh3f.kinematics import MH3F, ArmGeometry, fk, ik, within_limits
from telesurg.shared.robots.mh3f.trocar import MIN_TIP_DEPTH, trocar_ik

__all__ = ["TROCAR_SPEED_FRACTION", "ClampedTarget", "clamped_trocar_ik", "remove_step"]

#: Fraction of the joint speed limits a trocar-mode master–slave step may use. The arm's servos
#: lag a fast command joint by joint, and the lags bend the forceps axis off the trocar: an
#: RCM-exact pivot that starts and stops abruptly (a master that jumps after a stall of its
#: console) left the RCM of the MuJoCo MH3F by at most 0.23 mm at 0.4 × the limits, 0.30 mm at
#: 0.5 ×, 1.4 mm at 0.7 × and 3.1 mm at 0.875 × (3 starts, 60/110 mm deep, two directions;
#: docs/trocar.md). The slave's catch-up stays within 0.5 × (services/slave_control/arm.py).
TROCAR_SPEED_FRACTION = 0.4

_PIVOT_MIN_DEPTH = 0.002  # [m] below this depth removal no longer pivots (axis ill defined)
_BISECT_STEPS = 8  # bisection on the path fraction: 2^-8 of the sample's tip step


@dataclass(frozen=True)
class ClampedTarget:
    """The result of :func:`clamped_trocar_ik`.

    Attributes:
        q: joint angles ``(6,)`` [rad] to command; their kinematic RCM error is at rounding level.
        tip: the tip ``(3,)`` [m] they put the forceps at.
        clamped: what limited the target, empty when the requested target was used as it is:
            ``"depth"`` (insertion depth clamped into its range), ``"reach"`` (reach or joint
            limits: stopped at the last feasible point toward the target), ``"speed"`` (a joint
            would exceed its speed limit in this sample: the tip goes only part of the way).
        detail: one line saying what was clamped and by how much (empty if nothing was).
    """

    q: FloatArray
    tip: FloatArray
    clamped: tuple[str, ...] = ()
    detail: str = ""


def _depth_clamp(p: FloatArray, c: FloatArray, u: FloatArray, lo: float, hi: float) -> tuple[FloatArray, str]:
    """``p`` with its distance beyond the trocar (along ``p - c``) clamped into ``[lo, hi]``.

    ``u`` is the unit direction wrist → trocar: a tip behind or beside the trocar (depth along
    ``u`` below ``lo``) is moved along ``u`` to depth ``lo``, never through the patient wall.
    """
    v = p - c
    depth = float(v @ u)
    if depth < lo:
        lateral = v - depth * u
        q = c + lo * u + lateral
        # a target far to the side at small depth: keep its direction, bounded tilt
        return q, f"depth {depth * 1e3:.1f} → {lo * 1e3:.1f} mm"
    dist = float(np.linalg.norm(v))
    if dist > hi:
        return c + v * (hi / dist), f"depth {dist * 1e3:.1f} → {hi * 1e3:.1f} mm"
    return p, ""


def _reach_clamp(p: FloatArray, c: FloatArray, geom: ArmGeometry, margin: float) -> tuple[FloatArray, str]:
    """``p`` pivoted about the trocar (same depth) so the wrist centre is within reach − margin.

    The wrist centre of a tip ``p`` at depth ``δ = |p − c|`` lies on the sphere of radius
    ``L − δ`` about the trocar (``L`` = wrist to tip); within reach it must also lie inside the
    sphere of radius ``reach − margin`` about the shoulder (J2 axis, ``(0, 0, d1)``). If it does
    not, the nearest point of the two spheres' intersection circle to it is taken: the smallest
    pivot that keeps the depth. Returned unchanged when within reach or when the spheres do not
    intersect (left to the bisection of :func:`clamped_trocar_ik`).
    """
    s = np.array([0.0, 0.0, geom.d1])
    v = p - c
    delta = float(np.linalg.norm(v))
    if delta < 1e-9:
        return p, ""
    d = v / delta
    r1 = geom.wrist_to_tcp - delta
    w = c - r1 * d
    r2 = geom.reach - margin
    dist_w = float(np.linalg.norm(w - s))
    if dist_w <= r2:
        return p, ""
    e = s - c
    a = float(np.linalg.norm(e))
    if not (abs(r1 - r2) < a < r1 + r2):
        return p, ""
    e /= a
    x = (a * a + r1 * r1 - r2 * r2) / (2.0 * a)
    rho = math.sqrt(max(r1 * r1 - x * x, 0.0))
    rel = w - c
    perp = rel - float(rel @ e) * e
    n = float(np.linalg.norm(perp))
    if n < 1e-12:
        return p, ""
    w_new = c + x * e + rho * perp / n
    d_new = (c - w_new) / float(np.linalg.norm(c - w_new))
    angle = math.degrees(math.acos(max(-1.0, min(1.0, float(d @ d_new)))))
    note = f"reach: pivot {angle:.1f}° toward the arm (wrist {dist_w * 1e3:.0f} → {r2 * 1e3:.0f} mm from J2)"
    return c + delta * d_new, note


def clamped_trocar_ik(
    tip: npt.ArrayLike,
    trocar: npt.ArrayLike,
    q_last: npt.ArrayLike,
    dt: float,
    geom: ArmGeometry = MH3F,
    *,
    min_depth: float = 0.010,
    max_depth: float | None = None,
    speed_fraction: float = TROCAR_SPEED_FRACTION,
    reach_margin: float = 0.010,
) -> ClampedTarget:
    """Trocar IK toward ``tip`` limited to what the arm can reach and do within ``dt``.

    1. The depth beyond the trocar is clamped into ``[min_depth, max_depth]`` (``max_depth``
       default: the forceps length minus 150 mm, the part of the dummy forceps that is not shaft).
    2. If the (depth-clamped) target is out of reach or beyond a joint limit, or a joint would
       move faster than ``speed_fraction`` × its limit over ``dt``, the tip goes along the
       straight line from the current tip (``fk(q_last)``) toward the target only as far as is
       feasible (bisection, every candidate solved by the trocar IK: the RCM is exact).

    Args:
        tip: requested tip ``(3,)`` [m], base frame.
        trocar: trocar ``(3,)`` [m], base frame.
        q_last: joints ``(6,)`` [rad] commanded last (feasible, axis through the trocar).
        dt: time [s] since ``q_last`` was commanded (the master's clock), > 0 for any motion.
        geom: arm geometry (``tool`` = forceps length).
        min_depth, max_depth: insertion depth range [m].
        speed_fraction: fraction of the joint speed limits (``geom.max_velocity``) allowed
            (:data:`TROCAR_SPEED_FRACTION`): the servos keep the RCM within tenths of a millimetre
            at it, and the margin leaves the slave room to follow the setpoints on its own clock,
            and make up a stall, without clipping them (a clipped step leaves the RCM).
        reach_margin: the wrist centre is kept this far [m] inside the arm's reach (near full
            stretch the elbow is singular and J2/J3 would have to move arbitrarily fast).

    Returns:
        :class:`ClampedTarget`; ``q`` is ``q_last`` itself if not even a small step is feasible.

    Raises:
        KinematicsError: malformed inputs.
    """
    q0 = np.asarray(q_last, dtype=np.float64)
    c = np.asarray(trocar, dtype=np.float64)
    p = np.asarray(tip, dtype=np.float64)
    if q0.shape != (6,) or c.shape != (3,) or p.shape != (3,):
        raise KinematicsError("clamped_trocar_ik: q_last (6,), trocar (3,) and tip (3,) expected")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(c)) and math.isfinite(dt)):
        raise KinematicsError("clamped_trocar_ik: tip, trocar and dt must be finite")
    hi = geom.tool - 0.150 if max_depth is None else max_depth
    T0 = fk(q0, geom)
    p0 = T0[:3, 3]
    w0 = p0 - geom.wrist_to_tcp * T0[:3, 0]
    u = c - w0
    u /= np.linalg.norm(u)
    p_req, depth_note = _depth_clamp(p, c, u, max(min_depth, MIN_TIP_DEPTH), hi)
    p_req, reach_note = _reach_clamp(p_req, c, geom, reach_margin)
    vmax = np.asarray(geom.max_velocity, dtype=np.float64) * speed_fraction * max(dt, 0.0)

    why: list[str] = []

    over: list[float] = []  # speed ratio of the last infeasible solution (its largest joint)

    def solve(target: FloatArray) -> FloatArray | None:
        try:
            q = trocar_ik(target, c, q0, geom=geom)
        except IKError as exc:
            why.append("reach")
            why.append(str(exc))
            return None
        if np.any(np.abs(q - q0) > vmax):
            over.append(float(np.max(np.abs(q - q0) / np.maximum(vmax, 1e-12))))
            why.append("speed")
            j = int(np.argmax(np.abs(q - q0) / np.maximum(vmax, 1e-12)))
            why.append(f"{geom.joint_names[j]} {abs(q[j] - q0[j]) / max(dt, 1e-9):.2f} rad/s")
            return None
        return q

    q = solve(p_req)
    clamped = [k for k, n in (("depth", depth_note), ("reach", reach_note)) if n]
    notes = [n for n in (depth_note, reach_note) if n]
    if q is not None:
        return ClampedTarget(q, p_req, tuple(clamped), "; ".join(notes))
    first_why = list(why)
    lo_s, hi_s, best = 0.0, 1.0, q0
    if first_why[0] == "speed" and over and math.isfinite(over[0]) and over[0] > 1.0:
        # joint speed only: the joints scale about linearly with a short tip step, so the
        # fraction 1 / ratio (a little less) is usually feasible at once; bisect above it
        s_guess = 0.98 / over[0]
        q_guess = solve(p0 + s_guess * (p_req - p0))
        if q_guess is not None:
            lo_s, best = s_guess, q_guess
        else:
            hi_s = s_guess
    for _ in range(_BISECT_STEPS if lo_s == 0.0 else 0):
        mid = 0.5 * (lo_s + hi_s)
        qm = solve(p0 + mid * (p_req - p0))
        if qm is None:
            hi_s = mid
        else:
            lo_s, best = mid, qm
    kind = first_why[0]
    if kind not in clamped:
        clamped.append(kind)
    tip_out = p0 + lo_s * (p_req - p0)
    short = float(np.linalg.norm(p_req - tip_out)) * 1e3
    notes.append(f"{kind}: tip stopped {short:.1f} mm short of the target ({first_why[1]})")
    return ClampedTarget(best, tip_out if best is not q0 else p0, tuple(clamped), "; ".join(notes))


def remove_step(
    q: npt.ArrayLike,
    trocar: npt.ArrayLike,
    step_m: float,
    geom: ArmGeometry = MH3F,
    *,
    pivot_rad: float = 0.001,
    exit_depth: float = -0.003,
) -> tuple[FloatArray, bool]:
    """One period of removal: the tip ``step_m`` back along the forceps axis, out of the patient.

    The straight retraction (orientation kept, the 6-axis IK) is used while the pose it ends in
    (tip at ``exit_depth``, outside the trocar) is within the arm's reach and joint limits: the
    wrist centre moves on a straight line, so every pose between is reachable too. Otherwise (the
    straight way out would leave the reach, as with the forceps tilted away from the arm) the
    forceps also pivots about the trocar by up to ``pivot_rad`` per period, solved by the trocar
    IK (axis through the trocar, depth reduced by ``step_m``), toward the axis whose exit pose
    brings the wrist centre nearest the shoulder: removal goes on instead of stopping at the
    reach limit.

    Args:
        q: current joints ``(6,)`` [rad], forceps in the trocar.
        trocar: trocar ``(3,)`` [m].
        step_m: retraction this period [m], > 0.
        geom: arm geometry.
        pivot_rad: largest pivot of the axis this period [rad].
        exit_depth: depth [m] (negative: outside) at which the removal ends.

    Returns:
        ``(joints, pivoted)``: the next joints, and whether the forceps pivoted.

    Raises:
        IKError: no retraction is feasible (neither straight nor pivoting), with the reason.
    """
    q0 = np.asarray(q, dtype=np.float64)
    c = np.asarray(trocar, dtype=np.float64)
    T = fk(q0, geom)
    d = T[:3, 0]
    depth = float((T[:3, 3] - c) @ d)
    T_exit = T.copy()
    T_exit[:3, 3] = T[:3, 3] - (depth - exit_depth) * d
    T_next = T.copy()
    T_next[:3, 3] = T[:3, 3] - step_m * d
    straight = ""
    try:
        if depth - step_m > _PIVOT_MIN_DEPTH:
            ik(T_exit, q0, geom)  # the straight way out must stay feasible to its end
        return ik(T_next, q0, geom), False
    except IKError as exc:
        straight = str(exc)
    new_depth = depth - step_m
    if new_depth < _PIVOT_MIN_DEPTH:
        raise IKError(f"remove: straight retraction infeasible at the trocar ({straight})")
    shoulder = np.array([0.0, 0.0, geom.d1])
    e1 = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(d, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    # candidates: the axis tilted by pivot_rad toward 8 azimuths, retracting; if none is feasible,
    # the same pivots in place (no retraction this period) until the retraction is feasible again
    best: tuple[float, FloatArray] | None = None
    for tip_depth in (new_depth, depth):
        for k in range(8):
            a = 2.0 * math.pi * k / 8.0
            dk = math.cos(pivot_rad) * d + math.sin(pivot_rad) * (math.cos(a) * e1 + math.sin(a) * e2)
            w_exit = c + (exit_depth - geom.wrist_to_tcp) * dk
            dist = float(np.linalg.norm(w_exit - shoulder))
            try:
                qk = trocar_ik(c + tip_depth * dk, c, q0, geom=geom, min_depth=_PIVOT_MIN_DEPTH / 2)
            except IKError:
                continue
            if within_limits(qk, geom) and (best is None or dist < best[0]):
                best = (dist, qk)
        if best is not None:
            break
    if best is None:
        raise IKError(
            f"remove: neither straight retraction ({straight}) nor a pivot of "
            f"{math.degrees(pivot_rad):.2f}° about the trocar is feasible"
        )
    return best[1], True
