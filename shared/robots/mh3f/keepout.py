"""Patient keep-out: the forceps may cross the patient's surface only through the trocar.

The patient is an axis-aligned box in the base frame (the scene's torso under the trocar); the
forceps shaft is the segment from the wrist centre to the tip along the TCP x axis (Jinno 2014:
the forceps axis passes through the wrist centre). A pose is allowed when the segment does not
touch the box, or when it enters the box within ``trocar_tol`` of the trocar with the forceps
axis through the trocar (RCM error ≤ ``trocar_tol``). A motion is checked along its planned joint
path at fine steps (:func:`path_problem`), so a sweep that passes through the patient between
two allowed end poses is found too. A followed command (master–slave, a policy: any ``servo_jp``)
is clamped at the surface instead (:func:`clamp_step`): each control period's step goes only as
far as the keep-out allows.

Units: metres and radians. Pure (numpy in, str/None out).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError
from telesurg.shared.robots.mh3f.kinematics import MH3F, ArmGeometry, fk

__all__ = ["PatientBox", "clamp_step", "path_problem", "pose_problem", "shaft_inside_m"]


@dataclass(frozen=True)
class PatientBox:
    """The patient's body as a box in the base frame, and the trocar through which it may be entered.

    Attributes:
        lo, hi: box corners [m], base frame (lo < hi on every axis).
        trocar: trocar point [m]; None: no entry allowed anywhere (no trocar taught).
        trocar_tol: how far [m] from the trocar the shaft may enter and the axis may pass.
    """

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    trocar: tuple[float, float, float] | None = None
    trocar_tol: float = 0.005

    def __post_init__(self) -> None:
        if any(
            not (math.isfinite(a) and math.isfinite(b) and a < b)
            for a, b in zip(self.lo, self.hi, strict=True)
        ):
            raise KinematicsError(f"patient box needs finite lo < hi on every axis, got {self.lo}, {self.hi}")


def _segment_entry(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float | None:
    """Fraction in [0, 1] along ``a → b`` where the segment first touches the box (slab method)."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for i in range(3):
        if abs(d[i]) < 1e-15:
            if a[i] < lo[i] or a[i] > hi[i]:
                return None
            continue
        ta, tb = (lo[i] - a[i]) / d[i], (hi[i] - a[i]) / d[i]
        if ta > tb:
            ta, tb = tb, ta
        t0, t1 = max(t0, ta), min(t1, tb)
        if t0 > t1:
            return None
    return t0


def pose_problem(q: npt.ArrayLike, box: PatientBox, geom: ArmGeometry = MH3F) -> str | None:
    """Why the arm at ``q`` violates the keep-out, or None if it does not."""
    T = fk(q, geom)
    tip = T[:3, 3]
    axis = T[:3, 0]
    w = tip - geom.wrist_to_tcp * axis
    lo, hi = np.array(box.lo), np.array(box.hi)
    s = _segment_entry(w, tip, lo, hi)
    if s is None:
        return None
    entry = w + s * (tip - w)
    if box.trocar is None:
        return (
            f"the forceps would enter the patient at ({', '.join(f'{v * 1e3:.0f}' for v in entry)}) mm "
            "with no trocar taught"
        )
    c = np.array(box.trocar)
    rcm = float(np.linalg.norm(np.cross(c - tip, axis)))
    off = float(np.linalg.norm(entry - c))
    if s > 0.0 and off <= box.trocar_tol + 1e-9 and rcm <= box.trocar_tol:
        return None
    where = ", ".join(f"{v * 1e3:.0f}" for v in entry)
    return (
        f"the forceps would cross the patient surface outside the trocar: at ({where}) mm, "
        f"{off * 1e3:.1f} mm from the trocar (axis {rcm * 1e3:.1f} mm off it; allowed "
        f"{box.trocar_tol * 1e3:.1f} mm)"
    )


def path_problem(
    q_from: npt.ArrayLike,
    q_to: npt.ArrayLike,
    box: PatientBox,
    geom: ArmGeometry = MH3F,
    *,
    max_step_rad: float = 0.005,
) -> str | None:
    """Why the straight joint-space path ``q_from → q_to`` violates the keep-out, or None.

    Checked at both ends and at steps of at most ``max_step_rad`` on every joint (0.005 rad moves
    the tip of the 0.86 m forceps arm by at most ~4 mm per joint), by forward kinematics.
    """
    a = np.asarray(q_from, dtype=np.float64)
    b = np.asarray(q_to, dtype=np.float64)
    n = max(1, math.ceil(float(np.max(np.abs(b - a))) / max_step_rad))
    for i in range(n + 1):
        q = a + (b - a) * (i / n)
        if problem := pose_problem(q, box, geom):
            return f"{problem} ({i / n:.0%} along the path)"
    return None


def shaft_inside_m(q: npt.ArrayLike, box: PatientBox, geom: ArmGeometry = MH3F) -> float:
    """Length [m] of the forceps shaft (wrist centre → tip) inside the box at ``q`` (0 outside).

    A pose already crossing the box may move, so that it can get out; whether it goes deeper is
    this length growing.
    """
    T = fk(q, geom)
    tip = T[:3, 3]
    w = tip - geom.wrist_to_tcp * T[:3, 0]
    lo, hi = np.array(box.lo), np.array(box.hi)
    enter = _segment_entry(w, tip, lo, hi)
    if enter is None:
        return 0.0
    leave = _segment_entry(tip, w, lo, hi)
    assert leave is not None  # the same segment, walked the other way
    return max(0.0, (1.0 - leave) - enter) * geom.wrist_to_tcp


#: m: a pose already crossing the box may move while its shaft inside does not grow by more than this
DEEPER_TOL_M = 1e-6


def _allowed(q: npt.ArrayLike, box: PatientBox, geom: ArmGeometry) -> bool:
    """:func:`pose_problem` is None, without its message: plain floats after the FK (the
    bisection of :func:`clamp_step` runs it ~10 times in one control period)."""
    r0, r1, r2, _ = fk(q, geom).tolist()
    ax, ay, az = r0[0], r1[0], r2[0]
    tx, ty, tz = r0[3], r1[3], r2[3]
    L = geom.wrist_to_tcp
    a, d = (tx - L * ax, ty - L * ay, tz - L * az), (L * ax, L * ay, L * az)
    t0, t1 = 0.0, 1.0
    for i in range(3):
        lo, hi = box.lo[i], box.hi[i]
        if abs(d[i]) < 1e-15:
            if a[i] < lo or a[i] > hi:
                return True
            continue
        ta, tb = (lo - a[i]) / d[i], (hi - a[i]) / d[i]
        if ta > tb:
            ta, tb = tb, ta
        t0, t1 = max(t0, ta), min(t1, tb)
        if t0 > t1:
            return True  # the shaft misses the box
    if box.trocar is None or t0 <= 0.0:
        return False
    cx, cy, cz = box.trocar
    ex, ey, ez = a[0] + t0 * d[0] - cx, a[1] + t0 * d[1] - cy, a[2] + t0 * d[2] - cz  # entry - trocar
    if math.sqrt(ex * ex + ey * ey + ez * ez) > box.trocar_tol + 1e-9:
        return False
    vx, vy, vz = cx - tx, cy - ty, cz - tz  # the trocar's distance from the axis
    wx, wy, wz = vy * az - vz * ay, vz * ax - vx * az, vx * ay - vy * ax
    return math.sqrt(wx * wx + wy * wy + wz * wz) <= box.trocar_tol


def clamp_step(
    q_from: npt.ArrayLike,
    q_to: npt.ArrayLike,
    box: PatientBox,
    geom: ArmGeometry = MH3F,
    *,
    iterations: int = 6,
    explain: bool = True,
) -> tuple[np.ndarray, str | None]:
    """One control period's step ``q_from → q_to`` clamped at the patient's surface.

    Returns ``(q, why)``: ``q_to`` itself and None when the keep-out allows it; else the farthest
    joints along the straight joint-space step whose pose the keep-out allows (bisection,
    ``iterations`` halvings: within 1/64 of the step, and a clamp that goes on closes in on the
    surface period by period) and why ``q_to`` was refused (with where only if ``explain``: a clamp that
    goes on needs no new message). A ``q_from`` already crossing the box (an arm
    started inside it) may move while its shaft inside does not grow (so it can get out); a step
    that would take it deeper stays at ``q_from``.

    Only the end of the step is judged: meant for one period of a speed-limited command (a few
    mrad), not for a long path (:func:`path_problem`). Cost: one FK when allowed (~10 µs), about
    ``iterations`` + 2 when clamped (~100 µs).
    """
    b = np.asarray(q_to, dtype=np.float64)
    if _allowed(b, box, geom):
        return b, None
    problem = (pose_problem(b, box, geom) if explain else None) or (
        "the forceps would cross the patient surface outside the trocar"
    )
    a = np.asarray(q_from, dtype=np.float64)
    if not _allowed(a, box, geom):
        if shaft_inside_m(b, box, geom) <= shaft_inside_m(a, box, geom) + DEEPER_TOL_M:
            return b, None
        return a.copy(), problem
    lo, hi = 0.0, 1.0
    al, dl = a.tolist(), (b - a).tolist()
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if _allowed([x + mid * d for x, d in zip(al, dl, strict=True)], box, geom):
            lo = mid
        else:
            hi = mid
    out: np.ndarray = a + (b - a) * lo
    return out, problem
