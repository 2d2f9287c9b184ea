"""Joint-speed limiting shared by the slave's follow loop, its serial backend and the mapping.

A step that is too fast is scaled down as a whole, so the joints stay synchronised and the arm
keeps to the commanded path in joint space (per-joint clipping would bend it — off the trocar's
remote centre in trocar mode).

Example::

    >>> import numpy as np
    >>> limit_step(np.array([0.2, -0.1]), np.array([0.1, 0.1])).tolist()
    [0.1, -0.05]
"""

from __future__ import annotations

import numpy as np


def limit_step(want: np.ndarray, lim: np.ndarray) -> np.ndarray:
    """``want`` scaled down uniformly so that no joint exceeds its step limit ``lim`` (> 0)."""
    ratio = float(np.max(np.abs(want) / lim))
    if ratio <= 1.0:
        return want
    out: np.ndarray = want / ratio
    return out
