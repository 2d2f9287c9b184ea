"""The PLAS slave's own knobs: the ``robot`` table of the mapping config.

Example (site file)::

    [mapping.robot]
    all_joints_mode = "tip_exact"
"""

from __future__ import annotations

from dataclasses import dataclass

from telesurg.shared.errors import ConfigError


@dataclass
class PlasConfig:
    """PLAS config (the ``robot`` table)."""

    all_joints_mode: str = "factor"  # all_joints: factor (Table 6) or tip_exact (DLS Jacobian)
    d1_speed_mm_s: float = 10.0  # all_joints: slave d1 speed while the master's joint-1 switch is on

    def __post_init__(self) -> None:
        if self.all_joints_mode not in ("factor", "tip_exact"):
            raise ConfigError(f"all_joints_mode {self.all_joints_mode!r} invalid; valid: factor, tip_exact")
