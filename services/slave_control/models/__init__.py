"""MuJoCo models by name: the registered robots' scenes and the other models the robots ship.

A robot's scene comes from the robot registry (:attr:`telesurg.shared.robots.RobotSpec.scene`:
the built-in ``mh3f``, ``plas``, ``vip`` in ``shared/robots/<name>/``, a plugin's wherever it keeps
it); ``plas_master`` is the PLAS master device's model (``shared/robots/plas/plas_master/``).
"""

from __future__ import annotations

import pathlib

from telesurg.shared import robots
from telesurg.shared.errors import ConfigError

_MODELS_DIR = pathlib.Path(robots.__file__).resolve().parent

#: Models that are not registered robots, and their scene file, relative to shared/robots.
_OTHER_SCENES: dict[str, str] = {
    "plas_master": "plas/plas_master/scene.xml",
}


def model_names() -> tuple[str, ...]:
    """The valid names for :func:`model_path` (the registered robots and the other models), sorted."""
    return tuple(sorted({*robots.names(), *_OTHER_SCENES}))


def model_path(name: str, scene: str = "") -> pathlib.Path:
    """Path of the ``scene.xml`` of model ``name`` (e.g. ``"mh3f"``), or of its variant ``scene``
    (a file name from :meth:`~telesurg.shared.robots.RobotSpec.scene_variants`; ``""``: the
    robot's own scene).

    Raises:
        ValueError: ``name`` is not a known model, or ``scene`` not one of its variants; the
            message lists the valid names.
    """
    if name in robots.names():
        try:
            return pathlib.Path(robots.get(name).scene_file(scene))
        except ConfigError as e:
            raise ValueError(str(e)) from None
    if scene:
        raise ValueError(f"model {name!r} has no scene variants (scene = {scene!r})")
    try:
        relative = _OTHER_SCENES[name]
    except KeyError:
        valid = ", ".join(repr(n) for n in model_names())
        raise ValueError(f"unknown model {name!r}; valid names: {valid}") from None
    return _MODELS_DIR / relative
