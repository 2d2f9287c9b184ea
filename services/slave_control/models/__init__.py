"""MuJoCo models of the slave arm (MJCF scenes shipped as package data)."""

from __future__ import annotations

import pathlib

_MODELS_DIR = pathlib.Path(__file__).resolve().parent

#: Model names and their scene file, relative to this package.
_SCENES: dict[str, str] = {
    "mh3f": "mh3f/scene.xml",
    "plas": "plas/scene.xml",
    "plas_master": "plas_master/scene.xml",
    "vip": "vip/scene.xml",
}


def model_names() -> tuple[str, ...]:
    """The valid names for :func:`model_path`, sorted."""
    return tuple(sorted(_SCENES))


def model_path(name: str) -> pathlib.Path:
    """Path of the ``scene.xml`` of model ``name`` (e.g. ``"mh3f"``).

    Raises:
        ValueError: ``name`` is not a known model; the message lists the valid names.
    """
    try:
        relative = _SCENES[name]
    except KeyError:
        valid = ", ".join(repr(n) for n in model_names())
        raise ValueError(f"unknown model {name!r}; valid names: {valid}") from None
    return _MODELS_DIR / relative
