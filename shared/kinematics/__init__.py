"""Pure-numpy kinematics shared by every robot: SE(3)/SO(3) helpers, the arm interface, generic solvers.

Units are metres and radians; quaternions are [x, y, z, w]. :mod:`.interface` is the one
interface of every arm (:class:`ArmKinematics`: ``pose``, ``jacobian``, optional ``ik``; the robot
registry :mod:`telesurg.shared.robots` adapts each robot to it) and a generic position solver;
:mod:`.elbow` the redundancy of an arm whose controlled point hangs from an elbow;
:mod:`.transforms` holds the conventions. A robot's own maths lives in its folder
(``telesurg.shared.robots.<name>``, e.g. ``from telesurg.shared.robots.mh3f.kinematics import fk, ik``).
"""

from telesurg.shared.kinematics.interface import ArmKinematics, PositionSolution, solve_position
from telesurg.shared.kinematics.transforms import (
    FloatArray,
    make_transform,
    matrix_from_quat,
    matrix_from_rotvec,
    quat_from_matrix,
    quat_normalize,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle_between,
    rotvec_from_matrix,
    skew,
)

__all__ = [
    "ArmKinematics",
    "FloatArray",
    "PositionSolution",
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
    "skew",
    "solve_position",
]
