"""Elbow (null-space) motion of a redundant arm whose controlled point hangs from an elbow.

For an arm like Jang 2014's (:mod:`telesurg.shared.robots.vip.kinematics`) the controlled point W (the
wrist) hangs a rigid forearm of length ``|EW|`` from the elbow E, and the joints are fixed by E
and W together. With W held still, the elbow can still move on the sphere of radius ``|EW|``
about W: the arm's null space (two-dimensional for the five-joint VIP arm). Step 2 of the paper's
VIP selection ("adjust manually elbow (E) and wrist (W)", Section III-C) moves the elbow there;
Section V-B recommends joints "in the middle of range of motion as possible" afterwards.

* :func:`elbow_move` — the joints after moving the elbow by a displacement with W fixed (the
  part of the displacement along the forearm is dropped: the elbow cannot move that way).
* :func:`tangent` — a world direction as the elbow can follow it (perpendicular to the forearm).
* :func:`limit_margin` — the smallest distance of any joint to its limit, as a fraction of the
  joint's range (0 on a limit, 0.5 at mid-range of every joint).
* :func:`midrange_direction` — the direction on the sphere that raises :func:`limit_margin` most
  (a pattern search over ``directions`` probes), or None where no probe raises it: Section V-B's
  advice as a null-space motion at runtime.
* :func:`off_line` — the elbow's distance from the line W–V of a virtual incision port V.

Pure numpy; units m and rad. The arm is an :class:`ElbowChain` (elbow and wrist from the joints,
an IK from elbow and wrist): the VIP arm's is built in :mod:`telesurg.shared.robots`.

Example::

    from telesurg.shared.robots import arm_profile
    profile = arm_profile("vip", "arm1")
    chain, q = profile.elbow, np.array(profile.home)
    W = chain.wrist(q)
    q2 = elbow_move(chain, q, W, np.array([0.0, 0.0, 0.001]))   # elbow 1 mm up, W unchanged
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from telesurg.shared.errors import KinematicsError
from telesurg.shared.kinematics.transforms import FloatArray

__all__ = [
    "ALONG_FOREARM_TOL",
    "ElbowChain",
    "elbow_move",
    "limit_margin",
    "midrange_direction",
    "off_line",
    "tangent",
]

ALONG_FOREARM_TOL = 0.05
"""A direction whose part perpendicular to the forearm is shorter than this fraction of it
points along the forearm: the elbow cannot follow it with the wrist fixed."""


@dataclass(frozen=True)
class ElbowChain:
    """The redundancy of one arm: its elbow and controlled point, and an IK from both.

    Attributes:
        elbow: joints ``(n,)`` → elbow E ``(3,)`` [m], world frame.
        wrist: joints ``(n,)`` → controlled point W ``(3,)`` [m], world frame.
        solve: (E ``(3,)``, W ``(3,)``, joints to stay near ``(n,)``) → joints ``(n,)`` within the
            joint limits; raises :class:`~telesurg.shared.errors.IKError` (a
            :class:`~telesurg.shared.robots.vip.kinematics.JointLimitError` names the joint) otherwise.
        lower, upper: joint limits (rad, m for prismatic joints).
    """

    elbow: Callable[[FloatArray], FloatArray]
    wrist: Callable[[FloatArray], FloatArray]
    solve: Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
    lower: tuple[float, ...]
    upper: tuple[float, ...]


def tangent(chain: ElbowChain, q: FloatArray, W: FloatArray, direction: FloatArray) -> FloatArray:
    """``direction`` ``(3,)`` without its part along the forearm E–W (unit vector).

    Raises:
        KinematicsError: ``direction`` points along the forearm (within :data:`ALONG_FOREARM_TOL`).
    """
    d = np.asarray(direction, dtype=np.float64)
    norm = float(np.linalg.norm(d))
    if not (math.isfinite(norm) and norm > 0.0):
        raise KinematicsError(f"elbow direction must be a finite non-zero vector, got {d.tolist()}")
    n = chain.elbow(q) - W
    n = n / float(np.linalg.norm(n))
    t = d / norm - float(np.dot(d / norm, n)) * n
    tn = float(np.linalg.norm(t))
    if tn < ALONG_FOREARM_TOL:
        raise KinematicsError(
            "the direction points along the forearm: the elbow cannot move that way with the wrist fixed"
        )
    return np.asarray(t / tn, dtype=np.float64)


def elbow_move(chain: ElbowChain, q: FloatArray, W: FloatArray, d: FloatArray) -> FloatArray:
    """Joints with the controlled point at ``W`` and the elbow moved by ``d`` ``(3,)`` [m].

    The elbow goes to ``W + |EW| · (E + d − W)/|E + d − W|``: on the forearm sphere about W,
    so the part of ``d`` along the forearm is dropped (to first order ``d`` is followed exactly
    when it is perpendicular to the forearm).

    Raises:
        IKError: the new elbow is outside what the mechanism reaches, or a joint would leave its
            limits (the error names it).
    """
    E = chain.elbow(q)
    forearm = float(np.linalg.norm(E - W))
    u = E + np.asarray(d, dtype=np.float64) - W
    u = u / float(np.linalg.norm(u))
    return chain.solve(W + forearm * u, W, q)


def limit_margin(q: FloatArray, lower: tuple[float, ...], upper: tuple[float, ...]) -> float:
    """The smallest distance of a joint of ``q`` from its limits, as a fraction of its range."""
    lo, hi = np.asarray(lower), np.asarray(upper)
    qa = np.asarray(q, dtype=np.float64)
    return float(np.min(np.minimum(qa - lo, hi - qa) / (hi - lo)))


def midrange_direction(
    chain: ElbowChain, q: FloatArray, W: FloatArray, probe_m: float, directions: int = 12
) -> FloatArray | None:
    """The unit direction ``(3,)`` (perpendicular to the forearm) in which an elbow move of
    ``probe_m`` raises :func:`limit_margin` most, or None if no probe raises it (the elbow is as
    mid-range as this wrist allows, to the probe's resolution).

    ``directions`` probes are spread evenly around the forearm; a probe the mechanism cannot
    reach (IK error) does not count.
    """
    E = chain.elbow(q)
    n = (E - W) / float(np.linalg.norm(E - W))
    a = np.cross(n, np.array([0.0, 0.0, 1.0]))
    if float(np.linalg.norm(a)) < 1e-6:
        a = np.cross(n, np.array([1.0, 0.0, 0.0]))
    a = a / float(np.linalg.norm(a))
    b = np.cross(n, a)
    best, best_dir = limit_margin(q, chain.lower, chain.upper), None
    for k in range(directions):
        ang = 2.0 * math.pi * k / directions
        t = math.cos(ang) * a + math.sin(ang) * b
        try:
            qq = elbow_move(chain, q, W, probe_m * t)
        except ValueError:  # IKError / KinematicsError: not a configuration within the limits
            continue
        m = limit_margin(qq, chain.lower, chain.upper)
        if m > best + 1e-9:
            best, best_dir = m, t
    return None if best_dir is None else np.asarray(best_dir, dtype=np.float64)


def off_line(E: FloatArray, W: FloatArray, V: FloatArray) -> float:
    """Distance [m] of the elbow ``E`` from the line through the wrist ``W`` and the VIP ``V``."""
    u = np.asarray(V, dtype=np.float64) - W
    u = u / float(np.linalg.norm(u))
    r = np.asarray(E, dtype=np.float64) - W
    return float(np.linalg.norm(r - float(np.dot(r, u)) * u))
