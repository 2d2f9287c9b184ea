"""The one kinematics interface of every arm, and a position solver for arms without analytic IK.

Every robot's arm (:class:`telesurg.shared.robots.ArmProfile`) is an :class:`ArmKinematics`:
``pose(q)`` — the controlled point's pose ``(4, 4)`` in the scene's world frame (the MuJoCo tip
site), ``jacobian(q)`` — its geometric Jacobian ``(6, n)`` (rows ``v`` then ``ω``, world
coordinates), and ``ik(target, q_near)`` where the robot has an analytic one (else it raises
:class:`~telesurg.shared.errors.IKError`). The per-robot maths stays in its own module
(:mod:`.mh3f`, :mod:`.plas` / :mod:`.plas_layout`, :mod:`.vip`, a plugin's own); the registry
adapts it to this interface.

:func:`solve_position` moves the controlled point to a target position by damped least squares on
``pose`` and ``jacobian`` alone, so any registered arm can be driven in Cartesian position (the
mapping's ``position`` mode); given ``keep_up`` it also keeps the instrument's tilt from the
vertical, turning it only about the vertical (the mapping's ``keep_tilt``: a held object stays
upright).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray

__all__ = ["DEFAULT_DAMPING", "TILT_WEIGHT", "ArmKinematics", "PositionSolution", "solve_position"]

DEFAULT_DAMPING = 1e-3
"""[m] damping λ of :func:`solve_position`: ``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ e``."""
TILT_WEIGHT = 0.05
"""[m/rad] weight of the tilt rows against the position rows in :func:`solve_position`."""


class ArmKinematics(Protocol):
    """Forward kinematics, Jacobian and (optional) IK of one arm, one frame convention."""

    def pose(self, q: npt.ArrayLike) -> FloatArray:
        """Pose ``(4, 4)`` of the controlled point in the scene's world frame."""
        ...

    def jacobian(self, q: npt.ArrayLike) -> FloatArray:
        """Geometric Jacobian ``(6, n)`` of :meth:`pose` (rows v then ω, world frame)."""
        ...

    def ik(self, target: npt.ArrayLike, q_near: npt.ArrayLike) -> FloatArray:
        """Joints placing the controlled point at ``target`` ``(4, 4)``, nearest ``q_near``;
        :class:`~telesurg.shared.errors.IKError` if none (or no analytic IK)."""
        ...


class PositionSolution(NamedTuple):
    """Result of :func:`solve_position`.

    Attributes:
        q: joints ``(n,)``, inside ``[lower, upper]``.
        error: [m] distance left between the controlled point at ``q`` and the target.
        clamped: indices of the joints held at a limit.
        tilt_error: [rad] the angle between the world's vertical and the kept one (``keep_up``;
            0 without).
    """

    q: FloatArray
    error: float
    clamped: tuple[int, ...]
    tilt_error: float = 0.0


def solve_position(
    arm: ArmKinematics,
    q0: npt.ArrayLike,
    target: npt.ArrayLike,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    *,
    damping: float = DEFAULT_DAMPING,
    iterations: int = 5,
    tol: float = 1e-6,
    keep_up: npt.ArrayLike | None = None,
) -> PositionSolution:
    """Joints near ``q0`` that bring the controlled point to ``target`` ``(3,)`` [m, world].

    Damped least squares on the positional rows of the Jacobian, a few Newton steps from ``q0``;
    each step is clamped into ``[lower, upper]`` and a joint at its limit that the step pushes
    further out is dropped from the next solve (the others take over its share). An unreachable
    target gives the nearest joints the steps find (``error`` says how far off).

    ``keep_up`` ``(3,)``: the world's up (+z) as seen in the controlled point's frame, to be kept
    (take it from the pose at an engage: ``R.T @ (0, 0, 1)``). Two more rows (weight
    :data:`TILT_WEIGHT`) then hold the point's frame's tilt, leaving it free to turn about the
    vertical: a held object keeps its tilt while the arm carries it.

    Raises:
        KinematicsError: shapes that do not fit, or values that are not finite.
    """
    q = np.array(q0, dtype=np.float64)
    p = np.asarray(target, dtype=np.float64)
    lo, hi = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    if q.ndim != 1 or lo.shape != q.shape or hi.shape != q.shape or p.shape != (3,):
        raise KinematicsError(
            f"solve_position: q {q.shape}, lower/upper {lo.shape}/{hi.shape}, target {p.shape}"
        )
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p)) and damping > 0.0):
        raise KinematicsError("solve_position: q0 and target must be finite, damping > 0")
    up = None
    if keep_up is not None:
        up = np.asarray(keep_up, dtype=np.float64)
        norm = float(np.linalg.norm(up)) if up.shape == (3,) else 0.0
        if not (np.all(np.isfinite(up)) and norm > 1e-9):
            raise KinematicsError(f"solve_position: keep_up must be a finite non-zero (3,), got {up!r}")
        up = up / norm
    q = np.clip(q, lo, hi)
    free = np.ones(q.shape, dtype=bool)
    ez = np.array([0.0, 0.0, 1.0])

    def error(q: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Position error, every row's error, and where the kept up points now (world)."""
        T = arm.pose(q)
        e = p - T[:3, 3]
        if up is None:
            return e, e, ez
        # the rotation (x, y; world) that brings the kept up back onto the world's +z
        now_up = T[:3, :3] @ up
        return e, np.concatenate([e, TILT_WEIGHT * np.cross(now_up, ez)[:2]]), now_up

    e, full, now_up = error(q)
    rows = 3 if up is None else 5
    for _ in range(iterations):
        if float(np.linalg.norm(full)) <= tol:
            break
        J6 = arm.jacobian(q) * free
        J = J6[:3] if up is None else np.vstack([J6[:3], TILT_WEIGHT * J6[3:5]])
        dq = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(rows), full)
        q_new = np.clip(q + dq, lo, hi)
        free &= ~(((q_new <= lo) & (dq < 0.0)) | ((q_new >= hi) & (dq > 0.0)))
        q = q_new
        e, full, now_up = error(q)
    at_limit = np.flatnonzero(((q <= lo) | (q >= hi)) & ~free)
    tilt_error = float(np.arccos(np.clip(now_up @ ez, -1.0, 1.0)))  # (0 without keep_up)
    return PositionSolution(q, float(np.linalg.norm(e)), tuple(int(i) for i in at_limit), tilt_error)
