"""The slave's nearest joint limit as a wall in the master's frame, for haptic guidance.

The mapping linearises its own inverse kinematics at the current target: ``G = dq/dp`` (joints per
metre of slave tip motion, by central differences of ``solve``), and ``dp = A dx`` maps master
motion to slave motion (``A = k R_ms``: the motion scale and the master-to-slave rotation). Joint
``j`` comes within ``margin`` of its upper limit after master motion ``dx`` where
``(G A)_j · dx = room_j``; the nearest such plane over the joints and both limits is the wall: the
master may move where ``n · x ≤ d``. The console renders it locally like its workspace walls
(:mod:`telesurg.shared.haptics.guidance`), so the surgeon feels the limit before the mapping has
to clamp the slave at it.

Example::

    wall = limit_wall(lambda p: ik_at(p), p_slave, q, lower, upper, 0.087, k * r_ms, x_master)
    # (nx, ny, nz, d), or NO_WALL when no limit is within ``reach`` of master motion
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ``limit_wall`` of a pair with no joint limit near: nothing to render
NO_WALL = (0.0, 0.0, 0.0, 0.0)
#: m of master motion: a limit farther than this is not sent
REACH_M = 0.05
#: m: the central differences' step
STEP_M = 1e-4


def limit_wall(
    solve: Callable[[np.ndarray], np.ndarray],
    p_slave: np.ndarray,
    q: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    margin: float,
    slave_per_master: np.ndarray,
    x_master: np.ndarray,
    reach: float = REACH_M,
) -> tuple[float, float, float, float]:
    """The wall ``(nx, ny, nz, d)`` in the master's frame (module doc), or :data:`NO_WALL`.

    ``solve(p)``: the mapping's joints for a slave tip at ``p`` (m, base frame; it may raise where
    there is none: then :data:`NO_WALL`); ``q``: the joints at ``p_slave``; ``margin``: how far
    from each limit the wall stands (joint units); ``slave_per_master``: ``A``, (3, 3);
    ``x_master``: the master point now (m)."""
    cols = []
    try:
        for i in range(3):
            e = np.zeros(3)
            e[i] = STEP_M
            cols.append((solve(p_slave + e) - solve(p_slave - e)) / (2 * STEP_M))
    except Exception:  # no IK near here (an IK error of the mapping's solver): nothing to render
        return NO_WALL
    g = np.stack(cols, axis=1) @ slave_per_master  # (joints, 3): joints per metre of master motion
    best: tuple[float, np.ndarray] | None = None
    for j in range(len(q)):
        norm = float(np.linalg.norm(g[j]))
        if norm < 1e-9:  # master motion does not move this joint
            continue
        for sign, room in ((1.0, upper[j] - margin - q[j]), (-1.0, q[j] - lower[j] - margin)):
            dist = float(room) / norm  # master motion to the plane, along its normal
            if best is None or dist < best[0]:
                best = (dist, sign * g[j] / norm)
    if best is None or best[0] > reach:
        return NO_WALL
    dist, n = best
    return (float(n[0]), float(n[1]), float(n[2]), float(n @ x_master) + dist)
