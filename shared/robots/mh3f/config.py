"""The MH3F's own knobs: the ``robot`` table of the mapping and slave_control configs.

Example (site file)::

    [slave_control.robot]
    trocar_mm = [500.0, 0.0, 200.0]
    jog_speed_mm_s = 10.0
"""

from __future__ import annotations

from dataclasses import dataclass, field

from telesurg.shared.errors import ConfigError
from telesurg.shared.robots.mh3f.teach import TeachConfig


@dataclass
class Mh3fConfig:
    """MH3F config (the ``robot`` table)."""

    # mm: insertion depth range of the tip beyond the trocar in trocar-mode master–slave (mapping:
    # the target is clamped into it; the upper end leaves the non-shaft 150 mm of the forceps out)
    trocar_depth_mm: tuple[float, float] = (10.0, 350.0)
    # mm, base frame: the trocar (the scene's trocar site). The RCM error and insertion depth in
    # operating_state are measured against it from the simulated arm's tip pose.
    trocar_mm: tuple[float, float, float] = (500.0, 0.0, 200.0)
    trocar_taught: bool = True  # the configured trocar counts as taught (teach_trocar replaces it)
    jog_speed_mm_s: float = 10.0  # mm/s: Cartesian jog and insert/remove speed
    jog_joint_speed_deg_s: float = 5.0  # deg/s: joint jog speed
    ptp_speed_fraction: float = 0.2  # PTP moves (posture, playback) at this fraction of the joint limits
    playback_speed_mm_s: float = 20.0  # mm/s: tip speed of a playback in trocar mode
    playback_dwell_s: float = 0.3  # s: the arm rests this long at each taught point of a playback
    # JSON file of taught trocars and programs ("" = kept in memory only); loaded at start, so a
    # taught trocar (the current one) survives a restart
    state_file: str = ""
    teach: TeachConfig = field(default_factory=TeachConfig)  # direct-teach admittance

    def __post_init__(self) -> None:
        if not 5.0 <= self.trocar_depth_mm[0] < self.trocar_depth_mm[1]:
            raise ConfigError(f"trocar_depth_mm={self.trocar_depth_mm}: need 5 <= min < max")
