"""The package list: every folder with an ``__init__.py`` under the folders pyproject.toml maps
under the ``telesurg`` namespace ([tool.setuptools.package-dir]); everything else is in
pyproject.toml."""

import tomllib
from pathlib import Path

from setuptools import setup

ROOT = Path(__file__).resolve().parent


def packages() -> list[str]:
    """``telesurg.<folder>[.<sub>…]`` for each mapped folder and each package below it."""
    mapped = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    out = []
    for name, folder in mapped.items():
        for init in sorted((ROOT / folder).rglob("__init__.py")):
            parts = init.parent.relative_to(ROOT / folder).parts
            if "__pycache__" not in parts:
                out.append(".".join((name, *parts)))
    return out


setup(packages=packages())
