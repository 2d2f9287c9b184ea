"""Vectorised (numpy) forms of the MH3F 6-axis IK and the trocar-mode IK: many targets per call.

The same closed form as :func:`telesurg.shared.robots.mh3f.kinematics.ik` and
:func:`telesurg.shared.robots.mh3f.trocar.trocar_ik`, evaluated on arrays: every target's 8 branches at
once, each joint's ``2πk`` variant inside its limits nearest the reference, then the branch
nearest the reference (plain L2, the first on a tie, as the scalar solvers). For offline work —
workspace maps, trajectory checks, the benchmark — where a Python call per target costs more than
the arithmetic. A target the scalar solver refuses (out of reach, only outside the limits, tip
not beyond the trocar or deeper than the forceps) comes back with ``ok`` False and NaN joints;
the scalar solver gives the reason.

Example::

    q, ok = trocar_ik_batch(tips, trocar, q_current)   # tips (N, 3) -> q (N, 6), ok (N,)
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError
from telesurg.shared.robots.mh3f.kinematics import (
    MH3F,
    SHOULDER_SINGULAR_TOL,
    WRIST_SINGULAR_TOL,
    ArmGeometry,
    _params,
    fk,
)
from telesurg.shared.robots.mh3f.trocar import _POINT_TOL, MIN_TIP_DEPTH

TWO_PI = 2.0 * np.pi


def _rem(x: np.ndarray) -> np.ndarray:
    """``math.remainder(x, 2π)`` elementwise: into [-π, π], ties to even like IEEE remainder."""
    return x - TWO_PI * np.round(x / TWO_PI)


def _reference(q: npt.ArrayLike, what: str) -> np.ndarray:
    a = np.asarray(q, dtype=np.float64)
    if a.shape != (6,) or not np.all(np.isfinite(a)):
        raise KinematicsError(f"{what} must be 6 finite joint angles [rad], got {q!r}")
    return a


def ik_batch(
    T: npt.ArrayLike, q_ref: npt.ArrayLike, geom: ArmGeometry = MH3F
) -> tuple[np.ndarray, np.ndarray]:
    """Poses ``T`` ``(N, 4, 4)`` → joints ``(N, 6)`` nearest ``q_ref`` ``(6,)``, and ``ok`` ``(N,)``.

    Row ``i`` equals ``ik(T[i], q_ref, geom)`` where that succeeds (to rounding), NaN where it
    raises IKError.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise KinematicsError(f"T must be (N, 4, 4) finite poses, got shape {T.shape}")
    qc = _reference(q_ref, "q_ref")
    prm = _params(geom)
    r = T[:, :3, :3]
    r00, r01, r02 = r[:, 0, 0], r[:, 0, 1], r[:, 0, 2]
    r10, r11, r12 = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    r20, r21, r22 = r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    k = prm.wrist_to_tcp
    wx, wy, wz = T[:, 0, 3] - k * r00, T[:, 1, 3] - k * r10, T[:, 2, 3] - k * r20
    rxy = np.hypot(wx, wy)
    z = wz - prm.d1
    dist = np.hypot(rxy, z)
    reachable = (dist <= prm.reach_max) & (dist >= prm.reach_min)
    q1_front = np.where(rxy < SHOULDER_SINGULAR_TOL, qc[0], np.arctan2(wy, wx))
    L, a2 = prm.upper_arm_length, prm.a2
    s = np.clip((dist * dist - prm.a2_sq - prm.upper_arm_length_sq) / prm.two_a2_l, -1.0, 1.0)
    psi0 = np.arcsin(s)
    elbows = []
    for psi in (psi0, np.pi - psi0):
        elbows.append((psi - prm.upper_arm_angle, np.arctan2(L * np.cos(psi), a2 + L * np.sin(psi))))

    cands, valid = [], []
    for q1, x in ((q1_front, rxy), (q1_front + np.pi, -rxy)):
        c1, s1 = np.cos(q1), np.sin(q1)
        b10 = -s1 * r00 + c1 * r10
        b11 = -s1 * r01 + c1 * r11
        b12 = -s1 * r02 + c1 * r12
        q2_plane = np.arctan2(x, z)
        for q3, elbow_term in elbows:
            q2 = q2_plane - elbow_term
            q23 = q2 - q3
            c23, s23 = np.cos(q23), np.sin(q23)
            b00 = c1 * c23 * r00 + s1 * c23 * r10 - s23 * r20
            b20 = c1 * s23 * r00 + s1 * s23 * r10 + c23 * r20
            b21 = c1 * s23 * r01 + s1 * s23 * r11 + c23 * r21
            b22 = c1 * s23 * r02 + s1 * s23 * r12 + c23 * r22
            singular = np.hypot(b10, b20) <= WRIST_SINGULAR_TOL
            a0 = np.arctan2(b10, -b20)
            for flip in (0.0, np.pi):
                q4 = np.where(singular, qc[3], a0 + flip)
                c4, s4 = np.cos(q4), np.sin(q4)
                q5 = -np.arctan2(-(-s4 * b10 + c4 * b20), b00)
                q6 = np.arctan2(-(c4 * b12 + s4 * b22), c4 * b11 + s4 * b21)
                cands.append(np.stack([_rem(v) for v in (q1, q2, q3, q4, q5, q6)], axis=-1))
                # at a singular wrist the scalar solver has one q4, not two
                valid.append(reachable & ~(singular & (flip > 0.0)))
    C = np.stack(cands, axis=1)  # (N, 8, 6)
    ok_branch = np.stack(valid, axis=1)  # (N, 8)

    # each joint's 2πk variant inside [lo, hi] (with LIMIT_TOL) nearest q_ref, clipped onto [lo, hi]
    lo = np.array([b[0] for b in prm.bounds])
    hi = np.array([b[1] for b in prm.bounds])
    lo_tol = np.array([b[2] for b in prm.bounds])
    hi_tol = np.array([b[3] for b in prm.bounds])
    k_min = np.ceil((lo_tol - C) / TWO_PI)
    k_max = np.floor((hi_tol - C) / TWO_PI)
    k_best = np.clip(np.round((qc - C) / TWO_PI), k_min, k_max)
    ok_branch &= np.all(k_min <= k_max, axis=-1)
    S = np.clip(C + k_best * TWO_PI, lo, hi)
    cost = np.where(ok_branch, np.sum((S - qc) ** 2, axis=-1), np.inf)
    best = np.argmin(cost, axis=1)
    ok = np.isfinite(cost[np.arange(len(T)), best])
    q = S[np.arange(len(T)), best]
    q[~ok] = np.nan
    return q, ok


def trocar_ik_batch(
    tips: npt.ArrayLike,
    trocar: npt.ArrayLike,
    q_current: npt.ArrayLike,
    geom: ArmGeometry = MH3F,
    *,
    min_depth: float = MIN_TIP_DEPTH,
) -> tuple[np.ndarray, np.ndarray]:
    """Tip targets ``(N, 3)`` → joints ``(N, 6)`` with the forceps axis through ``trocar``, and ``ok``.

    Row ``i`` equals ``trocar_ik(tips[i], trocar, q_current, geom=geom, min_depth=min_depth)``
    (roll kept continuous with ``q_current``) where that succeeds, NaN where it raises IKError.
    """
    p = np.asarray(tips, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise KinematicsError(f"tips must be (N, 3) finite points [m], got shape {p.shape}")
    c = np.asarray(trocar, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise KinematicsError(f"trocar must be a finite point (3,) [m], got {trocar!r}")
    T_cur = fk(_reference(q_current, "q_current"), geom)
    w_cur = T_cur[:3, 3] - geom.wrist_to_tcp * T_cur[:3, 0]
    u = c - w_cur
    u_norm = float(np.linalg.norm(u))
    if u_norm < _POINT_TOL:
        raise KinematicsError("the current wrist centre coincides with the trocar")
    v = p - c
    dist = np.linalg.norm(v, axis=1)
    depth = v @ u / u_norm
    ok = (depth >= min_depth - _POINT_TOL) & (dist <= geom.tool)
    d = v / np.where(dist > 0.0, dist, 1.0)[:, None]
    # roll continuity: the current y axis projected ⟂ d (or, with d along it, the current z axis)
    y = T_cur[:3, 1] - d * (d @ T_cur[:3, 1])[:, None]
    ny = np.linalg.norm(y, axis=1)
    zc = T_cur[:3, 2] - d * (d @ T_cur[:3, 2])[:, None]
    zc /= np.maximum(np.linalg.norm(zc, axis=1), 1e-300)[:, None]
    y = np.where((ny < 1e-6)[:, None], np.cross(zc, d), y / np.maximum(ny, 1e-300)[:, None])
    z = np.cross(d, y)
    T = np.zeros((len(p), 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = d, y, z, p
    T[:, 3, 3] = 1.0
    q, ok_ik = ik_batch(T, q_current, geom)
    ok &= ok_ik
    q[~ok] = np.nan
    return q, ok
