"""The VIP slave's own knobs: the ``robot`` table of the mapping and slave_control configs.

Example (site file)::

    [mapping.robot]
    vip_ev_mm = 40.0
"""

from __future__ import annotations

from dataclasses import dataclass

from telesurg.shared.errors import ConfigError


@dataclass
class VipConfig:
    """VIP config (the ``robot`` table)."""

    vip_ev_mm: float = 50.0  # mapping: |EV| of the VIP chosen from the joints (20–50 mm)
    jog_speed_mm_s: float = 10.0  # mm/s: slave_control's elbow jog speed

    def __post_init__(self) -> None:
        if not 20.0 <= self.vip_ev_mm <= 50.0:
            raise ConfigError(f"vip_ev_mm={self.vip_ev_mm} outside [20, 50] (Jang 2014, Step 5)")
