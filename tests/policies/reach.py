"""A scripted policy for the policy master device (``docs/learning.md``): it moves the master tip
along one axis at a constant speed and pauses (returns None) while a flag file exists.

``--set master_capture.device_options.policy=tests/policies/reach.py:make`` with
``device_options.options.speed_mm_s=10`` (and ``options.pause_file=PATH``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from telesurg.services.master_capture.devices.policy import PolicyObservation


def make(speed_mm_s: float = 10.0, rate_hz: float = 30.0, axis: str = "x", pause_file: str = ""):  # type: ignore[no-untyped-def]
    """A policy moving the master ``speed_mm_s`` along ``axis`` while it is engaged."""
    step = np.zeros(3)
    step["xyz".index(axis)] = speed_mm_s / 1e3 / rate_hz
    pause = Path(pause_file) if pause_file else None

    def policy(obs: PolicyObservation) -> np.ndarray | None:
        if pause is not None and pause.exists():
            return None
        return step if obs.following else np.zeros(3)

    return policy
