"""The VIP slave's own knobs: the ``robot`` table of the mapping and slave_control configs.

Example (site file)::

    [mapping.robot]
    vip_ev_mm = 40.0
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from telesurg.shared.errors import ConfigError


@dataclass
class VipConfig:
    """VIP config (the ``robot`` table)."""

    vip_ev_mm: float = 50.0  # mapping: |EV| of the VIP chosen from the joints (20–50 mm)
    jog_speed_mm_s: float = 10.0  # mm/s: slave_control's elbow jog speed
    # mapping: mm, world: each arm's VIP set by the site (arm → [x, y, z]), taken at the first engage
    # instead of the selection procedure (as `set_vip` would set it); a VIP far along the
    # instrument keeps its tilt as the wrist moves (the study's peg transfer)
    vips_mm: dict[str, list[float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 20.0 <= self.vip_ev_mm <= 50.0:
            raise ConfigError(f"vip_ev_mm={self.vip_ev_mm} outside [20, 50] (Jang 2014, Step 5)")
        for arm, v in self.vips_mm.items():
            if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise ConfigError(f"vips_mm.{arm} = {v!r}: give the VIP as [x, y, z] mm")
