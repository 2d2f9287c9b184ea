"""Robot plugin of the ``tri3`` test arm: ``--plugin tests/robots/tri3/tri3.py``.

Three hinges: yaw ``q1`` about z, shoulder ``q2`` and elbow ``q3`` about the yawed y axis; links
``H`` (base height), ``L2``, ``L3``. The controlled point is the forearm's end (MuJoCo site
``tip`` of scene.xml next to this file), its frame the forearm's. No analytic IK: the mapping
drives it in mode ``position`` (damped least squares on :meth:`ArmProfile.pose` /
:meth:`ArmProfile.jacobian`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
from telesurg.shared import robots
from telesurg.shared.robots import ArmProfile, RobotSpec, Sketch

HERE = Path(__file__).resolve().parent
H, L2, L3 = 0.10, 0.20, 0.15  # m
JOINTS = ("q1", "q2", "q3")
LOWER = (-2.5, -1.5, 0.2)
UPPER = (2.5, 1.0, 2.6)
HOME = (0.0, -0.5, 1.2)

F = npt.NDArray[np.float64]


def _rz(a: float) -> F:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(a: float) -> F:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def points(q: F) -> tuple[F, F, F, F, F]:
    """(base, shoulder, elbow, tip positions, tip rotation) [m], world frame."""
    if np.shape(q) != (3,):
        raise ValueError(f"tri3 needs 3 joints, got {np.shape(q)}")
    r1 = _rz(float(q[0]))
    r2 = r1 @ _ry(float(q[1]))
    r3 = r2 @ _ry(float(q[2]))
    base = np.zeros(3)
    shoulder = np.array([0.0, 0.0, H])
    elbow = shoulder + L2 * r2[:, 0]
    tip = elbow + L3 * r3[:, 0]
    return base, shoulder, elbow, tip, r3


def pose(q: F) -> F:
    *_, tip, rot = points(q)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot, tip
    return T


def jacobian(q: F) -> F:
    _, shoulder, elbow, tip, _ = points(q)
    z = np.array([0.0, 0.0, 1.0])
    y = _rz(float(q[0]))[:, 1]
    axes, through = (z, y, y), (np.zeros(3), shoulder, elbow)
    cols = [np.concatenate([np.cross(a, tip - p), a]) for a, p in zip(axes, through, strict=True)]
    return np.column_stack(cols)


def arms(arm: str) -> tuple[ArmProfile, ...]:
    # one arm, named by the slave_control arm id it is given
    return (ArmProfile(arm, JOINTS, JOINTS, LOWER, UPPER, (1.5, 1.5, 1.5), HOME, "tip", pose, jacobian),)


def sketch(arm: str, q: F) -> Sketch:
    base, shoulder, elbow, tip, _ = points(np.asarray(q, dtype=np.float64))
    return Sketch(np.stack([base, shoulder, elbow, tip]), None, None)


robots.register(
    RobotSpec(
        name="tri3",
        arms=arms,
        scene=HERE / "scene.xml",
        mapping_modes=("position",),
        slave_family="joint",
        sketch=sketch,
        description="3-DoF test arm (yaw, shoulder, elbow), registered from the test tree",
    )
)
