"""Strict JSON for every report the tools write: no ``NaN`` / ``Infinity`` (not JSON).

Python's :func:`json.dumps` writes ``NaN`` and ``Infinity`` by default, which strict parsers
(browsers, ``jq``, most languages) refuse: one forged master pose with an infinite coordinate made
the demo report unreadable. :func:`finite` turns every non-finite float (also numpy scalars and
arrays, tuples) into ``None`` (JSON ``null``), and :func:`dumps` / :func:`write` then serialise with
``allow_nan=False``, so a value that slips past :func:`finite` is an error, never a bad file.

Example::

    from telesurg.shared import jsonio
    jsonio.write("out/report.json", {"max_mm": float("inf")})   # {"max_mm": null}
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any


def finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by ``None``; containers copied (dict keys
    kept, tuples and sets become lists), numpy scalars and arrays turned into Python values."""
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [finite(v) for v in value]
    tolist = getattr(value, "tolist", None)  # numpy arrays and scalars, without importing numpy
    if callable(tolist):
        return finite(tolist())
    return value


def dumps(value: Any, **kwargs: Any) -> str:
    """:func:`json.dumps` of :func:`finite` ``(value)`` with ``allow_nan=False``."""
    kwargs.pop("allow_nan", None)
    return json.dumps(finite(value), allow_nan=False, **kwargs)


def write(path: str | os.PathLike[str], value: Any, *, indent: int | None = 2, **kwargs: Any) -> None:
    """Write ``value`` to ``path`` as strict JSON (see :func:`dumps`), newline-terminated."""
    Path(path).write_text(dumps(value, indent=indent, **kwargs) + "\n")
