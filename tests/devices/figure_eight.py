"""A master device from one file: a figure-eight drawn in the master's xy plane, pedal pressed.

Load it with ``--plugin tests/devices/figure_eight.py`` and choose it with
``--set device=figure_eight``; its settings are ``device_options.*``
(``--set device_options.radius_mm=30``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.services.master_capture.devices.scripted import EngageRetry


@dataclass
class FigureEightConfig:
    """``[master_capture.device_options]`` of the figure_eight device."""

    radius_mm: float = 40.0  # mm: half-width of the figure-eight
    period_s: float = 10.0  # s: one lap
    press_at_s: float = 2.0  # s: the pedal is pressed from then on


@register
class FigureEight(MasterDevice):
    """A Gerono lemniscate around the master-frame origin; the pedal pressed from ``press_at_s``."""

    name = "figure_eight"
    config = FigureEightConfig

    def __init__(self, cfg: FigureEightConfig) -> None:
        self.cfg = cfg
        # master_capture tells it of refused engages (the slave was not ready): press again 1 s later
        self.engage_retry = EngageRetry(1.0)

    def read(self, t: float) -> DeviceSample:
        w = 2.0 * math.pi * t / self.cfg.period_s
        r = self.cfg.radius_mm / 1e3
        position = (r * math.sin(w), r * math.sin(w) * math.cos(w), 0.0)
        pedal = self.engage_retry.clutch(t >= self.cfg.press_at_s, t)
        return DeviceSample(position, (0.0, 0.0, 0.0, 1.0), clutch=pedal, operator_present=True)
