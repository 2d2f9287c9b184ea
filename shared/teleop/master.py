"""The master point the mapping maps to the slave tip (``master_mode``: ``pen`` or ``virtual_trocar``).

Used by every mapping strategy that maps the master's tip (the MH3F's Cartesian mapping, the VIP
mapping, the generic position mapping).

Example::

    master_point(cfg, (0.0, 0.0, 0.1))   # pen: the position itself, m, master frame
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from telesurg.shared.teleop.settings import MappingSettings


def master_point(cfg: MappingSettings, position: tuple[float, float, float]) -> np.ndarray:
    """The master point that is mapped to the slave tip, m, master frame.

    ``pen``: the master position itself. ``virtual_trocar``: the position is the handle of a dummy
    forceps that passes through a virtual trocar ``c`` (a fixed fulcrum on the master side); the
    mapped point is the dummy tip ``h + L · unit(c − h)`` beyond it. As through a real trocar, the
    tip moves opposite to the handle sideways and the same way along the shaft, so the surgeon's
    hand motion matches what the slave forceps does about the patient's trocar.
    """
    h = np.array(position, dtype=float)
    if cfg.master_mode == "pen":
        return h
    c = np.array(cfg.virtual_trocar_mm) / 1e3
    d = c - h
    n = float(np.linalg.norm(d))
    u = d / n if n > 1e-6 else np.array([0.0, 0.0, -1.0])  # (handle in the fulcrum: straight down)
    out: np.ndarray = h + (cfg.dummy_forceps_mm / 1e3) * u
    return out
