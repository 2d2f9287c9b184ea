"""Robots: the registry (:mod:`.registry`) and one folder per built-in robot.

Each robot lives in ``shared/robots/<name>/``: its MuJoCo model (``robot.xml``, ``scene.xml``),
kinematics, config dataclass, mapping strategies, slave-side motion sources and README.md; its
``__init__`` registers it. Importing this package registers ``mh3f``, ``plas`` and ``vip``;
plugins add more (:func:`load_plugin`). The protocols a robot implements are in :mod:`.api`.

Example::

    from telesurg.shared import robots
    spec = robots.get("vip")        # ConfigError naming the valid robots if unknown
    spec.arm("arm1").joint_names    # ('q1', 'q2', 'q3', 'q4', 'q5')
"""

from __future__ import annotations

from telesurg.shared.robots import mh3f, plas, vip
from telesurg.shared.robots.registry import (
    SLAVE_FAMILIES,
    ArmProfile,
    FloatArray,
    RobotSpec,
    Sketch,
    arm_profile,
    arms_of,
    config_help,
    get,
    load_plugin,
    names,
    recognise,
    register,
    two_arms,
)

#: The built-in robots (plugins add to :func:`names`).
MODELS = ("mh3f", "plas", "vip")

__all__ = [
    "MODELS",
    "SLAVE_FAMILIES",
    "ArmProfile",
    "FloatArray",
    "RobotSpec",
    "Sketch",
    "arm_profile",
    "arms_of",
    "config_help",
    "get",
    "load_plugin",
    "mh3f",
    "names",
    "plas",
    "recognise",
    "register",
    "two_arms",
    "vip",
]
