"""Pure-numpy kinematics: SE(3)/SO(3) helpers, the arm interface and each robot's own maths.

Units are metres and radians; quaternions are [x, y, z, w]. :mod:`.interface` is the one
interface of every arm (:class:`ArmKinematics`: ``pose``, ``jacobian``, optional ``ik``; the robot
registry :mod:`telesurg.shared.robots` adapts each robot to it) and a generic position solver;
the robots' own modules are :mod:`.mh3f` (frames and the IK derivation), :mod:`.trocar`,
:mod:`.plas` / :mod:`.plas_layout` and :mod:`.vip`; :mod:`.transforms` holds the conventions.
A robot's FK / IK / Jacobian are imported from its own module (``from
telesurg.shared.kinematics.mh3f import fk, ik``), or used through the registry's arm profiles;
this package exports only the robot-neutral helpers, the interface and the MH3F geometries.
"""

from telesurg.shared.kinematics.interface import ArmKinematics, PositionSolution, solve_position
from telesurg.shared.kinematics.mh3f import MH3F, MH3F_NO_TOOL
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
    "MH3F",
    "MH3F_NO_TOOL",
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

# Trocar mode (RCM kinematics, J4/J5 posture adjustment); see :mod:`.trocar`.
from telesurg.shared.kinematics.trocar import (
    MIN_TIP_DEPTH,
    ROLL_REF_SINGULAR_TOL,
    STRAIGHT_FORCEPS,
    TROCAR_MODE_DEPTH,
    Forceps,
    axis_angle_to_trocar,
    forceps_roll,
    insertion_depth,
    interpolate_posture,
    posture_adjust,
    posture_duration,
    rcm_error,
    roll_reference,
    trocar_ik,
)

__all__ += [
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
