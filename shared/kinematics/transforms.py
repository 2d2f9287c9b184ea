"""Small SO(3) / SE(3) helpers in pure numpy.

Conventions
-----------
* Rotation matrices are active, right-handed, shape ``(3, 3)``: ``v_parent = R @ v_child``.
* Homogeneous transforms are shape ``(4, 4)``: ``[[R, p], [0, 0, 0, 1]]`` with ``p`` in metres.
* Angles are in radians.
* **Quaternions are ordered [x, y, z, w]** (scalar last), shape ``(4,)``, Hamilton convention —
  the same order as ROS ``geometry_msgs/Quaternion``, rerun ``Quaternion(xyzw=...)`` and
  ``scipy.spatial.transform.Rotation.as_quat()``. :func:`quat_from_matrix` returns the canonical
  sign ``w >= 0`` (for ``w == 0`` the first non-zero of x, y, z is made positive).
* Rotation vectors (axis * angle, radians) are shape ``(3,)``; :func:`rotvec_from_matrix` is the
  SO(3) logarithm and :func:`matrix_from_rotvec` the exponential.

Every function validates shape and finiteness and raises
:class:`telesurg.shared.errors.KinematicsError` (a ``ValueError``) on bad input.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "FloatArray",
    "make_transform",
    "matrix_from_quat",
    "matrix_from_rotvec",
    "quat_from_matrix",
    "quat_normalize",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_angle_between",
    "rotvec_from_matrix",
    "rpy_matrix",
    "skew",
]


def _as_array(x: npt.ArrayLike, shape: tuple[int, ...], what: str) -> FloatArray:
    """Return ``x`` as a finite float64 array of exactly ``shape``, else raise KinematicsError."""
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise KinematicsError(f"{what} must be numeric with shape {shape}: {exc}") from exc
    if arr.shape != shape:
        raise KinematicsError(f"{what} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise KinematicsError(f"{what} must be finite, got {arr.tolist()}")
    return arr


def rot_x(a: float) -> FloatArray:
    """Rotation about +x by ``a`` radians. Returns ``(3, 3)``."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=np.float64)


def rot_y(a: float) -> FloatArray:
    """Rotation about +y by ``a`` radians (positive turns +z toward +x). Returns ``(3, 3)``."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=np.float64)


def rot_z(a: float) -> FloatArray:
    """Rotation about +z by ``a`` radians (positive turns +x toward +y). Returns ``(3, 3)``."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)


def rpy_matrix(rpy_deg: tuple[float, float, float]) -> FloatArray:
    """R = Rz(yaw) · Ry(pitch) · Rx(roll) from ``(roll, pitch, yaw)`` in **degrees** (e.g. the
    mapping's ``master_to_slave_rpy_deg``)."""
    r, p, y = np.radians(rpy_deg)
    out: FloatArray = rot_z(float(y)) @ rot_y(float(p)) @ rot_x(float(r))
    return out


def make_transform(R: npt.ArrayLike, p: npt.ArrayLike) -> FloatArray:
    """Transform ``(4, 4)`` from rotation ``R`` ``(3, 3)`` and position ``p`` ``(3,)`` [m]."""
    rot = _as_array(R, (3, 3), "R")
    pos = _as_array(p, (3,), "p")
    T = np.eye(4, dtype=np.float64)
    T[:3, :3] = rot
    T[:3, 3] = pos
    return T


def skew(v: npt.ArrayLike) -> FloatArray:
    """Cross-product matrix ``(3, 3)`` of ``v`` ``(3,)``: ``skew(v) @ u == np.cross(v, u)``."""
    x, y, z = _as_array(v, (3,), "v")
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=np.float64)


def quat_normalize(q: npt.ArrayLike) -> FloatArray:
    """Unit quaternion ``(4,)`` [x, y, z, w] with the same sign as ``q``.

    Raises KinematicsError if ``q`` has (near) zero norm.
    """
    arr = _as_array(q, (4,), "quaternion")
    n = float(np.linalg.norm(arr))
    if n < 1e-12:
        raise KinematicsError(f"cannot normalize a zero quaternion {arr.tolist()}")
    return arr / n


def quat_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """Unit quaternion ``(4,)`` [x, y, z, w] of rotation matrix ``R`` ``(3, 3)``.

    Shepperd's method: the largest of ``(trace, R00, R11, R22)`` picks which component is
    computed from a square root, so the division is always by a number >= 1/2 — accurate for
    every rotation, including 180° turns. The result is canonical: ``w >= 0``.
    """
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = _as_array(R, (3, 3), "R").tolist()
    # in plain floats: numpy indexing of a 3×3 costs ~20× more, and this runs per published pose
    tr = m00 + m11 + m22
    diag = (tr, m00, m11, m22)
    k = diag.index(max(diag))
    if k == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = ((m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s)
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + m00 - m11 - m22, 0.0))
        q = (0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s)
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - m00 + m11 - m22, 0.0))
        q = ((m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 - m00 - m11 + m22, 0.0))
        q = ((m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])  # >= 1/2 by the choice of k
    x, y, z, w = (v / n for v in q)
    # canonical sign: w > 0, or for a half turn (w = 0) the first non-zero component > 0
    first = next((v for v in (x, y, z) if v != 0.0), 0.0)
    if w < 0.0 or (w == 0.0 and first < 0.0):
        x, y, z, w = -x, -y, -z, -w
    return np.array((x, y, z, w), dtype=np.float64)


def _unit_quat_floats(q: npt.ArrayLike) -> tuple[float, float, float, float]:
    """:func:`quat_normalize` as four floats. A tuple of four finite floats (a message's
    orientation, every master sample) is normalised in plain arithmetic, without the ~10 µs of
    numpy validation; anything else goes through :func:`quat_normalize` and its errors."""
    if isinstance(q, tuple) and len(q) == 4 and all(type(v) is float for v in q):
        x, y, z, w = q
        n = math.sqrt(x * x + y * y + z * z + w * w)
        if math.isfinite(n) and n >= 1e-12:
            return (x / n, y / n, z / n, w / n)
    a, b, c, d = quat_normalize(q).tolist()
    return (a, b, c, d)


def matrix_from_quat(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrix ``(3, 3)`` of quaternion ``q`` ``(4,)`` [x, y, z, w] (normalized first)."""
    x, y, z, w = _unit_quat_floats(q)
    return np.array(
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
            [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
            [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
        ],
        dtype=np.float64,
    )


def rotvec_from_matrix(R: npt.ArrayLike) -> FloatArray:
    """SO(3) logarithm: rotation vector ``(3,)`` (unit axis * angle [rad], angle in [0, π]).

    Goes through the canonical quaternion, so it stays accurate near 0 and near π.
    """
    quat = quat_from_matrix(R)
    v = quat[:3].copy()
    w = float(quat[3])
    sin_half = float(np.linalg.norm(v))
    if sin_half < 1e-12:
        # angle = 2 asin(|v|) ≈ 2|v| / w; w ≈ 1 here.
        return v * (2.0 / w)
    angle = 2.0 * math.atan2(sin_half, w)
    return (angle / sin_half) * v


def matrix_from_rotvec(v: npt.ArrayLike) -> FloatArray:
    """SO(3) exponential: rotation matrix ``(3, 3)`` of rotation vector ``v`` ``(3,)`` [rad]."""
    vec = _as_array(v, (3,), "rotation vector")
    angle = float(np.linalg.norm(vec))
    K = skew(vec)
    if angle < 1e-8:
        # Second-order Taylor series; the truncation error (~angle³) is below float precision.
        return np.eye(3, dtype=np.float64) + K + 0.5 * (K @ K)
    a = math.sin(angle) / angle
    b = (1.0 - math.cos(angle)) / (angle * angle)
    return np.eye(3, dtype=np.float64) + a * K + b * (K @ K)


def rotation_angle_between(R1: npt.ArrayLike, R2: npt.ArrayLike) -> float:
    """Angle [rad] in [0, π] of the relative rotation ``R1ᵀ R2`` (both ``(3, 3)``).

    Uses ``atan2(sin, cos)`` of the relative rotation rather than ``acos`` of the trace, so
    tiny angles (1e-12 rad) are resolved to full precision.
    """
    a = _as_array(R1, (3, 3), "R1")
    b = _as_array(R2, (3, 3), "R2")
    rel = a.T @ b
    sin_v = 0.5 * math.sqrt(
        (rel[2, 1] - rel[1, 2]) ** 2 + (rel[0, 2] - rel[2, 0]) ** 2 + (rel[1, 0] - rel[0, 1]) ** 2
    )
    cos_v = 0.5 * (rel[0, 0] + rel[1, 1] + rel[2, 2] - 1.0)
    return math.atan2(sin_v, cos_v)
